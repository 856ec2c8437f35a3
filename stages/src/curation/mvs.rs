//! `MultiViewStereo`: depth of one camera image from the same camera's neighbouring frames.
//!
//! DiST-4D (Sec. 3.2, supp. A): LiDAR does not reach above its upper field of view (about +10
//! degrees on nuScenes), so building facades, tree crowns and the far street end get no prompt.
//! The paper fills them with multi-view stereo on calibrated neighbouring frames, up to 100 m.
//! Here: plane sweep over inverse depth in the target camera, 7x7 census costs against frames
//! t-1 and t+1 (the window's other images, placed by their ego poses), 8-path semi-global
//! aggregation, a uniqueness test and sub-plane refinement (see [`crate::stereo`]). A geometric
//! consistency check then keeps only depths that the neighbour with the longer baseline, matched
//! back against the target image, confirms within `consistency_px` and `consistency_depth`.
//!
//! Work happens at 1/`downscale` of the image size (default 1/4, 400x225 for nuScenes): the
//! baselines between keyframes are metres long, so at full size a side camera's epipolar lines
//! are thousands of pixels; the outputs keep that size (scale K by width / calibration width).
//! Near the epipole (ahead of a forward-moving front camera) depth is unobservable; those pixels
//! fail the uniqueness or consistency test and get no depth rather than a wrong one.
//! A frame without neighbours (a one-frame scene) gets no depth.

use dist4d_runtime::Made;
use crate::stage::Stage;
use dist4d_runtime::TaskContext;
use crate::stereo::{
    keep_consistent, sweep_depth_with, StereoDepth, StereoView, SweepBuffers, SweepParams, VolumeTooLarge,
};
use anyhow::{anyhow, ensure, Result};
use dist4d_graph::{ParamChecks, ParamProblem, Validate};
use dist4d_types::artifact::{Calibration, DepthMap, Image, Pose};
use serde::{Deserialize, Serialize};

#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// Working resolution is 1/downscale of the image's (integer, >= 1).
    pub downscale: u32,
    /// Nearest depth swept (m).
    pub min_depth: f64,
    /// Farthest depth swept (m; the paper's MVS maximum is 100 m).
    pub max_depth: f64,
    /// Cap on the number of depth planes.
    pub max_planes: u32,
    /// Planes are spaced to move the sample about this far (working-resolution px) along the
    /// longest epipolar line.
    pub plane_step_px: f64,
    /// SGM penalty for a one-plane change between neighbouring pixels (census-bit units).
    pub p1: u16,
    /// SGM penalty for a larger depth jump.
    pub p2: u16,
    /// The best aggregated cost must beat the second best by this fraction.
    pub uniqueness: f64,
    /// The second best is sought at least this far (working-resolution px along the epipolar
    /// line) from the best.
    pub distinct_px: f64,
    /// Geometric consistency: reprojection error allowed (working-resolution px).
    pub consistency_px: f64,
    /// Geometric consistency: relative depth difference allowed.
    pub consistency_depth: f64,
}

impl Default for Params {
    fn default() -> Self {
        Params {
            downscale: 4,
            min_depth: 3.0,
            max_depth: 100.0,
            max_planes: 256,
            plane_step_px: 1.0,
            p1: 8,
            p2: 48,
            uniqueness: 0.05,
            distinct_px: 1.0,
            consistency_px: 1.0,
            consistency_depth: 0.03,
        }
    }
}

/// Memory one MVS task may hold at its peak: its cost volume and aggregation (see
/// [`crate::stereo::volume_bytes`]), and the working images, census transforms and depth maps of
/// its frames ([`frame_bytes`]). The defaults need 69 MB for a 1600x900 camera (400 x 225 x 256
/// planes x 3 bytes); full resolution with 256 planes needs 1.1 GB. Measured: 990 planes at
/// 1600x900 (over this budget now) peaked at 4.35 GB resident for the whole process; 960 planes
/// (within it) at the figure in docs/BENCHMARKS.md. Tasks run in parallel (`--jobs`), each within
/// this budget: a run warns when `--jobs` times it exceeds the machine's memory.
pub const MAX_COST_VOLUME_BYTES: u64 = 4 << 30;

