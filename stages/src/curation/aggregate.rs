//! `AggregateLidar`: the LiDAR sweeps of a window of frames moved into the target frame.
//!
//! DiST-4D (Sec. 3.2): "we aggregate the LiDAR of neighbouring frames, remove dynamic objects and
//! the ego vehicle". Each sweep goes sensor -> ego -> world through its own calibration and ego
//! pose, then world -> the target frame's LiDAR. In every sweep but the target's, points inside a
//! moving box (moving attribute, or speed above `moving_speed`) are removed: a car that moved
//! between sweeps would otherwise leave a smeared trail in the target frame. Boxes are those of
//! the sweep's own frame, i.e. at its timestamp (the dataset readers interpolate boxes to sweep
//! times). The box is grown by `box_margin` sideways and on top, and its bottom raised by
//! `ground_clearance` so the road under a car stays. Points inside the ego vehicle's box and
//! points nearer than `min_distance` to their LiDAR are removed from every sweep (including
//! no-return points, which sit at the sensor origin).
//!
//! Hold-out evaluation: `holdout` > 0 takes a seeded fraction of the target sweep's (kept) points
//! out of the aggregate and returns them separately, so a curated depth can be scored on LiDAR
//! points it never saw (works on real data).

use dist4d_runtime::Made;
use crate::stage::Stage;
use dist4d_runtime::TaskContext;
use anyhow::{anyhow, ensure, Result};
use dist4d_graph::{ParamChecks, ParamProblem, Validate};
use dist4d_types::artifact::{Boxes3D, Calibration, PointCloud, Pose};
use dist4d_types::geometry::BoxTest;
use dist4d_types::rng::mix;
use glam::DVec3;
use serde::{Deserialize, Serialize};

#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// A box is dynamic when its attributes say moving or its speed exceeds this (m/s).
    pub moving_speed: f64,
    /// Dynamic boxes grow by this much (m) on each side and on top.
    pub box_margin: f64,
    /// Points less than this (m) above a dynamic box's bottom are kept: the ground under it.
    pub ground_clearance: f64,
    /// Points nearer than this (m) to their LiDAR are removed.
    pub min_distance: f64,
    /// The ego vehicle's box in the ego frame (x forward, y left, z up; metres), min corner.
    pub ego_box_min: [f64; 3],
    /// ... and max corner. Default: a nuScenes Renault Zoe with a little room.
    pub ego_box_max: [f64; 3],
    /// Fraction of the target sweep's points held out for evaluation (0 = none). Which points is
    /// drawn from the task's seed (its item and params), mixed with the point index.
    pub holdout: f64,
}

impl Default for Params {
    fn default() -> Self {
        Params {
            moving_speed: 0.5,
            box_margin: 0.2,
            ground_clearance: 0.2,
            min_distance: 1.0,
            ego_box_min: [-1.0, -1.0, -1.0],
            ego_box_max: [3.4, 1.0, 2.0],
            holdout: 0.0,
        }
    }
}

impl Validate for Params {
    fn validate(&self) -> Vec<ParamProblem> {
        let mut c = ParamChecks::new();
        c.within("moving_speed", self.moving_speed, 0.0, 1000.0)
            .within("box_margin", self.box_margin, 0.0, 100.0)
            .within("ground_clearance", self.ground_clearance, 0.0, 100.0)
            .within("min_distance", self.min_distance, 0.0, 1000.0)
            .within("holdout", self.holdout, 0.0, 1.0);
        for (field, corner) in [("ego_box_min", self.ego_box_min), ("ego_box_max", self.ego_box_max)] {
            for (axis, v) in corner.into_iter().enumerate() {
                if !(v.is_finite() && v.abs() <= 100.0) {
                    c.push(ParamProblem {
                        field,
                        index: Some(axis),
                        other: None,
                        message: format!("must hold numbers in [-100, 100] (metres), found {v}"),
                    });
                }
            }
        }
        for axis in 0..3 {
            let (lo, hi) = (self.ego_box_min[axis], self.ego_box_max[axis]);
            if lo > hi {
                c.push(ParamProblem {
                    field: "ego_box_min",
                    index: Some(axis),
                    other: Some("ego_box_max"),
                    message: format!("must not exceed `ego_box_max` on axis {axis} ({hi}), found {lo}"),
                });
            }
        }
        c.done()
    }
}

/// One sweep of the window: its points, LiDAR mounting, ego pose, the boxes of its frame, and its
/// position relative to the target (0 = target).
pub struct Sweep<'a> {
    pub position: i64,
    pub points: &'a PointCloud,
    pub calib: &'a Calibration,
    pub pose: &'a Pose,
    pub boxes: &'a Boxes3D,
}

