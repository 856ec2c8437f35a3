//! Writes a synthetic world as a nuScenes v1.0 dataset: the 13 tables plus `lidarseg`, keyframe
//! and sweep files under `samples/` and `sweeps/`, lidarseg labels, map masks, and the ground
//! truth sidecar under `groundtruth/`.
//!
//! The dataset is written into a hidden sibling folder and renamed into place at the end, so a
//! killed run never leaves something that looks like a finished dataset.

use super::render::{PinholeCamera, Snapshot};
use super::{SynthConfig, CAMERA_RIG, GENERATOR_VERSION, GROUND_TRUTH_DIR, LIDAR_TOP};
use crate::material::class;
use crate::world::{AgentKind, World, ROAD_HALF_WIDTH};
use anyhow::{bail, Context, Result};
use dist4d_types::artifact::DepthMap;
use dist4d_types::formats::depth_exr;
use dist4d_types::geometry::Se3;
use glam::DVec3;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use serde_json::{json, Value};
use std::collections::HashMap;
use std::path::Path;

/// The record of how a synthetic dataset was made (`groundtruth/synth.json`).
#[derive(Serialize, Deserialize)]
pub(super) struct SynthFile {
    pub generator_version: u32,
    pub config: SynthConfig,
}

const KEYFRAME_US: i64 = 500_000;
const LIDAR_US: i64 = 50_000;
const CAMERA_SWEEPS_PER_KEYFRAME: i64 = 6; // 12 Hz
const ANNOTATION_RANGE: f64 = 60.0;
const MAP_RESOLUTION: f64 = 0.1;

/// 2025-01-01 00:00 UTC, when the first synthetic scene starts.
const EPOCH_US: i64 = 1_735_689_600_000_000;

/// First timestamp of scene `i` (2025-01-01 00:00 UTC plus an hour per scene).
pub fn scene_start_us(scene: u32) -> i64 {
    EPOCH_US + scene as i64 * 3_600_000_000
}

/// The nuScenes-lidarseg classes, by index.
const LIDARSEG_CATEGORIES: [&str; 32] = [
    "noise",
    "animal",
    "human.pedestrian.adult",
    "human.pedestrian.child",
    "human.pedestrian.construction_worker",
    "human.pedestrian.personal_mobility",
    "human.pedestrian.police_officer",
    "human.pedestrian.stroller",
    "human.pedestrian.wheelchair",
    "movable_object.barrier",
    "movable_object.debris",
    "movable_object.pushable_pullable",
    "movable_object.trafficcone",
    "static_object.bicycle_rack",
    "vehicle.bicycle",
    "vehicle.bus.bendy",
    "vehicle.bus.rigid",
    "vehicle.car",
    "vehicle.construction",
    "vehicle.emergency.ambulance",
    "vehicle.emergency.police",
    "vehicle.motorcycle",
    "vehicle.trailer",
    "vehicle.truck",
    "flat.driveable_surface",
    "flat.other",
    "flat.sidewalk",
    "flat.terrain",
    "static.manmade",
    "static.other",
    "static.vegetation",
    "vehicle.ego",
];

const ATTRIBUTES: [&str; 8] = [
    "vehicle.moving",
    "vehicle.stopped",
    "vehicle.parked",
    "cycle.with_rider",
    "cycle.without_rider",
    "pedestrian.sitting_lying_down",
    "pedestrian.standing",
    "pedestrian.moving",
];

/// Cityscapes id (what the renderer labels) -> nuScenes-lidarseg index.
pub fn lidarseg_index(cityscapes: u8) -> u8 {
    match cityscapes {
        class::ROAD => 24,
        class::SIDEWALK => 26,
        class::TERRAIN => 27,
        class::BUILDING | class::POLE => 28,
        class::VEGETATION => 30,
        class::PERSON => 2,
        class::CAR => 17,
        class::EGO => 31,
        _ => 0,
    }
}

/// A 32-hex-digit token, stable for a seed and a name.
fn token(seed: u64, what: &str) -> String {
    let h = blake3::hash(format!("{seed}/{what}").as_bytes());
    h.to_hex()[..32].to_string()
}

fn global_token(what: &str) -> String {
    token(0, what)
}

/// What `write_dataset` made.
#[derive(Debug, Default)]
pub struct Summary {
    pub scenes: usize,
    pub samples: usize,
    pub lidar_sweeps: usize,
    pub camera_images: usize,
    pub annotations: usize,
    pub seconds: f64,
}

/// Tables being built for the whole dataset.
#[derive(Default)]
struct Tables {
    rows: HashMap<&'static str, Vec<Value>>,
}

impl Tables {
    fn push(&mut self, table: &'static str, row: Value) {
        self.rows.entry(table).or_default().push(row);
    }
}