/// What a task holds besides its sweep's volume: per frame of the window the working grey
/// image and its census (1 + 8 bytes per working pixel) and a depth and confidence map (8
/// bytes), and the full-resolution grey image made while downscaling (1 byte per pixel).
fn frame_bytes(frames: &[Frame], downscale: u32) -> u64 {
    let d = downscale.max(1) as u64;
    frames
        .iter()
        .map(|f| {
            let (w, h) = (f.calib.width as u64, f.calib.height as u64);
            w.div_ceil(d) * h.div_ceil(d) * 17 + w * h
        })
        .sum()
}

/// Most neighbouring frames one target is matched against: the cost of a plane sums one census
/// comparison per neighbour (in 8 bits of count), and the DiST-4D window is t-1..t+1.
pub const MAX_NEIGHBOURS: usize = 16;

/// Largest SGM penalty: a path cost stays below cost + `p2`, and 8 paths summed in 16 bits must
/// not overflow: 8 x (96 + p2) < 65536.
const MAX_PENALTY: u64 = 4096;

impl Validate for Params {
    fn validate(&self) -> Vec<ParamProblem> {
        let mut c = ParamChecks::new();
        c.count("downscale", self.downscale as u64, 1, 64)
            .above("min_depth", self.min_depth, 0.0, 1e4)
            .above("max_depth", self.max_depth, 0.0, 1e5)
            .below("min_depth", self.min_depth, "max_depth", self.max_depth)
            // The plane count sizes the cost volume (3 bytes per working pixel and plane).
            .count("max_planes", self.max_planes as u64, 8, 1024)
            .within("plane_step_px", self.plane_step_px, 0.01, 100.0)
            .count("p2", self.p2 as u64, 0, MAX_PENALTY)
            .check((0.0..1.0).contains(&self.uniqueness), "uniqueness", || {
                format!("must be a fraction in [0, 1), found {}", self.uniqueness)
            })
            .within("distinct_px", self.distinct_px, 0.0, 100.0)
            .within("consistency_px", self.consistency_px, 0.0, 100.0)
            .within("consistency_depth", self.consistency_depth, 0.0, 1.0);
        if self.p1 > self.p2 {
            c.push(ParamProblem {
                field: "p1",
                index: None,
                other: Some("p2"),
                message: format!("must not exceed `p2` ({}), found {}", self.p2, self.p1),
            });
        }
        c.done()
    }
}

impl Params {
    pub fn sweep(&self) -> SweepParams {
        SweepParams {
            min_depth: self.min_depth,
            max_depth: self.max_depth,
            max_planes: self.max_planes as usize,
            plane_step_px: self.plane_step_px,
            p1: self.p1,
            p2: self.p2,
            uniqueness: self.uniqueness,
            distinct_px: self.distinct_px,
            max_volume_bytes: MAX_COST_VOLUME_BYTES,
        }
    }

    /// A refused sweep, said with the params that size it.
    fn too_large(&self, e: VolumeTooLarge, frames: u64) -> anyhow::Error {
        let gib = |b: u64| format!("{:.1} GiB", b as f64 / (1u64 << 30) as f64);
        anyhow!(
            "a MultiViewStereo task would need {}: its cost volume {} ({} x {} pixels x {} planes x 3 bytes, and the \
             aggregation's rows) and its frames' images and maps {}, over the budget of {} per task: raise \
             `downscale` (now {}), or lower `max_planes` (now {}) or raise `plane_step_px` (now {})",
            gib(e.bytes + frames),
            gib(e.bytes),
            e.width,
            e.height,
            e.planes,
            gib(frames),
            gib(MAX_COST_VOLUME_BYTES),
            self.downscale,
            self.max_planes,
            self.plane_step_px
        )
    }
}

/// One frame of the window: the camera image, its calibration and the ego pose at its time.
pub struct Frame<'a> {
    pub position: i64,
    pub image: &'a Image,
    pub calib: &'a Calibration,
    pub pose: &'a Pose,
}

