"""Readers for stereo datasets with ground truth, in their official layouts.

Supported layouts (they work unchanged on a full copy of each dataset):

KITTI 2012 (``kind="kitti2012"``)
    ``<root>/colored_0|image_0/<frame>_10.png`` (left), ``colored_1|image_1``
    (right), ``disp_noc/`` (non-occluded GT) and ``disp_occ/`` (all GT); 16-bit
    PNGs, disparity = value / 256, 0 = unknown.
KITTI 2015 (``kind="kitti2015"``)
    ``image_2`` (left), ``image_3`` (right), ``disp_noc_0``, ``disp_occ_0``.
Middlebury MiddEval3 (``kind="middlebury"``)
    one folder per scene: ``im0.png``, ``im1.png``, ``disp0GT.pfm`` (or
    ``disp0.pfm``; +inf = unknown), optional ``mask0nocc.png`` (255 =
    non-occluded, 128 = occluded, 0 = unknown) and ``calib.txt``
    (``ndisp``, ``width``, ``height``, ...).  Scenes inside MiddEval3's
    ``trainingQ|H|F`` / ``testQ|H|F`` folders (the GT archive merged in) are
    named ``trainingQ/<scene>`` and belong to the ``middeval3`` dataset.
ETH3D two-view (``kind="eth3d"``)
    ``two_view_training/<scene>/{im0.png, im1.png, calib.txt}`` beside
    ``two_view_training_gt/<scene>/{disp0GT.pfm, mask0nocc.png}`` (the two
    official archives unpacked side by side; ``two_view_test`` has no GT).
    ETH3D's ``calib.txt`` sets ``ndisp`` to the image width, a loose bound
    rather than a range to search, so such pairs get ``ndisp`` =
    :data:`ETH3D_NDISP` (64: the GT of the 27 low-res training scenes stays
    below it; the largest is forest_1s at 61.3 px); the calib value is kept
    in ``calib_ndisp``.

Every pair belongs to a *dataset* (:func:`dataset_of`: kitti, middlebury,
middeval3, eth3d) and a *scene family* (:func:`scene_family`): Middlebury
scenes sharing a name stem (Cloth1-4, Baby1-3), MiddEval3's lighting /
exposure variants (Piano, PianoL), ETH3D's views of one place
(delivery_area_1l/1s/2l/2s); a KITTI frame is its own family.  Hold families
out whole when measuring.

Ground truth is optional (KITTI ``testing/``, MiddEval3 test scenes): such
pairs have ``disp = None``.  Every problem a user's files can cause raises
:class:`~mccnn_cl.errors.InputError`.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..imageops import luminance
from ..io import read_image, read_kitti_disparity, read_pfm

__all__ = ["StereoPair", "PairRef", "load_kitti2012", "load_kitti2015", "load_middlebury", "load_eth3d",
           "read_calib", "discover", "find_pairs", "KINDS", "DATASETS", "ETH3D_NDISP", "dataset_of",
           "scene_family"]

KINDS = ("kitti2012", "kitti2015", "middlebury", "eth3d")

#: Dataset families a pair can belong to (:func:`dataset_of`).
DATASETS = ("kitti", "middlebury", "middeval3", "eth3d")

#: Disparity range given to ETH3D two-view pairs (their calib.txt says the image width).
ETH3D_NDISP = 64

#: ETH3D folders holding scenes, and where their GT lives.
_ETH3D_SPLITS = {"two_view_training": "two_view_training_gt", "two_view_test": None}

#: Ground-truth files of a MiddEval3-layout scene, first existing wins.
MIDDLEBURY_GT = ("disp0GT.pfm", "disp0.pfm")

_KITTI = {
    # kind: (left dirs, right dirs, noc dir, occ dir) -- first existing wins
    "kitti2012": (("colored_0", "image_0"), ("colored_1", "image_1"), "disp_noc", "disp_occ"),
    "kitti2015": (("image_2",), ("image_3",), "disp_noc_0", "disp_occ_0"),
}


class _Named:
    """``key``, ``dataset`` and ``family`` of a pair from its ``kind`` and ``name``
    (shared by :class:`StereoPair` and :class:`PairRef`)."""

    @property
    def key(self) -> str:
        """``"<kind>/<name>"``, e.g. ``"kitti2015/000000"`` or ``"middlebury/Cones"``."""
        return f"{self.kind}/{self.name}"

    @property
    def dataset(self) -> str:
        """The pair's dataset family (:func:`dataset_of`)."""
        return dataset_of(self.key)

    @property
    def family(self) -> str:
        """The pair's scene family (:func:`scene_family`), e.g. ``"middlebury/Cloth"``."""
        return scene_family(self.key)


