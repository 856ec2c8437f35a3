//! `AggregateScene`: every LiDAR sweep of a scene gathered once, as Occ3D and SurroundOcc build
//! occupancy (a scene-grain task, not one per frame): the static points in world coordinates,
//! and each tracked object's points in its own box frame along its track, so that an object
//! placed at any frame's box pose is dense and a moving one leaves no smear.
//!
//! Per sweep: points go sensor -> ego -> world through its calibration and ego pose; points
//! inside the ego vehicle's box or nearer than `min_distance` to the LiDAR are dropped. A point
//! inside a box of its frame (grown by `box_margin`, bottom raised by `ground_clearance` so the
//! road under a car stays road) goes to that box's track, with the box's class. A labelled point
//! goes by its label instead: into the box when its label is the box's class, the bottom
//! included (a pedestrian's feet, which would otherwise stay behind as a trail of static
//! pedestrian points), and never when it is something else (a pole by a pedestrian). The others
//! are static. Classes ([`super::classes`]): nuScenes-lidarseg labels where the sweep has them. A
//! sweep without labels (nuScenes labels keyframes only: at 10-20 Hz, most sweeps) takes, for
//! each static point, the label of the nearest labelled static point of the scene in the world
//! frame, within `transfer_distance` metres (the labelled sweeps' static points are gathered
//! first). A point with none that near, or a scene without any labels, falls back to height:
//! within `fallback_ground` metres of the ego frame's ground plane driveable surface, above it
//! manmade. The `summary` says how many points took which. Both clouds are thinned to one point
//! per voxel (`voxel`, `track_voxel`), the first in sweep, then point order.

use super::classes::{self, DRIVEABLE_SURFACE, DROP, MANMADE};
use crate::stage::Stage;
use anyhow::{ensure, Result};
use dist4d_graph::{ParamChecks, ParamProblem, Validate};
use dist4d_runtime::TaskContext;
use dist4d_types::artifact::{Boxes3D, Calibration, File, PointCloud, Pose, TrackCloud, TrackClouds};
use dist4d_types::geometry::{BoxTest, Se3};
use glam::DVec3;
use serde::{Deserialize, Serialize};
use serde_json::json;
use std::collections::{BTreeMap, HashMap, HashSet};

/// Where the points of annotated objects are gathered.
#[derive(Serialize, Deserialize, Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum Objects {
    /// In each object's own box frame along its track (placed at each frame's box pose).
    #[default]
    BoxFrames,
    /// In the world, like the static points, with the box's class: what the box frames are
    /// for (a moving object smears along its path), kept as the ablation.
    World,
}

#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    pub objects: Objects,
    /// Static points: one per voxel of this size (m).
    pub voxel: f64,
    /// Object points: one per voxel of this size (m) of the box frame.
    pub track_voxel: f64,
    /// Boxes grow by this much (m) sideways and on top.
    pub box_margin: f64,
    /// Points less than this (m) above a box's bottom are the ground under it.
    pub ground_clearance: f64,
    /// Points nearer than this (m) to their LiDAR are dropped.
    pub min_distance: f64,
    /// The ego vehicle's box in the ego frame, min and max corners (m).
    pub ego_box_min: [f64; 3],
    pub ego_box_max: [f64; 3],
    /// Without point labels: points below this height (m, ego frame) are driveable surface.
    pub fallback_ground: f64,
    /// An unlabelled point takes the label of the nearest labelled one within this distance (m).
    pub transfer_distance: f64,
}

impl Default for Params {
    fn default() -> Self {
        Params {
            objects: Objects::BoxFrames,
            voxel: 0.1,
            track_voxel: 0.05,
            box_margin: 0.1,
            ground_clearance: 0.15,
            min_distance: 1.0,
            ego_box_min: [-1.0, -1.0, -1.0],
            ego_box_max: [3.4, 1.0, 2.0],
            fallback_ground: 0.3,
            transfer_distance: 0.5,
        }
    }
}

impl Validate for Params {
    fn validate(&self) -> Vec<ParamProblem> {
        let mut c = ParamChecks::new();
        c.above("voxel", self.voxel, 0.001, 100.0)
            .above("track_voxel", self.track_voxel, 0.001, 100.0)
            .within("box_margin", self.box_margin, 0.0, 100.0)
            .within("ground_clearance", self.ground_clearance, 0.0, 100.0)
            .within("min_distance", self.min_distance, 0.0, 1000.0)
            .within("fallback_ground", self.fallback_ground, -100.0, 100.0)
            .within("transfer_distance", self.transfer_distance, 0.0, 100.0);
        for a in 0..3 {
            c.check(
                self.ego_box_min[a].is_finite() && self.ego_box_max[a].is_finite() && self.ego_box_min[a] <= self.ego_box_max[a],
                "ego_box_min",
                || format!("must not exceed `ego_box_max` on axis {a}"),
            );
        }
        c.done()
    }
}

crate::ports! {
    pub struct Inputs {
        /// every sweep of the scene (`All("dataset.lidar")`), matched to the rest by position
        sweeps: Many<PointCloud>,
        /// their LiDAR calibrations
        calibs: Many<Calibration>,
        /// their ego poses
        poses: Many<Pose>,
        /// the boxes at each sweep's time
        boxes: Many<Boxes3D>,
    }
}

