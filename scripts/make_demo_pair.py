"""Build the bundled demo pair mccnn_cl/demo/ from Middlebury Cones (2003, quarter size).

    python scripts/make_demo_pair.py [SHARED_DATA_DIR]

Cones is held out of the shipped model's training.  Images are downscaled by
2 with cv2.INTER_AREA (450×375 -> 225×188); the ground truth is resampled
with INTER_NEAREST (never mixing disparities across depth edges) and halved,
+inf (unknown) kept; the non-occlusion mask likewise with INTER_NEAREST.
"""

import os
import sys

import cv2
import numpy as np

from mccnn_cl.io import read_image, read_pfm, write_image, write_pfm

SRC = os.path.join(sys.argv[1] if len(sys.argv) > 1 else
                   os.path.join(os.path.dirname(__file__), "..", "..", "shared", "data"),
                   "middlebury", "Cones")
DST = os.path.join(os.path.dirname(__file__), "..", "mccnn_cl", "demo")


def main():
    os.makedirs(DST, exist_ok=True)
    left = read_image(os.path.join(SRC, "im0.png"))
    right = read_image(os.path.join(SRC, "im1.png"))
    h, w = left.shape[:2]
    size = (int(round(w / 2)), int(round(h / 2 + 0.01)))  # 225 x 188
    for name, img in (("im0.png", left), ("im1.png", right)):
        write_image(os.path.join(DST, name), cv2.resize(img, size, interpolation=cv2.INTER_AREA))
    gt = read_pfm(os.path.join(SRC, "disp0GT.pfm"))
    small = cv2.resize(gt, size, interpolation=cv2.INTER_NEAREST) / np.float32(2.0)
    small[~np.isfinite(small)] = np.inf
    write_pfm(os.path.join(DST, "disp0GT.pfm"), small.astype(np.float32))
    mask = cv2.imread(os.path.join(SRC, "mask0nocc.png"), cv2.IMREAD_GRAYSCALE)
    write_image(os.path.join(DST, "mask0nocc.png"), cv2.resize(mask, size, interpolation=cv2.INTER_NEAREST))
    with open(os.path.join(DST, "calib.txt"), "w") as f:
        f.write(f"width={size[0]}\nheight={size[1]}\nndisp=32\n"
                "# Middlebury 2003 Cones, quarter size downscaled by 2 (eighth size); "
                "no cam0/baseline published\n")
    fin = np.isfinite(small)
    print(f"{DST}: {size[0]}x{size[1]}, GT {fin.mean():.1%} known, "
          f"range {small[fin].min():.2f}-{small[fin].max():.2f} px")


if __name__ == "__main__":
    main()
