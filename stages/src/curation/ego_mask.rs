//! `EgoMask`: which pixels of a camera image show the recording vehicle itself (hood, boot,
//! mirrors, pillars), so that no stage takes them for the scene.
//!
//! The ego body is fixed in each camera: a roof LiDAR never sees it (its returns there are the
//! road *behind* the hood, projected through it), so without a mask a completion paints road
//! depth onto the hood, a point cloud gets a hood lying on the road and a novel view carries the
//! car body of the neighbouring camera. The mask says where the body is; the stages that read it
//! (DepthPrompt, EstimateSky, StaticMvsPoints, CompleteDepth) drop samples there, never call it
//! sky and write depth 0 (invalid) there, which every stage that lifts depth to 3D skips.
//!
//! Sources, per camera, first that applies:
//! - `polygons`: polygons in image pixels given in the pipeline, per camera name (a pixel is
//!   masked when its centre lies inside, even-odd rule).
//! - `files`: a mask image per camera name (PNG or JPEG, any non-zero grey value = ego), the size
//!   of the camera's images; a relative path is taken from the working directory. Its bytes are
//!   part of the task key: editing the file reruns what depends on it.
//! - `rig`: a built-in rig, drawn by hand on real images (`ego_rigs/*.json`): `nuscenes` (the
//!   Renault Zoe's boot in CAM_BACK) and `ddad` (TRI's Ford Fusion: hood, mirrors, pillars and
//!   boot in CAMERA_05-09). `auto` (the default) takes the rig that names the camera and has its
//!   image size (nuScenes' CAM_* at 1600x900, DDAD's CAMERA_* at 1936x1216); `none` takes none.
//! - `estimate`: the mask `EstimateEgo` made from the camera's own frames (what stays in place
//!   while the scene moves), when the input is wired and `estimate` is on.
//! - none: an empty mask. A camera of another rig gets none until its polygons or file are given
//!   (or the estimate is wired), and the run says so once, naming the cameras (`unmasked_warnings`).
//!
//! `grow` then widens the mask by whole pixels: JPEG ringing and motion blur put the body's edge
//! a pixel or two into the scene, where a sample of the road would still be wrong.

use dist4d_runtime::Made;
use crate::polygons::{fill_opencv_polygons, fill_polygons, Polygon};
use crate::stage::Stage;
use anyhow::{ensure, Context, Result};
use dist4d_graph::{ParamChecks, ParamProblem, Validate};
use dist4d_runtime::TaskContext;
use dist4d_types::artifact::{Image, ImageInfo, Mask};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// Per camera name: the ego body as polygons in that camera's image pixels.
    pub polygons: BTreeMap<String, Vec<Polygon>>,
    /// Per camera name: a mask image (non-zero = ego), for cameras without polygons.
    pub files: BTreeMap<String, String>,
    /// The built-in rig for cameras without polygons or a file: `auto`, `none`, or a rig's name.
    pub rig: String,
    /// Pixels by which the mask grows (a square neighbourhood), 0-64.
    pub grow: u32,
    /// Whether cameras that no polygons, file or rig cover take the `estimate` input (when wired).
    pub estimate: bool,
}

impl Default for Params {
    fn default() -> Self {
        Params { polygons: BTreeMap::new(), files: BTreeMap::new(), rig: "auto".into(), grow: 1, estimate: true }
    }
}

/// A built-in rig: the ego body in the cameras of one vehicle model, drawn by hand.
#[derive(Deserialize)]
pub struct Rig {
    pub name: String,
    /// What it is and where it was drawn.
    pub what: String,
    /// The vehicles it was drawn for, as the first part of the images' file names
    /// (`n015-2018-07-24-11-22-45+0800__CAM_BACK__1532402927637525.jpg`: nuScenes names a
    /// log's files by the vehicle); empty = any (DGP names its files by timestamp).
    #[serde(default)]
    pub vehicles: Vec<String>,
    /// The same vehicles by the name py123d's logs give them (`vehicle_name` of the ego state).
    #[serde(default)]
    pub vehicle_names: Vec<String>,
    pub width: u32,
    pub height: u32,
    /// Per camera, polygons in OpenCV's `fillPoly` convention (the pixel (i, j) is the point (i, j)).
    pub cameras: BTreeMap<String, Vec<Vec<[f64; 2]>>>,
}

