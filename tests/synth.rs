//! End-to-end tests of the synthetic world: `dist4d synth` writes a nuScenes dataset that our
//! reader, the official devkit and the ground truth all agree on.

mod common;

use common::*;
use std::path::{Path, PathBuf};
use std::process::Command;

const SMALL: [&str; 6] = ["--keyframes", "3", "--width", "480", "--height", "270"];
const TINY: [&str; 6] = ["--keyframes", "2", "--width", "160", "--height", "90"];

fn synth(out: &Path, extra: &[&str]) -> std::process::Output {
    synth_with(out, &SMALL, extra)
}

fn synth_with(out: &Path, size: &[&str], extra: &[&str]) -> std::process::Output {
    let mut args = vec!["synth", "--out", out.to_str().unwrap()];
    args.extend(size);
    args.extend(extra);
    dist4d(&args)
}

/// Reads the single float32 channel of an EXR.
fn read_exr(path: &Path) -> (usize, usize, Vec<f32>) {
    use exr::prelude::*;
    let img = read_first_flat_layer_from_file(path).unwrap();
    let FlatSamples::F32(data) = &img.layer_data.channel_data.list[0].sample_data else { panic!("not f32") };
    (img.layer_data.size.0, img.layer_data.size.1, data.clone())
}

fn files_under(dir: &Path) -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(dir).unwrap().map(|e| e.unwrap().path()).collect();
    v.sort();
    v
}

#[test]
fn lidar_depth_runs_on_synthetic_data_and_lidar_agrees_with_ground_truth_depth() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("synth");
    let o = synth(&data, &[]);
    assert!(o.status.success(), "{}", text(&o));
    let (cache, out) = (tmp.path().join("c"), tmp.path().join("o"));
    let o = run_lidar_depth(&data, &cache, &out);
    assert!(o.status.success(), "{}", text(&o));
    assert!(text(&o).contains("54 executed"), "3 frames x 6 cameras x 3 stages: {}", text(&o));

    // Every projected LiDAR point lands on the rendered surface: the LiDAR, the cameras, the
    // calibrations, the ego poses and the ground truth are one consistent world.
    for (cam, gt_dir) in
        ["CAM_FRONT", "CAM_BACK", "CAM_FRONT_LEFT"].iter().map(|c| (c, data.join("groundtruth/depth").join(c)))
    {
        for (frame, gt_file) in files_under(&gt_dir).iter().enumerate() {
            let (w, h, gt) = read_exr(gt_file);
            assert_eq!((w, h), (480, 270));
            let uvz = read_npy_rows(&out.join(format!("synth-0000/{cam}/{frame:03}_uvz.npy")));
            assert!(uvz.len() > 500, "{cam} frame {frame}: only {} points", uvz.len());
            // Ground truth is per pixel centre; a point lies anywhere in its pixel, so compare
            // with the bilinear interpolation of the four nearest centres, relative to depth.
            let at = |x: usize, y: usize| gt[y.min(h - 1) * w + x.min(w - 1)];
            let mut err: Vec<f32> = uvz
                .iter()
                .filter_map(|&[u, v, z]| {
                    let (x, y) = ((u - 0.5).max(0.0), (v - 0.5).max(0.0));
                    let (x0, y0) = (x as usize, y as usize);
                    let (fx, fy) = (x - x0 as f32, y - y0 as f32);
                    let c = [at(x0, y0), at(x0 + 1, y0), at(x0, y0 + 1), at(x0 + 1, y0 + 1)];
                    c.iter().all(|d| d.is_finite()).then(|| {
                        let g = (c[0] * (1.0 - fx) + c[1] * fx) * (1.0 - fy) + (c[2] * (1.0 - fx) + c[3] * fx) * fy;
                        (z - g).abs() / g
                    })
                })
                .collect();
            err.sort_by(f32::total_cmp);
            let (median, p90) = (err[err.len() / 2], err[err.len() * 9 / 10]);
            // Range noise is 2 cm; the tail is object edges and agents that moved between the
            // LiDAR and camera timestamps.
            assert!(median < 0.003, "{cam} frame {frame}: median relative |lidar - gt| = {median}");
            assert!(p90 < 0.01, "{cam} frame {frame}: 90th percentile relative |lidar - gt| = {p90}");
        }
    }
}

