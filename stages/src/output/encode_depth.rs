//! `EncodeDepth`: a depth map as the files of the user-facing layout: OpenEXR (float32 metres,
//! channel `Y`, which OpenCV reads; compressed losslessly, see [`ExrCodec`]), 16-bit PNG (depth x 256, the KITTI convention; 0 = no depth, clamped at 255.99
//! m), NPY (float32 H x W) and a colour preview (turbo, near = warm, black = no depth).

use dist4d_runtime::Made;
use crate::stage::Stage;
use anyhow::Result;
use dist4d_graph::{ParamChecks, ParamProblem, Validate};
use dist4d_runtime::TaskContext;
use dist4d_types::artifact::{DepthMap, File};
pub use dist4d_types::formats::{depth_exr, depth_png16, npy_f32};
use dist4d_types::formats::{depth_exr_with, has_16_significant_bits, png, png_bytes, ExrCompression};
use serde::{Deserialize, Serialize};

#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// Depth (m) at the cold end of the preview colormap.
    pub preview_max_depth: f32,
    /// How the EXR is compressed (see [`ExrCodec`]).
    pub exr_compression: ExrCodec,
}

/// How EncodeDepth compresses its EXR; every choice is lossless for CompleteDepth's depths.
#[derive(Serialize, Deserialize, Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum ExrCodec {
    /// PXR24 when every value has 16 significant bits, which it then stores exactly (CompleteDepth's
    /// depths: a curated 1600x900 map in ~2.0 MB, ~10 ms), ZIP otherwise. OpenCV, the OpenEXR
    /// library and its Python bindings, OpenImageIO, exrs and three.js read PXR24; tinyexr (Godot,
    /// pbrt) and py-minexr do not: choose `Zip` for them.
    #[default]
    Pxr24,
    /// ZIP, blocks of 16 scanlines at deflate level 1, what OpenCV writes and every EXR reader
    /// reads: ~3.1 MB and ~23 ms for a curated map (0.75-0.9 of raw, ~20 ms, for full float bits).
    Zip,
    /// The floats as they are: 5.8 MB for 1600x900, ~1 ms.
    Uncompressed,
}

impl Default for Params {
    fn default() -> Self {
        Params { preview_max_depth: 80.0, exr_compression: ExrCodec::Pxr24 }
    }
}

impl ExrCodec {
    /// The compression the EXR of `values` gets: PXR24 only where it is exact.
    fn for_values(self, values: &[f32]) -> ExrCompression {
        match self {
            ExrCodec::Uncompressed => ExrCompression::None,
            ExrCodec::Pxr24 if has_16_significant_bits(values) => ExrCompression::Pxr24,
            ExrCodec::Pxr24 | ExrCodec::Zip => ExrCompression::Zip,
        }
    }
}

