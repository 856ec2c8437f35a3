"""A reference depth-completion worker (numpy only): the prompt's holes filled with the nearest
sample along the row, then along the column for rows without any. A stand-in for a learned
completer (DepthLab takes the same inputs), used by the tests and as a template: see
docs/workers.md for the protocol.

    python3 workers/fill_completer.py [--version V]

The version it reports can also come from $FILL_COMPLETER_VERSION (the tests change it that way,
as a new model release would, without touching the pipeline).
"""
import json
import os
import sys
from pathlib import Path

import numpy as np


def send(msg):
    sys.stdout.write(json.dumps(msg) + "\n")
    sys.stdout.flush()


def nearest_along_rows(depth):
    """Each empty pixel takes the nearest sample of its row (rows without one stay empty)."""
    h, w = depth.shape
    idx = np.arange(w)[None, :].repeat(h, 0)
    valid = depth > 0
    left = np.where(valid, idx, -1)
    np.maximum.accumulate(left, axis=1, out=left)
    right = np.where(valid, idx, w)
    right = np.minimum.accumulate(right[:, ::-1], axis=1)[:, ::-1]
    use_left = (left >= 0) & ((right >= w) | (idx - left <= right - idx))
    src = np.where(use_left, left, right)
    has = (src >= 0) & (src < w)
    out = np.zeros_like(depth)
    rows = np.nonzero(has)
    out[rows] = depth[rows[0], src[rows]]
    return out


def complete(prompt):
    filled = nearest_along_rows(prompt)
    # Rows with no sample at all: from the nearest filled row.
    return nearest_along_rows(filled.T).T


def main():
    args = sys.argv[1:]
    version = args[args.index("--version") + 1] if "--version" in args else os.environ.get("FILL_COMPLETER_VERSION", "1")
    send({"type": "hello", "protocol": 1, "name": "fill-completer", "version": version,
          "weights_digest": "none", "ops": ["complete_depth"], "max_batch": 1})
    for line in sys.stdin:
        msg = json.loads(line)
        if msg.get("type") == "shutdown":
            return
        if msg.get("type") == "ping":
            send({"type": "pong", "id": msg["id"]})
            continue
        if msg.get("type") != "request":
            continue
        try:
            files = {f["name"]: f["path"] for f in msg["inputs"]}
            prompt = np.load(files["prompt"]).astype(np.float32)
            depth = complete(prompt)
            out = Path(msg["out_dir"]) / "depth.npy"
            np.save(out, depth.astype(np.float32))
            send({"type": "reply", "id": msg["id"], "status": "ok", "outputs": [{"name": "depth", "path": str(out)}]})
        except Exception as e:  # the item fails, the worker goes on
            print(f"request {msg.get('id')}: {e!r}", file=sys.stderr, flush=True)
            send({"type": "reply", "id": msg["id"], "status": "error", "message": repr(e)})


if __name__ == "__main__":
    main()
