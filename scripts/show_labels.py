#!/usr/bin/env python3
"""Draw a hand-labelled region file over its camera image, to check the labels by eye.

    python scripts/show_labels.py LABEL.json DATASET_ROOT OUT.png [--crop X0 Y0 X1 Y1] [--scale S]

LABEL.json is one file of tests/fixtures/real_labels/ (see tests/fixtures/real_labels/README.md):

    {"image": "<path relative to DATASET_ROOT>", "width": W, "height": H,
     "regions": [{"class": "ego" | "sky" | "bright_structure", "what": "...",
                  "polygon": [[x, y], ...]}, ...], "notes": "..."}

Polygons are in pixel coordinates of the full-resolution image (x right, y down), closed
implicitly. The output shows every region filled semi-transparently (ego red, sky blue,
bright structure yellow) with a 1-px outline of the same colour and the region's index at its
first vertex. --crop draws only a window of the image (full-resolution coordinates) and --scale
resizes the result (nearest neighbour when enlarging, so single pixels stay visible).

The script also checks the file: it reports an image size that differs from width/height, an
unknown class, a polygon with fewer than 3 vertices, a vertex outside the image and a
self-intersecting polygon, and exits with status 1 when it found any of these.
Needs numpy and opencv-python (cv2).
"""
import argparse
import json
import os
import sys

import cv2
import numpy as np

COLOURS = {  # BGR
    "ego": (0, 0, 255),
    "sky": (255, 128, 0),
    "bright_structure": (0, 255, 255),
}
ALPHA = 0.35


def _segments_cross(p1, p2, q1, q2):
    """True when closed segments p1p2 and q1q2 intersect (touching counts)."""

    def orient(a, b, c):
        v = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
        return (v > 0) - (v < 0)

    def on_seg(a, b, c):
        return min(a[0], b[0]) <= c[0] <= max(a[0], b[0]) and min(a[1], b[1]) <= c[1] <= max(a[1], b[1])

    o1, o2, o3, o4 = orient(p1, p2, q1), orient(p1, p2, q2), orient(q1, q2, p1), orient(q1, q2, p2)
    if o1 != o2 and o3 != o4:
        return True
    return (
        (o1 == 0 and on_seg(p1, p2, q1))
        or (o2 == 0 and on_seg(p1, p2, q2))
        or (o3 == 0 and on_seg(q1, q2, p1))
        or (o4 == 0 and on_seg(q1, q2, p2))
    )


def self_intersections(poly):
    """Pairs (i, j) of non-adjacent edges of the closed polygon that touch or cross."""
    n = len(poly)
    bad = []
    for i in range(n):
        a, b = poly[i], poly[(i + 1) % n]
        for j in range(i + 2, n):
            if i == 0 and j == n - 1:
                continue  # adjacent through the closing edge
            c, d = poly[j], poly[(j + 1) % n]
            if _segments_cross(a, b, c, d):
                bad.append((i, j))
    return bad


def check(label, img):
    """List of problems found in the label file (empty when it is fine)."""
    problems = []
    h, w = img.shape[:2]
    if (label.get("width"), label.get("height")) != (w, h):
        problems.append(f"width/height {label.get('width')}x{label.get('height')} but image is {w}x{h}")
    for k, reg in enumerate(label.get("regions", [])):
        poly = reg.get("polygon", [])
        name = f"region {k} ({reg.get('class')}, {reg.get('what', '')!r})"
        if reg.get("class") not in COLOURS:
            problems.append(f"{name}: unknown class")
        if len(poly) < 3:
            problems.append(f"{name}: fewer than 3 vertices")
            continue
        if any(not (0 <= x <= w - 1 and 0 <= y <= h - 1) for x, y in poly):
            problems.append(f"{name}: vertex outside the image")
        crossings = self_intersections(poly)
        if crossings:
            problems.append(f"{name}: self-intersecting (edges {crossings[:5]})")
    return problems


def draw(label, img):
    """The image with every region filled semi-transparently and outlined."""
    fill = img.copy()
    for reg in label.get("regions", []):
        pts = np.array(reg["polygon"], np.int32).reshape(-1, 1, 2)
        cv2.fillPoly(fill, [pts], COLOURS.get(reg.get("class"), (255, 0, 255)))
    out = cv2.addWeighted(fill, ALPHA, img, 1 - ALPHA, 0)
    for k, reg in enumerate(label.get("regions", [])):
        colour = COLOURS.get(reg.get("class"), (255, 0, 255))
        pts = np.array(reg["polygon"], np.int32).reshape(-1, 1, 2)
        cv2.polylines(out, [pts], True, colour, 1, cv2.LINE_8)
        x, y = reg["polygon"][0]
        cv2.putText(out, str(k), (int(x) + 3, int(y) + 14), cv2.FONT_HERSHEY_SIMPLEX, 0.5, colour, 1)
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("label", help="label JSON file")
    ap.add_argument("root", help="dataset folder the label's 'image' path is relative to")
    ap.add_argument("out", help="output PNG")
    ap.add_argument("--crop", type=int, nargs=4, metavar=("X0", "Y0", "X1", "Y1"))
    ap.add_argument("--scale", type=float, default=1.0)
    args = ap.parse_args()

    with open(args.label) as f:
        label = json.load(f)
    path = os.path.join(args.root, label["image"])
    img = cv2.imread(path, cv2.IMREAD_COLOR)
    if img is None:
        sys.exit(f"cannot read image {path}")

    problems = check(label, img)
    for p in problems:
        print(f"{args.label}: {p}", file=sys.stderr)

    out = draw(label, img)
    if args.crop:
        x0, y0, x1, y1 = args.crop
        out = out[y0:y1, x0:x1]
    if args.scale != 1.0:
        interp = cv2.INTER_NEAREST if args.scale > 1 else cv2.INTER_AREA
        out = cv2.resize(out, None, fx=args.scale, fy=args.scale, interpolation=interp)
    if not cv2.imwrite(args.out, out):
        sys.exit(f"cannot write {args.out}")
    sys.exit(1 if problems else 0)


if __name__ == "__main__":
    main()
