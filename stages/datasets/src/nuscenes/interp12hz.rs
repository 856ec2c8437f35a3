//! The 12 Hz nuScenes tables that ASAP's users load (`interp_12Hz_<split>/`): every round of the
//! surround cameras is a `sample`, with its images, a LiDAR sweep and boxes at its time.
//!
//! MagicDrive, UniScene and others train at 12 Hz on the folder that ASAP's
//! `sAP3D/nusc_annotation_generator.py` (JeffWang987/ASAP) writes beside `v1.0-trainval/`, loaded
//! with `NuScenes(version='interp_12Hz_trainval')`. We follow its folder name, its token scheme (a
//! new sample is the token of the keyframe before it with the round's number after that keyframe
//! appended: `<keyframe>1` .. `<keyframe>5`; its annotations likewise append the number to the
//! track's keyframe annotation) and the tables it copies unchanged. We differ where it is wrong:
//!
//! - samples are the real camera rounds ([`super::camera_rounds`]) at their LiDAR sweep's real
//!   time (an integer, as nuScenes writes times), not six evenly spaced times per interval;
//! - every `sample_data` row is kept with its real time and its `prev`/`next` chain intact (ASAP
//!   drops the sweeps, invents rows named `<keyframe row>1..5` with interpolated times for the
//!   i-th next file, and leaves their chains dangling, so the devkit's `render_sample` fails);
//! - boxes are interpolated to each sample's time by the same code as the reader's (linear centre
//!   and size, slerp rotation), and a track seen on one keyframe only is extrapolated up to half an
//!   interval (or dropped with `lone_tracks: Drop`, ASAP's rule); `num_lidar_pts` is counted in
//!   the sample's own sweep, not copied from the keyframe;
//! - `scene` and `instance` are updated (sample and annotation counts, first and last tokens),
//!   and every scene of the version is written, not the val split alone.
//!
//! What the devkit needs of the result (nuscenes-devkit `nuscenes.py`): a sample's `data` is
//! built from the `sample_data` rows with `is_key_frame` that name it, so the round's images and
//! its sweep are marked key frames of the new sample; every other row (sweeps between, radar)
//! names the first sample at or after its time, as in nuScenes (`get_boxes` interpolates between
//! that sample and the one before). `lidarseg.json` is not written: the devkit would look for its
//! label files under `lidarseg/interp_12Hz_*`; the labels stay with the original version.

use super::*;
use glam::DVec3;
use rayon::prelude::*;
use serde_json::{json, Value};
use std::collections::{BTreeMap, HashSet};
use std::io::Write;

/// What [`write_interp_12hz`] wrote.
#[derive(Debug, Default)]
pub struct Export12Hz {
    pub out: PathBuf,
    pub scenes: usize,
    /// Samples written, and how many of them are the original keyframes.
    pub samples: usize,
    pub keyframes: usize,
    /// Annotations written for the new samples, and how many of them were extrapolated.
    pub annotations: usize,
    pub extrapolated: usize,
    /// What was odd but did not stop the export (from opening the dataset, and unreadable sweeps).
    pub warnings: Vec<String>,
}

/// The tables copied as they are.
const COPIED: [&str; 8] =
    ["category", "attribute", "visibility", "sensor", "calibrated_sensor", "ego_pose", "log", "map"];

/// ASAP's folder for a version: `v1.0-trainval` -> `interp_12Hz_trainval`.
pub fn default_folder(root: &Path, version: &str) -> PathBuf {
    root.join(format!("interp_12Hz_{}", version.strip_prefix("v1.0-").unwrap_or(version)))
}

/// A new table's rows by token (first occurrence; the reader has already refused two different
/// rows with one token).
struct Table {
    rows: Vec<Value>,
    by_token: HashMap<String, usize>,
}

impl Table {
    fn read(dir: &Path, name: &str, required: bool) -> Result<Table> {
        let path = dir.join(format!("{name}.json"));
        if !required && !path.exists() {
            return Ok(Table { rows: Vec::new(), by_token: HashMap::new() });
        }
        let bytes = crate::files::read_input(&path, "the nuScenes table", crate::checks::MAX_TABLE_FILE_BYTES)?;
        let all: Vec<Value> = serde_json::from_slice(&bytes)
            .with_context(|| format!("malformed nuScenes table {}: not a JSON list", path.display()))?;
        let mut rows = Vec::with_capacity(all.len());
        let mut by_token = HashMap::with_capacity(all.len());
        for row in all {
            let token = text(&row, "token").to_string();
            if by_token.contains_key(&token) {
                continue;
            }
            by_token.insert(token, rows.len());
            rows.push(row);
        }
        Ok(Table { rows, by_token })
    }

    fn get(&self, token: &str) -> Option<&Value> {
        self.by_token.get(token).map(|&i| &self.rows[i])
    }

    fn set(&mut self, token: &str, field: &str, value: Value) {
        if let Some(&i) = self.by_token.get(token) {
            self.rows[i][field] = value;
        }
    }
}

fn text<'a>(row: &'a Value, field: &str) -> &'a str {
    row.get(field).and_then(Value::as_str).unwrap_or("")
}

/// A row's `timestamp`, read as the reader reads it (a fraction rounded to the microsecond).
fn time(row: &Value) -> i64 {
    row.get("timestamp").and_then(|t| super::microseconds(t).ok()).unwrap_or(0)
}

/// One sample of the 12 Hz table: an original keyframe or a new camera round.
struct Sample {
    token: String,
    /// The keyframe (index in the scene's chain) it is.
    key: Option<usize>,
    /// Its camera round (frame index), when it has one.
    round: Option<usize>,
    /// Where it sorts: its round's time (the reference image's), or the keyframe's time.
    order: i64,
    /// Its time: the keyframe's, else its sweep's, else its round's.
    time: i64,
    /// Rows it holds as key frames, beyond an original keyframe's own.
    rows: Vec<String>,
    /// Rounds since the keyframe before it in the table (and that keyframe), and rounds until
    /// the keyframe after it (and that one).
    after: Option<(usize, usize)>,
    before: Option<(usize, usize)>,
}

