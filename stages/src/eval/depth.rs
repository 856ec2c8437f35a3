//! `EvalDepth` and the depth metrics: a dense depth scored against reference depths.
//!
//! The metrics of Eigen et al. (2014) as monodepth2 / SurroundDepth compute them: over reference
//! pixels with depth in [`min_depth`, `max_depth`] (default 0.1-80 m), the prediction clamped to
//! the same range (so a missing prediction, 0, counts as `min_depth`), Abs Rel, Sq Rel, RMSE,
//! RMSE log and the share with max(pred/ref, ref/pred) below 1.25, 1.25^2, 1.25^3; optionally
//! after scaling the prediction by median(ref) / median(pred) per image. On the same pixels, the
//! bad-pixel rates: the shares with a relative error |pred - ref| / ref above 10% and 25% (what
//! a mean hides: a few far-off pixels, a streak). Metrics are per image; `dist4d eval` averages
//! them per camera, then over cameras.
//!
//! Against a dense reference (`gt`: a depth or +inf = sky at every pixel) also the sky metrics
//! ([`super::sky`]: sky IoU, sky given a structure depth, structure given the sky depth) and the
//! depth-boundary errors ([`super::boundary`]: iBims-1 accuracy and completeness of Canny edges of
//! log depth). A sparse reference (LiDAR) says nothing about the sky and has no edges to find, so
//! these are absent for it (not 0).
//!
//! References, each an optional input: `gt` (a dense ground truth, e.g. the synthetic world's;
//! an empty map means the dataset has none), `lidar` (the target frame's single-sweep
//! projection), `lidar_multi` (the aggregated multi-frame projection, DiST-4D Table 7) and
//! `holdout` (held-out LiDAR points the curation never saw), and `gt_above_lidar` (the ground
//! truth only where it lies above the LiDAR's vertical field of view, from `AboveLidarFov`: where
//! LiDAR cannot help and MVS must; sparse, as it is 0 elsewhere, the sky included).

use dist4d_runtime::Made;
use super::boundary::{boundary_metrics, BoundaryMetrics, EdgeParams};
use super::sky::{sky_metrics, SkyMetrics};
use crate::stage::Stage;
use anyhow::{ensure, Context, Result};
use dist4d_graph::{ParamChecks, ParamProblem, Validate};
use dist4d_runtime::TaskContext;
use dist4d_types::artifact::{DepthMap, File};
use serde::{Deserialize, Serialize};

#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// Reference depths scored (m, exclusive): the Eigen et al. range 0.1-80 m.
    pub min_depth: f32,
    pub max_depth: f32,
    /// A depth at or beyond this (m) is sky, in the prediction and in a dense reference; just
    /// under the completion's `sky_depth` (100 m): change both together.
    pub sky_threshold: f32,
    /// Depths below this (m) are structure for the sky metrics (sky given a structure depth,
    /// structure given the sky depth).
    pub structure_depth: f32,
    /// Depth (m) sky is set to, and every depth clamped to, before taking edges (iBims-1 style
    /// boundary errors; 100 m as the completion's sky).
    pub edge_sky_depth: f32,
    /// Gaussian blur (px) before the Sobel gradients of the edge detector (iBims-1: sqrt 2).
    pub edge_sigma: f32,
    /// A sharp depth step by this ratio starts an edge (Canny's high threshold, on log depth).
    pub edge_high_step: f32,
    /// An edge continues through steps by this ratio (Canny's low threshold).
    pub edge_low_step: f32,
    /// Edge distances are capped at this many px (iBims-1: 10).
    pub edge_max_distance: f32,
}

impl Default for Params {
    fn default() -> Self {
        let e = EdgeParams::default();
        Params {
            min_depth: e.min_depth,
            max_depth: 80.0,
            sky_threshold: e.sky_threshold,
            structure_depth: 80.0,
            edge_sky_depth: e.sky_depth,
            edge_sigma: e.sigma,
            edge_high_step: e.high_step,
            edge_low_step: e.low_step,
            edge_max_distance: e.max_distance,
        }
    }
}

