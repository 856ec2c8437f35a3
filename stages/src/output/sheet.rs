//! `DepthSheet`: one PNG per frame to look at: per camera, the image, the sparse prompt drawn over
//! the darkened image, and the dense depth, side by side.

use super::encode_depth::turbo;
use crate::stage::Stage;
use anyhow::{Context, Result};
use dist4d_graph::{ParamChecks, ParamProblem, Validate};
use dist4d_runtime::TaskContext;
use dist4d_types::artifact::{DepthMap, File, Image};
use serde::{Deserialize, Serialize};

#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// Each panel is the image scaled by this factor (nearest pixel).
    pub scale: f32,
    /// Depth (m) at the cold end of the colormap.
    pub max_depth: f32,
}

impl Default for Params {
    fn default() -> Self {
        Params { scale: 0.5, max_depth: 80.0 }
    }
}

impl Validate for Params {
    fn validate(&self) -> Vec<ParamProblem> {
        ParamChecks::new()
            // The sheet is 3 x scale^2 image areas per camera (nearest pixel: above 1 it only
            // grows; 2 leaves room to enlarge small images).
            .above("scale", self.scale as f64, 0.0, 2.0)
            .above("max_depth", self.max_depth as f64, 0.0, 1e6)
            .done()
    }
}

/// One PNG with three panels side by side: the image, the sparse prompt drawn over the darkened
/// image (points as 3x3 dots, so they show at any scale), and the dense depth.
pub fn depth_sheet(p: &Params, image: &Image, sparse: &DepthMap, dense: &DepthMap) -> Result<Vec<u8>> {
    stack_rows(&[sheet_row(p, image, sparse, dense)?])
}

/// The three panels of one camera image as RGB8 pixels: (width, height, pixels).
fn sheet_row(p: &Params, image: &Image, sparse: &DepthMap, dense: &DepthMap) -> Result<(usize, usize, Vec<u8>)> {
    anyhow::ensure!(
        image.width == sparse.width
            && image.height == sparse.height
            && dense.width == image.width
            && dense.height == image.height,
        "the image, sparse and dense depth differ in size ({}x{}, {}x{}, {}x{})",
        image.width,
        image.height,
        sparse.width,
        sparse.height,
        dense.width,
        dense.height
    );
    let (w, h) = (image.width as usize, image.height as usize);
    let pw = ((w as f32 * p.scale).round() as usize).max(1);
    let ph = ((h as f32 * p.scale).round() as usize).max(1);
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
    let mut out = vec![0u8; 3 * pw * 3 * ph];
    for y in 0..ph {
        let sy = ((y as f32 + 0.5) / p.scale) as usize;
        let sy = sy.min(h - 1);
        for x in 0..pw {
            let sx = (((x as f32 + 0.5) / p.scale) as usize).min(w - 1);
            let i = sy * w + sx;
            let row = y * 3 * pw;
            out[3 * (row + x)..3 * (row + x) + 3].copy_from_slice(&image.rgb[3 * i..3 * i + 3]);
            out[3 * (row + pw + x)..3 * (row + pw + x) + 3].copy_from_slice(&dots[3 * i..3 * i + 3]);
            out[3 * (row + 2 * pw + x)..3 * (row + 2 * pw + x) + 3]
                .copy_from_slice(&colour(dense.data[i]).unwrap_or([0, 0, 0]));
        }
    }
    Ok((3 * pw, ph, out))
}

/// Stacks sheet rows (RGB8, each `(width, height, pixels)`) vertically, left-aligned, as PNG.
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
    let img = image::RgbImage::from_raw(w as u32, h as u32, out).context("sheet size")?;
    let mut buf = std::io::Cursor::new(Vec::new());
    img.write_to(&mut buf, image::ImageFormat::Png).context("encoding PNG")?;
    Ok(buf.into_inner())
}

crate::ports! {
    pub struct Inputs {
        /// the cameras' images: Gather("dataset.image", camera)
        images: Many<Image>,
        /// their sparse depth prompts (same Gather)
        sparse: Many<DepthMap>,
        /// their dense depths (same Gather)
        depth: Many<DepthMap>,
    }
}

crate::ports! {
    pub struct Outputs {
        /// RGB PNG, three panels per camera row
        png: One<File>,
    }
}

pub struct DepthSheet(Params);

impl Stage for DepthSheet {
    const KIND: &'static str = "DepthSheet";
    const VERSION: u32 = 1;
    const SUMMARY: &'static str =
        "Image | sparse prompt | dense depth side by side, one row per camera, as one PNG per frame";
    const GRAINS: &'static [&'static str] = &["frame", "camera", "scene"];
    type Params = Params;
    type Inputs = Inputs;
    type Outputs = Outputs;
    fn new(params: Params) -> Result<Self> {
        Ok(DepthSheet(params))
    }
    fn run(&self, _: &TaskContext, i: Inputs) -> Result<Outputs> {
        anyhow::ensure!(
            i.images.len() == i.sparse.len() && i.images.len() == i.depth.len(),
            "the sheet got {} images, {} sparse and {} dense depths: gather all three the same way",
            i.images.len(),
            i.sparse.len(),
            i.depth.len()
        );
        let rows = i
            .images
            .iter()
            .zip(&i.sparse)
            .zip(&i.depth)
            .map(|(((_, image), (_, s)), (_, d))| sheet_row(&self.0, image, s, d))
            .collect::<Result<Vec<_>>>()?;
        Ok(Outputs { png: File(stack_rows(&rows)?) })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::output::encode_depth::turbo;

    #[test]
    fn the_sheet_has_three_panels() {
        let image = Image { width: 8, height: 4, rgb: vec![200; 96] };
        let mut sparse = DepthMap::new(8, 4);
        sparse.data[9] = 5.0;
        let dense = DepthMap { width: 8, height: 4, data: vec![10.0; 32] };
        let png = depth_sheet(&Params::default(), &image, &sparse, &dense).unwrap();
        let sheet = image::load_from_memory(&png).unwrap().into_rgb8();
        assert_eq!(sheet.dimensions(), (12, 2));
        assert_eq!(sheet.get_pixel(0, 0).0, [200, 200, 200]);
        assert_eq!(sheet.get_pixel(4, 0).0, turbo(1.0 - 5.0 / 80.0), "a dot of the sparse point at (1, 1)");
        assert_eq!(sheet.get_pixel(8, 1).0, turbo(1.0 - 10.0 / 80.0));
        assert!(depth_sheet(&Params::default(), &image, &DepthMap::new(2, 2), &dense).is_err());
    }
}