fn view(frame: &Frame, downscale: u32) -> Result<StereoView> {
    let k = frame
        .calib
        .intrinsics
        .ok_or_else(|| anyhow!("camera calibration at position {} has no intrinsics", frame.position))?;
    let img = frame.image;
    ensure!(
        (img.width, img.height) == (frame.calib.width, frame.calib.height),
        "image at position {} is {}x{} but its calibration says {}x{}",
        frame.position,
        img.width,
        img.height,
        frame.calib.width,
        frame.calib.height
    );
    let grey = crate::stereo::grey(&img.rgb);
    let world_from_cam = frame.pose.ego_to_world.then_from(&frame.calib.sensor_to_ego);
    Ok(StereoView::downscaled(img.width as usize, img.height as usize, &grey, k, world_from_cam, downscale as usize))
}

/// Depth and confidence of the frame at position 0, at working resolution.
pub fn multi_view_stereo(params: &Params, frames: &[Frame]) -> Result<(DepthMap, DepthMap)> {
    crate::stage::ensure_valid(params)?;
    let target = frames
        .iter()
        .find(|f| f.position == 0)
        .ok_or_else(|| anyhow!("the window has no image at position 0 (the target frame)"))?;
    let neighbours = frames.iter().filter(|f| f.position != 0).count();
    ensure!(
        neighbours <= MAX_NEIGHBOURS,
        "the window gives {neighbours} neighbouring frames; MultiViewStereo matches at most {MAX_NEIGHBOURS}: \
         narrow the Window of `images`"
    );
    let reference = view(target, params.downscale)?;
    let sources =
        frames.iter().filter(|f| f.position != 0).map(|f| view(f, params.downscale)).collect::<Result<Vec<_>>>()?;
    let mut sweep = params.sweep();
    let held = frame_bytes(frames, params.downscale);
    sweep.max_volume_bytes = MAX_COST_VOLUME_BYTES.saturating_sub(held);
    let refs: Vec<&StereoView> = sources.iter().collect();
    let mut buffers = SweepBuffers::default();
    let mut depth = sweep_depth_with(&mut buffers, &reference, &refs, &sweep).map_err(|e| params.too_large(e, held))?;
    dist4d_types::cancel::check()?;
    // Each neighbour, matched back against the target alone, checks the depths it sees; one
    // confirmation keeps a depth. (Checking only the longest baseline lost what that neighbour
    // does not see: the side of a side camera's image that the other frame has left behind.)
    let backs: Vec<StereoDepth> = sources
        .iter()
        .map(|s| {
            let back = sweep_depth_with(&mut buffers, s, &[&reference], &sweep).map_err(|e| params.too_large(e, held))?;
            dist4d_types::cancel::check()?;
            Ok(back)
        })
        .collect::<Result<_>>()?;
    let checks: Vec<(&StereoView, &StereoDepth)> = sources.iter().zip(&backs).collect();
    keep_consistent(&reference, &mut depth, &checks, params.consistency_px, params.consistency_depth);
    let (w, h) = (depth.width as u32, depth.height as u32);
    Ok((DepthMap { width: w, height: h, data: depth.depth }, DepthMap { width: w, height: h, data: depth.confidence }))
}

crate::inputs! {
    pub struct Inputs {
        /// the camera's images: Window("dataset.image", frame, -1, 1)
        images: Many<Image>,
        /// their calibrations (same Window)
        calibs: Many<Calibration>,
        /// their ego poses (same Window)
        poses: Many<Pose>,
    }
}

crate::outputs! {
    pub struct Outputs {
        /// depth of the target image at 1/downscale size, 0 = none
        depth: One<DepthMap>,
        /// per-pixel confidence in [0, 1] (same size), 0 = no depth
        confidence: One<DepthMap>,
    }
}

pub struct MultiViewStereo(Params);