/// Writes the dataset of `config` to `root`. If `root` already holds the dataset of the same
/// config, nothing is done; if it holds anything else, that is an error (nothing is overwritten).
/// Whether `record` (a dataset's `synth.json`) says it holds the world of `config`.
fn same_world(record: &Path, config: &SynthConfig) -> bool {
    std::fs::read_to_string(record)
        .ok()
        .and_then(|text| serde_json::from_str::<SynthFile>(&text).ok())
        .is_some_and(|file| file.generator_version == GENERATOR_VERSION && &file.config == config)
}

pub fn write_dataset(config: &SynthConfig, root: &Path, log: &(dyn Fn(&str) + Sync)) -> Result<Option<Summary>> {
    let record = root.join(GROUND_TRUTH_DIR).join("synth.json");
    if root.exists() {
        if let Ok(text) = std::fs::read_to_string(&record) {
            if let Ok(file) = serde_json::from_str::<SynthFile>(&text) {
                if file.generator_version == GENERATOR_VERSION && &file.config == config {
                    return Ok(None);
                }
                bail!(
                    "{} holds a synthetic dataset made with other settings (see {}); delete it or choose another folder",
                    root.display(),
                    record.display()
                );
            }
        }
        if std::fs::read_dir(root).map(|mut d| d.next().is_some()).unwrap_or(true) {
            bail!("{} exists and is not a dist4d synthetic dataset; choose another folder", root.display());
        }
    }
    anyhow::ensure!(
        config.width >= 16 && config.height >= 16,
        "image size {}x{} is too small",
        config.width,
        config.height
    );
    anyhow::ensure!(config.keyframes >= 1 && config.scenes >= 1, "need at least one scene and one keyframe");
    let start = std::time::Instant::now();
    let name = root.file_name().context("the output folder needs a name")?.to_string_lossy().to_string();
    // One partial folder per process: two processes that open the same `Synth(..)` dataset at
    // once (a Slurm array's tasks) each write their own, and the second rename finds the world
    // in place. A dead process's leftover is removed.
    let prefix = format!(".{name}.partial-");
    if let Some(parent) = root.parent().filter(|p| p.is_dir()) {
        for leftover in std::fs::read_dir(parent)?.flatten() {
            let file_name = leftover.file_name();
            let Some(pid) = file_name.to_str().and_then(|n| n.strip_prefix(&prefix)) else { continue };
            if !Path::new("/proc").join(pid).exists() {
                let _ = std::fs::remove_dir_all(leftover.path());
            }
        }
    }
    let partial = root.with_file_name(format!("{prefix}{}", std::process::id()));
    if partial.exists() {
        std::fs::remove_dir_all(&partial).with_context(|| format!("removing the leftover {}", partial.display()))?;
    }
    std::fs::create_dir_all(&partial).with_context(|| format!("creating {}", partial.display()))?;

    let mut tables = Tables::default();
    global_tables(&mut tables);
    let mut summary = Summary::default();
    for scene in 0..config.scenes {
        log(&format!("scene {} of {}", scene + 1, config.scenes));
        write_scene(config, scene, &partial, &mut tables, &mut summary)
            .with_context(|| format!("synthesizing scene {scene}"))?;
    }
    let version_dir = partial.join("v1.0-mini");
    std::fs::create_dir_all(&version_dir)?;
    for (table, rows) in &tables.rows {
        let path = version_dir.join(format!("{table}.json"));
        std::fs::write(&path, serde_json::to_vec_pretty(rows)?)
            .with_context(|| format!("writing {}", path.display()))?;
    }
    let gt = partial.join(GROUND_TRUTH_DIR);
    std::fs::create_dir_all(&gt)?;
    let file = SynthFile { generator_version: GENERATOR_VERSION, config: config.clone() };
    std::fs::write(gt.join("synth.json"), serde_json::to_vec_pretty(&file)?)?;
    std::fs::write(gt.join("README.md"), GROUND_TRUTH_README)?;
    if root.exists() {
        std::fs::remove_dir(root).with_context(|| format!("replacing the empty folder {}", root.display()))?;
    }
    if let Some(parent) = root.parent() {
        std::fs::create_dir_all(parent)?;
    }
    if let Err(e) = std::fs::rename(&partial, root) {
        let _ = std::fs::remove_dir_all(&partial);
        // Another process made it meanwhile: the same world is there, or the error says why not.
        if same_world(&record, config) {
            return Ok(None);
        }
        return Err(e).with_context(|| format!("moving {} to {}", partial.display(), root.display()));
    }
    summary.scenes = config.scenes as usize;
    summary.seconds = start.elapsed().as_secs_f64();
    Ok(Some(summary))
}

const GROUND_TRUTH_README: &str = "\
# Ground truth of a dist4d synthetic dataset

- `depth/<CHANNEL>/<image name>.exr`: dense metric depth of every camera image, OpenEXR, one
  float32 channel `Y` (the name OpenCV reads): distance along the optical axis in metres (what the nuScenes devkit calls
  depth). Sky (no surface within 1000 m) is +inf. Pixel (col, row) is the ray through image point
  (col + 0.5, row + 0.5).
