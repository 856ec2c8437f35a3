//! `OnMovingObjects`: a depth map kept only on the pixels of objects that move.
//!
//! Moving cars are where LiDAR taken at another time than the image goes wrong (see
//! `FollowTracks`), and they are a few percent of the pixels, so a mean over the image cannot see
//! them: scored on their own (e.g. keyframe images against the 12 Hz images between them), they
//! can. Each pixel of the input depth (e.g. the synthetic ground truth) is lifted to the world
//! through the camera's calibration and pose and kept when it lies inside a box (at the image's
//! time: the dataset's `camera_boxes`) moving faster than `min_speed`, grown by `box_margin` and
//! with its bottom raised by `ground_clearance` (the road under the car is not the car).

use dist4d_runtime::Made;
use crate::camera::CameraView;
use crate::stage::Stage;
use anyhow::{ensure, Result};
use dist4d_graph::{ParamChecks, ParamProblem, Validate};
use dist4d_runtime::TaskContext;
use dist4d_types::artifact::{Boxes3D, Calibration, DepthMap, Pose};
use dist4d_types::geometry::BoxTest;
use serde::{Deserialize, Serialize};

#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// Boxes faster than this (m/s) are moving (the "agents moving faster than 1 m/s").
    pub min_speed: f64,
    /// Boxes grow by this much (m) on each side and on top.
    pub box_margin: f64,
    /// Pixels less than this (m) above a box's bottom are the ground under it, not the object.
    pub ground_clearance: f64,
}

impl Default for Params {
    fn default() -> Self {
        Params { min_speed: 1.0, box_margin: 0.1, ground_clearance: 0.1 }
    }
}

impl Validate for Params {
    fn validate(&self) -> Vec<ParamProblem> {
        ParamChecks::new()
            .within("min_speed", self.min_speed, 0.0, 1000.0)
            .within("box_margin", self.box_margin, 0.0, 100.0)
            .within("ground_clearance", self.ground_clearance, 0.0, 100.0)
            .done()
    }
}

/// `depth` on the pixels whose point lies inside a box of `boxes` faster than `min_speed`, 0
/// elsewhere (an empty depth gives an empty one).
pub fn on_moving_objects(
    params: &Params,
    depth: &DepthMap,
    camera: &Calibration,
    pose: &Pose,
    boxes: &Boxes3D,
) -> Result<DepthMap> {
    if depth.data.is_empty() {
        return Ok(DepthMap::new(0, 0));
    }
    ensure!(
        (depth.width, depth.height) == (camera.width, camera.height),
        "the depth map is {}x{} but the camera calibration says {}x{}",
        depth.width,
        depth.height,
        camera.width,
        camera.height
    );
    // The camera's own frame as the "cloud" frame: unproject gives camera-frame points.
    let view = CameraView::new(camera, pose, camera, pose)?;
    let world_from_cam = pose.ego_to_world.then_from(&camera.sensor_to_ego);
    let cam_from_world = world_from_cam.inverse();
    let moving: Vec<BoxTest> = boxes
        .boxes
        .iter()
        .filter(|b| b.speed() > params.min_speed)
        .map(|b| b.test(&cam_from_world, params.box_margin, params.ground_clearance))
        .collect();
    let w = depth.width as usize;
    let data = depth
        .data
        .iter()
        .enumerate()
        .map(|(i, &z)| {
            if moving.is_empty() || !(z > 0.0 && z.is_finite()) {
                return 0.0;
            }
            let p = view.unproject((i % w) as f64 + 0.5, (i / w) as f64 + 0.5, z as f64);
            if moving.iter().any(|b| b.contains(p)) {
                z
            } else {
                0.0
            }
        })
        .collect();
    Ok(DepthMap { width: depth.width, height: depth.height, data })
}

crate::inputs! {
    pub struct Inputs {
        /// the depth to restrict (e.g. dataset.gt_depth; empty = none)
        depth: One<DepthMap>,
        /// the camera's calibration
        camera_calib: One<Calibration>,
        /// the ego pose at the image's time
        camera_pose: One<Pose>,
        /// the boxes at the image's time (dataset.camera_boxes)
        boxes: One<Boxes3D>,
    }
}

crate::outputs! {
    pub struct Outputs {
        /// the input depth on moving objects, 0 elsewhere (empty if the input is)
        depth: One<DepthMap>,
    }
}

pub struct OnMovingObjects(Params);

impl Stage for OnMovingObjects {
    const KIND: &'static str = "OnMovingObjects";
    const VERSION: u32 = 1;
    const SUMMARY: &'static str =
        "Depth map + boxes at the image's time -> the depth only on objects moving faster than min_speed (a reference for EvalDepth)";
    const GRAINS: &'static [&'static str] = &["camera"];
    type Params = Params;
    type Inputs = Inputs;
    type Outputs = Outputs;
    fn new(params: Params) -> Result<Self> {
        Ok(OnMovingObjects(params))
    }
    fn run(&self, _: &TaskContext, i: Inputs) -> Result<Made<Outputs>> {
        Ok(Outputs { depth: on_moving_objects(&self.0, &i.depth, &i.camera_calib, &i.camera_pose, &i.boxes)? }.into())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use dist4d_types::artifact::Box3D;
    use dist4d_types::geometry::Se3;
    use glam::DVec3;

    #[test]
    fn only_the_pixels_of_the_moving_car_are_kept() {
        // A 40x20 camera at the origin looking along +z (camera = ego = world); a moving car on
        // the left half at 10 m, a parked one on the right half, the road below.
        let camera = Calibration {
            sensor_to_ego: Se3::from_wxyz_t([1.0, 0.0, 0.0, 0.0], [0.0; 3]),
            intrinsics: Some([[20.0, 0.0, 20.0], [0.0, 20.0, 10.0], [0.0, 0.0, 1.0]]),
            width: 40,
            height: 20,
        };
        let pose = Pose { ego_to_world: Se3::from_yaw(0.0, DVec3::ZERO), timestamp_us: 0 };
        let car = |x: f64, speed: f64| Box3D {
            // Upright in the world is -y here (the camera's y points down): the box's z axis is
            // turned onto -y by a quarter turn about x.
            center: [x, 0.0, 11.0],
            size: [4.0, 8.0, 3.0],
            rotation: [std::f64::consts::FRAC_1_SQRT_2, std::f64::consts::FRAC_1_SQRT_2, 0.0, 0.0],
            velocity: [speed, 0.0, 0.0],
            instance: format!("{x}"),
            category: "vehicle.car".into(),
            attributes: vec![],
            num_lidar_pts: 0,
            interpolated: false,
            extrapolated: false,
        };
        let boxes = Boxes3D { timestamp_us: 0, boxes: vec![car(-4.5, 8.0), car(4.5, 0.0)] };
        let depth = DepthMap { width: 40, height: 20, data: vec![10.0; 800] };
        let out = on_moving_objects(&Params::default(), &depth, &camera, &pose, &boxes).unwrap();
        let kept = |u: usize, v: usize| out.data[v * 40 + u] > 0.0;
        assert!(kept(8, 10) && kept(15, 10), "the moving car");
        assert!(!kept(30, 10), "the parked car");
        assert!(!kept(25, 10), "between them");
        assert!(on_moving_objects(&Params::default(), &DepthMap::new(0, 0), &camera, &pose, &boxes).unwrap().data.is_empty());
    }
}