/// The aggregate (in the target LiDAR frame) and the held-out target points (same frame), drawn
/// with `seed`.
pub fn aggregate(params: &Params, seed: u64, sweeps: &[Sweep]) -> Result<(PointCloud, PointCloud)> {
    let target = sweeps
        .iter()
        .find(|s| s.position == 0)
        .ok_or_else(|| anyhow!("the window has no sweep at position 0 (the target frame)"))?;
    ensure!((0.0..=1.0).contains(&params.holdout), "holdout must be in [0, 1], not {}", params.holdout);
    let world_from_target = target.pose.ego_to_world.then_from(&target.calib.sensor_to_ego);
    let target_from_world = world_from_target.inverse();
    let keep_labels = sweeps.iter().all(|s| s.points.labels.len() == s.points.points.len());
    let (mut out, mut held) = (PointCloud::default(), PointCloud::default());
    let threshold = (params.holdout * u64::MAX as f64) as u64;
    let (emin, emax) = (DVec3::from_array(params.ego_box_min), DVec3::from_array(params.ego_box_max));
    let min_d2 = params.min_distance * params.min_distance;
    for s in sweeps {
        let world_from_sweep = s.pose.ego_to_world.then_from(&s.calib.sensor_to_ego);
        let to_target = target_from_world.then_from(&world_from_sweep);
        let sweep_from_world = world_from_sweep.inverse();
        let boxes: Vec<BoxTest> = if s.position == 0 {
            Vec::new()
        } else {
            s.boxes
                .boxes
                .iter()
                .filter(|b| b.is_moving(params.moving_speed))
                .map(|b| b.test(&sweep_from_world, params.box_margin, params.ground_clearance))
                .collect()
        };
        let sensor_to_ego = &s.calib.sensor_to_ego;
        let ego_rot = sensor_to_ego.matrix();
        for (i, p) in s.points.points.iter().enumerate() {
            let v = DVec3::new(p[0] as f64, p[1] as f64, p[2] as f64);
            if v.length_squared() < min_d2 {
                continue;
            }
            let e = ego_rot * v + sensor_to_ego.translation;
            if e.cmpge(emin).all() && e.cmple(emax).all() {
                continue;
            }
            if boxes.iter().any(|b| b.contains(v)) {
                continue;
            }
            let t = to_target.apply(v);
            let row = [t.x as f32, t.y as f32, t.z as f32, p[3]];
            let dest = if s.position == 0
                && threshold > 0
                && mix(seed ^ mix(i as u64)) < threshold
            {
                &mut held
            } else {
                &mut out
            };
            dest.points.push(row);
            if keep_labels {
                dest.labels.push(s.points.labels[i]);
            }
        }
    }
    Ok((out, held))
}

crate::inputs! {
    pub struct Inputs {
        /// the window's sweeps: Window("dataset.lidar", frame, -1, 1)
        sweeps: Many<PointCloud>,
        /// their LiDAR mountings (same Window)
        calibs: Many<Calibration>,
        /// their ego poses (same Window)
        poses: Many<Pose>,
        /// their frames' boxes (same Window)
        boxes: Many<Boxes3D>,
    }
}

crate::outputs! {
    pub struct Outputs {
        /// the aggregate, in the target frame's LiDAR frame
        points: One<PointCloud>,
        /// held-out target points (empty unless holdout > 0)
        holdout: One<PointCloud>,
    }
}

pub struct AggregateLidar(Params);

