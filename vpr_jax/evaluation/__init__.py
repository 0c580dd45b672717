"""Scoring descriptors: cosine matching (single images, sequences), the place-recognition
metrics against a ground truth, and their bootstrap intervals. Pure functions of arrays."""
