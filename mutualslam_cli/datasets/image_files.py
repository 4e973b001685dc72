"""The structure of image files, checked before decoding: OpenCV decodes some truncated PNGs partially,
with only a warning on stderr, so a frame cut short would pass as an image.

A PNG must be a chain of chunks with matching CRC-32s ending in ``IEND``; a JPEG must start with SOI
and end with EOI. Used by ``mslam datasets check`` (:mod:`~mutualslam_cli.datasets.check`) and by the
recording converters (:class:`~mutualslam_cli.datasets.recordings.conversion.TumWriter`), which check every frame.
"""

from __future__ import annotations

import zlib
from pathlib import Path

import cv2
import numpy as np

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def png_problem(data: bytes | memoryview) -> str | None:
    """What is wrong with the structure of a PNG file, or ``None``.

    Walks the chunks (length, type, data, CRC-32) from the signature to ``IEND``: a chunk running
    past the end of the file or a missing ``IEND`` means a truncated file, a CRC mismatch a
    corrupted one. Bytes after ``IEND`` are ignored, as decoders do.
    """
    data = memoryview(data)
    if bytes(data[:8]) != _PNG_SIGNATURE:
        return "not a PNG file (no PNG signature)"
    pos, n = 8, len(data)
    while pos + 12 <= n:
        length = int.from_bytes(data[pos:pos + 4], "big")
        kind = bytes(data[pos + 4:pos + 8]).decode("latin-1")
        end = pos + 12 + length
        if end > n:
            return f"truncated PNG: chunk {kind!r} at byte {pos} needs {end} bytes, the file has {n}"
        if zlib.crc32(data[pos + 4:pos + 8 + length]) != int.from_bytes(data[end - 4:end], "big"):
            return f"corrupted PNG: CRC mismatch in chunk {kind!r} at byte {pos}"
        if kind == "IEND":
            return None
        pos = end
    return f"truncated PNG: no IEND chunk before the end of the file ({n} bytes)"


def jpeg_problem(data: bytes | memoryview) -> str | None:
    """What is wrong with the framing of a JPEG file (SOI at the start, EOI at the end), or ``None``."""
    data = bytes(data[:2]) + bytes(data[-64:]).rstrip(b"\x00\r\n ")  # some writers pad after EOI
    if data[:2] != b"\xff\xd8":
        return "not a JPEG file (no SOI marker)"
    if not data.endswith(b"\xff\xd9"):
        return "truncated JPEG: no EOI marker at the end of the file"
    return None


def image_file_problem(path: Path, data: bytes | memoryview) -> str | None:
    """Structural problem of the image file ``path`` with content ``data`` (PNG and JPEG), or ``None``."""
    suffix = path.suffix.lower()
    if suffix == ".png":
        return png_problem(data)
    if suffix in (".jpg", ".jpeg"):
        return jpeg_problem(data)
    return None


def decode_frame(data: bytes, suffix: str) -> tuple[np.ndarray | None, str | None]:
    """``(image, None)`` for the encoded image ``data`` (file suffix ``suffix``, e.g. ``".png"``) decoded as
    stored, or ``(None, problem)`` when its structure is broken or OpenCV cannot decode it."""
    problem = image_file_problem(Path("frame" + suffix), data)
    if problem:
        return None, problem
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        return None, f"cannot be decoded as a {suffix.lstrip('.').upper() or 'image'} file"
    return img, None
