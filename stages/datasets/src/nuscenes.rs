//! nuScenes v1.0 reader: scenes -> keyframes (samples) or LiDAR sweeps -> cameras.
//!
//! Reads the tables `scene`, `sample`, `sample_data`, `ego_pose`, `calibrated_sensor` and
//! `sensor` from `<root>/<version>/`. Quaternions are `[w, x, y, z]`, timestamps microseconds.
//! Every `sample_data` row a frame uses is resolved into the shared surround tree
//! ([`crate::surround`], which gives the items and source ports); this module adds what is
//! nuScenes' own: `.pcd.bin` sweeps with their lidarseg labels, and boxes from
//! `sample_annotation` with the devkit's velocities, interpolated between keyframes for sweeps.

use crate::checks::{
    box_values, image_size, join_inside, pinhole, principal_point_inside, rigid, Fields, Place, Renormalised, Transform,
};
use crate::checks::{MAX_SENSOR_FILE_BYTES, MAX_TABLE_FILE_BYTES};
use crate::files::read_input;
use crate::sidecar::Sidecars;
use crate::surround::{Frame, Reading, Scene, SurroundReader, Tree, DIMS, PORTS};
use anyhow::{anyhow, bail, ensure, Context, Result};
use dist4d_graph::{DatasetSchema, ParamsSpec};
use dist4d_runtime::{Digest, DigestBuilder, FileDigests, ItemKey};
use dist4d_types::artifact::{Box3D, Boxes3D, Calibration, PointCloud, Pose};
use dist4d_types::geometry::Se3;
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::path::{Path, PathBuf};

pub mod infos;
pub mod interp12hz;

/// The six cameras in the devkit's order.
pub const CAMERAS: [&str; 6] =
    ["CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_BACK_RIGHT", "CAM_BACK", "CAM_BACK_LEFT", "CAM_FRONT_LEFT"];

#[derive(Serialize, Deserialize, Clone, Copy, Debug, PartialEq, Eq)]
pub enum FrameMode {
    /// One frame per keyframe (2 Hz `sample`).
    Keyframes,
    /// One frame per LiDAR sweep (20 Hz `sample_data` chain); each camera gives its image
    /// nearest in time, and boxes are interpolated between keyframes.
    Sweeps,
    /// One frame per round of the surround cameras (12 Hz): the images of the first camera
    /// (`cameras[0]`, the reference) and, of every other camera, the image of the same round
    /// (see [`camera_rounds`]). Every image is in exactly one frame and keeps its own timestamp,
    /// pose and calibration; the frame's LiDAR is the sweep nearest the round's time.
    Camera,
}

#[derive(Serialize, Deserialize, Clone, Debug)]
#[serde(deny_unknown_fields, default)]
pub struct NuScenesConfig {
    /// The dataset root (holding `v1.0-*/`, `samples/`, `sweeps/`).
    pub root: String,
    /// Table folder: `v1.0-mini`, `v1.0-trainval` or `v1.0-test`.
    pub version: String,
    /// Camera channels, in item order; by default every camera the data has (the sensors of
    /// modality `camera` with sample_data), the devkit's six in its order first.
    pub cameras: Option<Vec<String>>,
    /// LiDAR channel.
    pub lidar: String,
    /// Keyframes or Sweeps.
    pub frames: FrameMode,
    /// Folder of semantic maps (`<CAMERA>/<image stem>.png`, Cityscapes ids), relative to the
    /// root; none by default (the `semantic` port then gives empty maps).
    pub semantics: Option<String>,
    /// Boxes between keyframes of a track annotated on only one of them: `Extrapolate` (with its
    /// velocity, up to half the keyframe interval, flagged) or `Drop`.
    pub lone_tracks: LoneTracks,
}

#[derive(Serialize, Deserialize, Clone, Copy, Debug, PartialEq, Eq)]
pub enum LoneTracks {
    Extrapolate,
    Drop,
}

impl Default for NuScenesConfig {
    fn default() -> Self {
        NuScenesConfig {
            root: String::new(),
            version: "v1.0-mini".into(),
            cameras: None,
            lidar: "LIDAR_TOP".into(),
            frames: FrameMode::Keyframes,
            semantics: None,
            lone_tracks: LoneTracks::Extrapolate,
        }
    }
}

#[derive(Deserialize)]
struct SceneRow {
    token: String,
    name: String,
    first_sample_token: String,
    #[serde(default)]
    log_token: String,
    /// Free text; the info pickles copy it.
    #[serde(default)]
    description: String,
}

/// A row of map.json: the map mask (semantic prior, 0.1 m per pixel) of the logs it lists.
#[derive(Deserialize)]
struct MapRow {
    token: String,
    filename: String,
    #[serde(default)]
    log_tokens: Vec<String>,
}

#[derive(Deserialize)]
struct SampleRow {
    /// Index in the table file, for errors.
    #[serde(skip)]
    row: usize,
    token: String,
    #[serde(default)]
    scene_token: String,
    #[serde(deserialize_with = "microseconds")]
    timestamp: i64,
    next: String,
}

#[derive(Deserialize)]
struct SampleDataRow {
    token: String,
    sample_token: String,
    ego_pose_token: String,
    calibrated_sensor_token: String,
    filename: String,
    is_key_frame: bool,
    /// Index in the table file, for errors.
    #[serde(skip)]
    row: usize,
    #[serde(default)]
    width: u32,
    #[serde(default)]
    height: u32,
    #[serde(deserialize_with = "microseconds")]
    timestamp: i64,
    #[serde(default)]
    prev: String,
    #[serde(default)]
    next: String,
}

#[derive(Deserialize)]
struct CalibratedSensorRow {
    #[serde(skip)]
    row: usize,
    token: String,
    sensor_token: String,
    translation: [f64; 3],
    rotation: [f64; 4],
    #[serde(default)]
    camera_intrinsic: Vec<Vec<f64>>,
}

#[derive(Deserialize)]
struct SensorRow {
    token: String,
    channel: String,
    #[serde(default)]
    modality: String,
}

#[derive(Deserialize)]
struct EgoPoseRow {
    #[serde(skip)]
    row: usize,
    token: String,
    translation: [f64; 3],
    rotation: [f64; 4],
}

#[derive(Deserialize, Clone)]
struct AnnotationRow {
    /// Index in the table file, for errors.
    #[serde(skip)]
    row: usize,
    token: String,
    sample_token: String,
    instance_token: String,
    #[serde(default)]
    attribute_tokens: Vec<String>,
    translation: [f64; 3],
    size: [f64; 3],
    rotation: [f64; 4],
    #[serde(default)]
    prev: String,
    #[serde(default)]
    next: String,
    #[serde(default)]
    num_lidar_pts: u32,
    /// Read by the info pickles only (`num_radar_pts`, `visibility`, `valid_flag`).
    #[serde(default)]
    num_radar_pts: u32,
    #[serde(default)]
    visibility_token: String,
}

#[derive(Deserialize)]
struct InstanceRow {
    token: String,
    category_token: String,
}

#[derive(Deserialize)]
struct NamedRow {
    token: String,
    name: String,
}

#[derive(Deserialize)]
struct LidarsegRow {
    #[serde(skip)]
    row: usize,
    #[serde(default)]
    token: String,
    sample_data_token: String,
    filename: String,
}

/// A timestamp in microseconds: an integer, as nuScenes writes it, or a number with a fraction,
/// as ASAP's `interp_12Hz_*` tables write their evenly spaced times (rounded to the microsecond).
fn microseconds<'de, D: serde::Deserializer<'de>>(d: D) -> Result<i64, D::Error> {
    let value = serde_json::Number::deserialize(d)?;
    if let Some(us) = value.as_i64() {
        return Ok(us);
    }
    match value.as_f64() {
        Some(us) if us.is_finite() && us.abs() < 9.0e18 => Ok(us.round() as i64),
        _ => Err(serde::de::Error::custom(format!("{value} is not a timestamp in microseconds"))),
    }
}

/// What a nuScenes frame keeps beside its readings.
pub struct Sweep {
    /// The frame's time (its LiDAR timestamp) and the keyframe (sample) it is or follows.
    timestamp: i64,
    sample: Option<usize>,
    key: bool,
    /// nuScenes-lidarseg labels of the frame's LiDAR reading, when the dataset has them.
    labels: Option<PathBuf>,
    /// Each camera's `sample_data` token in this frame, also when the reading failed to resolve
    /// (what the 12 Hz export regroups; `None` where the frame has no image of that camera).
    images: Vec<Option<String>>,
}

/// A scene's keyframe timestamps, and the annotations of each keyframe (indices into
/// `NuScenes::annotations`).
type Keyframes = Vec<(i64, Vec<usize>)>;

/// One box annotation with what its frame needs.
struct Annotation {
    row: AnnotationRow,
    /// Why the row is not a box (a zero quaternion, a negative size, a NaN): the frames whose
    /// boxes need it fail with this, and no NaN ever reaches a `Boxes3D` artifact.
    problem: Option<String>,
    category: String,
    attributes: Vec<String>,
}

pub struct NuScenes {
    pub config: NuScenesConfig,
    tree: Tree<Keyframes, Sweep>,
    /// The `scene` token of each scene of the tree.
    scene_tokens: Vec<String>,
    /// Each scene's map mask (map.json's file for the scene's log), if it has one.
    maps: Vec<Option<PathBuf>>,
    /// Each scene's sample tokens, in the order of its keyframes (the tree's scene extra).
    sample_tokens: Vec<Vec<String>>,
    annotations: Vec<Annotation>,
    annotation_by_token: HashMap<String, usize>,
    sample_time: HashMap<String, i64>,
    /// What was missing but optional, repeated or normalised (printed when the dataset is opened).
    pub warnings: Vec<String>,
    /// Whether the dataset has nuScenes-lidarseg labels (a `lidarseg` table with rows): stages
    /// that would fall back to geometry without them say so when the run starts.
    pub has_point_labels: bool,
}

/// A table row; the tables whose rows errors cite keep their index in the file.
trait TableRow: for<'de> Deserialize<'de> {
    fn set_row(&mut self, _row: usize) {}
}

macro_rules! rows_without_index {
    ($($t:ty),*) => { $(impl TableRow for $t {})* };
}
rows_without_index!(SceneRow, SensorRow, InstanceRow, NamedRow, MapRow);

macro_rules! rows_with_index {
    ($($t:ty),*) => { $(impl TableRow for $t { fn set_row(&mut self, row: usize) { self.row = row; } })* };
}
rows_with_index!(SampleDataRow, CalibratedSensorRow, EgoPoseRow, LidarsegRow, SampleRow, AnnotationRow);

/// Reads a table; a malformed row is reported with its index, token and the field at fault.
fn read_table<T: TableRow>(dir: &Path, name: &str, warnings: &mut Vec<String>) -> Result<Vec<T>> {
    let path = dir.join(format!("{name}.json"));
    let bytes = read_input(&path, "the nuScenes table", MAX_TABLE_FILE_BYTES)?;
    // Row by row: the JSON tree of a whole table takes several times its bytes (trainval's
    // sample_data.json alone is over a gigabyte, its 12 Hz tables more), so each row is parsed,
    // checked for a repeated token and typed on its own, and its tree dropped.
    let raw: Vec<&serde_json::value::RawValue> = serde_json::from_slice(&bytes)
        .with_context(|| format!("malformed nuScenes table {}: not a JSON list", path.display()))?;
    let mut tokens = UniqueTokens::new(&path, &raw);
    let mut rows = Vec::with_capacity(raw.len());
    for (i, text) in raw.iter().enumerate() {
        let row: serde_json::Value = serde_json::from_str(text.get())
            .with_context(|| format!("malformed nuScenes table {}: row {i}", path.display()))?;
        let token = row.get("token").and_then(|t| t.as_str()).map(str::to_string);
        if let Some(token) = &token {
            if tokens.repeated(i, token, &row)? {
                continue;
            }
        }
        let mut parsed: T = serde_path_to_error::deserialize(row).map_err(|e| {
            anyhow!(
                "malformed nuScenes table {}: row {i} (token {}), field `{}`: {}",
                path.display(),
                token.as_deref().unwrap_or("?"),
                e.path(),
                e.inner()
            )
        })?;
        parsed.set_row(i);
        rows.push(parsed);
    }
    tokens.warn(warnings);
    Ok(rows)
}

/// Each token of a table once. Two different rows with one token are an error naming both: every
/// lookup by token would silently take one of them. A row that repeats an earlier one exactly is
/// dropped with a warning (nothing is ambiguous, but a tool wrote the table twice over). Kept as a
/// 16-byte digest of each token and its row's index, not the rows (trainval's sample_data has
/// millions): on a repeated token the earlier row is parsed again from the table's text.
struct UniqueTokens<'p, 'r> {
    path: &'p Path,
    raw: &'r [&'r serde_json::value::RawValue],
    first: HashMap<[u8; 16], usize>,
    repeats: usize,
    /// The first repeat: (earlier row, the repeat, token).
    first_repeat: Option<(usize, usize, String)>,
}

