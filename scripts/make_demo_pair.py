"""Build the bundled demo pair mccnn_cl/demo/ from MiddEval3 Adirondack (training, quarter size).

    python scripts/make_demo_pair.py [SHARED_DATA_DIR] [--cones-eighth]

Adirondack is held out of the training of every shipped network.  The
images, the non-occlusion mask and calib.txt are copied byte for byte from
``SHARED_DATA_DIR/middeval3/trainingQ/Adirondack`` (the official MiddEval3
quarter-size files, 718x496); the float32 ground truth ``disp0GT.pfm``
(1.4 MB) is stored as ``disp0GT.png``, a KITTI-format 16-bit PNG
(round(d * 256), 0 = unknown; at most 1/512 px from the PFM), which
:func:`mccnn_cl.cli.demo.load_demo_pair` reads.

``--cones-eighth`` also rebuilds tests/cones_eighth/ (the tests' small
whole-scene pair): Middlebury Cones (2003, quarter size, 450x375) downscaled
by 2 with cv2.INTER_AREA to 225x188; the ground truth resampled with
INTER_NEAREST (never mixing disparities across depth edges) and halved, +inf
(unknown) kept; the non-occlusion mask likewise with INTER_NEAREST.
"""

import os
import shutil
import sys

import cv2
import numpy as np

from mccnn_cl.io import read_image, read_pfm, write_image, write_pfm

HERE = os.path.dirname(os.path.abspath(__file__))
DATA = next((a for a in sys.argv[1:] if not a.startswith("--")),
            os.path.join(HERE, "..", "..", "shared", "data"))
DST = os.path.join(HERE, "..", "mccnn_cl", "demo")
CONES_DST = os.path.join(HERE, "..", "tests", "cones_eighth")


def demo_pair():
    src = os.path.join(DATA, "middeval3", "trainingQ", "Adirondack")
    os.makedirs(DST, exist_ok=True)
    for name in ("im0.png", "im1.png", "mask0nocc.png", "calib.txt"):
        shutil.copyfile(os.path.join(src, name), os.path.join(DST, name))
    gt = read_pfm(os.path.join(src, "disp0GT.pfm"))
    known = np.isfinite(gt)
    # every known disparity is > 0 (calib.txt: vmin=8), so 0 can mean unknown
    assert (gt[known] > 0).all() and gt[known].max() * 256 < 65535
    raw = np.where(known, np.round(np.where(known, gt, 0) * 256.0), 0).astype(np.uint16)
    # what mccnn_cl.io.write_kitti_disparity writes, at PNG's highest compression (252 kB, not 342 kB)
    assert cv2.imwrite(os.path.join(DST, "disp0GT.png"), raw, [cv2.IMWRITE_PNG_COMPRESSION, 9])
    size = sum(os.path.getsize(os.path.join(DST, f)) for f in os.listdir(DST))
    print(f"{DST}: {gt.shape[1]}x{gt.shape[0]}, GT {known.mean():.1%} known, "
          f"range {gt[known].min():.2f}-{gt[known].max():.2f} px; folder {size / 1e6:.2f} MB")


def cones_eighth():
    src = os.path.join(DATA, "middlebury", "Cones")
    os.makedirs(CONES_DST, exist_ok=True)
    left = read_image(os.path.join(src, "im0.png"))
    right = read_image(os.path.join(src, "im1.png"))
    h, w = left.shape[:2]
    size = (int(round(w / 2)), int(round(h / 2 + 0.01)))  # 225 x 188
    for name, img in (("im0.png", left), ("im1.png", right)):
        write_image(os.path.join(CONES_DST, name), cv2.resize(img, size, interpolation=cv2.INTER_AREA))
    gt = read_pfm(os.path.join(src, "disp0GT.pfm"))
    small = cv2.resize(gt, size, interpolation=cv2.INTER_NEAREST) / np.float32(2.0)
    small[~np.isfinite(small)] = np.inf
    write_pfm(os.path.join(CONES_DST, "disp0GT.pfm"), small.astype(np.float32))
    mask = cv2.imread(os.path.join(src, "mask0nocc.png"), cv2.IMREAD_GRAYSCALE)
    write_image(os.path.join(CONES_DST, "mask0nocc.png"), cv2.resize(mask, size, interpolation=cv2.INTER_NEAREST))
    with open(os.path.join(CONES_DST, "calib.txt"), "w") as f:
        f.write(f"width={size[0]}\nheight={size[1]}\nndisp=32\n"
                "# Middlebury 2003 Cones, quarter size downscaled by 2 (eighth size); "
                "no cam0/baseline published\n")
    fin = np.isfinite(small)
    print(f"{CONES_DST}: {size[0]}x{size[1]}, GT {fin.mean():.1%} known, "
          f"range {small[fin].min():.2f}-{small[fin].max():.2f} px")


if __name__ == "__main__":
    demo_pair()
    if "--cones-eighth" in sys.argv[1:]:
        cones_eighth()