- `semantic/<CHANNEL>/<image name>.png`: 8-bit Cityscapes ids: road 7, sidewalk 8, building 11,
  pole 17, vegetation 21, terrain 22, sky 23, person 24, car 26.
- `boxes/<CHANNEL>/<image name>.json`: the exact box of every annotated agent at that image's own
  timestamp: `{\"timestamp_us\", \"boxes\": [{\"instance_token\", \"category\", \"translation\", \"size\",
  \"rotation\", \"velocity\"}]}` (world frame, nuScenes conventions: size w, l, h; rotation w, x, y, z),
  what boxes interpolated between keyframes are scored against.
- `synth.json`: the generator version and settings. `dist4d_stages::synth::Renderer::open(root)`
  rebuilds the world from it and renders exact RGB, depth and semantics for any camera pose at any
  timestamp.
";

fn global_tables(t: &mut Tables) {
    for (i, name) in LIDARSEG_CATEGORIES.iter().enumerate() {
        t.push(
            "category",
            json!({"token": global_token(&format!("category/{name}")), "name": name, "description": "", "index": i}),
        );
    }
    for name in ATTRIBUTES {
        t.push(
            "attribute",
            json!({"token": global_token(&format!("attribute/{name}")), "name": name, "description": ""}),
        );
    }
    for (i, level) in ["v0-40", "v40-60", "v60-80", "v80-100"].iter().enumerate() {
        t.push(
            "visibility",
            json!({"token": (i + 1).to_string(), "level": level,
                   "description": format!("visibility of whole object is between {level}% in the six images")}),
        );
    }
    for s in CAMERA_RIG.iter().chain([&LIDAR_TOP]) {
        let modality = if s.channel.starts_with("CAM") { "camera" } else { "lidar" };
        t.push("sensor", json!({"token": global_token(&format!("sensor/{}", s.channel)), "channel": s.channel, "modality": modality}));
    }
    for name in [
        "sample",
        "sample_data",
        "ego_pose",
        "calibrated_sensor",
        "instance",
        "sample_annotation",
        "scene",
        "log",
        "map",
        "lidarseg",
    ] {
        t.rows.entry(name).or_default();
    }
}

/// One sensor reading to produce.
struct Reading {
    token: String,
    channel: &'static str,
    timestamp: i64,
    key: bool,
    /// Keyframe index this reading's `sample_token` names (the next keyframe for sweeps).
    sample: usize,
    filename: String,
}

fn camera_offset_us(rig: &super::RigSensor) -> i64 {
    // Cameras fire as the LiDAR sweeps across their field of view: offset by the camera's yaw.
    let axis = rig.sensor_to_ego().rotation * DVec3::Z;
    let frac = (axis.y.atan2(axis.x) / std::f64::consts::TAU).rem_euclid(1.0);
    (frac * LIDAR_US as f64).round() as i64
}

