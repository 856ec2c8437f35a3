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
//! are static. Classes ([`super::classes`]), first source that has one:
//! 1. nuScenes-lidarseg labels where the sweep has them (`lidarseg: true`);
//! 2. the camera labels of `LabelPoints` (a segmenter worker), where it labelled the point;
//! 3. for a static point still without one (a sweep between labelled keyframes, a point no
//!    camera saw): the label of the nearest labelled static point of the scene in the world
//!    frame, within `transfer_distance` metres, else within `transfer_reach` metres (among the
//!    labelled points thinned to one per `transfer_distance` voxel). The second, wider search is
//!    what keeps the rings of the unlabelled 20 Hz sweeps that lie between the labelled rings
//!    (further than `transfer_distance` from any) from taking the geometry rule, which painted
//!    road-labelled arcs across terrain and sidewalk;
//! 4. the geometry rule, the only one on a scene without any labels: within `fallback_ground`
//!    metres of the ego frame's ground plane driveable surface, above it `others` (0), never a
//!    guessed class such as manmade (grass, hedges, cars without a box are not buildings).
//!
//! The `summary` says which sources the scene had (`semantics_source`: `lidarseg`, `camera`,
//! `lidarseg+camera`, `geometry`; `+transfer` when unlabelled sweeps took their neighbours'
//! labels) and how many static points took which. Both clouds are thinned to one point per voxel
//! (`voxel`, `track_voxel`), the first in sweep, then point order.

use dist4d_runtime::Made;
use super::classes::{self, DRIVEABLE_SURFACE, DROP, OTHERS, UNLABELLED};
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
    /// Without point labels: points below this height (m, ego frame) are driveable surface,
    /// the others `others`.
    pub fallback_ground: f64,
    /// An unlabelled point takes the label of the nearest labelled one within this distance (m).
    pub transfer_distance: f64,
    /// Failing that, of the nearest labelled one within this distance (m; 0 = no second search).
    pub transfer_reach: f64,
    /// Use the dataset's nuScenes-lidarseg labels (false: only cameras or geometry; what the
    /// segmenter is benchmarked with on data that has lidarseg).
    pub lidarseg: bool,
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
            transfer_reach: 3.0,
            lidarseg: true,
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
            .within("transfer_distance", self.transfer_distance, 0.0, 100.0)
            .within("transfer_reach", self.transfer_reach, 0.0, 100.0);
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

crate::inputs! {
    pub struct Inputs {
        /// every sweep of the scene (`All("dataset.lidar")`), matched to the rest by position
        sweeps: Many<PointCloud>,
        /// their LiDAR calibrations
        calibs: Many<Calibration>,
        /// their ego poses
        poses: Many<Pose>,
        /// the boxes at each sweep's time
        boxes: Many<Boxes3D>,
        /// the sweeps' points labelled by cameras (`All("labels.sweep")`, `LabelPoints`; Occ3D classes, 254 = none); unwired or empty without a segmenter
        camera_labels: OptionalMany<PointCloud>,
    }
}

crate::outputs! {
    pub struct Outputs {
        /// the static points in world coordinates, labels = Occ3D classes
        static_points: One<PointCloud>,
        /// each tracked object's points in its box frame, with its class
        tracks: One<TrackClouds>,
        /// JSON: sweeps, points kept, where the labels came from (`semantics_source`)
        summary: One<File>,
    }
}

pub struct AggregateScene(Params);

impl Stage for AggregateScene {
    const KIND: &'static str = "AggregateScene";
    // 2: unlabelled sweeps take the nearest labelled point's label.
    // 3: a labelled point joins a track exactly when its label is the box's class, feet included.
    // 5: camera labels; the wider transfer; the geometry rule says `others`, not manmade.
    // 6: a camera label of the box's class joins the box whole, feet included.
    const VERSION: u32 = 6;
    const SUMMARY: &'static str =
        "a scene's LiDAR gathered once: static points in the world, each object's in its box frame, Occ3D classes";
    const GRAINS: &'static [&'static str] = &["scene"];
    type Params = Params;
    type Inputs = Inputs;
    type Outputs = Outputs;

    fn new(params: Params) -> Result<Self> {
        Ok(AggregateScene(params))
    }

    fn run(&self, _: &TaskContext, i: Inputs) -> Result<Made<Outputs>> {
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
            // An empty cloud: `LabelPoints` without a worker.
            let camera = i
                .camera_labels
                .iter()
                .find(|(p, c)| *p == pos && !c.points.is_empty())
                .map(|(_, c)| c.labels.as_slice());
            if let Some(c) = camera {
                ensure!(
                    c.len() == i.sweeps[k].1.points.len(),
                    "`camera_labels` at position {pos} has {} labels for a sweep of {} points: wire it from the same sweeps",
                    c.len(),
                    i.sweeps[k].1.points.len()
                );
            }
            sweeps.push(Sweep {
                points: &i.sweeps[k].1,
                calib: &i.calibs[k].1,
                pose: &i.poses[k].1,
                boxes: &i.boxes[k].1,
                camera_labels: camera,
            });
        }
        let (static_points, tracks, summary) = aggregate(&self.0, &sweeps);
        Ok(Outputs { static_points, tracks, summary: File(serde_json::to_vec_pretty(&summary)?) }.into())
    }
}

