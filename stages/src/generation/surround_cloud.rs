//! `SurroundCloud`: "bullet time" (DiST-4D Sec. 4): every camera's RGB-D of one time step fused
//! into one coloured point cloud around the ego vehicle, frozen at that instant, to look at from
//! anywhere (PLY through `EncodePly`) and to draw novel views from. With it, a preview of the
//! step: the cameras' images in rig order beside a top-down view of the cloud.
//!
//! The cloud is in the ego frame of the rig's first camera at the step (x forward, y left, z up,
//! metres), thinned to one point per voxel (the first in camera, then row order, so the bytes do
//! not depend on threads). Only what [`crate::lift`] lifts becomes a point: no pixel on the far
//! side of a depth edge (the flying pixels between a tree and what is behind it), no lone pixel,
//! no pixel without a depth (0), and no sky (the curation's 100 m is a convention, not a surface).
//! Of the thinned cloud, the points alone in the air are dropped last ([`crate::lone_points`]).
//!
//! It runs per variant (a step) under a camera, as the generated views do, and reads every camera
//! of its step through `Across(.., camera)`; the cloud is made once, by the task of the rig's
//! first camera, and the other cameras' tasks have nothing to make (`n/a` in the run's table).
//! Which task it is comes from an input (`camera_calib`, this item's camera), never from the
//! item alone: a task's outputs must follow from its key, and the six tasks of a step read the
//! same views.

use crate::lift::{focal_of, liftable, LiftParams};
use crate::lone_points::{with_company, LoneParams};
use crate::stage::Stage;
use crate::views::resize::resize_image;
use crate::views::splat::PinholeView;
use crate::voxel_hash::VoxelHasher;
use anyhow::{ensure, Context, Result};
use dist4d_graph::{ParamChecks, ParamProblem, Validate};
use dist4d_runtime::{Made, TaskContext};
use dist4d_types::artifact::{Calibration, DepthMap, File, Image, Mask, PointCloud, Pose};
use glam::DVec3;
use serde::{Deserialize, Serialize};
use std::collections::HashSet;
use std::hash::BuildHasherDefault;

#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// One point per voxel of this size (m); 0 = every pixel.
    pub voxel: f32,
    /// Depths beyond this (m) are left out.
    pub max_depth: f32,
    /// Which pixels become points ([`crate::lift`]).
    pub lift: LiftParams,
    /// Which points of the fused cloud are dropped as alone in the air ([`crate::lone_points`]).
    pub lone: LoneParams,
    /// The preview's top-down view covers +-this many metres around the ego.
    pub bev_range: f32,
    /// The preview's height (px): the camera images are scaled to fit two rows of it.
    pub preview_height: u32,
}

impl Default for Params {
    fn default() -> Self {
        Params { voxel: 0.1, max_depth: 99.0, lift: LiftParams::default(), lone: LoneParams::default(), bev_range: 50.0, preview_height: 480 }
    }
}

impl Validate for Params {
    fn validate(&self) -> Vec<ParamProblem> {
        let mut c = ParamChecks::new();
        c.within("voxel", self.voxel as f64, 0.0, 100.0)
            .above("max_depth", self.max_depth as f64, 0.0, 1e6)
            .above("bev_range", self.bev_range as f64, 0.0, 1e4)
            .count("preview_height", self.preview_height as u64, 64, 4096);
        self.lift.check(&mut c);
        self.lone.check(&mut c);
        c.done()
    }
}

crate::inputs! {
    pub struct Inputs {
        /// every camera's image at the step (`Across("future.image", camera)`)
        images: Many<Image>,
        /// their metric depth (m, 0 = none)
        depths: Many<DepthMap>,
        /// their calibrations (`Across("dataset.camera_calib", camera)`)
        calibs: Many<Calibration>,
        /// their ego poses at the step (`Across("future.pose", camera)`)
        poses: Many<Pose>,
        /// this task's own camera (`dataset.camera_calib`): the cloud is made by the task whose
        /// camera is the first of `calibs`
        camera_calib: One<Calibration>,
        /// where each view shows what was seen (`Across("future.mask", camera)`): when wired, the
        /// pixels a generator filled in (a baseline's smears) are left out of the cloud
        masks: OptionalMany<Mask>,
        /// their support maps (px to the nearest prompt sample, `CompleteDepth`'s `support`), when
        /// the depths are curated ones: pixels beyond `lift.max_support_px` are left out
        supports: OptionalMany<DepthMap>,
    }
}

