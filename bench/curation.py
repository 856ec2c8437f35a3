"""End-to-end curation benchmark: accuracy, ablations, speed per stage, the completion against
IP-Basic, the whole chain against the peer programs, and LiDAR hold-out scores on the shared real
data. Prints Markdown for docs/BENCHMARKS.md.

    .venv-peers/bin/python bench/curation.py [--data DIR] [--keyframes 40] [--only SECTION ...]
                                             [--dist4d BINARY] [--set STAGE.PARAM=VALUE ...]

Sections: accuracy (full pipeline + ablations on synthetic data; the shipped pipeline's time per
stage and store/export bytes), shipped (the shipped pipeline alone: a cold run, a warm one, one
after deleting the output folder; store and export bytes; not run unless asked for), completion (vs ipbasic_cv2.py), chain (curation without MVS with its
depth files written vs ../shared/bench/peers/curation_chain.py, equal work; store/export bytes),
holdout (shared nuScenes and DGP). --dist4d measures another binary (say a copy of an older build)
instead of building target/release/dist4d.
Needs the peer venv of ../shared/bench/peers/setup.sh (numpy, OpenCV, Open3D, nuscenes-devkit);
dist4d itself is built with cargo. Everything is written under a temporary folder except the
synthetic dataset (--data, created once and reused).
"""
import argparse, json, os, re, resource, shutil, subprocess, sys, tempfile, time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
PEERS = REPO.parent / "shared" / "bench" / "peers"
SHARED = REPO.parent / "shared" / "data"
DIST4D = REPO / "target" / "release" / "dist4d"
SETS = []  # --set values for the chain section
CAMERAS = ["CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_BACK_RIGHT", "CAM_BACK", "CAM_BACK_LEFT", "CAM_FRONT_LEFT"]


