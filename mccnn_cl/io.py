"""File formats: PFM (Middlebury disparities), KITTI 16-bit disparity PNGs, images.

Every reader raises :class:`~mccnn_cl.errors.InputError` with the path for a
missing or unreadable file; every writer is atomic (a temporary file in the
same directory, then ``os.replace``), so an interrupted write never leaves a
half-written output under the final name.
"""

from __future__ import annotations

import os
import re

import cv2
import numpy as np

from .errors import InputError

__all__ = ["read_pfm", "write_pfm", "read_kitti_disparity", "write_kitti_disparity",
           "read_image", "write_image"]


def _check_exists(path) -> str:
    path = os.fspath(path)
    if not os.path.exists(path):
        raise InputError(f"file not found: {path}")
    if not os.path.isfile(path):
        raise InputError(f"not a file: {path}")
    return path


def _atomic_write(path, write_fn) -> None:
    """Call ``write_fn(tmp_path)`` then rename the temporary file onto ``path``
    (:func:`mccnn_cl.atomic.atomic_write`: recognisable temporary names, stale
    ones of crashed processes removed)."""
    from .atomic import atomic_write as write

    write(path, write_fn)


# -- PFM ------------------------------------------------------------------

def read_pfm(path) -> np.ndarray:
    """Read a PFM file into a float32 array, top row first.

    ``Pf`` files give (H, W), ``PF`` files (H, W, 3).  The scale line's sign is
    the byte order (negative = little-endian); rows are stored bottom-to-top
    and are flipped here.  Values (including ``inf`` markers) are returned
    unchanged.
    """
    path = _check_exists(path)
    with open(path, "rb") as f:
        data = f.read()
    # Header: three whitespace-separated tokens lines: magic, "W H", scale.
    m = re.match(rb"(P[fF])\s+(\d+)\s+(\d+)\s+([-+0-9.eE]+)\s", data)
    if m is None:
        raise InputError(f"{path}: not a PFM file (bad header)")
    magic, width, height, scale = m.group(1), int(m.group(2)), int(m.group(3)), m.group(4)
    try:
        scale = float(scale)
    except ValueError as exc:
        raise InputError(f"{path}: bad PFM scale {scale!r}") from exc
    if scale == 0 or width <= 0 or height <= 0:
        raise InputError(f"{path}: bad PFM header (size {width}x{height}, scale {scale})")
    channels = 3 if magic == b"PF" else 1
    dtype = np.dtype("<f4") if scale < 0 else np.dtype(">f4")
    count = width * height * channels
    offset = m.end()
    if len(data) - offset < count * 4:
        raise InputError(f"{path}: truncated PFM ({len(data) - offset} bytes of data, "
                         f"expected {count * 4})")
    arr = np.frombuffer(data, dtype=dtype, count=count, offset=offset)
    shape = (height, width, 3) if channels == 3 else (height, width)
    return np.ascontiguousarray(arr.reshape(shape)[::-1]).astype(np.float32)


def write_pfm(path, arr) -> None:
    """Write a float32 (H, W) or (H, W, 3) array as little-endian PFM, atomically."""
    a = np.asarray(arr)
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[:, :, 0]
    if a.ndim not in (2, 3) or (a.ndim == 3 and a.shape[2] != 3) or a.size == 0:
        raise InputError(f"write_pfm: expected an (H, W) or (H, W, 3) array, got shape {a.shape}")
    a = np.ascontiguousarray(a[::-1], dtype="<f4")
    magic = b"PF" if a.ndim == 3 else b"Pf"
    header = b"%s\n%d %d\n-1.0\n" % (magic, a.shape[1], a.shape[0])

    def write(tmp):
        with open(tmp, "wb") as f:
            f.write(header)
            f.write(a.tobytes())
    _atomic_write(path, write)


# -- KITTI disparity PNG --------------------------------------------------

