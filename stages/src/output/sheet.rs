//! `DepthSheet`: one PNG per frame to look at: per camera, the image, the sparse prompt drawn over
//! the darkened image, the dense depth, and, when the dataset has ground truth, the error against
//! it, side by side.
//!
//! - Dense depth: turbo up to `max_depth` (near = warm), with the outline of the predicted sky
//!   (depth at or beyond `sky_threshold`) in white.
//! - Error (only with a non-empty ground truth): the signed relative error (pred - gt) / gt on a
//!   diverging map, white at 0, blue where the prediction is too near, red where it is too far,
//!   saturated at +-`error_cap` (25%, the bad-pixel rate's upper threshold). Sky disagreements
//!   are flat colours: magenta where the ground truth is sky and the prediction is not (a wall in
//!   the sky), green where the prediction is sky and the ground truth is not. Where both are sky,
//!   or the ground truth has no value, black. The ground truth's sky outline is drawn over it in
//!   orange, so a magenta or green band beside it shows how far off the predicted sky is.
//!
//! Sky is decided as `EvalDepth` decides it: a depth (or ground truth, +inf included) at or beyond
//! `sky_threshold`. Outlines are 2 px wide in the panel (the pixels on both sides of the
//! boundary), not drawn along the image border.

use dist4d_runtime::Made;
use super::encode_depth::turbo;
use crate::eval::sky::is_sky;
use crate::stage::Stage;
use anyhow::{ensure, Context, Result};
use dist4d_graph::{ParamChecks, ParamProblem, Validate};
use dist4d_runtime::TaskContext;
use dist4d_types::artifact::{DepthMap, File, Image};
use dist4d_types::formats::{png, png_bytes};
use serde::{Deserialize, Serialize};

#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// Each panel is the image scaled by this factor (nearest pixel).
    pub scale: f32,
    /// Depth (m) at the cold end of the colormap.
    pub max_depth: f32,
    /// A depth at or beyond this (m) is sky (as in `EvalDepth`; the completion gives sky 100 m).
    pub sky_threshold: f32,
    /// Relative error at which the error panel's colours saturate.
    pub error_cap: f32,
}

impl Default for Params {
    fn default() -> Self {
        Params { scale: 0.5, max_depth: 80.0, sky_threshold: 99.0, error_cap: 0.25 }
    }
}

impl Validate for Params {
    fn validate(&self) -> Vec<ParamProblem> {
        ParamChecks::new()
            // The sheet is 4 x scale^2 image areas per camera (nearest pixel: above 1 it only
            // grows; 2 leaves room to enlarge small images).
            .above("scale", self.scale as f64, 0.0, 2.0)
            .above("max_depth", self.max_depth as f64, 0.0, 1e6)
            .above("sky_threshold", self.sky_threshold as f64, 0.0, 1e6)
            .above("error_cap", self.error_cap as f64, 0.0, 1e3)
            .done()
    }
}

/// The outline colours: predicted sky over the dense depth, ground-truth sky over the error.
pub const PREDICTED_SKY_OUTLINE: [u8; 3] = [255, 255, 255];
pub const GT_SKY_OUTLINE: [u8; 3] = [255, 140, 0];
/// The error panel's flat colours.
pub const SKY_GIVEN_DEPTH: [u8; 3] = [255, 0, 255];
pub const DEPTH_GIVEN_SKY: [u8; 3] = [0, 200, 0];
const NOTHING: [u8; 3] = [0, 0, 0];
/// The diverging map's ends (ColorBrewer RdBu): too near, too far.
const TOO_NEAR: [f32; 3] = [33.0, 102.0, 172.0];
const TOO_FAR: [f32; 3] = [178.0, 24.0, 43.0];

/// One PNG with the panels of one camera image side by side (see the module doc); `gt` empty or
/// `None`: no error panel.
pub fn depth_sheet(
    p: &Params,
    image: &Image,
    sparse: &DepthMap,
    dense: &DepthMap,
    gt: Option<&DepthMap>,
) -> Result<Vec<u8>> {
    stack_rows(&[sheet_row(p, image, sparse, dense, gt)?])
}

