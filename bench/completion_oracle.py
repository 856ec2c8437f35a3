"""What the depth completion reaches when its input is exact (docs/BENCHMARKS.md, "What the
completion can reach").

    .venv-peers/bin/python bench/completion_oracle.py DATA OUT WORK [--harness BIN] [--set k=v ...] [--levin N]

DATA is a synthetic scene (`dist4d synth`), OUT the output folder of a curation run that exported
the prompt (`prompt.sparse` as `{frame}_prompt.npy`: pipelines/curation.ron plus an EncodeDepth of
`prompt.sparse` and its `npy` export). For every camera image it writes to WORK the image, the
ground truth and three prompts with the same pixels: the real one, the ground-truth depth at each of
its pixels ("oracle"), and the real one without its samples off by more than 10% ("clean"). Then it
runs CompleteDepth on each (the `complete_npy` example; the ground-truth sky as its sky mask) and
prints the share of pixels off by more than 10% and the boundary accuracy and completeness. With
`--levin N` it also solves, for the first N images, the colour-affinity least squares of Levin et
al. 2004 (the NYU Depth v2 toolbox fill) on the oracle prompt with scipy: a reference for what a
global fill reaches, at ~40 s per image.
"""
import argparse
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

os.environ.setdefault("OPENCV_IO_ENABLE_OPENEXR", "1")
import cv2  # noqa: E402

CAMERAS = ["CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_BACK_RIGHT", "CAM_BACK", "CAM_BACK_LEFT", "CAM_FRONT_LEFT"]
ROOT = Path(__file__).resolve().parent.parent


def prepare(data, out, work):
    """Writes the NPYs and one list per prompt variant; returns the lists and the share of wrong
    prompt samples."""
    scene = next(p for p in Path(out).iterdir() if p.is_dir())
    lists = {v: [] for v in ["real", "oracle", "clean"]}
    wrong = total = 0
    for cam in CAMERAS:
        images = sorted((Path(data) / "samples" / cam).glob("*.jpg"))
        truths = sorted((Path(data) / "groundtruth" / "depth" / cam).glob("*.exr"))
        for k, (image, truth) in enumerate(zip(images, truths)):
            prompt = scene / cam / f"{k:03d}_prompt.npy"
            if not prompt.exists():
                sys.exit(f"{prompt} is missing: export prompt.sparse as {{frame}}_prompt.npy")
            b = Path(work) / f"{cam}_{k:03d}"
            rgb = cv2.imread(str(image))[:, :, ::-1].astype(np.float32)
            np.save(f"{b}_rgb.npy", np.ascontiguousarray(rgb))
            gt = cv2.imread(str(truth), cv2.IMREAD_UNCHANGED).astype(np.float32)
            np.save(f"{b}_gt.npy", gt)
            np.save(f"{b}_sky.npy", (~np.isfinite(gt)).astype(np.float32))
            real = np.load(prompt).astype(np.float32)
            has = real > 0
            with np.errstate(invalid="ignore", divide="ignore"):
                right = has & np.isfinite(gt) & (np.abs(real - gt) / gt <= 0.1)
            wrong += int((has & ~right).sum())
            total += int(has.sum())
            np.save(f"{b}_real.npy", real)
            np.save(f"{b}_oracle.npy", np.where(has & np.isfinite(gt), gt, 0).astype(np.float32))
            np.save(f"{b}_clean.npy", np.where(right, real, 0).astype(np.float32))
            for v in lists:
                lists[v].append(f"{b}_rgb.npy {b}_{v}.npy {b}_sky.npy {b}_out_{v}.npy {b}_gt.npy")
    paths = {}
    for v, lines in lists.items():
        paths[v] = Path(work) / f"{v}.txt"
        paths[v].write_text("\n".join(lines) + "\n")
    return paths, wrong / max(total, 1)


def summary(rows):
    scored = sum(int(r[1]) for r in rows)
    bad = sum(int(r[2]) for r in rows)
    acc = np.mean([float(r[3]) for r in rows])
    comp = np.mean([float(r[4]) for r in rows])
    ms = np.mean([float(r[5]) for r in rows])
    return f"{100 * bad / scored:.2f}% | {acc:.2f} px | {comp:.2f} px | " + (f"{ms:.0f} ms" if ms > 0 else "-")


