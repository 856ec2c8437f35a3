"""Depth on moving objects at keyframe and non-keyframe images (issue 21): reads the per-image
metrics a run of pipelines/video_12hz.ron exported (`{frame}_metrics.json`, reference `gt_moving`)
and its index.json (whose `sources` say which image each item is), and pools Abs Rel over the
moving-object pixels of the keyframe images (`samples/`) and of the 12 Hz images between them
(`sweeps/`). Pixel-weighted, like `dist4d eval`'s pooled rows. numpy-free; Python 3 only.

    python3 bench/moving_objects.py OUT [OUT_ABLATION]
"""
import json, sys
from pathlib import Path


def pooled(out):
    out = Path(out)
    index = json.loads((out / "index.json").read_text())
    sources = index.get("sources", {})
    sums = {"keyframe": [0.0, 0, 0], "between": [0.0, 0, 0]}  # abs_rel * pixels, pixels, images
    for f in index["files"]:
        if f["port"] != "json" or f["stage"] != "eval":
            continue
        source = sources.get(f["item"])
        if source is None:
            sys.exit(f"{out}/index.json has no source for {f['item']}: run with a dist4d that records sources")
        m = json.loads((out / f["path"]).read_text()).get("against", {}).get("gt_moving", {}).get("raw")
        if not m or not m.get("pixels"):
            continue
        kind = "keyframe" if source["file"].startswith("samples/") else "between"
        s = sums[kind]
        s[0] += m["abs_rel"] * m["pixels"]
        s[1] += m["pixels"]
        s[2] += 1
    return {k: (v[0] / v[1] if v[1] else float("nan"), v[1], v[2]) for k, v in sums.items()}


def main():
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    print("| run | keyframe images: Abs Rel (pixels, images) | 12 Hz images between: Abs Rel (pixels, images) | ratio |")
    print("| --- | ---: | ---: | ---: |")
    for out in sys.argv[1:]:
        p = pooled(out)
        (ka, kp, ki), (ba, bp, bi) = p["keyframe"], p["between"]
        print(f"| {out} | {ka:.4f} ({kp}, {ki}) | {ba:.4f} ({bp}, {bi}) | {ba / ka:.2f} |")


if __name__ == "__main__":
    main()
