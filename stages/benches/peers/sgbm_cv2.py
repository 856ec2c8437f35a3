"""OpenCV StereoSGBM on a rectified pair: the peer of dist4d's plane-sweep stereo on Middlebury.

    python sgbm_cv2.py LEFT RIGHT --num-disp 80 --mode sgbm|hh --out DISP.npy

Prints one JSON line: {"peer": ..., "best_seconds": ...}. DISP.npy is float32 disparity in
pixels, NaN where SGBM gives none. Settings are OpenCV's documented recipe for colour images:
blockSize 5, P1 = 8*3*5^2, P2 = 32*3*5^2, uniquenessRatio 10, disp12MaxDiff 1 (its left-right
check), speckle filter 100 px / range 2.
"""
import argparse, json, time

import cv2
import numpy as np

ap = argparse.ArgumentParser()
ap.add_argument("left")
ap.add_argument("right")
ap.add_argument("--num-disp", type=int, default=80)
ap.add_argument("--mode", choices=["sgbm", "hh"], default="sgbm")
ap.add_argument("--repeat", type=int, default=5)
ap.add_argument("--out", required=True)
a = ap.parse_args()

left, right = cv2.imread(a.left), cv2.imread(a.right)
bs = 5
sgbm = cv2.StereoSGBM_create(
    minDisparity=0,
    numDisparities=(a.num_disp + 15) // 16 * 16,
    blockSize=bs,
    P1=8 * 3 * bs * bs,
    P2=32 * 3 * bs * bs,
    disp12MaxDiff=1,
    uniquenessRatio=10,
    speckleWindowSize=100,
    speckleRange=2,
    mode=cv2.STEREO_SGBM_MODE_SGBM if a.mode == "sgbm" else cv2.STEREO_SGBM_MODE_HH,
)
cv2.setNumThreads(1)
best = float("inf")
for _ in range(a.repeat):
    t = time.perf_counter()
    raw = sgbm.compute(left, right)
    best = min(best, time.perf_counter() - t)
disp = raw.astype(np.float32) / 16.0
disp[raw < 0] = np.nan
np.save(a.out, disp)
print(json.dumps({"peer": f"cv2.StereoSGBM {a.mode}", "best_seconds": best}))