/// The built-in rigs.
pub fn rigs() -> &'static [Rig] {
    static RIGS: std::sync::OnceLock<Vec<Rig>> = std::sync::OnceLock::new();
    RIGS.get_or_init(|| {
        [include_str!("ego_rigs/nuscenes.json"), include_str!("ego_rigs/ddad.json")]
            .iter()
            .map(|text| serde_json::from_str(text).expect("the built-in rigs parse (a unit test reads them)"))
            .collect()
    })
}

impl Rig {
    /// The rig's mask of `camera` at `w` x `h`, if it has the camera at that size.
    fn mask(&self, camera: &str, w: u32, h: u32) -> Option<Vec<u8>> {
        let polygons = self.cameras.get(camera).filter(|_| (self.width, self.height) == (w, h))?;
        Some(fill_opencv_polygons(w, h, polygons))
    }

    /// Whether the rig is the one of the camera of `info`: it names the camera, or a camera of
    /// the same naming (`CAM_FRONT` for nuScenes' rig, which masks only CAM_BACK), at the image's
    /// size, and the image's file names one of its vehicles.
    /// The synthetic world names its files like nuScenes with vehicle `n000`: no rig of a real
    /// car fits it.
    fn fits(&self, info: &ImageInfo) -> bool {
        let family = |c: &str| c.trim_end_matches(|ch: char| ch.is_ascii_digit()).split('_').next().unwrap_or("").to_string();
        let file = info.file.rsplit('/').next().unwrap_or_default();
        let vehicle = match info.vehicle.as_str() {
            // Named by its files (nuScenes) or not at all (DGP).
            "" => self.vehicles.is_empty() || self.vehicles.iter().any(|v| file.starts_with(&format!("{v}-"))),
            // Named by the dataset (a py123d log).
            name => self.vehicle_names.iter().any(|v| v == name) || self.vehicles.is_empty() && self.vehicle_names.is_empty(),
        };
        (self.width, self.height) == (info.width, info.height)
            && self.cameras.keys().any(|c| family(c) == family(&info.camera))
            && vehicle
    }
}

/// Whether `info` is an image of dist4d's synthetic world, whose cameras see no car body.
fn synthetic(info: &ImageInfo) -> bool {
    info.vehicle == "dist4d_synthetic" || info.file.rsplit('/').next().is_some_and(|f| f.starts_with("n000-"))
}

/// The run's note, once, on the cameras of a pipeline's `EgoMask` stages that no source covers
/// (no polygons or file given, and with `rig: auto` no built-in rig fits): their masks are empty,
/// so their car body, if they see one, is taken for the scene. Read from the first frame's images.
pub fn unmasked_warnings(p: &dist4d_graph::Pipeline, dataset: &dyn dist4d_runtime::Dataset) -> Vec<String> {
    use dist4d_runtime::ItemKey;
    use dist4d_types::artifact::Artifact;
    let mut out = Vec::new();
    for node in &p.nodes {
        let Some(stage) = node.stage().filter(|s| s.kind == EgoMask::KIND) else { continue };
        let Some(params) = stage.params.get::<Params>() else { continue };
        if params.rig != "auto" || dataset.count(&ItemKey::new(&[])) == 0 || dataset.count(&ItemKey::new(&[0])) == 0 {
            continue;
        }
        let frame = ItemKey::new(&[0, 0]);
        let mut uncovered = Vec::new();
        for c in 0..dataset.count(&frame) {
            let Ok(bytes) = dataset.load_source("image_info", &ItemKey::new(&[0, 0, c])) else { continue };
            let Ok(info) = ImageInfo::decode(&bytes) else { continue };
            let covered = params.polygons.contains_key(&info.camera)
                || params.files.contains_key(&info.camera)
                || rigs().iter().any(|r| r.fits(&info))
                || synthetic(&info);
            if !covered && info.missing.is_none() {
                uncovered.push(format!("{} ({}x{})", info.camera, info.width, info.height));
            }
        }
        if !uncovered.is_empty() {
            let estimated = params.estimate && stage.inputs.iter().any(|i| i.port == "estimate");
            out.push(if estimated {
                format!(
                    "stage `{}` (EgoMask): no built-in rig fits camera(s) {} of this dataset, and no polygons or mask files are \
                     given: their ego masks are estimated from their frames (what stays in place while the car moves; a car \
                     standing still, or a single frame, gives none: docs/stages.md, EgoMask)",
                    node.name,
                    uncovered.join(", ")
                )
            } else {
                format!(
                    "stage `{}` (EgoMask): no built-in rig fits camera(s) {} of this dataset, and no polygons or mask files are \
                     given: their ego masks are empty, so a car body they see is taken for the scene (give `polygons` or \
                     `files` per camera: docs/stages.md, EgoMask)",
                    node.name,
                    uncovered.join(", ")
                )
            });
        }
    }
    out
}

