"""The curation chain done with the peer programs, for bench/curation.py's end-to-end ratio.

    python peer_chain.py DATAROOT VERSION

For every keyframe and camera: nuscenes-devkit `map_pointcloud_to_image` (LiDAR keyframe sweep ->
image), the points back to camera coordinates, Open3D `hidden_point_removal` from the camera
centre (radius 400 x the farthest point, as dist4d's default), a z-buffered sparse depth image, and
IP-Basic `fill_in_fast` (extrapolate, bilateral) from ../shared/bench/peers/ipbasic_cv2.py.
Prints one JSON line with the seconds spent in each step, summed over all images. Loading the
NuScenes tables is not counted.
"""
import json, sys, time
from pathlib import Path

import numpy as np
import open3d as o3d
from nuscenes.nuscenes import NuScenes

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "shared" / "bench" / "peers"))
from ipbasic_cv2 import fill_in_fast  # noqa: E402

CAMERAS = ["CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_BACK_RIGHT", "CAM_BACK", "CAM_BACK_LEFT", "CAM_FRONT_LEFT"]
nusc = NuScenes(version=sys.argv[2], dataroot=sys.argv[1], verbose=False)
spent = dict(project=0.0, hpr=0.0, splat=0.0, complete=0.0)
images = 0
for s in nusc.sample:
    for cam in CAMERAS:
        if cam not in s["data"]:
            continue
        t0 = time.perf_counter()
        pts, depth, img = nusc.explorer.map_pointcloud_to_image(s["data"]["LIDAR_TOP"], s["data"][cam])
        sd = nusc.get("sample_data", s["data"][cam])
        k = np.array(nusc.get("calibrated_sensor", sd["calibrated_sensor_token"])["camera_intrinsic"])
        t1 = time.perf_counter()
        u, v = pts[0], pts[1]
        xyz = np.stack([(u - k[0, 2]) / k[0, 0] * depth, (v - k[1, 2]) / k[1, 1] * depth, depth], axis=1)
        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz.astype(np.float64)))
        radius = 400.0 * float(np.linalg.norm(xyz, axis=1).max())
        _, idx = pc.hidden_point_removal([0.0, 0.0, 0.0], radius)
        idx = np.asarray(idx, dtype=np.int64)
        t2 = time.perf_counter()
        w, h = img.size
        sparse = np.zeros((h, w), np.float32)
        ui, vi, di = u[idx].astype(np.int64), v[idx].astype(np.int64), depth[idx].astype(np.float32)
        order = np.argsort(-di)  # far first, so the nearest point of a pixel is written last
        sparse[vi[order], ui[order]] = di[order]
        t3 = time.perf_counter()
        fill_in_fast(sparse, extrapolate=True, blur="bilateral")
        t4 = time.perf_counter()
        spent["project"] += t1 - t0
        spent["hpr"] += t2 - t1
        spent["splat"] += t3 - t2
        spent["complete"] += t4 - t3
        images += 1
spent["total"] = sum(spent.values())
spent["images"] = images
print(json.dumps(spent))
