"""The image shape every data source yields and every encoder takes.

A leaf module (it imports nothing), so the config can validate against it without loading
the data package, and the encoders without loading the config.
"""

IMAGE_SHAPE = (32, 64)  # (height, width): Nordland's 64x32 release, grayscale