def run(args, **kw):
    """Runs dist4d; returns (stdout+stderr text, wall seconds, child CPU seconds)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.perf_counter()
    p = subprocess.run([str(DIST4D)] + [str(a) for a in args], capture_output=True, text=True, **kw)
    wall = time.perf_counter() - t
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    out = p.stdout + p.stderr
    if p.returncode != 0:
        sys.exit(f"dist4d {' '.join(map(str, args))} failed:\n{out}")
    return out, wall, cpu


# Column headers of `dist4d eval`'s tables -> the keys `mean_row` gives them (others as printed).
HEADER_KEYS = {
    "d<1.25": "d1", "d<1.25^2": "d2", "d<1.25^3": "d3", "rel>10%": "bad10", "rel>25%": "bad25",
    "sky IoU": "sky_iou", "sky as structure": "sky_as_structure", "structure as sky": "structure_as_sky",
    "boundary acc (px)": "boundary_acc", "boundary comp (px)": "boundary_comp",
}


def mean_row(report, title):
    """The `mean` row of table `title` (e.g. "gt (raw)", "gt (sky, boundaries)") as a dict keyed by
    its header (see HEADER_KEYS): floats, None where the table shows `-` (no value)."""
    at = report.find(f"\n{title}\n")
    if at < 0:
        return None
    lines = report[at + len(title) + 2:].splitlines()
    cells = lambda line: [c.strip() for c in line.strip().strip("|").split("|")]
    keys = [HEADER_KEYS.get(h, h) for h in cells(lines[0])]
    for line in lines[2:]:
        if not line.startswith("|"):
            break
        if line.startswith("| mean |"):
            return {k: None if v == "-" else float(v) for k, v in zip(keys[1:], cells(line)[1:])}
    return None


def stage_table(report):
    """stage -> (executed, seconds) from the run table."""
    rows = {}
    for line in report.splitlines():
        f = line.split()
        # stage, kind, total, executed, cached, failed, skipped, [n/a,] seconds
        if len(f) in (8, 9) and f[2].isdigit() and re.match(r"^[0-9.]+$", f[-1]):
            rows[f[0]] = (int(f[3]), float(f[-1]))
    return rows


def edit(text, old, new):
    assert old in text, f"pipeline text changed: {old!r} not found"
    return text.replace(old, new)


def drop_stages(text, names):
    """The pipeline text without the stage blocks `names`."""
    out, skip = [], False
    for line in text.splitlines():
        m = re.match(r'^        "(\w+)": (\w+)\(', line)
        if m:
            skip = m.group(1) in names
        elif line.startswith("    },"):
            skip = False
        if not skip:
            out.append(line)
    return "\n".join(out) + "\n"


def lean(text):
    """Only what evaluation needs: no encoding, no sheets, only the metrics exported (a full run of
    40 keyframes stores ~12 GB of depth maps and images per variant otherwise)."""
    text = drop_stages(text, {"encode", "sheet"})
    at = text.index("    export: {")
    return text[:at] + '    export: {\n        "eval.json": "{scene}/{camera}/{frame}_metrics.json",\n    },\n)\n'


def variant(base, name, tmp, prompt_points=None, follow_points=None, visible_points=None, sky=True, slim=True):
    """`follow_points`: what FollowTracks moves (the fused points in the shipped file);
    `visible_points`: what hidden point removal reads instead of FollowTracks' output, with the boxes
    at the cloud's time (FollowTracks then unused)."""
    t = lean(base) if slim else base
    if follow_points:
        t = edit(t, '"follow": FollowTracks(\n            inputs: {\n                "points": "fuse.points",',
                 f'"follow": FollowTracks(\n            inputs: {{\n                "points": "{follow_points}",')
    if visible_points:
        t = edit(t, '"visible": HiddenPointRemoval(\n            inputs: {\n                "points": "follow.points",',
                 f'"visible": HiddenPointRemoval(\n            inputs: {{\n                "points": "{visible_points}",')
        t = edit(t, '"boxes": "dataset.camera_boxes",\n            },\n        ),\n        "prompt"',
                 '"boxes": "dataset.boxes",\n            },\n        ),\n        "prompt"')
    if prompt_points:
        t = edit(t, '"prompt": DepthPrompt(\n            inputs: {\n                "points": "visible.points",',
                 f'"prompt": DepthPrompt(\n            inputs: {{\n                "points": "{prompt_points}",')
    if not sky:  # the completion gets no sky mask
        t = edit(t, '"sparse": "prompt.sparse", "sky": "sky.sky", "ego": "ego.mask"}', '"sparse": "prompt.sparse", "ego": "ego.mask"}')
    path = tmp / f"{name}.ron"
    path.write_text(t)
    return path


def fmt(m):
    return f"{m['abs_rel']:.4f} | {m['rmse']:.2f} m | {m['d1']:.3f}"


def num(v, spec, unit=""):
    return "-" if v is None else f"{v:{spec}}{unit}"


def fmt_new(raw, dense):
    """rel>10% / >25%, sky IoU / ground-truth sky given a structure depth, boundary accuracy /
    completeness (the figures `dist4d eval` added for issue 14)."""
    pct = lambda v: num(None if v is None else 100 * v, ".2f", "%")
    dense = dense or {}
    return (f"{pct(raw.get('bad10'))} / {pct(raw.get('bad25'))} | "
            f"{num(dense.get('sky_iou'), '.3f')} / {pct(dense.get('sky_as_structure'))} | "
            f"{num(dense.get('boundary_acc'), '.2f')} / {num(dense.get('boundary_comp'), '.2f')} px")


