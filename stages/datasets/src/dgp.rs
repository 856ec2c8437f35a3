//! TRI DGP reader (the DDAD format): scene dataset JSON -> scenes -> samples -> cameras.
//!
//! Gives the shared surround-camera items and source ports ([`crate::surround`]), as the nuScenes
//! reader does, so every pipeline runs on either. DGP stores each datum's pose as sensor -> world and the calibration as sensor ->
//! vehicle; the ego pose of a datum is therefore `pose * extrinsics^-1`. Timestamps come from the
//! file names (100 ns units; the ISO fields of the test data are not meaningful). Boxes are
//! annotated in the LiDAR frame and returned in the world frame.

use crate::checks::MAX_TABLE_FILE_BYTES;
use crate::checks::{
    box_values, check_reference, image_size, join_inside, pinhole, principal_point_inside, rigid, Fields, Place,
    Renormalised, Transform,
};
use crate::files::{read_input, read_npz};
use crate::sidecar::Sidecars;
use crate::surround::{Frame, Reading, Scene, SurroundReader, Tree};
use anyhow::{anyhow, bail, ensure, Context, Result};
use dist4d_graph::{DatasetSchema, ParamsSpec};
use dist4d_runtime::{Digest, FileDigests, ItemKey};
use dist4d_types::artifact::{Box3D, Boxes3D, Calibration, PointCloud, Pose};
use dist4d_types::geometry::Se3;
use serde::{Deserialize, Serialize};
use serde_json::Value;
use std::collections::HashMap;
use std::path::{Path, PathBuf};

#[derive(Serialize, Deserialize, Clone, Debug)]
#[serde(deny_unknown_fields, default)]
pub struct DgpConfig {
    /// The folder holding `scene_dataset*.json`.
    pub root: String,
    /// `train`, `val` or `test` (DGP split ids 0, 1, 2).
    pub split: String,
    /// Camera datum names, in item order; by default every camera the split's scenes have (the
    /// names of their image datums, sorted: DDAD's CAMERA_01, CAMERA_05, ...).
    pub cameras: Option<Vec<String>>,
    /// LiDAR datum name.
    pub lidar: String,
    /// Folder of semantic maps (`<CAMERA>/<image stem>.png`, Cityscapes ids), relative to the
    /// root; none by default.
    pub semantics: Option<String>,
}

impl Default for DgpConfig {
    fn default() -> Self {
        DgpConfig { root: String::new(), split: "train".into(), cameras: None, lidar: "LIDAR".into(), semantics: None }
    }
}

/// A scene's box classes: the names of the ontology's ids.
type Ontology = HashMap<i64, String>;

/// What a DGP frame keeps beside its readings: its LiDAR datum's 3D box annotation file, or why
/// its reference is refused (none when the datum has no boxes or failed).
type BoxFile = Option<Result<PathBuf, String>>;

pub struct Dgp {
    pub config: DgpConfig,
    tree: Tree<Ontology, BoxFile>,
    /// What was normalised when the dataset was opened (for the caller to print).
    pub warnings: Vec<String>,
}

fn read_json(path: &Path) -> Result<Value> {
    let bytes = read_input(path, "the DGP file", MAX_TABLE_FILE_BYTES)?;
    serde_json::from_slice(&bytes).with_context(|| format!("{} is not valid JSON", path.display()))
}

/// A field of a JSON object, or an error naming the file, the object and the field.
fn field<'a>(v: &'a Value, name: &str, file: &Path, what: &str) -> Result<&'a Value> {
    v.get(name).ok_or_else(|| anyhow!("{}: {what} has no field `{name}`", file.display()))
}

fn num(v: &Value, name: &str, file: &Path, what: &str) -> Result<f64> {
    field(v, name, file, what)?
        .as_f64()
        .ok_or_else(|| anyhow!("{}: {what}: field `{name}` is not a number", file.display()))
}

/// The numbers of a DGP pose `{rotation: {qw, qx, qy, qz}, translation: {x, y, z}}`.
fn pose_values(v: &Value, file: &Path, what: &str) -> Result<([f64; 4], [f64; 3])> {
    let r = field(v, "rotation", file, what)?;
    let t = field(v, "translation", file, what)?;
    let what_r = format!("{what} rotation");
    let what_t = format!("{what} translation");
    Ok((
        [
            num(r, "qw", file, &what_r)?,
            num(r, "qx", file, &what_r)?,
            num(r, "qy", file, &what_r)?,
            num(r, "qz", file, &what_r)?,
        ],
        [num(t, "x", file, &what_t)?, num(t, "y", file, &what_t)?, num(t, "z", file, &what_t)?],
    ))
}