@dataclass
class StereoPair(_Named):
    """A rectified stereo pair and its ground truth.

    ``left``/``right``: uint8 images as read (colour = BGR (H, W, 3), or gray
    (H, W)).  ``disp``: float32 (H, W) left disparities, NaN where unknown, or
    ``None`` when the pair has no ground truth.  ``valid_noc``: bool (H, W),
    True where GT is known and not occluded (``None`` when the dataset gives no
    occlusion information).  ``valid_all``: True where GT is known (``None``
    without GT).  ``ndisp``: the disparity-range bound from ``calib.txt``
    (Middlebury) or ``None``.  ``calib``: path of the calibration file or
    ``None``.  ``kind``: one of :data:`KINDS`.  ``disp_range``: ``(vmin, vmax)``
    when the layout states the GT's disparity bounds (MiddEval3 calib.txt), else None.
    """

    name: str
    left: np.ndarray
    right: np.ndarray
    disp: np.ndarray | None
    valid_noc: np.ndarray | None
    valid_all: np.ndarray | None
    ndisp: int | None
    calib: str | None
    kind: str
    disp_range: tuple | None = None
    calib_ndisp: int | None = None  # ndisp as calib.txt states it, where it differs from ``ndisp``

    @property
    def shape(self) -> tuple:
        return tuple(self.left.shape[:2])

    def gray(self) -> tuple:
        """(left, right) as (H, W) uint8 gray images (colour → luminance, cv2's BGR2GRAY)."""
        return to_gray_u8(self.left), to_gray_u8(self.right)

    def max_gt(self) -> float:
        """Largest known GT disparity (NaN without GT)."""
        if self.disp is None or not np.isfinite(self.disp).any():
            return float("nan")
        return float(np.nanmax(self.disp))


def to_gray_u8(img: np.ndarray) -> np.ndarray:
    """uint8 BGR or gray → (H, W) uint8 gray (:func:`mccnn_cl.imageops.luminance`)."""
    return luminance(img)


def _check_shapes(name, **arrays):
    shapes = {k: tuple(v.shape[:2]) for k, v in arrays.items() if v is not None}
    if len(set(shapes.values())) > 1:
        detail = ", ".join(f"{k} {s[1]}x{s[0]}" for k, s in shapes.items())
        raise InputError(f"{name}: image/ground-truth sizes differ ({detail})")


def _frame_name(frame) -> str:
    if isinstance(frame, (int, np.integer)):
        return f"{int(frame):06d}"
    frame = str(frame)
    if frame.endswith(".png"):
        frame = frame[:-4]
    if frame.endswith("_10"):
        frame = frame[:-3]
    return frame


def _first_dir(root: Path, names) -> Path | None:
    for n in names:
        if (root / n).is_dir():
            return root / n
    return None


def _load_kitti(kind: str, root, frame) -> StereoPair:
    root = Path(root)
    if (root / "training").is_dir() and _first_dir(root, _KITTI[kind][0]) is None:
        root = root / "training"
    frame = _frame_name(frame)
    left_dirs, right_dirs, noc_dir, occ_dir = _KITTI[kind]
    ldir, rdir = _first_dir(root, left_dirs), _first_dir(root, right_dirs)
    if ldir is None or rdir is None:
        raise InputError(f"{root}: not a {kind} folder (needs {'/'.join(left_dirs)} and "
                         f"{'/'.join(right_dirs)})")
    fname = f"{frame}_10.png"
    left = read_image(ldir / fname)
    right = read_image(rdir / fname)
    disp = valid_noc = valid_all = None
    noc_path, occ_path = root / noc_dir / fname, root / occ_dir / fname
    d_noc = d_occ = None
    if noc_path.exists():
        d_noc, valid_noc = read_kitti_disparity(noc_path)
    if occ_path.exists():
        d_occ, valid_all = read_kitti_disparity(occ_path)
    _check_shapes(f"{kind} {root}/{frame}", left=left, right=right, disp_noc=d_noc, disp_occ=d_occ)
    if d_occ is not None:
        disp = np.where(valid_all, d_occ, np.float32(np.nan)).astype(np.float32)
    elif d_noc is not None:
        # Only the non-occluded GT exists: it is all the GT there is.
        valid_all = valid_noc.copy()
        disp = np.where(valid_noc, d_noc, np.float32(np.nan)).astype(np.float32)
    if valid_noc is not None and valid_all is not None:
        valid_noc = valid_noc & valid_all
    calib = None
    for c in (root / "calib_cam_to_cam" / f"{frame}.txt", root / "calib" / f"{frame}.txt"):
        if c.exists():
            calib = str(c)
            break
    return StereoPair(name=frame, left=left, right=right, disp=disp, valid_noc=valid_noc,
                      valid_all=valid_all, ndisp=None, calib=calib, kind=kind)


