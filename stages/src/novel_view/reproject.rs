//! `Reproject`: RGB-D images of one or more cameras and frames drawn into one target camera (any
//! pose, intrinsics and resolution): the image and depth conditions of DiST-S and SCC (paper Sec.
//! 3.3-3.4) and the valid mask. How points are splatted is in [`crate::views::splat`]; which pixels
//! become points in [`crate::lift`]. The sky is never a point: when `splat.max_depth` admits the
//! sky's depth (the default) it is drawn as directions from the target camera under the
//! surfaces, at `lift.sky_depth`; with `max_depth: 99` it is left out of the condition.

use dist4d_runtime::Made;
use crate::lift::LiftParams;
use crate::stage::Stage;
use crate::views::splat::{draw_sky, lift_source, reproject, PinholeView, RgbdView, SplatParams};
use anyhow::{bail, ensure, Context, Result};
use dist4d_graph::{ParamChecks, ParamProblem, Validate};
use dist4d_runtime::TaskContext;
use dist4d_types::artifact::{Calibration, DepthMap, Image, Mask, Pose};
use serde::{Deserialize, Serialize};

#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// Output width and height (px); 0 and 0 = the target camera's own image size. The target's
    /// intrinsics scale with the image ([`PinholeView::resized`]).
    pub width: u32,
    pub height: u32,
    pub splat: SplatParams,
    /// Which source pixels are drawn ([`crate::lift`]). The edge tests are off by default
    /// (`max_jump: 0`): the holes they leave cost the fill baseline's novel views 0.6 dB of PSNR
    /// on the synthetic scene (docs/BENCHMARKS.md, "Flying pixels (issue 42)"); 0, NaN and the
    /// sky are never points either way.
    pub lift: LiftParams,
}

impl Default for Params {
    fn default() -> Self {
        Params {
            width: 0,
            height: 0,
            splat: SplatParams::default(),
            lift: LiftParams { max_jump: 0.0, ..LiftParams::default() },
        }
    }
}

impl Validate for Params {
    fn validate(&self) -> Vec<ParamProblem> {
        let mut checks = ParamChecks::new();
        checks.count("width", self.width as u64, 0, 16384).count("height", self.height as u64, 0, 16384).check(
            (self.width == 0) == (self.height == 0),
            "width",
            || "and `height` are both 0 (the target's size) or both set".into(),
        );
        self.splat.check(&mut checks);
        self.lift.check(&mut checks);
        checks.done()
    }
}

crate::inputs! {
    pub struct Inputs {
        /// the source images (one, a window of frames, or a gather of cameras), matched to the
        /// depths, calibrations and poses by position
        images: Many<Image>,
        /// the sources' metric depth (dense curated depth, or ground truth), 0 = none
        depths: Many<DepthMap>,
        /// the sources' camera calibrations
        calibs: Many<Calibration>,
        /// the sources' ego poses
        poses: Many<Pose>,
        /// the sources' support maps (`CompleteDepth`'s `support`, px to the nearest prompt sample),
        /// matched by position: when wired, pixels beyond `lift.max_support_px` are not drawn
        supports: OptionalMany<DepthMap>,
        /// the target camera's mounting, intrinsics and image size
        target_calib: One<Calibration>,
        /// the target's ego pose
        target_pose: One<Pose>,
    }
}

crate::outputs! {
    pub struct Outputs {
        /// image condition: the sources' colours where they land, black elsewhere
        image: One<Image>,
        /// depth condition: metres along the target's optical axis, 0 = nothing landed
        depth: One<DepthMap>,
        /// 1 where something landed
        mask: One<Mask>,
    }
}

pub struct Reproject {
    params: Params,
}

