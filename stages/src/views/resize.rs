//! Images and depth maps at another size (the model's): colours averaged, depths never mixed. The
//! camera that goes with them is [`super::splat::PinholeView::resized`].

use anyhow::{Context, Result};
use dist4d_types::artifact::{DepthMap, Image};

/// An image resized with a triangle filter (widened when shrinking, so it averages).
pub fn resize_image(image: &Image, width: u32, height: u32) -> Result<Image> {
    if (image.width, image.height) == (width, height) {
        return Ok(image.clone());
    }
    let buf = image::RgbImage::from_raw(image.width, image.height, image.rgb.clone())
        .context("the image's bytes do not match its size")?;
    let out = image::imageops::resize(&buf, width, height, image::imageops::FilterType::Triangle);
    Ok(Image { width, height, rgb: out.into_raw() })
}

/// A depth map resized by taking, for each output pixel, the input pixel under its centre:
/// interpolating would invent depths between a foreground edge and its background.
pub fn resize_depth_nearest(depth: &DepthMap, width: u32, height: u32) -> DepthMap {
    let (sx, sy) = (depth.width as f64 / width as f64, depth.height as f64 / height as f64);
    let mut out = DepthMap::new(width, height);
    for y in 0..height as usize {
        let ys = (((y as f64 + 0.5) * sy) as usize).min(depth.height as usize - 1);
        for x in 0..width as usize {
            let xs = (((x as f64 + 0.5) * sx) as usize).min(depth.width as usize - 1);
            out.data[y * width as usize + x] = depth.data[ys * depth.width as usize + xs];
        }
    }
    out
}
