"""Reads the training pairs of dist4d's DiST-S and SCC pipelines with numpy only.

`pipelines/dist_s_pairs.ron` and `pipelines/scc.ron` write `OUT/<scene>/pairs.jsonl`: one JSON
object per pair (see docs/novel-views.md, "The index"). `load_pair` turns one into arrays in the
layout DiST-S takes: the condition image, the condition depth replicated to two channels with the
valid mask as a third, and the target image and depth. PNGs are decoded here with zlib so that the
example needs nothing but numpy; a training loader would use its own image library.

    python3 docs/examples/pair_loader.py OUT        # prints the first pair's arrays
"""
import json
import struct
import sys
import zlib
from pathlib import Path

import numpy as np


def pairs(out_dir):
    """Every pair record of every scene under `out_dir`, in scene and index order."""
    for path in sorted(Path(out_dir).glob("*/pairs.jsonl")):
        with open(path) as f:
            for line in f:
                yield json.loads(line)


def read_png(path):
    """An 8-bit grey or RGB PNG (non-interlaced, as dist4d writes them) as a uint8 array."""
    data = Path(path).read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n", f"{path} is not a PNG"
    pos, idat, header = 8, b"", None
    while pos < len(data):
        (n,) = struct.unpack(">I", data[pos : pos + 4])
        kind, body = data[pos + 4 : pos + 8], data[pos + 8 : pos + 8 + n]
        if kind == b"IHDR":
            header = struct.unpack(">IIBBBBB", body)
        elif kind == b"IDAT":
            idat += body
        pos += 12 + n
    width, height, depth, colour, _, _, interlace = header
    assert depth == 8 and colour in (0, 2) and interlace == 0, f"{path}: unsupported PNG"
    bpp = 3 if colour == 2 else 1
    raw = np.frombuffer(zlib.decompress(idat), dtype=np.uint8).reshape(height, 1 + width * bpp)
    out = np.zeros((height, width * bpp), dtype=np.int32)
    for y in range(height):
        f, line = raw[y, 0], raw[y, 1:].astype(np.int32)
        prev = out[y - 1] if y > 0 else np.zeros(width * bpp, dtype=np.int32)
        if f == 0:
            out[y] = line
        elif f == 2:
            out[y] = (line + prev) & 255
        else:  # Sub (1), Average (3), Paeth (4) depend on the pixel to the left: one pass per pixel
            row = np.zeros(width * bpp + bpp, dtype=np.int32)
            up = np.concatenate([np.zeros(bpp, dtype=np.int32), prev])
            for i in range(width * bpp):
                a, b, c = row[i], up[i + bpp], up[i]
                if f == 1:
                    pred = a
                elif f == 3:
                    pred = (a + b) // 2
                else:
                    p = a + b - c
                    pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
                    pred = a if pa <= pb and pa <= pc else (b if pb <= pc else c)
                row[i + bpp] = (line[i] + pred) & 255
            out[y] = row[bpp:]
    return out.astype(np.uint8).reshape(height, width, bpp).squeeze()


def load_pair(out_dir, pair):
    """One pair as arrays (H x W at the model size)."""
    out_dir = Path(out_dir)
    files = {k: out_dir / v for k, v in pair["files"].items()}
    cond_depth = np.load(files["cond_depth"])
    mask = read_png(files["mask"]) > 0
    return {
        "cond_image": read_png(files["cond_image"]),
        # DiST-S's depth condition: the depth twice and the valid mask, channels last.
        "cond_depth": np.stack([cond_depth, cond_depth, mask.astype(np.float32)], axis=-1),
        "target_image": read_png(files["target_image"]),
        "target_depth": np.load(files["target_depth"]),
        "target_intrinsics": np.array(pair["target"]["intrinsics"]),
        "offset": pair["offset"],
        "shift": pair["shift"],
        "kind": pair["kind"],
    }


if __name__ == "__main__":
    first = next(pairs(sys.argv[1]))
    arrays = load_pair(sys.argv[1], first)
    for k, v in arrays.items():
        print(k, v.shape if hasattr(v, "shape") else v, getattr(v, "dtype", ""))
