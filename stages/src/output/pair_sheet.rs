//! `PairSheet`: one PNG per training pair to look at, at the pair's size: on top the condition
//! image, the target image and the mask (white where the condition has a point); below the
//! condition depth, the target depth (turbo up to `max_depth`, near = warm, black = none) and
//! the condition's relative depth error against the target depth where both have one (white at
//! 0, blue = condition nearer, red = farther, saturated at +-`error_cap`). A condition that sits
//! off its target (a wrong pose, a shifted object) shows as colour in the last panel.

use dist4d_runtime::Made;
use super::encode_depth::turbo;
use crate::stage::Stage;
use anyhow::{ensure, Result};
use dist4d_graph::{ParamChecks, ParamProblem, Validate};
use dist4d_runtime::TaskContext;
use dist4d_types::artifact::{DepthMap, File, Image, Mask};
use dist4d_types::formats::{png, png_bytes};
use serde::{Deserialize, Serialize};

#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// Depth (m) at the cold end of the colormap.
    pub max_depth: f32,
    /// Relative error at which the error panel's colours saturate.
    pub error_cap: f32,
}

impl Default for Params {
    fn default() -> Self {
        Params { max_depth: 80.0, error_cap: 0.1 }
    }
}

impl Validate for Params {
    fn validate(&self) -> Vec<ParamProblem> {
        ParamChecks::new()
            .above("max_depth", self.max_depth as f64, 0.0, 1e6)
            .above("error_cap", self.error_cap as f64, 0.0, 1e3)
            .done()
    }
}

crate::inputs! {
    pub struct Inputs {
        /// the condition image
        cond_image: One<Image>,
        /// the condition depth
        cond_depth: One<DepthMap>,
        /// the condition's valid mask
        mask: One<Mask>,
        /// the target image
        target_image: One<Image>,
        /// the target depth
        target_depth: One<DepthMap>,
    }
}

crate::outputs! {
    pub struct Outputs {
        /// RGB PNG, 3 x 2 panels of the pair's size
        png: One<File>,
    }
}

pub struct PairSheet(Params);

impl Stage for PairSheet {
    const KIND: &'static str = "PairSheet";
    const VERSION: u32 = 1;
    const SUMMARY: &'static str =
        "a training pair to look at: condition | target | mask, and their depths with the condition's error";
    const GRAINS: &'static [&'static str] = &["variant", "camera"];
    type Params = Params;
    type Inputs = Inputs;
    type Outputs = Outputs;
    fn new(params: Params) -> Result<Self> {
        Ok(PairSheet(params))
    }
    fn run(&self, _: &TaskContext, i: Inputs) -> Result<Made<Outputs>> {
        let (w, h) = (i.cond_image.width as usize, i.cond_image.height as usize);
        let n = w * h;
        ensure!(
            i.cond_image.rgb.len() == 3 * n
                && i.target_image.rgb.len() == 3 * n
                && i.mask.data.len() == n
                && i.cond_depth.data.len() == n
                && i.target_depth.data.len() == n,
            "the pair's images, depths and mask must all be {w}x{h}"
        );
        let mut sheet = vec![0u8; 3 * (3 * w) * (2 * h)];
        let mut put = |panel: usize, row: usize, x: usize, y: usize, rgb: [u8; 3]| {
            let i = 3 * ((row * h + y) * 3 * w + panel * w + x);
            sheet[i..i + 3].copy_from_slice(&rgb);
        };
        let depth_colour = |z: f32| {
            if z > 0.0 && z.is_finite() {
                turbo(1.0 - z / self.0.max_depth)
            } else {
                [0, 0, 0]
            }
        };
        for y in 0..h {
            for x in 0..w {
                let p = y * w + x;
                let px = |img: &Image| [img.rgb[3 * p], img.rgb[3 * p + 1], img.rgb[3 * p + 2]];
                put(0, 0, x, y, px(&i.cond_image));
                put(1, 0, x, y, px(&i.target_image));
                put(2, 0, x, y, if i.mask.data[p] != 0 { [255; 3] } else { [0; 3] });
                let (c, t) = (i.cond_depth.data[p], i.target_depth.data[p]);
                put(0, 1, x, y, depth_colour(c));
                put(1, 1, x, y, depth_colour(t));
                put(2, 1, x, y, error_colour(c, t, self.0.error_cap));
            }
        }
        Ok(Outputs {
            png: File(png_bytes(3 * w as u32, 2 * h as u32, &sheet, png::ColorType::Rgb, png::BitDepth::Eight)?),
        }.into())
    }
}

/// White at no error, towards blue where the condition is nearer than the target, red where
/// farther, saturated at +-`cap`; black where either has no depth.
fn error_colour(cond: f32, target: f32, cap: f32) -> [u8; 3] {
    if !(cond > 0.0 && target > 0.0 && cond.is_finite() && target.is_finite()) {
        return [0, 0, 0];
    }
    let e = ((cond - target) / target / cap).clamp(-1.0, 1.0);
    let fade = (255.0 * (1.0 - e.abs())) as u8;
    if e < 0.0 {
        [fade, fade, 255]
    } else {
        [255, fade, fade]
    }
}