/// A DGP pose checked as a `kind` transform; `fields` prefixes the field names (`pose`,
/// `extrinsics[2]`).
fn checked_pose(v: &Value, at: &Place, fields: &str, kind: Transform, notes: &mut Renormalised) -> Result<Se3> {
    let (q, t) = pose_values(v, &at.file, &at.item)?;
    let (rotation, translation) = (format!("{fields}.rotation"), format!("{fields}.translation"));
    rigid(at, Fields { rotation: &rotation, translation: &translation }, q, t, kind, notes).map_err(anyhow::Error::msg)
}

/// Microseconds from a DGP file name in 100 ns units (`15616458250027900.npz`).
fn timestamp_of(filename: &str) -> Option<i64> {
    Path::new(filename).file_stem()?.to_str()?.parse::<i64>().ok().map(|t| t / 10)
}

impl Dgp {
    pub fn open(config: DgpConfig) -> Result<Dgp> {
        let root = PathBuf::from(&config.root);
        let index = std::fs::read_dir(&root)
            .with_context(|| format!("reading the DGP root {} (dataset.root)", root.display()))?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .find(|p| {
                p.file_name()
                    .and_then(|n| n.to_str())
                    .is_some_and(|n| n.starts_with("scene_dataset") && n.ends_with(".json"))
            })
            .ok_or_else(|| anyhow!("{} has no scene_dataset*.json", root.display()))?;
        let split = match config.split.as_str() {
            "train" => "0",
            "val" => "1",
            "test" => "2",
            other => bail!("dataset.split is {other:?}; DGP splits are train, val, test"),
        };
        let dataset = read_json(&index)?;
        let files = field(&dataset, "scene_splits", &index, "the scene dataset")?
            .get(split)
            .and_then(|s| s.get("filenames"))
            .and_then(|f| f.as_array())
            .ok_or_else(|| anyhow!("{}: split {} ({split}) lists no scene files", index.display(), config.split))?;
        let mut renormalised = Renormalised::default();
        let at = Place::new(&index, format!("split {}", config.split));
        let mut scene_files = Vec::new();
        for (i, f) in files.iter().enumerate() {
            let field = format!("filenames[{i}]");
            let rel = f.as_str().ok_or_else(|| anyhow!("{at}: field {field} is not a string"))?;
            let path = join_inside(&root, &at, &field, rel).map_err(anyhow::Error::msg)?;
            let json = read_json(&path)?;
            scene_files.push((path, json));
        }
        let cameras = match &config.cameras {
            Some(c) => c.clone(),
            None => {
                let mut names: Vec<String> = scene_files
                    .iter()
                    .flat_map(|(_, json)| json.get("data").and_then(|d| d.as_array()).into_iter().flatten())
                    .filter(|d| d.pointer("/datum/image").is_some())
                    .filter_map(|d| d.pointer("/id/name").and_then(|n| n.as_str()).map(String::from))
                    .collect();
                names.sort();
                names.dedup();
                ensure!(
                    !names.is_empty(),
                    "{}: no scene of split {} has an image datum",
                    index.display(),
                    config.split
                );
                names
            }
        };
        let mut scenes = Vec::new();
        for (path, json) in &scene_files {
            scenes.push(Self::scene(&config, &cameras, path, json, &mut renormalised)?);
        }
        let sidecars = Sidecars::new(&root, config.semantics.as_deref());
        let tree = Tree { root: root.clone(), cameras, scenes, sidecars };
        Ok(Dgp { config, tree, warnings: renormalised.warnings() })
    }