impl<'p, 'r> UniqueTokens<'p, 'r> {
    fn new(path: &'p Path, raw: &'r [&'r serde_json::value::RawValue]) -> Self {
        UniqueTokens { path, raw, first: HashMap::with_capacity(raw.len()), repeats: 0, first_repeat: None }
    }

    /// Whether row `i` repeats an earlier row exactly (to be dropped); an error when it has an
    /// earlier row's token and other contents.
    fn repeated(&mut self, i: usize, token: &str, row: &serde_json::Value) -> Result<bool> {
        use std::collections::hash_map::Entry;
        let key: [u8; 16] = blake3::hash(token.as_bytes()).as_bytes()[..16].try_into().expect("16 of 32 bytes");
        let earlier = match self.first.entry(key) {
            Entry::Vacant(e) => {
                e.insert(i);
                return Ok(false);
            }
            Entry::Occupied(e) => *e.get(),
        };
        let before: serde_json::Value = serde_json::from_str(self.raw[earlier].get()).unwrap_or_default();
        // Two tokens with one digest would be 2^-64 unlikely; still, only equal tokens compare.
        if before.get("token").and_then(|t| t.as_str()) != Some(token) {
            return Ok(false);
        }
        if before != *row {
            bail!("{}: rows {earlier} and {i} have the same token {token} but different contents", self.path.display());
        }
        self.repeats += 1;
        self.first_repeat.get_or_insert((earlier, i, token.to_string()));
        Ok(true)
    }

    fn warn(self, warnings: &mut Vec<String>) {
        if let Some((earlier, again, token)) = self.first_repeat {
            warnings.push(format!(
                "{}: {} row(s) repeat an earlier row exactly and were dropped (first: row {again} repeats row {earlier}, \
                 token {token})",
                self.path.display(),
                self.repeats,
            ));
        }
    }
}

/// An optional table: missing is a warning and no rows; malformed is still an error.
fn read_optional<T: TableRow>(dir: &Path, name: &str, warnings: &mut Vec<String>, why: &str) -> Result<Vec<T>> {
    if !dir.join(format!("{name}.json")).exists() {
        warnings.push(format!("{}/{name}.json is missing: {why}", dir.display()));
        return Ok(Vec::new());
    }
    read_table(dir, name, warnings)
}

/// An empty `sample_data` table, or one without keyframes, is one error when the dataset is
/// opened rather than one per task: every frame starts at a keyframe.
fn ensure_keyframes(rows: &[SampleDataRow], file: &Path) -> Result<()> {
    if rows.is_empty() {
        bail!("{} has no rows: the dataset has no sensor data", file.display());
    }
    if !rows.iter().any(|r| r.is_key_frame) {
        bail!(
            "{} has {} rows but no keyframe (is_key_frame: true); frames start at keyframes",
            file.display(),
            rows.len()
        );
    }
    Ok(())
}

/// The field names of the nuScenes transforms (`ego_pose`, `calibrated_sensor`).
const TRANSFORM_FIELDS: Fields = Fields { rotation: "rotation", translation: "translation" };

/// A `calibrated_sensor` row, checked: its mounting and, for cameras, its intrinsics.
struct Mount {
    sensor_to_ego: Se3,
    intrinsics: Option<[[f64; 3]; 3]>,
    /// The row, for errors found later against a `sample_data` row (principal point vs image size).
    at: Place,
}

fn check_mount(cs: &CalibratedSensorRow, file: &Path, notes: &mut Renormalised) -> Result<Mount, String> {
    let at = Place::row(file, cs.row, &cs.token);
    let sensor_to_ego = rigid(&at, TRANSFORM_FIELDS, cs.rotation, cs.translation, Transform::Mount, notes)?;
    let intrinsics = match cs.camera_intrinsic.as_slice() {
        [] => None,
        [a, b, c] if a.len() == 3 && b.len() == 3 && c.len() == 3 => {
            Some(pinhole(&at, "camera_intrinsic", [[a[0], a[1], a[2]], [b[0], b[1], b[2]], [c[0], c[1], c[2]]])?)
        }
        _ => return Err(format!("{at}: field camera_intrinsic is not a 3x3 matrix")),
    };
    Ok(Mount { sensor_to_ego, intrinsics, at })
}

/// The error of a token that names no row of the table it points into.
fn dangling(file: &Path, row: usize, token: &str, field: &str, value: &str, table: &str) -> String {
    format!("{}: field {field} {value} names no {table} row", Place::row(file, row, token))
}

/// The camera channels the data has: sensors of modality `camera` that some `sample_data` row
/// is of, the devkit's six in its order first, then the others by name.
fn data_cameras(
    sensors: &[SensorRow],
    calibs: &[CalibratedSensorRow],
    sample_data: &[SampleDataRow],
) -> Result<Vec<String>> {
    let used: std::collections::HashSet<&str> =
        sample_data.iter().map(|sd| sd.calibrated_sensor_token.as_str()).collect();
    let with_data: std::collections::HashSet<&str> =
        calibs.iter().filter(|c| used.contains(c.token.as_str())).map(|c| c.sensor_token.as_str()).collect();
    let mut cameras: Vec<String> = sensors
        .iter()
        .filter(|s| s.modality == "camera" && with_data.contains(s.token.as_str()))
        .map(|s| s.channel.clone())
        .collect();
    cameras.sort_by_key(|c| (CAMERAS.iter().position(|k| k == c).unwrap_or(CAMERAS.len()), c.clone()));
    cameras.dedup();
    ensure!(!cameras.is_empty(), "no sensor of modality \"camera\" has sample_data");
    Ok(cameras)
}

/// Whether a nuScenes file name says it is of `channel` (`samples/CAM_FRONT/..__CAM_FRONT__..`).
fn names_channel(filename: &str, channel: &str) -> bool {
    filename.contains(&format!("__{channel}__")) || filename.split('/').any(|part| part == channel)
}

/// Why `root` has no `version` table folder, in the words that lead to the fix: a path that does
/// not exist, a DGP dataset or scene (another reader), other versions than the one asked for.
fn not_nuscenes(root: &Path, config: &NuScenesConfig) -> String {
    let given = format!("(dataset.root = {:?}, dataset.version = {:?})", config.root, config.version);
    if !root.exists() {
        return format!("{} does not exist {given}", root.display());
    }
    if !root.is_dir() {
        return format!("{} is a file, not a nuScenes folder {given}", root.display());
    }
    let names: Vec<String> = std::fs::read_dir(root)
        .map(|d| d.filter_map(|e| e.ok()).map(|e| e.file_name().to_string_lossy().into_owned()).collect())
        .unwrap_or_default();
    let json_named = |prefix: &str| names.iter().any(|n| n.starts_with(prefix) && n.ends_with(".json"));
    if json_named("scene_dataset") {
        return format!(
            "{} looks like a DGP dataset (it holds a scene_dataset*.json), not nuScenes: read it with \
             `dataset: Dgp(root: {:?})` (or --set 'dataset=Dgp(root: {:?})') {given}",
            root.display(),
            config.root,
            config.root
        );
    }
    if json_named("scene_") {
        return format!(
            "{} looks like a DGP scene (it holds a scene_*.json), not nuScenes: read the folder holding its \
             scene_dataset*.json with `dataset: Dgp(root: ..)` {given}",
            root.display()
        );
    }
    let mut versions: Vec<&String> = names.iter().filter(|n| n.starts_with("v1.0-") && root.join(n).is_dir()).collect();
    versions.sort();
    if !versions.is_empty() {
        let list: Vec<String> = versions.iter().map(|v| format!("{v:?}")).collect();
        return format!(
            "{} has no {} tables, but {}: set dataset.version {given}",
            root.display(),
            config.version,
            list.join(", ")
        );
    }
    format!(
        "{} is not a nuScenes {} folder: it has no {}/ with the tables {given}",
        root.display(),
        config.version,
        config.version
    )
}

/// The tables of one version folder, each read once and in one order, so that a table's error or
/// warning always comes where it did.
struct Tables {
    /// The dataset root (file names are relative to it) and its `<version>/` folder.
    root: PathBuf,
    dir: PathBuf,
    scenes: Vec<SceneRow>,
    samples: Vec<SampleRow>,
    sample_data: Vec<SampleDataRow>,
    calibs: Vec<CalibratedSensorRow>,
    sensors: Vec<SensorRow>,
    poses: Vec<EgoPoseRow>,
    /// The optional tables of the boxes; empty when missing (a warning).
    annotations: Vec<AnnotationRow>,
    instances: Vec<InstanceRow>,
    categories: Vec<NamedRow>,
    attributes: Vec<NamedRow>,
    /// Each log's map mask (map.json), for the maps whose file exists.
    map_of_log: HashMap<String, PathBuf>,
    /// nuScenes-lidarseg, an add-on: empty when absent.
    lidarseg: Vec<LidarsegRow>,
}

impl Tables {
    /// Reads the tables `open` uses: a missing optional table, a repeated row or a map that is not
    /// there is a warning; a missing or malformed required table, or a `sample_data` without
    /// keyframes, is the error.
    fn read(config: &NuScenesConfig, w: &mut Vec<String>) -> Result<Tables> {
        let root = PathBuf::from(&config.root);
        let dir = root.join(&config.version);
        if !dir.is_dir() {
            bail!("{}", not_nuscenes(&root, config));
        }
        let scenes: Vec<SceneRow> = read_table(&dir, "scene", w)?;
        let samples: Vec<SampleRow> = read_table(&dir, "sample", w)?;
        let sample_data: Vec<SampleDataRow> = read_table(&dir, "sample_data", w)?;
        let calibs: Vec<CalibratedSensorRow> = read_table(&dir, "calibrated_sensor", w)?;
        let sensors: Vec<SensorRow> = read_table(&dir, "sensor", w)?;
        let poses: Vec<EgoPoseRow> = read_table(&dir, "ego_pose", w)?;
        let no_boxes = "frames have no boxes";
        let annotations: Vec<AnnotationRow> = read_optional(&dir, "sample_annotation", w, no_boxes)?;
        let instances: Vec<InstanceRow> = read_optional(&dir, "instance", w, no_boxes)?;
        let categories: Vec<NamedRow> = read_optional(&dir, "category", w, "boxes have no category")?;
        let attributes: Vec<NamedRow> = read_optional(&dir, "attribute", w, "boxes have no attributes")?;
        for t in ["log", "visibility"] {
            if !dir.join(format!("{t}.json")).exists() {
                w.push(format!("{}/{t}.json is missing (not needed by dist4d)", dir.display()));
            }
        }
        let map_rows: Vec<MapRow> = read_optional(&dir, "map", w, "the `map` port is empty")?;
        let map_of_log = maps_of_logs(&root, &dir, &map_rows, w);
        // lidarseg is an add-on: absent means no labels, without a warning.
        let lidarseg: Vec<LidarsegRow> =
            if dir.join("lidarseg.json").exists() { read_table(&dir, "lidarseg", w)? } else { Vec::new() };
        ensure_keyframes(&sample_data, &dir.join("sample_data.json"))?;
        Ok(Tables {
            root,
            dir,
            scenes,
            samples,
            sample_data,
            calibs,
            sensors,
            poses,
            annotations,
            instances,
            categories,
            attributes,
            map_of_log,
            lidarseg,
        })
    }

    /// The frames' cameras: `dataset.cameras`, or every camera the data has.
    fn cameras(&self, config: &NuScenesConfig) -> Result<Vec<String>> {
        Ok(match &config.cameras {
            Some(c) => c.clone(),
            None => data_cameras(&self.sensors, &self.calibs, &self.sample_data)
                .with_context(|| format!("{}: set dataset.cameras", self.dir.join("sensor.json").display()))?,
        })
    }
}

/// Each log's map mask file (map.json). A bad filename only costs the map (a control for
/// generators), never the dataset: it is a warning, as is a map file that does not exist.
fn maps_of_logs(root: &Path, dir: &Path, map_rows: &[MapRow], w: &mut Vec<String>) -> HashMap<String, PathBuf> {
    let map_file = dir.join("map.json");
    let mut map_of_log: HashMap<String, PathBuf> = HashMap::new();
    for (row, m) in map_rows.iter().enumerate() {
        match join_inside(root, &Place::row(&map_file, row, &m.token), "filename", &m.filename) {
            Ok(path) if path.is_file() => {
                for log in &m.log_tokens {
                    map_of_log.insert(log.clone(), path.clone());
                }
            }
            Ok(path) => w.push(format!("{}: row {row}: the map {} does not exist", map_file.display(), path.display())),
            Err(e) => w.push(e),
        }
    }
    map_of_log
}

impl Annotation {
    /// The annotation rows as boxes' annotations, category and attribute names resolved; a row
    /// that is no box keeps why. Quaternions a little off unit norm are normalised (one warning).
    fn from_rows(rows: Vec<AnnotationRow>, tables: &Tables, warnings: &mut Vec<String>) -> Vec<Annotation> {
        let cat_name: HashMap<&str, &str> =
            tables.categories.iter().map(|c| (c.token.as_str(), c.name.as_str())).collect();
        let attr_name: HashMap<&str, &str> =
            tables.attributes.iter().map(|c| (c.token.as_str(), c.name.as_str())).collect();
        let inst_cat: HashMap<&str, &str> = tables
            .instances
            .iter()
            .map(|i| (i.token.as_str(), cat_name.get(i.category_token.as_str()).copied().unwrap_or("")))
            .collect();
        let ann_file = tables.dir.join("sample_annotation.json");
        let mut box_rotations = Renormalised::default();
        let annotations: Vec<Annotation> = rows
            .into_iter()
            .map(|mut row| {
                let at = Place::row(&ann_file, row.row, &row.token);
                let problem = match box_values(&at, row.translation, row.size, row.rotation, &mut box_rotations) {
                    Ok(rotation) => {
                        row.rotation = rotation;
                        None
                    }
                    Err(e) => Some(e),
                };
                (row, problem)
            })
            .map(|(row, problem)| Annotation {
                problem,
                category: inst_cat.get(row.instance_token.as_str()).copied().unwrap_or("").to_string(),
                attributes: row
                    .attribute_tokens
                    .iter()
                    .filter_map(|t| attr_name.get(t.as_str()).map(|s| s.to_string()))
                    .collect(),
                row,
            })
            .collect();
        warnings.extend(box_rotations.warnings());
        annotations
    }
}

/// The annotations of each sample (indices into `annotations`), by sample token.
fn annotations_of_samples(annotations: &[Annotation]) -> HashMap<&str, Vec<usize>> {
    let mut anns_of_sample: HashMap<&str, Vec<usize>> = HashMap::new();
    for (i, a) in annotations.iter().enumerate() {
        anns_of_sample.entry(a.row.sample_token.as_str()).or_default().push(i);
    }
    anns_of_sample
}

/// The rows the frames are made of, by token, each checked once: a bad row becomes the error of
/// the items that use it, not of the dataset.
struct Rows<'a> {
    tables: &'a Tables,
    config: &'a NuScenesConfig,
    cameras: &'a [String],
    /// `sample_data.json` and `calibrated_sensor.json`, which the errors name.
    sd_file: PathBuf,
    cs_file: PathBuf,
    /// Each LiDAR `sample_data`'s lidarseg labels file, by its token.
    labels_by: HashMap<&'a str, Result<PathBuf, String>>,
    pose_by: HashMap<&'a str, Result<Se3, String>>,
    calib_by: HashMap<&'a str, (&'a CalibratedSensorRow, Result<Mount, String>)>,
    sample_by: HashMap<&'a str, &'a SampleRow>,
    /// Each sensor's channel, by the sensor's token.
    channel_by: HashMap<&'a str, &'a str>,
    sd_by: HashMap<&'a str, &'a SampleDataRow>,
    /// Keyframe sample_data by (sample, channel); those whose channel is unknown, by sample.
    keyframe: HashMap<(&'a str, &'a str), &'a SampleDataRow>,
    unresolved: HashMap<&'a str, Vec<(&'a SampleDataRow, String)>>,
}

