#!/usr/bin/env python3
"""Convert a nuScenes-format dataset (real nuScenes, or a scene written by `dist4d synth`) into
py123d Arrow logs, using py123d's own nuScenes parser and Arrow log writer.

Runs in the py123d venv (/work/.venv-py123d: py123d 0.7.0, pyarrow, numpy>=2, nuscenes-devkit
1.2.0 installed with --no-deps). Example:

    /work/.venv-py123d/bin/python scripts/py123d_convert.py \
        --nuscenes-root /work/shared/data/nuscenes-scene0061-kf0 --version v1.0-mini \
        --out /work/py123d-logs/nuscenes-kf0 --camera-storage jpeg --lidar-storage in_log

What it does, step by step:

1. py123d's nuScenes parser always opens the CAN-bus expansion (`NuScenesCanBus(dataroot)`), which
   fails when `<root>/can_bus/` does not exist. If the root has no `can_bus/`, a temporary folder
   is made of symlinks to every top-level entry of the root plus an empty `can_bus/`; the dataset
   itself is never written to. Relative paths stored in the logs ("path" storage) are the same
   for the temporary folder and the real root, so readers resolve them against the real root
   (env NUSCENES_DATA_ROOT).
2. Scene selection (`--scenes`):
   - `official`: exactly what `py123d-conversion dataset=nuscenes-mini` does. `NuScenesParser`
     keeps only scenes whose name is in the devkit's official split lists
     (`nuscenes.utils.splits.create_splits_scenes()`), for the splits
     `nuscenes-mini_train`/`nuscenes-mini_val` (or `nuscenes_*`, `nuscenes-interpolated*`).
   - `all`: every scene of the tables, whatever its name (e.g. `synth-0000` from `dist4d synth`).
     This builds py123d's `NuScenesLogParser` per scene directly (the class NuScenesParser
     returns), so the output is identical to `official` apart from the split folder name
     (`--split`, default `<prefix>_all`, e.g. `nuscenes-mini_all`).
   - `auto` (default): `official`, and if that finds no scene, `all`.
3. Timing (`--keyframes` / `--interpolated` / `--sweeps`):
   - `--keyframes` (default): py123d "sync" conversion at the 2 Hz nuScenes samples. One sync row per
     sample; each row holds the ego pose, boxes, the six keyframe camera images and the keyframe sweep.
   - `--interpolated`: py123d's `nuscenes-interpolated` mode, 10 Hz: every 2nd LiDAR sweep from the
     first to the last keyframe; boxes interpolated between keyframes (SLERP); nearest camera image
     (<= 100 ms) per sweep, camera poses from the ego trajectory interpolated to the image time.
   - `--sweeps`: py123d "async" conversion at native rates: ego + LiDAR at every sweep (20 Hz),
     every camera sample_data (12 Hz keyframes + sweeps), boxes at the keyframes (2 Hz). py123d then
     derives sync.arrow from the written files: one row per value of `--sync-reference` (default
     `lidar.lidar_merged.end_timestamp_us`, i.e. one row per sweep; keyframe rows are the rows whose
     box_detections_se3 index is not null), each other modality's last row in (previous ref, ref].
     py123d matches non-reference files by their first `*.timestamp_us` column, which for LiDAR is
     the sweep START (end - 50 ms); with `--sync-reference box_detections_se3.timestamp_us` the LiDAR
     index therefore points at the sweep after each keyframe, which is why it is not the default.
4. Storage: `--camera-storage jpeg|png|path|mp4` maps to py123d `camera_store_option`
   jpeg_binary|png_binary|path|mp4, `--lidar-storage in_log|path` to `lidar_store_option`
   binary|path with `--lidar-codec` (laz|draco|ipc|ipc_zstd|ipc_lz4, default ipc_zstd) for in_log.
   `--ipc-compression none|lz4|zstd` compresses the Arrow IPC record batches (py123d default: none).

Prints the log folders written, one per line, as `LOG <path>`.
"""

from __future__ import annotations

import argparse
import gc
import logging
import os
import shutil
import sys
import tempfile
import time
import traceback
from pathlib import Path
from typing import List, Optional

CAMERA_STORAGE = {"jpeg": "jpeg_binary", "png": "png_binary", "path": "path", "mp4": "mp4"}
LIDAR_STORAGE = {"in_log": "binary", "path": "path"}
VERSION_PREFIX = {"v1.0-mini": "nuscenes-mini", "v1.0-trainval": "nuscenes", "v1.0-test": "nuscenes"}