impl Validate for Params {
    fn validate(&self) -> Vec<ParamProblem> {
        use std::cmp::Ordering::Greater;
        // A positive minimum: the metrics divide by the reference and take logs of both.
        ParamChecks::new()
            .above("min_depth", self.min_depth as f64, 0.0, 1e6)
            .above("max_depth", self.max_depth as f64, 0.0, 1e6)
            .below("min_depth", self.min_depth as f64, "max_depth", self.max_depth as f64)
            .above("sky_threshold", self.sky_threshold as f64, 0.0, 1e6)
            .above("structure_depth", self.structure_depth as f64, 0.0, 1e6)
            .below("min_depth", self.min_depth as f64, "structure_depth", self.structure_depth as f64)
            .check(self.structure_depth.partial_cmp(&self.sky_threshold) != Some(Greater), "structure_depth", || {
                format!("must be at most `sky_threshold` ({}), found {}", self.sky_threshold, self.structure_depth)
            })
            .above("edge_sky_depth", self.edge_sky_depth as f64, 0.0, 1e6)
            .below("min_depth", self.min_depth as f64, "edge_sky_depth", self.edge_sky_depth as f64)
            // The blur kernel is 8 sigma + 1 px wide.
            .within("edge_sigma", self.edge_sigma as f64, 0.0, 50.0)
            .above("edge_low_step", self.edge_low_step as f64, 1.0, 1e6)
            .above("edge_high_step", self.edge_high_step as f64, 1.0, 1e6)
            .check(self.edge_low_step.partial_cmp(&self.edge_high_step) != Some(Greater), "edge_low_step", || {
                format!("must be at most `edge_high_step` ({}), found {}", self.edge_high_step, self.edge_low_step)
            })
            // Distances are searched within it: pi * max^2 offsets per edge pixel.
            .above("edge_max_distance", self.edge_max_distance as f64, 0.0, 100.0)
            .done()
    }
}

impl Params {
    fn edges(&self) -> EdgeParams {
        EdgeParams {
            min_depth: self.min_depth,
            sky_threshold: self.sky_threshold,
            sky_depth: self.edge_sky_depth,
            sigma: self.edge_sigma,
            low_step: self.edge_low_step,
            high_step: self.edge_high_step,
            max_distance: self.edge_max_distance,
        }
    }
}

/// One image's scores against one reference.
#[derive(Serialize, Deserialize, Clone, Copy, Debug, PartialEq, Default)]
pub struct DepthMetrics {
    pub abs_rel: f64,
    pub sq_rel: f64,
    pub rmse: f64,
    pub rmse_log: f64,
    pub a1: f64,
    pub a2: f64,
    pub a3: f64,
    /// Share of scored pixels with relative error above 10% (absent in files of EvalDepth 2).
    #[serde(default)]
    pub bad_10: Option<f64>,
    /// Share of scored pixels with relative error above 25%.
    #[serde(default)]
    pub bad_25: Option<f64>,
    /// Reference pixels scored.
    pub pixels: u64,
}

/// Scores of `pred` against `reference` on the pixels `mask` allows (all when `None`); `None`
/// when no reference pixel is in range.
pub fn depth_metrics(
    params: &Params,
    pred: &DepthMap,
    reference: &DepthMap,
    mask: Option<&[bool]>,
    median_scaling: bool,
) -> Result<Option<DepthMetrics>> {
    let pairs = scored_pairs(params, pred, reference, mask)?;
    Ok(metrics_of(params, pairs, median_scaling))
}

/// (prediction, reference) of the pixels scored: reference in range and allowed by `mask`; a
/// missing prediction counts as `max_depth`.
fn scored_pairs(params: &Params, pred: &DepthMap, reference: &DepthMap, mask: Option<&[bool]>) -> Result<Vec<(f32, f32)>> {
    ensure_same_size(pred, reference)?;
    let (lo, hi) = (params.min_depth, params.max_depth);
    let mut pairs: Vec<(f32, f32)> = Vec::new();
    for (i, (&p, &r)) in pred.data.iter().zip(&reference.data).enumerate() {
        if r > lo && r < hi && mask.is_none_or(|m| m[i]) {
            pairs.push((if p.is_finite() { p } else { hi }, r));
        }
    }
    Ok(pairs)
}