/// Writes the 12 Hz tables of the dataset `config` describes into `out` (a new folder beside the
/// version's, normally [`default_folder`]); `out` is replaced whole, atomically, when it exists.
pub fn write_interp_12hz(config: &NuScenesConfig, out: &Path) -> Result<Export12Hz> {
    let config = NuScenesConfig { frames: FrameMode::Camera, ..config.clone() };
    let ds = NuScenes::open(config.clone())?;
    let tables = Path::new(&config.root).join(&config.version);
    check_destination(out, Path::new(&config.root), &tables)?;
    let mut report = Export12Hz { out: out.to_path_buf(), warnings: ds.warnings.clone(), ..Default::default() };

    let sample_table = Table::read(&tables, "sample", true)?;
    let mut sample_data = Table::read(&tables, "sample_data", true)?;
    let mut annotations = Table::read(&tables, "sample_annotation", false)?;
    let mut scenes = Table::read(&tables, "scene", true)?;
    let mut instances = Table::read(&tables, "instance", false)?;
    let calibrated = Table::read(&tables, "calibrated_sensor", true)?;
    let sensors = Table::read(&tables, "sensor", true)?;
    let modality_channel = |sd: &Value| -> (String, String) {
        let sensor =
            calibrated.get(text(sd, "calibrated_sensor_token")).and_then(|cs| sensors.get(text(cs, "sensor_token")));
        sensor.map_or((String::new(), String::new()), |s| {
            (text(s, "modality").to_string(), text(s, "channel").to_string())
        })
    };
    // Annotations by (sample, instance): the anchors new boxes take their token and fields from.
    let anchor_of: HashMap<(String, String), String> = annotations
        .rows
        .iter()
        .map(|a| {
            ((text(a, "sample_token").to_string(), text(a, "instance_token").to_string()), text(a, "token").to_string())
        })
        .collect();
    let mut annotations_of: HashMap<String, Vec<String>> = HashMap::new();
    for a in &annotations.rows {
        annotations_of.entry(text(a, "sample_token").to_string()).or_default().push(text(a, "token").to_string());
    }
    let mut key_rows_of: HashMap<String, Vec<String>> = HashMap::new();
    for sd in sample_data.rows.iter().filter(|sd| sd.get("is_key_frame").and_then(Value::as_bool) == Some(true)) {
        key_rows_of.entry(text(sd, "sample_token").to_string()).or_default().push(text(sd, "token").to_string());
    }
    let mut unanchored = 0usize;
    let mut uncounted = 0usize;
    let tree_scene: HashMap<&str, usize> =
        ds.scene_tokens.iter().enumerate().map(|(i, token)| (token.as_str(), i)).collect();

    let mut out_samples: Vec<Value> = Vec::new();
    let mut written_samples: HashSet<String> = HashSet::new();
    let mut new_annotations: Vec<Value> = Vec::new();
    // Per instance, its annotations in table order: (scene, position in the scene, token).
    let mut tracks: BTreeMap<String, Vec<(usize, usize, String)>> = BTreeMap::new();
    let scene_rows: Vec<Value> = scenes.rows.clone();
    for (scene_no, scene_row) in scene_rows.iter().enumerate() {
        let Some(&tree_index) = tree_scene.get(text(scene_row, "token")) else { continue };
        let scene = &ds.tree.scenes[tree_index];
        let scene_token = text(scene_row, "token").to_string();
        // The keyframes, walked as the reader did.
        let mut keys: Vec<&Value> = Vec::new();
        let mut token = text(scene_row, "first_sample_token");
        while let Some(row) = sample_table.get(token).filter(|_| keys.len() < scene.extra.len()) {
            keys.push(row);
            token = text(row, "next");
        }

        let mut list = scene_samples(scene, &keys);
        let key_rows: HashSet<String> =
            keys.iter().flat_map(|k| key_rows_of.get(text(k, "token")).into_iter().flatten().cloned()).collect();
        let mut taken: HashSet<String> = key_rows.clone();
        // The round's images (those no keyframe holds), then per non-camera channel the reading
        // nearest the sample that no other sample holds (`nearest_free`): the LiDAR first (the
        // sample's time becomes its sweep's, as a keyframe's is), then radar.
        let chains = channel_chains(&sample_data, &key_rows, &modality_channel);
        let lidar_chain: &[(String, i64)] = chains.get(&config.lidar).map_or(&[], Vec::as_slice);
        let mut sweeps: HashMap<usize, &Reading> = HashMap::new();
        for (i, s) in list.iter_mut().enumerate() {
            let Some(round) = s.round.filter(|_| s.key.is_none()) else { continue };
            let frame = &scene.frames[round];
            for image in frame.extra.images.iter().flatten() {
                if taken.insert(image.clone()) {
                    s.rows.push(image.clone());
                }
            }
            if let Some(j) = nearest_free(lidar_chain, s.time, &taken) {
                let (token, t) = &lidar_chain[j];
                taken.insert(token.clone());
                s.rows.push(token.clone());
                s.time = *t;
                // The reader resolved the round's nearest sweep: its points are counted in the boxes.
                if let Some(reading) = frame.lidar.as_ref().ok().filter(|r| &r.token == token) {
                    sweeps.insert(i, reading);
                }
            }
        }
        for (channel, chain) in &chains {
            if *channel == config.lidar {
                continue;
            }
            for s in list.iter_mut().filter(|s| s.key.is_none()) {
                if let Some(j) = nearest_free(chain, s.time, &taken) {
                    taken.insert(chain[j].0.clone());
                    s.rows.push(chain[j].0.clone());
                }
            }
        }

        // Annotations of the new samples; their boxes' points counted in parallel (a trainval
        // export reads ~170k sweeps).
        let boxes: Vec<Vec<Box3D>> = list
            .iter()
            .map(|s| if s.key.is_some() { Ok(Vec::new()) } else { ds.boxes_at(scene, s.time, None) })
            .collect::<Result<_>>()?;
        let counts: Vec<Option<Result<Vec<u32>>>> = (0..list.len())
            .into_par_iter()
            .map(|i| sweeps.get(&i).map(|reading| points_in_boxes(reading, &boxes[i])))
            .collect();
        // Per sample, its annotations as (token, instance).
        let mut boxes_of: Vec<Vec<(String, String)>> = vec![Vec::new(); list.len()];
        for (i, s) in list.iter().enumerate() {
            if let Some(k) = s.key {
                for t in annotations_of.get(text(keys[k], "token")).into_iter().flatten() {
                    let instance = annotations.get(t).map_or("", |a| text(a, "instance_token"));
                    boxes_of[i].push((t.clone(), instance.to_string()));
                }
                continue;
            }
            let counts = match &counts[i] {
                Some(Ok(c)) => Some(c),
                Some(Err(e)) => {
                    report.warnings.push(format!("num_lidar_pts of sample {} kept from the keyframe: {e:#}", s.token));
                    None
                }
                None => {
                    uncounted += 1;
                    None
                }
            };
            for (b, bx) in boxes[i].iter().enumerate() {
                // The track's annotation on the keyframe before (`<annotation><n>`), else on the
                // one after (`<annotation>p<n>`, a track entering the annotated range).
                let named = |(n, k): (usize, usize), back: bool| {
                    let a = anchor_of.get(&(text(keys[k], "token").to_string(), bx.instance.clone()))?;
                    Some((a.clone(), if back { format!("{a}p{n}") } else { format!("{a}{n}") }))
                };
                let named = s.after.and_then(|x| named(x, false)).or_else(|| s.before.and_then(|x| named(x, true)));
                let Some((anchor, token)) = named else {
                    unanchored += 1;
                    continue;
                };
                let Some(mut row) = annotations.get(&anchor).cloned() else { continue };
                row["token"] = json!(token);
                row["sample_token"] = json!(s.token);
                row["translation"] = json!(bx.center);
                row["size"] = json!(bx.size);
                row["rotation"] = json!(bx.rotation);
                if let Some(c) = counts {
                    row["num_lidar_pts"] = json!(c[b]);
                }
                if let Some(o) = row.as_object_mut() {
                    o.remove("category_name");
                }
                report.extrapolated += bx.extrapolated as usize;
                boxes_of[i].push((token, bx.instance.clone()));
                new_annotations.push(row);
            }
        }
        for (i, held) in boxes_of.into_iter().enumerate() {
            for (token, instance) in held {
                tracks.entry(instance).or_default().push((scene_no, i, token));
            }
        }

        // sample_data: the rows each sample holds are its key frames; the scene's other rows of
        // the walked chains name the first sample at or after their time.
        for s in &list {
            for t in &s.rows {
                sample_data.set(t, "sample_token", json!(s.token));
                sample_data.set(t, "is_key_frame", json!(true));
            }
        }
        let mut by_time: Vec<(i64, &str)> = list.iter().map(|s| (s.time, s.token.as_str())).collect();
        by_time.sort();
        let held: HashSet<&String> = list.iter().flat_map(|s| s.rows.iter()).collect();
        let images = scene.frames.iter().flat_map(|f| f.extra.images.iter().flatten());
        for token in chains.values().flatten().map(|(t, _)| t).chain(images) {
            if key_rows.contains(token) || held.contains(token) {
                continue;
            }
            let Some(row) = sample_data.get(token) else { continue };
            let t = time(row);
            let at = by_time.partition_point(|(ts, _)| *ts < t).min(by_time.len() - 1);
            let sample = by_time[at].1.to_string();
            sample_data.set(token, "sample_token", json!(sample));
            sample_data.set(token, "is_key_frame", json!(false));
        }

        // The samples, chained.
        for (i, s) in list.iter().enumerate() {
            let prev = if i > 0 { list[i - 1].token.as_str() } else { "" };
            let next = list.get(i + 1).map_or("", |n| n.token.as_str());
            let mut row = match s.key {
                Some(k) => keys[k].clone(),
                None => json!({"token": s.token, "timestamp": s.time, "scene_token": scene_token}),
            };
            row["prev"] = json!(prev);
            row["next"] = json!(next);
            if let Some(o) = row.as_object_mut() {
                o.remove("data");
                o.remove("anns");
            }
            written_samples.insert(s.token.clone());
            out_samples.push(row);
        }
        scenes.set(&scene_token, "nbr_samples", json!(list.len()));
        scenes.set(&scene_token, "first_sample_token", json!(list.first().map_or("", |s| s.token.as_str())));
        scenes.set(&scene_token, "last_sample_token", json!(list.last().map_or("", |s| s.token.as_str())));
        report.scenes += 1;
        report.samples += list.len();
        report.keyframes += list.iter().filter(|s| s.key.is_some()).count();
    }
    if uncounted > 0 {
        report.warnings.push(format!(
            "{uncounted} sample(s) without their round's nearest sweep keep the keyframe's num_lidar_pts"
        ));
    }
    if unanchored > 0 {
        report.warnings.push(format!(
            "{unanchored} interpolated box(es) left out: their track has no annotation on the keyframes around them"
        ));
    }
    // Samples of no walked scene are kept as they were.
    out_samples.extend(sample_table.rows.iter().filter(|s| !written_samples.contains(text(s, "token"))).cloned());

    // Tracks: prev/next through every annotation of the instance, in sample order.
    report.annotations = new_annotations.len();
    let new_index: HashMap<String, usize> =
        new_annotations.iter().enumerate().map(|(i, a)| (text(a, "token").to_string(), i)).collect();
    for (instance, mut track) in tracks {
        track.sort();
        for (j, (_, _, token)) in track.iter().enumerate() {
            let prev = if j > 0 { track[j - 1].2.as_str() } else { "" };
            let next = track.get(j + 1).map_or("", |n| n.2.as_str());
            match new_index.get(token) {
                Some(&n) => {
                    new_annotations[n]["prev"] = json!(prev);
                    new_annotations[n]["next"] = json!(next);
                }
                None => {
                    annotations.set(token, "prev", json!(prev));
                    annotations.set(token, "next", json!(next));
                }
            }
        }
        instances.set(&instance, "nbr_annotations", json!(track.len()));
        instances.set(&instance, "first_annotation_token", json!(track[0].2));
        instances.set(&instance, "last_annotation_token", json!(track[track.len() - 1].2));
    }
    annotations.rows.extend(new_annotations);

    let files: Vec<(String, Vec<u8>)> = vec![
        ("sample".into(), serde_json::to_vec(&out_samples)?),
        ("sample_data".into(), serde_json::to_vec(&sample_data.rows)?),
        ("sample_annotation".into(), serde_json::to_vec(&annotations.rows)?),
        ("scene".into(), serde_json::to_vec(&scenes.rows)?),
        ("instance".into(), serde_json::to_vec(&instances.rows)?),
    ];
    let copied: Vec<PathBuf> =
        COPIED.iter().map(|name| tables.join(format!("{name}.json"))).filter(|p| p.exists()).collect();
    let marker = json!({"from": config.version, "lone_tracks": format!("{:?}", config.lone_tracks)}).to_string();
    write_folder(out, &files, &copied, &marker)?;
    Ok(report)
}