fn write_scene(config: &SynthConfig, scene: u32, root: &Path, t: &mut Tables, summary: &mut Summary) -> Result<()> {
    let seed = config.scene_seed(scene);
    let world = config.world(scene);
    let t0 = scene_start_us(scene);
    let k = config.keyframes as i64;
    let hour = t0.div_euclid(3_600_000_000).rem_euclid(24);
    let logfile = format!("n000-{}-{hour:02}-00-00+0000", date_of(t0));
    let tok = |what: &str| token(seed, what);

    // Readings: LiDAR at 20 Hz, cameras at 12 Hz, both from keyframe 0 to keyframe K-1.
    let mut lidar = Vec::new();
    let lidar_every = if config.lidar_sweeps { 1 } else { KEYFRAME_US / LIDAR_US };
    let mut n = 0;
    while n * LIDAR_US <= (k - 1) * KEYFRAME_US {
        let ts = t0 + n * LIDAR_US;
        let key = (n * LIDAR_US) % KEYFRAME_US == 0;
        let folder = if key { "samples" } else { "sweeps" };
        lidar.push(Reading {
            token: tok(&format!("sd/LIDAR_TOP/{n}")),
            channel: "LIDAR_TOP",
            timestamp: ts,
            key,
            sample: ((n * LIDAR_US + KEYFRAME_US - 1) / KEYFRAME_US) as usize,
            filename: format!("{folder}/LIDAR_TOP/{logfile}__LIDAR_TOP__{ts}.pcd.bin"),
        });
        n += lidar_every;
    }
    let mut cameras: Vec<Vec<Reading>> = Vec::new();
    for rig in &CAMERA_RIG {
        let off = camera_offset_us(rig);
        let mut v = Vec::new();
        for kf in 0..k {
            let sweeps = if config.camera_sweeps && kf + 1 < k { CAMERA_SWEEPS_PER_KEYFRAME } else { 1 };
            for j in 0..sweeps {
                let ts = t0 + kf * KEYFRAME_US + (j * KEYFRAME_US) / CAMERA_SWEEPS_PER_KEYFRAME + off;
                let key = j == 0;
                let folder = if key { "samples" } else { "sweeps" };
                v.push(Reading {
                    token: tok(&format!("sd/{}/{kf}/{j}", rig.channel)),
                    channel: rig.channel,
                    timestamp: ts,
                    key,
                    sample: (kf + (j > 0) as i64) as usize,
                    filename: format!("{folder}/{0}/{logfile}__{0}__{ts}.jpg", rig.channel),
                });
            }
        }
        cameras.push(v);
    }
    for r in lidar.iter().chain(cameras.iter().flatten()) {
        let dir = root.join(&r.filename);
        std::fs::create_dir_all(dir.parent().unwrap_or(root))?;
    }

    let secs = |ts: i64| (ts - t0) as f64 * 1e-6;
    let ego = |ts: i64| {
        let (p, yaw) = world.ego_pose(secs(ts));
        Se3::from_yaw(yaw, p)
    };
    let lidar_to_ego = LIDAR_TOP.sensor_to_ego();

    // LiDAR sweeps (the keyframes' class/instance labels are kept for lidarseg and box counts).
    let keyframe_labels: Vec<Option<(Vec<u8>, Vec<u32>)>> = lidar
        .par_iter()
        .enumerate()
        .map(|(i, r)| -> Result<Option<(Vec<u8>, Vec<u32>)>> {
            let snap = Snapshot::new(&world, secs(r.timestamp));
            let sensor_to_world = ego(r.timestamp).then_from(&lidar_to_ego);
            let sweep = snap.scan(&config.lidar, &sensor_to_world, &lidar_to_ego, seed ^ ((i as u64) << 20));
            let mut bytes = Vec::with_capacity(sweep.points.len() * 20);
            for p in &sweep.points {
                for x in p {
                    bytes.extend_from_slice(&x.to_le_bytes());
                }
            }
            let path = root.join(&r.filename);
            std::fs::write(&path, bytes).with_context(|| format!("writing {}", path.display()))?;
            Ok(r.key.then_some((sweep.class, sweep.instance)))
        })
        .collect::<Result<_>>()?;
    let keyframe_labels: Vec<(Vec<u8>, Vec<u32>)> = keyframe_labels.into_iter().flatten().collect();

    // The exact semantic occupancy of every keyframe, in Occ3D-nuScenes' grid and files, with
    // the visibility masks cast as dist4d's occupancy stages cast them.
    if config.ground_truth {
        let scene_name = format!("synth-{scene:04}");
        lidar.par_iter().filter(|r| r.key).try_for_each(|r| -> Result<()> {
            let labels_npz = exact_occupancy(config, &world, r, &cameras, &ego, secs(r.timestamp), root)?;
            let dir = root
                .join(GROUND_TRUTH_DIR)
                .join("occupancy/gts")
                .join(&scene_name)
                .join(tok(&format!("sample/{}", r.sample)));
            std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
            let path = dir.join("labels.npz");
            std::fs::write(&path, labels_npz).with_context(|| format!("writing {}", path.display()))
        })?;
    }

    // Camera images with their ground truth.
    let gt = root.join(GROUND_TRUTH_DIR);
    let jobs: Vec<(usize, &Reading)> =
        cameras.iter().enumerate().flat_map(|(c, v)| v.iter().map(move |r| (c, r))).collect();
    jobs.par_iter().try_for_each(|&(c, r)| -> Result<()> {
        let cam = pinhole(config, c, &ego(r.timestamp));
        let image = Snapshot::new(&world, secs(r.timestamp)).render(&cam);
        let path = root.join(&r.filename);
        let mut jpeg = Vec::new();
        image::codecs::jpeg::JpegEncoder::new_with_quality(&mut jpeg, config.jpeg_quality)
            .encode(&image.rgb, image.width, image.height, image::ExtendedColorType::Rgb8)
            .context("encoding JPEG")?;
        std::fs::write(&path, jpeg).with_context(|| format!("writing {}", path.display()))?;
        if config.ground_truth {
            let stem = Path::new(&r.filename).file_stem().map(|s| s.to_string_lossy().to_string()).unwrap_or_default();
            let dir = gt.join("depth").join(r.channel);
            std::fs::create_dir_all(&dir)?;
            let depth = DepthMap { width: image.width, height: image.height, data: image.depth };
            std::fs::write(dir.join(format!("{stem}.exr")), depth_exr(&depth)?)?;
            let dir = gt.join("semantic").join(r.channel);
            std::fs::create_dir_all(&dir)?;
            std::fs::write(
                dir.join(format!("{stem}.png")),
                fast_png_gray(&image.semantic, image.width, image.height)?,
            )?;
        }
        Ok(())
    })?;

    // Tables.
    let scene_token = tok("scene");
    let log_token = tok("log");
    let sample_tokens: Vec<String> = (0..k).map(|i| tok(&format!("sample/{i}"))).collect();
    for i in 0..k as usize {
        t.push(
            "sample",
            json!({
                "token": sample_tokens[i],
                "timestamp": t0 + i as i64 * KEYFRAME_US,
                "prev": if i > 0 { sample_tokens[i - 1].clone() } else { String::new() },
                "next": sample_tokens.get(i + 1).cloned().unwrap_or_default(),
                "scene_token": scene_token,
            }),
        );
    }
    t.push(
        "scene",
        json!({
            "token": scene_token,
            "log_token": log_token,
            "nbr_samples": k,
            "first_sample_token": sample_tokens[0],
            "last_sample_token": sample_tokens[k as usize - 1],
            "name": format!("synth-{scene:04}"),
            "description": format!("dist4d synthetic street, seed {}, scene {scene}", config.seed),
        }),
    );
    t.push(
        "log",
        json!({"token": log_token, "logfile": logfile, "vehicle": "synth",
               "date_captured": date_of(t0), "location": "dist4d-synthetic"}),
    );
    for s in CAMERA_RIG.iter().chain([&LIDAR_TOP]) {
        let intrinsic: Value = if s.focal > 0.0 { json!(s.intrinsics(config.width, config.height)) } else { json!([]) };
        t.push(
            "calibrated_sensor",
            json!({
                "token": tok(&format!("cs/{}", s.channel)),
                "sensor_token": global_token(&format!("sensor/{}", s.channel)),
                "translation": s.translation,
                "rotation": s.rotation,
                "camera_intrinsic": intrinsic,
            }),
        );
    }
    let mut push_chain = |readings: &[Reading], is_camera: bool| {
        for (i, r) in readings.iter().enumerate() {
            let pose = ego(r.timestamp);
            let pose_token = tok(&format!("ego/{}/{}", r.channel, r.timestamp));
            t.push(
                "ego_pose",
                json!({"token": pose_token, "timestamp": r.timestamp,
                       "rotation": pose.wxyz(), "translation": pose.translation.to_array()}),
            );
            let (w, h) = if is_camera { (config.width, config.height) } else { (0, 0) };
            t.push(
                "sample_data",
                json!({
                    "token": r.token,
                    "sample_token": sample_tokens[r.sample.min(k as usize - 1)],
                    "ego_pose_token": pose_token,
                    "calibrated_sensor_token": tok(&format!("cs/{}", r.channel)),
                    "timestamp": r.timestamp,
                    "fileformat": if is_camera { "jpg" } else { "pcd" },
                    "is_key_frame": r.key,
                    "height": h,
                    "width": w,
                    "filename": r.filename,
                    "prev": if i > 0 { readings[i - 1].token.clone() } else { String::new() },
                    "next": readings.get(i + 1).map(|r| r.token.clone()).unwrap_or_default(),
                }),
            );
        }
    };
    push_chain(&lidar, false);
    for v in &cameras {
        push_chain(v, true);
    }

    // lidarseg labels of the keyframes.
    let seg_dir = root.join("lidarseg").join("v1.0-mini");
    std::fs::create_dir_all(&seg_dir)?;
    let key_lidar: Vec<&Reading> = lidar.iter().filter(|r| r.key).collect();
    for (r, (classes, _)) in key_lidar.iter().zip(&keyframe_labels) {
        let labels: Vec<u8> = classes.iter().map(|&c| lidarseg_index(c)).collect();
        let filename = format!("lidarseg/v1.0-mini/{}_lidarseg.bin", r.token);
        std::fs::write(root.join(&filename), labels)?;
        t.push("lidarseg", json!({"token": r.token, "sample_data_token": r.token, "filename": filename}));
    }

    // Annotations: every car and pedestrian within range of the ego at a keyframe, as one
    // contiguous track per agent.
    let key_cams: Vec<Vec<&Reading>> = cameras.iter().map(|v| v.iter().filter(|r| r.key).collect()).collect();
    // One frozen world per keyframe, shared by every box's visibility rays.
    let key_snapshots: Vec<Snapshot> = (0..k).map(|kf| Snapshot::new(&world, secs(t0 + kf * KEYFRAME_US))).collect();
    // The annotated agents, with their instance token and category (for the exact boxes below).
    let mut annotated = Vec::new();
    for agent in &world.agents {
        let in_range = |kf: usize| {
            let ts = t0 + kf as i64 * KEYFRAME_US;
            agent
                .state(&world.path, secs(ts))
                .is_some_and(|(c, _, _)| (c - ego(ts).translation).truncate().length() <= ANNOTATION_RANGE)
        };
        let Some(first) = (0..k as usize).find(|&i| in_range(i)) else { continue };
        let last = (0..k as usize).rev().find(|&i| in_range(i)).unwrap_or(first);
        let instance_token = tok(&format!("instance/{}", agent.instance));
        let ann = |kf: usize| tok(&format!("ann/{}/{kf}", agent.instance));
        let (category, attribute) = match agent.kind {
            AgentKind::Car => ("vehicle.car", if agent.moving() { "vehicle.moving" } else { "vehicle.parked" }),
            AgentKind::Pedestrian => {
                ("human.pedestrian.adult", if agent.moving() { "pedestrian.moving" } else { "pedestrian.standing" })
            }
        };
        for kf in first..=last {
            let ts = t0 + kf as i64 * KEYFRAME_US;
            let Some((centre, yaw, _)) = agent.state(&world.path, secs(ts)) else { continue };
            let lidar_pts =
                keyframe_labels.get(kf).map_or(0, |(_, inst)| inst.iter().filter(|&&i| i == agent.instance).count());
            let vis = visibility(config, &world, &key_snapshots[kf], agent, secs(ts), &key_cams, kf, &ego);
            let [l, w, h] = agent.size;
            t.push(
                "sample_annotation",
                json!({
                    "token": ann(kf),
                    "sample_token": sample_tokens[kf],
                    "instance_token": instance_token,
                    "visibility_token": vis,
                    "attribute_tokens": [global_token(&format!("attribute/{attribute}"))],
                    "translation": centre.to_array(),
                    "size": [w, l, h],
                    "rotation": Se3::from_yaw(yaw, centre).wxyz(),
                    "prev": if kf > first { ann(kf - 1) } else { String::new() },
                    "next": if kf < last { ann(kf + 1) } else { String::new() },
                    "num_lidar_pts": lidar_pts,
                    "num_radar_pts": 0,
                }),
            );
            summary.annotations += 1;
        }
        annotated.push((agent, instance_token.clone(), category));
        t.push(
            "instance",
            json!({
                "token": instance_token,
                "category_token": global_token(&format!("category/{category}")),
                "nbr_annotations": last - first + 1,
                "first_annotation_token": ann(first),
                "last_annotation_token": ann(last),
            }),
        );
    }

    // The exact box of every annotated agent at every camera image's own time, what boxes
    // interpolated between keyframes are scored against (`groundtruth/boxes/<CAMERA>/<image
    // stem>.json`).
    if config.ground_truth {
        for r in cameras.iter().flatten() {
            let boxes: Vec<serde_json::Value> = annotated
                .iter()
                .filter_map(|(agent, instance, category)| {
                    let (centre, yaw, velocity) = agent.state(&world.path, secs(r.timestamp))?;
                    let [l, w, h] = agent.size;
                    Some(json!({
                        "instance_token": instance,
                        "category": category,
                        "translation": centre.to_array(),
                        "size": [w, l, h],
                        "rotation": Se3::from_yaw(yaw, centre).wxyz(),
                        "velocity": velocity.to_array(),
                    }))
                })
                .collect();
            let stem = Path::new(&r.filename).file_stem().map(|s| s.to_string_lossy().to_string()).unwrap_or_default();
            let dir = gt.join("boxes").join(r.channel);
            std::fs::create_dir_all(&dir)?;
            let file = dir.join(format!("{stem}.json"));
            std::fs::write(&file, serde_json::to_vec(&json!({"timestamp_us": r.timestamp, "boxes": boxes}))?)
                .with_context(|| format!("writing {}", file.display()))?;
        }
    }

    // Map mask: the drivable surface at 0.1 m per pixel, as the devkit's MapMask expects.
    let map_token = tok("map");
    let map_file = format!("maps/{map_token}.png");
    std::fs::create_dir_all(root.join("maps"))?;
    std::fs::write(root.join(&map_file), map_mask(&world)?)?;
    t.push(
        "map",
        json!({"token": map_token, "log_tokens": [log_token], "category": "semantic_prior", "filename": map_file}),
    );

    summary.samples += k as usize;
    summary.lidar_sweeps += lidar.len();
    summary.camera_images += jobs.len();
    Ok(())
}

