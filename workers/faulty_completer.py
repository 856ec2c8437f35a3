"""A depth-completion worker that misbehaves on purpose, for the tests of how dist4d survives
workers (tests/workers.rs). It completes like fill_completer.py, except on the items whose label
(`scene/frame/camera`) contains the text given to:

    --crash-on TEXT       exit mid-request (a segfault, an out-of-memory kill)
    --hang-on TEXT        never reply (a deadlock)
    --malformed-on TEXT   return a depth of the wrong shape
    --crash-once FILE     exit on the first request if FILE does not exist yet (creating it): a
                          crash mid-run that a restarted worker gets past
    --die-at-start        exit before its hello (a missing CUDA library, a bad checkpoint)
    --max-batch N         take batches of up to N requests
    --batch-log FILE      append the size of each batch to FILE
"""
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from fill_completer import fill  # noqa: E402
from protocol import one, serve  # noqa: E402

ARGS = sys.argv[1:]


def arg(name):
    return ARGS[ARGS.index(name) + 1] if name in ARGS else None


def matches(name, item):
    text = arg(name)
    return text is not None and text in item


def handle(op, files, params, out_dir, item):
    once = arg("--crash-once")
    if once is not None and not os.path.exists(once):
        Path(once).touch()
        print(f"crashing once, on {item}", file=sys.stderr, flush=True)
        os._exit(1)
    if matches("--crash-on", item):
        print(f"segmentation fault on {item}", file=sys.stderr, flush=True)
        os._exit(139)
    if matches("--hang-on", item):
        print(f"stuck on {item}", file=sys.stderr, flush=True)
        time.sleep(3600)
    prompt = np.load(files["prompt"]).astype(np.float32)
    (depth,) = fill([prompt], prompt > 0)
    if matches("--malformed-on", item):
        depth = depth.T
    out = Path(out_dir) / "depth.npy"
    np.save(out, np.ascontiguousarray(depth, dtype=np.float32))
    return {"depth": out}


def handle_batch(requests):
    log = arg("--batch-log")
    if log is not None:
        with open(log, "a") as f:
            f.write(f"{len(requests)}\n")
    return [one(handle, r) for r in requests]


if __name__ == "__main__":
    if "--die-at-start" in ARGS:
        print("CUDA error: no CUDA-capable device is detected", file=sys.stderr, flush=True)
        sys.exit(1)
    batch = int(arg("--max-batch") or 1)
    serve({"name": "faulty-completer", "version": "1", "weights_digest": "none", "ops": ["complete_depth"],
           "max_batch": batch}, handle, handle_batch)
