#!/usr/bin/env python3
"""The streak ratio of issue 42 on a synthetic dataset's exact depth, beside the curated depth's.

The ratio (stages/src/eval/labels.rs `streak_ratio`: in the top third, sky excluded, the share of
vertically equal neighbours over the share of horizontally equal ones) is measured on the exact
ground truth rounded as the curated depth is (16 significant bits), and on the curated depth;
then the copies the truth does not have: neighbour pairs with equal curated depth whose true
depths differ by more than 1%, vertically and horizontally (a streak is a vertical copy).

    python3 scripts/streak_truth.py GROUNDTRUTH_DIR EXPORT_SCENE_DIR
    e.g. demo/data/nuscenes/groundtruth demo/pipelines/out/curation/synth-0000   (after `dist4d demo`)

Needs numpy and OpenCV with OpenEXR (the peer venv of ../shared/bench/peers/setup.sh).
"""
import glob, os, sys
os.environ.setdefault('OPENCV_IO_ENABLE_OPENEXR', '1')
import cv2
import numpy as np

SKY = 99.0

def rounded(a):
    bits = np.ascontiguousarray(a.astype(np.float32)).view(np.uint32)
    return ((bits + np.uint32(0x80)) & np.uint32(0xFFFFFF00)).view(np.float32)

def pairs(d, n):
    """(vertical, horizontal) neighbour pairs of the top `n` rows: (a, b, both usable)."""
    use = (d > 0) & (d < SKY) & np.isfinite(d)
    return ((d[:n], d[1:n + 1], use[:n] & use[1:n + 1]), (d[:n, :-1], d[:n, 1:], use[:n, :-1] & use[:n, 1:]))

def ratio(d):
    (va, vb, vu), (ha, hb, hu) = pairs(d, d.shape[0] // 3)
    v = ((va == vb) & vu).sum() / max(vu.sum(), 1)
    h = ((ha == hb) & hu).sum() / max(hu.sum(), 1)
    return v / h if h > 0 else float('inf')

def false_copies(d, g):
    n = d.shape[0] // 3
    out = []
    for (a, b, u), (ga, gb, gu) in zip(pairs(d, n), pairs(g, n)):
        both = u & gu
        out.append((((a == b) & both & (np.abs(ga - gb) > 0.01 * ga)).sum()) / max(both.sum(), 1))
    return out

def main():
    truth, export = sys.argv[1], sys.argv[2]
    rows = []
    for cam in sorted(os.listdir(os.path.join(truth, 'depth'))):
        for i, path in enumerate(sorted(glob.glob(os.path.join(truth, 'depth', cam, '*.exr')))):
            curated = os.path.join(export, cam, f'{i:03d}_depth.npy')
            if not os.path.exists(curated):
                continue
            d = np.load(curated)
            g = cv2.imread(path, cv2.IMREAD_UNCHANGED)
            g = g[..., 0] if g.ndim == 3 else g
            if g.shape != d.shape:
                g = cv2.resize(g, (d.shape[1], d.shape[0]), interpolation=cv2.INTER_NEAREST)
            g = np.where(np.isfinite(g) & (g < 1e4), g, 1000.0).astype(np.float32)
            v, h = false_copies(d, g)
            rows.append((cam, i, ratio(rounded(g)), ratio(d), v, h))
    print('image | ratio of the truth | ratio of the curated depth | false vertical copies | false horizontal copies')
    for cam, i, rg, rd, v, h in rows:
        print(f'{cam} {i:03d} | {rg:.2f} | {rd:.2f} | {100 * v:.3f}% | {100 * h:.3f}%')
    col = lambda k: np.array([r[k] for r in rows])
    print(f'median | {np.median(col(2)):.2f} | {np.median(col(3)):.2f} | {100 * col(4).mean():.3f}% (mean) | '
          f'{100 * col(5).mean():.3f}% (mean)')
    print(f'worst | {col(2).max():.2f} | {col(3).max():.2f} | {100 * col(4).max():.3f}% | {100 * col(5).max():.3f}%')

main()
