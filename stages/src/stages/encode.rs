//! Encoding stages: artifacts -> files for the user-facing layout.
//!
//! `EncodeDepth` writes a depth map as OpenEXR (float32 metres, channel `Z`), 16-bit PNG (depth x
//! 256, the KITTI convention; 0 = no depth, clamped at 255.99 m), NPY (float32 H x W) and a colour
//! preview (turbo, near = warm, black = no depth). `EncodePoints` writes projected points as NPY.

use crate::artifact::{DepthMap, Image, ProjectedPoints};
use crate::stage::{input, one, StageDef, TypedOp};
use anyhow::{Context, Result};
use dist4d_graph::{ParamChecks, ParamProblem, PortSpec, Validate};
use serde::{Deserialize, Serialize};

#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct DepthParams {
    /// Depth (m) at the cold end of the preview colormap.
    pub preview_max_depth: f32,
}

impl Default for DepthParams {
    fn default() -> Self {
        DepthParams { preview_max_depth: 80.0 }
    }
}

impl Validate for DepthParams {
    fn validate(&self) -> Vec<ParamProblem> {
        ParamChecks::new().above("preview_max_depth", self.preview_max_depth as f64, 0.0, 1e6).done()
    }
}

/// OpenEXR, one float32 channel `Z`, ZIP-compressed.
pub fn depth_exr(d: &DepthMap) -> Result<Vec<u8>> {
    use exr::prelude::*;
    let channel = AnyChannel::new("Z", FlatSamples::F32(d.data.clone()));
    let layer = Layer::new(
        (d.width as usize, d.height as usize),
        LayerAttributes::named("depth"),
        Encoding::SMALL_LOSSLESS,
        AnyChannels::sort(smallvec::smallvec![channel]),
    );
    let image = Image::from_layer(layer);
    let mut out = std::io::Cursor::new(Vec::new());
    image.write().non_parallel().to_buffered(&mut out).context("encoding EXR")?;
    Ok(out.into_inner())
}

/// 16-bit grey PNG of depth x 256.
pub fn depth_png16(d: &DepthMap) -> Result<Vec<u8>> {
    let px: Vec<u16> = d
        .data
        .iter()
        .map(|&z| if z > 0.0 && z.is_finite() { (z * 256.0).round().clamp(1.0, 65535.0) as u16 } else { 0 })
        .collect();
    let img =
        image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::from_raw(d.width, d.height, px).context("depth map size")?;
    let mut out = std::io::Cursor::new(Vec::new());
    img.write_to(&mut out, image::ImageFormat::Png).context("encoding PNG")?;
    Ok(out.into_inner())
}

/// NPY v1.0 of a little-endian float32 array.
pub fn npy_f32(shape: &[usize], data: &[f32]) -> Vec<u8> {
    let dims = shape.iter().map(|d| d.to_string()).collect::<Vec<_>>().join(", ");
    let shape = if shape.len() == 1 { format!("({dims},)") } else { format!("({dims})") };
    let mut header = format!("{{'descr': '<f4', 'fortran_order': False, 'shape': {shape}, }}");
    // Magic (6) + version (2) + length (2) + header + '\n' is a multiple of 64.
    while (10 + header.len() + 1) % 64 != 0 {
        header.push(' ');
    }
    header.push('\n');
    let mut out = b"\x93NUMPY\x01\x00".to_vec();
    out.extend_from_slice(&(header.len() as u16).to_le_bytes());
    out.extend_from_slice(header.as_bytes());
    for x in data {
        out.extend_from_slice(&x.to_le_bytes());
    }
    out
}

/// Turbo colormap (Mikhailov 2019, polynomial fit), t in [0, 1].
pub fn turbo(t: f32) -> [u8; 3] {
    let x = t.clamp(0.0, 1.0) as f64;
    let r =
        0.13572138 + x * (4.61539260 + x * (-42.66032258 + x * (132.13108234 + x * (-152.94239396 + x * 59.28637943))));
    let g = 0.09140261 + x * (2.19418839 + x * (4.84296658 + x * (-14.18503333 + x * (4.27729857 + x * 2.82956604))));
    let b =
        0.10667330 + x * (12.64194608 + x * (-60.58204836 + x * (110.36276771 + x * (-89.90310912 + x * 27.34824973))));
    [r, g, b].map(|c| (c.clamp(0.0, 1.0) * 255.0).round() as u8)
}