crate::outputs! {
    pub struct Outputs {
        /// the coloured surround cloud, in the first camera's ego frame at the step
        points: One<PointCloud>,
        /// the cameras' images beside the cloud seen from above
        preview: One<Image>,
        /// JSON: the cloud's frame (the first camera's ego pose at the step, its time) and size,
        /// to place it in the world
        record: One<File>,
    }
}

pub struct SurroundCloud(Params);

impl Stage for SurroundCloud {
    const KIND: &'static str = "SurroundCloud";
    // 2: the first camera's task is found from its own calibration (an input), not its item.
    // 3: pixels lifted by the shared rule (crate::lift): no flying pixels.
    // 4: points alone in the air dropped (crate::lone_points).
    const VERSION: u32 = 4;
    const SUMMARY: &'static str =
        "bullet time: every camera's RGB-D of a step as one coloured point cloud, and a preview of the step";
    const GRAINS: &'static [&'static str] = &["variant"];
    type Params = Params;
    type Inputs = Inputs;
    type Outputs = Outputs;

    fn new(params: Params) -> Result<Self> {
        Ok(SurroundCloud(params))
    }

    fn run(&self, _: &TaskContext, i: Inputs) -> Result<Made<Outputs>> {
        let n = i.images.len();
        ensure!(
            n > 0 && i.depths.len() == n && i.calibs.len() == n && i.poses.len() == n,
            "`images`, `depths`, `calibs` and `poses` hold {n}, {}, {} and {} items: wire them all with Across(.., camera)",
            i.depths.len(),
            i.calibs.len(),
            i.poses.len()
        );
        if i.calibs[0].1 != i.camera_calib {
            return Ok(Made::Nothing("the step's surround cloud is made by its first camera's task".into()));
        }
        ensure!(
            i.masks.is_empty() || i.masks.len() == n,
            "`masks` holds {} items and `images` {n}: wire them with the same selector",
            i.masks.len()
        );
        ensure!(
            i.supports.is_empty() || i.supports.len() == n,
            "`supports` holds {} items and `images` {n}: wire them with the same selector",
            i.supports.len()
        );
        let mut cams = Vec::with_capacity(n);
        for k in 0..n {
            let (pos, image) = (&i.images[k].0, &i.images[k].1);
            ensure!(
                i.depths[k].0 == *pos
                    && i.calibs[k].0 == *pos
                    && i.poses[k].0 == *pos
                    && i.masks.get(k).is_none_or(|m| m.0 == *pos)
                    && i.supports.get(k).is_none_or(|m| m.0 == *pos),
                "the inputs must be wired with the same selector (Across(.., camera))"
            );
            cams.push(Camera {
                image,
                depth: &i.depths[k].1,
                calib: &i.calibs[k].1,
                pose: &i.poses[k].1,
                mask: i.masks.get(k).map(|m| &m.1),
                support: i.supports.get(k).map(|m| &m.1),
            });
        }
        let ego_from_world = cams[0].pose.ego_to_world.inverse();
        let points = drop_lone(fuse(&self.0, &cams, |p| ego_from_world.apply(p))?, &self.0.lone);
        let preview = preview(&self.0, &cams, &points)?;
        let pose = cams[0].pose;
        let t = |s: &dist4d_types::geometry::Se3| serde_json::json!({ "translation": s.translation.to_array(), "rotation": s.wxyz() });
        let record = serde_json::json!({
            "frame": "the ego frame of the rig's first camera at the step (x forward, y left, z up, m)",
            "timestamp_us": pose.timestamp_us,
            "ego_to_world": t(&pose.ego_to_world),
            "points": points.points.len(),
            "voxel": self.0.voxel,
        });
        Ok(Outputs { points, preview, record: File(serde_json::to_vec_pretty(&record)?) }.into())
    }
}

/// One camera of the step.
struct Camera<'a> {
    image: &'a Image,
    depth: &'a DepthMap,
    calib: &'a Calibration,
    pose: &'a Pose,
    mask: Option<&'a Mask>,
    support: Option<&'a DepthMap>,
}

