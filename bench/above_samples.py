"""Where the completion's bad pixels are relative to the prompt's highest sample in each column,
and what multi-view stereo could still bring there (docs/BENCHMARKS.md, "What the
completion can reach").

    .venv-peers/bin/python bench/above_samples.py DATA OUT WORK [--harness BIN] [--every N] [--set k=v ...]

DATA is a synthetic scene (`dist4d synth`), OUT the output folder of a curation run that exported
the prompt as `{frame}_prompt.npy` (as for bench/completion_oracle.py) and MultiViewStereo's depth
and confidence as `{frame}_mvs.npy` and `{frame}_mvs_confidence.npy` (EncodeDepth of `mvs.depth`
and of `mvs.confidence`, `npy`). WORK is bench/completion_oracle.py's work folder, after that
script has run (it holds the real and clean prompts and their completions).

Part 1 splits the pixels off by more than 10% (ground truth in 0.1-80 m) of the completions of
the real and the clean prompt (the real one without its samples off by more than 10%) into those
above the highest prompt sample of their column and the rest, and those above by ground-truth
class and by sign (completed nearer or farther than the truth). Shares are in points: 100 x bad
pixels / scored pixels of all the images.

Part 2 adds MultiViewStereo's pixels lying above the highest prompt sample of their column (not
sky in the ground truth, at the full-resolution pixel under the MVS pixel's centre) to the real
prompt and completes it (the `complete_npy` example): every pixel of confidence >= 0.4 (the
shipped StaticMvsPoints threshold), only those within 10% of the truth (a perfect selection), the
ground truth at the confident ones' pixels (their coverage with exact values), and the ground truth
at every MVS pixel with a depth.

Part 3 takes the prompt's own MVS samples (those where the aggregated LiDAR's projection, OUT's
`{frame}_lidar.npy` as for bench/prompt_errors.py, has no depth within 1%) and gives the ground
truth to the right ones only (within 10%: their precision) and then to all of them (the wrong
ones too: what a perfect MVS at the pipeline's sample positions would give).
"""
import sys
from collections import Counter
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from completion_oracle import arguments, harness_score  # noqa: E402

# Cityscapes ids (the synthetic world's semantic PNGs) -> names.
CLASSES = {7: "road", 8: "sidewalk", 11: "building", 12: "wall", 13: "fence", 17: "pole", 19: "traffic light",
           20: "traffic sign", 21: "vegetation", 22: "terrain", 24: "person", 25: "rider", 26: "car",
           27: "truck", 28: "bus", 32: "motorcycle", 33: "bicycle"}


def bad_pixels(depth, gt):
    """Pixels scored (ground truth in 0.1-80 m) and those off by more than 10%, as EvalDepth and
    the harness count them."""
    scored = np.isfinite(gt) & (gt > 0.1) & (gt < 80)
    rel = np.abs(np.clip(depth, 0.1, 80) - gt) / np.where(scored, gt, 1)
    return scored, scored & (rel > 0.1)


def above_highest(prompt):
    """Pixels above the highest sample of their column (every pixel of a column without one)."""
    has = prompt > 0
    h = prompt.shape[0]
    top = np.where(has.any(axis=0), has.argmax(axis=0), h)
    return np.arange(h)[:, None] < top[None, :]


def semantic(data, cam, frame):
    images = sorted((Path(data) / "samples" / cam).glob("*.jpg"))
    path = Path(data) / "groundtruth" / "semantic" / cam / f"{images[int(frame)].stem}.png"
    import cv2
    labels = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if labels is None:
        sys.exit(f"{path} is missing or unreadable")
    return labels


