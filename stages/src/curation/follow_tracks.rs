//! `FollowTracks`: the points of moving objects carried along their tracks to one image's time.
//!
//! A point cloud in a LiDAR frame holds the scene as the LiDAR saw it: the ego poses carry its
//! static part to any camera's time (LiDAR -> ego at the LiDAR time -> world -> ego at the camera
//! time -> camera), but a car moving at 10 m/s has moved 0.5 m in the ~50 ms between the LiDAR
//! passing it and the camera that sees it firing (nuScenes fires each camera as the LiDAR sweeps
//! past it; at 12 Hz a round's LiDAR sweep is up to ~40 ms from its images). Per camera, each
//! point inside a box moving faster than `moving_speed` at the cloud's time (`boxes`: the cloud's
//! frame's boxes) is moved with the box to the same instance's box at the image's time
//! (`image_boxes`: the dataset's `camera_boxes`), and given back in the cloud's frame, so that
//! every later step (hidden point removal, the prompt) puts the car's depth edges on the car in
//! the image. A moving box with no box of its instance at the image's time leaves its points
//! where they were measured. Boxes grow by `box_margin` sideways and on top, and their bottom is
//! raised by `ground_clearance` so that the road under a car stays (as in `AggregateLidar`).

use dist4d_runtime::Made;
use crate::stage::Stage;
use anyhow::Result;
use dist4d_graph::{ParamChecks, ParamProblem, Validate};
use dist4d_runtime::TaskContext;
use dist4d_types::artifact::{Boxes3D, Calibration, PointCloud, Pose};
use dist4d_types::geometry::{BoxTest, Se3};
use glam::DVec3;
use serde::{Deserialize, Serialize};

#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// A box is moving when its speed exceeds this (m/s); its attributes do not count (a box that
    /// does not move between the two times has no motion to follow, and a large value turns the
    /// stage off: the ablation of docs/BENCHMARKS.md).
    pub moving_speed: f64,
    /// Moving boxes grow by this much (m) on each side and on top.
    pub box_margin: f64,
    /// Points less than this (m) above a moving box's bottom stay: the ground under it.
    pub ground_clearance: f64,
}

impl Default for Params {
    fn default() -> Self {
        Params { moving_speed: 0.5, box_margin: 0.2, ground_clearance: 0.2 }
    }
}

impl Validate for Params {
    fn validate(&self) -> Vec<ParamProblem> {
        ParamChecks::new()
            .within("moving_speed", self.moving_speed, 0.0, 1000.0)
            .within("box_margin", self.box_margin, 0.0, 100.0)
            .within("ground_clearance", self.ground_clearance, 0.0, 100.0)
            .done()
    }
}

/// `points` (in the frame of `cloud` at `cloud_pose`) with the points of moving boxes moved from
/// `boxes` (at the cloud's time) to `image_boxes` (at the image's time); everything else as is.
pub fn follow_tracks(
    params: &Params,
    points: &PointCloud,
    cloud: &Calibration,
    cloud_pose: &Pose,
    boxes: &Boxes3D,
    image_boxes: &Boxes3D,
) -> PointCloud {
    let world_from_cloud = cloud_pose.ego_to_world.then_from(&cloud.sensor_to_ego);
    let cloud_from_world = world_from_cloud.inverse();
    // Per moving box with a later self: its inside test and its motion, both in the cloud frame.
    let motions: Vec<(BoxTest, Se3)> = boxes
        .boxes
        .iter()
        .filter(|b| b.speed() > params.moving_speed)
        .filter_map(|b| {
            let later = image_boxes.boxes.iter().find(|c| c.instance == b.instance)?;
            let (from, to) = (Se3::from_wxyz_t(b.rotation, b.center), Se3::from_wxyz_t(later.rotation, later.center));
            let motion = cloud_from_world.then_from(&to).then_from(&from.inverse()).then_from(&world_from_cloud);
            Some((b.test(&cloud_from_world, params.box_margin, params.ground_clearance), motion))
        })
        .collect();
    if motions.is_empty() {
        return points.clone();
    }
    let moved = points
        .points
        .iter()
        .map(|p| {
            let v = DVec3::new(p[0] as f64, p[1] as f64, p[2] as f64);
            match motions.iter().find(|(inside, _)| inside.contains(v)) {
                Some((_, motion)) => {
                    let m = motion.apply(v);
                    [m.x as f32, m.y as f32, m.z as f32, p[3]]
                }
                None => *p,
            }
        })
        .collect();
    PointCloud { points: moved, labels: points.labels.clone(), rgb: points.rgb.clone() }
}