def parse_args(argv: Optional[List[str]] = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--nuscenes-root", required=True, type=Path, help="folder holding <version>/ tables, samples/, sweeps/, ...")
    p.add_argument("--version", default="v1.0-mini", choices=sorted(VERSION_PREFIX), help="nuScenes table version")
    p.add_argument("--out", required=True, type=Path, help="py123d logs root: logs go to OUT/<split>/<scene name>/")
    p.add_argument("--camera-storage", default="jpeg", choices=sorted(CAMERA_STORAGE),
                   help="jpeg/png: image bytes in the log; path: path relative to the nuScenes root; "
                        "mp4: frame index into OUT/<split>/<log>/<camera key>.mp4")
    p.add_argument("--lidar-storage", default="in_log", choices=sorted(LIDAR_STORAGE),
                   help="in_log: encoded point cloud bytes in the log; path: .pcd.bin path relative to the nuScenes root")
    p.add_argument("--lidar-codec", default="ipc_zstd", choices=["laz", "draco", "ipc", "ipc_zstd", "ipc_lz4"],
                   help="codec of the in-log point cloud blob (ignored for --lidar-storage path)")
    p.add_argument("--ipc-compression", default="none", choices=["none", "lz4", "zstd"],
                   help="Arrow IPC body compression of every .arrow file (py123d's default: none)")
    timing = p.add_mutually_exclusive_group()
    timing.add_argument("--keyframes", dest="timing", action="store_const", const="keyframes",
                        help="2 Hz nuScenes samples only (default)")
    timing.add_argument("--interpolated", dest="timing", action="store_const", const="interpolated",
                        help="py123d nuscenes-interpolated: 10 Hz, boxes interpolated between keyframes")
    timing.add_argument("--sweeps", dest="timing", action="store_const", const="sweeps",
                        help="native rates: every LiDAR sweep (20 Hz) and camera image (12 Hz); boxes 2 Hz")
    p.set_defaults(timing="keyframes")
    p.add_argument("--scenes", default="auto", choices=["auto", "official", "all"],
                   help="official: devkit split lists only (py123d's behaviour); all: every scene in the tables")
    p.add_argument("--split", default=None,
                   help="split folder name for --scenes all (default <prefix>_all, e.g. nuscenes-mini_all)")
    p.add_argument("--sync-reference", default="lidar.lidar_merged.end_timestamp_us",
                   help="--sweeps only: column the sync table is built on (py123d's nuScenes configs name "
                        "box_detections_se3.timestamp_us, which mis-indexes LiDAR in this mode)")
    p.add_argument("--no-route", action="store_true", help="do not write route_position.arrow")
    p.add_argument("--no-infer-dynamics", action="store_true",
                   help="do not infer ego/box velocities by finite differences (py123d's nuScenes configs do)")
    p.add_argument("--maps", action="store_true",
                   help="also convert the HD map (needs <root>/maps/expansion/*.json; written to OUT/../maps)")
    p.add_argument("--keep-tmp", action="store_true", help="keep the symlinked temporary root")
    p.add_argument("-v", "--verbose", action="store_true")
    return p.parse_args(argv)


def prepare_root(root: Path, keep: bool) -> tuple[Path, Optional[Path]]:
    """Return a root that has a can_bus/ folder: `root` itself, or a symlinked temporary copy."""
    if (root / "can_bus").is_dir():
        return root, None
    tmp = Path(tempfile.mkdtemp(prefix="py123d-nuscenes-root-"))
    for entry in sorted(root.iterdir()):
        (tmp / entry.name).symlink_to(entry.resolve())
    (tmp / "can_bus").mkdir()
    print(f"# no can_bus/ in {root}: using symlinked copy {tmp} with an empty can_bus/" + (" (kept)" if keep else ""))
    return tmp, None if keep else tmp


def split_names(version: str, timing: str) -> List[str]:
    """py123d's nuScenes split names for a table version (the interpolated ones for --interpolated)."""
    prefix = VERSION_PREFIX[version]
    if timing == "interpolated":
        prefix = prefix.replace("nuscenes", "nuscenes-interpolated", 1)
    if version == "v1.0-test":
        return [f"{prefix}_test"]
    return [f"{prefix}_train", f"{prefix}_val"]


def main(argv: Optional[List[str]] = None) -> int:
    args = parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    root = args.nuscenes_root.resolve()
    if not (root / args.version).is_dir():
        print(f"error: {root / args.version} does not exist", file=sys.stderr)
        return 2

    # Readers of "path" logs resolve relative paths against NUSCENES_DATA_ROOT; set it to the real root.
    os.environ.setdefault("NUSCENES_DATA_ROOT", str(root))

    from nuscenes import NuScenes

    from py123d.api.scene.arrow.arrow_log_writer import ArrowLogWriter, SyncConfig
    from py123d.api.scene.arrow.utils.log_writer_config import LogWriterConfig
    from py123d.parser.nuscenes.nuscenes_parser import NuScenesLogParser, NuScenesParser
    from py123d.parser.nuscenes.utils.nuscenes_constants import NUSCENES_DT, TARGET_DT

    work_root, cleanup = prepare_root(root, args.keep_tmp)
    try:
        prefix = VERSION_PREFIX[args.version]
        splits = split_names(args.version, args.timing)
        map_root = work_root if (args.maps and (root / "maps" / "expansion").is_dir()) else None
        if args.maps and map_root is None:
            print(f"# --maps: no {root / 'maps' / 'expansion'}; map conversion skipped")

        log_parsers = []
        map_parsers = []
        mode = args.scenes
        if mode in ("auto", "official"):
            parser = NuScenesParser(splits=splits, nuscenes_data_root=work_root, nuscenes_map_root=map_root)
            log_parsers = parser.get_log_parsers()
            map_parsers = parser.get_map_parsers()
            print(f"# official splits {splits}: {len(log_parsers)} scene(s)")
            if not log_parsers and mode == "auto":
                mode = "all"
        if mode == "all":
            nusc = NuScenes(version=args.version, dataroot=str(work_root), verbose=False)
            split = args.split or (f"{prefix.replace('nuscenes', 'nuscenes-interpolated', 1)}_all"
                                   if args.timing == "interpolated" else f"{prefix}_all")
            target_dt = TARGET_DT if args.timing == "interpolated" else NUSCENES_DT
            for scene in nusc.scene:
                log_record = nusc.get("log", scene["log_token"])
                log_parsers.append(NuScenesLogParser(
                    split=split, scene_token=scene["token"], scene_name=scene["name"],
                    location=log_record["location"], nuscenes_data_root=work_root,
                    database_version=args.version, target_dt=target_dt, nusc=nusc))
            print(f"# all scenes of {args.version} (split folder '{split}'): {len(log_parsers)} scene(s)")

        writer_config = LogWriterConfig(
            force_log_conversion=True,
            force_map_conversion=True,
            async_conversion=args.timing == "sweeps",
            camera_store_option=CAMERA_STORAGE[args.camera_storage],
            lidar_store_option=LIDAR_STORAGE[args.lidar_storage],
            lidar_codec=args.lidar_codec if args.lidar_storage == "in_log" else None,
            infer_ego_dynamics=not args.no_infer_dynamics,
            infer_box_dynamics=not args.no_infer_dynamics,
            write_route=not args.no_route,
        )
        out = args.out.resolve()
        out.mkdir(parents=True, exist_ok=True)
        sync_config = SyncConfig(reference_column=args.sync_reference, direction="backward")
        log_writer = ArrowLogWriter(
            log_writer_config=writer_config,
            logs_root=out,
            sensors_root=out.parent / "sensors",
            ipc_compression=None if args.ipc_compression == "none" else args.ipc_compression,
            ipc_compression_level=None,
            sync_config=sync_config,
        )

        if map_parsers:
            from py123d.api.map.arrow.arrow_map_writer import ArrowMapWriter

            map_writer = ArrowMapWriter(force_map_conversion=True, maps_root=out.parent / "maps", logs_root=out)
            for map_parser in map_parsers:
                if map_writer.reset(map_parser.get_map_metadata()):
                    for map_object in map_parser.iter_map_objects():
                        map_writer.write_map_object(map_object)
                map_writer.close()

        failures = 0
        for log_parser in log_parsers:
            started = time.time()
            log_metadata = log_parser.get_log_metadata()
            try:
                if log_writer.reset(log_metadata):
                    if args.timing == "sweeps":
                        for modality in log_parser.iter_modalities_async():
                            log_writer.write_async(modality)
                    else:
                        for modalities_sync in log_parser.iter_modalities_sync():
                            log_writer.write_sync(modalities_sync)
                log_writer.close()
            except Exception:
                failures += 1
                traceback.print_exc()
                log_writer.close()
                gc.collect()
                continue
            log_dir = out / log_metadata.split / log_metadata.log_name
            print(f"LOG {log_dir}  ({time.time() - started:.1f}s)")
        return 1 if failures or not log_parsers else 0
    finally:
        if cleanup is not None:
            shutil.rmtree(cleanup, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