/// A scene's samples in time order: the keyframes (from their rounds, or on their own when no
/// round holds their images) and every other camera round, named after the keyframe before it
/// (`<keyframe><n>`) or, before the first keyframe, the one after it (`<keyframe>p<n>`).
fn scene_samples(scene: &Scene<Keyframes, Sweep>, keys: &[&Value]) -> Vec<Sample> {
    let mut used = vec![false; keys.len()];
    let mut list: Vec<Sample> = Vec::new();
    for (n, frame) in scene.frames.iter().enumerate() {
        let key = frame.extra.sample.filter(|&k| frame.extra.key && k < keys.len() && !used[k]);
        if let Some(k) = key {
            used[k] = true;
        }
        let time = key.map_or(frame.extra.timestamp, |k| time(keys[k]));
        list.push(Sample {
            token: String::new(),
            key,
            round: Some(n),
            order: frame.extra.timestamp,
            time,
            rows: Vec::new(),
            after: None,
            before: None,
        });
    }
    for (k, key) in keys.iter().enumerate().filter(|(k, _)| !used[*k]) {
        let t = time(key);
        list.push(Sample {
            token: String::new(),
            key: Some(k),
            round: None,
            order: t,
            time: t,
            rows: Vec::new(),
            after: None,
            before: None,
        });
    }
    list.sort_by_key(|s| s.order);
    let mut last: Option<(usize, usize)> = None;
    for s in list.iter_mut() {
        match s.key {
            Some(k) => last = Some((0, k)),
            None => {
                last = last.map(|(n, k)| (n + 1, k));
                s.after = last;
            }
        }
    }
    let mut next: Option<(usize, usize)> = None;
    for s in list.iter_mut().rev() {
        match s.key {
            Some(k) => next = Some((0, k)),
            None => {
                next = next.map(|(n, k)| (n + 1, k));
                s.before = next;
            }
        }
    }
    for s in list.iter_mut() {
        s.token = match (s.key, s.after, s.before) {
            (Some(k), _, _) => text(keys[k], "token").to_string(),
            (None, Some((n, k)), _) => format!("{}{n}", text(keys[k], "token")),
            (None, None, Some((n, k))) => format!("{}p{n}", text(keys[k], "token")),
            (None, None, None) => unreachable!("a scene has a keyframe"),
        };
    }
    list
}

