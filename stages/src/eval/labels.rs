//! Hand labels of real images, and the scores of curated depth against them.
//!
//! The synthetic street has exact ground truth, but a street one draws oneself cannot show
//! what real logs do: the recording car's own hood, white walls and soffits above the LiDAR's
//! reach, sky between leaves. The project's fixtures (`tests/fixtures/real_labels/`) are
//! polygons drawn by hand on the real images of `../shared/data/`, one JSON per image:
//!
//! ```json
//! {"image": "samples/CAM_BACK/x.jpg", "width": 1600, "height": 900,
//!  "regions": [{"class": "ego" | "sky" | "bright_structure", "what": "...", "polygon": [[x, y], ...]}]}
//! ```
//!
//! with vertices in OpenCV's `fillPoly` convention (the pixel (i, j) is the point (i, j));
//! `scripts/show_labels.py` draws them. The scores:
//! - **ego**: the share of labelled ego pixels whose depth is 0 (invalid: masked), and the share
//!   of all other pixels that are 0;
//! - **sky**: the share of labelled sky pixels at the sky depth (within 0.5%);
//! - **bright structure**: the share of labelled bright-structure pixels *not* at the sky depth;
//! - **streak ratio** (no labels): in the top third of the image, sky and invalid pixels left
//!   out, the share of pixels whose depth equals the one below it over the share equal to the one
//!   beside it. A completion that continues columns upward (the LiDAR's top ring carried up into
//!   a facade or a tree crown) leaves vertical runs of one value: a ratio well above 1.

use anyhow::{ensure, Context, Result};
use dist4d_types::artifact::DepthMap;
use serde::Deserialize;
use std::path::Path;

#[derive(Deserialize, Debug, Clone)]
pub struct LabelFile {
    /// The image, relative to the dataset's root.
    pub image: String,
    pub width: u32,
    pub height: u32,
    pub regions: Vec<Region>,
    #[serde(default)]
    pub notes: Option<String>,
}

#[derive(Deserialize, Debug, Clone)]
pub struct Region {
    pub class: String,
    #[serde(default)]
    pub what: String,
    pub polygon: Vec<[f64; 2]>,
}

/// The classes a label file may use.
pub const CLASSES: [&str; 3] = ["ego", "sky", "bright_structure"];

impl LabelFile {
    pub fn read(path: &Path) -> Result<LabelFile> {
        let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
        let f: LabelFile = serde_json::from_str(&text).with_context(|| format!("parsing {}", path.display()))?;
        for (k, r) in f.regions.iter().enumerate() {
            ensure!(CLASSES.contains(&r.class.as_str()), "{}: region {k} has class {:?}", path.display(), r.class);
            ensure!(r.polygon.len() >= 3, "{}: region {k} has {} vertices", path.display(), r.polygon.len());
        }
        Ok(f)
    }

    /// The pixels of the regions of `class`, as 1 in a row-major map.
    pub fn mask(&self, class: &str) -> Vec<u8> {
        let polygons = self.regions.iter().filter(|r| r.class == class).map(|r| &r.polygon);
        crate::polygons::fill_opencv_polygons(self.width, self.height, polygons)
    }
}

/// A share with its counts (`part` of `of`).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Share {
    pub part: u64,
    pub of: u64,
}

impl Share {
    pub fn value(&self) -> Option<f64> {
        (self.of > 0).then(|| self.part as f64 / self.of as f64)
    }
    pub fn add(&mut self, other: Share) {
        self.part += other.part;
        self.of += other.of;
    }
}

impl std::fmt::Display for Share {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self.value() {
            Some(v) => write!(f, "{:.2}% ({} of {})", 100.0 * v, self.part, self.of),
            None => write!(f, "n/a"),
        }
    }
}

/// The scores of one curated depth map against one label file.
#[derive(Debug, Clone, Copy, Default)]
pub struct LabelScores {
    /// Labelled ego pixels with depth 0.
    pub ego_masked: Share,
    /// Pixels not labelled ego with depth 0.
    pub other_masked: Share,
    /// Labelled sky pixels at the sky depth.
    pub sky_at_sky: Share,
    /// Labelled bright-structure pixels not at the sky depth.
    pub bright_not_sky: Share,
}

impl LabelScores {
    pub fn add(&mut self, o: &LabelScores) {
        self.ego_masked.add(o.ego_masked);
        self.other_masked.add(o.other_masked);
        self.sky_at_sky.add(o.sky_at_sky);
        self.bright_not_sky.add(o.bright_not_sky);
    }
}

