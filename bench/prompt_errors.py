"""Which wrong prompt samples cost the completion the most (docs/BENCHMARKS.md, "What the
completion can reach").

    .venv-peers/bin/python bench/prompt_errors.py DATA OUT WORK [--harness BIN] [--every N] [--set k=v ...]

DATA is a synthetic scene (`dist4d synth`), OUT the output folder of a curation run that exported
the prompt as `{frame}_prompt.npy` (as for bench/completion_oracle.py) and the aggregated LiDAR's
own projection (`lidar_multi.depth`) as `{frame}_lidar.npy`. WORK is bench/completion_oracle.py's
work folder (made here when absent). A prompt sample is wrong when it is off the ground truth by
more than 10% or lies on sky; each kind of wrong sample is removed in turn (every other kind kept),
CompleteDepth runs on the result (the `complete_npy` example), and the share of pixels off by more
than 10% is printed beside the real prompt's. Kinds: nearer or farther than the truth; LiDAR (the
LiDAR projection has that depth, within 1%, at that pixel) or not (MVS); within 2 px of a true depth
edge (a log-depth step of more than 10% between neighbours) or inside a surface.
"""
import sys
from pathlib import Path

import numpy as np
from scipy import ndimage

sys.path.insert(0, str(Path(__file__).resolve().parent))
from completion_oracle import CAMERAS, arguments, harness_score, prepare  # noqa: E402

KINDS = ["nearer, LiDAR, at an edge", "nearer, LiDAR, inside a surface", "nearer, MVS",
         "farther, LiDAR, at an edge", "farther, LiDAR, inside a surface", "farther, MVS", "on sky"]


def kinds(real, gt, lidar):
    """The wrong samples of one prompt, by kind (boolean maps)."""
    has = real > 0
    sky = ~np.isfinite(gt)
    with np.errstate(invalid="ignore", divide="ignore"):
        wrong = has & (sky | (np.abs(real - gt) / gt > 0.1))
    nearer = real < gt
    from_lidar = (lidar > 0) & (np.abs(lidar - real) <= 0.01 * real)
    log = np.log(np.where(sky, 100.0, np.clip(gt, 0.1, 100.0)))
    step = np.maximum(np.abs(np.diff(log, axis=1, append=log[:, -1:])), np.abs(np.diff(log, axis=0, append=log[-1:])))
    step = np.maximum(step, np.maximum(np.roll(step, 1, 1), np.roll(step, 1, 0)))
    edge = ndimage.distance_transform_cdt(step <= np.log(1.1), metric="chessboard") <= 2
    solid = wrong & ~sky
    return [solid & nearer & from_lidar & edge, solid & nearer & from_lidar & ~edge, solid & nearer & ~from_lidar,
            solid & ~nearer & from_lidar & edge, solid & ~nearer & from_lidar & ~edge, solid & ~nearer & ~from_lidar,
            wrong & sky]


def main():
    ap = arguments(__doc__)
    ap.add_argument("--every", type=int, default=1, help="every Nth image (in camera, then frame order)")
    a = ap.parse_args()
    work = Path(a.work)
    if not (work / "real.txt").exists():
        work.mkdir(parents=True, exist_ok=True)
        prepare(a.data, a.out, a.work)
    scene = next(p for p in Path(a.out).iterdir() if p.is_dir())
    images = [line.split() for line in (work / "real.txt").read_text().splitlines()][:: a.every]
    counts = np.zeros(len(KINDS), int)
    total = 0
    lines = {k: [] for k in range(len(KINDS))}
    for rgb, prompt, sky, _, gt_path in images:
        base = rgb[: -len("_rgb.npy")]
        cam, frame = Path(base).name.rsplit("_", 1)
        assert cam in CAMERAS, cam
        lidar_path = scene / cam / f"{frame}_lidar.npy"
        if not lidar_path.exists():
            sys.exit(f"{lidar_path} is missing: export lidar_multi.depth as {{frame}}_lidar.npy")
        real, gt, lidar = np.load(prompt), np.load(gt_path), np.load(lidar_path)
        total += int((real > 0).sum())
        for k, mask in enumerate(kinds(real, gt, lidar)):
            counts[k] += int(mask.sum())
            without = f"{base}_without_{k}.npy"
            np.save(without, np.where(mask, 0, real).astype(np.float32))
            lines[k].append(f"{rgb} {without} {sky} {base}_out_errors.npy {gt_path}")
    real = harness_score(a.harness, [" ".join([f[0], f[1], f[2], f"{f[0][:-8]}_out_errors.npy", f[4]]) for f in images],
                         work, "errors_real", a.set)
    print(f"{len(images)} images, {total} prompt samples, {counts.sum()} wrong ({100 * counts.sum() / total:.2f}%)\n")
    print("| wrong samples removed | samples | bad > 10% | points |")
    print("| --- | ---: | ---: | ---: |")
    print(f"| none | - | {real:.3f}% | |")
    for k, name in enumerate(KINDS):
        bad = harness_score(a.harness, lines[k], work, f"errors_{k}", a.set)
        print(f"| {name} | {counts[k]} | {bad:.3f}% | {bad - real:+.3f} |")


if __name__ == "__main__":
    main()
