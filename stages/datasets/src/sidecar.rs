//! Per-image files beside a dataset, read for the source ports `gt_depth` and `semantic`:
//! dense ground-truth depth (the synthetic world writes `groundtruth/depth/<CAMERA>/<image
//! stem>.exr`, +inf = sky) and semantic maps from any segmenter (`<semantics>/<CAMERA>/<image
//! stem>.png`, 8-bit Cityscapes ids). A dataset without them gives empty (0 x 0) artifacts, which
//! the stages read as "none", so one pipeline file serves real and synthetic data.

use anyhow::{bail, Context, Result};
use dist4d_types::artifact::{DepthMap, Segmentation};
use std::path::{Path, PathBuf};

#[derive(Clone, Debug, Default)]
pub struct Sidecars {
    depth: Option<PathBuf>,
    semantics: Option<PathBuf>,
}

impl Sidecars {
    /// `semantics`: the folder of segmentation PNGs, relative to `root` unless absolute.
    pub fn new(root: &Path, semantics: Option<&str>) -> Sidecars {
        let depth = root.join("groundtruth").join("depth");
        Sidecars { depth: depth.is_dir().then_some(depth), semantics: semantics.map(|s| root.join(s)) }
    }

    /// The sidecar file of `port` for an image, or `None` when the dataset has none.
    pub fn path(&self, port: &str, camera: &str, image: &Path) -> Option<PathBuf> {
        let stem = image.file_stem()?.to_string_lossy().to_string();
        match port {
            "gt_depth" => self.depth.as_ref().map(|d| d.join(camera).join(format!("{stem}.exr"))),
            "semantic" => self.semantics.as_ref().map(|d| d.join(camera).join(format!("{stem}.png"))),
            _ => None,
        }
    }

    pub fn gt_depth(&self, camera: &str, image: &Path) -> Result<DepthMap> {
        match self.path("gt_depth", camera, image) {
            None => Ok(DepthMap::new(0, 0)),
            Some(p) => read_depth_exr(&p).with_context(|| format!("ground-truth depth of {}", image.display())),
        }
    }

    pub fn semantic(&self, camera: &str, image: &Path) -> Result<Segmentation> {
        match self.path("semantic", camera, image) {
            None => Ok(Segmentation { width: 0, height: 0, ids: Vec::new() }),
            Some(p) => read_segmentation(&p).with_context(|| format!("semantic map of {}", image.display())),
        }
    }
}

/// The first float32 channel of an EXR as depth (+inf stays: "no surface").
pub fn read_depth_exr(path: &Path) -> Result<DepthMap> {
    use exr::prelude::*;
    let bytes = crate::files::read_input(path, "the depth EXR", crate::checks::MAX_SENSOR_FILE_BYTES)?;
    // The layers' sizes from the header, checked before anything is decoded: a small compressed
    // file may declare 65535 x 65535 pixels.
    let meta = exr::meta::MetaData::read_from_buffered(std::io::Cursor::new(&bytes), false)
        .with_context(|| format!("reading {}", path.display()))?;
    for h in &meta.headers {
        let side = |v: usize| u32::try_from(v).unwrap_or(u32::MAX);
        let at = path.display().to_string();
        crate::checks::image_size(&at, "its size", side(h.layer_size.0), side(h.layer_size.1))
            .map_err(anyhow::Error::msg)?;
    }
    let img = read()
        .no_deep_data()
        .largest_resolution_level()
        .all_channels()
        .first_valid_layer()
        .all_attributes()
        .from_buffered(std::io::Cursor::new(bytes))
        .with_context(|| format!("reading {}", path.display()))?;
    let (w, h): (usize, usize) = img.layer_data.size.into();
    let Some(ch) = img.layer_data.channel_data.list.first() else { bail!("{} has no channel", path.display()) };
    let data = match &ch.sample_data {
        FlatSamples::F32(v) => v.clone(),
        FlatSamples::F16(v) => v.iter().map(|x| x.to_f32()).collect(),
        FlatSamples::U32(_) => bail!("{}: channel {} is u32, not float depth", path.display(), ch.name),
    };
    Ok(DepthMap { width: w as u32, height: h as u32, data })
}

/// An 8-bit single-channel PNG of class ids.
pub fn read_segmentation(path: &Path) -> Result<Segmentation> {
    let bytes = crate::files::read_input(path, "the segmentation", crate::checks::MAX_IMAGE_FILE_BYTES)?;
    let img = image::load_from_memory(&bytes).with_context(|| format!("reading {}", path.display()))?;
    if img.color() != image::ColorType::L8 {
        bail!("{}: a segmentation must be an 8-bit grey PNG of class ids, not {:?}", path.display(), img.color());
    }
    let g = img.into_luma8();
    Ok(Segmentation { width: g.width(), height: g.height(), ids: g.into_raw() })
}