impl Stage for AggregateLidar {
    const KIND: &'static str = "AggregateLidar";
    // 2: the hold-out draw comes from the task's seed, not a param of its own.
    const VERSION: u32 = 2;
    const SUMMARY: &'static str =
        "LiDAR sweeps of a window of frames -> one static-scene cloud in the target frame's LiDAR frame";
    const GRAINS: &'static [&'static str] = &["frame"];
    const ALIGNED_INPUTS: &'static [&'static [&'static str]] = &[&["sweeps", "calibs", "poses", "boxes"]];
    const SEEDED: bool = true;
    type Params = Params;
    type Inputs = Inputs;
    type Outputs = Outputs;
    fn new(params: Params) -> Result<Self> {
        Ok(AggregateLidar(params))
    }
    fn run(&self, ctx: &TaskContext, i: Inputs) -> Result<Made<Outputs>> {
        let (points, calibs, poses, boxes) = (&i.sweeps, &i.calibs, &i.poses, &i.boxes);
        ensure!(
            calibs.len() == points.len() && poses.len() == points.len() && boxes.len() == points.len(),
            "the sweeps, calibrations, poses and boxes windows differ in length ({}, {}, {}, {}): wire them with the same Window",
            points.len(),
            calibs.len(),
            poses.len(),
            boxes.len()
        );
        let mut sweeps = Vec::with_capacity(points.len());
        for i in 0..points.len() {
            let position = points[i].0;
            ensure!(
                calibs[i].0 == position && poses[i].0 == position && boxes[i].0 == position,
                "the windows of sweeps, calibrations, poses and boxes are not aligned"
            );
            sweeps.push(Sweep {
                position,
                points: &points[i].1,
                calib: &calibs[i].1,
                pose: &poses[i].1,
                boxes: &boxes[i].1,
            });
        }
        let (points, holdout) = aggregate(&self.0, ctx.seed, &sweeps)?;
        Ok(Outputs { points, holdout }.into())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use dist4d_types::artifact::Box3D;
    use dist4d_types::geometry::Se3;

    fn lidar() -> Calibration {
        Calibration {
            sensor_to_ego: Se3::from_yaw(0.0, DVec3::new(0.0, 0.0, 2.0)),
            intrinsics: None,
            width: 0,
            height: 0,
        }
    }
    fn pose(x: f64, t: i64) -> Pose {
        Pose { ego_to_world: Se3::from_yaw(0.0, DVec3::new(x, 0.0, 0.0)), timestamp_us: t }
    }
    fn car(x: f64, speed: f64) -> Box3D {
        Box3D {
            center: [x, 5.0, 1.0],
            size: [2.0, 4.0, 2.0],
            rotation: [1.0, 0.0, 0.0, 0.0],
            velocity: [speed, 0.0, 0.0],
            instance: "car".into(),
            category: "vehicle.car".into(),
            attributes: vec![],
            num_lidar_pts: 0,
            interpolated: false,
            extrapolated: false,
        }
    }

    #[test]
    fn moves_sweeps_into_the_target_frame_and_drops_dynamic_ego_and_close_points() {
        let calib = lidar();
        // World point (20, 0, 0) seen from ego at x = 0 and x = 10: LiDAR at z = 2 above ego.
        let far_prev = PointCloud { points: vec![[20.0, 0.0, -2.0, 1.0]], labels: vec![], rgb: Vec::new() };
        let prev = PointCloud {
            points: vec![
                [20.0, 0.0, -2.0, 1.0], // static: kept, lands at x = 10 in the target frame
                [10.0, 5.0, -1.0, 2.0], // inside the moving car at world x = 10: dropped
                [10.0, 5.0, -1.9, 3.0], // under the car's bottom + clearance: ground, kept
                [0.5, 0.0, 0.0, 4.0],   // too close
                [2.5, 0.5, -1.5, 5.0],  // inside the ego box (ego x = 2.5, z = 0.5)
            ],
            labels: vec![],
            rgb: Vec::new(),
        };
        let target = PointCloud {
            points: vec![[0.0, 5.0, -1.0, 6.0]], // the car, now at world x = 10 + ... but in the target: kept
            labels: vec![],
            rgb: Vec::new(),
        };
        let moving = Boxes3D { timestamp_us: 0, boxes: vec![car(10.0, 5.0)] };
        let parked = Boxes3D { timestamp_us: 0, boxes: vec![car(20.0, 0.0)] };
        let (p0, p1) = (pose(0.0, 0), pose(10.0, 500_000));
        let sweeps = [
            Sweep { position: -1, points: &prev, calib: &calib, pose: &p0, boxes: &moving },
            Sweep { position: 0, points: &target, calib: &calib, pose: &p1, boxes: &moving },
            Sweep { position: 1, points: &far_prev, calib: &calib, pose: &p0, boxes: &parked },
        ];
        let (agg, held) = aggregate(&Params::default(), 0, &sweeps).unwrap();
        assert!(held.points.is_empty());
        let got: Vec<[f32; 4]> = agg.points.clone();
        assert_eq!(
            got,
            vec![[10.0, 0.0, -2.0, 1.0], [0.0, 5.0, -1.9, 3.0], [0.0, 5.0, -1.0, 6.0], [10.0, 0.0, -2.0, 1.0]]
        );
    }

    #[test]
    fn holds_out_a_seeded_fraction_of_the_target_sweep_only() {
        let calib = lidar();
        let pts = PointCloud {
            points: (0..10_000).map(|i| [5.0 + i as f32 * 1e-3, 3.0, 0.0, 0.0]).collect(),
            labels: vec![],
            rgb: Vec::new(),
        };
        let p = pose(0.0, 123);
        let none = Boxes3D::default();
        let sweeps = [
            Sweep { position: 0, points: &pts, calib: &calib, pose: &p, boxes: &none },
            Sweep { position: 1, points: &pts, calib: &calib, pose: &p, boxes: &none },
        ];
        let params = Params { holdout: 0.2, ..Params::default() };
        let (agg, held) = aggregate(&params, 0, &sweeps).unwrap();
        let frac = held.points.len() as f64 / 10_000.0;
        assert!((frac - 0.2).abs() < 0.02, "{frac}");
        assert_eq!(agg.points.len() + held.points.len(), 20_000);
        let (_, again) = aggregate(&params, 0, &sweeps).unwrap();
        assert_eq!(again, held);
        let (_, other) = aggregate(&params, 7, &sweeps).unwrap();
        assert_ne!(other, held);
    }

    #[test]
    fn a_window_without_its_target_is_an_error() {
        let calib = lidar();
        let p = pose(0.0, 0);
        let none = Boxes3D::default();
        let pts = PointCloud::default();
        let sweeps = [Sweep { position: 1, points: &pts, calib: &calib, pose: &p, boxes: &none }];
        assert!(aggregate(&Params::default(), 0, &sweeps).unwrap_err().to_string().contains("position 0"));
    }
}