impl Stage for MultiViewStereo {
    const KIND: &'static str = "MultiViewStereo";
    const VERSION: u32 = 2;
    const SUMMARY: &'static str =
        "Camera images of a window of frames -> depth of the target image by plane-sweep stereo + SGM";
    const GRAINS: &'static [&'static str] = &["camera"];
    const ALIGNED_INPUTS: &'static [&'static [&'static str]] = &[&["images", "calibs", "poses"]];
    type Params = Params;
    type Inputs = Inputs;
    type Outputs = Outputs;
    fn new(params: Params) -> Result<Self> {
        Ok(MultiViewStereo(params))
    }
    fn peak_memory(&self) -> Option<u64> {
        Some(MAX_COST_VOLUME_BYTES)
    }
    fn run(&self, _: &TaskContext, i: Inputs) -> Result<Made<Outputs>> {
        let mut frames = Vec::new();
        for (pos, image) in &i.images {
            let calib =
                i.calibs.iter().find(|(p, _)| p == pos).ok_or_else(|| anyhow!("no camera_calib at position {pos}"))?;
            let pose = i.poses.iter().find(|(p, _)| p == pos).ok_or_else(|| anyhow!("no camera_pose at position {pos}"))?;
            frames.push(Frame { position: *pos, image, calib: &calib.1, pose: &pose.1 });
        }
        let (depth, confidence) = multi_view_stereo(&self.0, &frames)?;
        Ok(Outputs { depth, confidence }.into())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use dist4d_types::geometry::Se3;
    use glam::DVec3;

    /// A camera looking left (ego +y), so driving along ego +x is a sideways baseline, at a
    /// textured wall 20 m to the left.
    fn frame_data(x: f64) -> (Image, Calibration, Pose) {
        frame_data_sized(x, 320, 180)
    }

    fn frame_data_sized(x: f64, w: u32, h: u32) -> (Image, Calibration, Pose) {
        let f = 200.0 * w as f64 / 320.0;
        // Camera x (right) = ego +x, y (down) = ego -z, z (optical axis) = ego +y: -90 deg about x.
        let calib = Calibration {
            sensor_to_ego: Se3::from_wxyz_t(
                [std::f64::consts::FRAC_1_SQRT_2, -std::f64::consts::FRAC_1_SQRT_2, 0.0, 0.0],
                [0.0, 0.0, 1.5],
            ),
            intrinsics: Some([[f, 0.0, w as f64 / 2.0], [0.0, f, h as f64 / 2.0], [0.0, 0.0, 1.0]]),
            width: w,
            height: h,
        };
        let pose = Pose { ego_to_world: Se3::from_yaw(0.0, DVec3::new(x, 0.0, 0.0)), timestamp_us: (x * 1e5) as i64 };
        let world_from_cam = pose.ego_to_world.then_from(&calib.sensor_to_ego);
        let mut rgb = vec![0u8; (w * h * 3) as usize];
        for v in 0..h {
            for u in 0..w {
                let ray = DVec3::new((u as f64 + 0.5 - w as f64 / 2.0) / f, (v as f64 + 0.5 - h as f64 / 2.0) / f, 1.0);
                let o = world_from_cam.translation;
                let d = world_from_cam.matrix() * ray;
                // The wall is the plane world y = 20.
                let t = (20.0 - o.y) / d.y;
                let p = o + d * t;
                let g = wall_texture(p.x, p.z);
                let i = ((v * w + u) * 3) as usize;
                rgb[i..i + 3].copy_from_slice(&[g, g, g]);
            }
        }
        (Image { width: w, height: h, rgb }, calib, pose)
    }

    fn wall_texture(a: f64, b: f64) -> u8 {
        let hash = |i: i64, j: i64| {
            let mut x = (i as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ (j as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F);
            x ^= x >> 29;
            x = x.wrapping_mul(0xBF58_476D_1CE4_E5B9);
            x ^= x >> 32;
            (x & 0xFF) as f64
        };
        let (s, t) = (a / 0.25, b / 0.25);
        let (i, j) = (s.floor() as i64, t.floor() as i64);
        let (fs, ft) = (s - i as f64, t - j as f64);
        (hash(i, j) * (1.0 - fs) * (1.0 - ft)
            + hash(i + 1, j) * fs * (1.0 - ft)
            + hash(i, j + 1) * (1.0 - fs) * ft
            + hash(i + 1, j + 1) * fs * ft) as u8
    }

    #[test]
    fn a_side_wall_seen_while_driving_past_it_gets_its_depth() {
        let data: Vec<(i64, (Image, Calibration, Pose))> =
            vec![(-1, frame_data(-3.0)), (0, frame_data(0.0)), (1, frame_data(3.0))];
        let frames: Vec<Frame> =
            data.iter().map(|(p, (i, c, q))| Frame { position: *p, image: i, calib: c, pose: q }).collect();
        let params = Params { downscale: 2, ..Params::default() };
        let (depth, conf) = multi_view_stereo(&params, &frames).unwrap();
        assert_eq!((depth.width, depth.height), (160, 90));
        // The camera looks straight at the wall: depth 20 m everywhere.
        let valid: Vec<f32> = depth.data.iter().copied().filter(|&z| z > 0.0).collect();
        assert!(valid.len() > depth.data.len() / 2, "{} of {}", valid.len(), depth.data.len());
        // Both image edges: each is seen by one neighbour only (the wall shifts 15 px per frame),
        // so the check must take either neighbour's word.
        for cols in [0..20usize, 140..160] {
            let n =
                (0..90).flat_map(|y| cols.clone().map(move |x| y * 160 + x)).filter(|&i| depth.data[i] > 0.0).count();
            assert!(n as f64 > 0.85 * (90 * 20) as f64, "columns {cols:?}: {n} of {}", 90 * 20);
        }
        let good = valid.iter().filter(|&&z| (z - 20.0).abs() < 0.6).count();
        assert!(good as f64 > 0.97 * valid.len() as f64, "{good} of {}", valid.len());
        assert!(conf.data.iter().zip(&depth.data).all(|(c, z)| (*c > 0.0) == (*z > 0.0)));
    }

    #[test]
    fn a_plan_over_the_memory_budget_fails_naming_the_params_that_size_it() {
        // Full nuScenes size, every pixel, 1024 planes: 1600 x 900 x 1024 x 3 bytes = 4.1 GiB.
        let data: Vec<(i64, (Image, Calibration, Pose))> =
            [(-1, -3.0), (0, 0.0), (1, 3.0)].map(|(p, x)| (p, frame_data_sized(x, 1600, 900))).into();
        let frames: Vec<Frame> =
            data.iter().map(|(p, (i, c, q))| Frame { position: *p, image: i, calib: c, pose: q }).collect();
        let params = Params { downscale: 1, max_planes: 1024, plane_step_px: 0.01, ..Params::default() };
        let e = multi_view_stereo(&params, &frames).unwrap_err().to_string();
        assert!(
            e.contains("a MultiViewStereo task would need 4.2 GiB: its cost volume 4.1 GiB (1600 x 900 pixels x 1024 planes x 3 bytes"),
            "{e}"
        );
        assert!(e.contains("its frames' images and maps 0.1 GiB, over the budget of 4.0 GiB per task"), "{e}");
        assert!(e.contains("raise `downscale` (now 1), or lower `max_planes` (now 1024)"), "{e}");
        assert!(e.contains("`plane_step_px` (now 0.01)"), "{e}");
        // What the message suggests, half the resolution, fits.
        assert!(crate::stereo::volume_bytes(800, 450, 1024) < MAX_COST_VOLUME_BYTES);
    }

    #[test]
    fn too_many_neighbours_are_refused() {
        let (i, c, q) = frame_data(0.0);
        let frames: Vec<Frame> = (-9..=9).map(|p| Frame { position: p, image: &i, calib: &c, pose: &q }).collect();
        let e = multi_view_stereo(&Params::default(), &frames).unwrap_err().to_string();
        assert!(e.contains("18 neighbouring frames; MultiViewStereo matches at most 16"), "{e}");
    }

    #[test]
    fn one_frame_gives_no_depth_and_bad_params_are_refused() {
        let (i, c, q) = frame_data(0.0);
        let frames = [Frame { position: 0, image: &i, calib: &c, pose: &q }];
        let (depth, _) = multi_view_stereo(&Params::default(), &frames).unwrap();
        assert!(depth.data.iter().all(|&z| z == 0.0));
        let bad = Params { min_depth: 50.0, max_depth: 10.0, ..Params::default() };
        assert!(multi_view_stereo(&bad, &frames).unwrap_err().to_string().contains("min_depth"));
        let none = [Frame { position: 1, image: &i, calib: &c, pose: &q }];
        assert!(multi_view_stereo(&Params::default(), &none).is_err());
    }
}
