//! `GenerateFuture`: DiST-T's task (paper Sec. 3.2): from a reference frame's multi-camera RGB-D
//! and the control signals of the future (where each camera will be along the ego's future
//! trajectory, the 3D boxes then), the RGB-D of every camera at t+1..t+k, one variant per step.
//!
//! The learned model runs as an external worker (op `generate_future`, docs/workers.md). The
//! built-in baseline keeps the pipeline runnable without one, and is named a baseline: every
//! reference camera's curated RGB-D is drawn into the camera at its future pose
//! ([`crate::views::splat`]), objects that moved drawn where their box is then (the same
//! box-track motion as the DiST-S pairs, [`crate::views::moving`]), the sky (the curation's
//! 100 m) drawn as directions from the future camera (it does not come nearer as the ego drives
//! on), and the holes filled background first ([`crate::views::fill`]). What the reference frame
//! never saw (the road ahead past its field of view, the far side of an object) is a smear;
//! docs/BENCHMARKS.md scores it per step against the synthetic world.
//!
//! The controls come in as the future item's `ImageInfo` (`Offset("dataset.image_info", frame,
//! variant)`): its pose, calibration and boxes, never its pixels.

use dist4d_runtime::Made;
use crate::model_worker::{npy_rgb8, read_npy_rgb8, worker_depth, Exchange, ModelWorker, WorkerSpec};
use crate::lift::{focal_of, liftable, LiftParams};
use crate::stage::{variant_of, Stage};
use crate::views::fill::fill;
use crate::views::frames::{camera_views, frame_record, info_view, view_of};
use crate::views::moving::{split, Moving, Piece};
use crate::views::splat::{draw_sky, lift_source, reproject, PinholeView, RgbdView, SplatParams};
use anyhow::{ensure, Context, Result};
use dist4d_graph::{ParamChecks, ParamProblem, Validate, VariantPlan, Variants};
use dist4d_runtime::TaskContext;
use dist4d_types::artifact::{DepthMap, File, Image, ImageInfo, Mask, Pose};
use dist4d_types::formats::npy_f32;
use serde::{Deserialize, Serialize};
use serde_json::json;
use std::collections::BTreeMap;

/// One generated step.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct Step {
    /// Frames after the reference frame (of the dataset's clock: keyframes, or 12 Hz rounds).
    pub offset: i32,
}

impl Default for Step {
    fn default() -> Self {
        Step { offset: 1 }
    }
}

#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// The steps generated per reference frame, by label (labels name the exported files).
    pub variants: BTreeMap<String, Step>,
    /// Objects that move between the reference and the step: by default drawn where their box is
    /// at the step's time (the boxes are controls).
    pub moving: Moving,
    /// Depths at least this are sky (the curation sets the sky to 100 m): drawn as directions from
    /// the future camera, and given this depth there.
    pub sky_depth: f32,
    /// The hole filling's background tolerance ([`crate::views::fill`]).
    pub background_tolerance: f32,
    pub splat: SplatParams,
    /// Which reference pixels are drawn ([`crate::lift`]; its `sky_depth` is this stage's).
    pub lift: LiftParams,
    /// Metres on the surface (support px times depth over the focal length) from the nearest
    /// prompt sample beyond which a drawn pixel is not `trusted` (when `supports` are wired): the
    /// view draws it (a hole filled in is worse to look at), the `trusted` mask, and with it the
    /// bullet-time cloud, leaves it out. 0 = every drawn pixel is trusted.
    pub trusted_support_m: f32,
    /// DiST-T (or any future-frame generator) as an external worker in place of the baseline:
    /// `Some((program: "python3", args: ["my_dist_t.py"]))`, op `generate_future`
    /// (docs/workers.md). Its name, version and weights enter the task keys.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub worker: Option<WorkerSpec>,
}

