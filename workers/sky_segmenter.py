"""A reference semantic-segmentation worker (numpy only), op `segment`: Cityscapes ids per pixel,
with sky (23) where a pixel is bright and bluish and connected to the top of the image through
such pixels, and road (7) elsewhere. A stand-in for a real segmenter (which writes the same ids),
used by the tests and as a template: see docs/workers.md.

    python3 workers/sky_segmenter.py
"""
import os
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from protocol import serve  # noqa: E402

SKY, ROAD = 23, 7


def segment(image):
    rgb = image.astype(np.int32)
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    candidate = (b >= r) & (b >= g - 10) & (rgb.mean(axis=-1) > 120)
    # Connected to the top: a column's sky is its run of candidates from row 0 down.
    sky = np.cumprod(candidate, axis=0).astype(bool)
    return np.where(sky, SKY, ROAD).astype(np.uint8)


def handle(op, files, params, out_dir, item):
    out = Path(out_dir) / "semantic.npy"
    np.save(out, segment(np.load(files["image"])))
    return {"semantic": out}


if __name__ == "__main__":
    serve({"name": "sky-segmenter", "version": "1", "weights_digest": "none", "ops": ["segment"]}, handle)
