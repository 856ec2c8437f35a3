"""A reference future-frame generator worker (numpy only), op `generate_future`: the persistence
baseline of video prediction, each camera's future is its reference image and depth as they were
(nothing moves). A stand-in for DiST-T (which takes the same reference RGB-D and controls), used by
the tests and as a template: see docs/workers.md.

    python3 workers/future_copy.py [--require-layout]

Inputs: `image_<i>` (uint8 H x W x 3) and `depth_<i>` (float32 H x W) per reference camera, and
`controls` (JSON): `step`, `offset`, `reference` (per camera i: its record, with `camera`,
`intrinsics`, `camera_to_ego`, `ego_to_world`, `timestamp_us`, `size` and `boxes`) and `target`
(the same for the camera to generate, at the step's time and pose). Outputs `image` and `depth` at
the target's size. With `--require-layout` it fails an item whose request has no `layout` (NPY uint8
S x S x 3: the bird's-eye view of road and boxes at the step), so tests see that it arrives.
"""
import json
import os
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from protocol import serve  # noqa: E402


def handle(op, files, params, out_dir, item):
    if "--require-layout" in sys.argv:
        if "layout" not in files:
            raise ValueError("the request has no layout")
        layout = np.load(files["layout"])
        if layout.dtype != np.uint8 or layout.ndim != 3 or layout.shape[2] != 3 or not (layout == 80).any():
            raise ValueError(f"the layout is not an RGB8 image with road: {layout.dtype} {layout.shape}")
    controls = json.loads(Path(files["controls"]).read_text())
    target = controls["target"]
    # The controls say where the camera will be, never which image is there.
    leaked = [k for k in ("token", "image") if k in target]
    if leaked:
        raise ValueError(f"the controls name the future image itself ({leaked})")
    cameras = [r["camera"] for r in controls["reference"]]
    if target["camera"] not in cameras:
        raise ValueError(f"the reference frame has no {target['camera']} image to persist")
    i = cameras.index(target["camera"])
    image, depth = np.load(files[f"image_{i}"]), np.load(files[f"depth_{i}"]).astype(np.float32)
    h, w = target["size"]
    if image.shape[:2] != (h, w):
        raise ValueError(f"the reference {target['camera']} is {image.shape[:2]}, the target {(h, w)}")
    out = Path(out_dir)
    np.save(out / "future_image.npy", image.astype(np.uint8))
    np.save(out / "future_depth.npy", depth)
    return {"image": out / "future_image.npy", "depth": out / "future_depth.npy"}


if __name__ == "__main__":
    serve({"name": "future-copy", "version": "1", "weights_digest": "none", "ops": ["generate_future"],
           "max_batch": 6}, handle)