impl Stage for Reproject {
    const KIND: &'static str = "Reproject";
    // 2: sources of another size than their calibration are seen by it resized.
    // 3: sources lifted by the shared rule (crate::lift); the sky drawn as directions.
    const VERSION: u32 = 3;
    const SUMMARY: &'static str =
        "RGB-D of one or more cameras/frames drawn into a target camera with footprint splats and a soft z-buffer";
    const GRAINS: &'static [&'static str] = &["camera", "variant", "frame", "scene"];
    const ALIGNED_INPUTS: &'static [&'static [&'static str]] = &[&["images", "depths", "calibs", "poses"]];
    type Params = Params;
    type Inputs = Inputs;
    type Outputs = Outputs;

    fn new(params: Params) -> Result<Self> {
        Ok(Reproject { params })
    }

    fn run(&self, _ctx: &TaskContext, inputs: Inputs) -> Result<Made<Outputs>> {
        let target = PinholeView::new(&inputs.target_calib, &inputs.target_pose).context("target camera")?;
        let target = match (self.params.width, self.params.height) {
            (0, 0) => target,
            (w, h) => target.resized(w, h),
        };
        let sources = Sources::match_by_position(&inputs)?;
        // A source image of another size than its calibration's (a view generated at the model's
        // size) is seen by the calibrated camera resized to it: intrinsics scale with the image.
        let views: Vec<PinholeView> = sources
            .iter()
            .map(|s| {
                let view =
                    PinholeView::new(s.calib, s.pose).with_context(|| format!("source at position {}", s.pos))?;
                ensure!(
                    (s.image.width, s.image.height) == (s.depth.width, s.depth.height),
                    "source at position {}: image {}x{} and depth {}x{} differ in size",
                    s.pos,
                    s.image.width,
                    s.image.height,
                    s.depth.width,
                    s.depth.height
                );
                Ok(if (s.image.width, s.image.height) == (view.width, view.height) {
                    view
                } else {
                    view.resized(s.image.width, s.image.height)
                })
            })
            .collect::<Result<_>>()?;
        ensure!(
            inputs.supports.is_empty() || inputs.supports.len() == sources.len(),
            "input `supports` has {} sources and `images` {}: they must be wired with the same selector",
            inputs.supports.len(),
            sources.len()
        );
        // Per source, its surface (what the rule lifts) and its sky.
        let mut split = Vec::with_capacity(sources.len());
        for (s, view) in sources.iter().zip(&views) {
            let support = if inputs.supports.is_empty() {
                None
            } else {
                let m = crate::stage::at_position(&inputs.supports, s.pos, "supports")?;
                ensure!(
                    (m.width, m.height) == (s.depth.width, s.depth.height),
                    "source at position {}: support map {}x{} and depth {}x{} differ in size",
                    s.pos,
                    m.width,
                    m.height,
                    s.depth.width,
                    s.depth.height
                );
                Some(&m.data[..])
            };
            split.push(lift_source(&s.depth.data, view, support, &self.params.lift));
        }
        let surfaces: Vec<RgbdView> = sources
            .iter()
            .zip(&views)
            .zip(&split)
            .map(|((s, view), (surface, _))| RgbdView { rgb: &s.image.rgb, depth: surface, view })
            .collect();
        let mut out = reproject(&surfaces, &target, &self.params.splat)?;
        if self.params.lift.is_sky(self.params.splat.max_depth) {
            let skies: Vec<RgbdView> = sources
                .iter()
                .zip(&views)
                .zip(&split)
                .map(|((s, view), (_, sky))| RgbdView { rgb: &s.image.rgb, depth: sky, view })
                .collect();
            draw_sky(&mut out, &skies, &target, &self.params.splat, self.params.lift.sky_depth)?;
        }
        Ok(Outputs {
            image: Image { width: out.width, height: out.height, rgb: out.rgb },
            depth: DepthMap { width: out.width, height: out.height, data: out.depth },
            mask: Mask { width: out.width, height: out.height, data: out.valid },
        }.into())
    }
}

/// One source of a task: the four inputs at one position.
struct Source<'a> {
    pos: i64,
    image: &'a Image,
    depth: &'a DepthMap,
    calib: &'a Calibration,
    pose: &'a Pose,
}

struct Sources;

impl Sources {
    /// The sources in position order; every position must be in all four inputs (a window clipped
    /// differently on one port, or a gather over other cameras, is a wiring mistake to report).
    fn match_by_position(inputs: &Inputs) -> Result<Vec<Source<'_>>> {
        let mut out = Vec::with_capacity(inputs.images.len());
        for (pos, image) in &inputs.images {
            let depth = crate::stage::at_position(&inputs.depths, *pos, "depths")?;
            let calib = crate::stage::at_position(&inputs.calibs, *pos, "calibs")?;
            let pose = crate::stage::at_position(&inputs.poses, *pos, "poses")?;
            out.push(Source { pos: *pos, image, depth, calib, pose });
        }
        for (port, n) in
            [("depths", inputs.depths.len()), ("calibs", inputs.calibs.len()), ("poses", inputs.poses.len())]
        {
            if n != out.len() {
                bail!(
                    "input `{port}` has {n} sources and `images` {}: they must be wired with the same selector",
                    out.len()
                );
            }
        }
        out.sort_by_key(|s| s.pos);
        Ok(out)
    }
}

