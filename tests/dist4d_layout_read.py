"""Reads a DiST-4D depth export the way DiST-4D's loaders find it, with numpy alone.

Usage: dist4d_layout_read.py RDEPTH_ROOT INFOS_PKL SKY_ID

For every info of the pickle (the samples a DiST-4D dataset iterates) and every camera of it:
token -> nus_sampletoken2depthroot.json -> relative root -> <CAMERA>/refined_depth.npz and
semantic_oneformer.npz, joined as the loaders join them (the root with a trailing slash, then
the value, by string concatenation). Checks `depth_pred` (float32 H x W) equals dist4d's own
`depth.npy` beside it, `sem` is uint8 of the same shape, and the loaders' sky rule
(depth[sem == SKY] = 100) changes nothing: sky already is at 100 m.
"""
import json
import pickle
import sys

import numpy as np

root, pkl, sky = sys.argv[1], sys.argv[2], int(sys.argv[3])
root = root.rstrip("/") + "/"
with open(root + "nus_sampletoken2depthroot.json") as f:
    token2root = json.load(f)
with open(pkl, "rb") as f:
    infos = pickle.load(f)["infos"]
files = sky_pixels = 0
for info in infos:
    rel = token2root[info["token"]]
    for cam in info["cams"]:
        folder = root + rel + "/" + cam + "/"
        depth = np.load(folder + "refined_depth.npz")["depth_pred"]
        sem = np.load(folder + "semantic_oneformer.npz")["sem"]
        ours = np.load(folder + "depth.npy")
        assert depth.dtype == np.float32 and depth.ndim == 2, (folder, depth.dtype, depth.shape)
        assert np.array_equal(depth, ours), folder
        assert sem.dtype == np.uint8 and sem.shape == depth.shape, (folder, sem.dtype, sem.shape)
        ruled = depth.copy()
        ruled[sem == sky] = 100.0
        assert np.array_equal(ruled, depth), f"{folder}: sky pixels not at 100 m"
        files += 1
        sky_pixels += int((sem == sky).sum())
assert len(token2root) >= len(infos)
print(f"{len(infos)} samples, {files} cameras read through {root}nus_sampletoken2depthroot.json; {sky_pixels} sky pixels (sem == {sky}) at 100 m")
