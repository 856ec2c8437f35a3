"""Draws one camera image of a 12 Hz sample between keyframes with its interpolated boxes (as the
nuscenes-devkit draws them) beside its curated depth, pairing the two by the image's sample_data
token: what `dist4d export-12hz` and `pipelines/video_12hz.ron` give a DiST-T data loader.

    python docs/examples/draw_12hz_sample.py DATA_ROOT OUT_DIR PICTURE.png [--camera CAM_FRONT] [--round 3]

DATA_ROOT holds interp_12Hz_mini/ (`dist4d export-12hz --root DATA_ROOT`); OUT_DIR is the output
folder of `dist4d run pipelines/video_12hz.ron --set dataset.root=DATA_ROOT`, whose index.json
names each exported file's source image. Needs nuscenes-devkit and matplotlib (the peer venv).
"""
import argparse, json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from nuscenes.nuscenes import NuScenes


def depth_by_token(out_dir: Path) -> dict:
    """sample_data token -> curated depth (.npy) path, from the run's index.json."""
    index = json.loads((out_dir / "index.json").read_text())
    by_item = {}
    for f in index["files"]:
        if f["path"].endswith("_depth.npy"):
            by_item[f["item"]] = out_dir / f["path"]
    return {src["token"]: by_item[item] for item, src in index["sources"].items() if item in by_item}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("root")
    ap.add_argument("out_dir")
    ap.add_argument("picture")
    ap.add_argument("--camera", default="CAM_FRONT")
    ap.add_argument("--round", type=int, default=3, help="which sample of the first scene (0 = its first keyframe)")
    a = ap.parse_args()
    nusc = NuScenes(version="interp_12Hz_mini", dataroot=a.root, verbose=False)
    token = nusc.scene[0]["first_sample_token"]
    for _ in range(a.round):
        token = nusc.get("sample", token)["next"]
    sample = nusc.get("sample", token)
    sd_token = sample["data"][a.camera]
    sd = nusc.get("sample_data", sd_token)
    depth = np.load(depth_by_token(Path(a.out_dir))[sd_token])

    fig, (left, right) = plt.subplots(1, 2, figsize=(16, 4.8))
    nusc.render_sample_data(sd_token, ax=left, verbose=False)
    key = "keyframe" if len(token) == 32 else "between keyframes"
    left.set_title(f"{a.camera} of sample ..{token[-7:]} ({key}): its boxes")
    shown = right.imshow(np.where(depth > 0, depth, np.nan), cmap="turbo", vmin=0, vmax=80)
    right.set_title("curated depth (m; sky at 100 m)")
    right.axis("off")
    fig.colorbar(shown, ax=right, fraction=0.025)
    fig.tight_layout()
    fig.savefig(a.picture, dpi=80)
    print(f"{a.picture}: sample {token}, image {sd['filename']}, {len(sample['anns'])} boxes")


if __name__ == "__main__":
    main()
