//! What the readers' tests share.

use dist4d_runtime::{Dataset, ItemKey};
use std::path::{Path, PathBuf};

/// `shared/data/<name>` beside the repository, or `None` (with a note) when it is absent.
pub fn shared_data(name: &str) -> Option<PathBuf> {
    let p = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/data").join(name);
    if p.is_dir() {
        Some(p)
    } else {
        eprintln!("SKIPPED: shared data not found at {}", p.display());
        None
    }
}

/// The error chain of loading `port` of `item`; panics when it loads.
pub fn load_err(ds: &dyn Dataset, port: &str, item: &[u32]) -> String {
    format!("{:#}", ds.load_source(port, &ItemKey::new(item)).err().unwrap_or_else(|| panic!("{port} {item:?} loads")))
}

/// A small synthetic nuScenes dataset with 12 Hz camera sweeps and its exact boxes.
pub fn with_camera_sweeps(keyframes: u32) -> (tempfile::TempDir, PathBuf) {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("synth");
    let config =
        dist4d_synth::SynthConfig { keyframes, width: 96, height: 54, camera_sweeps: true, ..Default::default() };
    dist4d_synth::write_dataset(&config, &root, &|_| {}).unwrap();
    (dir, root)
}