def section_accuracy(data, tmp, base):
    cache = tmp / "cache-accuracy"
    print("## Curation vs synthetic ground truth, and ablations\n")
    print(f"Data: `dist4d synth` scene at {data} (1600x900, six cameras). Each row is one "
          "`dist4d eval` of a variant of pipelines/curation.ron sharing one cache, so only the "
          "stages a variant changes rerun. Scores: mean over cameras of the per-camera means, "
          "valid range 0.1-80 m, no median scaling. \"Above the LiDAR's field of view\": pixels whose "
          "ground-truth point lies above the top beam seen from the LiDAR (`AboveLidarFov`). Bad pixels: "
          "share of the scored pixels off by more than 10% / 25%. Sky: IoU of predicted sky (>= 99 m) and "
          "ground-truth sky, and the share of ground-truth sky given a structure depth (< 80 m). Boundaries: "
          "iBims-1 depth-boundary accuracy / completeness (Canny edges of log depth, sky at 100 m, px capped "
          "at 10; docs/stages.md).\n")
    print("| variant | all pixels: Abs Rel / RMSE / d<1.25 | bad pixels >10% / >25% | sky IoU / sky as structure "
          "| boundary acc / comp | above the LiDAR's field of view: Abs Rel / RMSE / d<1.25 | wall |")
    print("| --- | --- | --- | --- | --- | --- | ---: |")
    rows = [
        ("LiDAR only (aggregate -> prompt -> completion, no sky)",
         dict(prompt_points="aggregate.points", sky=False), []),
        ("+ MVS (fused points -> prompt, no sky)",
         dict(prompt_points="fuse.points", sky=False), []),
        ("+ HPR (no sky)", dict(sky=False), []),
        ("+ sky, built-in estimate (the shipped pipeline on data without segmentations)", dict(), []),
        ("+ sky from the ground-truth segmentation", dict(), ["--set", 'dataset.semantics="groundtruth/semantic"']),
        ("shipped pipeline without MVS (HPR + built-in sky)", dict(follow_points="aggregate.points"), []),
        ("shipped pipeline without FollowTracks (moving objects where the LiDAR saw them)",
         dict(visible_points="fuse.points"), []),
    ]
    results = {}
    for i, (label, edits, extra) in enumerate(rows):
        ron = variant(base, f"ablation{i}", tmp, **edits)
        report, wall, _ = run(["eval", ron, "--set", f"dataset.root={data}", "--cache", cache,
                               "--out", tmp / f"out-ablation{i}", "--progress", "off"] + extra)
        a, b = mean_row(report, "gt (raw)"), mean_row(report, "gt_above_lidar (raw)")
        dense = mean_row(report, "gt (sky, boundaries)")
        results[label] = (a, b)
        print(f"| {label} | {fmt(a)} | {fmt_new(a, dense)} | {fmt(b)} | {wall:.1f} s |")
    lidar_only, mvs = results[rows[0][0]][1], results[rows[1][0]][1]
    print(f"\nMVS changes the error above the LiDAR's field of view by {100 * (mvs['abs_rel'] / lidar_only['abs_rel'] - 1):+.1f}% "
          f"(Abs Rel) and {100 * (mvs['rmse'] / lidar_only['rmse'] - 1):+.1f}% (RMSE) against LiDAR only.")
    shipped, no_mvs = results[rows[3][0]][1], results[rows[5][0]][1]
    print(f"In the shipped pipeline, MVS changes it by {100 * (shipped['abs_rel'] / no_mvs['abs_rel'] - 1):+.1f}% "
          f"(Abs Rel) and {100 * (shipped['rmse'] / no_mvs['rmse'] - 1):+.1f}% (RMSE).\n")

    # Per-stage time of the shipped pipeline from a cold cache.
    report, wall, cpu = run(["run", variant(base, "shipped", tmp, slim=False), "--set", f"dataset.root={data}",
                             "--cache", tmp / "cache-cold", "--out", tmp / "out-cold", "--progress", "off"])
    stages = stage_table(report)
    space_line = space(tmp / "cache-cold", tmp / "out-cold", stages["complete"][0])
    shutil.rmtree(tmp / "cache-cold")
    shutil.rmtree(tmp / "out-cold")
    frames = stages["aggregate"][0]
    print(f"### Time per stage (shipped pipeline, cold cache, {frames} keyframes x 6 cameras)\n")
    print(f"`dist4d run pipelines/curation.ron --set dataset.root={data}`: {wall:.1f} s wall, "
          f"{cpu:.1f} s CPU on 2 cores. Space: {space_line}.\n")
    print("| stage | tasks | CPU seconds | per task |")
    print("| --- | ---: | ---: | ---: |")
    for name, (n, s) in sorted(stages.items(), key=lambda kv: -kv[1][1]):
        if n:
            print(f"| {name} | {n} | {s:.1f} | {1000 * s / n:.0f} ms |")
    curation = ["aggregate", "visible", "prompt", "complete"]
    per_kf = sum(stages[s][1] for s in curation) / frames
    mvs_kf = sum(stages[s][1] for s in ["mvs", "mvs_points", "fuse"]) / frames
    print(f"\nOne keyframe of six cameras: {per_kf:.2f} s of CPU without MVS ({' + '.join(curation)}); "
          f"MVS adds {mvs_kf:.2f} s ({1000 * stages['mvs'][1] / stages['mvs'][0]:.0f} ms per camera image "
          f"for MultiViewStereo).\n")