/// The exact occupancy of keyframe reading `r` as Occ3D's `labels.npz`: the world's primitives
/// in Occ3D-nuScenes' grid around the ego ([`Snapshot::occupancy`]), classes mapped Cityscapes ->
/// lidarseg -> Occ3D as the lidarseg files and the occupancy stages map them, and the masks cast
/// from the keyframe's LiDAR sweep (read back as written) and its six cameras.
fn exact_occupancy(
    config: &SynthConfig,
    world: &World,
    r: &Reading,
    cameras: &[Vec<Reading>],
    ego: &(dyn Fn(i64) -> Se3 + Sync),
    t: f64,
    root: &Path,
) -> Result<Vec<u8>> {
    use dist4d_types::occ3d::{of_lidarseg, DROP, FREE};
    use dist4d_types::voxels::{cast_masks, MaskCamera};
    let g = dist4d_types::occ3d::grid();
    let ego_to_world = ego(r.timestamp);
    let ids = Snapshot::new(world, t).occupancy(&ego_to_world, g.min, g.voxel, g.dims, 3);
    let semantics: Vec<u8> = ids
        .iter()
        .map(|&id| match id {
            0 => FREE,
            c => match of_lidarseg(lidarseg_index(c)) {
                DROP => FREE,
                class => class,
            },
        })
        .collect();
    let lidar_to_ego = LIDAR_TOP.sensor_to_ego();
    let bytes = std::fs::read(root.join(&r.filename)).with_context(|| format!("reading {}", r.filename))?;
    // Without the car's own returns, as the nuScenes reader gives the sweep to the pipeline.
    let returns = bytes
        .chunks_exact(20)
        .map(|p| {
            let f = |i: usize| f32::from_le_bytes([p[i], p[i + 1], p[i + 2], p[i + 3]]) as f64;
            lidar_to_ego.apply(DVec3::new(f(0), f(4), f(8)))
        })
        .filter(|e| !dist4d_types::geometry::ego_box::contains(&dist4d_types::geometry::ego_box::NUSCENES, *e));
    let ego_from_world = ego_to_world.inverse();
    let views: Vec<MaskCamera> = CAMERA_RIG
        .iter()
        .zip(cameras)
        .filter_map(|(rig, readings)| {
            let c = readings.iter().find(|c| c.key && c.sample == r.sample)?;
            Some(MaskCamera {
                ego_from_camera: ego_from_world.then_from(&ego(c.timestamp).then_from(&rig.sensor_to_ego())),
                k: rig.intrinsics(config.width, config.height),
                width: config.width,
                height: config.height,
                // The synthetic cameras see no car body.
                blocked: Vec::new(),
            })
        })
        .collect();
    // The occupancy stages' defaults: a camera ray every 4 pixels, out to 100 m.
    let (mask_lidar, mask_camera) =
        cast_masks(&g, &semantics, FREE, lidar_to_ego.translation, returns, &views, 4, 100.0);
    let shape = g.dims;
    Ok(dist4d_types::formats::npz(&[
        ("semantics", dist4d_types::formats::npy_u8(&shape, &semantics)),
        ("mask_lidar", dist4d_types::formats::npy_u8(&shape, &mask_lidar)),
        ("mask_camera", dist4d_types::formats::npy_u8(&shape, &mask_camera)),
    ]))
}