/// RGB PNG preview: turbo with near = warm (red), far = cold (blue), no depth = black.
pub fn depth_preview(d: &DepthMap, max_depth: f32) -> Result<Vec<u8>> {
    let mut px = Vec::with_capacity(d.data.len() * 3);
    for &z in &d.data {
        if z > 0.0 && z.is_finite() {
            px.extend_from_slice(&turbo(1.0 - z / max_depth));
        } else {
            px.extend_from_slice(&[0, 0, 0]);
        }
    }
    let img = image::RgbImage::from_raw(d.width, d.height, px).context("depth map size")?;
    let mut out = std::io::Cursor::new(Vec::new());
    img.write_to(&mut out, image::ImageFormat::Png).context("encoding PNG")?;
    Ok(out.into_inner())
}

struct DepthOp(DepthParams);

impl TypedOp for DepthOp {
    fn run(
        &self,
        _ctx: &dist4d_runtime::TaskContext,
        inputs: &[Vec<dist4d_runtime::Artifact>],
    ) -> Result<Vec<Vec<u8>>> {
        let d = one::<DepthMap>(inputs, 0)?;
        Ok(vec![
            depth_exr(&d)?,
            depth_png16(&d)?,
            npy_f32(&[d.height as usize, d.width as usize], &d.data),
            depth_preview(&d, self.0.preview_max_depth)?,
        ])
    }
}

pub fn encode_depth() -> StageDef {
    StageDef::new::<DepthParams>(
        "EncodeDepth",
        1,
        "DepthMap -> OpenEXR (float32 m), 16-bit PNG (x256), NPY and a turbo colour preview",
        vec![input::<DepthMap>("depth", "metric depth, 0 = none")],
        vec![
            PortSpec::one("exr", "File", "OpenEXR, channel Z, float32 metres"),
            PortSpec::one("png16", "File", "16-bit PNG, depth x 256 (KITTI), 0 = none"),
            PortSpec::one("npy", "File", "float32 H x W"),
            PortSpec::one("preview", "File", "RGB PNG, turbo, near = warm"),
        ],
        vec!["camera", "frame", "scene"],
        |p: DepthParams| Ok(Box::new(DepthOp(p))),
    )
}

#[derive(Serialize, Deserialize, Clone, Debug, Default, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct NoParams {}

impl Validate for NoParams {}

struct PointsOp;

impl TypedOp for PointsOp {
    fn run(
        &self,
        _ctx: &dist4d_runtime::TaskContext,
        inputs: &[Vec<dist4d_runtime::Artifact>],
    ) -> Result<Vec<Vec<u8>>> {
        let p = one::<ProjectedPoints>(inputs, 0)?;
        Ok(vec![npy_f32(&[p.rows.len(), 3], p.rows.as_flattened())])
    }
}

pub fn encode_points() -> StageDef {
    StageDef::new::<NoParams>(
        "EncodePoints",
        1,
        "ProjectedPoints -> NPY float32 (N, 3) rows of u, v, depth",
        vec![input::<ProjectedPoints>("points", "projected points")],
        vec![PortSpec::one("npy", "File", "float32 (N, 3): u, v, depth")],
        vec!["camera", "frame", "scene"],
        |_: NoParams| Ok(Box::new(PointsOp)),
    )
}

#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct SheetParams {
    /// Each panel is the image scaled by this factor (nearest pixel).
    pub scale: f32,
    /// Depth (m) at the cold end of the colormap.
    pub max_depth: f32,
}

impl Default for SheetParams {
    fn default() -> Self {
        SheetParams { scale: 0.5, max_depth: 80.0 }
    }
}

