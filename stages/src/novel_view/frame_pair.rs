//! `FramePair`: DiST-S training pairs (paper Sec. 3.3): the RGB-D point cloud of frame t of one
//! camera (its image and curated dense depth) drawn into the same camera at frame t + offset,
//! whose own image and curated depth are the target. One task per variant: the paper's pairs are
//! t-2 and t+2, with t-4 / t+4 and a voxel-downsampled source cloud as augmentations. Everything
//! is at the model's size (default 448 x 768, H x W): the target image is resized with a
//! triangle filter (antialiased), the target depth by nearest sample (no depth mixed across an
//! edge), the target camera's intrinsics scaled with the image ([`PinholeView::resized`]).
//!
//! The target frame comes in through `Offset(.., frame, variant)`: each variant's tasks read the
//! frame its offset away, and a pair whose target frame the scene does not have (t+2 on its last
//! two frames) is not planned. Variants that draw from the other cameras (`from: Others`) read
//! them through `Across(.., camera)`; the others are planned without those inputs. The record
//! (JSON) says what the pair is; the `PairIndex` stage collects the records of a scene into its
//! index with the exported paths.

use dist4d_runtime::Made;
use crate::lift::LiftParams;
use crate::stage::{variant_of, Stage};
use crate::views::frames::{camera_views, frame_record, info_view, view_of};
use crate::views::moving::{split, Moved, Moving};
use crate::views::resize::{resize_depth_nearest, resize_image};
use crate::views::splat::{draw_sky, lift_source, reproject, PinholeView, RgbdView, SplatParams};
use crate::voxel_hash::VoxelHasher;
use anyhow::{ensure, Context, Result};
use dist4d_graph::{ParamChecks, ParamProblem, Validate, VariantPlan, Variants};
use dist4d_runtime::TaskContext;
use dist4d_types::artifact::{DepthMap, File, Image, ImageInfo, Mask};
use serde::{Deserialize, Serialize};
use serde_json::json;
use std::collections::BTreeMap;

/// Whose RGB-D a pair's condition is drawn from.
#[derive(Serialize, Deserialize, Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum Sources {
    /// The pair's own camera at frame t.
    #[default]
    Own,
    /// Every other camera of the rig at frame t (the surround, through the `surround_*` inputs):
    /// with offset 0, a cross-camera pair, which a single frame can give.
    Others,
}

/// One kind of pair.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct PairVariant {
    /// Target frame = source frame + offset (frames of the dataset's clock); 0 only with
    /// `from: Others`.
    pub offset: i32,
    /// Thin the source cloud to one point per voxel of this size (m) first; 0 = every point.
    pub voxel: f32,
    pub from: Sources,
}

impl Default for PairVariant {
    fn default() -> Self {
        PairVariant { offset: 2, voxel: 0.0, from: Sources::Own }
    }
}

#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// The model's input size (px); every output of a pair has it.
    pub width: u32,
    pub height: u32,
    /// The pairs made per camera image, by label (labels name the exported files).
    pub variants: BTreeMap<String, PairVariant>,
    /// Objects that moved between the source and target times ([`Moving`]): by default drawn
    /// where their box is at the target's time.
    pub moving: Moving,
    pub splat: SplatParams,
    /// Which source pixels are drawn ([`crate::lift`]); the sky only as directions, and only when
    /// `splat.max_depth` admits its depth (by default it does not).
    pub lift: LiftParams,
}

impl Default for Params {
    fn default() -> Self {
        let v = |offset| PairVariant { offset, ..PairVariant::default() };
        Params {
            width: 768,
            height: 448,
            variants: [("t-2".to_string(), v(-2)), ("t+2".to_string(), v(2))].into_iter().collect(),
            moving: Moving::Follow,
            // The curated sky (100 m) is a convention, not a surface: moved with the ego it would
            // land 5-10 m nearer in the target, so it is left out of the condition.
            splat: SplatParams { max_depth: 99.0, ..SplatParams::default() },
            lift: LiftParams::default(),
        }
    }
}

