"""A reference novel-view generator worker (numpy only), op `generate_view`: the reprojected
condition's holes filled with the nearest valid pixel along the row, then the column (colour and
depth alike). A stand-in for DiST-S (which takes the same condition), used by the tests and as a
template: see docs/workers.md.

    python3 workers/fill_generator.py
"""
import json
import os
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from fill_completer import send  # noqa: E402


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


def fill(image, depth, valid):
    """Rows first, then columns for the rows that had nothing."""
    for transpose in (False, True):
        if transpose:
            image, depth, valid = image.transpose(1, 0, 2), depth.T, valid.T
        src = nearest_index(valid)
        rows, cols = np.nonzero(src >= 0)
        image = image.copy()
        depth = depth.copy()
        image[rows, cols] = image[rows, src[rows, cols]]
        depth[rows, cols] = depth[rows, src[rows, cols]]
        valid = valid | (src >= 0)
        if transpose:
            image, depth, valid = image.transpose(1, 0, 2), depth.T, valid.T
    return image, depth


def main():
    send({"type": "hello", "protocol": 1, "name": "fill-generator", "version": "1",
          "weights_digest": "none", "ops": ["generate_view"], "max_batch": 1})
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
            image, depth, mask = np.load(files["image"]), np.load(files["depth"]), np.load(files["mask"])
            image, depth = fill(image, depth.astype(np.float32), (mask > 0) & (depth > 0))
            out = Path(msg["out_dir"])
            np.save(out / "out_image.npy", np.ascontiguousarray(image, dtype=np.uint8))
            np.save(out / "out_depth.npy", np.ascontiguousarray(depth, dtype=np.float32))
            send({"type": "reply", "id": msg["id"], "status": "ok", "outputs": [
                {"name": "image", "path": str(out / "out_image.npy")},
                {"name": "depth", "path": str(out / "out_depth.npy")}]})
        except Exception as e:
            print(f"request {msg.get('id')}: {e!r}", file=sys.stderr, flush=True)
            send({"type": "reply", "id": msg["id"], "status": "error", "message": repr(e)})


if __name__ == "__main__":
    main()
