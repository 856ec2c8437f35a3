//! Reads every camera item's image, calibration, pose and boxes and every frame's LiDAR sweep and
//! boxes of a dataset, and prints the time per image: what `bench/py123d_read.py` compares
//! between the nuScenes reader and a py123d log of the same scene.
//!
//!     cargo run --release -p dist4d-datasets --example read_sources -- nuscenes ROOT
//!     cargo run --release -p dist4d-datasets --example read_sources -- py123d LOGS [SENSOR_ROOT]

use dist4d_datasets::nuscenes::{NuScenes, NuScenesConfig};
use dist4d_datasets::py123d::{Py123d, Py123dConfig};
use dist4d_datasets::surround::Surround;
use dist4d_runtime::{Dataset, ItemKey};

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let (kind, root) = (args.get(1).map(String::as_str).unwrap_or(""), args.get(2).cloned().unwrap_or_default());
    let start = std::time::Instant::now();
    let ds: Box<dyn Dataset> = match kind {
        "nuscenes" => Box::new(Surround(NuScenes::open(NuScenesConfig { root, ..Default::default() })?)),
        "py123d" => Box::new(Surround(Py123d::open(Py123dConfig {
            root,
            sensor_root: args.get(3).cloned(),
            ..Default::default()
        })?)),
        _ => anyhow::bail!("usage: read_sources nuscenes|py123d ROOT [SENSOR_ROOT]"),
    };
    let opened = start.elapsed().as_secs_f64();
    let (mut images, mut bytes) = (0usize, 0usize);
    for s in 0..ds.count(&ItemKey::new(&[])) {
        for f in 0..ds.count(&ItemKey::new(&[s])) {
            let frame = ItemKey::new(&[s, f]);
            for port in ["lidar", "boxes", "lidar_pose"] {
                bytes += ds.load_source(port, &frame)?.len();
            }
            for c in 0..ds.count(&frame) {
                let item = ItemKey::new(&[s, f, c]);
                for port in ["image", "camera_calib", "camera_pose", "camera_boxes"] {
                    bytes += ds.load_source(port, &item)?.len();
                }
                images += 1;
            }
        }
    }
    let total = start.elapsed().as_secs_f64();
    println!(
        "{kind}: opened in {:.1} ms; {images} images with their sweeps and boxes in {:.1} ms: {:.2} ms per image ({bytes} bytes)",
        opened * 1e3,
        (total - opened) * 1e3,
        (total - opened) * 1e3 / images.max(1) as f64
    );
    Ok(())
}
