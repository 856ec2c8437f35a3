//! DynamicCity's data (3DTopia/DynamicCity): its released loader reads CarlaSC's layout
//! (`dynamic_city/dataset/carlasc.py`, `CarlaSCOccSequenceDataset`), so dist4d writes that layout
//! and the released training code runs on it with only its dataset config changed (`data_path`,
//! `spatial_size`, `num_classes`, `semantic_map`):
//!
//! - `EncodeCarlaSC`, per frame: `<frame:06>.label`, the classes as raw uint32 in C order over
//!   (X, Y, Z) (`np.fromfile(path, dtype=np.uint32).reshape(spatial_size)`), DynamicCity's scheme
//!   with 0 = free; and `<frame:06>.bin` beside it, float32 of the same shape, 0 where the voxel
//!   was not observed (the loader reads it by `path.replace('label', 'bin')` and uses `bin == 0`
//!   as the invalid mask of its metrics).
//! - `PosesTxt` (`poses_txt.rs`), per scene: `poses.txt`, one line per frame (row = frame number), the 3 x 4
//!   world-from-ego matrix row-major, as `np.loadtxt` reads it; the loader takes x, y from
//!   entries 3 and 7 and the yaw as atan2(entry 4, entry 0) (`data_utils.get_trajectory`).

use dist4d_runtime::Made;
use super::classes::FREE;
use crate::stage::Stage;
use anyhow::{ensure, Result};
use dist4d_graph::{ParamChecks, ParamProblem, Validate};
use dist4d_runtime::TaskContext;
use dist4d_types::artifact::{File, OccupancyGrid};
use serde::{Deserialize, Serialize};

/// Which mask marks a voxel valid in the `.bin`.
#[derive(Serialize, Deserialize, Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum Valid {
    /// Seen by a camera (what Occ3D evaluates on).
    #[default]
    Camera,
    /// Observed by the LiDAR.
    Lidar,
}

#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// The DynamicCity class of each Occ3D class (18 entries, by Occ3D index). Default: free
    /// (17) -> 0 and every other class c -> c + 1, so `num_classes: 18` and 0 = free as the
    /// loader's metrics expect (they leave class 0 out of the mIoU).
    pub classes: Vec<u32>,
    pub valid: Valid,
}

impl Default for Params {
    fn default() -> Self {
        Params { classes: (0..18).map(|c| if c == FREE as u32 { 0 } else { c + 1 }).collect(), valid: Valid::Camera }
    }
}

impl Validate for Params {
    fn validate(&self) -> Vec<ParamProblem> {
        let mut c = ParamChecks::new();
        c.check(self.classes.len() == 18, "classes", || {
            format!("needs one DynamicCity class per Occ3D class (18), found {}", self.classes.len())
        });
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
        /// `.label`: uint32 classes, C order over (X, Y, Z)
        label: One<File>,
        /// `.bin`: float32, 0 = not observed
        bin: One<File>,
    }
}

pub struct EncodeCarlaSC(Params);

impl Stage for EncodeCarlaSC {
    const KIND: &'static str = "EncodeCarlaSC";
    const VERSION: u32 = 1;
    const SUMMARY: &'static str =
        "OccupancyGrid -> DynamicCity's CarlaSC files: .label (uint32 classes, 0 = free) and .bin (float32 valid mask)";
    const GRAINS: &'static [&'static str] = &["frame"];
    type Params = Params;
    type Inputs = Inputs;
    type Outputs = Outputs;
    fn new(params: Params) -> Result<Self> {
        Ok(EncodeCarlaSC(params))
    }
    fn run(&self, _: &TaskContext, i: Inputs) -> Result<Made<Outputs>> {
        let g = &i.grid;
        let n = g.voxels();
        ensure!(g.semantics.len() == n, "the grid's volumes do not match its size {:?}", g.dims);
        let mut label = Vec::with_capacity(4 * n);
        for &s in &g.semantics {
            let class = self.0.classes.get(s as usize).copied().unwrap_or(0);
            label.extend_from_slice(&class.to_le_bytes());
        }
        let mask = match self.0.valid {
            Valid::Camera => &g.mask_camera,
            Valid::Lidar => &g.mask_lidar,
        };
        let mut bin = Vec::with_capacity(4 * n);
        for &m in mask {
            bin.extend_from_slice(&(if m != 0 { 1.0f32 } else { 0.0 }).to_le_bytes());
        }
        Ok(Outputs { label: File(label), bin: File(bin) }.into())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_label_is_uint32_with_free_zero_and_the_bin_marks_the_seen_voxels() {
        let grid = OccupancyGrid { dims: [1, 1, 3], semantics: vec![17, 11, 4], mask_lidar: vec![1, 1, 1], mask_camera: vec![0, 1, 1] };
        let out = EncodeCarlaSC(Params::default()).run(&TaskContext { item: Default::default(), seed: 0, label: "t", unread: &[] }, Inputs { grid }).unwrap().unwrap();
        let label: Vec<u32> = out.label.0.chunks(4).map(|c| u32::from_le_bytes(c.try_into().unwrap())).collect();
        assert_eq!(label, vec![0, 12, 5]);
        let bin: Vec<f32> = out.bin.0.chunks(4).map(|c| f32::from_le_bytes(c.try_into().unwrap())).collect();
        assert_eq!(bin, vec![0.0, 1.0, 1.0]);
    }
}
