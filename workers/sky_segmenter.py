"""A reference semantic-segmentation worker (numpy only), op `segment`: Cityscapes ids per pixel,
with sky (23) where a pixel is bright and bluish and connected to the top of the image through
such pixels, and road (7) elsewhere. A stand-in for a real segmenter (which writes the same ids),
used by the tests and as a template: see docs/workers.md.

    python3 workers/sky_segmenter.py
"""
import json
import os
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from fill_completer import send  # noqa: E402

SKY, ROAD = 23, 7


def segment(image):
    rgb = image.astype(np.int32)
    r, g, b = rgb[..., 0], rgb[..., 1], rgb[..., 2]
    candidate = (b >= r) & (b >= g - 10) & (rgb.mean(axis=-1) > 120)
    # Connected to the top: a column's sky is its run of candidates from row 0 down.
    sky = np.cumprod(candidate, axis=0).astype(bool)
    return np.where(sky, SKY, ROAD).astype(np.uint8)


def main():
    send({"type": "hello", "protocol": 1, "name": "sky-segmenter", "version": "1",
          "weights_digest": "none", "ops": ["segment"], "max_batch": 1})
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
            ids = segment(np.load(files["image"]))
            out = Path(msg["out_dir"]) / "semantic.npy"
            np.save(out, ids)
            send({"type": "reply", "id": msg["id"], "status": "ok", "outputs": [{"name": "semantic", "path": str(out)}]})
        except Exception as e:
            print(f"request {msg.get('id')}: {e!r}", file=sys.stderr, flush=True)
            send({"type": "reply", "id": msg["id"], "status": "error", "message": repr(e)})


if __name__ == "__main__":
    main()