#[test]
fn the_same_seed_gives_the_same_bytes_and_another_seed_does_not() {
    let tmp = tempfile::tempdir().unwrap();
    let (a, b, c) = (tmp.path().join("a"), tmp.path().join("b"), tmp.path().join("c"));
    for (dir, seed) in [(&a, "5"), (&b, "5"), (&c, "6")] {
        let o = synth_with(dir, &TINY, &["--seed", seed]);
        assert!(o.status.success(), "{}", text(&o));
    }
    assert_eq!(tree(&a), tree(&b));
    assert_ne!(tree(&a), tree(&c));
    // Asking again for the same dataset is a no-op; another config into it is refused.
    let o = synth_with(&a, &TINY, &["--seed", "5"]);
    assert!(o.status.success() && text(&o).contains("already there"), "{}", text(&o));
    let o = synth_with(&a, &TINY, &["--seed", "7"]);
    assert_eq!(o.status.code(), Some(1));
    assert!(text(&o).contains("other settings"), "{}", text(&o));
    assert_eq!(tree(&a), tree(&b), "a refused synth leaves the folder as it was");
}

#[test]
fn synth_refuses_a_folder_with_other_content_and_touches_nothing() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("mine");
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(dir.join("thesis.tex"), "do not delete").unwrap();
    let o = synth(&dir, &[]);
    assert_eq!(o.status.code(), Some(1));
    assert!(text(&o).contains("not a dist4d synthetic dataset"), "{}", text(&o));
    assert_eq!(std::fs::read_to_string(dir.join("thesis.tex")).unwrap(), "do not delete");
}

#[test]
fn the_dataset_has_sweeps_annotations_lidarseg_and_ground_truth() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("synth");
    let o = synth(&data, &["--camera-sweeps"]);
    assert!(o.status.success(), "{}", text(&o));
    let table = |name: &str| -> Vec<serde_json::Value> {
        serde_json::from_slice(&std::fs::read(data.join(format!("v1.0-mini/{name}.json"))).unwrap()).unwrap()
    };
    let sd = table("sample_data");
    let count = |chan: &str, key: bool| {
        sd.iter().filter(|r| r["filename"].as_str().unwrap().contains(chan) && r["is_key_frame"] == key).count()
    };
    // 3 keyframes 0.5 s apart: LiDAR at 20 Hz (21 sweeps), cameras at 12 Hz (13 images each).
    assert_eq!((count("LIDAR_TOP", true), count("LIDAR_TOP", false)), (3, 18));
    assert_eq!((count("/CAM_BACK/", true), count("/CAM_BACK/", false)), (3, 10));
    for r in &sd {
        assert!(data.join(r["filename"].as_str().unwrap()).is_file(), "{r}");
    }
    // A sweep is 32 beams x 1084 firings of 20 bytes, like the real LIDAR_TOP.
    let lidar = sd.iter().find(|r| r["is_key_frame"] == true && r["fileformat"] == "pcd").unwrap();
    let bytes = std::fs::read(data.join(lidar["filename"].as_str().unwrap())).unwrap();
    assert_eq!(bytes.len(), 32 * 1084 * 20);
    let seg = table("lidarseg");
    assert_eq!(seg.len(), 3);
    let labels = std::fs::read(data.join(seg[0]["filename"].as_str().unwrap())).unwrap();
    assert_eq!(labels.len(), 32 * 1084);
    for class in [17u8, 24, 26, 28, 30] {
        assert!(labels.contains(&class), "lidarseg class {class} missing");
    }
    let anns = table("sample_annotation");
    let cats = table("category");
    let inst = table("instance");
    let cat_of = |ann: &serde_json::Value| {
        let i = inst.iter().find(|i| i["token"] == ann["instance_token"]).unwrap();
        cats.iter().find(|c| c["token"] == i["category_token"]).unwrap()["name"].as_str().unwrap().to_string()
    };
    assert!(anns.iter().any(|a| cat_of(a) == "vehicle.car"));
    assert!(anns.iter().any(|a| cat_of(a) == "human.pedestrian.adult"));
    assert!(anns.iter().any(|a| a["prev"] != "" && a["num_lidar_pts"].as_u64().unwrap() > 0));
    // Ground truth for every camera image, keyframes and sweeps.
    let images = sd.iter().filter(|r| r["fileformat"] == "jpg").count();
    assert_eq!(images, 6 * 13);
    let gt_depth: usize = files_under(&data.join("groundtruth/depth")).iter().map(|d| files_under(d).len()).sum();
    let gt_sem: usize = files_under(&data.join("groundtruth/semantic")).iter().map(|d| files_under(d).len()).sum();
    assert_eq!((gt_depth, gt_sem), (images, images));
    let front = files_under(&data.join("groundtruth/semantic/CAM_FRONT"));
    let sem = image_gray(&front[0]);
    for id in [7u8, 8, 11, 23] {
        assert!(sem.contains(&id), "CAM_FRONT semantics lack Cityscapes id {id}");
    }
    let (_, _, depth) = read_exr(&files_under(&data.join("groundtruth/depth/CAM_FRONT"))[0]);
    assert!(depth.iter().any(|d| d.is_infinite()), "sky is +inf");
    assert!(depth.iter().all(|d| *d > 0.0));
}

