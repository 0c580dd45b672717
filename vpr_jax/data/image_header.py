"""An image's width and height from its file header, before anything is decoded.

A 30,000 x 30,000 PNG can be under a megabyte on disk and 900 MB once decoded; the readers
check ``data.max_pixels`` against the header first. PNG (IHDR), JPEG (the first SOF
segment) and BMP are read here; for other formats ``image_size`` returns None and the
decoder's own limit applies (OpenCV refuses images over 2^30 pixels).
"""

from __future__ import annotations

import struct
from pathlib import Path

_PNG = b"\x89PNG\r\n\x1a\n"
# JPEG start-of-frame markers: every SOFn except DHT (C4), JPG (C8) and DAC (CC)
_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}
_JPEG_SCAN_BYTES = 1 << 20  # SOF comes before the image data: EXIF thumbnails fit in this


def image_size(path: Path) -> tuple[int, int] | None:
    """(width, height) from the header of a PNG, JPEG or BMP file; None for other formats
    or a header this cannot parse (the decoder then reports the file)."""
    with open(path, "rb") as f:
        head = f.read(26)
        if head.startswith(_PNG) and len(head) >= 24 and head[12:16] == b"IHDR":
            return struct.unpack(">II", head[16:24])
        if head.startswith(b"BM") and len(head) >= 26:
            width, height = struct.unpack("<ii", head[18:26])
            return abs(width), abs(height)
        if head.startswith(b"\xff\xd8"):
            f.seek(0)
            return _jpeg_size(f.read(_JPEG_SCAN_BYTES))
    return None


def _jpeg_size(data: bytes) -> tuple[int, int] | None:
    pos = 2
    while pos + 9 <= len(data):
        if data[pos] != 0xFF:
            return None
        marker = data[pos + 1]
        if marker == 0xFF:  # fill byte
            pos += 1
            continue
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:  # markers without a length
            pos += 2
            continue
        (length,) = struct.unpack(">H", data[pos + 2 : pos + 4])
        if marker in _SOF:
            height, width = struct.unpack(">HH", data[pos + 5 : pos + 9])
            return width, height
        pos += 2 + length
    return None