/// Whether `z` is the sky depth (within 0.5%: the depth maps keep 16 significant bits).
fn at_sky(z: f32, sky_depth: f32) -> bool {
    (z - sky_depth).abs() <= 0.005 * sky_depth
}

pub fn score(labels: &LabelFile, depth: &DepthMap, sky_depth: f32) -> Result<LabelScores> {
    ensure!(
        (depth.width, depth.height) == (labels.width, labels.height),
        "the depth map is {}x{}, the labels of {} are for {}x{}",
        depth.width,
        depth.height,
        labels.image,
        labels.width,
        labels.height
    );
    let (ego, sky, bright) = (labels.mask("ego"), labels.mask("sky"), labels.mask("bright_structure"));
    let mut s = LabelScores::default();
    for (k, &z) in depth.data.iter().enumerate() {
        let masked = z == 0.0;
        if ego[k] != 0 {
            s.ego_masked.of += 1;
            s.ego_masked.part += masked as u64;
        } else {
            s.other_masked.of += 1;
            s.other_masked.part += masked as u64;
        }
        if sky[k] != 0 {
            s.sky_at_sky.of += 1;
            s.sky_at_sky.part += at_sky(z, sky_depth) as u64;
        }
        if bright[k] != 0 {
            s.bright_not_sky.of += 1;
            s.bright_not_sky.part += !at_sky(z, sky_depth) as u64;
        }
    }
    Ok(s)
}

/// The streak ratio of the top third of `depth` (see the module doc); `None` when no pair of
/// neighbours there is equal.
pub fn streak_ratio(depth: &DepthMap, sky_depth: f32) -> Option<f64> {
    let (w, h) = (depth.width as usize, depth.height as usize);
    let usable = |z: f32| z > 0.0 && !at_sky(z, sky_depth);
    let (mut vertical, mut horizontal, mut pairs_v, mut pairs_h) = (0u64, 0u64, 0u64, 0u64);
    for y in 0..h / 3 {
        for x in 0..w {
            let z = depth.data[y * w + x];
            if !usable(z) {
                continue;
            }
            if y + 1 < h && usable(depth.data[(y + 1) * w + x]) {
                pairs_v += 1;
                vertical += (depth.data[(y + 1) * w + x] == z) as u64;
            }
            if x + 1 < w && usable(depth.data[y * w + x + 1]) {
                pairs_h += 1;
                horizontal += (depth.data[y * w + x + 1] == z) as u64;
            }
        }
    }
    if pairs_v == 0 || pairs_h == 0 || horizontal == 0 {
        return (vertical > 0).then_some(f64::INFINITY);
    }
    Some((vertical as f64 / pairs_v as f64) / (horizontal as f64 / pairs_h as f64))
}

/// One labelled image of an export folder, scored.
#[derive(Debug, Clone)]
pub struct ScoredImage {
    /// The label file.
    pub labels: std::path::PathBuf,
    /// The exported depth (relative to the export folder).
    pub depth: String,
    pub scores: LabelScores,
    pub streak_ratio: Option<f64>,
}