/// The colour of the error panel at a pixel with prediction `z` and ground truth `g`.
pub fn error_colour(p: &Params, z: f32, g: f32) -> [u8; 3] {
    if g == 0.0 {
        return NOTHING;
    }
    match (is_sky(g, p.sky_threshold), is_sky(z, p.sky_threshold)) {
        (true, true) => NOTHING,
        (true, false) => SKY_GIVEN_DEPTH,
        (false, true) => DEPTH_GIVEN_SKY,
        (false, false) => {
            let t = ((z - g) / g / p.error_cap).clamp(-1.0, 1.0);
            let end = if t < 0.0 { TOO_NEAR } else { TOO_FAR };
            let a = t.abs();
            end.map(|c| (255.0 + (c - 255.0) * a).round() as u8)
        }
    }
}

/// The panels of one camera image as RGB8 pixels: (width, height, pixels).
fn sheet_row(
    p: &Params,
    image: &Image,
    sparse: &DepthMap,
    dense: &DepthMap,
    gt: Option<&DepthMap>,
) -> Result<(usize, usize, Vec<u8>)> {
    let size = |d: &DepthMap| (d.width, d.height);
    let gt = gt.filter(|g| g.width > 0 && g.height > 0);
    ensure!(
        size(sparse) == (image.width, image.height)
            && size(dense) == (image.width, image.height)
            && gt.is_none_or(|g| size(g) == (image.width, image.height)),
        "the image, sparse and dense depth{} differ in size ({}x{}, {}x{}, {}x{}{})",
        if gt.is_some() { " and ground truth" } else { "" },
        image.width,
        image.height,
        sparse.width,
        sparse.height,
        dense.width,
        dense.height,
        gt.map(|g| format!(", {}x{}", g.width, g.height)).unwrap_or_default()
    );
    let (w, h) = (image.width as usize, image.height as usize);
    let pw = ((w as f32 * p.scale).round() as usize).max(1);
    let ph = ((h as f32 * p.scale).round() as usize).max(1);
    // The source pixel of each panel pixel (nearest).
    let source: Vec<usize> = (0..ph)
        .flat_map(|y| {
            let sy = (((y as f32 + 0.5) / p.scale) as usize).min(h - 1);
            (0..pw).map(move |x| sy * w + (((x as f32 + 0.5) / p.scale) as usize).min(w - 1))
        })
        .collect();
    let panel = |colour: &dyn Fn(usize) -> [u8; 3]| -> Vec<u8> { source.iter().flat_map(|&i| colour(i)).collect() };
    let colour = |z: f32| if z > 0.0 && z.is_finite() { Some(turbo(1.0 - z / p.max_depth)) } else { None };
    // The sparse panel at full size first: darkened image, then dots.
    let mut dots: Vec<u8> = image.rgb.iter().map(|&c| c / 3).collect();
    for y in 0..h {
        for x in 0..w {
            if let Some(c) = colour(sparse.data[y * w + x]) {
                for yy in y.saturating_sub(1)..(y + 2).min(h) {
                    for xx in x.saturating_sub(1)..(x + 2).min(w) {
                        dots[3 * (yy * w + xx)..3 * (yy * w + xx) + 3].copy_from_slice(&c);
                    }
                }
            }
        }
    }
    let sky_outline = |d: &DepthMap| {
        let sky: Vec<bool> = source.iter().map(|&i| is_sky(d.data[i], p.sky_threshold)).collect();
        outline(&sky, pw, ph)
    };
    let mut panels = vec![
        panel(&|i| image.rgb[3 * i..3 * i + 3].try_into().unwrap_or(NOTHING)),
        panel(&|i| dots[3 * i..3 * i + 3].try_into().unwrap_or(NOTHING)),
        panel(&|i| colour(dense.data[i]).unwrap_or(NOTHING)),
    ];
    draw(&mut panels[2], &sky_outline(dense), PREDICTED_SKY_OUTLINE);
    if let Some(g) = gt {
        let mut error = panel(&|i| error_colour(p, dense.data[i], g.data[i]));
        draw(&mut error, &sky_outline(g), GT_SKY_OUTLINE);
        panels.push(error);
    }
    let n = panels.len();
    let mut out = vec![0u8; 3 * pw * n * ph];
    for y in 0..ph {
        for (k, panel) in panels.iter().enumerate() {
            let at = 3 * (y * n * pw + k * pw);
            out[at..at + 3 * pw].copy_from_slice(&panel[3 * y * pw..3 * (y + 1) * pw]);
        }
    }
    Ok((n * pw, ph, out))
}