impl<'a> Rows<'a> {
    /// Checks the poses, mounts and label files and indexes the rows; quaternions a little off
    /// unit norm are normalised (one warning per table).
    fn index(
        tables: &'a Tables,
        config: &'a NuScenesConfig,
        cameras: &'a [String],
        warnings: &mut Vec<String>,
    ) -> Self {
        let dir = &tables.dir;
        let (sd_file, cs_file) = (dir.join("sample_data.json"), dir.join("calibrated_sensor.json"));
        let mut renormalised = Renormalised::default();
        let seg_file = dir.join("lidarseg.json");
        let labels_by: HashMap<&str, Result<PathBuf, String>> = tables
            .lidarseg
            .iter()
            .map(|l| {
                let at = Place::row(&seg_file, l.row, &l.token);
                (l.sample_data_token.as_str(), join_inside(&tables.root, &at, "filename", &l.filename))
            })
            .collect();
        let pose_file = dir.join("ego_pose.json");
        let pose_by: HashMap<&str, Result<Se3, String>> = tables
            .poses
            .iter()
            .map(|p| {
                let at = Place::row(&pose_file, p.row, &p.token);
                let pose = rigid(&at, TRANSFORM_FIELDS, p.rotation, p.translation, Transform::Pose, &mut renormalised);
                (p.token.as_str(), pose)
            })
            .collect();
        let calib_by: HashMap<&str, (&CalibratedSensorRow, Result<Mount, String>)> = tables
            .calibs
            .iter()
            .map(|c| (c.token.as_str(), (c, check_mount(c, &cs_file, &mut renormalised))))
            .collect();
        warnings.extend(renormalised.warnings());
        let mut rows = Rows {
            tables,
            config,
            cameras,
            sd_file,
            cs_file,
            labels_by,
            pose_by,
            calib_by,
            sample_by: tables.samples.iter().map(|s| (s.token.as_str(), s)).collect(),
            channel_by: tables.sensors.iter().map(|s| (s.token.as_str(), s.channel.as_str())).collect(),
            sd_by: tables.sample_data.iter().map(|s| (s.token.as_str(), s)).collect(),
            keyframe: HashMap::new(),
            unresolved: HashMap::new(),
        };
        for sd in tables.sample_data.iter().filter(|sd| sd.is_key_frame) {
            match rows.channel_of(sd) {
                Ok(channel) => {
                    rows.keyframe.insert((sd.sample_token.as_str(), channel), sd);
                }
                Err(e) => rows.unresolved.entry(sd.sample_token.as_str()).or_default().push((sd, e)),
            }
        }
        rows
    }

    fn mount_of(&self, sd: &SampleDataRow) -> Result<&(&'a CalibratedSensorRow, Result<Mount, String>), String> {
        self.calib_by.get(sd.calibrated_sensor_token.as_str()).ok_or_else(|| {
            let (field, value) = ("calibrated_sensor_token", &sd.calibrated_sensor_token);
            dangling(&self.sd_file, sd.row, &sd.token, field, value, "calibrated_sensor")
        })
    }

    fn channel_of(&self, sd: &SampleDataRow) -> Result<&'a str, String> {
        let (cs, _) = self.mount_of(sd)?;
        self.channel_by
            .get(cs.sensor_token.as_str())
            .copied()
            .ok_or_else(|| dangling(&self.cs_file, cs.row, &cs.token, "sensor_token", &cs.sensor_token, "sensor"))
    }

    /// Why a sample has no keyframe of a channel: a keyframe of it whose sensor is unknown and
    /// whose file name says that channel is the one, and its dangling token the reason.
    fn no_keyframe(&self, sample: &str, channel: &str) -> String {
        let unknown = self.unresolved.get(sample).map(Vec::as_slice).unwrap_or_default();
        let named: Vec<&str> =
            unknown.iter().filter(|(sd, _)| names_channel(&sd.filename, channel)).map(|(_, e)| e.as_str()).collect();
        if !named.is_empty() {
            return named.join("; ");
        }
        let mut why = format!("sample {sample} has no keyframe sample_data for channel {channel}");
        if !unknown.is_empty() {
            let errors: Vec<&str> = unknown.iter().map(|(_, e)| e.as_str()).collect();
            why += &format!(" (its keyframes of unknown channel: {})", errors.join("; "));
        }
        why
    }

    /// A `sample_data` row as a reading: its file, mount, pose and (for a camera) image size,
    /// each checked.
    fn resolve(&self, sd: &SampleDataRow, camera: bool) -> Result<Reading, String> {
        let at = Place::row(&self.sd_file, sd.row, &sd.token);
        let file = join_inside(&self.tables.root, &at, "filename", &sd.filename)?;
        let mount = self.mount_of(sd)?.1.as_ref().map_err(String::clone)?;
        if camera {
            image_size(&at.to_string(), "fields width, height", sd.width, sd.height)?;
        }
        if sd.timestamp < 0 {
            return Err(format!("{at}: field timestamp {} is negative", sd.timestamp));
        }
        match &mount.intrinsics {
            Some(k) => principal_point_inside(&mount.at, "camera_intrinsic", k, sd.width, sd.height)
                .map_err(|e| format!("{e} of {at}"))?,
            None if camera => {
                return Err(format!("{}: field camera_intrinsic is empty, but {at} is a camera image", mount.at))
            }
            None => {}
        }
        let ego_to_world = self
            .pose_by
            .get(sd.ego_pose_token.as_str())
            .ok_or_else(|| {
                dangling(&self.sd_file, sd.row, &sd.token, "ego_pose_token", &sd.ego_pose_token, "ego_pose")
            })?
            .clone()?;
        Ok(Reading {
            file,
            calib: Calibration {
                sensor_to_ego: mount.sensor_to_ego,
                intrinsics: mount.intrinsics,
                width: sd.width,
                height: sd.height,
            },
            pose: Pose { ego_to_world, timestamp_us: sd.timestamp },
            what: format!("sample_data {}", sd.token),
            token: sd.token.clone(),
            row: None,
            stored_file: None,
        })
    }

    /// A LiDAR reading and its lidarseg labels: a refused labels file fails the whole reading.
    fn resolve_lidar(&self, sd: &SampleDataRow) -> Result<(Reading, Option<PathBuf>), String> {
        let reading = self.resolve(sd, false)?;
        Ok((reading, self.labels_by.get(sd.token.as_str()).cloned().transpose()?))
    }

    fn key_row(&self, sample: &str, channel: &str) -> Result<&'a SampleDataRow, String> {
        self.keyframe.get(&(sample, channel)).copied().ok_or_else(|| self.no_keyframe(sample, channel))
    }

    /// A channel's whole sample_data chain through a keyframe (prev to the start, next to the end).
    fn chain(&self, start: &'a SampleDataRow) -> Result<Vec<&'a SampleDataRow>> {
        let (sd_by, dir) = (&self.sd_by, &self.tables.dir);
        let mut first = start;
        let mut guard = 0;
        while !first.prev.is_empty() {
            first = sd_by.get(first.prev.as_str()).ok_or_else(|| {
                anyhow!(
                    "{}/sample_data.json: sample_data {}: field prev {} names no row",
                    dir.display(),
                    first.token,
                    first.prev
                )
            })?;
            guard += 1;
            anyhow::ensure!(guard < 1_000_000, "sample_data {}: the prev chain does not end", start.token);
        }
        let mut out = vec![first];
        while !out.last().map_or(true, |s| s.next.is_empty()) {
            let cur = out[out.len() - 1];
            out.push(sd_by.get(cur.next.as_str()).ok_or_else(|| {
                anyhow!(
                    "{}/sample_data.json: sample_data {}: field next {} names no row",
                    dir.display(),
                    cur.token,
                    cur.next
                )
            })?);
            anyhow::ensure!(out.len() < 1_000_000, "sample_data {}: the next chain does not end", start.token);
        }
        Ok(out)
    }

    /// Every scene that has samples, with its frames. A scene no sample names is left out (one
    /// warning for them all), as are the frames of none; a scene whose keyframes are out of time
    /// order has every frame fail.
    fn scenes(&self, anns_of_sample: &HashMap<&str, Vec<usize>>, warnings: &mut Vec<String>) -> Result<Scenes> {
        let dir = &self.tables.dir;
        let mut out = Scenes::default();
        let mut skipped: Vec<&str> = Vec::new();
        let mut keyframes_only: Vec<(&str, usize)> = Vec::new();
        let scenes_sampled: std::collections::HashSet<&str> =
            self.tables.samples.iter().map(|s| s.scene_token.as_str()).collect();
        for scene in &self.tables.scenes {
            let Some(keys) = self.keyframes_of(scene, &scenes_sampled)? else {
                skipped.push(scene.name.as_str());
                continue;
            };
            let samples_of_scene: Vec<(i64, Vec<usize>)> = keys
                .iter()
                .map(|k| (k.timestamp, anns_of_sample.get(k.token.as_str()).cloned().unwrap_or_default()))
                .collect();
            let mut frames: Vec<Frame<Sweep>> = match self.config.frames {
                FrameMode::Keyframes => self.keyframe_frames(&keys),
                FrameMode::Sweeps => self.sweep_frames(scene, &keys)?,
                FrameMode::Camera => self.camera_frames(scene, &keys, &mut keyframes_only, warnings)?,
            };
            fail_frames_on_keyframe_times(&keys, &mut frames, &dir.join("sample.json"));
            out.scenes.push(Scene { name: scene.name.clone(), frames, extra: samples_of_scene });
            out.tokens.push(scene.token.clone());
            out.maps.push(self.tables.map_of_log.get(scene.log_token.as_str()).cloned());
            out.sample_tokens.push(keys.iter().map(|k| k.token.clone()).collect());
        }
        if let Some((first, rounds)) = keyframes_only.first() {
            warnings.push(format!(
                "{} scene(s) have camera images at keyframes only (no sweeps between them): frames: Camera gives one \
                 round per keyframe, not 12 Hz (first: {first}, {rounds} round(s))",
                keyframes_only.len()
            ));
        }
        if let Some(first) = skipped.first() {
            warnings.push(format!(
                "{}/scene.json: {} scene(s) name a first_sample_token that is not in sample.json and have no frames \
                 (first: {first}); a folder written for one split (ASAP's interp_12Hz) keeps the others' scenes",
                dir.display(),
                skipped.len()
            ));
        }
        ensure!(!out.scenes.is_empty(), "{}: no scene has samples", dir.join("scene.json").display());
        Ok(out)
    }

    /// A scene's samples along their `next` chain; `None` for a scene no sample names.
    fn keyframes_of(
        &self,
        scene: &SceneRow,
        scenes_sampled: &std::collections::HashSet<&str>,
    ) -> Result<Option<Vec<&'a SampleRow>>> {
        let mut keys: Vec<&SampleRow> = Vec::new();
        let mut token = scene.first_sample_token.as_str();
        if !token.is_empty() && !self.sample_by.contains_key(token) && !scenes_sampled.contains(scene.token.as_str()) {
            // ASAP's interp_12Hz folders keep every scene of trainval but the samples of the
            // val split only: a scene no sample names has no frames, which the open report
            // says. (A scene with samples but a wrong first token is still an error below.)
            return Ok(None);
        }
        while !token.is_empty() {
            let sample = self.sample_by.get(token).ok_or_else(|| {
                anyhow!(
                    "{}/sample.json: no sample with token {token} (named by scene {} or a sample's `next`)",
                    self.tables.dir.display(),
                    scene.token
                )
            })?;
            keys.push(sample);
            token = sample.next.as_str();
            if keys.len() > 100_000 {
                bail!("scene {}: the sample `next` chain does not end", scene.name);
            }
        }
        Ok(Some(keys))
    }

    /// `frames: Keyframes`: one frame per sample, of its keyframe readings.
    fn keyframe_frames(&self, keys: &[&SampleRow]) -> Vec<Frame<Sweep>> {
        keys.iter()
            .enumerate()
            .map(|(i, k)| {
                let lidar = self.key_row(&k.token, &self.config.lidar).and_then(|sd| self.resolve_lidar(sd));
                let cameras = self.cameras.iter().map(|c| {
                    let sd = self.key_row(&k.token, c);
                    (sd.as_ref().ok().map(|sd| sd.token.clone()), sd.and_then(|sd| self.resolve(sd, true)))
                });
                frame(lidar, cameras.collect(), k.timestamp, Some(i), true)
            })
            .collect()
    }

    /// `frames: Sweeps`: one frame per LiDAR sweep of the scene, each camera's image nearest it.
    fn sweep_frames(&self, scene: &SceneRow, keys: &[&SampleRow]) -> Result<Vec<Frame<Sweep>>> {
        let Some(first) = keys.first() else { bail!("scene {}: it has no samples", scene.name) };
        let Some(first_key) = self.keyframe.get(&(first.token.as_str(), self.config.lidar.as_str())) else {
            bail!("scene {}: {}", scene.name, self.no_keyframe(&first.token, &self.config.lidar));
        };
        let lidar_chain = self.chain(first_key)?;
        let camera_chains: Vec<Option<Vec<&SampleDataRow>>> = self
            .cameras
            .iter()
            .map(|c| {
                keys.first()
                    .and_then(|k| self.keyframe.get(&(k.token.as_str(), c.as_str())))
                    .map(|sd| self.chain(sd))
                    .transpose()
            })
            .collect::<Result<_>>()?;
        Ok(lidar_chain
            .iter()
            .map(|sd| {
                let t = sd.timestamp;
                let sample = keys.iter().rposition(|k| k.timestamp <= t);
                let cameras = camera_chains.iter().zip(self.cameras).map(|(ch, name)| {
                    let Some(ch) = ch else {
                        return (None, Err(format!("scene {}: no {name} images", scene.name)));
                    };
                    match ch.iter().min_by_key(|c| (c.timestamp - t).abs()) {
                        Some(nearest) => (Some(nearest.token.clone()), self.resolve(nearest, true)),
                        None => (None, Err("empty chain".to_string())),
                    }
                });
                frame(self.resolve_lidar(sd), cameras.collect(), t, sample, sd.is_key_frame)
            })
            .collect())
    }

    /// `frames: Camera`: one frame per round of the surround cameras ([`camera_rounds`]), the
    /// LiDAR sweep nearest each. A scene with images at keyframes only goes on
    /// `keyframes_only`; incomplete rounds are a warning.
    fn camera_frames(
        &self,
        scene: &'a SceneRow,
        keys: &[&SampleRow],
        keyframes_only: &mut Vec<(&'a str, usize)>,
        warnings: &mut Vec<String>,
    ) -> Result<Vec<Frame<Sweep>>> {
        let Some(first) = keys.first() else { bail!("scene {}: it has no samples", scene.name) };
        // Each camera's whole chain, through its image of the first keyframe.
        let chains: Vec<Result<Vec<&SampleDataRow>, String>> = self
            .cameras
            .iter()
            .map(|c| match self.keyframe.get(&(first.token.as_str(), c.as_str())) {
                Some(sd) => self.chain(sd).map_err(|e| format!("{e:#}")),
                None => Err(format!("scene {}: {}", scene.name, self.no_keyframe(&first.token, c))),
            })
            .collect();
        let lidar = self
            .keyframe
            .get(&(first.token.as_str(), self.config.lidar.as_str()))
            .map(|sd| self.chain(sd))
            .transpose()?
            .unwrap_or_default();
        let times: Vec<Vec<i64>> = chains
            .iter()
            .map(|c| c.as_ref().map(|c| c.iter().map(|sd| sd.timestamp).collect()).unwrap_or_default())
            .collect();
        let rounds = camera_rounds(&times, &self.camera_offsets(keys));
        if rounds.len() <= keys.len() && chains.iter().any(Result::is_ok) {
            keyframes_only.push((scene.name.as_str(), rounds.len()));
        }
        let complete: Vec<bool> = chains.iter().map(|c| c.is_ok()).collect();
        if let Some(note) = incomplete_rounds(&scene.name, self.cameras, &rounds, &complete) {
            warnings.push(note);
        }
        let sample_of: HashMap<&str, usize> = keys.iter().enumerate().map(|(i, k)| (k.token.as_str(), i)).collect();
        let chains = RoundChains { cameras: chains, lidar, sample_of };
        Ok(rounds.iter().enumerate().map(|(n, round)| self.round_frame(scene, keys, &chains, n, round)).collect())
    }

    /// Each camera's offset from the reference (`cameras[0]`): the median over the keyframes, whose
    /// images are one round by the dataset's own definition.
    fn camera_offsets(&self, keys: &[&SampleRow]) -> Vec<i64> {
        let cameras = self.cameras;
        cameras
            .iter()
            .map(|c| {
                let mut d: Vec<i64> = keys
                    .iter()
                    .filter_map(|k| {
                        let own = self.keyframe.get(&(k.token.as_str(), c.as_str()))?;
                        let reference = self.keyframe.get(&(k.token.as_str(), cameras[0].as_str()))?;
                        Some(own.timestamp - reference.timestamp)
                    })
                    .collect();
                d.sort_unstable();
                d.get(d.len() / 2).copied().unwrap_or(0)
            })
            .collect()
    }

    /// The frame of camera round `n` of a scene: its images, the LiDAR sweep nearest its time, and
    /// the sample it is (a keyframe image among its images) or follows.
    fn round_frame(
        &self,
        scene: &SceneRow,
        keys: &[&SampleRow],
        chains: &RoundChains,
        n: usize,
        round: &CameraRound,
    ) -> Frame<Sweep> {
        // (`camera_frames` made no rounds for a scene without samples.)
        let first = keys[0];
        let image = |c: usize| round.images[c].and_then(|j| chains.cameras[c].as_ref().ok().map(|ch| ch[j]));
        let key_image = (0..self.cameras.len()).filter_map(image).find(|sd| sd.is_key_frame);
        let cameras = self.cameras.iter().enumerate().map(|(c, name)| {
            (
                image(c).map(|sd| sd.token.clone()),
                match (&chains.cameras[c], image(c)) {
                    (Err(e), _) => Err(e.clone()),
                    (Ok(_), Some(sd)) => self.resolve(sd, true),
                    (Ok(_), None) => Err(format!(
                        "scene {}: camera round {n} ({} us) has no {name} image: the camera has none within \
                     half a frame period of the round (a dropped frame)",
                        scene.name, round.time
                    )),
                },
            )
        });
        let lidar = match chains.lidar.iter().min_by_key(|sd| (sd.timestamp - round.time).abs()) {
            Some(sd) => self.resolve_lidar(sd),
            None => Err(format!("scene {}: {}", scene.name, self.no_keyframe(&first.token, &self.config.lidar))),
        };
        let sample = match key_image {
            Some(sd) => chains.sample_of.get(sd.sample_token.as_str()).copied(),
            None => keys.iter().rposition(|k| k.timestamp <= round.time),
        };
        frame(lidar, cameras.collect(), round.time, sample, key_image.is_some())
    }
}

