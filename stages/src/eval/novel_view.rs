//! `EvalNovelView`: a generated view against the exact one (synthetic data): PSNR and SSIM on RGB
//! (SSIM as Wang et al. 2004, matching scikit-image; see [`super::image_scores`]) over the whole
//! image and over the condition's valid pixels, and Abs Rel and delta < 1.25 on depth where the
//! reference is structure within `min_depth..max_depth` (the sky and beyond are left out, as in
//! the depth evaluation). `dist4d eval` tabulates the scores per variant (the shift).

use dist4d_runtime::Made;
use super::image_scores::{psnr, ssim_both};
use crate::stage::Stage;
use anyhow::{ensure, Result};
use dist4d_graph::{ParamChecks, ParamProblem, Validate};
use dist4d_runtime::TaskContext;
use dist4d_types::artifact::{DepthMap, File, Image, Mask};
use serde::{Deserialize, Serialize};

#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// Depth is scored where the reference lies in `min_depth..=max_depth` (m).
    pub min_depth: f32,
    pub max_depth: f32,
}

impl Default for Params {
    fn default() -> Self {
        Params { min_depth: 0.1, max_depth: 80.0 }
    }
}

impl Validate for Params {
    fn validate(&self) -> Vec<ParamProblem> {
        ParamChecks::new()
            .above("min_depth", self.min_depth as f64, 0.0, 1e6)
            .above("max_depth", self.max_depth as f64, 0.0, 1e6)
            .below("min_depth", self.min_depth as f64, "max_depth", self.max_depth as f64)
            .done()
    }
}

/// The scores of one view (`None`: no pixel to score).
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq, Default)]
pub struct ViewScores {
    pub psnr: Option<f64>,
    pub ssim: Option<f64>,
    /// Over the condition's valid pixels only.
    pub psnr_valid: Option<f64>,
    pub ssim_valid: Option<f64>,
    pub abs_rel: Option<f64>,
    pub delta1: Option<f64>,
    /// Over the condition's valid pixels only: what the reprojection gives, not the fill.
    pub abs_rel_valid: Option<f64>,
    pub delta1_valid: Option<f64>,
    /// The share of the image the condition covers.
    pub valid_share: f64,
    /// Pixels depth was scored on.
    pub depth_pixels: u64,
}

crate::inputs! {
    pub struct Inputs {
        /// the generated view's RGB
        image: One<Image>,
        /// the generated view's depth
        depth: One<DepthMap>,
        /// the condition's valid mask (the valid-pixel scores)
        mask: One<Mask>,
        /// the exact RGB
        ref_image: One<Image>,
        /// the exact depth (+inf = sky)
        ref_depth: One<DepthMap>,
    }
}

crate::outputs! {
    pub struct Outputs {
        /// the scores, JSON
        json: One<File>,
    }
}

pub struct EvalNovelView(Params);

/// Scores one generated view (see the module doc).
pub fn score(p: &Params, i: &Inputs) -> Result<ViewScores> {
    let (w, h) = (i.image.width as usize, i.image.height as usize);
    let n = w * h;
    ensure!(
        (i.ref_image.width as usize, i.ref_image.height as usize) == (w, h)
            && i.depth.data.len() == n
            && i.ref_depth.data.len() == n
            && i.mask.data.len() == n,
        "the generated view ({w}x{h}), its mask and the reference ({}x{}) must have one size",
        i.ref_image.width,
        i.ref_image.height
    );
    let valid: Vec<bool> = i.mask.data.iter().map(|&m| m != 0).collect();
    // [all, valid]: (sum of relative errors, pixels within 1.25, pixels)
    let mut acc = [(0f64, 0u64, 0u64); 2];
    for ((&z, &r), &v) in i.depth.data.iter().zip(&i.ref_depth.data).zip(&valid) {
        if r.is_finite() && r >= p.min_depth && r <= p.max_depth {
            // No depth where there is structure: as wrong as can be.
            let (e, ok) = if z > 0.0 && z.is_finite() {
                (((z - r) / r).abs() as f64, (z / r).max(r / z) < 1.25)
            } else {
                (1.0, false)
            };
            for a in &mut acc[..1 + v as usize] {
                a.0 += e;
                a.1 += ok as u64;
                a.2 += 1;
            }
        }
    }
    let rel = |a: (f64, u64, u64)| (a.2 > 0).then(|| a.0 / a.2 as f64);
    let d1 = |a: (f64, u64, u64)| (a.2 > 0).then(|| a.1 as f64 / a.2 as f64);
    let (ssim, ssim_valid) = ssim_both(&i.image.rgb, &i.ref_image.rgb, w, h, &valid);
    Ok(ViewScores {
        psnr: psnr(&i.image.rgb, &i.ref_image.rgb, w, h, None),
        ssim,
        psnr_valid: psnr(&i.image.rgb, &i.ref_image.rgb, w, h, Some(&valid)),
        ssim_valid,
        abs_rel: rel(acc[0]),
        delta1: d1(acc[0]),
        abs_rel_valid: rel(acc[1]),
        delta1_valid: d1(acc[1]),
        valid_share: valid.iter().filter(|&&v| v).count() as f64 / n.max(1) as f64,
        depth_pixels: acc[0].2,
    })
}

impl Stage for EvalNovelView {
    const KIND: &'static str = "EvalNovelView";
    const VERSION: u32 = 1;
    const SUMMARY: &'static str =
        "a generated view against the exact one: PSNR, SSIM (all / valid pixels), Abs Rel, delta < 1.25";
    const GRAINS: &'static [&'static str] = &["variant", "camera"];
    type Params = Params;
    type Inputs = Inputs;
    type Outputs = Outputs;
    fn new(params: Params) -> Result<Self> {
        Ok(EvalNovelView(params))
    }
    fn run(&self, _: &TaskContext, i: Inputs) -> Result<Made<Outputs>> {
        Ok(Outputs { json: File(serde_json::to_vec(&score(&self.0, &i)?)?) }.into())
    }
}
