//! The files dist4d writes open with the tools its users have: depth EXRs (curated and synthetic
//! ground truth) read with OpenCV (`cv2.imread(path, IMREAD_UNCHANGED)`) and with the OpenEXR
//! Python bindings give the values of the NPY written beside them. Needs the peer venv (skips
//! with a message without it; CI has it).

mod common;

use common::*;
use std::process::Command;

const CHECK: &str = r#"
import glob, os, sys, numpy as np, cv2, OpenEXR
out, data = sys.argv[1], sys.argv[2]
def both(path):
    a = cv2.imread(path, cv2.IMREAD_UNCHANGED)
    with OpenEXR.File(path) as f:
        channels = f.channels()
        assert list(channels) == ["Y"], (path, list(channels))
        b = channels["Y"].pixels
    assert a is not None and a.dtype == np.float32 and a.shape == b.shape, (path, None if a is None else a.shape)
    return a, b
curated = sorted(glob.glob(os.path.join(out, "*", "*", "*_depth.exr")))
assert curated, out
for path in curated:
    a, b = both(path)
    npy = np.load(path.replace("_depth.exr", "_depth.npy"))
    assert np.array_equal(a, npy) and np.array_equal(b, npy), path
    assert (npy > 0).mean() > 0.5, path
truth = sorted(glob.glob(os.path.join(data, "groundtruth", "depth", "*", "*.exr")))
assert truth, data
for path in truth:
    a, b = both(path)
    assert np.array_equal(a, b), path
    finite = np.isfinite(a)
    assert finite.mean() > 0.3 and (a[finite] > 0).all(), path
print(len(curated), len(truth))
"#;

#[test]
fn depth_exrs_read_the_same_in_opencv_the_openexr_bindings_and_numpy() {
    let Some(python) = peers_python() else { return };
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    let o =
        dist4d(&["synth", "--out", data.to_str().unwrap(), "--keyframes", "2", "--width", "320", "--height", "180"]);
    assert!(o.status.success(), "{}", text(&o));
    let out = tmp.path().join("out");
    let o = dist4d(&[
        "run",
        repo().join("pipelines/curation.ron").to_str().unwrap(),
        "--progress",
        "off",
        "--cache",
        tmp.path().join("cache").to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--set",
        &format!("dataset.root={}", data.display()),
    ]);
    assert!(o.status.success(), "{}", text(&o));
    let o = Command::new(python)
        .env("OPENCV_IO_ENABLE_OPENEXR", "1")
        .args(["-c", CHECK, out.to_str().unwrap(), data.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", text(&o));
    assert_eq!(String::from_utf8_lossy(&o.stdout).trim(), "12 12", "{}", text(&o));
}
