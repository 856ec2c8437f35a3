"""Checks dist4d's info pickles against what the nuscenes-devkit gives for the same tables.

Usage: infos_check.py DATAROOT VERSION PATH_PREFIX MAX_SWEEPS SPLIT=PKL [SPLIT=PKL ...]

Every info is recomputed here from the devkit alone (get_sample_data, box_velocity,
pyquaternion), following MagicDrive-V2's converter (flymin/MagicDrive-V2 @ 4ed72c6,
tools/prepare_data/data_converter/nuscenes_converter.py), and compared field by field: key order,
Python types, numpy dtypes and shapes, values (geometry within 1e-6, NaN where the devkit gives
NaN). Then the scene order, scene_tokens, token chains, split membership and box ids. Prints one
line per file; exits non-zero with the first difference.
"""
import math
import os
import pickle
import sys
import warnings

import numpy as np
from nuscenes.nuscenes import NuScenes
from nuscenes.utils import splits
from pyquaternion import Quaternion

warnings.simplefilter("error")  # a pickle numpy must warn about is a failure

CAMERAS = ["CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_FRONT_LEFT", "CAM_BACK", "CAM_BACK_LEFT", "CAM_BACK_RIGHT"]
NAME_MAPPING = {
    "movable_object.barrier": "barrier", "vehicle.bicycle": "bicycle", "vehicle.bus.bendy": "bus",
    "vehicle.bus.rigid": "bus", "vehicle.car": "car", "vehicle.construction": "construction_vehicle",
    "vehicle.motorcycle": "motorcycle", "human.pedestrian.adult": "pedestrian", "human.pedestrian.child": "pedestrian",
    "human.pedestrian.construction_worker": "pedestrian", "human.pedestrian.police_officer": "pedestrian",
    "movable_object.trafficcone": "traffic_cone", "vehicle.trailer": "trailer", "vehicle.truck": "truck",
}


def fail(where, msg):
    sys.exit(f"{where}: {msg}")


def sensor2top(nusc, token, prefix, l2e_t, l2e_r, e2g_t, e2g_r, kind):
    sd = nusc.get("sample_data", token)
    cs = nusc.get("calibrated_sensor", sd["calibrated_sensor_token"])
    pose = nusc.get("ego_pose", sd["ego_pose_token"])
    out = {
        "data_path": os.path.join(prefix, sd["filename"]),
        "type": kind,
        "sample_data_token": sd["token"],
        "sensor2ego_translation": cs["translation"],
        "sensor2ego_rotation": cs["rotation"],
        "ego2global_translation": pose["translation"],
        "ego2global_rotation": pose["rotation"],
        "timestamp": sd["timestamp"],
    }
    s2e = Quaternion(cs["rotation"]).rotation_matrix
    e2g_s = Quaternion(pose["rotation"]).rotation_matrix
    m = np.linalg.inv(e2g_r).T @ np.linalg.inv(l2e_r).T
    R = (s2e.T @ e2g_s.T) @ m
    T = (np.array(cs["translation"]) @ e2g_s.T + np.array(pose["translation"])) @ m
    T -= np.array(e2g_t) @ m + np.array(l2e_t) @ np.linalg.inv(l2e_r).T
    out["sensor2lidar_rotation"] = R.T
    out["sensor2lidar_translation"] = T
    return out


def ego_velocity(nusc, sample):
    first = nusc.get("sample", sample["prev"]) if sample["prev"] else sample
    last = nusc.get("sample", sample["next"]) if sample["next"] else sample

    def pose(s):
        return nusc.get("ego_pose", nusc.get("sample_data", s["data"]["LIDAR_TOP"])["ego_pose_token"])

    dt = 1e-6 * last["timestamp"] - 1e-6 * first["timestamp"]
    with np.errstate(all="ignore"):
        v = (np.array(pose(last)["translation"]) - np.array(pose(first)["translation"])) / dt
        q = (Quaternion(pose(last)["rotation"]) * Quaternion(pose(first)["rotation"]).inverse).normalised
        w = q.angle * q.axis / dt
    return (v, w)


