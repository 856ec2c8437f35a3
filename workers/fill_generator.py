"""A reference novel-view generator worker (numpy only), op `generate_view`: the reprojected
condition's holes filled with the nearest valid pixel along the row, then the column (colour and
depth alike). A stand-in for DiST-S (which takes the same condition), used by the tests and as a
template: see docs/workers.md.

    python3 workers/fill_generator.py
"""
import os
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from fill_completer import fill  # noqa: E402
from protocol import serve  # noqa: E402


def handle(op, files, params, out_dir, item):
    image, depth, mask = np.load(files["image"]), np.load(files["depth"]).astype(np.float32), np.load(files["mask"])
    image, depth = fill([image, depth], (mask > 0) & (depth > 0))
    out = Path(out_dir)
    np.save(out / "out_image.npy", image.astype(np.uint8))
    np.save(out / "out_depth.npy", depth.astype(np.float32))
    return {"image": out / "out_image.npy", "depth": out / "out_depth.npy"}


if __name__ == "__main__":
    serve({"name": "fill-generator", "version": "1", "weights_digest": "none", "ops": ["generate_view"]}, handle)
