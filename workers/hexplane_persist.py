"""A reference HexPlane generator worker (numpy only), op `generate_hexplane`: the persistence
baseline, the next window's HexPlane is the previous window's rollout as it was. A stand-in for
DynamicCity's DiT (which takes the same conditions, layout and previous rollout), used by the
tests and as a template: see docs/workers.md.

    python3 workers/hexplane_persist.py

Inputs `conditions` (JSON: `trajectory` T x 3, `command`), `layout` (npz, key `layout`, T x X/f x
Y/f uint8) and `previous` (npz, keys `rollout` C x H x W float32 and `mask`, `hex_txyz`).
Outputs `rollout` (NPY float32) and `hexplane` (JSON `hex_txyz`).
"""
import json
import os
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from protocol import serve  # noqa: E402


def handle(op, files, params, out_dir, item):
    conditions = json.loads(Path(files["conditions"]).read_text())
    layout = np.load(files["layout"])["layout"]
    if layout.shape[0] != len(conditions["trajectory"]):
        raise ValueError(f"the layout has {layout.shape[0]} frames, the trajectory {len(conditions['trajectory'])}")
    previous = np.load(files["previous"])
    rollout, txyz = previous["rollout"], [int(v) for v in previous["hex_txyz"]]
    out = Path(out_dir)
    np.save(out / "rollout.npy", rollout.astype(np.float32))
    (out / "hexplane.json").write_text(json.dumps({"hex_txyz": txyz}))
    return {"rollout": out / "rollout.npy", "hexplane": out / "hexplane.json"}


if __name__ == "__main__":
    serve({"name": "hexplane-persist", "version": "1", "weights_digest": "none", "ops": ["generate_hexplane"]}, handle)
