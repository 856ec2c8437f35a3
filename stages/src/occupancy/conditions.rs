//! `DitConditions`: the conditions DynamicCity's DiT is trained with, per window of `frames`
//! occupancy frames (T = 16), computed as its released code
//! computes them (3DTopia/DynamicCity, `dynamic_city/utils/data_utils.py`):
//!
//! - the trajectory, `get_trajectory`: per frame [x - x0, y - y0, yaw], x and y the world-frame
//!   translations relative to the window's first frame (not rotated into its heading), yaw the
//!   absolute heading atan2(R10, R00) (T x 3);
//! - the command, `get_command`: the yaw change from the first frame wrapped to [-pi, pi); LEFT (2)
//!   if any exceeds `angle_threshold`, else RIGHT (3) if any is below minus it, else FORWARD (1)
//!   if any planar displacement from the first frame exceeds `forward_threshold`, else STATIC (0).
//!   The thresholds are what the released DiT config passes (`conf/dit/dataset/carlasc.yaml`:
//!   `angle_thr_mul: 0.0025`, `forward_thr_mul: 0.03`, used as they are, in radians and metres);
//! - the layout, `convert_voxels_to_layouts`: the vehicle voxels, max over z, max-pooled by
//!   `layout_factor` (T x X/f x Y/f, uint8), as `layout.npz` key `layout`.
//!
//! A task is a window start; which frames start one is the pipeline's `every` on the stage
//! (`every: 16`: disjoint windows; 1: a window at every frame, as the released loader's sliding
//! windows), so the engine plans only those. A window that would run past the scene's end has
//! nothing to make.

use dist4d_runtime::Made;
use crate::stage::Stage;
use anyhow::{ensure, Result};
use dist4d_graph::{ParamChecks, ParamProblem, Validate};
use dist4d_runtime::TaskContext;
use dist4d_types::artifact::{File, OccupancyGrid, Pose};
use dist4d_types::formats::{npy_u8, npz};
use serde::{Deserialize, Serialize};
use serde_json::json;

#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// Frames per window (T); wire the inputs with `Window(.., frame, 0, frames - 1)`.
    pub frames: u32,
    /// The Occ3D classes the layout counts as vehicles.
    pub vehicle_classes: Vec<u8>,
    /// The layout's max-pooling factor.
    pub layout_factor: u32,
    pub angle_threshold: f64,
    pub forward_threshold: f64,
}

impl Default for Params {
    fn default() -> Self {
        Params {
            frames: 16,
            vehicle_classes: vec![3, 4, 5, 9, 10],
            layout_factor: 2,
            angle_threshold: 0.0025,
            forward_threshold: 0.03,
        }
    }
}

impl Validate for Params {
    fn validate(&self) -> Vec<ParamProblem> {
        let mut c = ParamChecks::new();
        c.count("frames", self.frames as u64, 1, 1024)
            .count("layout_factor", self.layout_factor as u64, 1, 64)
            .above("angle_threshold", self.angle_threshold, 0.0, 10.0)
            .above("forward_threshold", self.forward_threshold, 0.0, 1e6);
        c.done()
    }
}

crate::inputs! {
    pub struct Inputs {
        /// the window's occupancy (`Window("occupancy.grid", frame, 0, 15)`)
        grids: Many<OccupancyGrid>,
        /// the window's ego poses (`Window("dataset.lidar_pose", frame, 0, 15)`)
        poses: Many<Pose>,
    }
}

crate::outputs! {
    pub struct Outputs {
        /// JSON: `trajectory` (T x 3), `command` (0-3) and its name
        json: One<File>,
        /// layout.npz: `layout`, uint8 (T, X/f, Y/f)
        layout: One<File>,
    }
}

pub struct DitConditions(Params);