    fn scene(
        config: &DgpConfig,
        cameras: &[String],
        path: &Path,
        scene: &Value,
        notes: &mut Renormalised,
    ) -> Result<Scene<Ontology, BoxFile>> {
        let dir = path.parent().unwrap_or(Path::new("."));
        let name = dir.file_name().map(|n| n.to_string_lossy().to_string()).unwrap_or_default();
        let mut datums: HashMap<&str, &Value> = HashMap::new();
        for d in field(&scene, "data", path, "the scene")?.as_array().context("`data` is not a list")? {
            let key = d
                .get("key")
                .and_then(|k| k.as_str())
                .ok_or_else(|| anyhow!("{}: a datum has no `key`", path.display()))?;
            datums.insert(key, d);
        }
        // Ontology of the 3D boxes (annotation type 1).
        let mut ontology = HashMap::new();
        if let Some(key) = scene.get("ontologies").and_then(|o| o.get("1")).and_then(|k| k.as_str()) {
            check_reference(&Place::new(path, "(the scene)"), "ontologies.1", key).map_err(anyhow::Error::msg)?;
            let file = dir.join("ontology").join(format!("{key}.json"));
            let o = read_json(&file)?;
            for item in o.get("items").and_then(|i| i.as_array()).into_iter().flatten() {
                if let (Some(id), Some(n)) =
                    (item.get("id").and_then(|i| i.as_i64()), item.get("name").and_then(|n| n.as_str()))
                {
                    ontology.insert(id, n.to_string());
                }
            }
        }
        // Calibrations by key, each read once; a refused key fails the items of its samples.
        let mut calibrations: HashMap<String, Result<(Value, PathBuf), String>> = HashMap::new();
        let mut frames = Vec::new();
        let samples = field(&scene, "samples", path, "the scene")?.as_array().context("`samples` is not a list")?;
        for (i, sample) in samples.iter().enumerate() {
            let what = format!("sample {i}");
            let calib_key = field(sample, "calibration_key", path, &what)?.as_str().unwrap_or("").to_string();
            if !calibrations.contains_key(&calib_key) {
                let loaded = match check_reference(&Place::new(path, what.as_str()), "calibration_key", &calib_key) {
                    Err(e) => Err(e),
                    Ok(()) => {
                        let file = dir.join("calibration").join(format!("{calib_key}.json"));
                        Ok((read_json(&file)?, file))
                    }
                };
                calibrations.insert(calib_key.clone(), loaded);
            }
            let calibration = &calibrations[&calib_key];
            let keys: Vec<&str> = field(sample, "datum_keys", path, &what)?
                .as_array()
                .map(|a| a.iter().filter_map(|k| k.as_str()).collect())
                .unwrap_or_default();
            let mut resolve = |sensor: &str| -> Result<(Reading, BoxFile), String> {
                let (calib, calib_file) = calibration.as_ref().map_err(String::clone)?;
                let d = keys
                    .iter()
                    .filter_map(|k| datums.get(k))
                    .find(|d| d.pointer("/id/name").and_then(|n| n.as_str()) == Some(sensor))
                    .ok_or_else(|| format!("{}: sample {i} has no datum named {sensor}", path.display()))?;
                let sources = Sources { dir, scene_file: path, sample: i, calib, calib_file };
                datum(d, sensor, &sources, notes).map_err(|e| format!("{e:#}"))
            };
            let (lidar, boxes) = match resolve(&config.lidar) {
                Ok((reading, boxes)) => (Ok(reading), boxes),
                Err(e) => (Err(e), None),
            };
            let cameras = cameras.iter().map(|c| resolve(c).map(|(reading, _)| reading)).collect();
            frames.push(Frame { lidar, cameras, extra: boxes });
        }
        Ok(Scene { name, frames, extra: ontology })
    }
}

/// Where a datum's references resolve and what it is checked against.
struct Sources<'a> {
    /// The scene's folder: datum files are relative to it.
    dir: &'a Path,
    scene_file: &'a Path,
    sample: usize,
    calib: &'a Value,
    calib_file: &'a Path,
}

/// A datum as a reading, with its 3D box annotation file when it names one.
fn datum(d: &Value, sensor: &str, src: &Sources, notes: &mut Renormalised) -> Result<(Reading, BoxFile)> {
    let scene_file = src.scene_file;
    let key = d.get("key").and_then(|k| k.as_str()).unwrap_or("?").to_string();
    let what = format!("datum {key} ({sensor})");
    let at = Place::new(scene_file, format!("sample {} {what}", src.sample));
    let (body, is_image) = match (d.pointer("/datum/image"), d.pointer("/datum/point_cloud")) {
        (Some(image), _) => (image, true),
        (None, Some(cloud)) => (cloud, false),
        (None, None) => bail!("{at} is neither an image nor a point cloud"),
    };
    let filename = field(body, "filename", scene_file, &what)?.as_str().unwrap_or("");
    let file = join_inside(src.dir, &at, "filename", filename).map_err(anyhow::Error::msg)?;
    let timestamp = timestamp_of(filename)
        .ok_or_else(|| anyhow!("{}: {what}: file name {filename} is not a timestamp", scene_file.display()))?;
    let sensor_to_world = checked_pose(field(body, "pose", scene_file, &what)?, &at, "pose", Transform::Pose, notes)?;
    let names = src.calib.get("names").and_then(|n| n.as_array()).context("calibration has no `names`")?;
    let idx = names
        .iter()
        .position(|n| n.as_str() == Some(sensor))
        .ok_or_else(|| anyhow!("{}: no calibration for {sensor}", src.calib_file.display()))?;
    let cat = Place::new(src.calib_file, format!("entry {idx} ({sensor})"));
    let ext = src
        .calib
        .pointer(&format!("/extrinsics/{idx}"))
        .ok_or_else(|| anyhow!("{}: {sensor} calibration has no extrinsics", src.calib_file.display()))?;
    let sensor_to_ego = checked_pose(ext, &cat, &format!("extrinsics[{idx}]"), Transform::Mount, notes)?;
    // Saturated, not truncated: 2^32 + 5 must not pass as 5 (the bound check below refuses it).
    let dim = |n: &str| body.get(n).and_then(|v| v.as_u64()).map_or(0, |v| u32::try_from(v).unwrap_or(u32::MAX));
    let (width, height) = (dim("width"), dim("height"));
    if is_image {
        image_size(&at.to_string(), "fields width, height", width, height).map_err(anyhow::Error::msg)?;
    }
    // Point clouds have no intrinsics (DGP writes zeros for them); an image must have good ones.
    let intrinsics = if is_image { Some(intrinsics(src.calib, idx, &cat, width, height, &at)?) } else { None };
    let reading = Reading {
        file,
        calib: Calibration { sensor_to_ego, intrinsics, width, height },
        pose: Pose { ego_to_world: sensor_to_world.then_from(&sensor_to_ego.inverse()), timestamp_us: timestamp },
        what: format!("datum {key}"),
        token: key.to_string(),
        row: None,
        stored_file: None,
    };
    let boxes =
        body.pointer("/annotations/1").and_then(|a| a.as_str()).map(|a| join_inside(src.dir, &at, "annotations.1", a));
    Ok((reading, boxes))
}

