//! `CyclePair`: the record and target of a self-supervised cycle-consistency (SCC) pair (paper
//! Sec. 3.4, Fig. 4). The pipeline moves a camera image's view sideways (`ShiftView`), generates
//! dense RGB-D there from the image's own RGB-D (`FillViewBaseline`, or DiST-S through a worker),
//! and reprojects that back into the original camera (`Reproject`): that is the pair's condition.
//! Its target is the original image and curated depth, at the model size like the condition;
//! this stage makes them and the pair's record, in the format of the DiST-S pairs with `kind:
//! "scc"` and the shift, so one loader reads both.

use dist4d_runtime::Made;
use super::shift_view::lateral_of;
use crate::stage::Stage;
use crate::views::frames::{frame_record, view_of};
use crate::views::resize::{resize_depth_nearest, resize_image};
use anyhow::{Context, Result};
use dist4d_graph::{ParamChecks, ParamProblem, Validate};
use dist4d_runtime::TaskContext;
use dist4d_types::artifact::{DepthMap, File, Image, ImageInfo, Pose};
use serde::{Deserialize, Serialize};
use serde_json::json;

#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// The model's input size (px), as the condition's.
    pub width: u32,
    pub height: u32,
}

impl Default for Params {
    fn default() -> Self {
        Params { width: 768, height: 448 }
    }
}

impl Validate for Params {
    fn validate(&self) -> Vec<ParamProblem> {
        ParamChecks::new()
            .count("width", self.width as u64, 8, 16384)
            .count("height", self.height as u64, 8, 16384)
            .done()
    }
}

crate::inputs! {
    pub struct Inputs {
        /// the original image
        image: One<Image>,
        /// its curated dense depth
        depth: One<DepthMap>,
        /// what the image is and where it was taken
        info: One<ImageInfo>,
        /// the shifted ego pose the novel view was generated at
        shifted_pose: One<Pose>,
    }
}

crate::outputs! {
    pub struct Outputs {
        /// the original image at the model size
        target_image: One<Image>,
        /// its curated depth at the model size (nearest sample)
        target_depth: One<DepthMap>,
        /// the pair's record (JSON)
        record: One<File>,
    }
}

pub struct CyclePair(Params);

impl Stage for CyclePair {
    const KIND: &'static str = "CyclePair";
    const VERSION: u32 = 1;
    const SUMMARY: &'static str = "the target and record of a self-supervised cycle-consistency pair";
    const GRAINS: &'static [&'static str] = &["variant"];
    type Params = Params;
    type Inputs = Inputs;
    type Outputs = Outputs;
    fn new(params: Params) -> Result<Self> {
        Ok(CyclePair(params))
    }
    fn run(&self, ctx: &TaskContext, i: Inputs) -> Result<Made<Outputs>> {
        let (w, h) = (self.0.width, self.0.height);
        let view = view_of(&i.info, &i.image, &i.depth)?;
        let original = Pose { ego_to_world: i.info.ego_to_world, timestamp_us: i.info.timestamp_us };
        let tau = lateral_of(&original, &i.shifted_pose);
        let variant = ctx.label.rsplit('/').next().context("a pair runs per variant")?;
        let shifted_info = ImageInfo { ego_to_world: i.shifted_pose.ego_to_world, ..i.info.clone() };
        let mut novel = frame_record(&shifted_info, &view);
        novel["image"] = serde_json::Value::Null;
        novel["token"] = serde_json::Value::Null;
        let record = json!({
            "kind": "scc",
            "scene": i.info.scene,
            "camera": i.info.camera,
            "frame": i.info.frame,
            "variant": variant,
            "offset": 0,
            "shift": tau,
            "augmentation": { "offset": false, "voxel": 0.0 },
            "size": [h, w],
            // The generated novel view the condition was reprojected from (no image of the
            // dataset: its pose is the original's moved `shift` metres to the left).
            "from": "Own",
            "sources": [novel],
            "target": frame_record(&i.info, &view.resized(w, h)),
        });
        Ok(Outputs {
            target_image: resize_image(&i.image, w, h)?,
            target_depth: resize_depth_nearest(&i.depth, w, h),
            record: File(serde_json::to_vec(&record)?),
        }.into())
    }
}