impl Validate for Params {
    fn validate(&self) -> Vec<ParamProblem> {
        let mut c = ParamChecks::new();
        c.count("width", self.width as u64, 8, 16384).count("height", self.height as u64, 8, 16384);
        let labels: Vec<String> = self.variants.keys().cloned().collect();
        c.path_names("variants", &labels);
        for (label, v) in &self.variants {
            c.check(
                (v.offset != 0 || v.from == Sources::Others) && v.offset.unsigned_abs() <= 10_000,
                "variants",
                || {
                    format!(
                    "`{label}`: `offset` must be a non-zero number of frames (0 only with `from: Others`), found {}",
                    v.offset
                )
                },
            );
            c.check(v.voxel.is_finite() && (0.0..=100.0).contains(&v.voxel), "variants", || {
                format!("`{label}`: `voxel` must be in [0, 100] m, found {}", v.voxel)
            });
        }
        self.splat.check(&mut c);
        self.lift.check(&mut c);
        c.done()
    }
}

crate::inputs! {
    pub struct Inputs {
        /// the pair's own image at frame t
        image: One<Image>,
        /// its curated dense depth
        depth: One<DepthMap>,
        /// its support map (`complete.support`, px to the nearest prompt sample): when wired,
        /// pixels beyond `lift.max_support_px` are not drawn
        support: Optional<DepthMap>,
        /// what the image is and where it was taken
        info: One<ImageInfo>,
        /// the target frame's image: `Offset("dataset.image", frame, variant)`, the variant's
        /// offset (a pair whose target frame the scene does not have is not planned)
        target_image: One<Image>,
        /// the target frame's curated depth, the same way
        target_depth: One<DepthMap>,
        /// the target frame's image info, the same way
        target_info: One<ImageInfo>,
        /// every camera's image at frame t (`Across("dataset.image", camera)`), read by the
        /// `from: Others` variants only
        surround_images: OptionalMany<Image>,
        /// every camera's curated depth at frame t
        surround_depths: OptionalMany<DepthMap>,
        /// every camera's image info at frame t
        surround_infos: OptionalMany<ImageInfo>,
        /// every camera's support map at frame t, when wired (as `support`)
        surround_supports: OptionalMany<DepthMap>,
    }
}

crate::outputs! {
    pub struct Outputs {
        /// the source frame's colours drawn at the target (model size), black where none
        cond_image: One<Image>,
        /// the source frame's depth at the target (m), 0 where none
        cond_depth: One<DepthMap>,
        /// 1 where the condition has a point
        mask: One<Mask>,
        /// the target frame's image at the model size
        target_image: One<Image>,
        /// the target frame's curated depth at the model size
        target_depth: One<DepthMap>,
        /// the pair's record (JSON): frames, times, poses, intrinsics, variant
        record: One<File>,
    }
}

pub struct FramePair {
    params: Params,
}

