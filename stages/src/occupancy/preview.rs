//! `OccupancyPreview`: a frame's occupancy to look at. A bird's-eye view (forward up, left to
//! the left, `scale` pixels per voxel): each column in the colour of its highest occupied voxel
//! ([`super::classes::PALETTE`]); a free column the cameras saw mid grey, one nobody saw dark
//! grey. And the occupied voxels as a coloured point cloud (one point at each voxel's centre, in
//! the ego frame, with its class as the label), for `EncodePly`: Open3D and CloudCompare show it.

use dist4d_runtime::Made;
use super::classes::{FREE, PALETTE};
use super::grid::GridParams;
use crate::stage::Stage;
use anyhow::{ensure, Result};
use dist4d_graph::{ParamChecks, ParamProblem, Validate};
use dist4d_runtime::TaskContext;
use dist4d_types::artifact::{Image, OccupancyGrid, PointCloud};
use serde::{Deserialize, Serialize};

#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// The grid the occupancy was made on (set it as `Occupancy`'s): places the voxels.
    pub grid: GridParams,
    /// Pixels per voxel of the bird's-eye view.
    pub scale: u32,
}

impl Default for Params {
    fn default() -> Self {
        Params { grid: GridParams::default(), scale: 2 }
    }
}

impl Validate for Params {
    fn validate(&self) -> Vec<ParamProblem> {
        let mut c = ParamChecks::new();
        self.grid.check(&mut c);
        c.count("scale", self.scale as u64, 1, 16);
        c.done()
    }
}

crate::inputs! {
    pub struct Inputs {
        /// the frame's occupancy
        grid: One<OccupancyGrid>,
    }
}

crate::outputs! {
    pub struct Outputs {
        /// the bird's-eye view
        bev: One<Image>,
        /// the occupied voxels' centres, coloured by class (ego frame)
        voxels: One<PointCloud>,
    }
}

pub struct OccupancyPreview(Params);

const SEEN_FREE: [u8; 3] = [110, 110, 110];

impl Stage for OccupancyPreview {
    const KIND: &'static str = "OccupancyPreview";
    const VERSION: u32 = 1;
    const SUMMARY: &'static str = "an occupancy frame to look at: a bird's-eye view by class, and its voxels as a coloured cloud";
    const GRAINS: &'static [&'static str] = &["frame"];
    type Params = Params;
    type Inputs = Inputs;
    type Outputs = Outputs;
    fn new(params: Params) -> Result<Self> {
        Ok(OccupancyPreview(params))
    }
    fn run(&self, _: &TaskContext, i: Inputs) -> Result<Made<Outputs>> {
        let g = self.0.grid.grid();
        let o = &i.grid;
        ensure!(
            o.dims.map(|d| d as usize) == g.dims,
            "the occupancy is {:?} voxels, the preview's grid {:?}: set its `grid` as the occupancy's",
            o.dims,
            g.dims
        );
        let [nx, ny, nz] = g.dims;
        let s = self.0.scale as usize;
        // Rows run from the front (x max) down, columns from the left (y max) rightwards.
        let (w, h) = (ny * s, nx * s);
        let mut rgb = vec![0u8; w * h * 3];
        for i in 0..nx {
            for j in 0..ny {
                let c = (i * ny + j) * nz;
                let top = (0..nz).rev().find(|&k| o.semantics[c + k] != FREE);
                let colour = match top {
                    Some(k) => PALETTE[o.semantics[c + k] as usize % PALETTE.len()],
                    None if (0..nz).any(|k| o.mask_camera[c + k] != 0) => SEEN_FREE,
                    None => PALETTE[FREE as usize],
                };
                let (row, col) = ((nx - 1 - i) * s, (ny - 1 - j) * s);
                for dy in 0..s {
                    for dx in 0..s {
                        let p = 3 * ((row + dy) * w + col + dx);
                        rgb[p..p + 3].copy_from_slice(&colour);
                    }
                }
            }
        }
        let mut voxels = PointCloud::default();
        for v in 0..o.voxels() {
            let class = o.semantics[v];
            if class == FREE {
                continue;
            }
            let c = g.centre(v);
            voxels.points.push([c.x as f32, c.y as f32, c.z as f32, 0.0]);
            voxels.rgb.push(PALETTE[class as usize % PALETTE.len()]);
            voxels.labels.push(class);
        }
        Ok(Outputs { bev: Image { width: w as u32, height: h as u32, rgb }, voxels }.into())
    }
}