def main():
    ap = arguments(__doc__)
    ap.add_argument("--every", type=int, default=1, help="every Nth image (in camera, then frame order)")
    a = ap.parse_args()
    work = Path(a.work)
    if not (work / "real.txt").exists():
        sys.exit(f"{work / 'real.txt'} is missing: run bench/completion_oracle.py DATA OUT {work} first")
    scene = next(p for p in Path(a.out).iterdir() if p.is_dir())
    images = [line.split() for line in (work / "real.txt").read_text().splitlines()][:: a.every]

    scored_total = 0
    split = Counter()
    by_class = Counter()
    variants = {"confident": [], "right": [], "confident, exact": [], "exact": []}
    own = {"right MVS samples exact": [], "every MVS sample exact": []}
    mvs_samples = Counter()
    added = Counter()
    for rgb, prompt_path, sky, _, gt_path in images:
        base = rgb[: -len("_rgb.npy")]
        cam, frame = Path(base).name.rsplit("_", 1)
        gt = np.load(gt_path)
        labels = semantic(a.data, cam, frame)
        for variant in ["real", "clean"]:
            prompt = np.load(f"{base}_{variant}.npy")
            completed = np.load(f"{base}_out_{variant}.npy")
            scored, bad = bad_pixels(completed, gt)
            if variant == "real":
                scored_total += int(scored.sum())
            above = above_highest(prompt)
            split[(variant, "above")] += int((bad & above).sum())
            split[(variant, "below")] += int((bad & ~above).sum())
            split[(variant, "scored above")] += int((scored & above).sum())
            if variant == "clean":
                nearer = completed < gt
                for c in np.unique(labels[bad & above]):
                    m = bad & above & (labels == c)
                    by_class[(CLASSES.get(int(c), str(c)), "nearer")] += int((m & nearer).sum())
                    by_class[(CLASSES.get(int(c), str(c)), "farther")] += int((m & ~nearer).sum())

        mvs_path = scene / cam / f"{frame}_mvs.npy"
        conf_path = scene / cam / f"{frame}_mvs_confidence.npy"
        if not mvs_path.exists() or not conf_path.exists():
            sys.exit(f"{mvs_path} or {conf_path} is missing: export mvs.depth and mvs.confidence as NPY")
        real = np.load(prompt_path)
        mvs, conf = np.load(mvs_path), np.load(conf_path)
        (hh, ww), (h, w) = real.shape, mvs.shape
        ys, xs = np.nonzero(mvs > 0)
        y = ((ys + 0.5) * hh / h).astype(int)
        x = ((xs + 0.5) * ww / w).astype(int)
        truth = gt[y, x]
        at = above_highest(real)[y, x] & (real[y, x] == 0) & np.isfinite(truth)
        depth = mvs[ys, xs]
        with np.errstate(invalid="ignore", divide="ignore"):
            right = np.abs(depth - truth) / truth <= 0.1
        confident = conf[ys, xs] >= 0.4
        for name, keep, values in [("confident", at & confident, depth), ("right", at & confident & right, depth),
                                   ("confident, exact", at & confident, truth), ("exact", at, truth)]:
            p = real.copy()
            p[y[keep], x[keep]] = values[keep]
            path = f"{base}_above_{name.replace(', ', '_')}.npy"
            np.save(path, p.astype(np.float32))
            variants[name].append(f"{rgb} {path} {sky} {base}_out_above.npy {gt_path}")
            added[name] += int(keep.sum())
            added[name + " wrong"] += int((keep & ~right).sum()) if values is depth else 0

        lidar_path = scene / cam / f"{frame}_lidar.npy"
        if not lidar_path.exists():
            sys.exit(f"{lidar_path} is missing: export lidar_multi.depth as {{frame}}_lidar.npy")
        lidar = np.load(lidar_path)
        from_mvs = (real > 0) & ~((lidar > 0) & (np.abs(lidar - real) <= 0.01 * real)) & np.isfinite(gt)
        with np.errstate(invalid="ignore", divide="ignore"):
            right_sample = from_mvs & (np.abs(real - gt) / gt <= 0.1)
        mvs_samples["all"] += int(from_mvs.sum())
        mvs_samples["wrong"] += int((from_mvs & ~right_sample).sum())
        for name, keep in [("right MVS samples exact", right_sample), ("every MVS sample exact", from_mvs)]:
            p = real.copy()
            p[keep] = gt[keep]
            path = f"{base}_own_{name.split()[0]}.npy"
            np.save(path, p.astype(np.float32))
            own[name].append(f"{rgb} {path} {sky} {base}_out_above.npy {gt_path}")

    pts = lambda n: 100 * n / scored_total
    print(f"{len(images)} images, {scored_total} scored pixels\n")
    print("| completion of | bad above the highest sample | bad at or below it | scored pixels above |")
    print("| --- | ---: | ---: | ---: |")
    for v in ["real", "clean"]:
        print(f"| the {v} prompt | {pts(split[(v, 'above')]):.3f} | {pts(split[(v, 'below')]):.3f} | "
              f"{pts(split[(v, 'scored above')]):.1f}% |")
    print("\nThe clean prompt's bad pixels above the highest sample, by class and sign (points):\n")
    print("| class | completed nearer | completed farther |")
    print("| --- | ---: | ---: |")
    names = sorted({c for c, _ in by_class}, key=lambda c: -(by_class[(c, "nearer")] + by_class[(c, "farther")]))
    for c in names[:8]:
        print(f"| {c} | {pts(by_class[(c, 'nearer')]):.3f} | {pts(by_class[(c, 'farther')]):.3f} |")
    real_lines = [" ".join([f[0], f[1], f[2], f"{f[0][:-8]}_out_above.npy", f[4]]) for f in images]
    base_score = harness_score(a.harness, real_lines, work, "above_real", a.set)
    print("\n| prompt | samples added above | of them off by > 10% | bad > 10% |")
    print("| --- | ---: | ---: | ---: |")
    print(f"| real | - | - | {base_score:.3f}% |")
    labels = {"confident": "real + MVS of confidence >= 0.4", "right": "real + those within 10% only",
              "confident, exact": "real + the truth at the MVS pixels of confidence >= 0.4",
              "exact": "real + the truth at every MVS pixel"}
    for name, lines in variants.items():
        s = harness_score(a.harness, lines, work, "above_" + name.replace(", ", "_"), a.set)
        wrong = added[name + " wrong"] if name in ("confident", "right") else "-"
        print(f"| {labels[name]} | {added[name]} | {wrong} | {s:.3f}% |")
    print(f"\nThe prompt's {mvs_samples['all']} MVS samples ({mvs_samples['wrong']} off by > 10%):\n")
    print("| prompt | bad > 10% |")
    print("| --- | ---: |")
    print(f"| real | {base_score:.3f}% |")
    for name, lines in own.items():
        s = harness_score(a.harness, lines, work, "above_own_" + name.split()[0], a.set)
        print(f"| real, {name} | {s:.3f}% |")


if __name__ == "__main__":
    main()