def levin(base, sigma=5.0, weight=100.0, iterations=3000):
    """Colour-affinity least squares in inverse depth (4-neighbours, w = exp(-|dRGB|^2 / 2 sigma^2)),
    the samples held by `weight`; conjugate gradients from CompleteDepth's result."""
    import scipy.sparse as sp
    import scipy.sparse.linalg as sla
    rgb = np.load(f"{base}_rgb.npy").astype(np.float64)
    s = np.load(f"{base}_oracle.npy")
    sky = np.load(f"{base}_sky.npy") > 0
    h, w = s.shape
    idx = np.arange(h * w).reshape(h, w)
    rows, cols, vals = [], [], []
    for a, b in [((slice(None), slice(0, -1)), (slice(None), slice(1, None))),
                 ((slice(0, -1), slice(None)), (slice(1, None), slice(None)))]:
        wt = np.exp(-((rgb[a] - rgb[b]) ** 2).sum(-1) / (2 * sigma * sigma)) + 1e-4
        ok = ~(sky[a] | sky[b])
        rows.append(idx[a][ok]), cols.append(idx[b][ok]), vals.append(wt[ok])
    i, j, v = np.concatenate(rows), np.concatenate(cols), np.concatenate(vals)
    a = sp.coo_matrix((np.r_[v, v], (np.r_[i, j], np.r_[j, i])), shape=(h * w, h * w)).tocsr()
    has = (s > 0).ravel()
    inv = np.where(has, 1 / np.where(has, s.ravel(), 1), 0)
    m = (sp.diags(np.asarray(a.sum(1)).ravel()) - a + sp.diags(weight * has + 1e-6 * sky.ravel())).tocsr()
    start = np.load(f"{base}_out_oracle.npy").ravel()
    x, _ = sla.cg(m, weight * inv, x0=np.where(start > 0, 1 / np.maximum(start, 1e-3), 0),
                  M=sp.diags(1 / m.diagonal()), maxiter=iterations, rtol=1e-8)
    z = np.where(x > 1e-4, 1 / np.maximum(x, 1e-6), 1000).reshape(h, w).astype(np.float32)
    z[sky] = 100
    np.save(f"{base}_out_levin.npy", z)


def harness_score(harness, lines, work, name, settings):
    """Runs the harness on `lines` (written to WORK/NAME.txt) and returns the share (%) of scored
    pixels off by more than 10% over all of them."""
    path = Path(work) / f"{name}.txt"
    path.write_text("\n".join(lines) + "\n")
    out = subprocess.run([harness, path] + settings, capture_output=True, text=True, check=True).stdout
    rows = [line.split() for line in out.splitlines()]
    return 100 * sum(int(r[2]) for r in rows) / sum(int(r[1]) for r in rows)


def arguments(doc):
    """The arguments this script and bench/prompt_errors.py share: DATA OUT WORK, the harness and
    CompleteDepth's parameters."""
    ap = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("data")
    ap.add_argument("out")
    ap.add_argument("work")
    ap.add_argument("--harness", default=str(ROOT / "target" / "release" / "examples" / "complete_npy"))
    ap.add_argument("--set", nargs="*", default=[], help="CompleteDepth parameters, field=value")
    return ap


def main():
    ap = arguments(__doc__)
    ap.add_argument("--levin", type=int, default=0, help="also the Levin fill for the first N images")
    a = ap.parse_args()
    Path(a.work).mkdir(parents=True, exist_ok=True)
    if not Path(a.harness).exists():
        subprocess.run(["cargo", "build", "--release", "-p", "dist4d-stages", "--example", "complete_npy"],
                       cwd=ROOT, check=True)
    lists, wrong = prepare(a.data, a.out, a.work)
    print(f"prompt samples off by > 10% (or on sky): {100 * wrong:.2f}%\n")
    print("| prompt | pixels off by > 10% | boundary accuracy | completeness | completion time |")
    print("| --- | ---: | ---: | ---: | ---: |")
    for v, path in lists.items():
        p = subprocess.run([a.harness, path] + a.set, capture_output=True, text=True, check=True)
        rows = [line.split() for line in p.stdout.splitlines()]
        print(f"| {v} | {summary(rows)} |")
    if a.levin:
        lines = lists["oracle"].read_text().splitlines()[: a.levin]
        for line in lines:
            levin(line.split()[0][: -len("_rgb.npy")])
        scored = Path(a.work) / "levin.txt"
        scored.write_text("\n".join(
            " ".join([f[0], "-", f[2], f[3].replace("_out_oracle", "_out_levin"), f[4]])
            for f in (line.split() for line in lines)) + "\n")
        p = subprocess.run([a.harness, scored], capture_output=True, text=True, check=True)
        rows = [line.split() for line in p.stdout.splitlines()]
        print(f"| oracle, Levin fill ({len(rows)} images) | {summary(rows)} |")


if __name__ == "__main__":
    main()
