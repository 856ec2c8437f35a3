//! `EncodeImage`: an image, or a mask, as a PNG file (RGB8; a mask as 8-bit grey, 255 = set):
//! the condition and target images of training pairs, which a loader reads losslessly.

use dist4d_runtime::Made;
use crate::stage::Stage;
use anyhow::{ensure, Result};
use dist4d_graph::Validate;
use dist4d_runtime::TaskContext;
use dist4d_types::artifact::{File, Image, Mask};
use dist4d_types::formats::{png, png_bytes};
use serde::{Deserialize, Serialize};

#[derive(Serialize, Deserialize, Clone, Debug, PartialEq, Default)]
#[serde(deny_unknown_fields, default)]
pub struct Params {}

impl Validate for Params {}

crate::inputs! {
    pub struct Inputs {
        /// an RGB8 image (wire this or `mask`)
        image: Optional<Image>,
        /// a mask, written 0 / 255
        mask: Optional<Mask>,
    }
}

crate::outputs! {
    pub struct Outputs {
        /// PNG: RGB8 for an image, grey 0 / 255 for a mask
        png: One<File>,
    }
}

pub struct EncodeImage;

impl Stage for EncodeImage {
    const KIND: &'static str = "EncodeImage";
    const VERSION: u32 = 1;
    const SUMMARY: &'static str = "Image -> RGB PNG, or Mask -> 8-bit PNG (255 = set)";
    const GRAINS: &'static [&'static str] = &["camera", "variant", "frame", "scene"];
    type Params = Params;
    type Inputs = Inputs;
    type Outputs = Outputs;
    fn new(_: Params) -> Result<Self> {
        Ok(EncodeImage)
    }
    fn run(&self, _: &TaskContext, i: Inputs) -> Result<Made<Outputs>> {
        let png = match (i.image, i.mask) {
            (Some(img), None) => {
                ensure!(
                    img.rgb.len() == 3 * img.width as usize * img.height as usize,
                    "the image's bytes do not match its size"
                );
                png_bytes(img.width, img.height, &img.rgb, png::ColorType::Rgb, png::BitDepth::Eight)?
            }
            (None, Some(m)) => {
                ensure!(m.data.len() == m.width as usize * m.height as usize, "the mask's bytes do not match its size");
                let grey: Vec<u8> = m.data.iter().map(|&b| if b != 0 { 255 } else { 0 }).collect();
                png_bytes(m.width, m.height, &grey, png::ColorType::Grayscale, png::BitDepth::Eight)?
            }
            _ => anyhow::bail!("wire exactly one of `image` and `mask`"),
        };
        Ok(Outputs { png: File(png) }.into())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn images_and_masks_read_back() {
        let ctx = TaskContext { item: Default::default(), seed: 0, label: "t", unread: &[] };
        let img = Image { width: 2, height: 1, rgb: vec![1, 2, 3, 250, 251, 252] };
        let out = EncodeImage.run(&ctx, Inputs { image: Some(img.clone()), mask: None }).unwrap().unwrap();
        assert_eq!(image::load_from_memory(&out.png.0).unwrap().into_rgb8().into_raw(), img.rgb);
        let m = Mask { width: 3, height: 1, data: vec![0, 1, 7] };
        let out = EncodeImage.run(&ctx, Inputs { image: None, mask: Some(m) }).unwrap().unwrap();
        assert_eq!(image::load_from_memory(&out.png.0).unwrap().into_luma8().into_raw(), vec![0, 255, 255]);
        assert!(EncodeImage.run(&ctx, Inputs { image: None, mask: None }).is_err());
    }
}
