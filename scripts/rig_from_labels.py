#!/usr/bin/env python3
"""Writes a built-in ego rig (stages/src/curation/ego_rigs/NAME.json) from hand-label files.

    python scripts/rig_from_labels.py NAME "what it is" OUT.json LABEL.json [LABEL.json ...]

Takes the `ego` regions of the first label file of each camera (the camera is the label file's
folder for DGP-style trees, else its stem), simplified to 1 px (OpenCV approxPolyDP). The shipped
rigs were made this way from tests/fixtures/real_labels/. Needs numpy and OpenCV.
"""
import json
import sys
from pathlib import Path

import cv2
import numpy as np


def main():
    if len(sys.argv) < 5:
        sys.exit(__doc__)
    name, what, out, files = sys.argv[1], sys.argv[2], Path(sys.argv[3]), [Path(f) for f in sys.argv[4:]]
    cameras, size = {}, None
    for f in sorted(files):
        labels = json.loads(f.read_text())
        size = size or (labels["width"], labels["height"])
        if (labels["width"], labels["height"]) != size:
            sys.exit(f"{f}: {labels['width']}x{labels['height']}, the others {size[0]}x{size[1]}")
        camera = f.parent.name if f.stem.isdigit() else f.stem
        if camera in cameras:
            continue
        polygons = []
        for r in labels["regions"]:
            if r["class"] == "ego":
                p = np.array(r["polygon"], np.float32).reshape(-1, 1, 2)
                polygons.append([[int(round(x)), int(round(y))] for x, y in cv2.approxPolyDP(p, 1.0, True).reshape(-1, 2)])
        if polygons:
            cameras[camera] = polygons
    lines = [f"    {json.dumps(c)}: {json.dumps(p, separators=(',', ':'))}" for c, p in cameras.items()]
    out.write_text(
        "{\n"
        f'  "name": {json.dumps(name)},\n  "what": {json.dumps(what)},\n'
        f'  "width": {size[0]},\n  "height": {size[1]},\n'
        '  "cameras": {\n' + ",\n".join(lines) + "\n  }\n}\n"
    )
    print(f"{out}: {', '.join(f'{c} ({len(p)} polygons)' for c, p in cameras.items())}")


if __name__ == "__main__":
    main()