impl Stage for FramePair {
    const KIND: &'static str = "FramePair";
    // 2: moving objects follow their boxes to the target's time.
    // 3: the own and target frames as single inputs (Offset by the variant).
    // 4: the target may come resized already.
    // 5: sources lifted by the shared rule (crate::lift): no flying pixels.
    const VERSION: u32 = 5;
    const SUMMARY: &'static str =
        "DiST-S training pairs: frame t's RGB-D cloud drawn into frame t+offset of the same camera, per variant";
    const GRAINS: &'static [&'static str] = &["variant"];
    const VARIANTS: bool = true;
    type Params = Params;
    type Inputs = Inputs;
    type Outputs = Outputs;

    fn new(params: Params) -> Result<Self> {
        Ok(FramePair { params })
    }

    fn variants(params: &Params) -> Option<Variants> {
        Variants::split_planned(
            params,
            |p| std::mem::take(&mut p.variants),
            |v| {
                let surround = vec!["surround_images", "surround_depths", "surround_infos"];
                match v.from {
                    Sources::Own => VariantPlan {
                        offset: v.offset,
                        unused: [&surround[..], &["surround_supports"]].concat(),
                        needs: Vec::new(),
                    },
                    Sources::Others => VariantPlan { offset: v.offset, unused: vec!["support"], needs: surround },
                }
            },
        )
    }

    fn run(&self, ctx: &TaskContext, inputs: Inputs) -> Result<Made<Outputs>> {
        let (label, variant) = variant_of(ctx, &self.params.variants)?;
        let (src_image, src_depth, src_info) = (&inputs.image, &inputs.depth, &inputs.info);
        let (tgt_image, tgt_depth, tgt_info) = (&inputs.target_image, &inputs.target_depth, &inputs.target_info);
        // The target may come at the camera's size or already at the pair's (`ResizeView`, once
        // per frame instead of once per pair that reads it); any other size is resized to the
        // pair's (its camera is the target's, resized to the pair's size, either way).
        let tgt_full = info_view(tgt_info).context("the target frame")?;
        let tgt_view = tgt_full.resized(self.params.width, self.params.height);
        // The sources: this camera at t, or every other camera at t.
        let sources: Vec<(&Image, &DepthMap, &ImageInfo)> = match variant.from {
            Sources::Own => vec![(src_image, src_depth, src_info)],
            Sources::Others => {
                let s = &inputs;
                anyhow::ensure!(
                    !s.surround_images.is_empty(),
                    "variant `{label}` draws from the other cameras: wire `surround_images`, `surround_depths` and `surround_infos` with Across(.., camera)"
                );
                let out: Vec<(&Image, &DepthMap, &ImageInfo)> =
                    camera_views(&s.surround_images, &s.surround_depths, &s.surround_infos, "the `surround_*` inputs")?
                        .into_iter()
                        .filter(|(_, _, info)| info.camera != src_info.camera)
                        .collect();
                anyhow::ensure!(
                    !out.is_empty(),
                    "variant `{label}` draws from the other cameras of frame t, and the `surround_*` inputs hold none \
                     (they are wired with Across(.., camera))"
                );
                out
            }
        };
        let views: Vec<PinholeView> = sources
            .iter()
            .map(|(image, depth, info)| {
                view_of(info, image, depth).with_context(|| format!("the source {}", info.camera))
            })
            .collect::<Result<_>>()?;
        // Each source's support map, when wired: its own, or the surround's of the same camera.
        let supports: Vec<Option<&DepthMap>> = sources
            .iter()
            .map(|(_, depth, _)| {
                let s = match variant.from {
                    Sources::Own => inputs.support.as_ref(),
                    Sources::Others => {
                        let pos = inputs.surround_depths.iter().find(|(_, d)| std::ptr::eq(d, *depth)).map(|(p, _)| *p);
                        inputs.surround_supports.iter().find(|(p, _)| Some(*p) == pos).map(|(_, s)| s)
                    }
                };
                if let Some(s) = s {
                    ensure!(
                        (s.width, s.height) == (depth.width, depth.height),
                        "a support map of {}x{} for a depth of {}x{}",
                        s.width,
                        s.height,
                        depth.width,
                        depth.height
                    );
                }
                Ok(s)
            })
            .collect::<Result<_>>()?;
        // Each source thinned to voxels (an augmentation), then split into its static rest and
        // the objects that moved between its time and the target's.
        // The rule first (it needs every neighbour), then the thinning.
        let mut moved = Moved::default();
        let mut pieces = Vec::new();
        let mut skies = Vec::new();
        for (((image, depth, info), view), support) in sources.iter().zip(&views).zip(&supports) {
            let (surface, sky) = lift_source(&depth.data, view, support.map(|s| &s.data[..]), &self.params.lift);
            skies.push((*image, sky, *view));
            let depth = if variant.voxel > 0.0 { thin_to_voxels(&surface, view, variant.voxel) } else { surface };
            let (parts, m) = split(&depth, view, &info.boxes.boxes, &tgt_info.boxes.boxes, self.params.moving);
            moved.followed += m.followed;
            moved.dropped += m.dropped;
            pieces.extend(parts.into_iter().map(|p| (*image, p)));
        }
        let rgbd: Vec<RgbdView> =
            pieces.iter().map(|(image, p)| RgbdView { rgb: &image.rgb, depth: &p.depth, view: &p.view }).collect();
        let mut cond = reproject(&rgbd, &tgt_view, &self.params.splat)?;
        if self.params.lift.is_sky(self.params.splat.max_depth) {
            let sky: Vec<RgbdView> =
                skies.iter().map(|(image, sky, view)| RgbdView { rgb: &image.rgb, depth: sky, view }).collect();
            draw_sky(&mut cond, &sky, &tgt_view, &self.params.splat, self.params.lift.sky_depth)?;
        }
        let (w, h) = (self.params.width, self.params.height);
        let record = json!({
            "kind": "dist_s",
            "scene": src_info.scene,
            "camera": src_info.camera,
            "frame": src_info.frame,
            "variant": label,
            "offset": variant.offset,
            "shift": 0.0,
            // The f32 as written (0.2, not 0.20000000298023224).
            "augmentation": { "offset": variant.offset.abs() > 2, "voxel": variant.voxel.to_string().parse::<f64>().unwrap_or(0.0) },
            "size": [h, w],
            "from": variant.from,
            "moving": { "mode": self.params.moving, "followed": moved.followed, "dropped": moved.dropped },
            "sources": sources.iter().zip(&views).map(|((_, _, info), view)| frame_record(info, view)).collect::<Vec<_>>(),
            "target": frame_record(tgt_info, &tgt_view),
        });
        Ok(Outputs {
            cond_image: Image { width: w, height: h, rgb: cond.rgb },
            cond_depth: DepthMap { width: w, height: h, data: cond.depth },
            mask: Mask { width: w, height: h, data: cond.valid },
            target_image: resize_image(tgt_image, w, h)?,
            target_depth: resize_depth_nearest(tgt_depth, w, h),
            record: File(serde_json::to_vec(&record)?),
        }.into())
    }
}

