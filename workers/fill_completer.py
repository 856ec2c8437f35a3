"""A reference depth-completion worker (numpy only), op `complete_depth`: the prompt's holes
filled with the nearest sample along the row, then along the column for rows without any. A
stand-in for a learned completer (DepthLab takes the same inputs), used by the tests and as a
template: see docs/workers.md.

    python3 workers/fill_completer.py [--version V]

The version it reports can also come from $FILL_COMPLETER_VERSION (the tests change it that way,
as a new model release would, without touching the pipeline).
"""
import os
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from protocol import serve  # noqa: E402


def nearest_index(valid):
    """Per pixel, the column of the nearest valid pixel of its row (-1 for a row without any)."""
    h, w = valid.shape
    idx = np.arange(w)[None, :].repeat(h, 0)
    left = np.where(valid, idx, -1)
    np.maximum.accumulate(left, axis=1, out=left)
    right = np.where(valid, idx, w)
    right = np.minimum.accumulate(right[:, ::-1], axis=1)[:, ::-1]
    use_left = (left >= 0) & ((right >= w) | (idx - left <= right - idx))
    src = np.where(use_left, left, right)
    return np.where(src >= w, -1, src)


def fill(maps, valid):
    """Each map (H x W, or H x W x C) with its invalid pixels taken from the nearest valid pixel
    of the row, then of the column for the rows that had none."""
    maps = [m.copy() for m in maps]
    for transpose in (False, True):
        if transpose:
            maps, valid = [np.swapaxes(m, 0, 1) for m in maps], valid.T
        src = nearest_index(valid)
        rows, cols = np.nonzero(src >= 0)
        for m in maps:
            m[rows, cols] = m[rows, src[rows, cols]]
        valid = valid | (src >= 0)
        if transpose:
            maps, valid = [np.ascontiguousarray(np.swapaxes(m, 0, 1)) for m in maps], valid.T
    return maps


def handle(op, files, params, out_dir, item):
    prompt = np.load(files["prompt"]).astype(np.float32)
    (depth,) = fill([prompt], prompt > 0)
    out = Path(out_dir) / "depth.npy"
    np.save(out, depth.astype(np.float32))
    return {"depth": out}


if __name__ == "__main__":
    args = sys.argv[1:]
    version = args[args.index("--version") + 1] if "--version" in args else os.environ.get("FILL_COMPLETER_VERSION", "1")
    serve({"name": "fill-completer", "version": version, "weights_digest": "none", "ops": ["complete_depth"]}, handle)