impl Validate for Params {
    fn validate(&self) -> Vec<ParamProblem> {
        let mut c = ParamChecks::new();
        c.within("grow", self.grow as f64, 0.0, 64.0);
        let mut problems = c.done();
        for (camera, polygons) in &self.polygons {
            for (k, p) in polygons.iter().enumerate() {
                if p.len() < 3 {
                    problems.push(ParamProblem::new(
                        "polygons",
                        format!("polygon {k} of camera {camera:?} has {} vertices; a polygon needs 3 or more", p.len()),
                    ));
                }
                if let Some((x, y)) = p.iter().find(|(x, y)| x.abs() > 1 << 20 || y.abs() > 1 << 20) {
                    problems.push(ParamProblem::new(
                        "polygons",
                        format!("polygon {k} of camera {camera:?} has vertex ({x}, {y}), beyond any image"),
                    ));
                }
            }
        }
        if !matches!(self.rig.as_str(), "auto" | "none") && !rigs().iter().any(|r| r.name == self.rig) {
            let names: Vec<&str> = rigs().iter().map(|r| r.name.as_str()).collect();
            problems.push(ParamProblem::new(
                "rig",
                format!("is {:?}; it is `auto`, `none` or a built-in rig: {}", self.rig, names.join(", ")),
            ));
        }
        for (camera, path) in &self.files {
            if self.polygons.contains_key(camera) {
                problems.push(ParamProblem::new(
                    "files",
                    format!("camera {camera:?} has both polygons and a file ({path}); give one"),
                ));
            }
        }
        problems
    }
}

/// Sets `values` to `to` wherever `mask` is non-zero: what a stage does on the ego body.
pub fn set_where<T: Copy>(values: &mut [T], mask: &[u8], to: T) {
    for (v, &m) in values.iter_mut().zip(mask) {
        if m != 0 {
            *v = to;
        }
    }
}

/// `mask` widened by `by` pixels in every direction (a (2by+1)-square dilation, separable).
pub fn grow(mask: &[u8], w: usize, h: usize, by: usize) -> Vec<u8> {
    if by == 0 || w == 0 || h == 0 {
        return mask.to_vec();
    }
    // A line of `n` values `stride` apart: each is set if a set value lies within `by` of it,
    // from the distance to the last set value seen going each way.
    fn dilate_line(src: &[u8], dst: &mut [u8], start: usize, n: usize, stride: usize, by: usize) {
        let mut since = usize::MAX;
        for k in 0..n {
            since = if src[start + k * stride] != 0 { 0 } else { since.saturating_add(1) };
            dst[start + k * stride] = (since <= by) as u8;
        }
        since = usize::MAX;
        for k in (0..n).rev() {
            since = if src[start + k * stride] != 0 { 0 } else { since.saturating_add(1) };
            dst[start + k * stride] |= (since <= by) as u8;
        }
    }
    let mut rows = vec![0u8; w * h];
    for y in 0..h {
        dilate_line(mask, &mut rows, y * w, w, 1, by);
    }
    let mut out = vec![0u8; w * h];
    for x in 0..w {
        dilate_line(&rows, &mut out, x, h, w, by);
    }
    out
}