fn pinhole(config: &SynthConfig, camera: usize, ego_to_world: &Se3) -> PinholeCamera {
    let rig = &CAMERA_RIG[camera];
    PinholeCamera {
        k: rig.intrinsics(config.width, config.height),
        width: config.width,
        height: config.height,
        camera_to_world: ego_to_world.then_from(&rig.sensor_to_ego()),
    }
}

/// nuScenes visibility token ("1".."4" for 0-40, 40-60, 60-80, 80-100 %): the fraction of sample
/// points of the box (centre and shrunken corners) that the keyframe cameras see unoccluded,
/// among those inside some camera's image.
#[allow(clippy::too_many_arguments)]
fn visibility(
    config: &SynthConfig,
    world: &World,
    snap: &Snapshot,
    agent: &super::world::Agent,
    t: f64,
    key_cams: &[Vec<&Reading>],
    kf: usize,
    ego: &dyn Fn(i64) -> Se3,
) -> &'static str {
    let Some((c, yaw, _)) = agent.state(&world.path, t) else { return "1" };
    let [l, w, h] = agent.size;
    let mut samples = vec![c];
    for (a, b, z) in [
        (1.0, 1.0, 1.0),
        (1.0, -1.0, 1.0),
        (-1.0, 1.0, 1.0),
        (-1.0, -1.0, 1.0),
        (1.0, 1.0, -1.0),
        (1.0, -1.0, -1.0),
        (-1.0, 1.0, -1.0),
        (-1.0, -1.0, -1.0),
    ] {
        let local = DVec3::new(a * l * 0.35, b * w * 0.35, z * h * 0.35);
        samples.push(c + Se3::from_yaw(yaw, DVec3::ZERO).apply(local));
    }
    let (mut seen, mut visible) = (0, 0);
    for p in samples {
        let mut in_view = false;
        let mut unoccluded = false;
        for (cam, readings) in key_cams.iter().enumerate() {
            let Some(r) = readings.get(kf) else { continue };
            let pin = pinhole(config, cam, &ego(r.timestamp));
            let pc = pin.camera_to_world.inverse().apply(p);
            if pc.z <= 0.1 {
                continue;
            }
            let (u, v) = (pin.k[0][0] * pc.x / pc.z + pin.k[0][2], pin.k[1][1] * pc.y / pc.z + pin.k[1][2]);
            if u < 0.0 || v < 0.0 || u >= pin.width as f64 || v >= pin.height as f64 {
                continue;
            }
            in_view = true;
            let o = pin.camera_to_world.translation;
            let dist = (p - o).length();
            let d = (p - o) / dist;
            match snap.cast(o, d, dist + 0.5) {
                Some(hit) if hit.instance != agent.instance && hit.t < dist - 0.05 => {}
                _ => unoccluded = true,
            }
        }
        seen += in_view as u32;
        visible += (in_view && unoccluded) as u32;
    }
    let frac = if seen == 0 { 0.0 } else { visible as f64 / seen as f64 };
    match frac {
        f if f < 0.4 => "1",
        f if f < 0.6 => "2",
        f if f < 0.8 => "3",
        _ => "4",
    }
}