/// The scene's non-camera channels (LiDAR, radar), each its chain of (token, time) through the
/// scene's keyframe rows.
fn channel_chains(
    sample_data: &Table,
    key_rows: &HashSet<String>,
    modality_channel: &dyn Fn(&Value) -> (String, String),
) -> BTreeMap<String, Vec<(String, i64)>> {
    let mut chains: BTreeMap<String, Vec<(String, i64)>> = BTreeMap::new();
    for token in key_rows {
        let Some(row) = sample_data.get(token) else { continue };
        let (modality, channel) = modality_channel(row);
        if modality == "camera" || chains.contains_key(&channel) {
            continue;
        }
        chains.insert(channel, walk(sample_data, row));
    }
    chains
}

/// The reading of `chain` (in time order) nearest `t` that no sample holds yet, within the chain's
/// median period (a dropped sweep leaves the round its neighbour rather than no LiDAR).
fn nearest_free(chain: &[(String, i64)], t: i64, taken: &HashSet<String>) -> Option<usize> {
    let mut steps: Vec<i64> = chain.windows(2).map(|w| w[1].1 - w[0].1).filter(|&d| d > 0).collect();
    steps.sort_unstable();
    let reach = steps.get(steps.len() / 2).copied().unwrap_or(0);
    let at = chain.partition_point(|(_, ct)| *ct < t);
    let (mut lo, mut hi) = (at.checked_sub(1), (at < chain.len()).then_some(at));
    loop {
        let dl = lo.map(|i| t - chain[i].1);
        let dh = hi.map(|i| chain[i].1 - t);
        let (i, d) = match (dl, dh) {
            (Some(a), Some(b)) if a <= b => (lo?, a),
            (_, Some(b)) => (hi?, b),
            (Some(a), None) => (lo?, a),
            (None, None) => return None,
        };
        if d > reach {
            return None;
        }
        if !taken.contains(&chain[i].0) {
            return Some(i);
        }
        if Some(i) == lo {
            lo = i.checked_sub(1);
        } else {
            hi = (i + 1 < chain.len()).then_some(i + 1);
        }
    }
}

/// The whole `prev`/`next` chain through `row`, as (token, time); a broken link ends it.
fn walk(sample_data: &Table, row: &Value) -> Vec<(String, i64)> {
    let mut first = row;
    let mut guard = 0;
    while let Some(prev) = sample_data.get(text(first, "prev")).filter(|_| guard < 1_000_000) {
        first = prev;
        guard += 1;
    }
    let mut out = vec![(text(first, "token").to_string(), time(first))];
    let mut cur = first;
    while let Some(next) = sample_data.get(text(cur, "next")).filter(|_| out.len() < 1_000_000) {
        out.push((text(next, "token").to_string(), time(next)));
        cur = next;
    }
    out
}

/// How many points of the sweep lie in each box (what nuScenes' `num_lidar_pts` counts).
fn points_in_boxes(reading: &Reading, boxes: &[Box3D]) -> Result<Vec<u32>> {
    let cloud = read_pcd_bin(&reading.file).with_context(|| reading.what.clone())?;
    let lidar_from_world = reading.pose.ego_to_world.then_from(&reading.calib.sensor_to_ego).inverse();
    Ok(boxes
        .iter()
        .map(|b| {
            let test = b.test(&lidar_from_world, 0.0, 0.0);
            cloud.points.iter().filter(|p| test.contains(DVec3::new(p[0] as f64, p[1] as f64, p[2] as f64))).count()
                as u32
        })
        .collect())
}

/// Marks a folder as written by this export: only such a folder is ever replaced.
const MARKER: &str = ".dist4d-export-12hz";

/// `out` must not hold the dataset (its root, its tables or a folder above them), and an existing
/// `out` must be an earlier export (an ASAP folder, or anything else, is left alone).
fn check_destination(out: &Path, root: &Path, tables: &Path) -> Result<()> {
    let absolute = |p: &Path| p.canonicalize().or_else(|_| std::path::absolute(p)).unwrap_or_else(|_| p.to_path_buf());
    let (o, r, t) = (absolute(out), absolute(root), absolute(tables));
    if o == t || r.starts_with(&o) {
        bail!("{} holds the dataset itself: give the 12 Hz tables a folder of their own", out.display());
    }
    if out.exists() && !out.join(MARKER).is_file() {
        bail!(
            "{} exists and was not written by `dist4d export-12hz` (no {MARKER} in it): remove it or give another --out",
            out.display()
        );
    }
    Ok(())
}