fn image_gray(path: &Path) -> Vec<u8> {
    image::open(path).unwrap().into_luma8().into_raw()
}

#[test]
fn the_nuscenes_devkit_loads_synthetic_data_and_projects_like_dist4d() {
    let Some(python) = peers_python() else { return };
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("synth");
    assert!(synth(&data, &[]).status.success());
    let check = r#"
import sys, json, numpy as np
from nuscenes.nuscenes import NuScenes
from nuscenes.utils.data_classes import LidarPointCloud
n = NuScenes(version='v1.0-mini', dataroot=sys.argv[1], verbose=False)
s = n.sample[1]
pc, times = LidarPointCloud.from_file_multisweep(n, s, 'LIDAR_TOP', 'LIDAR_TOP', nsweeps=10)
speeds = {}
for a in s['anns']:
    ann = n.get('sample_annotation', a)
    attr = n.get('attribute', ann['attribute_tokens'][0])['name']
    speeds.setdefault(attr, []).append(float(np.linalg.norm(n.box_velocity(a)[:2])))
print(json.dumps(dict(points=pc.points.shape[1], sweeps=len(set(np.round(times[0], 3))), lidarseg=len(n.lidarseg),
                      speeds={k: [min(v), max(v)] for k, v in speeds.items()})))
"#;
    let o = Command::new(&python).args(["-c", check, data.to_str().unwrap()]).output().unwrap();
    assert!(o.status.success(), "{}", text(&o));
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(v["sweeps"], 10, "{v}");
    assert_eq!(v["lidarseg"], 3);
    // Parked cars stand still; moving cars drive at urban speeds (6-15 m/s by construction).
    let parked = &v["speeds"]["vehicle.parked"];
    assert!(parked[1].as_f64().unwrap() < 1e-6, "{v}");
    let moving = &v["speeds"]["vehicle.moving"];
    assert!(moving[0].as_f64().unwrap() > 5.0 && moving[1].as_f64().unwrap() < 16.0, "{v}");

    // map_pointcloud_to_image agrees with dist4d's projection on every keyframe and camera.
    let (cache, out) = (tmp.path().join("c"), tmp.path().join("o"));
    let o = run_lidar_depth(&data, &cache, &out);
    assert!(o.status.success(), "{}", text(&o));
    let samples: Vec<serde_json::Value> =
        serde_json::from_slice(&std::fs::read(data.join("v1.0-mini/sample.json")).unwrap()).unwrap();
    let checked = check_against_devkit(&python, &data, &tmp.path().join("peer"), |sample, cam| {
        let frame = samples.iter().position(|s| s["token"] == sample).unwrap();
        out.join(format!("synth-0000/{cam}/{frame:03}_uvz.npy"))
    });
    assert_eq!(checked, 18);
}