/// The metrics of the scored pairs, the prediction first scaled by the ratio of the medians when
/// `median_scaling`; `None` without a pair.
fn metrics_of(params: &Params, mut pairs: Vec<(f32, f32)>, median_scaling: bool) -> Option<DepthMetrics> {
    let (lo, hi) = (params.min_depth, params.max_depth);
    if pairs.is_empty() {
        return None;
    }
    if median_scaling {
        let med = |mut v: Vec<f32>| {
            let mid = v.len() / 2;
            *v.select_nth_unstable_by(mid, f32::total_cmp).1
        };
        let ratio = med(pairs.iter().map(|x| x.1).collect()) / med(pairs.iter().map(|x| x.0.max(lo)).collect());
        for x in &mut pairs {
            x.0 *= ratio;
        }
    }
    let mut m = DepthMetrics::default();
    let (mut se, mut sel, mut bad_10, mut bad_25) = (0.0f64, 0.0f64, 0u64, 0u64);
    for &(p, r) in &pairs {
        let (p, r) = (p.clamp(lo, hi) as f64, r as f64);
        let thresh = (p / r).max(r / p);
        m.a1 += (thresh < 1.25) as u8 as f64;
        m.a2 += (thresh < 1.25f64.powi(2)) as u8 as f64;
        m.a3 += (thresh < 1.25f64.powi(3)) as u8 as f64;
        let rel = (p - r).abs() / r;
        m.abs_rel += rel;
        bad_10 += (rel > 0.10) as u64;
        bad_25 += (rel > 0.25) as u64;
        m.sq_rel += (p - r).powi(2) / r;
        se += (p - r).powi(2);
        sel += (p.ln() - r.ln()).powi(2);
    }
    let n = pairs.len() as f64;
    m.a1 /= n;
    m.a2 /= n;
    m.a3 /= n;
    m.abs_rel /= n;
    m.sq_rel /= n;
    m.rmse = (se / n).sqrt();
    m.rmse_log = (sel / n).sqrt();
    m.bad_10 = Some(bad_10 as f64 / n);
    m.bad_25 = Some(bad_25 as f64 / n);
    m.pixels = pairs.len() as u64;
    Some(m)
}

fn ensure_same_size(pred: &DepthMap, reference: &DepthMap) -> Result<()> {
    ensure!(
        pred.width == reference.width && pred.height == reference.height,
        "prediction is {}x{} but the reference is {}x{}",
        pred.width,
        pred.height,
        reference.width,
        reference.height
    );
    Ok(())
}

/// Scores against one reference: raw and median-scaled, and for a dense reference the sky and
/// boundary metrics (absent from the JSON otherwise).
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
pub struct Scores {
    pub raw: DepthMetrics,
    pub median_scaled: DepthMetrics,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sky: Option<SkyMetrics>,
    /// Absent also when the reference has no depth edge.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub boundary: Option<BoundaryMetrics>,
}

/// What `EvalDepth` writes for one image: scores per reference (absent references left out).
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq, Default)]
pub struct ImageScores {
    #[serde(default, skip_serializing_if = "std::collections::BTreeMap::is_empty")]
    pub against: std::collections::BTreeMap<String, Scores>,
}

/// Whether a reference has a value at every pixel (a depth, or +inf for sky), and so says where
/// the sky and the depth edges are, or only at some (0 elsewhere: no measurement).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Coverage {
    Dense,
    Sparse,
}

pub fn evaluate(
    params: &Params,
    pred: &DepthMap,
    references: &[(&str, Option<&DepthMap>, Coverage)],
) -> Result<ImageScores> {
    let mut out = ImageScores::default();
    for &(name, reference, coverage) in references {
        // An empty reference: the dataset has none.
        let Some(r) = reference.filter(|r| r.width > 0 && r.height > 0) else { continue };
        // The pairs once for both (copied, not gathered again, for the scaled metrics).
        let pairs = scored_pairs(params, pred, r, None).with_context(|| format!("against `{name}`"))?;
        let (Some(raw), Some(median_scaled)) =
            (metrics_of(params, pairs.clone(), false), metrics_of(params, pairs, true))
        else {
            continue;
        };
        let mut scores = Scores { raw, median_scaled, sky: None, boundary: None };
        if coverage == Coverage::Dense {
            let p = params;
            scores.sky = Some(sky_metrics(pred, r, p.sky_threshold, p.structure_depth, p.min_depth));
            scores.boundary = boundary_metrics(&p.edges(), pred, r);
        }
        out.against.insert(name.to_string(), scores);
    }
    Ok(out)
}