/// Entry `idx` of a calibration's `intrinsics` as a checked pinhole matrix whose principal point
/// lies inside the `width` x `height` image of the datum at `datum`.
fn intrinsics(calib: &Value, idx: usize, at: &Place, width: u32, height: u32, datum: &Place) -> Result<[[f64; 3]; 3]> {
    let field_name = format!("intrinsics[{idx}]");
    let k =
        calib.pointer(&format!("/intrinsics/{idx}")).ok_or_else(|| anyhow!("{at}: field {field_name} is missing"))?;
    let what = format!("{} {field_name}", at.item);
    let get = |n: &str| num(k, n, &at.file, &what);
    let m = [[get("fx")?, get("skew").unwrap_or(0.0), get("cx")?], [0.0, get("fy")?, get("cy")?], [0.0, 0.0, 1.0]];
    let m = pinhole(at, &field_name, m).map_err(anyhow::Error::msg)?;
    principal_point_inside(at, &field_name, &m, width, height).map_err(|e| anyhow!("{e} of {datum}"))?;
    Ok(m)
}

/// A `bounding_box_3d` file, boxes moved from the sensor frame to the world.
fn read_boxes(file: &Path, sensor_to_world: &Se3, ontology: &HashMap<i64, String>) -> Result<Vec<Box3D>> {
    let v = read_json(file)?;
    let list = field(&v, "annotations", file, "the box file")?.as_array().context("`annotations` is not a list")?;
    list.iter()
        .enumerate()
        .map(|(i, a)| {
            let what = format!("annotation {i}");
            let b = field(a, "box", file, &what)?;
            // Checked in the sensor frame, as written: a zero quaternion or a negative size would
            // become NaN or an inside-out box in every stage that uses it.
            let (q, t) = pose_values(field(b, "pose", file, &what)?, file, &what)?;
            let size = [num(b, "width", file, &what)?, num(b, "length", file, &what)?, num(b, "height", file, &what)?];
            let at = Place::new(file, format!("{what} (box.pose, box.width/length/height)"));
            let q = box_values(&at, t, size, q, &mut Renormalised::default()).map_err(anyhow::Error::msg)?;
            let world = sensor_to_world.then_from(&Se3::from_wxyz_t(q, t));
            let class = field(a, "class_id", file, &what)?.as_i64().unwrap_or(-1);
            Ok(Box3D {
                center: world.translation.to_array(),
                size,
                rotation: world.wxyz(),
                velocity: [f64::NAN; 3],
                instance: field(a, "instance_id", file, &what)?.to_string(),
                category: ontology.get(&class).cloned().unwrap_or_else(|| format!("class {class}")),
                attributes: Vec::new(),
                num_lidar_pts: a.get("num_points").and_then(|n| n.as_u64()).unwrap_or(0) as u32,
                interpolated: false,
                extrapolated: false,
            })
        })
        .collect()
}