#[test]
fn demo_synthesizes_once_runs_the_shipped_pipeline_and_says_where_outputs_are() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().join("demo");
    let args = [
        "demo",
        "--dir",
        dir.to_str().unwrap(),
        "--keyframes",
        "2",
        "--width",
        "160",
        "--height",
        "90",
        "--progress",
        "off",
    ];
    let o = dist4d(&args);
    assert!(o.status.success(), "{}", text(&o));
    let t = text(&o);
    assert!(t.contains("232 executed"), "2 frames x 6 cameras x 19 stages + 2 x 2 per-frame stages: {t}");
    assert!(t.contains("gt (raw)"), "the demo prints its scores against ground truth: {t}");
    let sheet = dir.join("pipelines/out/curation/synth-0000/sheets/001.png");
    assert!(t.contains(&sheet.display().to_string()), "{t}");
    assert!(sheet.is_file());
    // Second time: the dataset is reused and everything is cached.
    let o = dist4d(&args);
    let t = text(&o);
    assert!(o.status.success() && t.contains("already there") && t.contains("0 executed, 232 cached"), "{t}");
    // The shipped pipeline, written unchanged beside the data, finds it and its store on its own.
    let written = std::fs::read_to_string(dir.join("pipelines/curation.ron")).unwrap();
    assert_eq!(written, std::fs::read_to_string(repo().join("pipelines/curation.ron")).unwrap());
    let o = dist4d(&["run", dir.join("pipelines/curation.ron").to_str().unwrap(), "--progress", "off"]);
    assert!(o.status.success() && text(&o).contains("0 executed"), "{}", text(&o));
}

#[test]
fn the_renderer_reproduces_the_ground_truth_from_synth_json_for_any_pose() {
    use dist4d_synth::{PinholeCamera, Renderer};
    use dist4d_types::geometry::Se3;
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("synth");
    assert!(synth_with(&data, &TINY, &[]).status.success());
    let table = |name: &str| -> Vec<serde_json::Value> {
        serde_json::from_slice(&std::fs::read(data.join(format!("v1.0-mini/{name}.json"))).unwrap()).unwrap()
    };
    let (sds, poses, calibs) = (table("sample_data"), table("ego_pose"), table("calibrated_sensor"));
    let sd = sds.iter().find(|r| r["filename"].as_str().unwrap().contains("/CAM_FRONT_LEFT/")).unwrap();
    let find = |rows: &[serde_json::Value], token: &serde_json::Value| {
        rows.iter().find(|r| r["token"] == *token).unwrap().clone()
    };
    let (pose, cs) = (find(&poses, &sd["ego_pose_token"]), find(&calibs, &sd["calibrated_sensor_token"]));
    let se3 = |r: &serde_json::Value| {
        let q: Vec<f64> = r["rotation"].as_array().unwrap().iter().map(|x| x.as_f64().unwrap()).collect();
        let t: Vec<f64> = r["translation"].as_array().unwrap().iter().map(|x| x.as_f64().unwrap()).collect();
        Se3::from_wxyz_t([q[0], q[1], q[2], q[3]], [t[0], t[1], t[2]])
    };
    let k: Vec<Vec<f64>> = serde_json::from_value(cs["camera_intrinsic"].clone()).unwrap();
    let camera = PinholeCamera {
        k: [[k[0][0], k[0][1], k[0][2]], [k[1][0], k[1][1], k[1][2]], [k[2][0], k[2][1], k[2][2]]],
        width: 160,
        height: 90,
        camera_to_world: se3(&pose).then_from(&se3(&cs)),
    };
    let renderer = Renderer::open(&data).unwrap();
    let ts = sd["timestamp"].as_i64().unwrap();
    let image = renderer.render_at_timestamp(0, ts, &camera).unwrap();
    let stem = Path::new(sd["filename"].as_str().unwrap()).file_stem().unwrap().to_string_lossy().to_string();
    let (_, _, gt) = read_exr(&data.join(format!("groundtruth/depth/CAM_FRONT_LEFT/{stem}.exr")));
    assert_eq!(image.depth, gt, "the renderer rebuilt from synth.json gives the written ground truth exactly");
    // A novel view: 2 m to the left of that camera, half a second later, still a full image.
    // (Camera x points right, so -2 m along it is 2 m to the left.)
    let left = Se3::from_yaw(0.0, glam::DVec3::new(-2.0, 0.0, 0.0));
    let shifted = PinholeCamera { camera_to_world: camera.camera_to_world.then_from(&left), ..camera };
    let novel = renderer.render_at_timestamp(0, ts + 500_000, &shifted).unwrap();
    assert_eq!(novel.depth.len(), 160 * 90);
    assert_ne!(novel.depth, image.depth);
    assert!(novel.depth.iter().all(|d| *d > 0.0));
}