/// What a scene's camera rounds are made of: each camera's `sample_data` chain (or why it has
/// none), the LiDAR's (empty without one), and each sample's keyframe index by its token.
struct RoundChains<'a> {
    cameras: Vec<Result<Vec<&'a SampleDataRow>, String>>,
    lidar: Vec<&'a SampleDataRow>,
    sample_of: HashMap<&'a str, usize>,
}

/// The scenes with frames, and what the reader keeps of each.
#[derive(Default)]
struct Scenes {
    scenes: Vec<Scene<Keyframes, Sweep>>,
    /// Each scene's `scene` token, map mask (if its log has one) and sample tokens in keyframe order.
    tokens: Vec<String>,
    maps: Vec<Option<PathBuf>>,
    sample_tokens: Vec<Vec<String>>,
}

/// Keyframes out of time order (swapped, reversed, repeated) would give wrong windows, box
/// interpolation (between keyframes found by time) and velocities anywhere in the scene: every
/// frame of it fails, naming the first bad row. A keyframe before 1970 fails its own frames.
fn fail_frames_on_keyframe_times(keys: &[&SampleRow], frames: &mut [Frame<Sweep>], sample_file: &Path) {
    let (negative, disorder) = keyframe_time_problems(keys, sample_file);
    for f in frames.iter_mut() {
        let why = disorder.as_ref().or_else(|| f.extra.sample.and_then(|k| negative.get(&k)));
        if let Some(why) = why {
            f.lidar = Err(why.clone());
            f.cameras.iter_mut().for_each(|c| *c = Err(why.clone()));
        }
    }
}

impl NuScenes {
    /// Opens a nuScenes version folder: reads its tables, checks and indexes their rows, resolves
    /// the boxes' annotations, and makes each scene's frames (keyframes, sweeps or camera rounds).
    pub fn open(config: NuScenesConfig) -> Result<NuScenes> {
        let mut warnings = Vec::new();
        let mut tables = Tables::read(&config, &mut warnings)?;
        // Moved out, not copied (trainval has over a million): the boxes are made of them once
        // the other rows are indexed, by reference into the tables.
        let annotation_rows = std::mem::take(&mut tables.annotations);
        let cameras = tables.cameras(&config)?;
        let rows = Rows::index(&tables, &config, &cameras, &mut warnings);
        let annotations = Annotation::from_rows(annotation_rows, &tables, &mut warnings);
        let scenes = rows.scenes(&annotations_of_samples(&annotations), &mut warnings)?;
        let annotation_by_token = annotations.iter().enumerate().map(|(i, a)| (a.row.token.clone(), i)).collect();
        let sample_time = tables.samples.iter().map(|s| (s.token.clone(), s.timestamp)).collect();
        let has_point_labels = !tables.lidarseg.is_empty();
        let sidecars = Sidecars::new(&tables.root, config.semantics.as_deref());
        let tree = Tree { root: tables.root, cameras, scenes: scenes.scenes, sidecars };
        Ok(NuScenes {
            config,
            tree,
            scene_tokens: scenes.tokens,
            maps: scenes.maps,
            sample_tokens: scenes.sample_tokens,
            annotations,
            annotation_by_token,
            sample_time,
            warnings,
            has_point_labels,
        })
    }

    /// The devkit's `box_velocity`: centre difference of the neighbouring annotations, NaN when
    /// the track has one annotation or the neighbours are too far apart in time.
    fn velocity(&self, a: &AnnotationRow) -> [f64; 3] {
        let get = |t: &str| self.annotation_by_token.get(t).map(|&i| &self.annotations[i].row);
        let (prev, next) = (get(&a.prev), get(&a.next));
        if prev.is_none() && next.is_none() {
            return [f64::NAN; 3];
        }
        let (first, last) = (prev.unwrap_or(a), next.unwrap_or(a));
        let time = |r: &AnnotationRow| self.sample_time.get(&r.sample_token).copied().unwrap_or(0);
        let dt = (time(last) - time(first)) as f64 * 1e-6;
        let max_dt = if prev.is_some() && next.is_some() { 3.0 } else { 1.5 };
        if dt <= 0.0 || dt > max_dt {
            return [f64::NAN; 3];
        }
        [0, 1, 2].map(|i| (last.translation[i] - first.translation[i]) / dt)
    }

    fn box_of(&self, a: &Annotation) -> Box3D {
        Box3D {
            center: a.row.translation,
            size: a.row.size,
            rotation: a.row.rotation,
            velocity: self.velocity(&a.row),
            instance: a.row.instance_token.clone(),
            category: a.category.clone(),
            attributes: a.attributes.clone(),
            num_lidar_pts: a.row.num_lidar_pts,
            interpolated: false,
            extrapolated: false,
        }
    }
}

/// One round of the surround cameras: its time (the reference image's timestamp, or for a round
/// the reference has no image in, the earliest offset-corrected time of its images) and, per
/// camera, the index of its image in that camera's chain.
#[derive(Debug, PartialEq)]
pub struct CameraRound {
    pub time: i64,
    pub images: Vec<Option<usize>>,
}

/// Groups the images of every camera (`times[c]`: camera c's timestamps in chain order, us) into
/// rounds, each image in exactly one round. Camera 0 is the reference: each of its images opens a
/// round. Every other camera's image, shifted by the camera's `offsets[c]` from the reference,
/// joins the nearest round within half the reference's frame period that has no image of its
/// camera yet (of two claimants, the nearer wins). What is left (a dropped reference image, a
/// stray or duplicated one) forms rounds of its own, grouped the same way. Rounds come out in
/// time order. nuScenes fires each camera as the LiDAR sweeps past it, so the offsets are up to
/// ~50 ms while rounds are ~83 ms apart: the nearest image alone would give one image to two
/// rounds, or skip one, wherever a camera's offset nears half the period.
pub fn camera_rounds(times: &[Vec<i64>], offsets: &[i64]) -> Vec<CameraRound> {
    let cameras = times.len();
    let Some(reference) = times.first() else { return Vec::new() };
    let period = {
        let mut steps: Vec<i64> = reference.windows(2).map(|w| w[1] - w[0]).filter(|&d| d > 0).collect();
        steps.sort_unstable();
        steps.get(steps.len() / 2).copied().unwrap_or(83_333)
    };
    let half = period / 2;
    let mut rounds: Vec<CameraRound> = reference
        .iter()
        .enumerate()
        .map(|(j, &t)| {
            let mut images = vec![None; cameras];
            images[0] = Some(j);
            CameraRound { time: t, images }
        })
        .collect();
    // (corrected time, camera, index) of the images no reference round took.
    let mut left: Vec<(i64, usize, usize)> = Vec::new();
    for c in 1..cameras {
        let offset = offsets.get(c).copied().unwrap_or(0);
        // (round, distance) each image of this camera claims.
        let mut taken: HashMap<usize, (usize, i64)> = HashMap::new();
        for (j, &t) in times[c].iter().enumerate() {
            let tau = t - offset;
            let at = rounds.partition_point(|r| r.time < tau);
            let nearest = [at.checked_sub(1), (at < rounds.len()).then_some(at)]
                .into_iter()
                .flatten()
                .min_by_key(|&r| (rounds[r].time - tau).abs());
            let Some(r) = nearest.filter(|&r| (rounds[r].time - tau).abs() <= half) else {
                left.push((tau, c, j));
                continue;
            };
            let distance = (rounds[r].time - tau).abs();
            match taken.get(&r) {
                Some(&(_, d)) if d <= distance => left.push((tau, c, j)),
                Some(&(other, _)) => {
                    left.push((times[c][other] - offset, c, other));
                    taken.insert(r, (j, distance));
                }
                None => {
                    taken.insert(r, (j, distance));
                }
            }
        }
        for (r, (j, _)) in taken {
            rounds[r].images[c] = Some(j);
        }
    }
    left.sort_unstable();
    let mut extra: Vec<CameraRound> = Vec::new();
    for (tau, c, j) in left {
        match extra.last_mut() {
            Some(round) if tau - round.time <= half && round.images[c].is_none() => round.images[c] = Some(j),
            _ => {
                let mut images = vec![None; cameras];
                images[c] = Some(j);
                extra.push(CameraRound { time: tau, images });
            }
        }
    }
    rounds.extend(extra);
    rounds.sort_by_key(|r| r.time);
    rounds
}