/// The drivable area as an 8-bit PNG over x, y >= 0 (row 0 at the largest y).
fn map_mask(world: &World) -> Result<Vec<u8>> {
    // Extent of the street, with room for the sidewalks.
    let (mut max_x, mut max_y) = (0.0f64, 0.0f64);
    let len = world.path.length();
    let mut s = -200.0;
    while s < len {
        let (x, y, _) = world.path.at(s);
        (max_x, max_y) = (max_x.max(x), max_y.max(y));
        s += 2.0;
    }
    let (w, h) = (((max_x + 40.0) / MAP_RESOLUTION) as usize, ((max_y + 40.0) / MAP_RESOLUTION) as usize);
    // Coarse blocks first (2 m), so only blocks near the road test every pixel.
    let block = 20;
    let mut px = vec![0u8; w * h];
    px.par_chunks_mut(w * block).enumerate().for_each(|(bj, rows)| {
        let nrows = rows.len() / w;
        for bi in 0..w.div_ceil(block) {
            let cx = ((bi * block) as f64 + block as f64 / 2.0) * MAP_RESOLUTION;
            let cy = ((h - bj * block) as f64 - block as f64 / 2.0) * MAP_RESOLUTION;
            let near = world.path.station(cx, cy).is_some_and(|(_, d)| d.abs() < ROAD_HALF_WIDTH + 2.0);
            if !near {
                continue;
            }
            for r in 0..nrows {
                let y = (h - (bj * block + r)) as f64 * MAP_RESOLUTION - MAP_RESOLUTION / 2.0;
                for col in bi * block..((bi + 1) * block).min(w) {
                    let x = (col as f64 + 0.5) * MAP_RESOLUTION;
                    if world.path.station(x, y).is_some_and(|(_, d)| d.abs() <= ROAD_HALF_WIDTH) {
                        rows[r * w + col] = 255;
                    }
                }
            }
        }
    });
    fast_png_gray(&px, w as u32, h as u32)
}