def load_kitti2012(root, frame) -> StereoPair:
    """Load KITTI 2012 frame ``frame`` (``"000000"`` or ``0``) from a ``training``/``testing`` folder
    (or the dataset root holding ``training/``)."""
    return _load_kitti("kitti2012", root, frame)


def load_kitti2015(root, frame) -> StereoPair:
    """Load KITTI 2015 frame ``frame`` from a ``training``/``testing`` folder (or the dataset root)."""
    return _load_kitti("kitti2015", root, frame)


def read_calib(path) -> dict:
    """Parse a Middlebury ``calib.txt`` (``key=value`` lines; ``#`` comments) into a dict of strings."""
    path = os.fspath(path)
    out = {}
    try:
        with open(path, encoding="utf-8", errors="replace") as f:
            for line in f:
                line = line.split("#", 1)[0].strip()
                if "=" in line:
                    k, v = line.split("=", 1)
                    out[k.strip()] = v.strip()
    except OSError as exc:
        raise InputError(f"{path}: unreadable calib file ({exc})") from exc
    return out


def _calib_int(calib: dict, key: str, path) -> int | None:
    if key not in calib:
        return None
    try:
        return int(float(calib[key]))
    except ValueError as exc:
        raise InputError(f"{path}: {key}={calib[key]!r} is not a number") from exc


def _calib_range(calib: dict, path):
    """``(vmin, vmax)`` of a calib.txt that states both (MiddEval3), else None."""
    if "vmin" not in calib or "vmax" not in calib:
        return None
    try:
        lo, hi = float(calib["vmin"]), float(calib["vmax"])
    except ValueError as exc:
        raise InputError(f"{path}: vmin/vmax are not numbers") from exc
    if not (np.isfinite(lo) and np.isfinite(hi)) or lo >= hi:
        raise InputError(f"{path}: vmin={lo:g} must be smaller than vmax={hi:g}")
    return lo, hi


def load_middlebury(scene_dir) -> StereoPair:
    """Load a MiddEval3-layout scene folder (``im0.png``, ``im1.png``, ``disp0GT.pfm``, ...)."""
    scene = Path(scene_dir)
    if not scene.is_dir():
        raise InputError(f"Middlebury scene folder not found: {scene}")
    left = read_image(scene / "im0.png")
    right = read_image(scene / "im1.png")
    disp = valid_noc = valid_all = None
    calib_path = scene / "calib.txt"
    c = read_calib(calib_path) if calib_path.exists() else {}
    disp_range = _calib_range(c, calib_path)
    gt_path = next((scene / n for n in MIDDLEBURY_GT if (scene / n).exists()), None)
    if gt_path is not None:
        gt = read_pfm(gt_path)
        if gt.ndim != 2:
            raise InputError(f"{gt_path}: expected a 1-channel PFM, got {gt.shape[2]} channels")
        # +inf marks unknown; negative disparities only where calib.txt's vmin says the range has them
        valid_all = np.isfinite(gt) & (gt >= min(0.0, disp_range[0] if disp_range else 0.0))
        disp = np.where(valid_all, gt, np.float32(np.nan)).astype(np.float32)
    mask_path = scene / "mask0nocc.png"
    mask = read_image(mask_path, gray=True) if mask_path.exists() else None
    _check_shapes(f"Middlebury {scene}", im0=left, im1=right, disp0GT=disp, mask0nocc=mask)
    if mask is not None and valid_all is not None:
        valid_noc = (mask == 255) & valid_all
    ndisp, calib = None, None
    if calib_path.exists():
        calib = str(calib_path)
        ndisp = _calib_int(c, "ndisp", calib_path)
        w, h = _calib_int(c, "width", calib_path), _calib_int(c, "height", calib_path)
        if (w is not None and w != left.shape[1]) or (h is not None and h != left.shape[0]):
            raise InputError(f"{calib_path}: says {w}x{h} but im0.png is "
                             f"{left.shape[1]}x{left.shape[0]}")
    return StereoPair(name=scene.name, left=left, right=right, disp=disp, valid_noc=valid_noc,
                      valid_all=valid_all, ndisp=ndisp, calib=calib, kind="middlebury", disp_range=disp_range)


