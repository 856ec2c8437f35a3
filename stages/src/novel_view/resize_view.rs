//! `ResizeView`: a camera image and its depth at the model's size, once per image: the target of
//! every pair that reads it (up to seven DiST-S pairs target one frame) then needs neither the
//! camera-size image nor a resize of its own. The image is resized with an antialiasing triangle
//! filter, the depth by nearest sample (see `FramePair`).

use dist4d_runtime::Made;
use crate::stage::Stage;
use crate::views::resize::{resize_depth_nearest, resize_image};
use anyhow::Result;
use dist4d_graph::{ParamChecks, ParamProblem, Validate};
use dist4d_runtime::TaskContext;
use dist4d_types::artifact::{DepthMap, Image};
use serde::{Deserialize, Serialize};

#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// The model's input size (px).
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
        /// the camera image
        image: One<Image>,
        /// its depth (curated)
        depth: One<DepthMap>,
    }
}

crate::outputs! {
    pub struct Outputs {
        /// the image at the model's size
        image: One<Image>,
        /// the depth at the model's size (nearest sample)
        depth: One<DepthMap>,
    }
}

pub struct ResizeView(Params);

impl Stage for ResizeView {
    const KIND: &'static str = "ResizeView";
    const VERSION: u32 = 1;
    const SUMMARY: &'static str = "an image (triangle filter) and its depth (nearest sample) at the model's size";
    const GRAINS: &'static [&'static str] = &["camera"];
    type Params = Params;
    type Inputs = Inputs;
    type Outputs = Outputs;
    fn new(params: Params) -> Result<Self> {
        Ok(ResizeView(params))
    }
    fn run(&self, _: &TaskContext, i: Inputs) -> Result<Made<Outputs>> {
        let (w, h) = (self.0.width, self.0.height);
        Ok(Outputs { image: resize_image(&i.image, w, h)?, depth: resize_depth_nearest(&i.depth, w, h) }.into())
    }
}
