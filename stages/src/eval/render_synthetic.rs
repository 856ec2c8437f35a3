//! `RenderSynthetic`: the exact view of a synthetic dataset's world from any camera pose at the
//! image's time (ray cast by dist4d-synth's renderer): the reference novel views are scored
//! against. On a dataset that is not synthetic (no `dataset.synth_world`) it has nothing to make,
//! and neither do the scores that read it.

use crate::stage::Stage;
use anyhow::{Context, Result};
use dist4d_graph::{ParamChecks, ParamProblem, Validate};
use dist4d_runtime::{Made, TaskContext};
use dist4d_synth::{PinholeCamera, Renderer};
use dist4d_types::artifact::{Calibration, DepthMap, File, Image, Pose};
use serde::{Deserialize, Serialize};

#[derive(Serialize, Deserialize, Clone, Debug, PartialEq, Default)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// Image size (px); 0 and 0 = the calibration's (intrinsics scale with the image).
    pub width: u32,
    pub height: u32,
}

impl Validate for Params {
    fn validate(&self) -> Vec<ParamProblem> {
        let mut c = ParamChecks::new();
        c.count("width", self.width as u64, 0, 16384).count("height", self.height as u64, 0, 16384).check(
            (self.width == 0) == (self.height == 0),
            "width",
            || "and `height` are both 0 (the calibration's size) or both set".into(),
        );
        c.done()
    }
}

crate::inputs! {
    pub struct Inputs {
        /// the synthetic world (`dataset.synth_world`; empty for other datasets)
        world: One<File>,
        /// the camera's mounting and intrinsics
        camera_calib: One<Calibration>,
        /// the ego pose to render from (its time is the world's time)
        pose: One<Pose>,
    }
}

crate::outputs! {
    pub struct Outputs {
        /// exact RGB
        image: One<Image>,
        /// exact depth along the optical axis (m; +inf = sky)
        depth: One<DepthMap>,
    }
}

pub struct RenderSynthetic(Params);

impl Stage for RenderSynthetic {
    const KIND: &'static str = "RenderSynthetic";
    const VERSION: u32 = 1;
    const SUMMARY: &'static str =
        "the exact view of a synthetic world from a camera at any pose (the novel-view reference)";
    const GRAINS: &'static [&'static str] = &["variant", "camera"];
    type Params = Params;
    type Inputs = Inputs;
    type Outputs = Outputs;
    fn new(params: Params) -> Result<Self> {
        Ok(RenderSynthetic(params))
    }
    fn run(&self, _: &TaskContext, i: Inputs) -> Result<Made<Outputs>> {
        if i.world.0.is_empty() {
            return Ok(Made::Nothing("not a synthetic dataset: no world to render".into()));
        }
        let r = Renderer::shared(&i.world.0)?;
        let scene_name: serde_json::Value = serde_json::from_slice(&i.world.0)?;
        let name = scene_name["scene"].as_str().unwrap_or_default();
        let scene = r.scene_index(name).with_context(|| format!("the synthetic world has no scene `{name}`"))?;
        let view = crate::views::splat::PinholeView::new(&i.camera_calib, &i.pose)?;
        let view = match (self.0.width, self.0.height) {
            (0, 0) => view,
            (w, h) => view.resized(w, h),
        };
        let cam =
            PinholeCamera { k: view.k, width: view.width, height: view.height, camera_to_world: view.world_from_cam };
        let img = r.render_at_timestamp(scene, i.pose.timestamp_us, &cam)?;
        Ok(Outputs {
            image: Image { width: img.width, height: img.height, rgb: img.rgb },
            depth: DepthMap { width: img.width, height: img.height, data: img.depth },
        }.into())
    }
}
