"""Loads info pickles with mmengine.load (what MagicDriveDiT's and DiST-4D's datasets call) and
with plain pickle.load, warnings as errors, and checks that both give the same values.

Usage: infos_load.py PKL [PKL ...]
"""
import pickle
import sys
import warnings

import mmengine
import numpy as np

warnings.simplefilter("error")


def same(where, a, b):
    if type(a) is not type(b):
        sys.exit(f"{where}: {type(a)} != {type(b)}")
    if isinstance(a, dict):
        if list(a) != list(b):
            sys.exit(f"{where}: keys differ")
        for k in a:
            same(f"{where}.{k}", a[k], b[k])
    elif isinstance(a, (list, tuple)):
        if len(a) != len(b):
            sys.exit(f"{where}: lengths differ")
        for i, (x, y) in enumerate(zip(a, b)):
            same(f"{where}[{i}]", x, y)
    elif isinstance(a, np.ndarray):
        if a.dtype != b.dtype or a.shape != b.shape or not np.array_equal(a, b, equal_nan=a.dtype.kind == "f"):
            sys.exit(f"{where}: arrays differ")
        if not (a.flags.c_contiguous and a.flags.writeable):
            sys.exit(f"{where}: not a C-contiguous writeable array")
    elif a != b and not (isinstance(a, float) and a != a and b != b):
        sys.exit(f"{where}: {a!r} != {b!r}")


for path in sys.argv[1:]:
    data = mmengine.load(path)
    with open(path, "rb") as f:
        same(path, data, pickle.load(f))
    infos = data["infos"]
    if infos and not isinstance(infos[0]["gt_boxes"], np.ndarray):
        sys.exit(f"{path}: gt_boxes is not an array")
    print(f"{path}: mmengine {mmengine.__version__} (numpy {np.__version__}) loads {len(infos)} infos")