/// A DGP point cloud (`.npz`, key `data`, X, Y, Z, INTENSITY as float64) in the sensor frame.
pub fn read_dgp_points(path: &Path) -> Result<PointCloud> {
    let a = read_npz(path, "data")?;
    ensure!(
        a.shape.len() == 2 && a.shape[1] >= 3,
        "{}: array `data` has shape {:?}, expected (N, 4)",
        path.display(),
        a.shape
    );
    let cols = a.shape[1];
    Ok(PointCloud {
        points: a
            .data
            .chunks_exact(cols)
            .map(|r| [r[0] as f32, r[1] as f32, r[2] as f32, if cols > 3 { r[3] as f32 } else { 0.0 }])
            .collect(),
        labels: Vec::new(),
        rgb: Vec::new(),
    })
}

impl SurroundReader for Dgp {
    /// DDAD's Ford Fusion (the ego frame on the ground, the cameras 1.55 m up around x 0.1-1.5).
    const EGO_BOX: Option<([f64; 3], [f64; 3])> = Some(dist4d_types::geometry::ego_box::DDAD);
    const FORMAT: &'static str = "DGP";
    /// DGP is the format TRI ships DDAD in.
    const SOURCE_DATASET: &'static str = "ddad";
    type Scene = Ontology;
    type Frame = BoxFile;

    fn tree(&self) -> &Tree<Ontology, BoxFile> {
        &self.tree
    }

    fn lidar_digest(&self, lidar: &Reading, _: &BoxFile, files: &dyn FileDigests) -> Result<Option<Digest>> {
        lidar.file_digest(files)
    }

    fn read_lidar(&self, lidar: &Reading, _: &BoxFile) -> Result<PointCloud> {
        read_dgp_points(&lidar.file).with_context(|| lidar.what.clone())
    }

    /// Boxes of a LiDAR datum in the world frame, with velocities from the neighbouring samples'
    /// boxes of the same instance (centre difference, like the nuScenes devkit).
    fn boxes(&self, item: &ItemKey) -> Result<Boxes3D> {
        // The frame's LiDAR datum first: its error is the boxes' error.
        self.tree.reading("lidar", item)?;
        let (scene, _) = self.tree.scene_frame(item)?;
        let f = item.idx[1] as usize;
        let read = |frame: usize| -> Result<Option<(i64, Vec<Box3D>)>> {
            let Some(Frame { lidar: Ok(d), extra: boxes, .. }) = scene.frames.get(frame) else { return Ok(None) };
            let file = match boxes {
                None => return Ok(Some((d.pose.timestamp_us, Vec::new()))),
                Some(Err(e)) => bail!("{e}"),
                Some(Ok(file)) => file,
            };
            let sensor_to_world = d.pose.ego_to_world.then_from(&d.calib.sensor_to_ego);
            Ok(Some((d.pose.timestamp_us, read_boxes(file, &sensor_to_world, &scene.extra)?)))
        };
        let (t, mut boxes) = read(f)?.ok_or_else(|| anyhow!("frame {f} has no LiDAR datum"))?;
        let prev = if f > 0 { read(f - 1)? } else { None };
        let next = read(f + 1)?;
        for b in &mut boxes {
            let find = |n: &Option<(i64, Vec<Box3D>)>| {
                n.as_ref().and_then(|(t, v)| v.iter().find(|x| x.instance == b.instance).map(|x| (*t, x.center)))
            };
            let (p, n) = (find(&prev), find(&next));
            if p.is_none() && n.is_none() {
                continue;
            }
            let (t0, c0) = p.unwrap_or((t, b.center));
            let (t1, c1) = n.unwrap_or((t, b.center));
            let dt = (t1 - t0) as f64 * 1e-6;
            if dt > 0.0 {
                b.velocity = [0, 1, 2].map(|i| (c1[i] - c0[i]) / dt);
            }
        }
        Ok(Boxes3D { timestamp_us: t, boxes })
    }
}

/// Camera and LiDAR names become folder and file names of exports, so each must be one safe
/// path component; the cameras, at least one, once each.
impl dist4d_graph::Validate for DgpConfig {
    fn validate(&self) -> Vec<dist4d_graph::ParamProblem> {
        let mut checks = dist4d_graph::ParamChecks::new();
        if let Some(cameras) = &self.cameras {
            checks.path_names("cameras", cameras);
        }
        checks.path_name("lidar", &self.lidar).done()
    }
}

/// The Dgp dataset kind as pipelines see it: the items and ports of nuScenes.
/// The `Dgp(..)` dataset kind.
pub const DATASET: crate::DatasetDef =
    crate::DatasetDef { schema, open: open_checked, root: root_of, recognises, makes_root: false };

fn open_checked(checked: &dist4d_graph::ParamsValue) -> Result<crate::Opened> {
    let ds = Dgp::open(crate::registry::config::<DgpConfig>(checked)?.clone()).context("opening the DGP dataset")?;
    Ok(crate::Opened {
        description: format!("Dgp at {}", ds.config.root),
        warnings: ds.warnings.clone(),
        has_point_labels: false,
        dataset: Box::new(crate::surround::Surround(ds)),
    })
}

