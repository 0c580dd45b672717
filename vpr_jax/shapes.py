"""The image shape every data source yields and every encoder takes.

A leaf module (it imports nothing), so the config can validate against it without loading
the data package, and the encoders without loading the config.
"""

IMAGE_SHAPE = (32, 64)  # (height, width): Nordland's 64x32 release, grayscale
# Images with more pixels than this are refused before decoding (``data.max_pixels``): a
# 30,000 x 30,000 PNG is under a megabyte on disk and 900 MB decoded.
MAX_PIXELS = 8192 * 8192