/// Scores the curated depth of an export folder (`dist4d run pipelines/curation.ron --out OUT`:
/// its `index.json` names each item's source image and its `encode.npy` depth) against every
/// label file under `labels` whose image the export has. Label files of images the export does
/// not have are skipped (a run over part of a dataset).
pub fn score_export(out: &Path, labels: &Path, sky_depth: f32) -> Result<Vec<ScoredImage>> {
    let index_path = out.join("index.json");
    let index: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(&index_path).with_context(|| format!("reading {}", index_path.display()))?,
    )
    .with_context(|| format!("parsing {}", index_path.display()))?;
    // Source image -> item label (`scene/frame/camera`).
    let mut item_of = std::collections::HashMap::new();
    for (frame_item, v) in index["sources"].as_object().into_iter().flatten() {
        for (camera, c) in v["cameras"].as_object().into_iter().flatten() {
            if let Some(file) = c["file"].as_str() {
                item_of.insert(file.to_string(), format!("{frame_item}/{camera}"));
            }
        }
    }
    let mut depth_of = std::collections::HashMap::new();
    for f in index["files"].as_array().into_iter().flatten() {
        if f["stage"] == "encode" && f["port"] == "npy" {
            if let (Some(item), Some(path)) = (f["item"].as_str(), f["path"].as_str()) {
                depth_of.insert(item.to_string(), path.to_string());
            }
        }
    }
    let mut files = Vec::new();
    let mut stack = vec![labels.to_path_buf()];
    while let Some(dir) = stack.pop() {
        for e in std::fs::read_dir(&dir).with_context(|| format!("listing {}", dir.display()))? {
            let p = e?.path();
            if p.is_dir() {
                stack.push(p);
            } else if p.extension().is_some_and(|x| x == "json") {
                files.push(p);
            }
        }
    }
    files.sort();
    let mut scored = Vec::new();
    for file in files {
        let l = LabelFile::read(&file)?;
        let Some(depth) = item_of.get(&l.image).and_then(|item| depth_of.get(item)) else { continue };
        let bytes = std::fs::read(out.join(depth)).with_context(|| format!("reading {}", out.join(depth).display()))?;
        let (shape, data) = dist4d_types::formats::read_npy_f32(&bytes).with_context(|| format!("reading {depth}"))?;
        ensure!(shape.len() == 2, "{depth}: shape {shape:?}, expected H x W");
        let map = DepthMap { width: shape[1] as u32, height: shape[0] as u32, data };
        scored.push(ScoredImage {
            scores: score(&l, &map, sky_depth)
                .with_context(|| format!("scoring {depth} against {}", file.display()))?,
            streak_ratio: streak_ratio(&map, sky_depth),
            labels: file,
            depth: depth.clone(),
        });
    }
    Ok(scored)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn labels(regions: Vec<(&str, Vec<[f64; 2]>)>) -> LabelFile {
        LabelFile {
            image: "x.jpg".into(),
            width: 10,
            height: 10,
            regions: regions
                .into_iter()
                .map(|(c, polygon)| Region { class: c.into(), what: String::new(), polygon })
                .collect(),
            notes: None,
        }
    }

    #[test]
    fn scores_count_the_labelled_pixels_by_their_depth() {
        // Ego: rows 8-9 (OpenCV convention: the pixel (i, j) is the point (i, j), so the outline of
        // rows 8-9 runs half a pixel outside their centres).
        let l = labels(vec![
            ("ego", vec![[-0.5, 7.5], [9.5, 7.5], [9.5, 9.5], [-0.5, 9.5]]),
            ("sky", vec![[-0.5, -0.5], [9.5, -0.5], [9.5, 1.5], [-0.5, 1.5]]),
            ("bright_structure", vec![[-0.5, 2.5], [4.5, 2.5], [4.5, 4.5], [-0.5, 4.5]]),
        ]);
        assert_eq!(l.mask("ego").iter().filter(|&&v| v == 1).count(), 20);
        let mut d = DepthMap { width: 10, height: 10, data: vec![10.0; 100] };
        for x in 0..10 {
            d.data[80 + x] = 0.0; // row 8 masked, row 9 not
            d.data[x] = 100.0; // row 0 sky, row 1 not
        }
        d.data[30] = 100.0; // one bright pixel taken for sky
        d.data[55] = 0.0; // one scene pixel masked
        let s = score(&l, &d, 100.0).unwrap();
        assert_eq!(s.ego_masked, Share { part: 10, of: 20 });
        assert_eq!(s.other_masked, Share { part: 1, of: 80 });
        assert_eq!(s.sky_at_sky, Share { part: 10, of: 20 });
        assert_eq!(s.bright_not_sky, Share { part: 9, of: 10 });
        assert!(score(&l, &DepthMap::new(5, 5), 100.0).is_err());
    }

    #[test]
    fn columns_of_one_value_make_a_high_streak_ratio() {
        let (w, h) = (30usize, 30usize);
        // Varied in both directions: no equal neighbours but by chance.
        let smooth = DepthMap {
            width: w as u32,
            height: h as u32,
            data: (0..w * h)
                .map(|i| 10.0 + (i % w) as f32 * 0.1 + (i / w) as f32 * 0.07 + ((i * 7) % 3) as f32)
                .collect(),
        };
        let mut streaked = smooth.clone();
        for y in 0..h {
            for x in (0..w).step_by(2) {
                streaked.data[y * w + x] = 20.0 + x as f32; // constant down each even column
            }
        }
        let r = streak_ratio(&streaked, 100.0).unwrap();
        assert!(r > 5.0, "{r}");
        let flat = DepthMap { width: w as u32, height: h as u32, data: vec![12.0; w * h] };
        assert!((streak_ratio(&flat, 100.0).unwrap() - 1.0).abs() < 1e-9, "a flat wall is not streaked");
    }
}