fn root_of(checked: &dist4d_graph::ParamsValue) -> Option<PathBuf> {
    checked.get::<DgpConfig>().map(|c| PathBuf::from(&c.root))
}

/// A DGP root holds its `scene_dataset*.json`.
fn recognises(folder: &Path) -> bool {
    crate::registry::has_entry(folder, |n| n.starts_with("scene_dataset") && n.ends_with(".json"))
}

pub fn schema() -> DatasetSchema {
    DatasetSchema {
        kind: "Dgp",
        summary: "TRI DGP scenes (DDAD): samples, cameras, LiDAR, 3D boxes",
        dims: crate::surround::DIMS.to_vec(),
        ports: crate::surround::PORTS.to_vec(),
        config: ParamsSpec::of::<DgpConfig>(),
        path_fields: vec!["root"],
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::surround::Surround;
    use crate::testing::{load_err, shared_data};
    use dist4d_runtime::{Dataset, ItemSpace};
    use dist4d_types::artifact::Artifact;

    fn shared_dgp() -> Option<PathBuf> {
        shared_data("dgp-scene02")
    }

    fn open() -> Option<Surround<Dgp>> {
        let root = shared_dgp()?;
        Some(Surround(Dgp::open(DgpConfig { root: root.display().to_string(), ..Default::default() }).unwrap()))
    }

    #[test]
    fn reads_the_shared_scene() {
        let Some(ds) = open() else { return };
        assert!(ds.0.warnings.is_empty(), "real data passes every check silently: {:?}", ds.0.warnings);
        assert_eq!(ds.count(&ItemKey::new(&[])), 1);
        assert_eq!(ds.count(&ItemKey::new(&[0])), 3);
        assert_eq!(ds.path(&ItemKey::new(&[0, 2, 5])), "scene_02/002/CAMERA_09");
        let pc = PointCloud::decode(&ds.load_source("lidar", &ItemKey::new(&[0, 0])).unwrap()).unwrap();
        assert!((40_000..48_000).contains(&pc.points.len()));
        let cal = Calibration::decode(&ds.load_source("camera_calib", &ItemKey::new(&[0, 0, 0])).unwrap()).unwrap();
        assert_eq!((cal.width, cal.height), (1936, 1216));
        let img = dist4d_types::artifact::Image::decode(&ds.load_source("image", &ItemKey::new(&[0, 0, 0])).unwrap())
            .unwrap();
        assert_eq!((img.width, img.height), (1936, 1216));
        // 10 Hz samples: about 100 ms apart.
        let t = |f| Pose::decode(&ds.load_source("lidar_pose", &ItemKey::new(&[0, f])).unwrap()).unwrap().timestamp_us;
        assert!((95_000..105_000).contains(&(t(1) - t(0))), "{}", t(1) - t(0));
        // Boxes come in the world frame, with velocities from the neighbouring samples.
        let boxes = Boxes3D::decode(&ds.load_source("boxes", &ItemKey::new(&[0, 1])).unwrap()).unwrap();
        assert!(!boxes.boxes.is_empty());
        assert!(boxes.boxes.iter().any(|b| b.category == "Car"));
        assert!(boxes.boxes.iter().filter(|b| b.velocity[0].is_finite()).count() > boxes.boxes.len() / 2);
    }

    /// A writable copy of the shared DGP scene in a temp folder: (temp, root).
    fn copy_of_shared_dgp() -> Option<(tempfile::TempDir, PathBuf)> {
        let src = shared_dgp()?;
        let tmp = tempfile::tempdir().unwrap();
        let root = tmp.path().join("dgp");
        copy_dir(&src, &root);
        Some((tmp, root))
    }

    fn copy_dir(from: &Path, to: &Path) {
        std::fs::create_dir_all(to).unwrap();
        for e in std::fs::read_dir(from).unwrap() {
            let p = e.unwrap().path();
            let dest = to.join(p.file_name().unwrap());
            if p.is_dir() {
                copy_dir(&p, &dest)
            } else {
                std::fs::copy(&p, &dest).unwrap();
            }
        }
    }

    /// The scene JSON of the copy (its path and content).
    fn scene_json(root: &Path) -> (PathBuf, Value) {
        let dir = root.join("scene_02");
        let file = std::fs::read_dir(&dir)
            .unwrap()
            .map(|e| e.unwrap().path())
            .find(|p| p.file_name().unwrap().to_string_lossy().starts_with("scene_"))
            .unwrap();
        let v = read_json(&file).unwrap();
        (file, v)
    }

    fn write(path: &Path, v: &Value) {
        std::fs::write(path, serde_json::to_vec(v).unwrap()).unwrap();
    }

    fn open_at(root: &Path) -> Result<Surround<Dgp>> {
        Dgp::open(DgpConfig { root: root.display().to_string(), ..Default::default() }).map(Surround)
    }

    /// The datum of `sensor` in sample `sample` of a scene JSON (mutable).
    fn datum_mut<'a>(scene: &'a mut Value, sample: usize, sensor: &str) -> &'a mut Value {
        let keys: Vec<String> = scene["samples"][sample]["datum_keys"]
            .as_array()
            .unwrap()
            .iter()
            .map(|k| k.as_str().unwrap().to_string())
            .collect();
        scene["data"]
            .as_array_mut()
            .unwrap()
            .iter_mut()
            .find(|d| keys.iter().any(|k| d["key"] == k.as_str()) && d["id"]["name"] == sensor)
            .unwrap()
    }

    #[test]
    fn the_cameras_default_to_those_the_scenes_have() {
        let Some((_tmp, root)) = copy_of_shared_dgp() else { return };
        // A three-camera rig: the other cameras' datums are gone from the scene.
        let (file, mut scene) = scene_json(&root);
        let kept = ["CAMERA_01", "CAMERA_06", "CAMERA_09"];
        scene["data"].as_array_mut().unwrap().retain(|d| {
            let name = d.pointer("/id/name").and_then(|n| n.as_str()).unwrap();
            d.pointer("/datum/image").is_none() || kept.contains(&name)
        });
        write(&file, &scene);
        let ds = open_at(&root).unwrap();
        assert_eq!(ds.0.tree.cameras, kept.map(String::from));
        for c in 0..3 {
            for f in 0..3 {
                assert!(ds.load_source("camera_calib", &ItemKey::new(&[0, f, c])).is_ok(), "frame {f} camera {c}");
            }
        }
        // Named cameras stay as named (a missing one fails its items, naming it).
        let named = Dgp::open(DgpConfig {
            root: root.display().to_string(),
            cameras: Some(vec!["CAMERA_01".into(), "CAMERA_05".into()]),
            ..Default::default()
        })
        .map(Surround)
        .unwrap();
        assert!(load_err(&named, "image", &[0, 0, 1]).contains("no datum named CAMERA_05"));
    }

    #[test]
    fn file_references_outside_the_root_are_refused() {
        let Some((tmp, root)) = copy_of_shared_dgp() else { return };
        let index = root.join("scene_dataset_v1.0.json");
        let original_index = read_json(&index).unwrap();
        let (scene_file, original) = scene_json(&root);
        let scene_name = scene_file.file_name().unwrap().to_string_lossy().to_string();

        // A scene file outside the root: a full copy of the scene there, which would read fine.
        let outside = tmp.path().join("outside");
        copy_dir(&root.join("scene_02"), &outside);
        for bad in [format!("../outside/{scene_name}"), outside.join(&scene_name).display().to_string()] {
            let mut v = original_index.clone();
            v["scene_splits"]["0"]["filenames"][0] = bad.clone().into();
            write(&index, &v);
            let err = format!("{:#}", open_at(&root).err().unwrap());
            assert!(
                err.contains(&format!(
                    "scene_dataset_v1.0.json split train: field filenames[0] {bad:?} leaves the dataset root"
                )),
                "{err}"
            );
        }
        write(&index, &original_index);

        // An ontology key that climbs out: the whole scene is refused.
        let mut v = original.clone();
        v["ontologies"]["1"] = "../../../onto".into();
        write(&scene_file, &v);
        let err = format!("{:#}", open_at(&root).err().unwrap());
        assert!(err.contains("field ontologies.1 \"../../../onto\" leaves the dataset root"), "{err}");

        // Datum files, box files and calibration keys: only the items that use them fail.
        let mut v = original.clone();
        let cam = datum_mut(&mut v, 0, "CAMERA_01");
        let real = root.join("scene_02").join(cam["datum"]["image"]["filename"].as_str().unwrap());
        std::fs::copy(&real, tmp.path().join("x.jpg")).unwrap();
        cam["datum"]["image"]["filename"] = "../../x.jpg".into();
        let key = cam["key"].as_str().unwrap().to_string();
        let lidar = datum_mut(&mut v, 2, "LIDAR");
        lidar["datum"]["point_cloud"]["annotations"]["1"] = "/etc/passwd".into();
        let calib = root.join("scene_02/calibration");
        let calib_file = std::fs::read_dir(&calib).unwrap().next().unwrap().unwrap().path();
        std::fs::copy(&calib_file, tmp.path().join("calib.json")).unwrap();
        v["samples"][1]["calibration_key"] = "../../../calib".into();
        write(&scene_file, &v);
        let ds = open_at(&root).unwrap();
        let err = load_err(&ds, "image", &[0, 0, 0]);
        assert!(
            err.contains(&format!(
                "sample 0 datum {key} (CAMERA_01): field filename \"../../x.jpg\" leaves the dataset root"
            )),
            "{err}"
        );
        assert!(ds.load_source("image", &ItemKey::new(&[0, 0, 1])).is_ok());
        let err = load_err(&ds, "boxes", &[0, 2]);
        assert!(
            err.contains("field annotations.1 \"/etc/passwd\" leaves the dataset root (an absolute path)"),
            "{err}"
        );
        assert!(ds.load_source("lidar", &ItemKey::new(&[0, 2])).is_ok(), "only the boxes are refused");
        let err = load_err(&ds, "camera_calib", &[0, 1, 3]);
        assert!(err.contains("sample 1: field calibration_key \"../../../calib\" leaves the dataset root"), "{err}");
        assert!(ds.load_source("camera_calib", &ItemKey::new(&[0, 2, 3])).is_ok());
    }

    #[test]
    fn bad_poses_and_intrinsics_fail_their_datums_and_slightly_off_quaternions_warn() {
        let Some((_tmp, root)) = copy_of_shared_dgp() else { return };
        let (scene_file, mut v) = scene_json(&root);
        let cam = datum_mut(&mut v, 0, "CAMERA_05");
        cam["datum"]["image"]["pose"]["rotation"] = serde_json::json!({"qw": 0.0, "qx": 0.0, "qy": 0.0, "qz": 0.0});
        let key = cam["key"].as_str().unwrap().to_string();
        let cam = datum_mut(&mut v, 1, "CAMERA_09");
        cam["datum"]["image"]["width"] = 1000.into();
        let small_key = cam["key"].as_str().unwrap().to_string();
        for s in 0..3 {
            let r = &mut datum_mut(&mut v, s, "LIDAR")["datum"]["point_cloud"]["pose"]["rotation"];
            for c in ["qw", "qx", "qy", "qz"] {
                r[c] = (r[c].as_f64().unwrap() * 1.005).into();
            }
        }
        write(&scene_file, &v);
        let calib_file = std::fs::read_dir(root.join("scene_02/calibration")).unwrap().next().unwrap().unwrap().path();
        let mut c = read_json(&calib_file).unwrap();
        // Entries: LIDAR, CAMERA_01, _05, _06, _07, _08, _09.
        c["intrinsics"][3] = serde_json::json!({"cx": 0.0, "cy": 0.0, "fx": 0.0, "fy": 0.0, "skew": 0.0});
        c["extrinsics"][4]["translation"]["x"] = 1000.0.into();
        write(&calib_file, &c);

        let ds = open_at(&root).unwrap();
        assert_eq!(ds.0.warnings.len(), 1, "{:?}", ds.0.warnings);
        assert!(ds.0.warnings[0].contains("3 quaternion(s) off unit norm were normalised"), "{:?}", ds.0.warnings);
        let err = load_err(&ds, "camera_pose", &[0, 0, 1]);
        assert!(
            err.contains(&format!(
                "sample 0 datum {key} (CAMERA_05): field pose.rotation [0, 0, 0, 0] is not a rotation"
            )),
            "{err}"
        );
        assert!(ds.load_source("camera_pose", &ItemKey::new(&[0, 1, 1])).is_ok());
        for f in 0..3 {
            let err = load_err(&ds, "camera_calib", &[0, f, 2]);
            assert!(err.contains("entry 3 (CAMERA_06): field intrinsics[3]") && err.contains("fx 0 and fy 0"), "{err}");
            let err = load_err(&ds, "camera_calib", &[0, f, 3]);
            assert!(err.contains("entry 4 (CAMERA_07): field extrinsics[4].translation [1000, "), "{err}");
        }
        let err = load_err(&ds, "image", &[0, 1, 5]);
        assert!(
            err.contains(&format!("is 1936x1216 but datum {small_key} (fields width, height) says 1000x1216")),
            "{err}"
        );
        assert!(err.contains("rgb/CAMERA_09/"), "{err}");
        // The LiDAR poses were normalised: projection still lands in every camera left intact.
        let lidar = Pose::decode(&ds.load_source("lidar_pose", &ItemKey::new(&[0, 0])).unwrap()).unwrap();
        assert!((lidar.ego_to_world.rotation.length() - 1.0).abs() < 1e-12);
    }
}