crate::ports! {
    pub struct Outputs {
        /// the static points in world coordinates, labels = Occ3D classes
        static_points: One<PointCloud>,
        /// each tracked object's points in its box frame, with its class
        tracks: One<TrackClouds>,
        /// JSON: sweeps, points kept, where the labels came from
        summary: One<File>,
    }
}

pub struct AggregateScene(Params);

impl Stage for AggregateScene {
    const KIND: &'static str = "AggregateScene";
    // 2: unlabelled sweeps take the nearest labelled point's label.
    // 3: a labelled point joins a track exactly when its label is the box's class, feet included.
    const VERSION: u32 = 4;
    const SUMMARY: &'static str =
        "a scene's LiDAR gathered once: static points in the world, each object's in its box frame, Occ3D classes";
    const GRAINS: &'static [&'static str] = &["scene"];
    type Params = Params;
    type Inputs = Inputs;
    type Outputs = Outputs;

    fn new(params: Params) -> Result<Self> {
        Ok(AggregateScene(params))
    }

    fn run(&self, _: &TaskContext, i: Inputs) -> Result<Outputs> {
        let n = i.sweeps.len();
        ensure!(
            i.calibs.len() == n && i.poses.len() == n && i.boxes.len() == n,
            "`sweeps`, `calibs`, `poses` and `boxes` hold {n}, {}, {} and {} items: wire them all with All(..)",
            i.calibs.len(),
            i.poses.len(),
            i.boxes.len()
        );
        let mut sweeps = Vec::with_capacity(n);
        for k in 0..n {
            let pos = i.sweeps[k].0;
            ensure!(
                i.calibs[k].0 == pos && i.poses[k].0 == pos && i.boxes[k].0 == pos,
                "the inputs must be wired with the same selector (All(..))"
            );
            sweeps.push(Sweep { points: &i.sweeps[k].1, calib: &i.calibs[k].1, pose: &i.poses[k].1, boxes: &i.boxes[k].1 });
        }
        let (static_points, tracks, summary) = aggregate(&self.0, &sweeps);
        Ok(Outputs { static_points, tracks, summary: File(serde_json::to_vec_pretty(&summary)?) })
    }
}

pub struct Sweep<'a> {
    pub points: &'a PointCloud,
    pub calib: &'a Calibration,
    pub pose: &'a Pose,
    pub boxes: &'a Boxes3D,
}

type Voxel = (i64, i64, i64);

fn voxel_of(p: DVec3, size: f64) -> Voxel {
    ((p.x / size).floor() as i64, (p.y / size).floor() as i64, (p.z / size).floor() as i64)
}

/// A static point of a sweep, in the world, with its class if its sweep had labels, and its
/// height in its own ego frame (for the height fallback).
struct StaticPoint {
    world: DVec3,
    intensity: f32,
    class: Option<u8>,
    ego_z: f64,
}

/// Labelled points binned by voxel of `size`, for nearest-label lookups.
struct LabelIndex {
    size: f64,
    cells: HashMap<Voxel, Vec<(DVec3, u8)>>,
}

impl LabelIndex {
    fn nearest(&self, p: DVec3, within: f64) -> Option<u8> {
        let (cx, cy, cz) = voxel_of(p, self.size);
        let reach = (within / self.size).ceil() as i64;
        let mut best: Option<(f64, u8)> = None;
        for dx in -reach..=reach {
            for dy in -reach..=reach {
                for dz in -reach..=reach {
                    for (q, class) in self.cells.get(&(cx + dx, cy + dy, cz + dz)).into_iter().flatten() {
                        let d = (*q - p).length();
                        if d <= within && best.is_none_or(|(bd, _)| d < bd) {
                            best = Some((d, *class));
                        }
                    }
                }
            }
        }
        best.map(|(_, c)| c)
    }
}