/// What to tell the user about loading the tables written to `out` from the dataset at `root`.
/// The devkit reads a version's tables from `dataroot/<version>/` and the images and map masks
/// (`maps/..`, opened when it loads) from `dataroot` itself: a folder beside the dataset's
/// `samples/` and `maps/` loads as it is, one elsewhere does not until it is linked there.
pub fn how_to_load(root: &Path, out: &Path) -> Vec<String> {
    let absolute = |p: &Path| p.canonicalize().or_else(|_| std::path::absolute(p)).unwrap_or_else(|_| p.to_path_buf());
    let (root, out) = (absolute(root), absolute(out));
    let name = out.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let load = format!("NuScenes(version='{name}', dataroot='{}')", root.display());
    if out.parent() == Some(root.as_path()) {
        return vec![format!("load it with {load}")];
    }
    vec![
        format!(
            "{} is outside the dataset root {}: the devkit reads the images and the map masks (maps/) from its \
             dataroot, which the folder's parent does not hold, so loading it there fails on a missing map mask",
            out.display(),
            root.display()
        ),
        format!("link it into the dataset root: ln -s {} {}", out.display(), root.join(&name).display()),
        format!("then load it with {load}"),
    ]
}

/// Writes the tables into a new folder beside `out` and moves it into place (the old export, if
/// any, moved aside first, put back if the move fails, removed after), so a loader never sees half
/// a version; the copied tables are copied file to file.
fn write_folder(out: &Path, files: &[(String, Vec<u8>)], copied: &[PathBuf], marker: &str) -> Result<()> {
    let name =
        out.file_name().and_then(|n| n.to_str()).ok_or_else(|| anyhow!("{} has no folder name", out.display()))?;
    let parent = out.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
    std::fs::create_dir_all(parent).with_context(|| format!("creating {}", parent.display()))?;
    let tmp = parent.join(format!(".{name}.tmp-{}", std::process::id()));
    let old = parent.join(format!(".{name}.old-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&tmp);
    let written = (|| -> Result<()> {
        std::fs::create_dir(&tmp).with_context(|| format!("creating {}", tmp.display()))?;
        let whole = files
            .iter()
            .map(|(t, b)| (format!("{t}.json"), b.as_slice()))
            .chain([(MARKER.to_string(), marker.as_bytes())]);
        for (file, bytes) in whole {
            let path = tmp.join(file);
            let mut f = std::fs::File::create(&path).with_context(|| format!("creating {}", path.display()))?;
            f.write_all(bytes).and_then(|_| f.sync_all()).with_context(|| format!("writing {}", path.display()))?;
        }
        for source in copied {
            let path = tmp.join(source.file_name().unwrap_or_default());
            std::fs::copy(source, &path)
                .with_context(|| format!("copying {} to {}", source.display(), path.display()))?;
            std::fs::File::open(&path)
                .and_then(|f| f.sync_all())
                .with_context(|| format!("syncing {}", path.display()))?;
        }
        Ok(())
    })();
    if let Err(e) = written {
        let _ = std::fs::remove_dir_all(&tmp);
        return Err(e);
    }
    if out.exists() {
        std::fs::rename(out, &old).with_context(|| format!("moving the old {} aside", out.display()))?;
    }
    if let Err(e) = std::fs::rename(&tmp, out) {
        if old.exists() {
            let _ = std::fs::rename(&old, out);
        }
        let _ = std::fs::remove_dir_all(&tmp);
        return Err(e).with_context(|| format!("moving {} to {}", tmp.display(), out.display()));
    }
    if old.exists() {
        std::fs::remove_dir_all(&old).with_context(|| format!("removing the old tables {}", old.display()))?;
    }
    if let Ok(dir) = std::fs::File::open(parent) {
        let _ = dir.sync_all();
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::with_camera_sweeps;

    fn config(root: &Path, version: &str, frames: FrameMode) -> NuScenesConfig {
        NuScenesConfig { root: root.display().to_string(), version: version.into(), frames, ..Default::default() }
    }

    fn table(dir: &Path, name: &str) -> Vec<Value> {
        serde_json::from_slice(&std::fs::read(dir.join(format!("{name}.json"))).unwrap()).unwrap()
    }

    fn by_token(rows: &[Value]) -> HashMap<&str, &Value> {
        rows.iter().map(|r| (text(r, "token"), r)).collect()
    }

    /// Every `prev`/`next` of a table names a row of it (or nothing), and each `next` is matched
    /// by that row's `prev`.
    fn chains_hold(rows: &[Value], what: &str) {
        let by = by_token(rows);
        for r in rows {
            for field in ["prev", "next"] {
                let t = text(r, field);
                assert!(t.is_empty() || by.contains_key(t), "{what} {}: {field} {t} names no row", text(r, "token"));
            }
            if let Some(next) = by.get(text(r, "next")) {
                assert_eq!(text(next, "prev"), text(r, "token"), "{what}: next's prev");
            }
        }
    }

    #[test]
    fn every_camera_round_is_a_sample_with_its_images_its_sweep_and_boxes_at_its_time() {
        let (_tmp, root) = with_camera_sweeps(3);
        let out = default_folder(&root, "v1.0-mini");
        assert_eq!(out, root.join("interp_12Hz_mini"));
        let report = write_interp_12hz(&config(&root, "v1.0-mini", FrameMode::Keyframes), &out).unwrap();
        assert_eq!((report.scenes, report.samples, report.keyframes), (1, 13, 3), "{report:?}");
        assert!(report.annotations > 0 && report.warnings.is_empty(), "{report:?}");

        // Our reader reads it as keyframes: one frame per camera round, holding that round's images.
        let rounds = NuScenes::open(config(&root, "v1.0-mini", FrameMode::Camera)).unwrap();
        let twelve = NuScenes::open(config(&root, "interp_12Hz_mini", FrameMode::Keyframes)).unwrap();
        assert!(twelve.warnings.is_empty(), "{:?}", twelve.warnings);
        let (a, b) = (&rounds.tree.scenes[0], &twelve.tree.scenes[0]);
        assert_eq!(a.frames.len(), b.frames.len());
        for (fa, fb) in a.frames.iter().zip(&b.frames) {
            assert_eq!(fa.extra.images, fb.extra.images);
            // The sample's time is its sweep's, the one the round's frame reads.
            let lidar = fa.lidar.as_ref().unwrap();
            assert_eq!(fb.lidar.as_ref().unwrap().token, lidar.token);
            assert_eq!(fb.extra.timestamp, lidar.pose.timestamp_us);
            // Its boxes are the reader's own boxes at that time.
            let (theirs, ours) = (
                rounds.boxes_at(a, fb.extra.timestamp, None).unwrap(),
                twelve.boxes_at(b, fb.extra.timestamp, None).unwrap(),
            );
            assert_eq!(theirs.len(), ours.len());
            for (x, y) in theirs.iter().zip(&ours) {
                assert_eq!(x.instance, y.instance);
                assert!((0..3).all(|i| (x.center[i] - y.center[i]).abs() < 1e-9), "{:?} vs {:?}", x.center, y.center);
            }
        }

        // The tables: nothing lost, chains whole, counts right, tokens as ASAP names them.
        let tables = root.join("v1.0-mini");
        let (sd0, sd1) = (table(&tables, "sample_data"), table(&out, "sample_data"));
        assert_eq!(sd0.len(), sd1.len(), "every sample_data row is kept");
        chains_hold(&sd1, "sample_data");
        let samples = table(&out, "sample");
        chains_hold(&samples, "sample");
        let sample_by = by_token(&samples);
        let keys: Vec<String> = table(&tables, "sample").iter().map(|s| text(s, "token").to_string()).collect();
        let scene = &table(&out, "scene")[0];
        assert_eq!(scene["nbr_samples"], json!(13));
        let mut walk = vec![text(scene, "first_sample_token").to_string()];
        while let Some(next) =
            sample_by.get(walk.last().unwrap().as_str()).map(|s| text(s, "next")).filter(|n| !n.is_empty())
        {
            walk.push(next.to_string());
        }
        assert_eq!(walk.len(), 13);
        assert_eq!(walk.last().map(String::as_str), Some(text(scene, "last_sample_token")));
        let names: Vec<String> =
            walk.iter().map(|t| t.replace(&keys[0], "K0").replace(&keys[1], "K1").replace(&keys[2], "K2")).collect();
        assert_eq!(names, ["K0", "K01", "K02", "K03", "K04", "K05", "K1", "K11", "K12", "K13", "K14", "K15", "K2"]);
        assert!(samples.iter().all(|s| s["timestamp"].is_i64()), "times are integers");
        let times: Vec<i64> = walk.iter().map(|t| time(sample_by[t.as_str()])).collect();
        assert!(times.windows(2).all(|w| w[0] < w[1]), "{times:?}");
        // Each sample holds the six images and a sweep; every other row names the first sample at
        // or after its time (the devkit's get_boxes interpolates towards it).
        for t in &walk {
            let held =
                sd1.iter().filter(|sd| text(sd, "sample_token") == t && sd["is_key_frame"] == json!(true)).count();
            assert_eq!(held, 7, "sample {t}");
        }
        for sd in sd1.iter().filter(|sd| sd["is_key_frame"] == json!(false)) {
            let at = times.partition_point(|&s| s < time(sd)).min(times.len() - 1);
            assert_eq!(text(sd, "sample_token"), walk[at], "{sd}");
        }
        let images = sd1.iter().filter(|sd| text(sd, "filename").contains("CAM_")).count();
        let key_images =
            sd1.iter().filter(|sd| text(sd, "filename").contains("CAM_") && sd["is_key_frame"] == json!(true)).count();
        assert_eq!((images, key_images), (78, 78));

        let anns = table(&out, "sample_annotation");
        let ann_by = by_token(&anns);
        assert_eq!(ann_by.len(), anns.len(), "annotation tokens are unique");
        chains_hold(&anns, "sample_annotation");
        for a in &anns {
            assert!(sample_by.contains_key(text(a, "sample_token")));
            if let Some(next) = ann_by.get(text(a, "next")) {
                assert_eq!(text(next, "instance_token"), text(a, "instance_token"));
            }
        }
        for inst in table(&out, "instance") {
            let n = anns.iter().filter(|a| text(a, "instance_token") == text(&inst, "token")).count();
            assert_eq!(inst["nbr_annotations"], json!(n));
            assert_eq!(text(ann_by[text(&inst, "first_annotation_token")], "prev"), "");
            assert_eq!(text(ann_by[text(&inst, "last_annotation_token")], "next"), "");
        }
        // The boxes of a new sample count their own sweep's points (counted here again by hand).
        let sweep = sd1
            .iter()
            .find(|sd| {
                text(sd, "sample_token") == walk[3]
                    && sd["is_key_frame"] == json!(true)
                    && text(sd, "filename").contains("LIDAR_TOP")
            })
            .unwrap();
        let pose = |table: &str, token: &str| {
            let row = self::table(&tables, table).into_iter().find(|r| text(r, "token") == token).unwrap();
            let q: Vec<f64> = row["rotation"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect();
            let t: Vec<f64> = row["translation"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect();
            (glam::DQuat::from_xyzw(q[1], q[2], q[3], q[0]).normalize(), DVec3::new(t[0], t[1], t[2]))
        };
        let (cq, ct) = pose("calibrated_sensor", text(sweep, "calibrated_sensor_token"));
        let (eq, et) = pose("ego_pose", text(sweep, "ego_pose_token"));
        let cloud = read_pcd_bin(&root.join(text(sweep, "filename"))).unwrap();
        let world: Vec<DVec3> = cloud
            .points
            .iter()
            .map(|p| eq * (cq * DVec3::new(p[0] as f64, p[1] as f64, p[2] as f64) + ct) + et)
            .collect();
        let mut counted = 0;
        for a in anns.iter().filter(|a| text(a, "sample_token") == walk[3]) {
            let v = |f: &str, i: usize| a[f][i].as_f64().unwrap();
            let q = glam::DQuat::from_xyzw(v("rotation", 1), v("rotation", 2), v("rotation", 3), v("rotation", 0));
            let c = DVec3::new(v("translation", 0), v("translation", 1), v("translation", 2));
            let inside = world
                .iter()
                .filter(|p| {
                    let l = q.inverse() * (**p - c);
                    l.x.abs() <= v("size", 1) / 2.0
                        && l.y.abs() <= v("size", 0) / 2.0
                        && l.z.abs() <= v("size", 2) / 2.0
                })
                .count();
            assert_eq!(a["num_lidar_pts"], json!(inside), "{a}");
            counted += (inside > 0) as usize;
        }
        assert!(counted > 3, "boxes with points in sample {}: {counted}", walk[3]);

        // Dropping lone tracks writes fewer boxes; the folder is replaced whole, nothing left beside it.
        let drop = NuScenesConfig { lone_tracks: LoneTracks::Drop, ..config(&root, "v1.0-mini", FrameMode::Keyframes) };
        let dropped = write_interp_12hz(&drop, &out).unwrap();
        assert_eq!(dropped.extrapolated, 0);
        assert_eq!(dropped.annotations, report.annotations - report.extrapolated);
        let beside: Vec<String> =
            std::fs::read_dir(&root).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect();
        assert!(!beside.iter().any(|n| n.starts_with('.')), "{beside:?}");
    }

    #[test]
    fn a_dropped_sweep_leaves_its_round_a_neighbour_and_radar_joins_every_sample() {
        let (_tmp, root) = with_camera_sweeps(3);
        let tables = root.join("v1.0-mini");
        let write = |name: &str, rows: &[Value]| {
            std::fs::write(tables.join(format!("{name}.json")), serde_json::to_vec(rows).unwrap()).unwrap()
        };
        let mut sd = table(&tables, "sample_data");
        let lidar = |r: &Value| text(r, "filename").contains("LIDAR_TOP");
        // A radar firing 7 ms after each sweep, with its own chain and keyframes.
        let radar: Vec<Value> = sd
            .iter()
            .filter(|r| lidar(r))
            .map(|r| {
                let mut x = r.clone();
                for f in ["token", "prev", "next"] {
                    if !text(r, f).is_empty() {
                        x[f] = json!(format!("r{}", text(r, f)));
                    }
                }
                x["calibrated_sensor_token"] = json!("radar-cs");
                x["filename"] = json!("samples/RADAR_FRONT/none.pcd");
                x["timestamp"] = json!(time(r) + 7_000);
                x
            })
            .collect();
        sd.extend(radar);
        // The third sweep is lost: its neighbours link to each other.
        let lost = sd.iter().filter(|r| lidar(r)).nth(2).unwrap().clone();
        assert_eq!(lost["is_key_frame"], json!(false));
        for r in sd.iter_mut() {
            if text(r, "next") == text(&lost, "token") {
                r["next"] = lost["next"].clone();
            }
            if text(r, "prev") == text(&lost, "token") {
                r["prev"] = lost["prev"].clone();
            }
        }
        sd.retain(|r| text(r, "token") != text(&lost, "token"));
        write("sample_data", &sd);
        let mut sensors = table(&tables, "sensor");
        sensors.push(json!({"token": "radar-sensor", "channel": "RADAR_FRONT", "modality": "radar"}));
        write("sensor", &sensors);
        let mut cs = table(&tables, "calibrated_sensor");
        let mut radar_cs =
            cs.iter().find(|c| c["camera_intrinsic"].as_array().is_none_or(|k| k.is_empty())).unwrap().clone();
        radar_cs["token"] = json!("radar-cs");
        radar_cs["sensor_token"] = json!("radar-sensor");
        cs.push(radar_cs);
        write("calibrated_sensor", &cs);

        let out = default_folder(&root, "v1.0-mini");
        let report = write_interp_12hz(&config(&root, "v1.0-mini", FrameMode::Keyframes), &out).unwrap();
        assert_eq!(report.samples, 13, "{report:?}");
        let samples = table(&out, "sample");
        let rows = table(&out, "sample_data");
        assert_eq!(rows.len(), sd.len(), "every row kept");
        chains_hold(&rows, "sample_data");
        let mut times: Vec<i64> = samples.iter().map(time).collect();
        times.sort();
        for s in &samples {
            let held: Vec<&str> = rows
                .iter()
                .filter(|r| text(r, "sample_token") == text(s, "token") && r["is_key_frame"] == json!(true))
                .map(|r| text(r, "filename"))
                .collect();
            assert_eq!(held.len(), 8, "six images, a sweep and a radar reading: {held:?}");
            assert!(held.iter().any(|f| f.contains("LIDAR_TOP")) && held.iter().any(|f| f.contains("RADAR")));
        }
        // The sample that would have had the lost sweep still has times in order.
        let mut chain = vec![text(&table(&out, "scene")[0], "first_sample_token").to_string()];
        let by = by_token(&samples);
        while let Some(n) = by.get(chain.last().unwrap().as_str()).map(|s| text(s, "next")).filter(|n| !n.is_empty()) {
            chain.push(n.to_string());
        }
        let ordered: Vec<i64> = chain.iter().map(|t| time(by[t.as_str()])).collect();
        assert!(ordered.windows(2).all(|w| w[0] < w[1]), "{ordered:?}");
        assert_eq!(ordered, times);
    }

    #[test]
    fn only_an_earlier_export_is_ever_replaced() {
        let (_tmp, root) = with_camera_sweeps(2);
        let cfg = config(&root, "v1.0-mini", FrameMode::Keyframes);
        for holds_data in [root.clone(), root.join("v1.0-mini"), root.parent().unwrap().to_path_buf()] {
            let e = format!("{:#}", write_interp_12hz(&cfg, &holds_data).unwrap_err());
            assert!(e.contains("holds the dataset itself"), "{e}");
        }
        let theirs = root.join("interp_12Hz_mini");
        std::fs::create_dir(&theirs).unwrap();
        std::fs::write(theirs.join("sample.json"), "[]").unwrap();
        let e = format!("{:#}", write_interp_12hz(&cfg, &theirs).unwrap_err());
        assert!(e.contains("was not written by `dist4d export-12hz`"), "{e}");
        assert_eq!(std::fs::read(theirs.join("sample.json")).unwrap(), b"[]", "left as it was");
        std::fs::remove_dir_all(&theirs).unwrap();
        write_interp_12hz(&cfg, &theirs).unwrap();
        write_interp_12hz(&cfg, &theirs).unwrap();
        assert!(root.join("samples").is_dir() && root.join("v1.0-mini/sample.json").is_file(), "the dataset is whole");
    }

    /// Writes `interp_12Hz_trainval/` from `v1.0-mini/` by the rules of ASAP's
    /// `sAP3D/nusc_annotation_generator.py` (interp strategy), as we read it: five new samples per
    /// keyframe interval at evenly spaced times written as fractions, named `<keyframe><i>`; the
    /// keyframe sample_data rows only, each followed by five rows `<row><i>` for the i-th next file
    /// of its channel, all key frames, with dangling `prev`/`next`; annotations of tracks on both
    /// keyframes interpolated (others dropped); `scene` and `instance` copied as they are, here with
    /// one more scene whose samples are not in the folder (ASAP writes the val split's samples but
    /// copies every scene).
    fn asap_style(root: &Path) -> PathBuf {
        let src = root.join("v1.0-mini");
        let out = root.join("interp_12Hz_trainval");
        std::fs::create_dir(&out).unwrap();
        let samples = table(&src, "sample");
        let sd = table(&src, "sample_data");
        let anns = table(&src, "sample_annotation");
        let (sample_by, sd_by) = (by_token(&samples), by_token(&sd));
        let mut new_samples = Vec::new();
        let mut new_sd = Vec::new();
        let mut new_anns = Vec::new();
        let t = |v: &Value| v["timestamp"].as_f64().unwrap();
        for s in &samples {
            let token = text(s, "token");
            let last = text(s, "next").is_empty();
            let mut k = s.clone();
            k["data"] = json!({});
            k["anns"] = json!([]);
            if !text(s, "prev").is_empty() {
                k["prev"] = json!(format!("{}5", text(s, "prev")));
            }
            if !last {
                k["next"] = json!(format!("{token}1"));
            }
            new_samples.push(k);
            let next = (!last).then(|| sample_by[text(s, "next")]);
            for i in 1..6 {
                let Some(next) = next else { break };
                let time = t(s) + i as f64 / 6.0 * (t(next) - t(s));
                new_samples.push(
                    json!({"token": format!("{token}{i}"), "scene_token": s["scene_token"], "timestamp": time,
                    "prev": if i == 1 { token.to_string() } else { format!("{token}{}", i - 1) },
                    "next": if i == 5 { text(s, "next").to_string() } else { format!("{token}{}", i + 1) }}),
                );
            }
            for row in sd.iter().filter(|r| text(r, "sample_token") == token && r["is_key_frame"] == json!(true)) {
                let mut k = row.clone();
                if last {
                    k["prev"] = json!(format!("{}5", text(row, "prev")));
                } else {
                    k["next"] = json!(format!("{}1", text(row, "token")));
                }
                new_sd.push(k);
                let Some(next) = next else { continue };
                let mut file = row;
                for i in 1..6 {
                    if let Some(n) = sd_by.get(text(file, "next")).filter(|n| n["is_key_frame"] != json!(true)) {
                        file = n;
                    }
                    let mut e = row.clone();
                    let tok = format!("{}{i}", text(row, "token"));
                    e["prev"] = json!(format!("{tok}{}", i - 1));
                    e["next"] = json!(format!("{tok}{}", i + 1));
                    e["token"] = json!(tok);
                    e["sample_token"] = json!(format!("{token}{i}"));
                    e["timestamp"] = json!(t(row) + i as f64 / 6.0 * (t(next) - t(row)));
                    for f in ["ego_pose_token", "calibrated_sensor_token", "filename"] {
                        e[f] = file[f].clone();
                    }
                    new_sd.push(e);
                }
            }
            let of = |sample: &str, inst: &str| {
                anns.iter().find(|a| text(a, "sample_token") == sample && text(a, "instance_token") == inst)
            };
            for a in anns.iter().filter(|a| text(a, "sample_token") == token) {
                let inst = text(a, "instance_token");
                let mut k = a.clone();
                k["category_name"] = json!("vehicle.car");
                let later = next.and_then(|n| of(text(n, "token"), inst));
                if later.is_some() {
                    k["next"] = json!(format!("{}1", text(a, "token")));
                }
                if of(text(s, "prev"), inst).is_some() {
                    k["prev"] = json!(format!("{}5", text(a, "prev")));
                }
                new_anns.push(k);
                let (Some(next), Some(b)) = (next, later) else { continue };
                for i in 1..6 {
                    let w = i as f64 / 6.0;
                    let _ = next;
                    let lerp: Vec<f64> = (0..3)
                        .map(|j| {
                            let (x, y) = (a["translation"][j].as_f64().unwrap(), b["translation"][j].as_f64().unwrap());
                            x + (y - x) * w
                        })
                        .collect();
                    let mut e = a.clone();
                    let tok = text(a, "token");
                    e["token"] = json!(format!("{tok}{i}"));
                    e["sample_token"] = json!(format!("{token}{i}"));
                    e["translation"] = json!(lerp);
                    e["prev"] = json!(if i == 1 { tok.to_string() } else { format!("{tok}{}", i - 1) });
                    e["next"] = json!(if i == 5 { text(b, "token").to_string() } else { format!("{tok}{}", i + 1) });
                    new_anns.push(e);
                }
            }
        }
        let write =
            |name: &str, rows: &Value| std::fs::write(out.join(format!("{name}.json")), rows.to_string()).unwrap();
        write("sample", &json!(new_samples));
        write("sample_data", &json!(new_sd));
        write("sample_annotation", &json!(new_anns));
        let mut scenes = table(&src, "scene");
        let mut train = scenes[0].clone();
        train["token"] = json!("0".repeat(32));
        train["name"] = json!("scene-train");
        train["first_sample_token"] = json!("f".repeat(32));
        scenes.push(train);
        write("scene", &json!(scenes));
        for name in COPIED.iter().chain(&["instance"]) {
            std::fs::copy(src.join(format!("{name}.json")), out.join(format!("{name}.json"))).unwrap();
        }
        out
    }

    #[test]
    fn a_folder_made_by_asaps_rules_reads_as_one_frame_per_sample() {
        let (_tmp, root) = with_camera_sweeps(3);
        asap_style(&root);
        let ds = NuScenes::open(config(&root, "interp_12Hz_trainval", FrameMode::Keyframes)).unwrap();
        assert!(
            ds.warnings.iter().any(|w| w.contains("1 scene(s) name a first_sample_token") && w.contains("scene-train")),
            "{:?}",
            ds.warnings
        );
        assert_eq!(ds.tree.scenes.len(), 1);
        let scene = &ds.tree.scenes[0];
        assert_eq!(scene.frames.len(), 13);
        // Times with fractions are read to the microsecond; each sample has its six images.
        let times: Vec<i64> = scene.frames.iter().map(|f| f.extra.timestamp).collect();
        assert!(times.windows(2).all(|w| (w[1] - w[0] - 83_333).abs() <= 1), "{times:?}");
        for f in &scene.frames {
            assert!(f.cameras.iter().all(Result::is_ok) && f.lidar.is_ok());
        }
        // A new sample's boxes are its own interpolated annotations.
        let boxes = ds.boxes_at(scene, times[3], Some(3)).unwrap();
        assert!(!boxes.is_empty());
        assert!(boxes.iter().all(|b| b.velocity.iter().all(|v| v.is_finite())), "velocities from the 12 Hz track");
    }
}