crate::inputs! {
    pub struct Inputs {
        /// the cloud, in its sensor frame (e.g. the aggregate, or the fused cloud of one camera)
        points: One<PointCloud>,
        /// the cloud's sensor mounting
        cloud_calib: One<Calibration>,
        /// the ego pose at the cloud's time
        cloud_pose: One<Pose>,
        /// the boxes at the cloud's time (dataset.boxes of its frame)
        boxes: One<Boxes3D>,
        /// the boxes at the image's time (dataset.camera_boxes)
        image_boxes: One<Boxes3D>,
    }
}

crate::outputs! {
    pub struct Outputs {
        /// the same cloud, moving objects where they are at the image's time
        points: One<PointCloud>,
    }
}

pub struct FollowTracks(Params);

impl Stage for FollowTracks {
    const KIND: &'static str = "FollowTracks";
    const VERSION: u32 = 1;
    const SUMMARY: &'static str =
        "Point cloud + boxes at its time and at an image's time -> the points of moving objects moved along their tracks to the image's time";
    const GRAINS: &'static [&'static str] = &["camera"];
    type Params = Params;
    type Inputs = Inputs;
    type Outputs = Outputs;
    fn new(params: Params) -> Result<Self> {
        Ok(FollowTracks(params))
    }
    fn run(&self, _: &TaskContext, i: Inputs) -> Result<Made<Outputs>> {
        Ok(Outputs { points: follow_tracks(&self.0, &i.points, &i.cloud_calib, &i.cloud_pose, &i.boxes, &i.image_boxes) }.into())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use dist4d_types::artifact::Box3D;

    fn car(x: f64, speed: f64, instance: &str) -> Box3D {
        Box3D {
            center: [x, 10.0, 0.75],
            size: [2.0, 4.0, 1.5],
            rotation: [1.0, 0.0, 0.0, 0.0],
            velocity: [speed, 0.0, 0.0],
            instance: instance.into(),
            category: "vehicle.car".into(),
            attributes: vec![],
            num_lidar_pts: 0,
            interpolated: false,
            extrapolated: false,
        }
    }

    #[test]
    fn points_of_a_moving_car_follow_it_to_the_image_time_and_nothing_else_moves() {
        // The LiDAR 1.8 m up on an ego at (100, 0) facing +y (yaw 90 degrees): the cloud frame is
        // not the world's, so the motion must go through both poses.
        let cloud = Calibration {
            sensor_to_ego: Se3::from_wxyz_t([1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.8]),
            intrinsics: None,
            width: 0,
            height: 0,
        };
        let pose = Pose { ego_to_world: Se3::from_yaw(std::f64::consts::FRAC_PI_2, DVec3::new(100.0, 0.0, 0.0)), timestamp_us: 0 };
        let world_from_cloud = pose.ego_to_world.then_from(&cloud.sensor_to_ego);
        let in_cloud = |w: [f64; 3]| {
            let p = world_from_cloud.inverse().apply(DVec3::from_array(w));
            [p.x as f32, p.y as f32, p.z as f32, 7.0]
        };
        // A car crossing at 10 m/s (0.5 m by the image), a parked one, the road under the moving
        // one, a wall.
        let at_cloud = Boxes3D { timestamp_us: 0, boxes: vec![car(100.0, 10.0, "a"), car(105.0, 0.0, "p")] };
        let at_image = Boxes3D { timestamp_us: 50_000, boxes: vec![car(100.5, 10.0, "a"), car(105.0, 0.0, "p")] };
        let world = [[100.9, 10.0, 1.0], [105.0, 10.0, 1.0], [100.0, 10.0, 0.05], [100.0, 30.0, 2.0]];
        let points = PointCloud { points: world.iter().map(|&w| in_cloud(w)).collect(), labels: vec![1, 2, 3, 4], rgb: Vec::new() };
        let out = follow_tracks(&Params::default(), &points, &cloud, &pose, &at_cloud, &at_image);
        let back = |p: [f32; 4]| world_from_cloud.apply(DVec3::new(p[0] as f64, p[1] as f64, p[2] as f64));
        assert!((back(out.points[0]) - DVec3::new(101.4, 10.0, 1.0)).length() < 1e-4, "{:?}", back(out.points[0]));
        assert_eq!(out.points[0][3], 7.0, "intensity kept");
        assert_eq!(out.points[1..], points.points[1..], "the parked car, the road and the wall stay");
        assert_eq!(out.labels, points.labels);
        // Without a box of its instance at the image's time, the car's points stay.
        let gone = Boxes3D { timestamp_us: 50_000, boxes: vec![] };
        assert_eq!(follow_tracks(&Params::default(), &points, &cloud, &pose, &at_cloud, &gone), points);
    }
}
