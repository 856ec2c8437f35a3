"""An ORACLE segmenter for `dist4d synth` data (numpy and the standard library only), op
`segment`: it does not look at the image; it returns the exact Cityscapes ids the synthetic
dataset wrote for it (`groundtruth/semantic/<CHANNEL>/<image name>.png`). It is a baseline that
tests the plumbing of a segmenter (LabelPoints, EstimateSky), not a model: on real data it has
nothing to read and fails the item, saying so. See docs/workers.md.

    python3 workers/synth_semantic_oracle.py --root DATA

A request names its image file in `params.file` (relative to the dataset root, as the dataset's
`image_info` has it: `samples/CAM_FRONT/<name>.jpg`); without it the item fails.
"""
import argparse
import os
import struct
import sys
import zlib
from pathlib import Path

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from protocol import serve  # noqa: E402


def read_png_gray8(path):
    """An 8-bit greyscale, non-interlaced PNG (what `dist4d synth` writes) as an H x W uint8 array."""
    data = Path(path).read_bytes()
    if data[:8] != b"\x89PNG\r\n\x1a\n":
        raise ValueError(f"{path} is not a PNG")
    pos, idat, width = 8, [], None
    while pos < len(data):
        (length,) = struct.unpack(">I", data[pos:pos + 4])
        kind, body = data[pos + 4:pos + 8], data[pos + 8:pos + 8 + length]
        if kind == b"IHDR":
            width, height, depth, colour, _, _, interlace = struct.unpack(">IIBBBBB", body)
            if (depth, colour, interlace) != (8, 0, 0):
                raise ValueError(f"{path}: depth {depth}, colour type {colour}, interlace {interlace}: not 8-bit grey")
        elif kind == b"IDAT":
            idat.append(body)
        pos += 12 + length
    raw = np.frombuffer(zlib.decompress(b"".join(idat)), np.uint8).reshape(height, width + 1)
    out = np.zeros((height, width), np.uint8)
    prev = np.zeros(width, np.int32)
    for y in range(height):
        f, row = raw[y, 0], raw[y, 1:].astype(np.int32)
        if f == 0:
            cur = row
        elif f == 1:  # Sub: a running sum along the row
            cur = np.cumsum(row) & 255
        elif f == 2:  # Up
            cur = (row + prev) & 255
        else:  # Average, Paeth: sequential along the row
            cur = np.zeros(width, np.int32)
            for x in range(width):
                a = cur[x - 1] if x else 0
                b, c = prev[x], (prev[x - 1] if x else 0)
                if f == 3:
                    pred = (a + b) // 2
                else:
                    p = a + b - c
                    pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
                    pred = a if pa <= pb and pa <= pc else (b if pb <= pc else c)
                cur[x] = (row[x] + pred) & 255
        out[y] = cur
        prev = cur
    return out


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--root", required=True, help="the synthetic dataset's folder")
    root = Path(parser.parse_args().root)

    def handle(op, files, params, out_dir, item):
        rel = params.get("file")
        if not rel:
            raise ValueError(f"{item}: the request names no `file` (the oracle reads the dataset's own labels)")
        image = Path(rel)
        png = root / "groundtruth" / "semantic" / image.parent.name / (image.stem + ".png")
        if not png.is_file():
            raise FileNotFoundError(f"{item}: no exact semantics at {png}: the oracle serves `dist4d synth` data only")
        ids = read_png_gray8(png)
        h, w = np.load(files["image"], mmap_mode="r").shape[:2]
        if ids.shape != (h, w):
            raise ValueError(f"{item}: {png} is {ids.shape[1]}x{ids.shape[0]}, the image {w}x{h}")
        out = Path(out_dir) / "semantic.npy"
        np.save(out, ids)
        return {"semantic": out}

    serve({"name": "synth-semantic-oracle", "version": "1", "weights_digest": "none", "ops": ["segment"]}, handle)


if __name__ == "__main__":
    main()
