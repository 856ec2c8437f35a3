//! File formats dist4d writes, shared by the stages that export them and the synthetic world that
//! writes its ground truth: OpenEXR depth, 16-bit PNG depth, NPY arrays.

use crate::artifact::DepthMap;
use anyhow::{Context, Result};

/// OpenEXR, one float32 channel `Y`, ZIP-compressed. `Y`, not `Z`: OpenCV (`cv2.imread(path,
/// IMREAD_UNCHANGED)`, how most users open an EXR) reads a lone `Y` channel as a grey float image
/// and returns zeros for a lone `Z`; the OpenEXR bindings and readers that take the first channel
/// read either.
pub fn depth_exr(d: &DepthMap) -> Result<Vec<u8>> {
    use exr::prelude::*;
    let channel = AnyChannel::new("Y", FlatSamples::F32(d.data.clone()));
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