/// A mask image file as 0/1, checked against the camera's image size.
fn read_mask_file(path: &str, camera: &str, w: u32, h: u32) -> Result<Vec<u8>> {
    let bytes = std::fs::read(path).with_context(|| format!("reading the ego mask of camera {camera}: {path}"))?;
    let image = image::load_from_memory(&bytes)
        .with_context(|| format!("decoding the ego mask of camera {camera}: {path}"))?
        .to_luma8();
    ensure!(
        image.dimensions() == (w, h),
        "the ego mask of camera {camera} ({path}) is {}x{}, but the camera's images are {w}x{h}",
        image.width(),
        image.height()
    );
    Ok(image.into_raw().into_iter().map(|v| (v != 0) as u8).collect())
}

/// The camera's image with the mask tinted red and outlined, for a look at it.
pub fn preview(image: &Image, mask: &Mask) -> Image {
    let (w, h) = (image.width as usize, image.height as usize);
    let mut rgb = image.rgb.clone();
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            if mask.data[i] == 0 {
                continue;
            }
            let edge = [(x > 0, i.wrapping_sub(1)), (x + 1 < w, i + 1), (y > 0, i.wrapping_sub(w)), (y + 1 < h, i + w)]
                .iter()
                .any(|&(inside, j)| inside && mask.data[j] == 0);
            let px = &mut rgb[3 * i..3 * i + 3];
            if edge {
                px.copy_from_slice(&[255, 32, 32]);
            } else {
                px[0] = ((px[0] as u16 + 255) / 2) as u8;
                px[1] /= 2;
                px[2] /= 2;
            }
        }
    }
    Image { width: image.width, height: image.height, rgb }
}

crate::inputs! {
    pub struct Inputs {
        /// the camera and its image size (dataset.image_info)
        info: One<ImageInfo>,
        /// the image, for the preview only
        image: Optional<Image>,
        /// the body estimated from the camera's frames (EstimateEgo.mask), for cameras that no
        /// polygons, file or rig cover
        estimate: Optional<Mask>,
    }
}

crate::outputs! {
    pub struct Outputs {
        /// 1 = the ego vehicle's body
        mask: One<Mask>,
        /// the image with the mask tinted red (an empty image when `image` is not wired); made
        /// only when the run reads it
        preview: OnDemand<Image>,
    }
}

pub struct EgoMask(Params);

impl Stage for EgoMask {
    const KIND: &'static str = "EgoMask";
    const VERSION: u32 = 2;
    const SUMMARY: &'static str =
        "Camera -> the pixels of the ego vehicle's body (per-camera polygons, mask files, a built-in rig or the estimate)";
    const GRAINS: &'static [&'static str] = &["camera"];
    type Params = Params;
    type Inputs = Inputs;
    type Outputs = Outputs;
    fn new(params: Params) -> Result<Self> {
        Ok(EgoMask(params))
    }
    /// The mask files' bytes decide the outputs too.
    fn identity(&self) -> Result<Option<String>> {
        if self.0.files.is_empty() {
            return Ok(None);
        }
        let mut text = String::new();
        for (camera, path) in &self.0.files {
            let bytes = std::fs::read(path).with_context(|| format!("reading the ego mask of camera {camera}: {path}"))?;
            text += &format!("{camera}={}\n", blake3::hash(&bytes).to_hex());
        }
        Ok(Some(text))
    }
    fn run(&self, ctx: &TaskContext, i: Inputs) -> Result<Made<Outputs>> {
        let (w, h, camera) = (i.info.width, i.info.height, i.info.camera.as_str());
        let drawn = if let Some(polygons) = self.0.polygons.get(camera) {
            fill_polygons(w, h, polygons)
        } else if let Some(path) = self.0.files.get(camera) {
            read_mask_file(path, camera, w, h)?
        } else {
            let rig = match self.0.rig.as_str() {
                "none" => None,
                "auto" => rigs().iter().find(|r| r.fits(&i.info)),
                name => rigs().iter().find(|r| r.name == name),
            };
            let estimate = i.estimate.as_ref().filter(|e| self.0.estimate && e.width > 0);
            match (rig, estimate) {
                // A camera of the rig that shows nothing of the body (CAM_FRONT) gets an empty mask.
                (Some(r), _) => r.mask(camera, w, h).unwrap_or_else(|| vec![0; w as usize * h as usize]),
                (None, Some(e)) => {
                    ensure!(
                        (e.width, e.height) == (w, h),
                        "the estimated ego mask of camera {camera} is {}x{}, its images {w}x{h}",
                        e.width,
                        e.height
                    );
                    e.data.clone()
                }
                (None, None) => vec![0; w as usize * h as usize],
            }
        };
        let data = grow(&drawn, w as usize, h as usize, self.0.grow as usize);
        let mask = Mask { width: w, height: h, data };
        let preview = match &i.image {
            _ if !ctx.wants("preview") => None,
            Some(image) if image.width > 0 => {
                ensure!(
                    (image.width, image.height) == (w, h),
                    "the image of camera {camera} is {}x{}, its info says {w}x{h}",
                    image.width,
                    image.height
                );
                Some(preview(image, &mask))
            }
            _ => Some(Image { width: 0, height: 0, rgb: Vec::new() }),
        };
        Ok(Outputs { mask, preview }.into())
    }
}