impl Validate for Params {
    fn validate(&self) -> Vec<ParamProblem> {
        ParamChecks::new().above("preview_max_depth", self.preview_max_depth as f64, 0.0, 1e6).done()
    }
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

/// RGB PNG preview: turbo with near = warm (red), far = cold (blue), no depth = black. The colour
/// comes from a 4096-entry table of [`turbo`] (steps of 1/4095 of the depth range: finer than the
/// 8-bit colours can show), not from the polynomial per pixel.
pub fn depth_preview(d: &DepthMap, max_depth: f32) -> Result<Vec<u8>> {
    const STEPS: usize = 4096;
    static TABLE: std::sync::OnceLock<Vec<[u8; 3]>> = std::sync::OnceLock::new();
    // One entry more, black, for no depth: a select, not a branch, picks it.
    let table = TABLE.get_or_init(|| {
        (0..STEPS).map(|i| turbo(i as f32 / (STEPS - 1) as f32)).chain(std::iter::once([0; 3])).collect()
    });
    let scale = (STEPS - 1) as f32 / max_depth;
    anyhow::ensure!(d.data.len() == d.width as usize * d.height as usize, "depth map size");
    let mut px = vec![0u8; 3 * d.data.len()];
    for (&z, rgb) in d.data.iter().zip(px.chunks_exact_mut(3)) {
        // t = 1 - z / max, clamped to [0, 1], as a table index; no depth stays black.
        let near = (STEPS - 1) - ((z * scale).round().min((STEPS - 1) as f32) as usize);
        rgb.copy_from_slice(&table[if z > 0.0 && z.is_finite() { near } else { STEPS }]);
    }
    png_bytes(d.width, d.height, &px, png::ColorType::Rgb, png::BitDepth::Eight)
}

crate::inputs! {
    pub struct Inputs {
        /// metric depth, 0 = none
        depth: One<DepthMap>,
    }
}

// Each made only when the run reads it: a pipeline that exports the NPY alone (the training
// pairs) does not pay for the EXR's deflate, the PNGs or the preview's colours.
crate::outputs! {
    pub struct Outputs {
        /// OpenEXR, channel Y, float32 metres
        exr: OnDemand<File>,
        /// 16-bit PNG, depth x 256 (KITTI), 0 = none
        png16: OnDemand<File>,
        /// float32 H x W
        npy: OnDemand<File>,
        /// RGB PNG, turbo, near = warm
        preview: OnDemand<File>,
    }
}

pub struct EncodeDepth(Params);

impl Stage for EncodeDepth {
    const KIND: &'static str = "EncodeDepth";
    // 2: the EXR channel is `Y` (OpenCV reads it), not `Z`.
    // 3: fast encoders: EXR blocks at deflate level 1, PNGs with fast deflate and the Paeth filter,
    //    the preview's colours from a table (same values, other bytes).
    // 4: PXR24 for maps with 16 significant bits (the same values, a third of the bytes).
    // 5: PXR24's deflate by `deflate_rle` (runs and literals, one Huffman block): other bytes,
    //    the same values, ~10 ms instead of ~15 for a 1600x900 map. `exr_zip: bool` became
    //    `exr_compression` (Pxr24, Zip, Uncompressed).
    const VERSION: u32 = 5;
    const SUMMARY: &'static str =
        "DepthMap -> OpenEXR (float32 m), 16-bit PNG (x256), NPY and a turbo colour preview, each made only when the run reads it";
    const GRAINS: &'static [&'static str] = &["camera", "frame", "scene", "variant"];
    type Params = Params;
    type Inputs = Inputs;
    type Outputs = Outputs;
    fn new(params: Params) -> Result<Self> {
        Ok(EncodeDepth(params))
    }
    fn run(&self, ctx: &TaskContext, i: Inputs) -> Result<Made<Outputs>> {
        let d = i.depth;
        let exr = self.0.exr_compression.for_values(&d.data);
        // Each encoding only if the run reads it (`None` otherwise).
        let wanted = |port: &str, encode: &dyn Fn() -> Result<Vec<u8>>| -> Result<Option<File>> {
            ctx.wants(port).then(encode).transpose().map(|b| b.map(File))
        };
        // Four independent encodings: a worker that would otherwise idle (the end of a run, or
        // fewer ready tasks than threads) takes some.
        let ((exr, png16), (npy, preview)) = rayon::join(
            || rayon::join(|| wanted("exr", &|| depth_exr_with(&d, exr)), || wanted("png16", &|| depth_png16(&d))),
            || {
                rayon::join(
                    || wanted("npy", &|| Ok(npy_f32(&[d.height as usize, d.width as usize], &d.data))),
                    || wanted("preview", &|| depth_preview(&d, self.0.preview_max_depth)),
                )
            },
        );
        Ok(Outputs { exr: exr?, png16: png16?, npy: npy?, preview: preview? }.into())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pxr24_is_chosen_only_where_it_is_exact() {
        let curated = [0.0, 2.5, 100.0, f32::from_bits(0x4120_1300)];
        let full = [0.0, 2.5, 100.0, f32::from_bits(0x4120_1301)];
        assert_eq!(ExrCodec::default().for_values(&curated), ExrCompression::Pxr24);
        assert_eq!(ExrCodec::Pxr24.for_values(&full), ExrCompression::Zip);
        assert_eq!(ExrCodec::Zip.for_values(&curated), ExrCompression::Zip);
        assert_eq!(ExrCodec::Uncompressed.for_values(&curated), ExrCompression::None);
    }

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
        assert_eq!(ch.name, Text::from("Y"));
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
    fn only_the_encodings_the_run_reads_are_made() {
        let d = DepthMap { width: 3, height: 2, data: vec![0.0, 1.5, 80.0, 300.0, 0.25, 10.0] };
        let unread = ["exr".to_string(), "preview".to_string()];
        let ctx = TaskContext { item: Default::default(), seed: 0, label: "t", unread: &unread };
        let out = EncodeDepth(Params::default()).run(&ctx, Inputs { depth: d.clone() }).unwrap().unwrap();
        assert!(out.exr.is_none() && out.preview.is_none());
        assert_eq!(out.npy.map(|f| f.0), Some(npy_f32(&[2, 3], &d.data)));
        assert_eq!(out.png16.map(|f| f.0), Some(depth_png16(&d).unwrap()));
        let all = TaskContext { unread: &[], ..ctx };
        let out = EncodeDepth(Params::default()).run(&all, Inputs { depth: d }).unwrap().unwrap();
        assert!(out.exr.is_some() && out.png16.is_some() && out.npy.is_some() && out.preview.is_some());
    }
}