/// The pixels of a `w x h` mask that differ from one of their 4 neighbours inside it: a boundary
/// 2 px wide (one on each side).
fn outline(mask: &[bool], w: usize, h: usize) -> Vec<bool> {
    let mut out = vec![false; w * h];
    for y in 0..h {
        for x in 0..w {
            let m = mask[y * w + x];
            out[y * w + x] = (x > 0 && mask[y * w + x - 1] != m)
                || (x + 1 < w && mask[y * w + x + 1] != m)
                || (y > 0 && mask[(y - 1) * w + x] != m)
                || (y + 1 < h && mask[(y + 1) * w + x] != m);
        }
    }
    out
}

fn draw(rgb: &mut [u8], mask: &[bool], colour: [u8; 3]) {
    for (px, _) in rgb.chunks_exact_mut(3).zip(mask).filter(|(_, &m)| m) {
        px.copy_from_slice(&colour);
    }
}

/// Stacks sheet rows (RGB8, each `(width, height, pixels)`) vertically, left-aligned, as PNG (fast
/// deflate: the default level took most of the sheet's time for ~26 MB of pixels).
fn stack_rows(rows: &[(usize, usize, Vec<u8>)]) -> Result<Vec<u8>> {
    let w = rows.iter().map(|r| r.0).max().unwrap_or(1).max(1);
    let h = rows.iter().map(|r| r.1).sum::<usize>().max(1);
    let mut out = vec![0u8; 3 * w * h];
    let mut y0 = 0;
    for (rw, rh, px) in rows {
        for y in 0..*rh {
            out[3 * ((y0 + y) * w)..3 * ((y0 + y) * w + rw)].copy_from_slice(&px[3 * y * rw..3 * (y + 1) * rw]);
        }
        y0 += rh;
    }
    png_bytes(w as u32, h as u32, &out, png::ColorType::Rgb, png::BitDepth::Eight)
}

crate::inputs! {
    pub struct Inputs {
        /// the cameras' images: Gather("dataset.image", camera)
        images: Many<Image>,
        /// their sparse depth prompts (same Gather)
        sparse: Many<DepthMap>,
        /// their dense depths (same Gather)
        depth: Many<DepthMap>,
        /// their ground truths, +inf = sky (same Gather of dataset.gt_depth); a camera whose map is
        /// empty (a dataset without ground truth) gets no error panel
        gt: OptionalMany<DepthMap>,
    }
}

crate::outputs! {
    pub struct Outputs {
        /// RGB PNG, three panels per camera row (four with ground truth)
        png: One<File>,
    }
}

pub struct DepthSheet(Params);