def load_eth3d(scene_dir, gt_dir=None) -> StereoPair:
    """Load an ETH3D two-view scene: ``two_view_training/<scene>`` (images, calib.txt); its GT
    (``disp0GT.pfm``, ``mask0nocc.png``) from ``gt_dir``, by default the sibling
    ``two_view_training_gt/<scene>`` (no GT when that folder does not exist).

    ``ndisp`` is :data:`ETH3D_NDISP` (the calib's ``ndisp``, the image width, is in ``calib_ndisp``).
    """
    scene = Path(scene_dir)
    if not scene.is_dir():
        raise InputError(f"ETH3D scene folder not found: {scene}")
    if gt_dir is None:
        gt_name = _ETH3D_SPLITS.get(scene.parent.name)
        gt_dir = scene.parent.parent / gt_name / scene.name if gt_name else None
    pair = load_middlebury(scene) if gt_dir is None or not Path(gt_dir).is_dir() else None
    if pair is None:
        gt = Path(gt_dir)
        left = read_image(scene / "im0.png")
        right = read_image(scene / "im1.png")
        disp = valid_noc = valid_all = None
        if (gt / "disp0GT.pfm").exists():
            g = read_pfm(gt / "disp0GT.pfm")
            if g.ndim != 2:
                raise InputError(f"{gt / 'disp0GT.pfm'}: expected a 1-channel PFM, got {g.shape[2]} channels")
            valid_all = np.isfinite(g) & (g >= 0)
            disp = np.where(valid_all, g, np.float32(np.nan)).astype(np.float32)
        mask_path = gt / "mask0nocc.png"
        mask = read_image(mask_path, gray=True) if mask_path.exists() else None
        _check_shapes(f"ETH3D {scene}", im0=left, im1=right, disp0GT=disp, mask0nocc=mask)
        if mask is not None and valid_all is not None:
            valid_noc = (mask == 255) & valid_all
        calib = str(scene / "calib.txt") if (scene / "calib.txt").exists() else None
        cnd = _calib_int(read_calib(calib), "ndisp", calib) if calib else None
        pair = StereoPair(name=scene.name, left=left, right=right, disp=disp, valid_noc=valid_noc,
                          valid_all=valid_all, ndisp=None, calib=calib, kind="eth3d")
    else:
        cnd = pair.ndisp
    pair.kind, pair.name = "eth3d", scene.name
    pair.calib_ndisp, pair.ndisp = cnd, ETH3D_NDISP
    return pair


# -- families ------------------------------------------------------------------

def dataset_of(key: str) -> str:
    """Dataset family of a pair key: ``kitti`` (2012 and 2015), ``middeval3`` (scenes in a
    MiddEval3 ``trainingQ|H|F``/``testQ|H|F`` folder), ``eth3d``, else ``middlebury``."""
    kind, _, name = str(key).partition("/")
    if kind.startswith("kitti"):
        return "kitti"
    if kind == "eth3d":
        return "eth3d"
    if re.match(r"(training|test)[QHF]/", name):
        return "middeval3"
    return "middlebury"


def scene_family(key: str) -> str:
    """``"<dataset>/<stem>"``: pairs of one scene family share it (hold them out together).

    Middlebury: the name without trailing digits (Cloth1-4 -> Cloth, Baby1-3 -> Baby) and
    without 2014's rectification suffix (Adirondack-perfect, -imperfect -> Adirondack);
    MiddEval3: the scene without its lighting / exposure / perfect-rectification suffix
    (PianoL -> Piano, MotorcycleE -> Motorcycle, PlaytableP -> Playtable, Classroom2E ->
    Classroom2); ETH3D: the place without ``_<n><l|s>`` (delivery_area_1l
    -> delivery_area); KITTI: the frame itself (``kitti2015/000000``).
    """
    ds = dataset_of(key)
    kind, _, name = str(key).partition("/")
    base = name.rsplit("/", 1)[-1]
    if ds == "kitti":
        return f"{kind}/{name}"
    if ds == "eth3d":
        return "eth3d/" + re.sub(r"_\d+[ls]?$", "", base)
    if ds == "middeval3":
        return "middeval3/" + re.sub(r"(?<=[a-z0-9])[LEP]$", "", base)
    base = re.sub(r"-(perfect|imperfect)$", "", base)
    return "middlebury/" + (re.sub(r"\d+$", "", base) or base)


# -- layout detection -------------------------------------------------------