/// Every camera's pixels that [`crate::lift`] lifts, with a depth below max_depth (and inside
/// its mask, if any), back-projected, moved by `to_frame` from the world, thinned to voxels.
fn fuse(p: &Params, cams: &[Camera], to_frame: impl Fn(DVec3) -> DVec3) -> Result<PointCloud> {
    let mut seen: HashSet<(i64, i64, i64), BuildHasherDefault<VoxelHasher>> = HashSet::default();
    let mut cloud = PointCloud::default();
    for (k, &Camera { image, depth, calib, pose, mask, support }) in cams.iter().enumerate() {
        ensure!(
            (image.width, image.height) == (depth.width, depth.height)
                && mask.is_none_or(|m| (m.width, m.height) == (depth.width, depth.height))
                && support.is_none_or(|m| (m.width, m.height) == (depth.width, depth.height)),
            "camera {k}: image {}x{}, depth {}x{} and mask differ in size",
            image.width,
            image.height,
            depth.width,
            depth.height
        );
        let view = PinholeView::new(calib, pose).with_context(|| format!("camera {k}"))?;
        let view = view.resized(image.width, image.height);
        let kk = view.k;
        let (w, h) = (image.width as usize, image.height as usize);
        let lifted = liftable(&depth.data, w, h, focal_of(&kk), support.map(|s| &s.data[..]), &p.lift);
        for y in 0..h {
            for x in 0..w {
                let z = depth.data[y * w + x];
                if !lifted[y * w + x] || z >= p.max_depth || mask.is_some_and(|m| m.data[y * w + x] == 0) {
                    continue;
                }
                let z = z as f64;
                let yc = (y as f64 + 0.5 - kk[1][2]) / kk[1][1];
                let xc = (x as f64 + 0.5 - kk[0][2] - kk[0][1] * yc) / kk[0][0];
                let at = to_frame(view.world_from_cam.apply(DVec3::new(xc * z, yc * z, z)));
                if p.voxel > 0.0 {
                    let v = p.voxel as f64;
                    let key = ((at.x / v).floor() as i64, (at.y / v).floor() as i64, (at.z / v).floor() as i64);
                    if !seen.insert(key) {
                        continue;
                    }
                }
                cloud.points.push([at.x as f32, at.y as f32, at.z as f32, 0.0]);
                let c = 3 * (y * w + x);
                cloud.rgb.push([image.rgb[c], image.rgb[c + 1], image.rgb[c + 2]]);
            }
        }
    }
    Ok(cloud)
}

/// `cloud` without the points [`crate::lone_points`] finds alone.
fn drop_lone(cloud: PointCloud, p: &LoneParams) -> PointCloud {
    let xyz: Vec<[f32; 3]> = cloud.points.iter().map(|q| [q[0], q[1], q[2]]).collect();
    let keep = with_company(&xyz, p);
    let mut out = PointCloud::default();
    for (k, &ok) in keep.iter().enumerate() {
        if ok {
            out.points.push(cloud.points[k]);
            if let Some(c) = cloud.rgb.get(k) {
                out.rgb.push(*c);
            }
        }
    }
    out
}

/// The cameras' images in two rows as a driver would place them (the forward-looking ones on
/// top, the others below, each row from left to right), beside a top-down view of the cloud (ego
/// at the centre facing up, higher points drawn over lower ones, a white mark at the ego).
fn preview(p: &Params, cams: &[Camera], cloud: &PointCloud) -> Result<Image> {
    // Each camera's heading in the ego frame: its optical axis (camera z).
    let heading = |c: &Camera| {
        let axis = c.calib.sensor_to_ego.rotation * DVec3::Z;
        axis.y.atan2(axis.x)
    };
    let (mut front, mut back): (Vec<(f64, &Image)>, Vec<(f64, &Image)>) = (Vec::new(), Vec::new());
    for c in cams {
        let a = heading(c);
        if a.abs() <= std::f64::consts::FRAC_PI_2 {
            front.push((-a, c.image)); // left (positive heading) first
        } else {
            back.push((a.rem_euclid(std::f64::consts::TAU), c.image)); // back left, back, back right
        }
    }
    front.sort_by(|a, b| a.0.total_cmp(&b.0));
    back.sort_by(|a, b| a.0.total_cmp(&b.0));
    let cols = front.len().max(back.len()).max(1);
    let mut slots: Vec<Option<&Image>> = vec![None; 2 * cols];
    for (k, (_, im)) in front.iter().enumerate() {
        slots[2 * k] = Some(im);
    }
    for (k, (_, im)) in back.iter().enumerate() {
        slots[2 * k + 1] = Some(im);
    }
    let first = cams[0].image;
    preview_of(p, first, &slots, cloud)
}

