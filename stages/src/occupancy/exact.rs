//! `ExactOccupancy`: a synthetic dataset's exact semantic occupancy of a frame, the reference
//! the LiDAR-built occupancy is scored against: every voxel of the same grid that shares volume
//! with one of the world's primitives or reaches below the ground
//! ([`dist4d_synth::Snapshot::occupancy`]: exact overlap tests, the class by 3 x 3 x 3 samples),
//! the classes mapped to Occ3D's as the synthetic lidarseg files are, and the visibility masks cast
//! exactly as [`super::occupancy_frame`] casts them (the frame's sweep for `mask_lidar`, camera
//! rays stopping at the first occupied voxel for `mask_camera`). On a dataset that is not
//! synthetic it has nothing to make.

use super::classes::{of_lidarseg, DROP, FREE};
use super::grid::GridParams;
use super::occupancy_frame::{with_masks, Params as FrameParams};
use crate::stage::Stage;
use anyhow::{Context, Result};
use dist4d_graph::{ParamChecks, ParamProblem, Validate};
use dist4d_runtime::{Made, TaskContext};
use dist4d_types::artifact::{Calibration, File, OccupancyGrid, PointCloud, Pose};
use serde::{Deserialize, Serialize};

#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// The grid and the masks' rays: set them as `Occupancy`'s.
    pub grid: GridParams,
    pub camera_ray_step: u32,
    pub camera_max_distance: f64,
    /// Samples per voxel along each axis (they choose the class where primitives meet).
    pub samples: u32,
}

impl Default for Params {
    fn default() -> Self {
        let f = FrameParams::default();
        Params { grid: f.grid, camera_ray_step: f.camera_ray_step, camera_max_distance: f.camera_max_distance, samples: 3 }
    }
}

impl Params {
    fn frame(&self) -> FrameParams {
        FrameParams {
            grid: self.grid.clone(),
            camera_ray_step: self.camera_ray_step,
            camera_max_distance: self.camera_max_distance,
            ..FrameParams::default()
        }
    }
}

impl Validate for Params {
    fn validate(&self) -> Vec<ParamProblem> {
        let mut problems = self.frame().validate();
        problems.extend(ParamChecks::new().count("samples", self.samples as u64, 1, 16).done());
        problems
    }
}

crate::inputs! {
    pub struct Inputs {
        /// the synthetic world (`dataset.synth_world`; empty for other datasets)
        world: One<File>,
        /// the frame's sweep, for the LiDAR rays
        sweep: One<PointCloud>,
        /// its LiDAR calibration
        lidar_calib: One<Calibration>,
        /// the ego pose at the sweep: the grid's frame
        lidar_pose: One<Pose>,
        /// every camera of the frame (`Gather("dataset.camera_calib", camera)`)
        camera_calibs: Many<Calibration>,
        /// their ego poses
        camera_poses: Many<Pose>,
    }
}

crate::outputs! {
    pub struct Outputs {
        /// the exact semantics with the masks
        grid: One<OccupancyGrid>,
    }
}

pub struct ExactOccupancy(Params);

impl Stage for ExactOccupancy {
    const KIND: &'static str = "ExactOccupancy";
    // 2: a voxel is occupied when it shares any volume with a primitive (exact tests), not only
    // when one of its 27 samples is inside one: slivers up to 6.7 cm thick were left free.
    const VERSION: u32 = 2;
    const SUMMARY: &'static str = "a synthetic world's exact semantic occupancy of a frame (the occupancy reference)";
    const GRAINS: &'static [&'static str] = &["frame"];
    const ALIGNED_INPUTS: &'static [&'static [&'static str]] = &[&["camera_calibs", "camera_poses"]];
    type Params = Params;
    type Inputs = Inputs;
    type Outputs = Outputs;

    fn new(params: Params) -> Result<Self> {
        Ok(ExactOccupancy(params))
    }

    fn run(&self, _: &TaskContext, i: Inputs) -> Result<Made<Outputs>> {
        if i.world.0.is_empty() {
            return Ok(Made::Nothing("not a synthetic dataset: no exact occupancy".into()));
        }
        let r = dist4d_synth::Renderer::shared(&i.world.0)?;
        let head: serde_json::Value = serde_json::from_slice(&i.world.0)?;
        let name = head["scene"].as_str().unwrap_or_default();
        let scene = r.scene_index(name).with_context(|| format!("the synthetic world has no scene `{name}`"))?;
        let g = self.0.grid.grid();
        let ids = r.occupancy_at_timestamp(
            scene,
            i.lidar_pose.timestamp_us,
            &i.lidar_pose.ego_to_world,
            g.min,
            g.voxel,
            g.dims,
            self.0.samples as usize,
        )?;
        let semantics = ids
            .iter()
            .map(|&id| match id {
                0 => FREE,
                c => match of_lidarseg(dist4d_synth::lidarseg_index(c)) {
                    DROP => FREE,
                    class => class,
                },
            })
            .collect();
        let n = g.len();
        let grid = OccupancyGrid { dims: g.dims.map(|d| d as u32), semantics, mask_lidar: vec![0; n], mask_camera: vec![0; n] };
        let ego_from_world = i.lidar_pose.ego_to_world.inverse();
        let cameras: Vec<(&Calibration, &Pose)> =
            i.camera_calibs.iter().zip(&i.camera_poses).map(|((_, c), (_, p))| (c, p)).collect();
        Ok(Outputs { grid: with_masks(&self.0.frame(), grid, &i.sweep, &i.lidar_calib, &ego_from_world, &cameras)? }.into())
    }
}
