//! `EvalOccupancy`: a frame's occupancy scored against a reference (the synthetic world's exact
//! occupancy) as Occ3D's released metric does (CVPR2023-3D-Occupancy-Prediction,
//! `projects/mmdet3d_plugin/datasets/occ_metrics.py`, `Metric_mIoU` with `use_image_mask`): the
//! 18 x 18 confusion matrix of the voxels the reference's `mask_camera` marks, free included.
//! Per frame it writes the matrix; `dist4d eval` sums the matrices over the frames and reports
//! each class's IoU, the mIoU (NaN-mean over classes 0-16, free left out) and the geometry IoU
//! (occupied against free).

use dist4d_runtime::Made;
use super::classes::{FREE, NAMES};
use crate::stage::Stage;
use anyhow::{ensure, Result};
use dist4d_graph::Validate;
use dist4d_runtime::TaskContext;
use dist4d_types::artifact::{File, OccupancyGrid};
use serde::{Deserialize, Serialize};

#[derive(Serialize, Deserialize, Clone, Debug, Default, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Params {}

impl Validate for Params {}

crate::inputs! {
    pub struct Inputs {
        /// the occupancy to score
        grid: One<OccupancyGrid>,
        /// the reference (its `mask_camera` says which voxels count)
        reference: One<OccupancyGrid>,
    }
}

crate::outputs! {
    pub struct Outputs {
        /// JSON: `confusion` (rows: reference class, columns: predicted), and the classes
        json: One<File>,
    }
}

/// A frame's scores as written.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
pub struct FrameConfusion {
    pub classes: Vec<String>,
    /// `confusion[reference][predicted]`, voxels.
    pub confusion: Vec<Vec<u64>>,
}

pub struct EvalOccupancy;

impl Stage for EvalOccupancy {
    const KIND: &'static str = "EvalOccupancy";
    const VERSION: u32 = 1;
    const SUMMARY: &'static str = "occupancy against a reference: Occ3D's confusion matrix on the camera-visible voxels";
    const GRAINS: &'static [&'static str] = &["frame"];
    type Params = Params;
    type Inputs = Inputs;
    type Outputs = Outputs;
    fn new(_: Params) -> Result<Self> {
        Ok(EvalOccupancy)
    }
    fn run(&self, _: &TaskContext, i: Inputs) -> Result<Made<Outputs>> {
        let c = confusion(&i.grid, &i.reference)?;
        let scores = FrameConfusion { classes: NAMES.iter().map(|s| s.to_string()).collect(), confusion: c };
        Ok(Outputs { json: File(serde_json::to_vec(&scores)?) }.into())
    }
}

/// The confusion matrix of the module doc.
pub fn confusion(grid: &OccupancyGrid, reference: &OccupancyGrid) -> Result<Vec<Vec<u64>>> {
    ensure!(grid.dims == reference.dims, "the grid is {:?}, the reference {:?}", grid.dims, reference.dims);
    let n = NAMES.len();
    let mut m = vec![vec![0u64; n]; n];
    for v in 0..reference.voxels() {
        if reference.mask_camera[v] == 0 {
            continue;
        }
        let (r, p) = (reference.semantics[v] as usize, grid.semantics[v] as usize);
        if r < n && p < n {
            m[r][p] += 1;
        }
    }
    Ok(m)
}

/// Per class IoU (None where the class is in neither), the mIoU over classes 0-16 and the
/// geometry IoU, from a confusion matrix.
pub fn scores(m: &[Vec<u64>]) -> (Vec<Option<f64>>, Option<f64>, Option<f64>) {
    let n = m.len();
    let iou: Vec<Option<f64>> = (0..n)
        .map(|c| {
            let tp = m[c][c] as f64;
            let row: u64 = m[c].iter().sum();
            let col: u64 = m.iter().map(|r| r[c]).sum();
            let union = row as f64 + col as f64 - tp;
            (union > 0.0).then(|| tp / union)
        })
        .collect();
    let occupied: Vec<f64> = iou.iter().take(FREE as usize).flatten().copied().collect();
    let miou = (!occupied.is_empty()).then(|| occupied.iter().sum::<f64>() / occupied.len() as f64);
    let f = FREE as usize;
    let (mut tp, mut fp, mut fn_) = (0u64, 0u64, 0u64);
    for (r, row) in m.iter().enumerate() {
        for (p, &k) in row.iter().enumerate() {
            match (r != f, p != f) {
                (true, true) => tp += k,
                (false, true) => fp += k,
                (true, false) => fn_ += k,
                _ => {}
            }
        }
    }
    let geometry = (tp + fp + fn_ > 0).then(|| tp as f64 / (tp + fp + fn_) as f64);
    (iou, miou, geometry)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn counts_only_camera_visible_reference_voxels_and_scores_as_occ3d_does() {
        let reference = OccupancyGrid {
            dims: [1, 1, 4],
            semantics: vec![11, 4, 17, 17],
            mask_lidar: vec![1; 4],
            mask_camera: vec![1, 1, 1, 0],
        };
        let grid = OccupancyGrid { semantics: vec![11, 17, 4, 4], ..reference.clone() };
        let m = confusion(&grid, &reference).unwrap();
        assert_eq!((m[11][11], m[4][17], m[17][4], m[17][17]), (1, 1, 1, 0), "the unmasked voxel is left out");
        let (iou, miou, geometry) = scores(&m);
        assert_eq!(iou[11], Some(1.0));
        assert_eq!(iou[4], Some(0.0));
        assert_eq!(iou[7], None, "absent classes are NaN, left out of the mean");
        assert_eq!(miou, Some(0.5));
        // Occupied: reference 2, predicted 2 (11 and the free voxel called car), both 1.
        assert_eq!(geometry, Some(1.0 / 3.0));
    }
}
