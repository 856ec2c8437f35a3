"""Issue 42's occupancy figures from the folders `dist4d run pipelines/occupancy.ron` writes on
`dist4d synth` data (numpy only):

- per class IoU and mIoU as Occ3D's metric (and `dist4d eval`) computes them: the confusion
  matrix of the reference's camera-visible voxels, summed over the frames;
- the empty road: of the exact driveable-surface voxels (the whole grid), the share left free in
  the output, and the share left free where the output's own `mask_lidar` says the voxel was
  observed (what teaches a model "free" on the road).

    python3 bench/occupancy_provenance.py OUT [OTHER_OUT]

With a second folder (e.g. keyframes against sweeps), each class's IoU is also given for the
frames both folders have, and the difference.
"""
import sys
from pathlib import Path

import numpy as np

NAMES = ["others", "barrier", "bicycle", "bus", "car", "construction_vehicle", "motorcycle",
         "pedestrian", "traffic_cone", "trailer", "truck", "driveable_surface", "other_flat",
         "sidewalk", "terrain", "manmade", "vegetation", "free"]
ROAD, FREE = 11, 17


def frames(out):
    out = Path(out)
    for exact in sorted((out / "exact" / "gts").glob("*/*/labels.npz")):
        rel = exact.relative_to(out / "exact" / "gts")
        mine = out / "gts" / rel
        if mine.is_file():
            yield str(rel.parent), np.load(mine), np.load(exact)


def measure(out, only=None):
    m = np.zeros((18, 18), np.int64)
    road = road_free = road_free_seen = 0
    names = []
    for name, mine, ref in frames(out):
        if only is not None and name not in only:
            continue
        names.append(name)
        vis = ref["mask_camera"] != 0
        np.add.at(m, (ref["semantics"][vis].astype(int), mine["semantics"][vis].astype(int)), 1)
        r = ref["semantics"] == ROAD
        free = mine["semantics"] == FREE
        road += int(r.sum())
        road_free += int((r & free).sum())
        road_free_seen += int((r & free & (mine["mask_lidar"] != 0)).sum())
    tp = np.diag(m).astype(float)
    union = m.sum(0) + m.sum(1) - tp
    iou = np.where(union > 0, tp / np.maximum(union, 1), np.nan)
    return names, iou, road, road_free, road_free_seen


def report(out, only=None):
    names, iou, road, free, seen = measure(out, only)
    print(f"{out}: {len(names)} frames")
    for c in range(18):
        if not np.isnan(iou[c]):
            print(f"  {NAMES[c]:20s} {iou[c]:.4f}")
    print(f"  mIoU (0-16)          {np.nanmean(iou[:17]):.4f}")
    print(f"  exact road voxels {road}: free in the output {free / max(road, 1):.2%}, "
          f"free with mask_lidar = 1 {seen / max(road, 1):.2%}")
    return names, iou


if __name__ == "__main__":
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    names, a = report(sys.argv[1])
    if len(sys.argv) > 2:
        _, b = report(sys.argv[2])
        both = set(names) & {n for n, _, _ in frames(sys.argv[2])}
        _, a2, *_ = measure(sys.argv[1], both)
        _, b2, *_ = measure(sys.argv[2], both)
        print(f"on the {len(both)} frames both have: class, first, second, second - first")
        for c in range(17):
            if not (np.isnan(a2[c]) and np.isnan(b2[c])):
                print(f"  {NAMES[c]:20s} {a2[c]:.4f} {b2[c]:.4f} {b2[c] - a2[c]:+.4f}")