pub struct Sweep<'a> {
    pub points: &'a PointCloud,
    pub calib: &'a Calibration,
    pub pose: &'a Pose,
    pub boxes: &'a Boxes3D,
    /// `LabelPoints`' Occ3D class per point ([`UNLABELLED`]: none), when a segmenter ran.
    pub camera_labels: Option<&'a [u8]>,
}

type Voxel = (i64, i64, i64);

fn voxel_of(p: DVec3, size: f64) -> Voxel {
    ((p.x / size).floor() as i64, (p.y / size).floor() as i64, (p.z / size).floor() as i64)
}

/// Where a static point's class came from.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
enum Source {
    Lidarseg,
    Camera,
}

/// A static point of a sweep, in the world, with its class and its source if it has one, and
/// its height in its own ego frame (for the geometry rule).
struct StaticPoint {
    world: DVec3,
    intensity: f32,
    class: Option<(u8, Source)>,
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
            let rank = |c: &Option<(u8, Source)>| match c {
                None => 0,
                Some((_, Source::Camera)) => 1,
                Some((_, Source::Lidarseg)) => 2,
            };
            if rank(&sp.class) > rank(&old.class) {
                *old = sp;
            }
        }
    };
    // instance -> (class, voxels seen, points)
    let mut tracks: BTreeMap<String, (u8, HashSet<Voxel>, Vec<[f32; 3]>)> = BTreeMap::new();
    let (emin, emax) = (DVec3::from_array(p.ego_box_min), DVec3::from_array(p.ego_box_max));
    let (mut labelled, mut camera_labelled, mut points_in, mut dropped) = (0usize, 0usize, 0usize, 0usize);
    for s in sweeps {
        let has_labels = p.lidarseg && s.points.labels.len() == s.points.points.len() && !s.points.points.is_empty();
        labelled += has_labels as usize;
        let camera = if has_labels { None } else { s.camera_labels.filter(|c| c.len() == s.points.points.len()) };
        camera_labelled += camera.is_some() as usize;
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
            // A camera label joins the same way when it is the box's class (a pedestrian's feet,
            // under the raised bottom, would otherwise trail behind as static points); when it is
            // another class the box geometry decides, as for an unlabelled point (a pixel on a
            // car's rim may be the road behind it).
            let seen = camera.map(|c| c[k]);
            let in_box = boxes
                .iter()
                .find(|(raised, whole, class, _)| match (label, seen) {
                    (Some(l), _) => l == *class && whole.contains(world),
                    (None, Some(c)) if c == *class => whole.contains(world),
                    _ => raised.contains(world),
                })
                .map(|(_, whole, _, b)| (whole, *b));
            if let (Some((_, b)), Objects::World) = (in_box, p.objects) {
                let class = Some((classes::of_category(&b.category), Source::Lidarseg));
                keep(StaticPoint { world, intensity: q[3], class, ego_z: ego.z });
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
            if label == Some(DROP) {
                dropped += 1;
                continue;
            }
            let class = match (label, seen) {
                (Some(l), _) => Some((l, Source::Lidarseg)),
                (None, Some(c)) if c != UNLABELLED && c != DROP => Some((c, Source::Camera)),
                _ => None,
            };
            keep(StaticPoint { world, intensity: q[3], class, ego_z: ego.z });
        }
    }
    drop(keep);
    // Labels for the points of unlabelled sweeps: the nearest labelled static point's, near,
    // then (among labelled points thinned to one per `transfer_distance` voxel) within reach.
    let size = p.transfer_distance.max(0.05);
    let mut index = LabelIndex { size, cells: HashMap::new() };
    let reach_size = p.transfer_reach.max(size);
    let mut wide = LabelIndex { size: reach_size, cells: HashMap::new() };
    let mut thinned: HashSet<Voxel> = HashSet::new();
    for sp in &statics {
        let Some((class, _)) = sp.class else { continue };
        index.cells.entry(voxel_of(sp.world, size)).or_default().push((sp.world, class));
        if thinned.insert(voxel_of(sp.world, size)) {
            wide.cells.entry(voxel_of(sp.world, reach_size)).or_default().push((sp.world, class));
        }
    }
    let (mut from_lidarseg, mut from_camera, mut transferred, mut fallback) = (0usize, 0usize, 0usize, 0usize);
    let mut static_points = PointCloud::default();
    for sp in &statics {
        let near = || {
            index.nearest(sp.world, p.transfer_distance).or_else(|| {
                (p.transfer_reach > p.transfer_distance).then(|| wide.nearest(sp.world, p.transfer_reach)).flatten()
            })
        };
        let class = match sp.class {
            Some((c, Source::Lidarseg)) => {
                from_lidarseg += 1;
                c
            }
            Some((c, Source::Camera)) => {
                from_camera += 1;
                c
            }
            None => match near() {
                Some(c) => {
                    transferred += 1;
                    c
                }
                None => {
                    fallback += 1;
                    if sp.ego_z < p.fallback_ground {
                        DRIVEABLE_SURFACE
                    } else {
                        OTHERS
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
    let provenance = semantics_source(sweeps.len(), labelled, camera_labelled);
    let source = match provenance.as_str() {
        "geometry" => "geometry only: no sweep has point labels and no segmenter labelled any; boxes give their class, the rest is driveable surface below `fallback_ground` (ego frame) and others (0) above",
        "lidarseg" => "nuScenes-lidarseg (every sweep), boxes give their class",
        "camera" => "camera segmentation (LabelPoints) on every sweep; points no camera labelled take the nearest labelled point's label within `transfer_reach` (else the geometry rule); boxes give their class",
        _ => "nuScenes-lidarseg where a sweep has it, camera segmentation (LabelPoints) where a segmenter labelled it; the other static points take the nearest labelled point's label within `transfer_reach` (else the geometry rule); boxes give their class",
    };
    let summary = json!({
        "sweeps": sweeps.len(),
        "sweeps_with_labels": labelled,
        "sweeps_with_camera_labels": camera_labelled,
        "semantics_source": provenance,
        "labels": source,
        "points_read": points_in,
        "points_dropped": dropped,
        "static_labels_lidarseg": from_lidarseg,
        "static_labels_camera": from_camera,
        "static_labels_transferred": transferred,
        "static_labels_by_height": fallback,
        "static_points": static_points.points.len(),
        "tracks": tracks.tracks.len(),
        "track_points": tracks.tracks.iter().map(|t| t.points.len()).sum::<usize>(),
    });
    (static_points, tracks, summary)
}

/// The `semantics_source` of a scene: which label sources its sweeps had (`lidarseg`, `camera`,
/// both joined by `+`, or `geometry` for none), with `+transfer` when some sweeps had neither
/// and took their neighbours' labels. Every frame's metadata repeats it
/// ([`super::occupancy_frame`]).
pub fn semantics_source(sweeps: usize, lidarseg: usize, camera: usize) -> String {
    let mut parts = Vec::new();
    if lidarseg > 0 {
        parts.push("lidarseg");
    }
    if camera > 0 {
        parts.push("camera");
    }
    if parts.is_empty() {
        return "geometry".into();
    }
    if lidarseg + camera < sweeps {
        parts.push("transfer");
    }
    parts.join("+")
}

#[cfg(test)]
mod tests {
    use super::*;
    use dist4d_types::artifact::{Calibration, Pose};

    fn identity() -> (Calibration, Pose, Boxes3D) {
        (
            Calibration { sensor_to_ego: Se3::default(), intrinsics: None, width: 0, height: 0 },
            Pose { ego_to_world: Se3::default(), timestamp_us: 0 },
            Boxes3D::default(),
        )
    }

    /// A ring of ground points (z = 0) at radius `r` around the origin, 2 degrees apart.
    fn ring(r: f32) -> Vec<[f32; 4]> {
        (0..180).map(|a| (a as f32 * 2.0).to_radians()).map(|t| [r * t.cos(), r * t.sin(), 0.0, 0.0]).collect()
    }

    fn class_near(cloud: &PointCloud, x: f32, y: f32) -> u8 {
        let k = (0..cloud.points.len())
            .min_by(|&a, &b| {
                let d = |q: &[f32; 4]| (q[0] - x).powi(2) + (q[1] - y).powi(2);
                d(&cloud.points[a]).total_cmp(&d(&cloud.points[b]))
            })
            .unwrap();
        cloud.labels[k]
    }

    #[test]
    fn geometry_only_marks_the_ground_driveable_and_the_rest_others_not_manmade() {
        let (calib, pose, boxes) = identity();
        let mut points = ring(10.0);
        points.push([5.0, 5.0, 1.5, 0.0]); // a bush, a wall, a parked car without a box: unknown
        let sweep = PointCloud { points, ..PointCloud::default() };
        let s = [Sweep { points: &sweep, calib: &calib, pose: &pose, boxes: &boxes, camera_labels: None }];
        let (statics, _, summary) = aggregate(&Params::default(), &s);
        assert_eq!(class_near(&statics, 10.0, 0.0), DRIVEABLE_SURFACE);
        assert_eq!(class_near(&statics, 5.0, 5.0), OTHERS);
        assert_eq!(summary["semantics_source"], "geometry");
    }

    #[test]
    fn an_unlabelled_ring_between_labelled_terrain_rings_takes_terrain_not_road() {
        // Keyframe rings of terrain (lidarseg 27) at 10 and 13 m; an unlabelled sweep's ring at
        // 11.5 m, 1.5 m from both: beyond `transfer_distance`, within `transfer_reach`.
        let (calib, pose, boxes) = identity();
        let mut labelled = PointCloud::default();
        for q in ring(10.0).into_iter().chain(ring(13.0)) {
            labelled.points.push(q);
            labelled.labels.push(27);
        }
        let unlabelled = PointCloud { points: ring(11.5), ..PointCloud::default() };
        let s = [
            Sweep { points: &labelled, calib: &calib, pose: &pose, boxes: &boxes, camera_labels: None },
            Sweep { points: &unlabelled, calib: &calib, pose: &pose, boxes: &boxes, camera_labels: None },
        ];
        let (statics, _, summary) = aggregate(&Params::default(), &s);
        assert_eq!(class_near(&statics, 11.5, 0.0), 14, "terrain, not an arc of road");
        assert_eq!(summary["static_labels_by_height"], 0);
        assert_eq!(summary["semantics_source"], "lidarseg+transfer");
        // Within `transfer_distance` only (the old rule), the ring took the height fallback.
        let narrow = Params { transfer_reach: 0.0, ..Params::default() };
        let (statics, _, _) = aggregate(&narrow, &s);
        assert_eq!(class_near(&statics, 11.5, 0.0), DRIVEABLE_SURFACE);
    }

    #[test]
    fn a_pedestrians_feet_labelled_by_a_camera_walk_with_it() {
        let (calib, pose, _) = identity();
        let boxes = Boxes3D {
            timestamp_us: 0,
            boxes: vec![dist4d_types::artifact::Box3D {
                center: [10.0, 0.0, 0.9],
                size: [0.6, 0.6, 1.8],
                rotation: [1.0, 0.0, 0.0, 0.0],
                velocity: [0.0; 3],
                instance: "walker".into(),
                category: "human.pedestrian.adult".into(),
                attributes: Vec::new(),
                num_lidar_pts: 0,
                interpolated: false,
                extrapolated: false,
            }],
        };
        // A foot 0.05 m up (under the raised bottom), the person's chest, and the road beside.
        let sweep = PointCloud {
            points: vec![[10.0, 0.0, 0.05, 0.0], [10.0, 0.0, 1.2, 0.0], [12.0, 0.0, 0.0, 0.0]],
            ..PointCloud::default()
        };
        let camera = [7u8, 7, 11];
        let s = [Sweep { points: &sweep, calib: &calib, pose: &pose, boxes: &boxes, camera_labels: Some(&camera) }];
        let (statics, tracks, _) = aggregate(&Params::default(), &s);
        assert_eq!(tracks.tracks[0].points.len(), 2, "the foot joins the track: {:?}", tracks.tracks[0].points);
        assert_eq!(statics.labels, vec![11], "only the road stays behind");
    }

    #[test]
    fn camera_labels_class_static_points_and_lidarseg_comes_first() {
        let (calib, pose, boxes) = identity();
        let sweep = PointCloud { points: ring(10.0), ..PointCloud::default() };
        let mut camera: Vec<u8> = vec![13; 180]; // sidewalk
        camera[0] = UNLABELLED; // (10, 0): no camera saw it; its neighbour's label
        let s = [Sweep { points: &sweep, calib: &calib, pose: &pose, boxes: &boxes, camera_labels: Some(&camera) }];
        let (statics, _, summary) = aggregate(&Params::default(), &s);
        assert!(statics.labels.iter().all(|&c| c == 13), "{:?}", statics.labels);
        assert_eq!(summary["semantics_source"], "camera");
        assert_eq!(summary["static_labels_camera"], 179);
        // With lidarseg on the same sweep, lidarseg wins.
        let seg = PointCloud { labels: vec![27; 180], ..sweep.clone() };
        let s = [Sweep { points: &seg, calib: &calib, pose: &pose, boxes: &boxes, camera_labels: Some(&camera) }];
        let (statics, _, summary) = aggregate(&Params::default(), &s);
        assert!(statics.labels.iter().all(|&c| c == 14));
        assert_eq!(summary["semantics_source"], "lidarseg");
    }
}