/// An 8-bit grey PNG with fast compression: label images and masks are flat regions that
/// compress well even so, and the default level costs several times more.
fn fast_png_gray(px: &[u8], width: u32, height: u32) -> Result<Vec<u8>> {
    use image::codecs::png::{CompressionType, FilterType, PngEncoder};
    use image::ImageEncoder;
    let mut out = Vec::new();
    PngEncoder::new_with_quality(&mut out, CompressionType::Fast, FilterType::Sub)
        .write_image(px, width, height, image::ExtendedColorType::L8)
        .context("encoding PNG")?;
    Ok(out)
}

/// `YYYY-MM-DD` (UTC) of a synthetic timestamp: the days from 2025-01-01, when the first scene
/// starts, walked month by month (scenes start an hour apart, so a few days in at most).
pub(super) fn date_of(us: i64) -> String {
    let mut days = (us - EPOCH_US).div_euclid(86_400_000_000).max(0);
    let (mut year, mut month) = (2025i64, 1u32);
    loop {
        let leap = year % 4 == 0 && (year % 100 != 0 || year % 400 == 0);
        let length = match month {
            2 if leap => 29,
            2 => 28,
            4 | 6 | 9 | 11 => 30,
            _ => 31,
        };
        if days < length {
            return format!("{year:04}-{month:02}-{:02}", days + 1);
        }
        days -= length;
        (year, month) = if month == 12 { (year + 1, 1) } else { (year, month + 1) };
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dates_walk_the_calendar_from_the_first_scene() {
        let day = 86_400_000_000;
        assert_eq!(date_of(scene_start_us(0)), "2025-01-01");
        assert_eq!(date_of(scene_start_us(23)), "2025-01-01");
        assert_eq!(date_of(scene_start_us(24)), "2025-01-02");
        assert_eq!(date_of(EPOCH_US + 31 * day), "2025-02-01");
        assert_eq!(date_of(EPOCH_US + 59 * day), "2025-03-01");
        assert_eq!(date_of(EPOCH_US + 365 * day), "2026-01-01");
        assert_eq!(date_of(EPOCH_US + (365 + 365 + 365 + 59) * day), "2028-02-29");
    }
}