/// The run report's line for a scene whose camera rounds are not all complete, naming the rounds
/// (the first few) and the cameras missing from them; cameras without any image (`has[c]`
/// false) fail on their own account and are not counted.
fn incomplete_rounds(scene: &str, cameras: &[String], rounds: &[CameraRound], has: &[bool]) -> Option<String> {
    let missing: Vec<String> = rounds
        .iter()
        .enumerate()
        .filter_map(|(n, round)| {
            let names: Vec<&str> = (0..cameras.len())
                .filter(|&c| has[c] && round.images[c].is_none())
                .map(|c| cameras[c].as_str())
                .collect();
            (!names.is_empty()).then(|| format!("round {n} without {}", names.join(", ")))
        })
        .collect();
    if missing.is_empty() {
        return None;
    }
    let shown: Vec<&str> = missing.iter().take(5).map(String::as_str).collect();
    Some(format!(
        "scene {scene}: {} of {} camera rounds are incomplete ({}{}); those cameras' items of those rounds fail",
        missing.len(),
        rounds.len(),
        shown.join("; "),
        if missing.len() > shown.len() { "; ..." } else { "" }
    ))
}

/// The timestamps of a scene's keyframes (its samples in `next` order) that cannot be used:
/// by keyframe index, those that are negative; and the first keyframe not after the one before
/// it, if any (the scene's keyframes are then out of time order).
fn keyframe_time_problems(keys: &[&SampleRow], file: &Path) -> (HashMap<usize, String>, Option<String>) {
    let mut negative = HashMap::new();
    let mut disorder = None;
    for (i, k) in keys.iter().enumerate() {
        let at = Place::row(file, k.row, &k.token);
        if k.timestamp < 0 {
            negative.insert(i, format!("{at}: field timestamp {} is negative", k.timestamp));
        }
        if let Some(p) = i.checked_sub(1).map(|j| keys[j]).filter(|p| k.timestamp <= p.timestamp) {
            disorder.get_or_insert_with(|| {
                format!(
                    "{at}: field timestamp {} is not after that of the keyframe before it in the scene (row {}, token \
                     {}: {}); keyframes must be in time order",
                    k.timestamp, p.row, p.token, p.timestamp
                )
            });
        }
    }
    (negative, disorder)
}

/// A frame from its LiDAR reading with that reading's lidarseg labels (none when it failed), and
/// per camera its image's token (when known) and reading.
fn frame(
    lidar: Result<(Reading, Option<PathBuf>), String>,
    cameras: Vec<(Option<String>, Result<Reading, String>)>,
    timestamp: i64,
    sample: Option<usize>,
    key: bool,
) -> Frame<Sweep> {
    let (lidar, labels) = match lidar {
        Ok((reading, labels)) => (Ok(reading), labels),
        Err(e) => (Err(e), None),
    };
    let (images, cameras) = cameras.into_iter().unzip();
    Frame { lidar, cameras, extra: Sweep { timestamp, sample, key, labels, images } }
}

impl SurroundReader for NuScenes {
    /// The Renault Zoe (its self-returns within 0.5 m of the sensor were 24% of the shared
    /// keyframe's sweep); the synthetic world, read by this reader, puts its hatchback inside.
    const EGO_BOX: Option<([f64; 3], [f64; 3])> = Some(dist4d_types::geometry::ego_box::NUSCENES);
    const FORMAT: &'static str = "nuScenes";
    /// Also dist4d's synthetic world, which is written as a nuScenes dataset.
    const SOURCE_DATASET: &'static str = "nuscenes";
    type Scene = Keyframes;
    type Frame = Sweep;

    fn tree(&self) -> &Tree<Keyframes, Sweep> {
        &self.tree
    }

    /// A keyframe's sample token (what Occ3D names its folders by); another frame's LiDAR
    /// `sample_data` token.
    fn frame_token(&self, scene: usize, frame: usize) -> Option<String> {
        let f = self.tree.scenes.get(scene)?.frames.get(frame)?;
        match f.extra.sample.filter(|_| f.extra.key) {
            Some(k) => self.sample_tokens.get(scene)?.get(k).cloned(),
            None => f.lidar.as_ref().ok().map(|r| r.token.clone()),
        }
    }

    fn map_file(&self, scene: usize) -> Option<&Path> {
        self.maps.get(scene)?.as_deref()
    }

    /// The points' digest, and the labels' when the frame has them.
    fn lidar_digest(&self, lidar: &Reading, frame: &Sweep, files: &dyn FileDigests) -> Result<Option<Digest>> {
        let Some(points) = lidar.file_digest(files)? else { return Ok(None) };
        let mut b = DigestBuilder::new("nuscenes.lidar");
        b.digest(&points);
        if let Some(labels) = &frame.labels {
            let digest = files.file_digest(labels).with_context(|| format!("{}: {}", lidar.what, labels.display()))?;
            let Some(l) = digest else { return Ok(None) };
            b.digest(&l);
        }
        Ok(Some(b.finish()))
    }

    fn read_lidar(&self, lidar: &Reading, frame: &Sweep) -> Result<PointCloud> {
        let mut pc = read_pcd_bin(&lidar.file).with_context(|| lidar.what.clone())?;
        if let Some(path) = &frame.labels {
            let labels = read_input(path, "the lidarseg labels", MAX_SENSOR_FILE_BYTES)
                .with_context(|| format!("the lidarseg labels of {}", lidar.what))?;
            if labels.len() != pc.points.len() {
                bail!(
                    "{} has {} labels but {} has {} points",
                    path.display(),
                    labels.len(),
                    lidar.file.display(),
                    pc.points.len()
                );
            }
            pc.labels = labels;
        }
        Ok(pc)
    }

    /// Boxes at the time of the frame's LiDAR sweep (what stages that move or remove its points
    /// need; a camera round's own time is its reference image's, up to ~40 ms away): a keyframe
    /// sweep's own annotations, otherwise [`NuScenes::boxes_at`] its time. Without a LiDAR
    /// reading, at the frame's time.
    fn boxes(&self, item: &ItemKey) -> Result<Boxes3D> {
        let (scene, frame) = self.tree.scene_frame(item)?;
        let t = frame.lidar.as_ref().map_or(frame.extra.timestamp, |l| l.pose.timestamp_us);
        let key = frame.extra.sample.filter(|&k| frame.extra.key && scene.extra.get(k).is_some_and(|s| s.0 == t));
        Ok(Boxes3D { timestamp_us: t, boxes: self.boxes_at(scene, t, key)? })
    }

    /// Boxes at the image's own time (cameras fire up to ~50 ms apart within a round, and a
    /// keyframe image is not at its sample's time either).
    fn camera_boxes(&self, item: &ItemKey) -> Result<Boxes3D> {
        let (scene, _) = self.tree.scene_frame(item)?;
        let t = self.tree.reading("image", item)?.pose.timestamp_us;
        Ok(Boxes3D { timestamp_us: t, boxes: self.boxes_at(scene, t, None)? })
    }
}

impl NuScenes {
    /// The boxes of `scene` at time `t` (us): keyframe `key`'s annotations when given, or those of
    /// the keyframe at exactly `t`; otherwise the tracks annotated on both keyframes around `t`,
    /// interpolated (linear centre, size and velocity, slerp rotation), and the tracks annotated
    /// on only one of them (an object entering or leaving), moved with their velocity from that
    /// annotation when `t` is within half the keyframe interval of it (flagged `extrapolated`;
    /// a track of one annotation has no velocity and stays where it was annotated), or dropped
    /// with `lone_tracks: Drop`. Before the first and after the last keyframe only extrapolation
    /// applies.
    ///
    /// An annotation refused when the dataset was opened (a zero quaternion, a negative size)
    /// among those used fails the call with its row and field.
    fn boxes_at(&self, scene: &Scene<Keyframes, Sweep>, t: i64, key: Option<usize>) -> Result<Vec<Box3D>> {
        let keys = &scene.extra;
        let own = |k: usize| -> Result<Vec<Box3D>> {
            keys[k]
                .1
                .iter()
                .map(|&i| {
                    let a = &self.annotations[i];
                    match &a.problem {
                        Some(why) => Err(anyhow!("{why}")),
                        None => Ok(self.box_of(a)),
                    }
                })
                .collect()
        };
        if let Some(k) = key.filter(|&k| k < keys.len()) {
            return own(k);
        }
        let times: Vec<i64> = keys.iter().map(|(tk, _)| *tk).collect();
        boxes_at_time(&times, &own, t, self.config.lone_tracks == LoneTracks::Extrapolate)
    }
}

/// The boxes at time `t` from annotations at `times` (sorted; `own(k)` the boxes of time k): the
/// annotated time's own at exactly `t`; otherwise the tracks annotated on both times around `t`,
/// interpolated (linear centre, size and velocity, slerp rotation), and, with `lone`, the tracks
/// of only one of them moved with their velocity when `t` is within half the interval of it
/// (flagged `extrapolated`). Before the first and after the last time only extrapolation applies.
pub(crate) fn boxes_at_time(
    times: &[i64],
    own: &dyn Fn(usize) -> Result<Vec<Box3D>>,
    t: i64,
    lone: bool,
) -> Result<Vec<Box3D>> {
    let after = times.partition_point(|&tk| tk <= t);
    let before = after.checked_sub(1);
    if let Some(k) = before.filter(|&k| times[k] == t) {
        return own(k);
    }
    // Half the interval around t (a neighbouring one at the ends; 0.25 s with one time).
    let interval = match (before, times.get(after)) {
        (Some(k0), Some(t1)) => t1 - times[k0],
        _ => times.windows(2).map(|w| w[1] - w[0]).next().unwrap_or(500_000),
    };
    let reach = interval / 2;
    let extrapolate = |b: Box3D, from: i64| -> Option<Box3D> {
        let dt = t - from;
        if !lone || dt.abs() > reach {
            return None;
        }
        Some(Box3D { center: b.advanced(dt as f64 * 1e-6), num_lidar_pts: 0, extrapolated: true, ..b })
    };
    let early: Vec<Box3D> = before.map(own).transpose()?.unwrap_or_default();
    let late: Vec<Box3D> = if after < times.len() { own(after)? } else { Vec::new() };
    let (t0, t1) = (before.map(|k| times[k]), times.get(after).copied());
    let mut out = Vec::new();
    for a in &early {
        match late.iter().find(|b| b.instance == a.instance) {
            Some(b) => {
                let (t0, t1) = (t0.unwrap_or(t), t1.unwrap_or(t));
                // Two annotations at one time (a malformed table) give the earlier one.
                let w = if t1 > t0 { (t - t0) as f64 / (t1 - t0) as f64 } else { 0.0 };
                out.push(interpolate(a, b, w));
            }
            None => out.extend(extrapolate(a.clone(), t0.unwrap_or(t))),
        }
    }
    for b in late.into_iter().filter(|b| !early.iter().any(|a| a.instance == b.instance)) {
        out.extend(extrapolate(b, t1.unwrap_or(t)));
    }
    Ok(out)
}

/// The box of a track a fraction `w` of the way from annotation `a` to annotation `b`: linear
/// centre, size and velocity, slerp rotation.
pub(crate) fn interpolate(a: &Box3D, b: &Box3D, w: f64) -> Box3D {
    let lerp = |x: [f64; 3], y: [f64; 3]| [0, 1, 2].map(|i| x[i] + (y[i] - x[i]) * w);
    let q0 = glam::DQuat::from_xyzw(a.rotation[1], a.rotation[2], a.rotation[3], a.rotation[0]).normalize();
    let q1 = glam::DQuat::from_xyzw(b.rotation[1], b.rotation[2], b.rotation[3], b.rotation[0]).normalize();
    let q = q0.slerp(q1, w);
    Box3D {
        center: lerp(a.center, b.center),
        size: lerp(a.size, b.size),
        rotation: [q.w, q.x, q.y, q.z],
        velocity: lerp(a.velocity, b.velocity),
        num_lidar_pts: 0,
        interpolated: true,
        ..a.clone()
    }
}

/// Reads a nuScenes `.pcd.bin`: float32 x, y, z, intensity, ring per point.
pub fn read_pcd_bin(path: &Path) -> Result<PointCloud> {
    let bytes = read_input(path, "the LiDAR sweep", MAX_SENSOR_FILE_BYTES)?;
    if bytes.len() % 20 != 0 {
        bail!("{} is truncated: {} bytes is not a whole number of 20-byte points", path.display(), bytes.len());
    }
    let f = |c: &[u8]| f32::from_le_bytes(c.try_into().unwrap());
    Ok(PointCloud {
        points: bytes.chunks_exact(20).map(|p| [f(&p[0..4]), f(&p[4..8]), f(&p[8..12]), f(&p[12..16])]).collect(),
        labels: Vec::new(),
        rgb: Vec::new(),
    })
}

/// Camera and LiDAR names become folder and file names of exports (and the version a folder
/// under the root), so each must be one safe path component; the cameras, at least one, once each.
impl dist4d_graph::Validate for NuScenesConfig {
    fn validate(&self) -> Vec<dist4d_graph::ParamProblem> {
        let mut checks = dist4d_graph::ParamChecks::new();
        if let Some(cameras) = &self.cameras {
            checks.path_names("cameras", cameras);
        }
        checks.path_name("lidar", &self.lidar).path_name("version", &self.version).done()
    }
}

/// The `NuScenes(..)` dataset kind.
pub const DATASET: crate::DatasetDef =
    crate::DatasetDef { schema, open: open_checked, root: root_of, recognises, makes_root: false };

fn open_checked(checked: &dist4d_graph::ParamsValue) -> Result<crate::Opened> {
    let ds = NuScenes::open(crate::registry::config::<NuScenesConfig>(checked)?.clone())
        .context("opening the NuScenes dataset")?;
    Ok(crate::Opened {
        description: format!("NuScenes at {}", ds.config.root),
        warnings: ds.warnings.clone(),
        has_point_labels: ds.has_point_labels,
        dataset: Box::new(crate::surround::Surround(ds)),
    })
}

fn root_of(checked: &dist4d_graph::ParamsValue) -> Option<PathBuf> {
    checked.get::<NuScenesConfig>().map(|c| PathBuf::from(&c.root))
}

/// A nuScenes root holds table folders (`v1.0-mini/scene.json`, ASAP's `interp_12Hz_*`).
fn recognises(folder: &Path) -> bool {
    crate::registry::has_entry(folder, |n| {
        (n.starts_with("v1.0-") || n.starts_with("interp_12Hz_")) && folder.join(n).join("scene.json").is_file()
    })
}

