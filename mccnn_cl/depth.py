"""Calibration files, disparity → depth, coloured point clouds (PLY).

Depth of a rectified pair: ``z = f · B / (d + doffs)`` with ``f`` the focal
length in pixels, ``B`` the baseline and ``doffs`` the difference of the two
cameras' principal points (``cx_right - cx_left``, 0 for KITTI).  ``z`` has
the unit of ``B``: metres for KITTI, millimetres for Middlebury.  Points:
``X = (x - cx) · z / f``, ``Y = (y - cy) · z / f``, ``Z = z`` (camera frame of
the left camera, x right, y down, z forward).

Calibration formats read by :func:`read_calib`:

* KITTI ``calib_cam_to_cam/*.txt`` (``P_rect_02``/``P_rect_03``, the colour
  cameras the datasets use) — or other cameras via ``cameras=(0, 1)``;
* KITTI per-frame ``calib/*.txt`` (``P0:`` … ``P3:`` lines);
* Middlebury ``calib.txt`` (``cam0=[f 0 cx; 0 f cy; 0 0 1]``, ``cam1``,
  ``doffs``, ``baseline`` in mm, ``width``, ``height``, ``ndisp``).  The
  2001–2006 scenes publish no calibration: their ``calib.txt`` has only the
  size and ``ndisp``, which is parsed (for the disparity range), but asking
  for depth then raises :class:`~mccnn_cl.errors.InputError`.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass

import numpy as np

from .errors import InputError

__all__ = ["Calibration", "read_calib", "disparity_to_depth", "point_cloud", "write_ply", "read_ply",
           "atomic_write", "colours_uint8"]


@dataclass
class Calibration:
    """What depth needs from a calibration file (``None`` where the file does not say)."""

    focal: float | None = None  # f, pixels
    baseline: float | None = None  # B, in `unit`
    doffs: float = 0.0  # cx_right - cx_left, pixels
    cx: float | None = None
    cy: float | None = None
    unit: str = ""
    width: int | None = None
    height: int | None = None
    ndisp: int | None = None
    source: str = ""
    kind: str = ""  # "kitti_cam_to_cam", "kitti_frame", "middlebury"

    @property
    def has_depth(self) -> bool:
        return self.focal is not None and self.baseline is not None

    def require_depth(self) -> None:
        if not self.has_depth:
            raise InputError(f"{self.source}: no focal length/baseline in this calibration file "
                             "(Middlebury 2001-2006 scenes publish none); depth needs cam0= and "
                             "baseline= (Middlebury) or P_rect_02/P_rect_03 (KITTI)")


def atomic_write(path, write_fn) -> None:
    """Call ``write_fn(tmp_path)`` then rename the temporary file onto ``path``
    (:func:`mccnn_cl.atomic.atomic_write`: recognisable temporary names, stale
    ones of crashed processes removed)."""
    from .atomic import atomic_write as write

    write(path, write_fn)


def _numbers(text, path, key, count):
    try:
        vals = [float(v) for v in re.split(r"[\s;,\[\]]+", text.strip()) if v]
    except ValueError as exc:
        raise InputError(f"{path}: cannot parse {key}: {text.strip()!r}") from exc
    if len(vals) != count:
        raise InputError(f"{path}: {key} has {len(vals)} numbers, expected {count}")
    return vals


def read_calib(path, cameras=(2, 3)) -> Calibration:
    """Read a KITTI or Middlebury calibration file (see the module docstring)."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise InputError(f"calibration file not found: {path}")
    try:
        with open(path, encoding="utf-8", errors="replace") as f:
            lines = f.read().splitlines()
    except OSError as exc:
        raise InputError(f"{path}: unreadable calibration file ({exc})") from exc
    entries = {}
    for line in lines:
        m = re.match(r"\s*([A-Za-z_][A-Za-z0-9_]*)\s*([:=])\s*(.*)$", line)
        if m:
            entries[m.group(1)] = m.group(3)
    left, right = cameras
    keys_ctc = (f"P_rect_{left:02d}", f"P_rect_{right:02d}")
    keys_frame = (f"P{left}", f"P{right}")
    for keys, kind in ((keys_ctc, "kitti_cam_to_cam"), (keys_frame, "kitti_frame")):
        if all(k in entries for k in keys):
            pl = np.array(_numbers(entries[keys[0]], path, keys[0], 12)).reshape(3, 4)
            pr = np.array(_numbers(entries[keys[1]], path, keys[1], 12)).reshape(3, 4)
            f = float(pl[0, 0])
            if f <= 0:
                raise InputError(f"{path}: {keys[0]} has focal length {f}")
            # P = K [I | t]: P[0, 3] = f * t_x; baseline = t_x(left) - t_x(right)
            baseline = (pl[0, 3] - pr[0, 3]) / f
            size = entries.get(f"S_rect_{left:02d}")
            w = h = None
            if size:
                w, h = (int(round(v)) for v in _numbers(size, path, "S_rect", 2))
            return Calibration(focal=f, baseline=float(baseline), doffs=float(pr[0, 2] - pl[0, 2]),
                               cx=float(pl[0, 2]), cy=float(pl[1, 2]), unit="m", width=w, height=h,
                               source=path, kind=kind)
    if any(k in entries for k in ("ndisp", "cam0", "baseline", "width")):
        cal = Calibration(unit="mm", source=path, kind="middlebury")
        for key, conv in (("width", int), ("height", int), ("ndisp", int)):
            if key in entries:
                try:
                    setattr(cal, key, conv(float(entries[key].split()[0])))
                except (ValueError, IndexError) as exc:
                    raise InputError(f"{path}: bad {key}: {entries[key]!r}") from exc
        if "cam0" in entries:
            k0 = _numbers(entries["cam0"], path, "cam0", 9)
            cal.focal, cal.cx, cal.cy = k0[0], k0[2], k0[5]
            if "cam1" in entries:
                cal.doffs = _numbers(entries["cam1"], path, "cam1", 9)[2] - k0[2]
        if "doffs" in entries:
            cal.doffs = _numbers(entries["doffs"], path, "doffs", 1)[0]
        if "baseline" in entries:
            cal.baseline = _numbers(entries["baseline"], path, "baseline", 1)[0]
        return cal
    raise InputError(f"{path}: not a KITTI (P_rect_{left:02d}/P_rect_{right:02d} or P{left}/P{right}) "
                     "or Middlebury (cam0/baseline/ndisp) calibration file")