impl Default for Params {
    fn default() -> Self {
        let step = |offset| Step { offset };
        Params {
            variants: [("t+1".to_string(), step(1)), ("t+2".to_string(), step(2)), ("t+3".to_string(), step(3))]
                .into_iter()
                .collect(),
            moving: Moving::Follow,
            sky_depth: 100.0,
            background_tolerance: 0.1,
            splat: SplatParams::default(),
            lift: LiftParams::default(),
            trusted_support_m: 0.2,
            worker: None,
        }
    }
}

impl Validate for Params {
    fn validate(&self) -> Vec<ParamProblem> {
        let mut c = ParamChecks::new();
        let labels: Vec<String> = self.variants.keys().cloned().collect();
        c.path_names("variants", &labels);
        c.check(!self.variants.is_empty(), "variants", || "names no step".into());
        for (label, s) in &self.variants {
            c.check((1..=1000).contains(&s.offset), "variants", || {
                format!("`{label}`: `offset` is a step into the future, 1..=1000 frames, found {}", s.offset)
            });
        }
        c.above("sky_depth", self.sky_depth as f64, 0.0, 1e6).within(
            "background_tolerance",
            self.background_tolerance as f64,
            0.0,
            10.0,
        );
        self.splat.check(&mut c);
        self.lift.check(&mut c);
        c.within("trusted_support_m", self.trusted_support_m as f64, 0.0, 1e6);
        if let Some(w) = &self.worker {
            w.check(&mut c);
        }
        c.done()
    }
}

crate::inputs! {
    pub struct Inputs {
        /// the reference frame's images, every camera (`Across("dataset.image", camera)`)
        images: Many<Image>,
        /// their curated dense depth (`Across("complete.depth", camera)`)
        depths: Many<DepthMap>,
        /// what each image is and where it was taken, with the boxes at its time
        infos: Many<ImageInfo>,
        /// the controls of this camera at the step: `Offset("dataset.image_info", frame, variant)`
        /// (its pose on the future trajectory, calibration and the boxes then; not its pixels)
        target_info: One<ImageInfo>,
        /// their support maps (`Across("complete.support", camera)`, px to the nearest prompt
        /// sample): when wired, pixels beyond `lift.max_support_px` are not drawn
        supports: OptionalMany<DepthMap>,
        /// the bird's-eye-view layout at the step (`BevLayout`: road and boxes), for a worker;
        /// the baseline does not read it
        layout: Optional<Image>,
    }
}

crate::outputs! {
    pub struct Outputs {
        /// the generated image of this camera at the step
        image: One<Image>,
        /// the generated metric depth (m), the sky at `sky_depth`
        depth: One<DepthMap>,
        /// 1 where the reference frame saw what is drawn (the baseline's warp landed), 0 where it
        /// was filled in; all 1 from a worker
        mask: One<Mask>,
        /// the part of `mask` drawn from reference pixels within `trusted_support_m` of a prompt
        /// sample (all of `mask` without `supports` or from a worker): what a bullet-time cloud
        /// makes points of
        trusted: One<Mask>,
        /// the camera's ego pose at the step (its time included): where the view was generated
        pose: One<Pose>,
        /// JSON: the reference frame, the step, and the view's camera, time and pose
        record: One<File>,
    }
}

pub struct GenerateFuture(Params, ModelWorker);