def read_kitti_disparity(path):
    """Read a KITTI 16-bit disparity PNG: returns ``(disp float32, valid bool)``.

    disparity = value / 256; value 0 means no ground truth (``disp`` is 0 there
    and ``valid`` False).
    """
    path = _check_exists(path)
    raw = cv2.imread(path, cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise InputError(f"{path}: unreadable image")
    if raw.dtype != np.uint16 or raw.ndim != 2:
        raise InputError(f"{path}: expected a single-channel 16-bit PNG (KITTI disparity), "
                         f"got dtype {raw.dtype} shape {raw.shape}")
    valid = raw > 0
    disp = raw.astype(np.float32) / np.float32(256.0)
    return disp, valid


#: Largest disparity the format holds: value / 256 with value <= 65535.
KITTI_MAX_DISPARITY = 65535 / 256


def write_kitti_disparity(path, disp) -> None:
    """Write disparities as a KITTI 16-bit PNG (round(d*256); NaN/inf/0 → 0 = invalid), atomically.

    The format holds disparities in [0, 65535/256 = 255.996]: a finite value
    outside that range is an InputError (write .pfm or .npy), never clipped."""
    d = np.asarray(disp, dtype=np.float64)
    if d.ndim != 2 or d.size == 0:
        raise InputError(f"write_kitti_disparity: expected an (H, W) array, got shape {d.shape}")
    fin = d[np.isfinite(d)]
    if fin.size and (fin.min() < 0 or fin.max() > KITTI_MAX_DISPARITY):
        raise InputError(f"{os.fspath(path)}: a KITTI 16-bit PNG holds disparities 0..{KITTI_MAX_DISPARITY:.3f}, "
                         f"the map has {fin.min():g}..{fin.max():g}; write .pfm or .npy instead")
    ok = np.isfinite(d) & (d > 0)
    raw = np.zeros(d.shape, np.uint16)
    raw[ok] = np.clip(np.round(d[ok] * 256.0), 1, 65535).astype(np.uint16)

    def write(tmp):
        if not cv2.imwrite(tmp, raw):
            raise InputError(f"{path}: cv2 could not write the PNG")
    _atomic_write(path, write)


# -- images ---------------------------------------------------------------

def jpeg_complete(data: bytes) -> bool:
    """Whether JPEG bytes reach their end-of-image marker: the segments are walked by their
    lengths (EXIF thumbnails are skipped whole) and each scan's entropy-coded data to the next
    marker.  False for a truncated file, which cv2 decodes anyway, grey below the cut, with
    only a libjpeg message on stderr.  Data after the marker (e.g. a motion photo's video)
    does not matter."""
    n, i = len(data), 2
    if data[:2] != b"\xff\xd8":
        return False
    while True:
        while i < n and data[i] == 0xFF and i + 1 < n and data[i + 1] == 0xFF:
            i += 1  # fill bytes before a marker
        if i + 1 >= n or data[i] != 0xFF:
            return False
        marker = data[i + 1]
        if marker == 0xD9:
            return True
        if 0xD0 <= marker <= 0xD7 or marker == 0x01:  # RSTn, TEM: no length
            i += 2
            continue
        if i + 3 >= n:
            return False
        i += 2 + int.from_bytes(data[i + 2:i + 4], "big")
        if marker != 0xDA:
            continue
        while True:  # entropy-coded data of a scan: up to a marker other than 0x00 stuffing or RSTn
            i = data.find(b"\xff", i)
            if i < 0 or i + 1 >= n:
                return False
            nxt = data[i + 1]
            if nxt == 0x00 or 0xD0 <= nxt <= 0xD7 or nxt == 0xFF:
                i += 1 if nxt == 0xFF else 2
                continue
            break


def read_image(path, gray: bool = False) -> np.ndarray:
    """Read an 8-bit image with cv2: (H, W) uint8 if ``gray`` else as stored (BGR or gray).

    16-bit images are rejected (stereo images are 8-bit here), and so is a JPEG cut short
    (:func:`jpeg_complete`; cv2 would return it grey below the cut).  The file is read once:
    the bytes checked are the bytes decoded (``cv2.imdecode``, as ``cv2.imread`` would).
    """
    path = _check_exists(path)
    try:
        with open(path, "rb") as f:
            data = f.read()
    except OSError as exc:
        raise InputError(f"{path}: cannot read the file ({exc.strerror or exc})") from exc
    img = None
    if data:  # cv2.imdecode refuses an empty buffer with an assertion
        try:
            img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE if gray else cv2.IMREAD_UNCHANGED)
        except cv2.error:
            img = None
    if img is None:
        raise InputError(f"{path}: unreadable image (not a format cv2 can decode)")
    if data[:2] == b"\xff\xd8" and not jpeg_complete(data):
        raise InputError(f"{path}: the JPEG file ends before its end-of-image marker (truncated?)")
    if img.dtype != np.uint8:
        raise InputError(f"{path}: expected an 8-bit image, got {img.dtype}")
    if img.ndim == 3 and img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    return np.ascontiguousarray(img)


def write_image(path, img) -> None:
    """Write an 8-bit image (extension picks the format), atomically."""
    a = np.asarray(img)
    if a.dtype != np.uint8 or a.ndim not in (2, 3):
        raise InputError(f"write_image: expected a uint8 (H, W[, C]) array, got {a.dtype} {a.shape}")

    def write(tmp):
        if not cv2.imwrite(tmp, a):
            raise InputError(f"{path}: cv2 could not write the image")
    _atomic_write(path, write)
