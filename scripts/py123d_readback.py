#!/usr/bin/env python3
"""What py123d's own Python API returns for a log, as JSON on stdout: every camera's intrinsics and
size, every image's time and camera -> world pose, and the boxes at every annotated time. dist4d's
tests compare it with what the `Py123d` reader gives (stages/datasets/src/py123d/cross_check.rs).

    .venv-py123d/bin/python scripts/py123d_readback.py LOG_DIR [SENSOR_ROOT]

SENSOR_ROOT is the source dataset's root for logs that store paths (py123d reads it from
NUSCENES_DATA_ROOT).
"""
import json
import os
import sys

if len(sys.argv) > 2:
    os.environ["NUSCENES_DATA_ROOT"] = sys.argv[2]

import pyarrow.ipc as ipc  # noqa: E402
from py123d.api.scene.arrow.arrow_scene_api import ArrowSceneAPI  # noqa: E402

log = sys.argv[1]
scene = ArrowSceneAPI(log)
out = {"cameras": {}, "boxes": []}
for cam_id, md in scene.get_camera_metadatas().items():
    # Every image of the camera, by the times in its file: py123d's own listing skips images
    # outside the sync rows that reference the camera.
    table = ipc.open_file(os.path.join(log, f"camera.{cam_id.serialize().lower()}.arrow")).read_all()
    times = table.column(0).to_pylist()
    images = []
    for t in times:
        cam = scene.get_camera_at_timestamp(t, cam_id, criteria="exact")
        images.append({"timestamp_us": t, "camera_to_global": cam.camera_to_global_se3.array.tolist()})
    out["cameras"][md.camera_name] = {
        "intrinsics": md.intrinsics.array.tolist(),
        "width": md.width,
        "height": md.height,
        "camera_to_imu": md.camera_to_imu_se3.array.tolist(),
        "images": images,
    }
boxes_file = os.path.join(log, "box_detections_se3.arrow")
if os.path.exists(boxes_file):
    for t in ipc.open_file(boxes_file).read_all().column(0).to_pylist():
        boxes = scene.get_box_detections_se3_at_timestamp(t, criteria="exact")
        out["boxes"].append({
            "timestamp_us": t,
            "boxes": [
                {"track": b.attributes.track_token, "label": int(b.attributes.label), "box": b.bounding_box_se3.array.tolist()}
                for b in boxes
            ],
        })
json.dump(out, sys.stdout)