/// Checks a mask wired into a stage against the image size and returns its data, or `None`
/// when it is not wired (or empty: a dataset item without an image).
pub fn wired<'m>(mask: Option<&'m Mask>, w: u32, h: u32, what: &str) -> Result<Option<&'m [u8]>> {
    match mask {
        Some(m) if m.width > 0 && m.height > 0 => {
            ensure!(
                (m.width, m.height) == (w, h),
                "the ego mask is {}x{} but the {what} is {w}x{h}",
                m.width,
                m.height
            );
            Ok(Some(&m.data))
        }
        _ => Ok(None),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn growing_widens_by_whole_pixels_in_every_direction() {
        let (w, h) = (9, 7);
        let mut m = vec![0u8; w * h];
        m[3 * w + 4] = 1;
        let g = grow(&m, w, h, 2);
        for y in 0..h {
            for x in 0..w {
                let near = (x as i32 - 4).abs() <= 2 && (y as i32 - 3).abs() <= 2;
                assert_eq!(g[y * w + x] == 1, near, "({x}, {y})");
            }
        }
        assert_eq!(grow(&m, w, h, 0), m);
        // At the border.
        let mut c = vec![0u8; w * h];
        c[0] = 1;
        assert_eq!(grow(&c, w, h, 1).iter().filter(|&&v| v == 1).count(), 4);
    }

    fn info(camera: &str, w: u32, h: u32) -> ImageInfo {
        ImageInfo { camera: camera.into(), width: w, height: h, ..Default::default() }
    }

    fn run(params: Params, info: ImageInfo, image: Option<Image>) -> Result<Outputs> {
        let ctx = TaskContext { item: Default::default(), seed: 0, label: "s/0/c", unread: &[] };
        EgoMask::new(params)?.run(&ctx, Inputs { info, image, estimate: None }).map(Made::unwrap)
    }

    #[test]
    fn each_camera_takes_its_own_polygons_or_file_and_the_others_are_empty() {
        let mut params = Params { grow: 0, ..Default::default() };
        params.polygons.insert("CAM_BACK".into(), vec![vec![(0, 6), (8, 6), (8, 8), (0, 8)]]);
        let back = run(params.clone(), info("CAM_BACK", 8, 8), None).unwrap();
        assert_eq!(back.mask.data.iter().filter(|&&v| v == 1).count(), 16);
        assert_eq!(back.preview.unwrap().width, 0);
        let front = run(params.clone(), info("CAM_FRONT", 8, 8), None).unwrap();
        assert!(front.mask.data.iter().all(|&v| v == 0));

        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("m.png");
        let mut png = image::GrayImage::new(8, 8);
        png.put_pixel(3, 7, image::Luma([255]));
        png.save(&path).unwrap();
        params.files.insert("CAM_FRONT".into(), path.display().to_string());
        let front = run(params.clone(), info("CAM_FRONT", 8, 8), None).unwrap();
        assert_eq!(front.mask.data.iter().position(|&v| v == 1), Some(7 * 8 + 3));
        let id = EgoMask::new(params.clone()).unwrap().identity().unwrap().unwrap();
        png.put_pixel(4, 7, image::Luma([255]));
        png.save(&path).unwrap();
        assert_ne!(EgoMask::new(params.clone()).unwrap().identity().unwrap().unwrap(), id, "the file is in the key");

        // A file of the wrong size, or none, is an error naming the camera and the file.
        let e = run(params.clone(), info("CAM_FRONT", 16, 8), None).err().unwrap().to_string();
        assert!(e.contains("CAM_FRONT") && e.contains("is 8x8") && e.contains("16x8"), "{e}");
        params.files.insert("CAM_FRONT".into(), dir.path().join("gone.png").display().to_string());
        let e = format!("{:#}", run(params, info("CAM_FRONT", 8, 8), None).err().unwrap());
        assert!(e.contains("CAM_FRONT") && e.contains("gone.png"), "{e}");
    }

    #[test]
    fn the_built_in_rigs_parse_and_auto_takes_the_one_of_the_cameras_names_and_size() {
        assert_eq!(rigs().iter().map(|r| r.name.as_str()).collect::<Vec<_>>(), ["nuscenes", "ddad"]);
        let count = |params: &Params, camera: &str, w: u32, h: u32| {
            let file = if camera.starts_with("CAM") {
                format!("samples/{camera}/n015-2018-07-24-11-22-45+0800__{camera}__1532402927637525.jpg")
            } else {
                format!("scene_02/rgb/{camera}/15616458249936530.jpg")
            };
            let info = ImageInfo { file, ..info(camera, w, h) };
            run(params.clone(), info, None).unwrap().mask.data.iter().filter(|&&v| v == 1).count()
        };
        let auto = Params { grow: 0, ..Default::default() };
        // nuScenes: the boot along CAM_BACK's bottom rows, nothing in CAM_FRONT.
        let boot = count(&auto, "CAM_BACK", 1600, 900);
        assert!(boot > 20_000 && boot < 80_000, "{boot}");
        assert_eq!(count(&auto, "CAM_FRONT", 1600, 900), 0);
        // DDAD: the hood of CAMERA_05; CAMERA_01 sees none of the car.
        assert!(count(&auto, "CAMERA_05", 1936, 1216) > 50_000);
        assert_eq!(count(&auto, "CAMERA_01", 1936, 1216), 0);
        // Another size or naming is another rig: no mask.
        assert_eq!(count(&auto, "CAM_BACK", 800, 450), 0);
        assert_eq!(count(&auto, "CAMERA_05", 1600, 900), 0);
        assert_eq!(count(&auto, "pcam_b0", 1600, 900), 0);
        // The synthetic world's files (vehicle n000) are no real car's.
        let synthetic = ImageInfo { file: "samples/CAM_BACK/n000-2018-01-01-00-00-00+0000__CAM_BACK__1.jpg".into(), ..info("CAM_BACK", 1600, 900) };
        assert!(run(auto.clone(), synthetic, None).unwrap().mask.data.iter().all(|&v| v == 0));
        // A py123d log names its vehicle apart from its files.
        let logged = |vehicle: &str| ImageInfo {
            file: "nuscenes-mini_train/scene-0061/camera.pcam_b0.arrow".into(),
            vehicle: vehicle.into(),
            ..info("CAM_BACK", 1600, 900)
        };
        let masked = |i: ImageInfo| run(auto.clone(), i, None).unwrap().mask.data.iter().filter(|&&v| v > 0).count();
        assert_eq!(masked(logged("nuscenes_renault_zoe")), boot);
        assert_eq!(masked(logged("dist4d_synthetic")), 0);
        let none = Params { rig: "none".into(), ..auto.clone() };
        assert_eq!(count(&none, "CAM_BACK", 1600, 900), 0);
        // Polygons given for a camera replace the rig's.
        let mut own = auto.clone();
        own.polygons.insert("CAM_BACK".into(), vec![vec![(0, 0), (10, 0), (10, 10)]]);
        assert!(count(&own, "CAM_BACK", 1600, 900) < 100);
        let bad = Params { rig: "zoe".into(), ..auto };
        assert!(format!("{:?}", bad.validate()).contains("nuscenes, ddad"));
    }

    #[test]
    fn the_estimate_masks_only_the_cameras_that_nothing_else_covers() {
        let ctx = TaskContext { item: Default::default(), seed: 0, label: "s/0/c", unread: &[] };
        let estimate = Mask { width: 8, height: 8, data: (0..64).map(|i| (i >= 56) as u8).collect() };
        let mut params = Params { grow: 0, ..Default::default() };
        params.polygons.insert("CAM_BACK".into(), vec![vec![(0, 0), (8, 0), (8, 1), (0, 1)]]);
        let masked = |params: &Params, camera: &str, estimate: Option<Mask>| {
            let out = EgoMask::new(params.clone()).unwrap().run(&ctx, Inputs { info: info(camera, 8, 8), image: None, estimate });
            let mask = out.map(|o| o.unwrap().mask);
            mask.map(|m| (0..64).filter(|&i| m.data[i] == 1).collect::<Vec<usize>>())
        };
        // Polygons win; a camera without takes the estimate's bottom row.
        assert_eq!(masked(&params, "CAM_BACK", Some(estimate.clone())).unwrap(), (0..8).collect::<Vec<_>>());
        assert_eq!(masked(&params, "CAM_FRONT", Some(estimate.clone())).unwrap(), (56..64).collect::<Vec<_>>());
        // Turned off, unwired, or empty (a camera item without an image): none.
        let off = Params { estimate: false, ..params.clone() };
        assert!(masked(&off, "CAM_FRONT", Some(estimate.clone())).unwrap().is_empty());
        assert!(masked(&params, "CAM_FRONT", None).unwrap().is_empty());
        assert!(masked(&params, "CAM_FRONT", Some(Mask { width: 0, height: 0, data: vec![] })).unwrap().is_empty());
        // A built-in rig that fits the camera wins over the estimate, even where it masks nothing.
        let front = ImageInfo {
            file: "samples/CAM_FRONT/n015-2018-07-24-11-22-45+0800__CAM_FRONT__1532402927637525.jpg".into(),
            ..info("CAM_FRONT", 1600, 900)
        };
        let big = Mask { width: 1600, height: 900, data: vec![1; 1600 * 900] };
        let out = EgoMask::new(Params::default()).unwrap().run(&ctx, Inputs { info: front, image: None, estimate: Some(big) }).unwrap().unwrap();
        assert!(out.mask.data.iter().all(|&v| v == 0));
        // An estimate of another size is an error naming the camera.
        let e = masked(&params, "CAM_FRONT", Some(Mask { width: 4, height: 4, data: vec![0; 16] })).err().unwrap().to_string();
        assert!(e.contains("CAM_FRONT") && e.contains("4x4"), "{e}");
    }

    #[test]
    fn the_preview_tints_the_mask_and_outlines_it() {
        let mut params = Params { grow: 0, ..Default::default() };
        params.polygons.insert("C".into(), vec![vec![(0, 2), (4, 2), (4, 4), (0, 4)]]);
        let image = Image { width: 4, height: 4, rgb: vec![100; 48] };
        let out = run(params, info("C", 4, 4), Some(image.clone())).unwrap();
        let shown = out.preview.unwrap();
        assert_eq!(&shown.rgb[..24], &image.rgb[..24], "outside is untouched");
        assert_eq!(&shown.rgb[3 * 8..3 * 8 + 3], &[255, 32, 32], "the mask's edge is red");
        let bad = Image { width: 5, height: 4, rgb: vec![0; 60] };
        assert!(run(Params::default(), info("C", 4, 4), Some(bad)).is_err());
    }

    #[test]
    fn bad_polygons_are_param_problems() {
        let mut p = Params::default();
        p.polygons.insert("C".into(), vec![vec![(0, 0), (1, 1)]]);
        p.files.insert("C".into(), "x.png".into());
        let problems: Vec<String> = p.validate().iter().map(|q| format!("{q:?}")).collect();
        assert_eq!(problems.len(), 2, "{problems:?}");
    }
}