crate::inputs! {
    pub struct Inputs {
        /// the depth to score
        depth: One<DepthMap>,
        /// dense ground truth, +inf = sky (empty = the dataset has none); the only reference
        /// with sky and boundary metrics
        gt: Optional<DepthMap>,
        /// single-sweep LiDAR projection of the target frame
        lidar: Optional<DepthMap>,
        /// multi-frame aggregated LiDAR projection
        lidar_multi: Optional<DepthMap>,
        /// projection of held-out LiDAR points
        holdout: Optional<DepthMap>,
        /// the ground truth above the LiDAR's field of view (AboveLidarFov of `gt`)
        gt_above_lidar: Optional<DepthMap>,
        /// the ground truth on moving objects (OnMovingObjects of `gt`)
        gt_moving: Optional<DepthMap>,
    }
}

crate::outputs! {
    pub struct Outputs {
        /// scores per reference (JSON); `dist4d eval` tabulates them
        json: One<File>,
    }
}

pub struct EvalDepth(Params);

impl Stage for EvalDepth {
    const KIND: &'static str = "EvalDepth";
    const VERSION: u32 = 5;
    const SUMMARY: &'static str = "Dense depth -> Abs Rel, Sq Rel, RMSE, RMSE log, delta<1.25^k, bad-pixel rates (raw and \
         median-scaled) per reference; sky IoU and misses, depth-boundary accuracy and completeness against a dense one; as JSON";
    const GRAINS: &'static [&'static str] = &["camera"];
    type Params = Params;
    type Inputs = Inputs;
    type Outputs = Outputs;
    fn new(params: Params) -> Result<Self> {
        Ok(EvalDepth(params))
    }
    fn run(&self, _: &TaskContext, i: Inputs) -> Result<Made<Outputs>> {
        use Coverage::*;
        let references = [
            ("gt", i.gt.as_ref(), Dense),
            ("lidar", i.lidar.as_ref(), Sparse),
            ("lidar_multi", i.lidar_multi.as_ref(), Sparse),
            ("holdout", i.holdout.as_ref(), Sparse),
            ("gt_above_lidar", i.gt_above_lidar.as_ref(), Sparse),
            ("gt_moving", i.gt_moving.as_ref(), Sparse),
        ];
        let scores = evaluate(&self.0, &i.depth, &references)?;
        Ok(Outputs { json: File(serde_json::to_vec_pretty(&scores)?) }.into())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn map(data: Vec<f32>) -> DepthMap {
        DepthMap { width: data.len() as u32, height: 1, data }
    }

    #[test]
    fn metrics_match_hand_computed_values() {
        let pred = map(vec![10.0, 22.0, 0.0, 5.0]);
        let gt = map(vec![10.0, 20.0, 40.0, 100.0]); // 100 m is out of range
        let m = depth_metrics(&Params::default(), &pred, &gt, None, false).unwrap().unwrap();
        assert_eq!(m.pixels, 3);
        // Missing prediction counts as 0.1 m.
        let abs_rel = (0.0 + 2.0 / 20.0 + 39.9 / 40.0) / 3.0;
        assert!((m.abs_rel - abs_rel).abs() < 1e-6, "{}", m.abs_rel);
        let rmse = ((0.0 + 4.0 + 39.9f64.powi(2)) / 3.0).sqrt();
        assert!((m.rmse - rmse).abs() < 1e-4);
        assert!((m.a1 - 2.0 / 3.0).abs() < 1e-12 && (m.a3 - 2.0 / 3.0).abs() < 1e-12);
        let sq_rel = (4.0 / 20.0 + 39.9f64.powi(2) / 40.0) / 3.0;
        assert!((m.sq_rel - sq_rel).abs() < 1e-4);
        // Relative errors 0, 0.1 (not above 10%), 0.9975.
        assert_eq!((m.bad_10, m.bad_25), (Some(1.0 / 3.0), Some(1.0 / 3.0)));
    }

    #[test]
    fn bad_pixel_rates_count_exactly_the_pixels_off_by_more_than_10_and_25_percent() {
        // 20 pixels at 10 m: errors of 0%, 5%, 10.5%, 20%, 30% and -40%, four of each but the
        // last two kinds; one more reference pixel out of range (90 m) is not scored.
        let mut gt = vec![10.0f32; 20];
        gt.push(90.0);
        let mut pred = vec![10.0; 4];
        pred.extend([10.5; 4]);
        pred.extend([11.05; 4]);
        pred.extend([12.0; 4]);
        pred.extend([13.0; 2]);
        pred.extend([6.0; 2]);
        pred.push(1.0);
        let m = depth_metrics(&Params::default(), &map(pred), &map(gt), None, false).unwrap().unwrap();
        assert_eq!(m.pixels, 20);
        assert_eq!(m.bad_10, Some(12.0 / 20.0));
        assert_eq!(m.bad_25, Some(4.0 / 20.0));
    }

    #[test]
    fn median_scaling_removes_a_global_scale() {
        let gt = map((1..40).map(|i| i as f32).collect()); // doubled, still below 80 m
        let pred = map(gt.data.iter().map(|z| z * 2.0).collect());
        let raw = depth_metrics(&Params::default(), &pred, &gt, None, false).unwrap().unwrap();
        let scaled = depth_metrics(&Params::default(), &pred, &gt, None, true).unwrap().unwrap();
        assert!((raw.abs_rel - 1.0).abs() < 1e-3);
        assert!(scaled.abs_rel < 1e-6 && scaled.a1 == 1.0);
    }

    #[test]
    fn absent_or_empty_references_are_left_out() {
        let pred = map(vec![10.0, 20.0]);
        let gt = map(vec![10.0, 25.0]);
        let refs = [
            ("gt", Some(&gt), Coverage::Dense),
            ("lidar", None, Coverage::Sparse),
            ("gt_above_lidar", Some(&DepthMap::new(0, 0)), Coverage::Sparse),
        ];
        let scores = evaluate(&Params::default(), &pred, &refs).unwrap();
        assert_eq!(scores.against.keys().collect::<Vec<_>>(), vec!["gt"]);
        let small = map(vec![1.0]);
        let err = evaluate(&Params::default(), &pred, &[("holdout", Some(&small), Coverage::Sparse)]).unwrap_err();
        assert!(format!("{err:#}").contains("against `holdout`"), "{err:#}");
    }

    #[test]
    fn sky_and_boundary_metrics_only_against_a_dense_reference() {
        // Sky in the top 10 of 40 rows, a wall at 20 m with a near box in it.
        let (w, h) = (64u32, 40u32);
        let gt = DepthMap {
            width: w,
            height: h,
            data: (0..w * h)
                .map(|i| match (i % w, i / w) {
                    (_, y) if y < 10 => f32::INFINITY,
                    (x, y) if y >= 20 && (20..40).contains(&x) => 8.0,
                    _ => 20.0,
                })
                .collect(),
        };
        let pred = DepthMap { data: gt.data.iter().map(|&z| z.min(100.0)).collect(), ..gt.clone() };
        let refs = [("gt", Some(&gt), Coverage::Dense), ("lidar", Some(&gt), Coverage::Sparse)];
        let scores = evaluate(&Params::default(), &pred, &refs).unwrap();
        let dense = &scores.against["gt"];
        let sky = dense.sky.unwrap();
        assert_eq!((sky.iou, sky.sky_as_structure, sky.structure_as_sky), (Some(1.0), Some(0.0), Some(0.0)));
        let b = dense.boundary.unwrap();
        assert_eq!((b.accuracy, b.completeness), (0.0, 0.0));
        assert!(b.reference_edges > 0);
        let sparse = &scores.against["lidar"];
        assert_eq!((sparse.sky, sparse.boundary), (None, None));
        // Absent, not 0, in the JSON; and files of EvalDepth 2 still read.
        let json = serde_json::to_string(&scores).unwrap();
        assert_eq!(json.matches("\"sky\"").count(), 1, "{json}");
        let old = r#"{"against":{"lidar":{"raw":{"abs_rel":0.1,"sq_rel":0.1,"rmse":1,"rmse_log":0.1,"a1":0.9,"a2":0.95,
            "a3":0.99,"pixels":5},"median_scaled":{"abs_rel":0.1,"sq_rel":0.1,"rmse":1,"rmse_log":0.1,"a1":0.9,"a2":0.95,
            "a3":0.99,"pixels":5}}}}"#;
        let old: ImageScores = serde_json::from_str(old).unwrap();
        assert_eq!(old.against["lidar"].raw.bad_10, None);
    }

    #[test]
    fn param_ranges() {
        let bad = Params { structure_depth: 120.0, edge_low_step: 1.5, edge_sigma: -1.0, ..Params::default() };
        let fields: Vec<&str> = bad.validate().iter().map(|p| p.field).collect();
        assert_eq!(fields, ["structure_depth", "edge_sigma", "edge_low_step"]);
        assert!(Params::default().validate().is_empty());
    }
}