/// The preview of [`preview`]: `slots[2 * column + row]`.
fn preview_of(p: &Params, first: &Image, slots: &[Option<&Image>], cloud: &PointCloud) -> Result<Image> {
    let images = slots;
    let side = p.preview_height;
    let tile_h = side / 2;
    let cols = images.len().div_ceil(2).max(1) as u32;
    let aspect = first.width as f64 / first.height.max(1) as f64;
    let tile_w = ((tile_h as f64 * aspect).round() as u32).max(1);
    let width = cols * tile_w + side;
    let mut out = Image { width, height: side, rgb: vec![0; (width * side * 3) as usize] };
    let mut put = |x: u32, y: u32, c: [u8; 3]| {
        if x < out.width && y < out.height {
            let i = 3 * (y * out.width + x) as usize;
            out.rgb[i..i + 3].copy_from_slice(&c);
        }
    };
    for (k, image) in images.iter().enumerate() {
        let Some(image) = image else { continue };
        let tile = resize_image(image, tile_w, tile_h)?;
        let (x0, y0) = ((k as u32 / 2) * tile_w, (k as u32 % 2) * tile_h);
        for y in 0..tile_h {
            for x in 0..tile_w {
                let i = 3 * (y * tile_w + x) as usize;
                put(x0 + x, y0 + y, [tile.rgb[i], tile.rgb[i + 1], tile.rgb[i + 2]]);
            }
        }
    }
    // Top-down: forward (x) up, left (y) to the left; lowest points first.
    let x0 = cols * tile_w;
    let scale = side as f32 / (2.0 * p.bev_range);
    let mut order: Vec<usize> = (0..cloud.points.len()).collect();
    order.sort_by(|&a, &b| cloud.points[a][2].total_cmp(&cloud.points[b][2]));
    for k in order {
        let [x, y, _, _] = cloud.points[k];
        let (u, v) = (side as f32 / 2.0 - y * scale, side as f32 / 2.0 - x * scale);
        if u >= 0.0 && v >= 0.0 && u < side as f32 && v < side as f32 {
            put(x0 + u as u32, v as u32, cloud.rgb.get(k).copied().unwrap_or([255, 255, 255]));
        }
    }
    let c = side / 2;
    for d in 0..=4u32 {
        for e in 0..=d / 2 {
            put(x0 + c - e, c - 2 + d, [255, 255, 255]);
            put(x0 + c + e, c - 2 + d, [255, 255, 255]);
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use dist4d_types::geometry::Se3;

    #[test]
    fn a_forward_camera_puts_a_wall_ahead_of_the_ego_in_its_own_colours_thinned_to_voxels() {
        let (w, h) = (40u32, 30u32);
        let calib = Calibration {
            sensor_to_ego: Se3::from_wxyz_t([0.5, -0.5, 0.5, -0.5], [1.0, 0.0, 1.5]),
            intrinsics: Some([[20.0, 0.0, 20.0], [0.0, 20.0, 15.0], [0.0, 0.0, 1.0]]),
            width: w,
            height: h,
        };
        let pose = Pose { ego_to_world: Se3::from_yaw(0.3, DVec3::new(100.0, 50.0, 0.0)), timestamp_us: 0 };
        let image = Image { width: w, height: h, rgb: vec![200, 10, 10].repeat((w * h) as usize) };
        let mut depth = DepthMap { width: w, height: h, data: vec![10.0; (w * h) as usize] };
        depth.data[0] = 100.0; // sky: left out
        let mut mask = Mask { width: w, height: h, data: vec![1; (w * h) as usize] };
        mask.data[1] = 0; // filled in: left out
        let cams = vec![Camera { image: &image, depth: &depth, calib: &calib, pose: &pose, mask: Some(&mask), support: None }];
        let inverse = pose.ego_to_world.inverse();
        let all = fuse(&Params { voxel: 0.0, ..Params::default() }, &cams, |p| inverse.apply(p)).unwrap();
        assert_eq!(all.points.len(), (w * h - 2) as usize);
        for q in &all.points {
            assert!((q[0] - 11.0).abs() < 1e-3, "10 m ahead of a camera 1 m ahead of the ego: {q:?}");
        }
        assert!(all.rgb.iter().all(|c| *c == [200, 10, 10]));
        let thin = fuse(&Params { voxel: 2.0, ..Params::default() }, &cams, |p| inverse.apply(p)).unwrap();
        // 0.5 m between pixels at 10 m: 16 pixels per 2 m voxel, give or take the edges.
        assert!(thin.points.len() < all.points.len() / 10 && thin.points.len() == thin.rgb.len(), "{}", thin.points.len());
    }
}