/// The aggregation of the module doc: static points, tracks and a summary.
pub fn aggregate(p: &Params, sweeps: &[Sweep]) -> (PointCloud, TrackClouds, serde_json::Value) {
    // One static point per voxel (the first; a labelled point replaces an unlabelled one), so
    // that memory follows the scene's extent, not its number of sweeps.
    let mut statics: Vec<StaticPoint> = Vec::new();
    let mut static_at: HashMap<Voxel, usize> = HashMap::new();
    let mut keep = |sp: StaticPoint| match static_at.entry(voxel_of(sp.world, p.voxel)) {
        std::collections::hash_map::Entry::Vacant(e) => {
            e.insert(statics.len());
            statics.push(sp);
        }
        std::collections::hash_map::Entry::Occupied(e) => {
            let old = &mut statics[*e.get()];
            if old.class.is_none() && sp.class.is_some() {
                *old = sp;
            }
        }
    };
    // instance -> (class, voxels seen, points)
    let mut tracks: BTreeMap<String, (u8, HashSet<Voxel>, Vec<[f32; 3]>)> = BTreeMap::new();
    let (emin, emax) = (DVec3::from_array(p.ego_box_min), DVec3::from_array(p.ego_box_max));
    let (mut labelled, mut points_in, mut dropped) = (0usize, 0usize, 0usize);
    for s in sweeps {
        let has_labels = s.points.labels.len() == s.points.points.len() && !s.points.points.is_empty();
        labelled += has_labels as usize;
        // Per box: the test for unlabelled points (its bottom raised: the ground under a car is
        // not the car) and the one for points its class labels (whole: a pedestrian's feet are).
        let boxes: Vec<(BoxTest, BoxTest, u8, &dist4d_types::artifact::Box3D)> = s
            .boxes
            .boxes
            .iter()
            .map(|b| {
                let pose = Se3::from_wxyz_t(b.rotation, b.center);
                (
                    BoxTest::new(b.size, &pose, &Se3::default(), p.box_margin, p.ground_clearance),
                    BoxTest::new(b.size, &pose, &Se3::default(), p.box_margin, 0.0),
                    classes::of_category(&b.category),
                    b,
                )
            })
            .collect();
        for (k, q) in s.points.points.iter().enumerate() {
            points_in += 1;
            let sensor = DVec3::new(q[0] as f64, q[1] as f64, q[2] as f64);
            if sensor.length() < p.min_distance {
                dropped += 1;
                continue;
            }
            let ego = s.calib.sensor_to_ego.apply(sensor);
            if ego.cmpge(emin).all() && ego.cmple(emax).all() {
                dropped += 1;
                continue;
            }
            let world = s.pose.ego_to_world.apply(ego);
            let label = has_labels.then(|| classes::of_lidarseg(s.points.labels[k]));
            // A labelled point joins a box's track only when its label is the box's class: the
            // pole or the wall a pedestrian stands by, inside the grown box, is not the pedestrian
            // (drawn at every pose of the track, it would walk along with it).
            let in_box = boxes
                .iter()
                .find(|(raised, whole, class, _)| match label {
                    None => raised.contains(world),
                    Some(l) => l == *class && whole.contains(world),
                })
                .map(|(_, whole, _, b)| (whole, *b));
            if let (Some((_, b)), Objects::World) = (in_box, p.objects) {
                keep(StaticPoint { world, intensity: q[3], class: Some(classes::of_category(&b.category)), ego_z: ego.z });
                continue;
            }
            if let Some((test, b)) = in_box {
                let local = test.local(world);
                let entry = tracks.entry(b.instance.clone()).or_insert_with(|| (classes::of_category(&b.category), HashSet::new(), Vec::new()));
                if entry.1.insert(voxel_of(local, p.track_voxel)) {
                    entry.2.push([local.x as f32, local.y as f32, local.z as f32]);
                }
                continue;
            }
            let class = label;
            if class == Some(DROP) {
                dropped += 1;
                continue;
            }
            keep(StaticPoint { world, intensity: q[3], class, ego_z: ego.z });
        }
    }
    drop(keep);
    // Labels for the points of unlabelled sweeps: the nearest labelled static point's.
    let size = p.transfer_distance.max(0.05);
    let mut index = LabelIndex { size, cells: HashMap::new() };
    for sp in statics.iter().filter(|sp| sp.class.is_some()) {
        index.cells.entry(voxel_of(sp.world, size)).or_default().push((sp.world, sp.class.unwrap_or(0)));
    }
    let (mut transferred, mut fallback) = (0usize, 0usize);
    let mut static_points = PointCloud::default();
    for sp in &statics {
        let class = match sp.class {
            Some(c) => c,
            None => match index.nearest(sp.world, p.transfer_distance) {
                Some(c) => {
                    transferred += 1;
                    c
                }
                None => {
                    fallback += 1;
                    if sp.ego_z < p.fallback_ground {
                        DRIVEABLE_SURFACE
                    } else {
                        MANMADE
                    }
                }
            },
        };
        static_points.points.push([sp.world.x as f32, sp.world.y as f32, sp.world.z as f32, sp.intensity]);
        static_points.labels.push(class);
    }
    let tracks = TrackClouds {
        tracks: tracks
            .into_iter()
            .map(|(instance, (class, _, points))| TrackCloud { instance, class, points })
            .collect(),
    };
    let source = match labelled {
        0 => "fallback: no sweep has point labels; boxes give their class, the rest is driveable surface below `fallback_ground` (ego frame) and manmade above",
        l if l == sweeps.len() => "nuScenes-lidarseg (every sweep), boxes give their class",
        _ => "nuScenes-lidarseg where a sweep has it; the other sweeps' static points take the nearest labelled point's label within `transfer_distance` (else the height fallback); boxes give their class",
    };
    let summary = json!({
        "sweeps": sweeps.len(),
        "sweeps_with_labels": labelled,
        "labels": source,
        "points_read": points_in,
        "points_dropped": dropped,
        "static_labels_transferred": transferred,
        "static_labels_by_height": fallback,
        "static_points": static_points.points.len(),
        "tracks": tracks.tracks.len(),
        "track_points": tracks.tracks.iter().map(|t| t.points.len()).sum::<usize>(),
    });
    (static_points, tracks, summary)
}