def section_completion(data, tmp, base):
    """CompleteDepth and IP-Basic on the same sparse prompts, scored against the ground truth."""
    print("## Depth completion vs IP-Basic (same sparse input)\n")
    t = drop_stages(base, {"encode", "sheet", "eval", "lidar", "lidar_multi", "holdout"})
    at = t.index("    export: {")
    t = t[:at] + """        "encode_depth": EncodeDepth(inputs: {"depth": "complete.depth"}),
        "encode_sparse": EncodeDepth(inputs: {"depth": "prompt.sparse"}),
        "encode_gt": EncodeDepth(inputs: {"depth": "dataset.gt_depth"}),
    },
    export: {
        "encode_depth.npy": "{scene}/{camera}/{frame}_depth.npy",
        "encode_sparse.npy": "{scene}/{camera}/{frame}_sparse.npy",
        "encode_gt.npy": "{scene}/{camera}/{frame}_gt.npy",
    },
)
"""
    # The stages map closes before the added stages: reopen it.
    t = t.replace("    },\n        \"encode_depth\"", "        \"encode_depth\"", 1)
    ron = tmp / "completion.ron"
    ron.write_text(t)
    out = tmp / "out-completion"
    report, _, _ = run(["run", ron, "--set", f"dataset.root={data}", "--cache", tmp / "cache-accuracy",
                        "--out", out, "--progress", "off"])
    stages = stage_table(report)
    scene = next(p for p in out.iterdir() if p.is_dir())
    # Three keyframes from the middle of the scene (the whole scene when it is shorter).
    count = len(list((scene / "CAM_FRONT").glob("*_gt.npy")))
    frames = list(range(max(0, count // 2 - 1), min(count, count // 2 + 2)))

    def score(d, g):
        v = (g > 0.1) & (g < 80)
        d, g = d[v], g[v]
        ok = d > 0
        dd = np.where(ok, d, 1e-3)
        ratio = np.maximum(dd / g, g / dd)
        rel = np.abs(dd - g) / g
        return np.mean(rel), np.sqrt(np.mean((dd - g) ** 2)), np.mean(ratio < 1.25), np.mean(rel > 0.1), np.mean(rel > 0.25)

    scores = {"dist4d CompleteDepth": [], "IP-Basic fill_in_fast (bilateral)": [],
              "IP-Basic fill_in_fast (extrapolate, bilateral)": []}
    times = {k: [] for k in scores}
    py = sys.executable
    for f in frames:
        for cam in CAMERAS:
            sparse = scene / cam / f"{f:03d}_sparse.npy"
            gt = np.load(scene / cam / f"{f:03d}_gt.npy")
            scores["dist4d CompleteDepth"].append(score(np.load(scene / cam / f"{f:03d}_depth.npy"), gt))
            for label, extra in [("IP-Basic fill_in_fast (bilateral)", []),
                                 ("IP-Basic fill_in_fast (extrapolate, bilateral)", ["--extrapolate"])]:
                dense = tmp / "ipbasic.npy"
                p = subprocess.run([py, PEERS / "ipbasic_cv2.py", sparse, "--out", dense, "--repeat", "3"] + extra,
                                   capture_output=True, text=True, check=True)
                times[label].append(json.loads(p.stdout.splitlines()[0])["best_seconds"])
                scores[label].append(score(np.load(dense), gt))
    # CompleteDepth alone on one worker (a param change reruns exactly it): its task time, which
    # includes decoding its inputs (the JPEG among them) and encoding its output.
    report, _, _ = run(["run", ron, "--set", f"dataset.root={data}", "--cache", tmp / "cache-accuracy",
                        "--out", out, "--progress", "off", "--jobs", "1", "--set", "complete.sky_depth=99.5"])
    n, s = stage_table(report)["complete"]
    ours_ms = 1000 * s / max(n, 1)
    print(f"{len(frames) * 6} camera images (keyframes {frames[0]}-{frames[-1]}, 1600x900) of the synthetic "
          "scene; the sparse input is the pipeline's prompt (`prompt.sparse`: aggregated LiDAR + MVS after "
          "hidden point removal). IP-Basic times are best of 3 per image (one thread, no I/O); CompleteDepth's is "
          f"its mean task time over all {n} images on one worker, decoding its inputs (the JPEG among them) "
          "and encoding its output included.\n")
    print("| method | Abs Rel | RMSE | d<1.25 | >10% | >25% | time per image |")
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: |")
    for label, rows in scores.items():
        a = np.array(rows).mean(axis=0)
        ms = ours_ms if label.startswith("dist4d") else 1000 * np.mean(times[label])
        print(f"| {label} | {a[0]:.4f} | {a[1]:.2f} m | {a[2]:.3f} | {100 * a[3]:.2f}% | {100 * a[4]:.2f}% | {ms:.0f} ms |")
    print()


def du(path):
    """Bytes of the files under `path` (apparent sizes: what a copy elsewhere would take)."""
    return sum(f.stat().st_size for f in Path(path).rglob("*") if f.is_file()) if Path(path).exists() else 0


def space(cache, out, images):
    """Store bytes (cas/ + ac/) and exported bytes, per image, and their ratio."""
    store = du(cache / "cas") + du(cache / "ac")
    exported = du(out) - du(out / ".dist4d-tmp")
    return (f"store {store / images / 1e6:.2f} MB per image (cas/ + ac/), exported files "
            f"{exported / images / 1e6:.2f} MB per image: store / exports = {store / max(exported, 1):.2f}")


def section_shipped(data, tmp, base):
    """The shipped pipeline as it ships: a cold run, the same command again (everything cached),
    and again after deleting the output folder; the store and export bytes per image after the
    cold run."""
    ron = tmp / "shipped.ron"
    ron.write_text(base)
    cache, out = tmp / "cache-shipped", tmp / "out-shipped"
    args = ["run", ron, "--set", f"dataset.root={data}", "--cache", cache, "--out", out, "--progress", "off"]
    report, cold, cold_cpu = run(args)
    stages = stage_table(report)
    space_line = space(cache, out, stages["complete"][0])
    report, warm, warm_cpu = run(args)
    cached = re.search(r"(\d+) executed, (\d+) cached", report)
    shutil.rmtree(out)
    report, lost, lost_cpu = run(args)
    redone = re.search(r"(\d+) executed, (\d+) cached", report)
    shutil.rmtree(cache)
    shutil.rmtree(out)
    print("## The shipped pipeline: cold and warm runs, store and export bytes\n")
    print(f"`dist4d run pipelines/curation.ron --set dataset.root={data} --cache C --out O` "
          f"({stages['aggregate'][0]} keyframes x 6 cameras), then the same command again, and again "
          "after `rm -r O`:\n")
    print("| run | wall | CPU |")
    print("| --- | ---: | ---: |")
    print(f"| cold | {cold:.1f} s | {cold_cpu:.1f} s |")
    print(f"| warm ({cached.group(1)} executed, {cached.group(2)} cached) | {warm:.2f} s | {warm_cpu:.2f} s |")
    print(f"| output folder deleted ({redone.group(1)} executed, {redone.group(2)} cached) | {lost:.1f} s "
          f"| {lost_cpu:.1f} s |")
    print(f"\nSpace after the cold run: {space_line}.\n")


def section_chain(data, tmp, base):
    """Curation without MVS, depth files written: dist4d vs curation_chain.py (equal work)."""
    print("## End to end vs the peer chain (curation without MVS, EXR + PNG16 + NPY written)\n")
    # dist4d: the shipped pipeline without MVS, FollowTracks, sky estimation, evaluation or sheets (the peer
    # estimates no sky: IP-Basic leaves it as it fills it); EncodeDepth's EXR, PNG16 and NPY
    # exported (it also makes the preview, which the peer does not: not exported).
    t = variant(base, "chain", tmp, visible_points="aggregate.points", sky=False, slim=False).read_text()
    names = set(re.findall(r'^        "(\w+)": \w+\(', t, re.M))
    # No ego mask either (the synthetic world's is empty, and the peer has none).
    t = re.sub(r'\n\s*"ego": "ego\.mask",', "", t)
    t = t.replace(', "ego": "ego.mask"', "")
    # Nor TemporalBlend (the peer completes each frame on its own): encode the completion.
    t = t.replace('EncodeDepth(inputs: {"depth": "blend.depth"})', 'EncodeDepth(inputs: {"depth": "complete.depth"})')
    t = drop_stages(t, names - {"aggregate", "visible", "prompt", "complete", "encode"})
    t = t[:t.index("    export: {")] + """    export: {
        "encode.exr": "{scene}/{camera}/{frame}_depth.exr",
        "encode.png16": "{scene}/{camera}/{frame}_depth.png",
        "encode.npy": "{scene}/{camera}/{frame}_depth.npy",
    },
)
"""
    ron = tmp / "chain_only.ron"
    ron.write_text(t)
    cache, out = tmp / "cache-chain", tmp / "out-chain"
    sets = [x for kv in SETS for x in ("--set", kv)]
    report, wall, cpu = run(["run", ron, "--set", f"dataset.root={data}", "--cache", cache,
                             "--out", out, "--progress", "off"] + sets)
    stages = stage_table(report)
    frames = stages["aggregate"][0]
    images = stages["complete"][0]
    space_line = space(cache, out, images)
    shutil.rmtree(cache)
    shutil.rmtree(out)
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    p = subprocess.run([sys.executable, PEERS / "curation_chain.py", data, "v1.0-mini", "--out", tmp / "out-peer"],
                       capture_output=True, text=True)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    peer_cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    shutil.rmtree(tmp / "out-peer", ignore_errors=True)
    if p.returncode != 0:
        print(f"(peer chain failed: {p.stderr.strip()[-500:]})\n")
        return
    peer = json.loads(p.stdout.strip().splitlines()[-1])
    print(f"{frames} keyframes x 6 cameras of the synthetic scene (1600x900), same run. dist4d: `dist4d run` of "
          "curation.ron without MVS, sky estimation, evaluation and sheets (aggregation of 3 LiDAR keyframes without moving "
          "boxes, HPR, z-buffered prompt, CompleteDepth, EncodeDepth), EXR + PNG16 + NPY exported; cold cache, "
          "dataset reading and exports included. Peer: ../shared/bench/peers/curation_chain.py (nuscenes-devkit "
          "aggregation and projection, Open3D HPR, z-buffer, IP-Basic, JPEG decode, EXR + PNG16 + NPY written; "
          "one Python process; its wall excludes loading the tables).\n")
    print("| | wall | CPU |")
    print("| --- | ---: | ---: |")
    print(f"| dist4d (2 worker threads{''.join(', ' + kv for kv in SETS)}) | {wall:.1f} s | {cpu:.1f} s |")
    steps = " + ".join(f"{k} {peer[k]:.1f} s" for k in
                       ["aggregate", "project", "hpr", "splat", "complete", "decode", "write"] if k in peer)
    print(f"| peer: {steps} | {peer['wall']:.1f} s | {peer_cpu:.1f} s |")
    print(f"\nRatio: {peer['wall'] / wall:.2f}x by wall time, {peer_cpu / cpu:.2f}x by CPU time.\n")
    print(f"Space (dist4d): {space_line}.\n")
    print("dist4d per stage:\n")
    print("| stage | tasks | CPU seconds | per task |")
    print("| --- | ---: | ---: | ---: |")
    for name, (n, s) in sorted(stages.items(), key=lambda kv: -kv[1][1]):
        if n:
            print(f"| {name} | {n} | {s:.1f} | {1000 * s / n:.0f} ms |")
    print()


def section_holdout(tmp, base):
    print("## LiDAR hold-out on the shared real data\n")
    print("A seeded 20% of the target frame's LiDAR points is left out of curation "
          "(`--set aggregate.holdout=0.2`) and the dense depth is scored on exactly those points "
          "(valid range 0.1-80 m).\n")
    print("| data | images | Abs Rel | Sq Rel | RMSE | RMSE log | d<1.25 | d<1.25^2 | d<1.25^3 | >10% | >25% "
          "| Abs Rel, median-scaled |")
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    dgp_text = re.sub(r"    dataset: NuScenes\((.|\n)*?\n    \),\n", '    dataset: Dgp(root: ""),\n', base, count=1)
    (tmp / "holdout_dgp.ron").write_text(dgp_text)
    (tmp / "holdout_nus.ron").write_text(base)
    for label, ron, root in [
        ("nuScenes scene-0061, 1 keyframe (no neighbours: no MVS)", tmp / "holdout_nus.ron",
         SHARED / "nuscenes-scene0061-kf0"),
        ("DGP/DDAD scene 02, 3 frames", tmp / "holdout_dgp.ron", SHARED / "dgp-scene02"),
    ]:
        if not root.is_dir():
            print(f"| {label} | (absent: {root}) |")
            continue
        report, _, _ = run(["eval", ron, "--set", f"dataset.root={root}", "--set", "aggregate.holdout=0.2",
                            "--cache", tmp / f"cache-{ron.stem}", "--out", tmp / f"out-{ron.stem}",
                            "--progress", "off"])
        m, s = mean_row(report, "holdout (raw)"), mean_row(report, "holdout (median-scaled)")
        print(f"| {label} | {m['images']:.0f} | {m['abs_rel']:.4f} | {m['sq_rel']:.4f} | {m['rmse']:.3f} m | "
              f"{m['rmse_log']:.4f} | {m['d1']:.4f} | {m['d2']:.4f} | {m['d3']:.4f} | "
              f"{num(m.get('bad10'), '.4f')} | {num(m.get('bad25'), '.4f')} | {s['abs_rel']:.4f} |")
    print()


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", default="/tmp/dist4d-bench-synth")
    ap.add_argument("--keyframes", type=int, default=40)
    ap.add_argument("--only", nargs="*", default=["accuracy", "completion", "chain", "holdout"])
    ap.add_argument("--set", action="append", default=[], metavar="STAGE.PARAM=VALUE",
                    help="passed to dist4d in the chain section (e.g. encode.exr_compression=Zip)")
    ap.add_argument("--dist4d", help="a dist4d binary to measure (e.g. a copy of an older build) instead of "
                    "building target/release/dist4d")
    a = ap.parse_args()
    global DIST4D
    SETS.extend(a.set)
    if a.dist4d:
        DIST4D = Path(a.dist4d).resolve()
    else:
        subprocess.run(["cargo", "build", "--release", "-q"], cwd=REPO, check=True)
    data = Path(a.data)
    if set(a.only) != {"holdout"}:
        if not (data / "v1.0-mini").is_dir():
            run(["synth", "--out", data, "--keyframes", a.keyframes])
    base = (REPO / "pipelines" / "curation.ron").read_text()
    tmp = Path(tempfile.mkdtemp(prefix="dist4d-bench-"))
    try:
        print(f"Machine: {os.cpu_count()} cores; command: `{' '.join(sys.argv)}`; {time.strftime('%Y-%m-%d')}\n")
        if "accuracy" in a.only:
            section_accuracy(data, tmp, base)
        if "completion" in a.only:
            section_completion(data, tmp, base)
        if "shipped" in a.only:
            section_shipped(data, tmp, base)
        if "chain" in a.only:
            section_chain(data, tmp, base)
        if "holdout" in a.only:
            section_holdout(tmp, base)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