@dataclass(frozen=True)
class PairRef(_Named):
    """A pair found on disk but not loaded yet: ``load()`` reads it."""

    kind: str
    root: str  # KITTI: the training/testing folder; Middlebury, ETH3D: the scene folder
    name: str
    labeled: bool = True  # ground truth on disk (False: images only, e.g. the shared data's unlabeled/)

    def load(self) -> StereoPair:
        if self.kind == "eth3d":
            return load_eth3d(self.root)
        if self.kind == "middlebury":
            pair = load_middlebury(self.root)
            pair.name = self.name
            return pair
        return _load_kitti(self.kind, self.root, self.name)


def _kitti_kind(d: Path) -> str | None:
    if (d / "image_2").is_dir() and (d / "image_3").is_dir():
        return "kitti2015"
    if _first_dir(d, _KITTI["kitti2012"][0]) and _first_dir(d, _KITTI["kitti2012"][1]):
        return "kitti2012"
    return None


def _kitti_refs(kind: str, d: Path) -> list:
    ldir = _first_dir(d, _KITTI[kind][0])
    frames = sorted(p.name[:-7] for p in ldir.glob("*_10.png"))
    gt_dirs = [d / n for n in _KITTI[kind][2:]]
    return [PairRef(kind, str(d), f, any((g / f"{f}_10.png").exists() for g in gt_dirs)) for f in frames]


def _middlebury_gt(d: Path) -> bool:
    return any((d / n).exists() for n in MIDDLEBURY_GT)


def _scene_name(d: Path) -> str:
    """Scene name; inside MiddEval3's resolution folders it keeps the folder (``trainingQ/Adirondack``)
    so the same scene at several resolutions gets distinct keys, and so does a scene without
    ground truth (``eth3d_two_view/electro_1l``): the same scene may be in a labelled collection too."""
    if re.fullmatch(r"(training|test)[QHF]", d.parent.name) or not _middlebury_gt(d):
        return f"{d.parent.name}/{d.name}"
    return d.name


def discover(root, dataset: str | None = None, labeled: bool | None = None) -> list:
    """Find every stereo pair under ``root`` without loading it: a list of :class:`PairRef`.

    ``root`` may be a KITTI dataset root (holding ``training/``), a KITTI
    ``training``/``testing`` folder, a Middlebury scene folder, a folder of
    scenes (e.g. MiddEval3 ``trainingQ``, ETH3D ``two_view_training``), or any folder holding such folders
    (searched three levels deep, in sorted order).  ``dataset`` (one of
    :data:`KINDS`) keeps only pairs of that kind; ``labeled`` True only pairs
    with ground truth on disk, False only pairs without (images only: they
    load with ``disp``, ``valid_all``, ``valid_noc`` None), None both.
    """
    refs = _discover(root, dataset, 0)
    return refs if labeled is None else [r for r in refs if r.labeled == bool(labeled)]


def _discover(root, dataset, _depth):
    if dataset is not None and dataset not in KINDS:
        raise InputError(f"unknown dataset {dataset!r}; expected one of {', '.join(KINDS)}")
    d = Path(root)
    if not d.is_dir():
        raise InputError(f"data folder not found: {d}")
    kind = _kitti_kind(d)
    if kind is not None:
        return _kitti_refs(kind, d) if dataset in (None, kind) else []
    if (d / "im0.png").exists() and (d / "im1.png").exists() and d.parent.name in _ETH3D_SPLITS:
        gt_name = _ETH3D_SPLITS[d.parent.name]
        labeled = bool(gt_name) and (d.parent.parent / gt_name / d.name / "disp0GT.pfm").exists()
        return [PairRef("eth3d", str(d), d.name, labeled)] if dataset in (None, "eth3d") else []
    if (d / "im0.png").exists() and (d / "im1.png").exists():
        return ([PairRef("middlebury", str(d), _scene_name(d), _middlebury_gt(d))]
                if dataset in (None, "middlebury") else [])
    if _depth >= 3:
        return []
    refs = []
    for sub in sorted(p for p in d.iterdir() if p.is_dir() and not p.name.startswith(".")):
        # In a KITTI root prefer training/ (which has GT) and skip testing/ unless asked directly.
        if sub.name == "testing" and (d / "training").is_dir():
            continue
        refs.extend(_discover(sub, dataset, _depth + 1))
    return refs


def find_pairs(root, dataset: str | None = None, labeled: bool | None = None) -> list:
    """Load every pair :func:`discover` finds under ``root``; raises InputError if there is none."""
    refs = discover(root, dataset, labeled)
    if not refs:
        raise InputError(f"no stereo pairs found under {root}"
                         + (f" for dataset {dataset}" if dataset else "")
                         + " (expected a KITTI 2012/2015, Middlebury MiddEval3 or ETH3D two-view layout)")
    return [r.load() for r in refs]