/// `depth` with one pixel kept per voxel of `size` metres (the first in row order), the others
/// set to 0: the paper's voxel downsampling of the source cloud, done on the map so the kept
/// points are splatted like any other (isolated, they get a source pixel's footprint).
pub fn thin_to_voxels(depth: &[f32], view: &PinholeView, size: f32) -> Vec<f32> {
    let mut seen: std::collections::HashSet<(i64, i64, i64), std::hash::BuildHasherDefault<VoxelHasher>> =
        std::collections::HashSet::with_capacity_and_hasher(depth.len() / 8, Default::default());
    let mut out = vec![0.0; depth.len()];
    let k = view.k;
    let w = view.width as usize;
    let inv = 1.0 / size as f64;
    for (i, &d) in depth.iter().enumerate() {
        if !(d > 0.0 && d.is_finite()) {
            continue;
        }
        let (x, y) = ((i % w) as f64 + 0.5, (i / w) as f64 + 0.5);
        let z = d as f64;
        let yc = (y - k[1][2]) / k[1][1] * z;
        let xc = (x - k[0][2] - k[0][1] * yc / z) / k[0][0] * z;
        // Camera-frame voxels: the thinning of a cloud is the same in any fixed frame up to
        // where the voxel borders fall.
        let key = ((xc * inv).floor() as i64, (yc * inv).floor() as i64, (z * inv).floor() as i64);
        if seen.insert(key) {
            out[i] = d;
        }
    }
    out
}