impl Stage for DepthSheet {
    const KIND: &'static str = "DepthSheet";
    // 3: the PNG written with the fast deflate and Paeth filter of the other sheets (same pixels).
    const VERSION: u32 = 3;
    const SUMMARY: &'static str =
        "Image | sparse prompt | dense depth with the sky outline | error against the ground truth \
         (when there is one) side by side, one row per camera, as one PNG per frame";
    const GRAINS: &'static [&'static str] = &["frame", "camera", "scene"];
    type Params = Params;
    type Inputs = Inputs;
    type Outputs = Outputs;
    fn new(params: Params) -> Result<Self> {
        Ok(DepthSheet(params))
    }
    fn run(&self, _: &TaskContext, i: Inputs) -> Result<Made<Outputs>> {
        let n = i.images.len();
        ensure!(
            i.sparse.len() == n && i.depth.len() == n && (i.gt.is_empty() || i.gt.len() == n),
            "the sheet got {n} images, {} sparse and {} dense depths and {} ground truths: gather them all the same way",
            i.sparse.len(),
            i.depth.len(),
            i.gt.len()
        );
        let mut rows = Vec::with_capacity(n);
        for (k, (position, image)) in i.images.iter().enumerate() {
            let (sparse, dense, gt) = (&i.sparse[k], &i.depth[k], i.gt.get(k));
            ensure!(
                sparse.0 == *position && dense.0 == *position && gt.is_none_or(|g| g.0 == *position),
                "the sheet's inputs are not gathered alike: image {position} came with sparse {}, dense {}{}",
                sparse.0,
                dense.0,
                gt.map(|g| format!(" and ground truth {}", g.0)).unwrap_or_default()
            );
            let row = sheet_row(&self.0, image, &sparse.1, &dense.1, gt.map(|g| &g.1))
                .with_context(|| format!("camera {position}"))?;
            rows.push(row);
        }
        Ok(Outputs { png: File(stack_rows(&rows)?) }.into())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::output::encode_depth::turbo;

    fn decode(png: &[u8]) -> image::RgbImage {
        image::load_from_memory(png).unwrap().into_rgb8()
    }

    #[test]
    fn the_sheet_has_three_panels_without_ground_truth() {
        let image = Image { width: 8, height: 4, rgb: vec![200; 96] };
        let mut sparse = DepthMap::new(8, 4);
        sparse.data[9] = 5.0;
        let dense = DepthMap { width: 8, height: 4, data: vec![10.0; 32] };
        for gt in [None, Some(DepthMap::new(0, 0))] {
            let sheet = decode(&depth_sheet(&Params::default(), &image, &sparse, &dense, gt.as_ref()).unwrap());
            assert_eq!(sheet.dimensions(), (12, 2));
            assert_eq!(sheet.get_pixel(0, 0).0, [200, 200, 200]);
            assert_eq!(sheet.get_pixel(4, 0).0, turbo(1.0 - 5.0 / 80.0), "a dot of the sparse point at (1, 1)");
            assert_eq!(sheet.get_pixel(8, 1).0, turbo(1.0 - 10.0 / 80.0));
        }
        assert!(depth_sheet(&Params::default(), &image, &DepthMap::new(2, 2), &dense, None).is_err());
        let small_gt = DepthMap::new(2, 2);
        let err = depth_sheet(&Params::default(), &image, &sparse, &dense, Some(&small_gt)).unwrap_err();
        assert!(err.to_string().contains("ground truth"), "{err}");
    }

    #[test]
    fn the_error_panel_shows_relative_error_and_sky_disagreements() {
        // 8 x 8 at scale 1. Ground truth: sky in rows 0-2, 20 m below. Prediction: sky in rows
        // 0-1 (row 2: a wall at 50 m in the sky), then exact, 10% too near, 50% too far (capped),
        // and sky again in the last row (sky where there is a surface).
        let (w, h) = (8usize, 8usize);
        let gt = DepthMap {
            width: 8,
            height: 8,
            data: (0..w * h).map(|i| if i / w < 3 { f32::INFINITY } else { 20.0 }).collect(),
        };
        let rows = [100.0, 100.0, 50.0, 20.0, 20.0, 18.0, 30.0, 100.0];
        let dense = DepthMap { width: 8, height: 8, data: (0..w * h).map(|i| rows[i / w]).collect() };
        let image = Image { width: 8, height: 8, rgb: vec![90; 3 * w * h] };
        let p = Params { scale: 1.0, ..Params::default() };
        let sheet = decode(&depth_sheet(&p, &image, &DepthMap::new(8, 8), &dense, Some(&gt)).unwrap());
        assert_eq!(sheet.dimensions(), (32, 8));
        let error = |x: u32, y: u32| sheet.get_pixel(24 + x, y).0;
        assert_eq!(error(4, 0), NOTHING, "both sky");
        assert_eq!(error(4, 3), GT_SKY_OUTLINE, "the ground truth's sky ends between rows 2 and 3");
        assert_eq!(error(4, 2), GT_SKY_OUTLINE);
        assert_eq!(error(4, 4), [255, 255, 255], "exact");
        assert_eq!(error(4, 5), error_colour(&p, 18.0, 20.0));
        assert_eq!(error_colour(&p, 18.0, 20.0), [166, 194, 222], "40% of the way to blue");
        assert_eq!(error(4, 6), [178, 24, 43], "50% too far: saturated red");
        assert_eq!(error(4, 7), DEPTH_GIVEN_SKY);
        assert_eq!(error_colour(&p, 50.0, f32::INFINITY), SKY_GIVEN_DEPTH);
        assert_eq!(error_colour(&p, 50.0, 0.0), NOTHING, "no ground truth");
        // The predicted sky's outline over the dense panel: rows 1-2 (its boundary) and 6-7.
        let outlined: Vec<u32> = (0..8).filter(|&y| sheet.get_pixel(16 + 4, y).0 == PREDICTED_SKY_OUTLINE).collect();
        assert_eq!(outlined, vec![1, 2, 6, 7]);
        assert_eq!(sheet.get_pixel(16 + 4, 4).0, turbo(1.0 - 20.0 / 80.0));
    }
}
