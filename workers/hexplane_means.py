"""A reference HexPlane encoder worker (numpy only), op `encode_hexplane`: the non-learned baseline
of dist4d's HexPlaneBaseline (each plane the mean of the window's one-hot volume over the two
other axes), rolled out as DynamicCity's released `hexplane_to_rollout` lays the planes out. A
stand-in for DynamicCity's VAE (which takes the same window and returns its own planes), used by
the tests, and a cross-check of the layout: see docs/workers.md.

    python3 workers/hexplane_means.py

Input `semantics` (uint8, T x X x Y x Z, classes; the request's params name them). Outputs
`rollout` (float32, C x (X+T+Z) x (Y+Z+T)) and `hexplane` (JSON: `hex_txyz`).
"""
import json
import os
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from protocol import serve  # noqa: E402


def rollout(xy, xz, yz, tx, ty, tz):
    """hexplane_to_rollout for one sample: planes (C, a, b) -> (C, X+T+Z, Y+Z+T)."""
    c, t, z = xy.shape[0], tx.shape[1], xz.shape[2]
    top = np.concatenate([xy, xz, tx.transpose(0, 2, 1)], axis=2)
    middle = np.concatenate([ty, tz, np.zeros((c, t, t), np.float32)], axis=2)
    bottom = np.concatenate([yz.transpose(0, 2, 1), np.zeros((c, z, z), np.float32), np.zeros((c, z, t), np.float32)], axis=2)
    return np.concatenate([top, middle, bottom], axis=1)


def handle(op, files, params, out_dir, item):
    volume = np.load(files["semantics"])
    c = len(params["classes"])
    onehot = (volume[None] == np.arange(c, dtype=volume.dtype)[:, None, None, None, None]).astype(np.float32)  # C T X Y Z
    xy, xz, yz = onehot.mean(axis=(1, 4)), onehot.mean(axis=(1, 3)), onehot.mean(axis=(1, 2))
    tx, ty, tz = onehot.mean(axis=(3, 4)), onehot.mean(axis=(2, 4)), onehot.mean(axis=(2, 3))
    out = Path(out_dir)
    np.save(out / "rollout.npy", rollout(xy, xz, yz, tx, ty, tz).astype(np.float32))
    t, x, y, z = volume.shape
    (out / "hexplane.json").write_text(json.dumps({"hex_txyz": [t, x, y, z]}))
    return {"rollout": out / "rollout.npy", "hexplane": out / "hexplane.json"}


if __name__ == "__main__":
    serve({"name": "hexplane-means", "version": "1", "weights_digest": "none", "ops": ["encode_hexplane"]}, handle)