impl Stage for GenerateFuture {
    const KIND: &'static str = "GenerateFuture";
    // 2: a record of each view; the sky's depth exactly `sky_depth` after the fill.
    // 3: the reference depth lifted by the shared rule (crate::lift): no flying pixels.
    // 4: the `trusted` mask (support in metres).
    const VERSION: u32 = 4;
    const SUMMARY: &'static str =
        "DiST-T: future multi-camera RGB-D per step from a reference frame and controls (worker, or a warp baseline)";
    const GRAINS: &'static [&'static str] = &["variant"];
    const VARIANTS: bool = true;
    type Params = Params;
    type Inputs = Inputs;
    type Outputs = Outputs;

    fn new(params: Params) -> Result<Self> {
        let worker = ModelWorker::new(params.worker.clone());
        Ok(GenerateFuture(params, worker))
    }
    fn identity(&self) -> Result<Option<String>> {
        self.1.identity()
    }
    fn resource(&self) -> Option<dist4d_runtime::Resource> {
        self.1.resource()
    }
    fn variants(params: &Params) -> Option<Variants> {
        Variants::split_planned(
            params,
            |p| std::mem::take(&mut p.variants),
            |s| VariantPlan { offset: s.offset, unused: Vec::new(), needs: Vec::new() },
        )
    }

    fn run(&self, ctx: &TaskContext, i: Inputs) -> Result<Made<Outputs>> {
        let (label, step) = variant_of(ctx, &self.0.variants)?;
        let target = &i.target_info;
        let view = info_view(target).context("the step's camera")?;
        let references = references(&i)?;
        let pose = Pose { ego_to_world: target.ego_to_world, timestamp_us: target.timestamp_us };
        let (image, depth, mask, trusted) = if self.1.is_set() {
            let (image, depth, mask) =
                generate_by_worker(ctx, &self.1, &references, target, i.layout.as_ref(), &view, label, step.offset)?;
            let trusted = mask.clone();
            (image, depth, mask, trusted)
        } else {
            warp_baseline(&self.0, &references, target, &view)?
        };
        let seen = mask.data.iter().filter(|&&m| m != 0).count() as f64 / mask.data.len().max(1) as f64;
        let reference = references.iter().find(|r| r.info.camera == target.camera).unwrap_or(&references[0]).info;
        let record = json!({
            "kind": "dist_t",
            "scene": target.scene,
            "camera": target.camera,
            "reference_frame": reference.frame,
            "reference_timestamp_us": reference.timestamp_us,
            "step": label,
            "offset": step.offset,
            "generator": if self.1.is_set() { "worker" } else { "warp baseline" },
            "seen": seen,
            "view": step_record(target, &view),
        });
        Ok(Outputs { image, depth, mask, trusted, pose, record: File(serde_json::to_vec_pretty(&record)?) }.into())
    }
}

/// What a generated view is: the camera, the frame and time of the step, intrinsics, size and
/// poses. Not the future image's token or file: a generator must not find the answer by it.
fn step_record(target: &ImageInfo, view: &PinholeView) -> serde_json::Value {
    let mut r = frame_record(target, view);
    if let Some(o) = r.as_object_mut() {
        o.remove("token");
        o.remove("image");
    }
    r
}

/// One reference camera: its image, depth (and support map, when wired), info and camera.
struct Reference<'a> {
    image: &'a Image,
    depth: &'a DepthMap,
    support: Option<&'a DepthMap>,
    info: &'a ImageInfo,
    view: PinholeView,
}

/// The reference cameras that have an image, matched by position.
fn references(i: &Inputs) -> Result<Vec<Reference<'_>>> {
    ensure!(
        i.supports.is_empty() || i.supports.len() == i.depths.len(),
        "`supports` holds {} items and `depths` {}: wire them with the same selector (Across(.., camera))",
        i.supports.len(),
        i.depths.len()
    );
    let mut out = Vec::new();
    for (image, depth, info) in camera_views(&i.images, &i.depths, &i.infos, "`images`, `depths` and `infos`")? {
        let view = view_of(info, image, depth).with_context(|| format!("the reference {}", info.camera))?;
        // The support map of the same camera (the same position as its depth).
        let pos = i.depths.iter().find(|(_, d)| std::ptr::eq(d, depth)).map(|(p, _)| *p);
        let support = match pos {
            Some(pos) if !i.supports.is_empty() => {
                let s = i.supports.iter().find(|(p, _)| *p == pos).map(|(_, s)| s).with_context(|| {
                    format!("`supports` has nothing at the position of the reference {}", info.camera)
                })?;
                ensure!(
                    (s.width, s.height) == (depth.width, depth.height),
                    "the reference {}: support map {}x{} and depth {}x{} differ in size",
                    info.camera,
                    s.width,
                    s.height,
                    depth.width,
                    depth.height
                );
                Some(s)
            }
            _ => None,
        };
        out.push(Reference { image, depth, support, info, view });
    }
    ensure!(!out.is_empty(), "the reference frame has no camera image");
    Ok(out)
}