/// The NuScenes dataset kind as pipelines see it.
pub fn schema() -> DatasetSchema {
    DatasetSchema {
        kind: "NuScenes",
        summary: "nuScenes v1.0 tables and files: scenes, keyframes, sweeps or camera rounds, cameras, boxes, lidarseg",
        dims: DIMS.to_vec(),
        ports: PORTS.to_vec(),
        config: ParamsSpec::of::<NuScenesConfig>(),
        path_fields: vec!["root"],
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::surround::Surround;
    use crate::testing::{load_err, shared_data, with_camera_sweeps};
    use dist4d_runtime::{Dataset, ItemSpace};
    use dist4d_types::artifact::Artifact;

    #[test]
    fn reads_the_shared_keyframe() {
        let Some(root) = shared_data("nuscenes-scene0061-kf0") else { return };
        let ds = Surround(
            NuScenes::open(NuScenesConfig { root: root.display().to_string(), ..Default::default() }).unwrap(),
        );
        assert!(ds.0.warnings.is_empty(), "real data passes every check silently: {:?}", ds.0.warnings);
        assert_eq!(ds.count(&ItemKey::new(&[])), 1);
        assert_eq!(ds.count(&ItemKey::new(&[0])), 1);
        assert_eq!(ds.label(&ItemKey::new(&[0])), "scene-0061");
        assert_eq!(ds.path(&ItemKey::new(&[0, 0, 0])), "scene-0061/000/CAM_FRONT");
        let pc = PointCloud::decode(&ds.load_source("lidar", &ItemKey::new(&[0, 0])).unwrap()).unwrap();
        // 8,220 of them within 1 m of the sensor (its mount; the devkit's remove_close drops them) and
        // 306 more on the roof and body.
        assert_eq!(pc.points.len(), 26_162, "the sweep's 34,688 points less the car's own returns");
        let cal = Calibration::decode(&ds.load_source("camera_calib", &ItemKey::new(&[0, 0, 0])).unwrap()).unwrap();
        assert_eq!((cal.width, cal.height), (1600, 900));
        let boxes = Boxes3D::decode(&ds.load_source("boxes", &ItemKey::new(&[0, 0])).unwrap()).unwrap();
        assert_eq!(boxes.boxes.len(), 69, "the shared keyframe's 69 annotated boxes");
        // One keyframe: single-annotation tracks have unknown velocity, like the devkit's NaN.
        assert!(boxes.boxes.iter().all(|b| b.velocity[0].is_nan()));
    }

    /// A small synthetic nuScenes dataset (3 keyframes, LiDAR sweeps, tiny images).
    fn synthetic() -> (tempfile::TempDir, PathBuf) {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path().join("synth");
        let config = dist4d_synth::SynthConfig { keyframes: 3, width: 160, height: 90, ..Default::default() };
        dist4d_synth::write_dataset(&config, &root, &|_| {}).unwrap();
        (dir, root)
    }

    fn open(root: &Path, frames: FrameMode) -> Result<Surround<NuScenes>> {
        NuScenes::open(NuScenesConfig { root: root.display().to_string(), frames, ..Default::default() }).map(Surround)
    }

    /// The sample_data token of a reading.
    fn token(r: &Reading) -> String {
        r.what.strip_prefix("sample_data ").unwrap().to_string()
    }

    #[test]
    fn keyframes_carry_boxes_with_devkit_velocities_images_and_lidarseg() {
        let (_tmp, root) = synthetic();
        let ds = open(&root, FrameMode::Keyframes).unwrap();
        assert!(ds.0.warnings.is_empty(), "{:?}", ds.0.warnings);
        assert_eq!(ds.count(&ItemKey::new(&[0])), 3);
        let boxes = Boxes3D::decode(&ds.load_source("boxes", &ItemKey::new(&[0, 1])).unwrap()).unwrap();
        assert!(!boxes.boxes.is_empty());
        let moving: Vec<&Box3D> =
            boxes.boxes.iter().filter(|b| b.attributes.contains(&"vehicle.moving".to_string())).collect();
        assert!(!moving.is_empty());
        for b in &moving {
            let v = b.velocity[0].hypot(b.velocity[1]);
            assert!((6.0..15.5).contains(&v), "{v} m/s");
            assert!(b.is_moving(1.0));
        }
        assert!(boxes.boxes.iter().any(|b| b.category == "vehicle.car" && !b.is_moving(0.5)));
        let pc = PointCloud::decode(&ds.load_source("lidar", &ItemKey::new(&[0, 0])).unwrap()).unwrap();
        assert_eq!(pc.labels.len(), pc.points.len());
        assert!(pc.labels.contains(&24) && pc.labels.contains(&17));
        let img = dist4d_types::artifact::Image::decode(&ds.load_source("image", &ItemKey::new(&[0, 0, 3])).unwrap())
            .unwrap();
        assert_eq!((img.width, img.height, img.rgb.len()), (160, 90, 160 * 90 * 3));
    }

    #[test]
    fn sweeps_are_frames_with_interpolated_boxes_and_the_nearest_images() {
        let (_tmp, root) = synthetic();
        let ds = open(&root, FrameMode::Sweeps).unwrap();
        // 3 keyframes 0.5 s apart at 20 Hz: 21 sweeps.
        assert_eq!(ds.count(&ItemKey::new(&[0])), 21);
        let at = |f: u32| Boxes3D::decode(&ds.load_source("boxes", &ItemKey::new(&[0, f])).unwrap()).unwrap();
        let (k0, mid, k1) = (at(0), at(5), at(10));
        assert!(!k0.boxes[0].interpolated && mid.boxes.iter().all(|b| b.interpolated));
        assert_eq!(mid.timestamp_us - k0.timestamp_us, 250_000);
        // Halfway between two keyframes, a box is halfway between its two annotations.
        let b = &mid.boxes[0];
        let (a0, a1) = (
            k0.boxes.iter().find(|x| x.instance == b.instance).unwrap(),
            k1.boxes.iter().find(|x| x.instance == b.instance).unwrap(),
        );
        for i in 0..3 {
            assert!((b.center[i] - (a0.center[i] + a1.center[i]) / 2.0).abs() < 1e-9);
        }
        // Sweeps have no lidarseg labels; keyframes do.
        let pc = |f: u32| PointCloud::decode(&ds.load_source("lidar", &ItemKey::new(&[0, f])).unwrap()).unwrap();
        assert!(pc(5).labels.is_empty() && !pc(10).labels.is_empty());
        // Each camera gives its image nearest in time.
        let pose = Pose::decode(&ds.load_source("camera_pose", &ItemKey::new(&[0, 5, 0])).unwrap()).unwrap();
        let lidar = Pose::decode(&ds.load_source("lidar_pose", &ItemKey::new(&[0, 5])).unwrap()).unwrap();
        assert!((pose.timestamp_us - lidar.timestamp_us).abs() <= 250_000);
    }

    /// Every image of every camera is in exactly one round.
    fn each_image_once(times: &[Vec<i64>], rounds: &[CameraRound]) {
        for (c, t) in times.iter().enumerate() {
            let mut seen: Vec<usize> = rounds.iter().filter_map(|r| r.images[c]).collect();
            seen.sort_unstable();
            assert_eq!(seen, (0..t.len()).collect::<Vec<_>>(), "camera {c}");
        }
        assert!(rounds.windows(2).all(|w| w[0].time <= w[1].time), "rounds in time order");
    }

    #[test]
    fn camera_rounds_use_every_image_once_even_where_the_nearest_image_would_repeat() {
        // 12 Hz, three cameras; camera 2 fires 40 ms after the reference (near half the 83 ms
        // period) with +-5 ms of jitter, so the image nearest a reference time is sometimes the
        // one of the round before or after.
        let period = 83_333;
        let jitter = |j: i64| [5_000, -5_000, 3_000, -4_000][(j % 4) as usize];
        let times: Vec<Vec<i64>> = vec![
            (0..12).map(|j| j * period).collect(),
            (0..12).map(|j| j * period + 20_000 + jitter(j) / 2).collect(),
            (0..12).map(|j| j * period + 40_000 + jitter(j)).collect(),
        ];
        let rounds = camera_rounds(&times, &[0, 20_000, 40_000]);
        each_image_once(&times, &rounds);
        assert_eq!(rounds.len(), 12);
        for (j, r) in rounds.iter().enumerate() {
            assert_eq!(r.images, vec![Some(j), Some(j), Some(j)], "round {j}");
            assert_eq!(r.time, times[0][j], "a round's time is its reference image's");
        }
        // Without the offsets the same images still go one to a round.
        let rounds = camera_rounds(&times, &[0, 0, 0]);
        each_image_once(&times, &rounds);
    }

    #[test]
    fn dropped_and_stray_images_make_incomplete_rounds_and_nothing_is_lost() {
        let period = 83_333;
        let mut reference: Vec<i64> = (0..10).map(|j| j * period).collect();
        reference.remove(4); // the reference drops round 4
        let mut other: Vec<i64> = (0..10).map(|j| j * period + 10_000).collect();
        other.remove(7); // the other camera drops round 7
        other.insert(2, 2 * period + 12_000); // and fires twice in round 2
        let times = vec![reference, other];
        let rounds = camera_rounds(&times, &[0, 10_000]);
        each_image_once(&times, &rounds);
        // 9 reference rounds, round 4 from the other camera alone, the stray image alone.
        assert_eq!(rounds.len(), 11);
        let without = |c: usize| rounds.iter().filter(|r| r.images[c].is_none()).count();
        assert_eq!((without(0), without(1)), (2, 1));
        let report = incomplete_rounds("s", &["A".into(), "B".into()], &rounds, &[true, true]).unwrap();
        assert!(report.contains("3 of 11 camera rounds are incomplete") && report.contains("without A"), "{report}");
        assert_eq!(
            incomplete_rounds("s", &["A".into()], &[CameraRound { time: 0, images: vec![Some(0)] }], &[true]),
            None
        );
    }

    #[test]
    fn camera_frames_are_the_12_hz_rounds_each_image_once_with_its_own_time() {
        let (_dir, root) = with_camera_sweeps(3);
        let ds = open(&root, FrameMode::Camera).unwrap();
        assert!(ds.0.warnings.is_empty(), "{:?}", ds.0.warnings);
        // 3 keyframes 0.5 s apart at 12 Hz: 13 rounds; each camera image is read once.
        assert_eq!(ds.count(&ItemKey::new(&[0])), 13);
        let sweeps = open(&root, FrameMode::Sweeps).unwrap();
        for c in 0..6u32 {
            let tokens = |ds: &Surround<NuScenes>, n: u32| -> Vec<String> {
                let mut t: Vec<String> =
                    (0..n).map(|f| token(ds.0.tree.reading("image", &ItemKey::new(&[0, f, c])).unwrap())).collect();
                t.sort();
                t
            };
            let rounds = tokens(&ds, 13);
            let mut distinct = rounds.clone();
            distinct.dedup();
            assert_eq!(distinct.len(), 13, "camera {c}: every image once");
            // Sweeps mode (20 Hz) repeats images and may skip one: 21 frames from at most 13.
            let mut from_sweeps = tokens(&sweeps, 21);
            from_sweeps.dedup();
            assert!(from_sweeps.len() < 21 && from_sweeps.iter().all(|t| rounds.contains(t)));
        }
        let pose =
            |f: u32, c: u32| Pose::decode(&ds.load_source("camera_pose", &ItemKey::new(&[0, f, c])).unwrap()).unwrap();
        // Cameras keep their own times (they fire as the LiDAR passes them), within one round.
        let (front, back) = (pose(3, 0), pose(3, 3));
        assert_ne!(front.timestamp_us, back.timestamp_us);
        assert!((front.timestamp_us - back.timestamp_us).abs() < 50_000);
        assert!(pose(4, 0).timestamp_us - front.timestamp_us > 80_000);
        // The frame's LiDAR is the sweep nearest the round.
        let lidar = Pose::decode(&ds.load_source("lidar_pose", &ItemKey::new(&[0, 3])).unwrap()).unwrap();
        assert!((lidar.timestamp_us - front.timestamp_us).abs() <= 25_000);
        // Rounds 0, 6 and 12 hold the keyframe images and sweeps: their boxes are the
        // annotations; the others' are interpolated to the time of their LiDAR sweep.
        let boxes = |f: u32| Boxes3D::decode(&ds.load_source("boxes", &ItemKey::new(&[0, f])).unwrap()).unwrap();
        assert!(boxes(6).boxes.iter().all(|b| !b.interpolated) && !boxes(6).boxes.is_empty());
        assert!(boxes(3).boxes.iter().all(|b| b.interpolated) && !boxes(3).boxes.is_empty());
        assert_eq!(boxes(3).timestamp_us, lidar.timestamp_us);
    }

    /// Centre errors (m) against the synthetic world's exact boxes at every non-keyframe image of
    /// a camera-sweeps dataset, of the agents moving faster than 1 m/s: of `camera_boxes` (each
    /// image's own time), and of the same interpolation at ASAP's time (the k-th of n rounds
    /// between two keyframes at k/n of the way, the same time for every camera of a round).
    fn box_errors(ds: &Surround<NuScenes>, root: &Path) -> (Vec<f64>, Vec<f64>) {
        let scene = &ds.0.tree.scenes[0];
        let rounds = scene.frames.len();
        let key_rounds: Vec<usize> = (0..rounds).filter(|&f| scene.frames[f].extra.key).collect();
        let (mut ours, mut asap) = (Vec::new(), Vec::new());
        for f in (0..rounds).filter(|f| !key_rounds.contains(f)) {
            let r1 = key_rounds.iter().position(|&k| k > f).map(|i| key_rounds[i]).unwrap();
            let r0 = key_rounds.iter().rev().find(|&&k| k < f).copied().unwrap();
            let (k0, k1) = (scene.frames[r0].extra.sample.unwrap(), scene.frames[r1].extra.sample.unwrap());
            let (t0, t1) = (scene.extra[k0].0, scene.extra[k1].0);
            let t_asap = t0 + (t1 - t0) * (f - r0) as i64 / (r1 - r0) as i64;
            let at_asap = ds.0.boxes_at(scene, t_asap, None).unwrap();
            for c in 0..ds.0.tree.cameras.len() as u32 {
                let item = ItemKey::new(&[0, f as u32, c]);
                let image = ds.0.tree.reading("image", &item).unwrap();
                let stem = image.file.file_stem().unwrap().to_string_lossy().to_string();
                let camera = &ds.0.tree.cameras[c as usize];
                let truth: serde_json::Value = serde_json::from_slice(
                    &std::fs::read(root.join(format!("groundtruth/boxes/{camera}/{stem}.json"))).unwrap(),
                )
                .unwrap();
                let truth_of = |instance: &str| {
                    let b = truth["boxes"].as_array().unwrap().iter().find(|b| b["instance_token"] == instance)?;
                    let v = |k: &str| [0, 1, 2].map(|i| b[k][i].as_f64().unwrap());
                    let speed = v("velocity").iter().map(|x| x * x).sum::<f64>().sqrt();
                    (speed > 1.0).then(|| v("translation"))
                };
                let error = |b: &Box3D| {
                    truth_of(&b.instance).map(|t| ((0..3).map(|i| (b.center[i] - t[i]).powi(2)).sum::<f64>()).sqrt())
                };
                let own = Boxes3D::decode(&ds.load_source("camera_boxes", &item).unwrap()).unwrap();
                assert_eq!(own.timestamp_us, image.pose.timestamp_us);
                ours.extend(own.boxes.iter().filter(|b| b.interpolated).filter_map(error));
                asap.extend(at_asap.iter().filter(|b| b.interpolated).filter_map(error));
            }
        }
        (ours, asap)
    }

    fn median_p95(mut v: Vec<f64>) -> (f64, f64) {
        v.sort_by(|a, b| a.total_cmp(b));
        (v[v.len() / 2], v[(v.len() * 95) / 100])
    }

    #[test]
    fn boxes_at_each_images_time_are_within_5_cm_of_the_truth_and_closer_than_asaps() {
        let (_dir, root) = with_camera_sweeps(4);
        let ds = open(&root, FrameMode::Camera).unwrap();
        let (ours, asap) = box_errors(&ds, &root);
        assert!(ours.len() > 100, "{} interpolated boxes of moving agents", ours.len());
        let ((m, p), (am, ap)) = (median_p95(ours), median_p95(asap.clone()));
        eprintln!(
            "{} boxes of moving agents, centre error median / p95: at each image's time {m:.3} / {p:.3} m; \
             ASAP's rule {am:.3} / {ap:.3} m",
            asap.len()
        );
        assert!(m <= 0.05 && p <= 0.2, "{m} / {p}");
        assert!(am > 2.0 * m && ap > p, "ASAP's rule {am} / {ap} against {m} / {p}");
    }

    #[test]
    fn image_info_says_which_image_an_item_is_or_why_it_has_none() {
        use dist4d_types::artifact::ImageInfo;
        let (_dir, root) = with_camera_sweeps(3);
        // CAM_BACK drops its 5th image.
        let file = root.join("v1.0-mini/sample_data.json");
        let mut rows: Vec<serde_json::Value> = serde_json::from_slice(&std::fs::read(&file).unwrap()).unwrap();
        let mut back: Vec<usize> =
            (0..rows.len()).filter(|&i| rows[i]["filename"].as_str().unwrap().contains("__CAM_BACK__")).collect();
        back.sort_by_key(|&i| rows[i]["timestamp"].as_i64().unwrap());
        let gone = rows[back[4]].clone();
        for r in rows.iter_mut() {
            if r["token"] == gone["prev"] {
                r["next"] = gone["next"].clone();
            }
            if r["token"] == gone["next"] {
                r["prev"] = gone["prev"].clone();
            }
        }
        rows.retain(|r| r["token"] != gone["token"]);
        std::fs::write(&file, serde_json::to_vec(&rows).unwrap()).unwrap();
        let ds = open(&root, FrameMode::Camera).unwrap();
        let info = |f: u32, c: u32| {
            ImageInfo::decode(&ds.load_source("image_info", &ItemKey::new(&[0, f, c])).unwrap()).unwrap()
        };
        let front = info(4, 0);
        assert_eq!(
            (front.scene.as_str(), front.frame.as_str(), front.camera.as_str()),
            ("synth-0000", "004", "CAM_FRONT")
        );
        assert!(
            front.missing.is_none() && front.file.starts_with("sweeps/CAM_FRONT/") && root.join(&front.file).is_file()
        );
        assert_eq!(front.boxes.timestamp_us, front.timestamp_us, "boxes at the image's time");
        assert!(front.intrinsics.is_some() && front.width == 96);
        let dropped = info(4, 3);
        assert_eq!(dropped.camera, "CAM_BACK");
        assert!(
            dropped.missing.as_deref().is_some_and(|m| m.contains("has no CAM_BACK image")),
            "{:?}",
            dropped.missing
        );
        // The other ports of that item still fail, naming why.
        assert!(load_err(&ds, "camera_calib", &[0, 4, 3]).contains("has no CAM_BACK image"));
    }

    #[test]
    fn a_track_on_one_keyframe_only_is_extrapolated_half_an_interval_or_dropped() {
        let (_dir, root) = with_camera_sweeps(6);
        let ds = open(&root, FrameMode::Camera).unwrap();
        let scene = &ds.0.tree.scenes[0];
        let keys = &scene.extra;
        // Tracks that enter or leave the annotated range: annotated on one keyframe of a pair.
        let instances = |k: usize| -> Vec<String> {
            keys[k].1.iter().map(|&i| ds.0.annotations[i].row.instance_token.clone()).collect()
        };
        let (k, lone) = (0..keys.len() - 1)
            .find_map(|k| instances(k).into_iter().find(|i| !instances(k + 1).contains(i)).map(|i| (k, i)))
            .expect("an agent leaves the annotated range");
        let (t0, t1) = (keys[k].0, keys[k + 1].0);
        let at = |t: i64, ds: &Surround<NuScenes>| {
            ds.0.boxes_at(scene, t, None).unwrap().into_iter().find(|b| b.instance == lone)
        };
        let near = at(t0 + (t1 - t0) / 4, &ds).expect("a quarter interval on: extrapolated");
        assert!(near.extrapolated && !near.interpolated);
        let annotated = ds.0.boxes_at(scene, t0, None).unwrap().into_iter().find(|b| b.instance == lone).unwrap();
        let moved: f64 = (0..3).map(|i| (near.center[i] - annotated.center[i]).powi(2)).sum::<f64>().sqrt();
        let speed: f64 = annotated.velocity.iter().map(|v| v * v).sum::<f64>().sqrt();
        assert!((moved - speed * (t1 - t0) as f64 * 0.25e-6).abs() < 1e-6, "moved {moved} at {speed} m/s");
        assert!(at(t0 + (t1 - t0) * 3 / 4, &ds).is_none(), "beyond half the interval: gone");
        let dropping = NuScenes::open(NuScenesConfig {
            root: root.display().to_string(),
            frames: FrameMode::Camera,
            lone_tracks: LoneTracks::Drop,
            ..Default::default()
        })
        .map(Surround)
        .unwrap();
        let scene = &dropping.0.tree.scenes[0];
        assert!(dropping.0.boxes_at(scene, t0 + (t1 - t0) / 4, None).unwrap().iter().all(|b| b.instance != lone));
        assert!(
            dropping.0.boxes_at(scene, t0, None).unwrap().iter().any(|b| b.instance == lone),
            "its annotation stays"
        );
    }

    /// The figures of docs/BENCHMARKS.md ("Boxes at each image's time"), on a dataset made with
    /// `dist4d synth --camera-sweeps`: `DIST4D_BOXES_ROOT=DIR cargo test --release -p
    /// dist4d-datasets box_error_figures -- --ignored --nocapture`.
    #[test]
    #[ignore]
    fn box_error_figures() {
        let root = PathBuf::from(std::env::var("DIST4D_BOXES_ROOT").expect("DIST4D_BOXES_ROOT names a synthetic root"));
        let ds = open(&root, FrameMode::Camera).unwrap();
        let (ours, asap) = box_errors(&ds, &root);
        let n = ours.len();
        let ((m, p), (am, ap)) = (median_p95(ours), median_p95(asap));
        println!("{n} boxes of moving agents at non-keyframe images: centre error median / p95 {m:.4} / {p:.4} m at each image's own time, {am:.4} / {ap:.4} m by ASAP's rule");
    }

    #[test]
    fn the_cameras_default_to_those_the_data_has_in_the_devkit_order() {
        let (_tmp, root) = synthetic();
        assert_eq!(open(&root, FrameMode::Keyframes).unwrap().0.tree.cameras, CAMERAS.map(String::from));
        // A rig without CAM_BACK_LEFT data: five cameras, none failing.
        let file = root.join("v1.0-mini/sample_data.json");
        let mut rows: Vec<serde_json::Value> = serde_json::from_slice(&std::fs::read(&file).unwrap()).unwrap();
        rows.retain(|r| !r["filename"].as_str().unwrap().contains("__CAM_BACK_LEFT__"));
        std::fs::write(&file, serde_json::to_vec(&rows).unwrap()).unwrap();
        let ds = open(&root, FrameMode::Keyframes).unwrap();
        let five: Vec<String> = CAMERAS.iter().filter(|c| **c != "CAM_BACK_LEFT").map(|c| c.to_string()).collect();
        assert_eq!(ds.0.tree.cameras, five);
        for c in 0..5 {
            assert!(ds.load_source("camera_calib", &ItemKey::new(&[0, 0, c])).is_ok(), "camera {c}");
        }
    }

    #[test]
    fn malformed_rows_name_file_token_and_field_and_optional_tables_only_warn() {
        let (_tmp, root) = synthetic();
        let table = root.join("v1.0-mini/ego_pose.json");
        let text = std::fs::read_to_string(&table).unwrap();
        let mut rows: Vec<serde_json::Value> = serde_json::from_str(&text).unwrap();
        rows[2]["translation"][1] = serde_json::json!("north");
        let token = rows[2]["token"].as_str().unwrap().to_string();
        std::fs::write(&table, serde_json::to_vec(&rows).unwrap()).unwrap();
        let err = format!("{:#}", open(&root, FrameMode::Keyframes).err().unwrap());
        assert!(err.contains("ego_pose.json") && err.contains(&token) && err.contains("translation[1]"), "{err}");
        std::fs::write(&table, text).unwrap();

        for t in ["sample_annotation", "instance", "log", "map"] {
            std::fs::remove_file(root.join(format!("v1.0-mini/{t}.json"))).unwrap();
        }
        let ds = open(&root, FrameMode::Keyframes).unwrap();
        assert_eq!(ds.0.warnings.len(), 4, "{:?}", ds.0.warnings);
        assert!(ds.0.warnings[0].contains("sample_annotation.json is missing"));
        let boxes = Boxes3D::decode(&ds.load_source("boxes", &ItemKey::new(&[0, 0])).unwrap()).unwrap();
        assert!(boxes.boxes.is_empty());
        // An unreadable JPEG fails that camera's image only.
        let cam = ds.0.tree.reading("image", &ItemKey::new(&[0, 1, 2])).unwrap().file.clone();
        std::fs::write(&cam, b"not a jpeg").unwrap();
        let err = format!("{:#}", ds.load_source("image", &ItemKey::new(&[0, 1, 2])).unwrap_err());
        assert!(err.contains("not a readable image") && err.contains(&cam.display().to_string()), "{err}");
        assert!(ds.load_source("image", &ItemKey::new(&[0, 1, 3])).is_ok());
    }

    #[test]
    fn missing_tables_and_truncated_sweeps_are_clear_errors() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::create_dir_all(dir.path().join("v1.0-mini")).unwrap();
        let err = NuScenes::open(NuScenesConfig { root: dir.path().display().to_string(), ..Default::default() })
            .err()
            .unwrap();
        assert!(format!("{err:#}").contains("v1.0-mini/scene.json"), "{err:#}");
        let f = dir.path().join("x.pcd.bin");
        std::fs::write(&f, [0u8; 30]).unwrap();
        let err = read_pcd_bin(&f).unwrap_err().to_string();
        assert!(err.contains("truncated"), "{err}");
    }

    /// Rewrites a table of the dataset at `root`.
    fn edit_table(root: &Path, table: &str, edit: impl FnOnce(&mut Vec<serde_json::Value>)) {
        let path = root.join(format!("v1.0-mini/{table}.json"));
        let mut rows: Vec<serde_json::Value> = serde_json::from_slice(&std::fs::read(&path).unwrap()).unwrap();
        edit(&mut rows);
        std::fs::write(&path, serde_json::to_vec(&rows).unwrap()).unwrap();
    }

    /// The index of the row with `token` in a table.
    fn row_of(root: &Path, table: &str, token: &str) -> usize {
        let path = root.join(format!("v1.0-mini/{table}.json"));
        let rows: Vec<serde_json::Value> = serde_json::from_slice(&std::fs::read(&path).unwrap()).unwrap();
        rows.iter().position(|r| r["token"] == token).unwrap()
    }

    /// The sample_data token of an item's reading (`lidar` or `image` port).
    fn token_of(root: &Path, port: &str, item: &[u32]) -> String {
        open(root, FrameMode::Keyframes).unwrap().0.tree.reading(port, &ItemKey::new(item)).map(token).unwrap()
    }

    #[test]
    fn file_references_outside_the_root_fail_their_item_only() {
        let (tmp, root) = synthetic();
        let lidar = token_of(&root, "lidar", &[0, 1]);
        let (cam, other_cam) = (token_of(&root, "image", &[0, 0, 2]), token_of(&root, "image", &[0, 2, 1]));
        let lidar_file = open(&root, FrameMode::Keyframes)
            .unwrap()
            .0
            .tree
            .reading("lidar", &ItemKey::new(&[0, 1]))
            .unwrap()
            .file
            .clone();
        let cam_file = open(&root, FrameMode::Keyframes)
            .unwrap()
            .0
            .tree
            .reading("image", &ItemKey::new(&[0, 0, 2]))
            .unwrap()
            .file
            .clone();
        // Real files outside the root: a reader that followed the references would read them fine.
        std::fs::create_dir_all(tmp.path().join("outside")).unwrap();
        std::fs::copy(&lidar_file, tmp.path().join("outside/x.pcd.bin")).unwrap();
        let outside_jpg = tmp.path().join("outside/x.jpg");
        std::fs::copy(&cam_file, &outside_jpg).unwrap();
        edit_table(&root, "sample_data", |rows| {
            for r in rows.iter_mut() {
                if r["token"] == lidar.as_str() {
                    r["filename"] = "../outside/x.pcd.bin".into();
                } else if r["token"] == cam.as_str() {
                    r["filename"] = outside_jpg.display().to_string().into();
                } else if r["token"] == other_cam.as_str() {
                    r["filename"] = "../../../../etc/passwd".into();
                }
            }
        });
        let first_lidar = token_of(&root, "lidar", &[0, 0]);
        edit_table(&root, "lidarseg", |rows| {
            let r = rows.iter_mut().find(|r| r["sample_data_token"] == first_lidar.as_str()).unwrap();
            r["filename"] = "lidarseg/../../labels.bin".into();
        });
        let ds = open(&root, FrameMode::Keyframes).unwrap();
        let row = row_of(&root, "sample_data", &lidar);
        let err = load_err(&ds, "lidar", &[0, 1]);
        assert!(
            err.contains(&format!(
                "v1.0-mini/sample_data.json row {row} (token {lidar}): field filename \"../outside/x.pcd.bin\" leaves the \
                 dataset root"
            )),
            "{err}"
        );
        // The whole reading is refused: its calibration and pose too.
        assert!(ds.load_source("lidar_pose", &ItemKey::new(&[0, 1])).is_err());
        let err = load_err(&ds, "image", &[0, 0, 2]);
        assert!(err.contains(&format!("(token {cam}): field filename")) && err.contains("(an absolute path)"), "{err}");
        let err = load_err(&ds, "camera_calib", &[0, 2, 1]);
        assert!(err.contains("\"../../../../etc/passwd\" leaves the dataset root"), "{err}");
        let err = load_err(&ds, "lidar", &[0, 0]);
        assert!(err.contains("v1.0-mini/lidarseg.json row") && err.contains("lidarseg/../../labels.bin"), "{err}");
        // Everything else still loads.
        assert!(ds.load_source("lidar", &ItemKey::new(&[0, 2])).is_ok());
        assert!(ds.load_source("image", &ItemKey::new(&[0, 0, 3])).is_ok());
        assert!(ds.load_source("image", &ItemKey::new(&[0, 1, 2])).is_ok());
    }

    #[test]
    fn bad_poses_and_calibrations_fail_the_items_that_use_them() {
        let (_tmp, root) = synthetic();
        let ds = open(&root, FrameMode::Keyframes).unwrap();
        let sd_row = |item: &[u32], port: &str| -> serde_json::Value {
            let token = ds.0.tree.reading(port, &ItemKey::new(item)).map(token).unwrap();
            let rows: Vec<serde_json::Value> =
                serde_json::from_slice(&std::fs::read(root.join("v1.0-mini/sample_data.json")).unwrap()).unwrap();
            rows.into_iter().find(|r| r["token"] == token.as_str()).unwrap()
        };
        let lidar_pose = sd_row(&[0, 1], "lidar")["ego_pose_token"].as_str().unwrap().to_string();
        let cam_pose = sd_row(&[0, 2, 0], "image")["ego_pose_token"].as_str().unwrap().to_string();
        let cs =
            |camera: u32| sd_row(&[0, 0, camera], "image")["calibrated_sensor_token"].as_str().unwrap().to_string();
        let (right, back, back_left, front_left) = (cs(1), cs(3), cs(4), cs(5));
        edit_table(&root, "ego_pose", |rows| {
            for r in rows.iter_mut() {
                if r["token"] == lidar_pose.as_str() {
                    r["rotation"] = serde_json::json!([0.0, 0.0, 0.0, 0.0]);
                } else if r["token"] == cam_pose.as_str() {
                    r["translation"] = serde_json::json!([1e300, 0.0, 0.0]);
                }
            }
        });
        edit_table(&root, "calibrated_sensor", |rows| {
            for r in rows.iter_mut() {
                let t = r["token"].as_str().unwrap().to_string();
                if t == back {
                    r["camera_intrinsic"] = serde_json::json!([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]);
                } else if t == front_left {
                    r["rotation"] = serde_json::json!([0.0, 0.0, 0.0, 0.0]);
                } else if t == right {
                    r["translation"] = serde_json::json!([0.0, 0.0, 1000.0]);
                } else if t == back_left {
                    r["camera_intrinsic"][0][2] = serde_json::json!(5000.0);
                }
            }
        });
        let ds = open(&root, FrameMode::Keyframes).unwrap();
        let row = row_of(&root, "ego_pose", &lidar_pose);
        let err = load_err(&ds, "lidar_pose", &[0, 1]);
        assert!(
            err.contains(&format!(
                "v1.0-mini/ego_pose.json row {row} (token {lidar_pose}): field rotation [0, 0, 0, 0] is not a rotation \
                 (norm 0"
            )),
            "{err}"
        );
        let err = load_err(&ds, "camera_pose", &[0, 2, 0]);
        assert!(err.contains(&format!("(token {cam_pose}): field translation [1e300, 0, 0] is 1e300 m")), "{err}");
        for f in 0..3 {
            let err = load_err(&ds, "camera_calib", &[0, f, 3]);
            assert!(
                err.contains(&format!(
                    "calibrated_sensor.json row {} (token {back}): field camera_intrinsic",
                    row_of(&root, "calibrated_sensor", &back)
                )),
                "{err}"
            );
            assert!(err.contains("fx 0 and fy 0; both must be positive"), "{err}");
        }
        assert!(load_err(&ds, "camera_pose", &[0, 0, 5]).contains("field rotation [0, 0, 0, 0] is not a rotation"));
        assert!(load_err(&ds, "image", &[0, 0, 1])
            .contains("field translation [0, 0, 1000] is 1000 m from the origin, beyond the 100 m bound"));
        let err = load_err(&ds, "camera_calib", &[0, 1, 4]);
        assert!(err.contains("principal point (5000, ") && err.contains("outside the 160x90 image of"), "{err}");
        assert!(err.contains("v1.0-mini/sample_data.json row"), "{err}");
        // The rows nobody broke still load.
        for item in [[0u32, 0, 0], [0, 1, 0], [0, 1, 2]] {
            assert!(ds.load_source("camera_calib", &ItemKey::new(&item)).is_ok(), "{item:?}");
            assert!(ds.load_source("camera_pose", &ItemKey::new(&item)).is_ok(), "{item:?}");
        }
        assert!(ds.load_source("lidar_pose", &ItemKey::new(&[0, 0])).is_ok());
    }

    #[test]
    fn slightly_off_quaternions_are_normalised_with_one_warning() {
        let (_tmp, root) = synthetic();
        let before = Pose::decode(
            &open(&root, FrameMode::Keyframes).unwrap().load_source("lidar_pose", &ItemKey::new(&[0, 1])).unwrap(),
        )
        .unwrap();
        edit_table(&root, "ego_pose", |rows| {
            for r in rows.iter_mut() {
                let q: Vec<f64> =
                    r["rotation"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap() * 0.995).collect();
                r["rotation"] = serde_json::json!(q);
            }
        });
        let ds = open(&root, FrameMode::Keyframes).unwrap();
        assert_eq!(ds.0.warnings.len(), 1, "{:?}", ds.0.warnings);
        assert!(
            ds.0.warnings[0].contains("ego_pose.json") && ds.0.warnings[0].contains("normalised"),
            "{:?}",
            ds.0.warnings
        );
        let after = Pose::decode(&ds.load_source("lidar_pose", &ItemKey::new(&[0, 1])).unwrap()).unwrap();
        assert!(after.ego_to_world.rotation.abs_diff_eq(before.ego_to_world.rotation, 1e-12));
    }

    #[test]
    fn duplicate_tokens_with_different_rows_are_rejected_and_identical_ones_kept_once() {
        let (_tmp, root) = synthetic();
        // Boxes of all three keyframes.
        let boxes = |ds: &Surround<NuScenes>| -> usize {
            (0..3)
                .map(|f| {
                    Boxes3D::decode(&ds.load_source("boxes", &ItemKey::new(&[0, f])).unwrap()).unwrap().boxes.len()
                })
                .sum()
        };
        let n = boxes(&open(&root, FrameMode::Keyframes).unwrap());
        let mut token = String::new();
        edit_table(&root, "sample_annotation", |rows| {
            let copy = rows[0].clone();
            rows.push(copy);
        });
        let ds = open(&root, FrameMode::Keyframes).unwrap();
        assert!(
            ds.0.warnings.iter().any(|w| w.contains("sample_annotation.json: 1 row(s) repeat an earlier row exactly")),
            "{:?}",
            ds.0.warnings
        );
        // The repeated annotation is one box, not two.
        assert_eq!(boxes(&ds), n);
        edit_table(&root, "ego_pose", |rows| {
            let mut copy = rows[2].clone();
            copy["translation"][0] = serde_json::json!(copy["translation"][0].as_f64().unwrap() + 1.0);
            token = copy["token"].as_str().unwrap().to_string();
            rows.push(copy);
        });
        let rows = std::fs::read(root.join("v1.0-mini/ego_pose.json")).unwrap();
        let last = serde_json::from_slice::<Vec<serde_json::Value>>(&rows).unwrap().len() - 1;
        let err = format!("{:#}", open(&root, FrameMode::Keyframes).err().unwrap());
        assert!(
            err.contains(&format!(
                "v1.0-mini/ego_pose.json: rows 2 and {last} have the same token {token} but different contents"
            )),
            "{err}"
        );
    }

    #[test]
    fn dangling_tokens_name_the_sample_data_row_and_field() {
        let (_tmp, root) = synthetic();
        let (front, back) = (token_of(&root, "image", &[0, 1, 0]), token_of(&root, "image", &[0, 1, 3]));
        edit_table(&root, "sample_data", |rows| {
            for r in rows.iter_mut() {
                if r["token"] == front.as_str() {
                    r["calibrated_sensor_token"] = "nope".into();
                } else if r["token"] == back.as_str() {
                    r["ego_pose_token"] = "gone".into();
                }
            }
        });
        let ds = open(&root, FrameMode::Keyframes).unwrap();
        let err = load_err(&ds, "camera_calib", &[0, 1, 0]);
        let row = row_of(&root, "sample_data", &front);
        assert!(
            err.contains(&format!(
                "v1.0-mini/sample_data.json row {row} (token {front}): field calibrated_sensor_token nope names no \
                 calibrated_sensor row"
            )),
            "{err}"
        );
        assert!(!err.contains("has no keyframe sample_data"), "{err}");
        let err = load_err(&ds, "camera_pose", &[0, 1, 3]);
        let row = row_of(&root, "sample_data", &back);
        assert!(
            err.contains(&format!("row {row} (token {back}): field ego_pose_token gone names no ego_pose row")),
            "{err}"
        );
        assert!(ds.load_source("camera_calib", &ItemKey::new(&[0, 0, 0])).is_ok());
    }

    #[test]
    fn an_empty_sample_data_table_or_one_without_keyframes_is_one_error_at_open() {
        let (_tmp, root) = synthetic();
        edit_table(&root, "sample_data", |rows| {
            for r in rows.iter_mut() {
                r["is_key_frame"] = false.into();
            }
        });
        let err = format!("{:#}", open(&root, FrameMode::Keyframes).err().unwrap());
        assert!(err.contains("v1.0-mini/sample_data.json has") && err.contains("rows but no keyframe"), "{err}");
        edit_table(&root, "sample_data", |rows| rows.clear());
        for mode in [FrameMode::Keyframes, FrameMode::Sweeps] {
            let err = format!("{:#}", open(&root, mode).err().unwrap());
            assert!(err.ends_with("v1.0-mini/sample_data.json has no rows: the dataset has no sensor data"), "{err}");
        }
    }

    #[test]
    fn truncated_and_wrong_size_images_fail_naming_the_file() {
        let (_tmp, root) = synthetic();
        let ds = open(&root, FrameMode::Keyframes).unwrap();
        let file = |camera: u32| ds.0.tree.reading("image", &ItemKey::new(&[0, 1, camera])).unwrap().file.clone();
        let (cut, small) = (file(2), file(3));
        let jpeg = std::fs::read(&cut).unwrap();
        std::fs::write(&cut, &jpeg[..jpeg.len() / 2]).unwrap();
        let err = load_err(&ds, "image", &[0, 1, 2]);
        assert!(err.contains(&format!("{} is truncated", cut.display())), "{err}");
        let mut half = Vec::new();
        image::codecs::jpeg::JpegEncoder::new(&mut half)
            .encode(&vec![128u8; 80 * 45 * 3], 80, 45, image::ExtendedColorType::Rgb8)
            .unwrap();
        std::fs::write(&small, half).unwrap();
        let err = load_err(&ds, "image", &[0, 1, 3]);
        let token = ds.0.tree.reading("image", &ItemKey::new(&[0, 1, 3])).map(token).unwrap();
        assert_eq!(
            err,
            format!("{} is 80x45 but sample_data {token} (fields width, height) says 160x90", small.display())
        );
        assert!(ds.load_source("image", &ItemKey::new(&[0, 1, 1])).is_ok());
    }

    /// `semantics` is the user's own setting, not dataset metadata: it may point anywhere.
    #[test]
    fn the_semantics_folder_may_live_outside_the_root() {
        let (tmp, root) = synthetic();
        let elsewhere = tmp.path().join("segmenter-output");
        std::fs::rename(root.join("groundtruth/semantic"), &elsewhere).unwrap();
        for semantics in [elsewhere.display().to_string(), "../segmenter-output".to_string()] {
            let ds = Surround(
                NuScenes::open(NuScenesConfig {
                    root: root.display().to_string(),
                    semantics: Some(semantics.clone()),
                    ..Default::default()
                })
                .unwrap(),
            );
            let seg = dist4d_types::artifact::Segmentation::decode(
                &ds.load_source("semantic", &ItemKey::new(&[0, 0, 0])).unwrap(),
            )
            .unwrap();
            assert_eq!((seg.width, seg.height), (160, 90), "{semantics}");
        }
    }
}