def expected_info(nusc, sample, prefix, max_sweeps):
    lidar_token = sample["data"]["LIDAR_TOP"]
    sd = nusc.get("sample_data", lidar_token)
    cs = nusc.get("calibrated_sensor", sd["calibrated_sensor_token"])
    pose = nusc.get("ego_pose", sd["ego_pose_token"])
    scene = nusc.get("scene", sample["scene_token"])
    log = nusc.get("log", scene["log_token"])
    _, boxes, _ = nusc.get_sample_data(lidar_token)
    info = {
        "lidar_path": os.path.join(prefix, sd["filename"]),
        "token": sample["token"],
        "sweeps": [],
        "cams": {},
        "lidar2ego_translation": cs["translation"],
        "lidar2ego_rotation": cs["rotation"],
        "ego2global_translation": pose["translation"],
        "ego2global_rotation": pose["rotation"],
        "timestamp": sample["timestamp"],
        "location": log["location"],
        "description": scene["description"],
        "timeofday": log["logfile"][5:],
        "is_key_frame": True,
        "ego_velocity": ego_velocity(nusc, sample),
    }
    l2e_r = Quaternion(cs["rotation"]).rotation_matrix
    e2g_r = Quaternion(pose["rotation"]).rotation_matrix
    args = (cs["translation"], l2e_r, pose["translation"], e2g_r)
    for cam in CAMERAS:
        _, _, k = nusc.get_sample_data(sample["data"][cam])
        c = sensor2top(nusc, sample["data"][cam], prefix, *args, cam)
        c["camera_intrinsics"] = np.asarray(k, dtype=np.float64)
        info["cams"][cam] = c
    at = sd
    while len(info["sweeps"]) < max_sweeps and at["prev"]:
        info["sweeps"].append(sensor2top(nusc, at["prev"], prefix, *args, "lidar"))
        at = nusc.get("sample_data", at["prev"])
    anns = [nusc.get("sample_annotation", t) for t in sample["anns"]]
    velocity = []
    for t in sample["anns"]:
        with np.errstate(all="ignore"):
            v = nusc.box_velocity(t)[:2]
        velocity.append(np.array([*v, 0.0]) @ np.linalg.inv(e2g_r).T @ np.linalg.inv(l2e_r).T)
    names = [NAME_MAPPING.get(b.name, b.name) for b in boxes]
    locs = np.array([b.center for b in boxes]).reshape(-1, 3)
    dims = np.array([b.wlh for b in boxes]).reshape(-1, 3)
    rots = np.array([b.orientation.yaw_pitch_roll[0] for b in boxes]).reshape(-1, 1)
    info["gt_boxes"] = np.concatenate([locs, dims, -rots - np.pi / 2], axis=1)
    info["gt_box_ids"] = [nusc.get("sample_annotation", b.token)["instance_token"] for b in boxes]
    info["gt_names"] = np.array(names)
    info["gt_velocity"] = np.array([v[:2] for v in velocity]).reshape(-1, 2)
    info["num_lidar_pts"] = np.array([a["num_lidar_pts"] for a in anns])
    info["num_radar_pts"] = np.array([a["num_radar_pts"] for a in anns])
    info["visibility"] = np.array([a["visibility_token"] for a in anns], dtype=np.uint8)
    info["valid_flag"] = np.array([a["num_lidar_pts"] + a["num_radar_pts"] > 0 for a in anns], dtype=bool).reshape(-1)
    return info


def same(where, got, want):
    """Equal in structure, type, dtype, shape; values within 1e-6 (NaN where NaN)."""
    if isinstance(want, dict):
        if not isinstance(got, dict) or list(got) != list(want):
            fail(where, f"keys {list(got) if isinstance(got, dict) else type(got)} != {list(want)}")
        for k in want:
            same(f"{where}.{k}", got[k], want[k])
    elif isinstance(want, (list, tuple)):
        if type(got) is not type(want) or len(got) != len(want):
            fail(where, f"{type(got).__name__} of {len(got)} != {type(want).__name__} of {len(want)}")
        for i, (g, w) in enumerate(zip(got, want)):
            same(f"{where}[{i}]", g, w)
    elif isinstance(want, np.ndarray):
        if not isinstance(got, np.ndarray) or got.dtype != want.dtype or got.shape != want.shape:
            fail(where, f"{getattr(got, 'dtype', type(got))} {getattr(got, 'shape', '')} != {want.dtype} {want.shape}")
        if want.dtype.kind == "f":
            if not np.allclose(got, want, rtol=0, atol=1e-6, equal_nan=True):
                fail(where, f"{got} != {want} (max diff {np.nanmax(np.abs(got - want))})")
        elif not (got == want).all():
            fail(where, f"{got} != {want}")
    elif isinstance(want, bool) or isinstance(want, str) or want is None:
        if type(got) is not type(want) or got != want:
            fail(where, f"{got!r} != {want!r}")
    elif isinstance(want, float) or isinstance(want, int):
        # JSON's 0 is an int to json.load and a float in the pickle; timestamps keep their type.
        if where.endswith("timestamp") and type(got) is not type(want):
            fail(where, f"{type(got).__name__} != {type(want).__name__}")
        if not (math.isclose(got, want, rel_tol=1e-12, abs_tol=1e-9) or (math.isnan(got) and math.isnan(want))):
            fail(where, f"{got!r} != {want!r}")
    else:
        fail(where, f"unexpected {type(want)}")


