//! `EncodeDistDepth`: a camera's curated depth in the files DiST-4D's loaders open,
//! `refined_depth.npz` (key `depth_pred`) and `semantic_oneformer.npz` (key `sem`), which
//! `pipelines/dist4d_layout.ron` exports to `<scene>/<sample token>/<CAMERA>/` and
//! `dist4d depthroot` indexes in `nus_sampletoken2depthroot.json` (docs/interop.md).
//!
//! `depth_pred` is the curated depth as it is (float32 H x W, metres): sky at the pipeline's sky
//! depth, 0 where there is no depth, which includes the ego vehicle's body; the loaders treat
//! values <= 0 as invalid. `sem` holds OneFormer class ids. Which label space DiST-4D's released
//! files use is not settled: the issue says ADE20K-150 (sky 2), while every loader we could read
//! sets `depth[sem == 27] = 100` (Mapillary Vistas-65, sky 27). The default is what the loaders
//! read; `label_space: Ade20k150` writes ADE20K ids. Sky comes from the sky mask; other pixels
//! from the dataset's Cityscapes segmentation through the table below when it has one, else 255
//! (no class in either space).

use dist4d_runtime::Made;
use crate::stage::Stage;
use anyhow::{ensure, Result};
use dist4d_graph::Validate;
use dist4d_runtime::TaskContext;
use dist4d_types::artifact::{DepthMap, File, Mask, Segmentation};
use dist4d_types::formats::{npy_f32, npy_u8, npz};
use serde::{Deserialize, Serialize};

/// The class-id space of `sem`: OneFormer's Mapillary Vistas (65 classes, `nature--sky` = 27) or
/// ADE20K (150 classes, `sky` = 2).
#[derive(Serialize, Deserialize, Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum LabelSpace {
    #[default]
    Mapillary65,
    Ade20k150,
}

/// No class: outside both spaces' ids (OneFormer's ignore label).
pub const UNLABELLED: u8 = 255;

/// Cityscapes full id -> (Mapillary Vistas-65, ADE20K-150) id, from cityscapesScripts'
/// `labels.py` and OneFormer's `register_mapillary_vistas.py` / `register_ade20k_panoptic.py`;
/// a class the space lacks takes the nearest one (rider -> bicyclist / person, train -> on-rails /
/// bus, caravan -> van); unlabelled, static, dynamic and borders stay [`UNLABELLED`].
const CITYSCAPES: [(u8, u8, u8); 29] = [
    (1, 64, UNLABELLED), // ego vehicle: MV has it, ADE does not
    (6, 11, 13),         // ground: pedestrian-area / earth
    (7, 13, 6),          // road
    (8, 15, 11),         // sidewalk
    (9, 10, 6),          // parking
    (10, 12, 6),         // rail track
    (11, 17, 1),         // building
    (12, 6, 0),          // wall
    (13, 3, 32),         // fence
    (14, 4, 38),         // guard rail / rail
    (15, 16, 61),        // bridge
    (16, 18, 1),         // tunnel
    (17, 45, 93),        // pole
    (18, 45, 93),        // polegroup
    (19, 48, 136),       // traffic light
    (20, 50, 43),        // traffic sign / signboard
    (21, 30, 4),         // vegetation / tree
    (22, 29, 9),         // terrain / grass
    (23, 27, 2),         // sky
    (24, 19, 12),        // person
    (25, 20, 12),        // rider: bicyclist / person
    (26, 55, 20),        // car
    (27, 61, 83),        // truck
    (28, 54, 80),        // bus
    (29, 56, 102),       // caravan / van
    (30, 60, 83),        // trailer / truck
    (31, 58, 80),        // train: on-rails / bus
    (32, 57, 116),       // motorcycle / minibike
    (33, 52, 127),       // bicycle
];

impl LabelSpace {
    pub fn sky(self) -> u8 {
        self.of_cityscapes(Segmentation::SKY)
    }

    /// The id of a Cityscapes class.
    pub fn of_cityscapes(self, id: u8) -> u8 {
        CITYSCAPES.iter().find(|(c, ..)| *c == id).map_or(UNLABELLED, |&(_, mv, ade)| match self {
            LabelSpace::Mapillary65 => mv,
            LabelSpace::Ade20k150 => ade,
        })
    }
}

#[derive(Serialize, Deserialize, Clone, Debug, Default, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// The ids `sem` holds (`Mapillary65`: sky 27, what DiST-4D's loaders read; `Ade20k150`: sky 2).
    pub label_space: LabelSpace,
}

