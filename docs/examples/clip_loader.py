"""Reads the training clips of dist4d's 12 Hz pipeline with numpy only.

`pipelines/video_12hz.ron` writes `OUT/<scene>/clips.jsonl`: one JSON object per clip (see
docs/datasets.md, "Training clips"). `load_clip` turns one into arrays; images stay paths (decode
them with the image library your training code already uses). A camera record with `image_row`
names a py123d log's camera file, which holds the encoded images as rows: `image_bytes` reads
one (with pyarrow, which py123d users have; everything else here needs numpy alone).

    python3 docs/examples/clip_loader.py OUT DATA_ROOT     # prints the first clip's arrays
"""
import json
import sys
from pathlib import Path

import numpy as np


def clips(out_dir):
    """Every clip record of every scene under `out_dir`, in scene and clip order."""
    for path in sorted(Path(out_dir).glob("*/clips.jsonl")):
        with open(path) as f:
            for line in f:
                yield json.loads(line)


def rigid(t):
    """4x4 matrix of {"translation": [x, y, z], "rotation": [w, x, y, z]}."""
    w, x, y, z = t["rotation"]
    m = np.eye(4)
    m[:3, :3] = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    m[:3, 3] = t["translation"]
    return m


def image_bytes(data_root, camera):
    """The encoded image (JPEG or PNG bytes) of one camera record of a clip."""
    path = Path(data_root) / camera["image"]
    row = camera.get("image_row")
    if row is None:
        return path.read_bytes()
    import pyarrow as pa  # only for images inside py123d's Arrow files

    reader = pa.ipc.open_file(pa.memory_map(str(path)))
    column = next(n for n in reader.schema.names if n.endswith(".data"))
    for b in range(reader.num_record_batches):
        batch = reader.get_batch(b)
        if row < batch.num_rows:
            return batch.column(column)[row].as_py()
        row -= batch.num_rows
    raise IndexError(f"{path} has no row {camera['image_row']}")


def load_clip(out_dir, data_root, clip):
    """One clip as arrays: F frames x C cameras (the cameras in the record's order)."""
    out_dir, data_root = Path(out_dir), Path(data_root)
    frames = clip["frames"]
    per = lambda key: [[cam[key] for cam in f["cameras"]] for f in frames]
    load = lambda rel: np.load(out_dir / rel)
    return {
        "cameras": [cam["camera"] for cam in frames[0]["cameras"]],
        # Paths to open; for a camera record with `image_row` the file is a py123d camera file
        # (read the image with `image_bytes`).
        "images": [[str(data_root / p) for p in row] for row in per("image")],
        "image_rows": per("image_row") if "image_row" in frames[0]["cameras"][0] else [],
        "tokens": per("token"),
        "timestamps_us": np.array(per("timestamp_us"), dtype=np.int64),
        "intrinsics": np.array(per("intrinsics"), dtype=np.float64),
        "camera_to_ego": np.array([[rigid(c) for c in row] for row in per("camera_to_ego")]),
        "ego_to_world": np.array([[rigid(c) for c in row] for row in per("ego_to_world")]),
        "depth": np.stack([np.stack([load(p) for p in row]) for row in per("depth")]),
        "confidence": np.stack([np.stack([load(p) for p in row]) for row in per("confidence")]),
        "boxes": per("boxes"),
        "ego_trajectory": np.array([rigid(t["ego_to_world"]) for t in clip["ego_trajectory"]]),
    }


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit(__doc__)
    first = next(clips(sys.argv[1]), None)
    if first is None:
        sys.exit(f"no clips under {sys.argv[1]}")
    arrays = load_clip(sys.argv[1], sys.argv[2], first)
    for key, value in arrays.items():
        shape = getattr(value, "shape", None)
        print(key, list(shape) if shape is not None else f"{len(value)} x {len(value[0]) if value else 0}")