def main():
    dataroot, version, prefix, max_sweeps = sys.argv[1:5]
    files = dict(a.split("=", 1) for a in sys.argv[5:])
    nusc = NuScenes(version=version, dataroot=dataroot, verbose=False)
    lists = {"trainval": ("train", "val"), "mini": ("mini_train", "mini_val"), "test": ("test",)}[version.split("_")[-1].replace("v1.0-", "")]
    official = {split: set(getattr(splits, lst)) for split, lst in zip(("train", "val") if len(lists) == 2 else ("test",), lists)}
    first_split = next(iter(official))
    scene_index = {s["token"]: i for i, s in enumerate(nusc.scene)}
    by_token = {s["token"]: s for s in nusc.sample}
    for split, path in files.items():
        with open(path, "rb") as f:
            data = pickle.load(f)
        want_keys = ["infos", "metadata"] + ([] if split == "test" else ["scene_tokens"])
        if list(data) != want_keys:
            fail(path, f"top-level keys {list(data)} != {want_keys}")
        same(f"{path}:metadata", data["metadata"], {"version": version})

        def split_of(sample):
            name = nusc.get("scene", sample["scene_token"])["name"]
            member = [s for s, names in official.items() if name in names]
            return member[0] if member else first_split

        want_samples = [s for s in nusc.sample if split_of(s) == split]
        got = data["infos"]
        if [i["token"] for i in got] != [s["token"] for s in want_samples]:
            fail(path, f"{len(got)} infos are not the {len(want_samples)} samples of the {split} split in sample.json order")
        for n, (info, sample) in enumerate(zip(got, want_samples)):
            same(f"{path}:infos[{n}]", info, expected_info(nusc, sample, prefix, int(max_sweeps)))
        # scene_tokens: per scene, in the order scenes come in sample.json (and so in nusc.scene
        # order, DiST-4D's scene indices), the scene's whole token chain, kept when > 6 samples.
        if split != "test":
            want_lists = []
            for s in want_samples:
                if not want_lists or by_token[want_lists[-1][-1]]["scene_token"] != s["scene_token"]:
                    want_lists.append([])
                want_lists[-1].append(s["token"])
            want_lists = [l for l in want_lists if len(l) > 6]
            same(f"{path}:scene_tokens", data["scene_tokens"], want_lists)
            order = [scene_index[by_token[l[0]]["scene_token"]] for l in data["scene_tokens"]]
            if order != sorted(order):
                fail(path, f"scenes of scene_tokens are not in the devkit's scene order: {order}")
            for tokens in data["scene_tokens"]:
                scene = nusc.get("scene", by_token[tokens[0]]["scene_token"])
                chain, t = [], scene["first_sample_token"]
                while t:
                    chain.append(t)
                    t = nusc.get("sample", t)["next"]
                if chain != tokens:
                    fail(path, f"scene {scene['name']}: scene_tokens is not its devkit next chain")
        # gt_box_ids: one id per track, the same in every sample the track's annotation chain visits.
        ids = {}
        for info in got:
            sample = by_token[info["token"]]
            for ann_token, box_id in zip(sample["anns"], info["gt_box_ids"]):
                ann = nusc.get("sample_annotation", ann_token)
                ids[ann_token] = box_id
                if ann["prev"] in ids and ids[ann["prev"]] != box_id:
                    fail(path, f"annotation {ann_token}: box id {box_id} differs from its prev's {ids[ann['prev']]}")
        n_boxes = sum(len(i["gt_box_ids"]) for i in got)
        print(f"{path}: {len(got)} infos, {n_boxes} boxes, {len(data.get('scene_tokens', []))} scene lists: equal to the devkit")


main()
