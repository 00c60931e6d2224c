"""Build tests/data/, the small real data bundled with the tests, from a full
data folder (default ../shared/data): crops of a few pairs in their datasets'
official layouts, so the package's loaders read them as they read the full
datasets.  Crops keep the top-left corner (pixel (x, y) of a crop is pixel
(x, y) of the original), so a test's window inside the crop sees the same
pixels with either folder.

    .venv/bin/python scripts/make_test_data.py [SRC] [DST]
"""

import re
import shutil
import sys
from pathlib import Path

import cv2

REPO = Path(__file__).resolve().parents[1]

#: (relative folder, files, rows, columns) copied as crops [0:rows, 0:columns]
KITTI2015 = ("kitti2015/training", ("image_2/000000_10.png", "image_3/000000_10.png",
                                     "disp_occ_0/000000_10.png", "disp_noc_0/000000_10.png"), 375, 704)
MIDDLEBURY = {"Tsukuba": None, "Cones": (240, 300), "Venus": (240, 300)}  # None: the whole scene
ETH3D = ("delivery_area_1s", 200, 320)


def crop_png(src: Path, dst: Path, rows: int, cols: int) -> None:
    img = cv2.imread(str(src), cv2.IMREAD_UNCHANGED)  # 16-bit KITTI disparities stay 16-bit
    assert img is not None, src
    dst.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(dst), img[:rows, :cols], [cv2.IMWRITE_PNG_COMPRESSION, 9]), dst


def crop_pfm(src: Path, dst: Path, rows: int, cols: int) -> None:
    sys.path.insert(0, str(REPO))
    from mccnn_cl.io import read_pfm, write_pfm

    write_pfm(dst, read_pfm(src)[:rows, :cols])


def crop_calib(src: Path, dst: Path, rows: int, cols: int) -> None:
    text = src.read_text()
    text = re.sub(r"(?m)^width=\d+", f"width={cols}", text)
    text = re.sub(r"(?m)^height=\d+", f"height={rows}", text)
    dst.write_text(text)


def crop_scene(src: Path, dst: Path, size) -> None:
    dst.mkdir(parents=True, exist_ok=True)
    for f in sorted(src.iterdir()):
        if size is None:
            shutil.copy(f, dst / f.name)
        elif f.suffix == ".png":
            crop_png(f, dst / f.name, *size)
        elif f.suffix == ".pfm":
            crop_pfm(f, dst / f.name, *size)
        elif f.name == "calib.txt":
            crop_calib(f, dst / f.name, *size)


def main(src: Path, dst: Path) -> None:
    rel, files, rows, cols = KITTI2015
    for f in files:
        crop_png(src / rel / f, dst / rel / f, rows, cols)
    (dst / rel / "calib_cam_to_cam").mkdir(parents=True, exist_ok=True)
    shutil.copy(src / rel / "calib_cam_to_cam/000000.txt", dst / rel / "calib_cam_to_cam/000000.txt")
    for scene, size in MIDDLEBURY.items():
        crop_scene(src / "middlebury" / scene, dst / "middlebury" / scene, size)
    scene, rows, cols = ETH3D
    for part in ("two_view_training", "two_view_training_gt"):
        crop_scene(src / "eth3d" / part / scene, dst / "eth3d" / part / scene, (rows, cols))


if __name__ == "__main__":
    args = sys.argv[1:]
    main(Path(args[0]) if args else REPO.parent / "shared" / "data",
         Path(args[1]) if len(args) > 1 else REPO / "tests" / "data")