impl Validate for Params {}

crate::inputs! {
    pub struct Inputs {
        /// the curated depth (sky at the sky depth, 0 = none)
        depth: One<DepthMap>,
        /// 1 = sky (EstimateSky.sky)
        sky: Optional<Mask>,
        /// Cityscapes ids (the dataset's `semantic`; empty when it has none)
        semantic: Optional<Segmentation>,
    }
}

crate::outputs! {
    pub struct Outputs {
        /// refined_depth.npz: `depth_pred`, float32 (H, W), metres, 0 = none
        depth: One<File>,
        /// semantic_oneformer.npz: `sem`, uint8 (H, W), the label space's ids, 255 = none
        semantic: One<File>,
    }
}

pub struct EncodeDistDepth(Params);

impl Stage for EncodeDistDepth {
    const KIND: &'static str = "EncodeDistDepth";
    const VERSION: u32 = 1;
    const SUMMARY: &'static str =
        "DepthMap (+ sky, segmentation) -> DiST-4D's refined_depth.npz (depth_pred) and semantic_oneformer.npz (sem)";
    const GRAINS: &'static [&'static str] = &["camera"];
    type Params = Params;
    type Inputs = Inputs;
    type Outputs = Outputs;
    fn new(params: Params) -> Result<Self> {
        Ok(EncodeDistDepth(params))
    }
    fn run(&self, _: &TaskContext, i: Inputs) -> Result<Made<Outputs>> {
        let d = &i.depth;
        let (w, h) = (d.width as usize, d.height as usize);
        let sem = semantic(self.0.label_space, d, i.sky.as_ref(), i.semantic.as_ref())?;
        Ok(Outputs {
            depth: File(npz(&[("depth_pred", npy_f32(&[h, w], &d.data))])),
            semantic: File(npz(&[("sem", npy_u8(&[h, w], &sem))])),
        }.into())
    }
}

/// `sem` for a depth map's pixels: the segmentation's classes where there is one, sky where the
/// sky mask says so, [`UNLABELLED`] elsewhere.
pub fn semantic(space: LabelSpace, d: &DepthMap, sky: Option<&Mask>, seg: Option<&Segmentation>) -> Result<Vec<u8>> {
    let n = d.width as usize * d.height as usize;
    let mut sem = vec![UNLABELLED; n];
    if let Some(seg) = seg.filter(|s| !s.ids.is_empty()) {
        ensure!(
            (seg.width, seg.height) == (d.width, d.height),
            "the segmentation is {}x{}, the depth {}x{}",
            seg.width,
            seg.height,
            d.width,
            d.height
        );
        for (s, &c) in sem.iter_mut().zip(&seg.ids) {
            *s = space.of_cityscapes(c);
        }
    }
    if let Some(sky) = sky {
        ensure!(
            (sky.width, sky.height) == (d.width, d.height),
            "the sky mask is {}x{}, the depth {}x{}",
            sky.width,
            sky.height,
            d.width,
            d.height
        );
        for (s, &m) in sem.iter_mut().zip(&sky.data) {
            if m != 0 {
                *s = space.sky();
            }
        }
    }
    Ok(sem)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sky_is_27_in_mapillary_and_2_in_ade20k() {
        assert_eq!(LabelSpace::Mapillary65.sky(), 27);
        assert_eq!(LabelSpace::Ade20k150.sky(), 2);
        assert_eq!(LabelSpace::Mapillary65.of_cityscapes(26), 55);
        assert_eq!(LabelSpace::Ade20k150.of_cityscapes(7), 6);
        assert_eq!(LabelSpace::Ade20k150.of_cityscapes(0), UNLABELLED);
    }

    #[test]
    fn the_sky_mask_wins_over_the_segmentation_and_the_rest_is_unlabelled() {
        let d = DepthMap { width: 3, height: 1, data: vec![5.0, 100.0, 0.0] };
        let sky = Mask { width: 3, height: 1, data: vec![0, 1, 0] };
        let seg = Segmentation { width: 3, height: 1, ids: vec![26, 26, 7] };
        assert_eq!(semantic(LabelSpace::Mapillary65, &d, Some(&sky), None).unwrap(), vec![255, 27, 255]);
        assert_eq!(semantic(LabelSpace::Ade20k150, &d, Some(&sky), Some(&seg)).unwrap(), vec![20, 2, 6]);
        let small = Mask { width: 2, height: 1, data: vec![0, 1] };
        assert!(semantic(LabelSpace::Ade20k150, &d, Some(&small), None).is_err());
    }
}