impl Stage for DitConditions {
    const KIND: &'static str = "DitConditions";
    const VERSION: u32 = 1;
    const SUMMARY: &'static str =
        "DynamicCity's DiT conditions per window of occupancy frames: trajectory, command, vehicle layout";
    const GRAINS: &'static [&'static str] = &["frame"];
    type Params = Params;
    type Inputs = Inputs;
    type Outputs = Outputs;

    fn new(params: Params) -> Result<Self> {
        Ok(DitConditions(params))
    }

    fn run(&self, _: &TaskContext, i: Inputs) -> Result<Made<Outputs>> {
        let p = &self.0;
        let t = p.frames as usize;
        let grids = crate::or_nothing!(super::window("grids", &i.grids, t)?);
        let poses = crate::or_nothing!(super::window("poses", &i.poses, t)?);
        let trajectory: Vec<[f64; 3]> = {
            let first = poses[0].ego_to_world.translation;
            poses
                .iter()
                .map(|p| {
                    let r = p.ego_to_world.matrix();
                    let t = p.ego_to_world.translation;
                    [t.x - first.x, t.y - first.y, r.x_axis.y.atan2(r.x_axis.x)]
                })
                .collect()
        };
        let command = command(&trajectory, p.angle_threshold, p.forward_threshold);
        let names = ["STATIC", "FORWARD", "LEFT", "RIGHT"];
        let layout = layout(p, &grids)?;
        Ok(Outputs {
            json: File(serde_json::to_vec_pretty(&json!({
                "frames": t,
                "trajectory": trajectory,
                "command": command,
                "command_name": names[command as usize],
            }))?),
            layout: File(layout),
        }.into())
    }
}

/// DynamicCity's `get_command` (see the module doc).
pub fn command(trajectory: &[[f64; 3]], angle: f64, forward: f64) -> u8 {
    let pi = std::f64::consts::PI;
    let rot: Vec<f64> = trajectory.iter().map(|t| (t[2] - trajectory[0][2] + pi).rem_euclid(2.0 * pi) - pi).collect();
    if rot.iter().any(|&r| r > angle) {
        return 2;
    }
    if rot.iter().any(|&r| r < -angle) {
        return 3;
    }
    let moved = trajectory.iter().any(|t| ((t[0] - trajectory[0][0]).powi(2) + (t[1] - trajectory[0][1]).powi(2)).sqrt() > forward);
    if moved {
        1
    } else {
        0
    }
}

/// The layout NPZ of the module doc.
fn layout(p: &Params, grids: &[&OccupancyGrid]) -> Result<Vec<u8>> {
    let [nx, ny, nz] = grids[0].dims.map(|d| d as usize);
    let f = p.layout_factor as usize;
    ensure!(nx % f == 0 && ny % f == 0, "the grid's {nx} x {ny} is not a multiple of the layout factor {f}");
    let (lx, ly) = (nx / f, ny / f);
    let mut out = vec![0u8; grids.len() * lx * ly];
    for (t, g) in grids.iter().enumerate() {
        ensure!(g.dims == grids[0].dims, "the window's grids differ in size");
        for i in 0..nx {
            for j in 0..ny {
                let c = (i * ny + j) * nz;
                if g.semantics[c..c + nz].iter().any(|s| p.vehicle_classes.contains(s)) {
                    out[(t * lx + i / f) * ly + j / f] = 1;
                }
            }
        }
    }
    Ok(npz(&[("layout", npy_u8(&[grids.len(), lx, ly], &out))]))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn commands_follow_the_released_thresholds() {
        let straight: Vec<[f64; 3]> = (0..16).map(|k| [k as f64 * 0.5, 0.0, 0.3]).collect();
        assert_eq!(command(&straight, 0.0025, 0.03), 1);
        let still: Vec<[f64; 3]> = (0..16).map(|_| [0.0, 0.0, 0.3]).collect();
        assert_eq!(command(&still, 0.0025, 0.03), 0);
        let left: Vec<[f64; 3]> = (0..16).map(|k| [k as f64, 0.0, 0.3 + k as f64 * 0.01]).collect();
        assert_eq!(command(&left, 0.0025, 0.03), 2);
        // Across the +-pi seam: from 3.13 to -3.13 is a left turn of 0.023 rad.
        let seam: Vec<[f64; 3]> = (0..2).map(|k| [k as f64, 0.0, if k == 0 { 3.13 } else { -3.13 }]).collect();
        assert_eq!(command(&seam, 0.0025, 0.03), 2);
        let right: Vec<[f64; 3]> = (0..16).map(|k| [k as f64, 0.0, -(k as f64) * 0.01]).collect();
        assert_eq!(command(&right, 0.0025, 0.03), 3);
    }
}
