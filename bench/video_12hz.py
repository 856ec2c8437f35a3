"""The 12 Hz pipeline's speed: per-image cost in camera-clock mode against keyframe mode (the same
pipeline, pipelines/video_12hz.ron, with `dataset.frames` set), images per second on a 20 s scene at
12 Hz, and the projected hours for nuScenes trainval at 12 Hz. Prints Markdown for docs/BENCHMARKS.md.

    python3 bench/video_12hz.py [--data DIR] [--keyframes 40] [--dist4d BINARY] [--jobs N]

--data is a synthetic dataset with camera sweeps (made with `dist4d synth --camera-sweeps` when
absent: 40 keyframes is a 19.5 s scene, 235 camera rounds x 6 cameras at 1600x900). Each mode runs
cold (fresh cache and output folder) under a temporary folder. Needs only Python 3 and dist4d.
"""
import argparse, re, resource, subprocess, sys, tempfile, time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
DIST4D = REPO / "target" / "release" / "dist4d"
# nuScenes trainval: 850 scenes of ~20 s, 34,149 keyframes; its cameras give ~12 images a second.
TRAINVAL_IMAGES_12HZ = 850 * 20 * 12 * 6


def run(args):
    """(output, wall s, CPU s of the child)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.perf_counter()
    p = subprocess.run([str(DIST4D)] + [str(a) for a in args], capture_output=True, text=True)
    wall = time.perf_counter() - t
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    out = p.stdout + p.stderr
    if p.returncode != 0:
        sys.exit(f"dist4d {' '.join(map(str, args))} failed:\n{out}")
    return out, wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def stage_seconds(report):
    """{stage: (executed, seconds)} from the run's stage table."""
    rows = {}
    for line in report.splitlines():
        m = re.match(r"^(\S+)\s+[A-Za-z]+\s+(\d+)\s+(\d+)\s+\d+\s+\d+\s+\d+\s+([\d.]+)$", line)
        if m:
            rows[m.group(1)] = (int(m.group(3)), float(m.group(4)))
    return rows


def main():
    global DIST4D
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", default="/tmp/dist4d-video12-data")
    ap.add_argument("--keyframes", type=int, default=40)
    ap.add_argument("--dist4d", default=None, help="the binary to measure [default: target/release/dist4d]")
    ap.add_argument("--jobs", type=int, default=0, help="worker threads (default: dist4d's, the cores)")
    a = ap.parse_args()
    DIST4D = Path(a.dist4d) if a.dist4d else DIST4D
    data = Path(a.data)
    if not (data / "v1.0-mini").is_dir():
        print(f"synthesizing {data} ({a.keyframes} keyframes with camera sweeps) ...", file=sys.stderr)
        run(["synth", "--out", data, "--keyframes", a.keyframes, "--camera-sweeps"])
    pipeline = REPO / "pipelines" / "video_12hz.ron"
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        for mode in ["Keyframes", "Camera"]:
            args = ["run", pipeline, "--set", f"dataset.root={data}", "--set", f"dataset.frames={mode}",
                    "--cache", f"{tmp}/{mode}/cache", "--out", f"{tmp}/{mode}/out", "--progress", "off"]
            if a.jobs:
                args += ["--jobs", a.jobs]
            report, wall, cpu = run(args)
            stages = stage_seconds(report)
            images = stages["complete"][0]
            results[mode] = (images, wall, cpu, stages)
            print(f"{mode}: {images} images in {wall:.1f} s wall, {cpu:.1f} s CPU", file=sys.stderr)
    print("| frames | images | wall | CPU | wall per image | CPU per image | images/s |")
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: |")
    for mode, (images, wall, cpu, _) in results.items():
        print(f"| {mode} | {images} | {wall:.1f} s | {cpu:.1f} s | {1000 * wall / images:.0f} ms | "
              f"{1000 * cpu / images:.0f} ms | {images / wall:.2f} |")
    (ki, kw, kc, _), (ci, cw, cc, cam_stages) = results["Keyframes"], results["Camera"]
    print(f"\nCamera / keyframe mode per image: {(cw / ci) / (kw / ki):.2f}x wall, {(cc / ci) / (kc / ki):.2f}x CPU.")
    print("\nStage seconds per image (Camera mode): " + ", ".join(
        f"{name} {1000 * s / max(n, 1):.0f} ms" for name, (n, s) in sorted(cam_stages.items(), key=lambda x: -x[1][1]) if n))
    cpu_per_image = cc / ci
    hours_here = TRAINVAL_IMAGES_12HZ / (ci / cw) / 3600
    hours_64 = TRAINVAL_IMAGES_12HZ * cpu_per_image / 64 / 3600
    print(f"\nnuScenes trainval at 12 Hz (~{TRAINVAL_IMAGES_12HZ:,} images): {hours_here:.0f} h on this machine "
          f"at {ci / cw:.2f} images/s; {hours_64:.1f} h on a 64-core node if the CPU per image "
          f"({1000 * cpu_per_image:.0f} ms) scaled perfectly over its cores.")


if __name__ == "__main__":
    main()