def disparity_to_depth(disp, calib: Calibration) -> np.ndarray:
    """float32 depth ``f·B / (d + doffs)``; NaN where the disparity is invalid or ``d + doffs <= 0``."""
    calib.require_depth()
    d = np.asarray(disp, dtype=np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        denom = d + calib.doffs
        ok = np.isfinite(denom) & (denom > 0)
        z = np.full(d.shape, np.nan)
        z[ok] = calib.focal * calib.baseline / denom[ok]
    return z.astype(np.float32)


def colours_uint8(c, what: str = "colour image") -> np.ndarray:
    """Colour values as uint8, scaled as :func:`mccnn_cl.imageops.to_gray` reads
    the same types (the full range of each type is 0 .. 255): uint8 as they
    are, uint16 (either byte order) / 257 rounded (65535 -> 255, as 65535 and
    255 both mean 1.0 there), float in [0, 1] x 255 rounded (clipped to
    0 .. 255; NaN or infinity is an InputError).  Any other type is an
    :class:`~mccnn_cl.errors.InputError` (a plain cast would wrap uint16 and
    truncate [0, 1] floats to 0: a black cloud)."""
    a = np.asarray(c)
    if not a.dtype.isnative:
        a = a.astype(a.dtype.newbyteorder("="))
    if a.dtype == np.uint8:
        return a
    if a.dtype == np.uint16:
        return ((a.astype(np.uint32) * 2 + 257) // 514).astype(np.uint8)  # round(a / 257), exact integers
    if a.dtype.kind == "f":
        v = a.astype(np.float64)
        if not np.isfinite(v).all():
            raise InputError(f"{what}: float colours must be finite (NaN or infinity found)")
        return np.clip(np.round(v * 255.0), 0, 255).astype(np.uint8)
    raise InputError(f"{what}: dtype {a.dtype} not supported for colours (uint8, uint16, or float in [0, 1]); "
                     "convert it first, e.g. .astype(np.uint8) for values already in 0..255")


def point_cloud(disp, calib: Calibration, color=None, max_depth=None):
    """Points (N, 3) float32 and colours (N, 3) uint8 RGB of every pixel with a valid depth.

    ``color`` is the left image (BGR, BGRA or gray, as cv2 reads it: uint8,
    uint16 or float in [0, 1], brought to uint8 by :func:`colours_uint8`);
    without it the points are white.  ``max_depth`` drops points farther than
    that (unit of B).
    """
    z = disparity_to_depth(disp, calib).astype(np.float64)
    h, w = z.shape
    cx = calib.cx if calib.cx is not None else (w - 1) / 2.0
    cy = calib.cy if calib.cy is not None else (h - 1) / 2.0
    ok = np.isfinite(z)
    if max_depth is not None:
        ok &= z <= max_depth
    ys, xs = np.nonzero(ok)
    zz = z[ok]
    pts = np.stack([(xs - cx) * zz / calib.focal, (ys - cy) * zz / calib.focal, zz], 1).astype(np.float32)
    if color is None:
        rgb = np.full((len(zz), 3), 255, np.uint8)
    else:
        c = np.asarray(color)
        if c.shape[:2] != (h, w):
            raise InputError(f"colour image {c.shape[:2]} does not match the disparity map {(h, w)}")
        if c.ndim == 3 and c.shape[2] == 1:
            c = c[:, :, 0]
        if not (c.ndim == 2 or (c.ndim == 3 and c.shape[2] in (3, 4))):
            raise InputError(f"colour image: expected H x W (gray) or H x W x 3/4 (BGR/BGRA), got shape {c.shape}")
        picked = colours_uint8(c[ok], "colour image")
        if c.ndim == 2:
            rgb = np.repeat(picked[:, None], 3, 1)
        else:
            rgb = np.ascontiguousarray(picked[:, 2::-1])  # BGR -> RGB
    return pts, rgb


def write_ply(path, points, colors=None, binary=True) -> None:
    """Write a point cloud as PLY (binary little-endian or ASCII), atomically.
    ``colors``: (N, 3) RGB, uint8, uint16 or float in [0, 1] (:func:`colours_uint8`);
    None: white."""
    pts = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    n = len(pts)
    if colors is None:
        colors = np.full((n, 3), 255, np.uint8)
    cols = colours_uint8(colors, "write_ply colours").reshape(-1, 3)
    if len(cols) != n:
        raise InputError(f"write_ply: {n} points but {len(cols)} colours")
    fmt = "binary_little_endian" if binary else "ascii"
    header = (f"ply\nformat {fmt} 1.0\ncomment written by mccnn_cl\nelement vertex {n}\n"
              "property float x\nproperty float y\nproperty float z\n"
              "property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n").encode("ascii")
    rec = np.empty(n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                             ("red", "u1"), ("green", "u1"), ("blue", "u1")])
    rec["x"], rec["y"], rec["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
    rec["red"], rec["green"], rec["blue"] = cols[:, 0], cols[:, 1], cols[:, 2]

    def write(tmp):
        with open(tmp, "wb") as f:
            f.write(header)
            if binary:
                f.write(rec.tobytes())
            else:
                for p, c in zip(pts, cols):
                    f.write(b"%.6g %.6g %.6g %d %d %d\n" % (p[0], p[1], p[2], c[0], c[1], c[2]))
    atomic_write(path, write)


_PLY_TYPES = {"float": "f4", "float32": "f4", "double": "f8", "float64": "f8", "uchar": "u1",
              "uint8": "u1", "char": "i1", "int8": "i1", "short": "i2", "ushort": "u2",
              "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4"}


def read_ply(path):
    """Read a vertex-only PLY (as written by :func:`write_ply`): returns ``(points, colors or None)``."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise InputError(f"file not found: {path}")
    with open(path, "rb") as f:
        data = f.read()
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply") or end < 0:
        raise InputError(f"{path}: not a PLY file")
    header = data[:end].decode("ascii").splitlines()
    body = data[end + len(b"end_header\n"):]
    fmt, n, props = None, None, []
    for line in header:
        parts = line.split()
        if parts[:1] == ["format"]:
            fmt = parts[1]
        elif parts[:2] == ["element", "vertex"]:
            n = int(parts[2])
        elif parts[:1] == ["element"]:
            raise InputError(f"{path}: only vertex elements are supported")
        elif parts[:1] == ["property"]:
            if parts[1] not in _PLY_TYPES:
                raise InputError(f"{path}: unsupported property type {parts[1]}")
            props.append((parts[2], _PLY_TYPES[parts[1]]))
    if fmt not in ("ascii", "binary_little_endian") or n is None:
        raise InputError(f"{path}: unsupported PLY header (format {fmt}, vertices {n})")
    names = [p for p, _ in props]
    if fmt == "binary_little_endian":
        dt = np.dtype([(p, "<" + t) for p, t in props])
        if len(body) < n * dt.itemsize:
            raise InputError(f"{path}: truncated PLY ({len(body)} bytes, expected {n * dt.itemsize})")
        rec = np.frombuffer(body, dtype=dt, count=n)
        cols = {p: rec[p] for p in names}
    else:
        rows = body.decode("ascii").split("\n")
        rows = [r for r in rows if r.strip()]
        if len(rows) < n:
            raise InputError(f"{path}: truncated PLY ({len(rows)} rows, expected {n})")
        table = np.array([r.split() for r in rows[:n]], dtype=np.float64).reshape(n, len(names))
        cols = {p: table[:, i] for i, p in enumerate(names)}
    pts = np.stack([cols["x"], cols["y"], cols["z"]], 1).astype(np.float32)
    rgb = None
    if all(k in cols for k in ("red", "green", "blue")):
        rgb = np.stack([cols["red"], cols["green"], cols["blue"]], 1).astype(np.uint8)
    return pts, rgb
