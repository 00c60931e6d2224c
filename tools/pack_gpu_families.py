"""Pack the labeled pairs of every family for a GPU training run into one archive.

    python -m tools.pack_gpu_families [--data DATA] [--out .gpu_data.tar.xz]
                                      [--holdout PATTERN ...] [--val KEY ...] [--step 32]

The device tool carries 64 MiB in all and the four families' pairs are ~140 MB
on disk, most of it float PFM ground truth whose low mantissa bits are noise
to a compressor.  This writes the training pairs (every labeled pair that no
``--holdout`` pattern matches) and the validation pairs (``--val``: held-out
pairs, one per dataset by default) in their official layouts, ground-truth
PFMs rounded to 1/``--step`` px (finite values only; +inf stays unknown) and
images stored gray (training reads gray images only), as
one xz-compressed tar that ``scripts/gpu_train.sh`` unpacks into
``.gpu_data``.  ``discover`` reads the unpacked folder as it reads DATA.
Fails when the archive is over ``--limit-mib``.
"""

from __future__ import annotations

import argparse
import io
import sys
import tarfile
import tempfile
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from mccnn_cl.evaluation.datasets import _KITTI, _first_dir, discover, dataset_of  # noqa: E402
from mccnn_cl.evaluation.datasets import to_gray_u8  # noqa: E402
from mccnn_cl.io import read_image, read_pfm, write_pfm  # noqa: E402
from mccnn_cl.train.train import _matches  # noqa: E402

def general_fst_held_out() -> list:
    """The pairs the shipped general-fst was held out from (its training record): by default
    never packed for training."""
    from mccnn_cl.models import resolve

    return list(resolve("general-fst").meta["training"]["held_out"])


#: Held-out pairs packed for validation: one per dataset.
VAL = ("kitti2015/000000", "middlebury/Cones", "middlebury/trainingQ/Piano", "eth3d/delivery_area_1l")


def pair_files(ref) -> tuple:
    """(image files, other files) of one pair (absolute paths) in its official layout."""
    root = Path(ref.root)
    if ref.kind in _KITTI:
        frame = f"{ref.name}_10.png"
        images = [_first_dir(root, _KITTI[ref.kind][0]) / frame, _first_dir(root, _KITTI[ref.kind][1]) / frame]
        return images, [root / n / frame for n in _KITTI[ref.kind][2:] if (root / n / frame).exists()]
    images = [root / "im0.png", root / "im1.png"]
    other = [p for p in sorted(root.iterdir()) if p.is_file() and p not in images]
    if ref.kind == "eth3d":
        gt = root.parent.parent / "two_view_training_gt" / root.name
        other += [p for p in sorted(gt.iterdir()) if p.is_file()] if gt.is_dir() else []
    return images, other


def gray_png(path: Path) -> bytes:
    """The image at ``path`` as a gray PNG: training reads pairs through ``StereoPair.gray()``,
    which gives the same uint8 pixels for the original and for this."""
    ok, buf = cv2.imencode(".png", to_gray_u8(read_image(path)), [cv2.IMWRITE_PNG_COMPRESSION, 9])
    if not ok:
        raise RuntimeError(f"cannot encode {path} as PNG")
    return buf.tobytes()


def _add(tar, rel: str, blob: bytes) -> None:
    info = tarfile.TarInfo(rel)
    info.size = len(blob)
    tar.addfile(info, io.BytesIO(blob))


def quantized_pfm(path: Path, step: int, scratch: Path) -> bytes:
    """The PFM at ``path`` with its finite values rounded to 1/``step`` (written by the package's writer)."""
    g = read_pfm(path)
    q = np.where(np.isfinite(g), np.round(g * step) / step, g).astype(np.float32)
    write_pfm(scratch, q)
    return scratch.read_bytes()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", default=str(REPO.parent / "shared" / "data"))
    ap.add_argument("--out", default=str(REPO / ".gpu_data.tar.xz"))
    ap.add_argument("--holdout", nargs="*", default=None,
                    help="pairs (keys or patterns) not packed for training (default: general-fst's held-out pairs)")
    ap.add_argument("--val", nargs="*", default=list(VAL))
    ap.add_argument("--step", type=int, default=32, help="ground truth rounded to 1/STEP px (default %(default)s)")
    ap.add_argument("--limit-mib", type=float, default=50.0)
    args = ap.parse_args(argv)
    data = Path(args.data).resolve()
    if not data.is_dir():
        print(f"pack_gpu_families: no data folder at {data}", file=sys.stderr)
        return 2
    holdout = general_fst_held_out() if args.holdout is None else args.holdout
    refs = discover(data, labeled=True)
    train = [r for r in refs if not _matches(r.key, holdout)]
    val = [r for r in refs if r.key in set(args.val)]
    missing = sorted(set(args.val) - {r.key for r in val})
    if missing:
        print(f"pack_gpu_families: validation pairs not found under {data}: {', '.join(missing)}", file=sys.stderr)
        return 2
    out = Path(args.out)
    tmp = out.with_name(out.name + ".part")
    raw = 0
    with tempfile.TemporaryDirectory() as scratch, tarfile.open(tmp, "w:xz", preset=6) as tar:
        for ref in train + val:
            images, other = pair_files(ref)
            for f in images:
                _add(tar, f.relative_to(data).as_posix(), gray_png(f))
            for f in other:
                rel = f.relative_to(data).as_posix()
                if f.suffix == ".pfm":
                    _add(tar, rel, quantized_pfm(f, args.step, Path(scratch) / "gt.pfm"))
                else:
                    tar.add(f, arcname=rel)
            raw += sum(f.stat().st_size for f in images + other)
    tmp.replace(out)
    size = out.stat().st_size
    per = {}
    for r in train:
        per[dataset_of(r.key)] = per.get(dataset_of(r.key), 0) + 1
    print(f"pack_gpu_families: {len(train)} training pairs ("
          + ", ".join(f"{k} {v}" for k, v in sorted(per.items())) + f"), {len(val)} validation pairs ("
          + ", ".join(r.key for r in val) + f"); {raw / 2**20:.1f} MiB of files -> {out} {size / 2**20:.1f} MiB "
          f"(gray images, ground truth rounded to 1/{args.step} px)")
    if size > args.limit_mib * 2**20:
        print(f"pack_gpu_families: {out} is over the {args.limit_mib:g} MiB limit", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