/// The built-in baseline of the module doc, with the `trusted` mask.
fn warp_baseline(
    p: &Params,
    refs: &[Reference],
    target: &ImageInfo,
    view: &PinholeView,
) -> Result<(Image, DepthMap, Mask, Mask)> {
    let (w, h) = (view.width, view.height);
    let lift = LiftParams { sky_depth: p.sky_depth, ..p.lift.clone() };
    // Surfaces: every reference camera's liftable depth (crate::lift: no edges' far sides, no
    // sky, no unsupported pixels), split into the static rest and the objects that moved by the
    // step's time; the sky apart, drawn as directions.
    // Of each piece, the pixels with support in metres (`trusted_support_m`), when that asks
    // anything: drawn again on their own, they mark where the view shows a trusted surface.
    let strict = (p.trusted_support_m > 0.0 && refs.iter().any(|r| r.support.is_some()))
        .then(|| LiftParams { max_support_m: p.trusted_support_m, ..lift.clone() });
    let mut pieces = Vec::new();
    let mut trusted_pieces = Vec::new();
    let mut skies = Vec::new();
    for r in refs {
        let support = r.support.map(|s| &s.data[..]);
        let (surface, sky) = lift_source(&r.depth.data, &r.view, support, &lift);
        let (parts, _) = split(&surface, &r.view, &r.info.boxes.boxes, &target.boxes.boxes, p.moving);
        if let Some(strict) = &strict {
            let keep = liftable(&r.depth.data, r.view.width as usize, r.view.height as usize, focal_of(&r.view.k), support, strict);
            for piece in &parts {
                let depth = piece.depth.iter().zip(&keep).map(|(&z, &k)| if k { z } else { 0.0 }).collect();
                trusted_pieces.push((r.image, Piece { depth, view: piece.view }));
            }
        }
        pieces.extend(parts.into_iter().map(|piece| (r.image, piece)));
        skies.push((r.image, sky, r.view));
    }
    fn rgbd<'a>(pieces: &'a [(&'a Image, Piece)]) -> Vec<RgbdView<'a>> {
        pieces.iter().map(|(image, piece)| RgbdView { rgb: &image.rgb, depth: &piece.depth, view: &piece.view }).collect()
    }
    let splat = SplatParams { max_depth: f32::MAX, ..p.splat.clone() };
    let mut surfaces = reproject(&rgbd(&pieces), view, &splat)?;
    // Trusted where the nearest surface drawn is a trusted one: both drawings agree there.
    let trusted: Vec<u8> = if strict.is_some() {
        let t = reproject(&rgbd(&trusted_pieces), view, &splat)?;
        (0..surfaces.valid.len())
            .map(|k| {
                let (a, b) = (surfaces.depth[k], t.depth[k]);
                (surfaces.valid[k] != 0 && t.valid[k] != 0 && (a - b).abs() <= p.splat.surface_tolerance * a) as u8
            })
            .collect()
    } else {
        surfaces.valid.clone()
    };
    let sky_views: Vec<RgbdView> =
        skies.iter().map(|(image, sky, v)| RgbdView { rgb: &image.rgb, depth: sky, view: v }).collect();
    draw_sky(&mut surfaces, &sky_views, view, &splat, p.sky_depth)?;
    let valid: Vec<bool> = surfaces.valid.iter().map(|&v| v != 0).collect();
    let mask = Mask { width: w, height: h, data: surfaces.valid };
    let (rgb, mut depth) = fill(&surfaces.rgb, &surfaces.depth, &valid, w as usize, h as usize, p.background_tolerance);
    // The fill averages neighbours: a hole in the sky comes out at 100.000015, not 100.
    for z in depth.iter_mut().filter(|z| lift.is_sky(**z)) {
        *z = p.sky_depth;
    }
    Ok((
        Image { width: w, height: h, rgb },
        DepthMap { width: w, height: h, data: depth },
        mask,
        Mask { width: w, height: h, data: trusted },
    ))
}

/// The step generated by the stage's worker (op `generate_future`): inputs `image_<i>` (NPY uint8
/// H x W x 3) and `depth_<i>` (NPY float32 H x W) per reference camera, in the order of
/// `controls.json`'s `reference` list, `controls` (JSON: the step, every reference camera's
/// record and boxes, and the target's) and, when wired, `layout` (NPY uint8 S x S x 3, the BEV
/// layout at the step); outputs `image` and `depth` at the target's size, checked (shape,
/// finite, not negative).
#[allow(clippy::too_many_arguments)]
fn generate_by_worker(
    ctx: &TaskContext,
    worker: &ModelWorker,
    refs: &[Reference],
    target: &ImageInfo,
    layout: Option<&Image>,
    view: &PinholeView,
    label: &str,
    offset: i32,
) -> Result<(Image, DepthMap, Mask)> {
    let (w, h) = (view.width, view.height);
    let ex = Exchange::new()?;
    let mut inputs = Vec::new();
    let mut reference = Vec::new();
    // The reference frame is the same for every camera and step of it: written once for the
    // requests in flight, named by digest (a worker may cache what it decoded by path too).
    let mut held = Vec::new();
    for (k, r) in refs.iter().enumerate() {
        let (rw, rh) = (r.image.width, r.image.height);
        let (image, a) = worker.put_shared(&format!("image_{k}"), "npy", &npy_rgb8(rw, rh, &r.image.rgb))?;
        let (depth, b) =
            worker.put_shared(&format!("depth_{k}"), "npy", &npy_f32(&[rh as usize, rw as usize], &r.depth.data))?;
        inputs.extend([image, depth]);
        held.extend([a, b]);
        let mut record = frame_record(r.info, &r.view);
        record["boxes"] = serde_json::to_value(&r.info.boxes.boxes)?;
        reference.push(record);
    }
    let mut target_record = step_record(target, view);
    target_record["boxes"] = serde_json::to_value(&target.boxes.boxes)?;
    let controls = json!({ "step": label, "offset": offset, "reference": reference, "target": target_record });
    inputs.push(ex.put("controls", "controls.json", &serde_json::to_vec_pretty(&controls)?)?);
    if let Some(l) = layout {
        inputs.push(ex.put("layout", "layout.npy", &npy_rgb8(l.width, l.height, &l.rgb))?);
    }
    let params = json!({ "step": label, "offset": offset, "camera": target.camera });
    let outputs = worker.call(ctx, &ex, "generate_future", inputs, params)?;
    drop(held);
    let rgb = read_npy_rgb8(&ex.get(&outputs, "image")?, w, h).context("the worker's `image`")?;
    let data = worker_depth(&ex, &outputs, "depth", w, h)?;
    Ok((
        Image { width: w, height: h, rgb },
        DepthMap { width: w, height: h, data },
        Mask { width: w, height: h, data: vec![1; (w * h) as usize] },
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::views::splat::PinholeView;
    use dist4d_types::artifact::Boxes3D;
    use dist4d_types::geometry::Se3;
    use glam::DVec3;

    /// A camera looking along the ego's +x (nuScenes camera axes: z forward, x right, y down).
    fn info(camera: &str, x: f64, w: u32, h: u32) -> ImageInfo {
        let cam_to_ego = Se3::from_wxyz_t([0.5, -0.5, 0.5, -0.5], [0.0, 0.0, 1.5]);
        ImageInfo {
            scene: "s".into(),
            frame: "000".into(),
            camera: camera.into(),
            width: w,
            height: h,
            intrinsics: Some([[w as f64 / 2.0, 0.0, w as f64 / 2.0], [0.0, w as f64 / 2.0, h as f64 / 2.0], [0.0, 0.0, 1.0]]),
            camera_to_ego: cam_to_ego,
            ego_to_world: Se3::from_yaw(0.0, DVec3::new(x, 0.0, 0.0)),
            boxes: Boxes3D::default(),
            ..ImageInfo::default()
        }
    }

    #[test]
    fn a_wall_ahead_comes_nearer_by_the_distance_driven_and_the_sky_stays_at_its_depth() {
        let (w, h) = (64u32, 48u32);
        let reference = info("CAM_FRONT", 0.0, w, h);
        let target = info("CAM_FRONT", 2.0, w, h);
        // The lower half a wall 20 m ahead, the upper half sky.
        let image = Image { width: w, height: h, rgb: (0..w * h * 3).map(|i| (i % 251) as u8).collect() };
        let depth = DepthMap {
            width: w,
            height: h,
            data: (0..w * h).map(|i| if i / w < h / 2 { 100.0 } else { 20.0 }).collect(),
        };
        let refs = vec![Reference {
            image: &image,
            depth: &depth,
            support: None,
            info: &reference,
            view: info_view(&reference).unwrap(),
        }];
        let view: PinholeView = info_view(&target).unwrap();
        let (_, out, mask, _) = warp_baseline(&Params::default(), &refs, &target, &view).unwrap();
        let at = |x: u32, y: u32| out.data[(y * w + x) as usize];
        assert!((at(32, 40) - 18.0).abs() < 0.05, "the wall is 18 m ahead now: {}", at(32, 40));
        assert_eq!(at(32, 5), 100.0, "the sky keeps its depth");
        let seen = mask.data.iter().filter(|&&m| m != 0).count() as f64 / (w * h) as f64;
        assert!(seen > 0.9, "driving towards a wall, the reference saw nearly all of the view: {seen}");
    }

    #[test]
    fn pixels_far_from_every_prompt_sample_are_drawn_but_not_trusted() {
        let (w, h) = (64u32, 48u32);
        let reference = info("CAM_FRONT", 0.0, w, h);
        let target = info("CAM_FRONT", 2.0, w, h);
        let image = Image { width: w, height: h, rgb: vec![90; (w * h * 3) as usize] };
        let depth = DepthMap { width: w, height: h, data: vec![20.0; (w * h) as usize] };
        // The left half on the prompt's samples, the right half 8 px from the nearest: 5 m on a
        // wall at 20 m seen with f = 32 px.
        let support = DepthMap {
            width: w,
            height: h,
            data: (0..w * h).map(|i| if i % w < w / 2 { 0.0 } else { 8.0 }).collect(),
        };
        let refs = vec![Reference {
            image: &image,
            depth: &depth,
            support: Some(&support),
            info: &reference,
            view: info_view(&reference).unwrap(),
        }];
        let view: PinholeView = info_view(&target).unwrap();
        let (_, out, mask, trusted) = warp_baseline(&Params::default(), &refs, &target, &view).unwrap();
        let at = |m: &Mask, x: u32, y: u32| m.data[(y * w + x) as usize];
        for y in 4..h - 4 {
            assert_eq!((at(&mask, 8, y), at(&trusted, 8, y)), (1, 1), "left, row {y}: drawn and trusted");
            assert_eq!((at(&mask, 56, y), at(&trusted, 56, y)), (1, 0), "right, row {y}: drawn, not trusted");
            assert!((out.data[(y * w + 56) as usize] - 18.0).abs() < 0.05, "the view still draws the wall");
        }
        // Without the test every drawn pixel is trusted.
        let off = Params { trusted_support_m: 0.0, ..Params::default() };
        let (_, _, mask, trusted) = warp_baseline(&off, &refs, &target, &view).unwrap();
        assert_eq!(mask, trusted);
    }
}