impl Validate for SheetParams {
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
pub fn depth_sheet(p: &SheetParams, image: &Image, sparse: &DepthMap, dense: &DepthMap) -> Result<Vec<u8>> {
    stack_rows(&[sheet_row(p, image, sparse, dense)?])
}

/// The three panels of one camera image as RGB8 pixels: (width, height, pixels).
fn sheet_row(p: &SheetParams, image: &Image, sparse: &DepthMap, dense: &DepthMap) -> Result<(usize, usize, Vec<u8>)> {
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

struct SheetOp(SheetParams);

impl TypedOp for SheetOp {
    fn run(
        &self,
        _ctx: &dist4d_runtime::TaskContext,
        inputs: &[Vec<dist4d_runtime::Artifact>],
    ) -> Result<Vec<Vec<u8>>> {
        use crate::stage::each;
        let images = each::<Image>(inputs, 0)?;
        let sparse = each::<DepthMap>(inputs, 1)?;
        let dense = each::<DepthMap>(inputs, 2)?;
        anyhow::ensure!(
            images.len() == sparse.len() && images.len() == dense.len(),
            "the sheet got {} images, {} sparse and {} dense depths: gather all three the same way",
            images.len(),
            sparse.len(),
            dense.len()
        );
        let rows = images
            .iter()
            .zip(&sparse)
            .zip(&dense)
            .map(|(((_, i), (_, s)), (_, d))| sheet_row(&self.0, i, s, d))
            .collect::<Result<Vec<_>>>()?;
        Ok(vec![stack_rows(&rows)?])
    }
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

pub fn depth_sheet_def() -> StageDef {
    StageDef::new::<SheetParams>(
        "DepthSheet",
        1,
        "Image | sparse prompt | dense depth side by side, one row per camera, as one PNG per frame",
        vec![
            PortSpec::many("images", "Image", "the cameras' images: Gather(\"dataset.image\", camera)"),
            PortSpec::many("sparse", "DepthMap", "their sparse depth prompts (same Gather)"),
            PortSpec::many("depth", "DepthMap", "their dense depths (same Gather)"),
        ],
        vec![PortSpec::one("png", "File", "RGB PNG, three panels per camera row")],
        vec!["frame", "camera", "scene"],
        |p: SheetParams| Ok(Box::new(SheetOp(p))),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn npy_header_is_aligned_and_numpy_shaped() {
        let b = npy_f32(&[2, 3], &[0.0; 6]);
        let hlen = u16::from_le_bytes([b[8], b[9]]) as usize;
        assert_eq!((10 + hlen) % 64, 0);
        assert!(std::str::from_utf8(&b[10..10 + hlen]).unwrap().contains("'shape': (2, 3)"));
        assert_eq!(b.len(), 10 + hlen + 24);
    }

    #[test]
    fn encodings_decode_back() {
        let d = DepthMap { width: 3, height: 2, data: vec![0.0, 1.5, 80.0, 300.0, 0.25, 10.0] };
        let png = image::load_from_memory(&depth_png16(&d).unwrap()).unwrap().into_luma16();
        assert_eq!(png.as_raw(), &vec![0, 384, 20480, 65535, 64, 2560]);
        use exr::prelude::*;
        let img = read()
            .no_deep_data()
            .largest_resolution_level()
            .all_channels()
            .first_valid_layer()
            .all_attributes()
            .from_buffered(std::io::Cursor::new(depth_exr(&d).unwrap()))
            .unwrap();
        let ch = &img.layer_data.channel_data.list[0];
        assert_eq!(ch.name, Text::from("Z"));
        match &ch.sample_data {
            FlatSamples::F32(v) => assert_eq!(v, &d.data),
            _ => panic!("EXR depth is float32"),
        }
        let prev = image::load_from_memory(&depth_preview(&d, 80.0).unwrap()).unwrap().into_rgb8();
        assert_eq!(prev.get_pixel(0, 0).0, [0, 0, 0]);
        let near = prev.get_pixel(1, 1).0;
        assert!(near[0] > near[2], "near is warm: {near:?}");
    }

    #[test]
    fn the_sheet_has_three_panels() {
        let image = Image { width: 8, height: 4, rgb: vec![200; 96] };
        let mut sparse = DepthMap::new(8, 4);
        sparse.data[9] = 5.0;
        let dense = DepthMap { width: 8, height: 4, data: vec![10.0; 32] };
        let png = depth_sheet(&SheetParams::default(), &image, &sparse, &dense).unwrap();
        let sheet = image::load_from_memory(&png).unwrap().into_rgb8();
        assert_eq!(sheet.dimensions(), (12, 2));
        assert_eq!(sheet.get_pixel(0, 0).0, [200, 200, 200]);
        assert_eq!(sheet.get_pixel(4, 0).0, turbo(1.0 - 5.0 / 80.0), "a dot of the sparse point at (1, 1)");
        assert_eq!(sheet.get_pixel(8, 1).0, turbo(1.0 - 10.0 / 80.0));
        assert!(depth_sheet(&SheetParams::default(), &image, &DepthMap::new(2, 2), &dense).is_err());
    }
}
