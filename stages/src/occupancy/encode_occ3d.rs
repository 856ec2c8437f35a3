//! `EncodeOcc3d`: a frame's occupancy as Occ3D-nuScenes' `labels.npz`, what its loader reads
//! (CVPR2023-3D-Occupancy-Prediction, `projects/mmdet3d_plugin/datasets/pipelines/loading.py`:
//! `np.load(path)` and the keys `semantics`, `mask_lidar`, `mask_camera`): three uint8 arrays of
//! shape (X, Y, Z) = (200, 200, 16) by default, C order, compressed as `np.savez_compressed` does.

use dist4d_runtime::Made;
use crate::stage::Stage;
use anyhow::{ensure, Result};
use dist4d_graph::Validate;
use dist4d_runtime::TaskContext;
use dist4d_types::artifact::{File, OccupancyGrid};
use dist4d_types::formats::{npy_u8, npz};
use serde::{Deserialize, Serialize};

#[derive(Serialize, Deserialize, Clone, Debug, Default, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Params {}

impl Validate for Params {}

crate::inputs! {
    pub struct Inputs {
        /// the frame's occupancy
        grid: One<OccupancyGrid>,
    }
}

crate::outputs! {
    pub struct Outputs {
        /// labels.npz: `semantics`, `mask_lidar`, `mask_camera`, uint8 (X, Y, Z)
        npz: One<File>,
    }
}

pub struct EncodeOcc3d;

impl Stage for EncodeOcc3d {
    const KIND: &'static str = "EncodeOcc3d";
    const VERSION: u32 = 1;
    const SUMMARY: &'static str = "OccupancyGrid -> Occ3D labels.npz (semantics, mask_lidar, mask_camera; uint8 X x Y x Z)";
    const GRAINS: &'static [&'static str] = &["frame"];
    type Params = Params;
    type Inputs = Inputs;
    type Outputs = Outputs;
    fn new(_: Params) -> Result<Self> {
        Ok(EncodeOcc3d)
    }
    fn run(&self, _: &TaskContext, i: Inputs) -> Result<Made<Outputs>> {
        let g = &i.grid;
        let n = g.voxels();
        ensure!(
            g.semantics.len() == n && g.mask_lidar.len() == n && g.mask_camera.len() == n,
            "the grid's volumes do not match its size {:?}",
            g.dims
        );
        let shape = g.dims.map(|d| d as usize);
        Ok(Outputs {
            npz: File(npz(&[
                ("semantics", npy_u8(&shape, &g.semantics)),
                ("mask_lidar", npy_u8(&shape, &g.mask_lidar)),
                ("mask_camera", npy_u8(&shape, &g.mask_camera)),
            ])),
        }.into())
    }
}
