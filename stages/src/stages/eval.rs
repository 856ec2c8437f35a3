//! `EvalDepth` and the depth metrics: a dense depth scored against reference depths.
//!
//! The metrics of Eigen et al. (2014) as monodepth2 / SurroundDepth compute them: over reference
//! pixels with depth in [`min_depth`, `max_depth`] (default 0.1-80 m), the prediction clamped to
//! the same range (so a missing prediction, 0, counts as `min_depth`), Abs Rel, Sq Rel, RMSE,
//! RMSE log and the share with max(pred/ref, ref/pred) below 1.25, 1.25^2, 1.25^3; optionally
//! after scaling the prediction by median(ref) / median(pred) per image. Metrics are per image;
//! `dist4d eval` averages them per camera, then over cameras.
//!
//! References, each an optional input: `gt` (a dense ground truth, e.g. the synthetic world's;
//! an empty map means the dataset has none), `lidar` (the target frame's single-sweep
//! projection), `lidar_multi` (the aggregated multi-frame projection, DiST-4D Table 7) and
//! `holdout` (held-out LiDAR points the curation never saw), and `gt_above_lidar` (the ground
//! truth only where it lies above the LiDAR's vertical field of view, from `AboveLidarFov`: where
//! LiDAR cannot help and MVS must).

use crate::artifact::{DepthMap, File};
use crate::stage::{maybe_one, one, optional_input, StageDef, TypedOp};
use anyhow::{ensure, Context, Result};
use dist4d_graph::{ParamChecks, ParamProblem, PortSpec, Validate};
use serde::{Deserialize, Serialize};

#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    pub min_depth: f32,
    pub max_depth: f32,
}

impl Default for Params {
    fn default() -> Self {
        Params { min_depth: 0.1, max_depth: 80.0 }
    }
}

impl Validate for Params {
    fn validate(&self) -> Vec<ParamProblem> {
        // A positive minimum: the metrics divide by the reference and take logs of both.
        ParamChecks::new()
            .above("min_depth", self.min_depth as f64, 0.0, 1e6)
            .above("max_depth", self.max_depth as f64, 0.0, 1e6)
            .below("min_depth", self.min_depth as f64, "max_depth", self.max_depth as f64)
            .done()
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
    /// Reference pixels scored.
    pub pixels: u64,
}

impl DepthMetrics {
    pub const NAMES: [&'static str; 7] = ["abs_rel", "sq_rel", "rmse", "rmse_log", "a1", "a2", "a3"];
    pub fn values(&self) -> [f64; 7] {
        [self.abs_rel, self.sq_rel, self.rmse, self.rmse_log, self.a1, self.a2, self.a3]
    }
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
    ensure!(
        pred.width == reference.width && pred.height == reference.height,
        "prediction is {}x{} but the reference is {}x{}",
        pred.width,
        pred.height,
        reference.width,
        reference.height
    );
    let (lo, hi) = (params.min_depth, params.max_depth);
    let mut pairs: Vec<(f32, f32)> = Vec::new();
    for (i, (&p, &r)) in pred.data.iter().zip(&reference.data).enumerate() {
        if r > lo && r < hi && mask.is_none_or(|m| m[i]) {
            pairs.push((if p.is_finite() { p } else { hi }, r));
        }
    }
    if pairs.is_empty() {
        return Ok(None);
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
    let (mut se, mut sel) = (0.0f64, 0.0f64);
    for &(p, r) in &pairs {
        let (p, r) = (p.clamp(lo, hi) as f64, r as f64);
        let thresh = (p / r).max(r / p);
        m.a1 += (thresh < 1.25) as u8 as f64;
        m.a2 += (thresh < 1.25f64.powi(2)) as u8 as f64;
        m.a3 += (thresh < 1.25f64.powi(3)) as u8 as f64;
        m.abs_rel += (p - r).abs() / r;
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
    m.pixels = pairs.len() as u64;
    Ok(Some(m))
}

/// Raw and median-scaled scores against one reference.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
pub struct Scores {
    pub raw: DepthMetrics,
    pub median_scaled: DepthMetrics,
}

/// What `EvalDepth` writes for one image: scores per reference (absent references left out).
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq, Default)]
pub struct ImageScores {
    #[serde(default, skip_serializing_if = "std::collections::BTreeMap::is_empty")]
    pub against: std::collections::BTreeMap<String, Scores>,
}

pub fn evaluate(params: &Params, pred: &DepthMap, references: &[(&str, Option<&DepthMap>)]) -> Result<ImageScores> {
    let mut out = ImageScores::default();
    for &(name, reference) in references {
        // An empty reference: the dataset has none.
        let Some(r) = reference.filter(|r| r.width > 0 && r.height > 0) else { continue };
        let scores = (depth_metrics(params, pred, r, None, false), depth_metrics(params, pred, r, None, true));
        let context = || format!("against `{name}`");
        if let (Some(raw), Some(median_scaled)) = (scores.0.with_context(context)?, scores.1.with_context(context)?) {
            out.against.insert(name.to_string(), Scores { raw, median_scaled });
        }
    }
    Ok(out)
}

/// The reference inputs, in port order after `depth`.
const REFERENCES: [&str; 5] = ["gt", "lidar", "lidar_multi", "holdout", "gt_above_lidar"];

struct Op(Params);

impl TypedOp for Op {
    fn run(
        &self,
        _ctx: &dist4d_runtime::TaskContext,
        inputs: &[Vec<dist4d_runtime::Artifact>],
    ) -> Result<Vec<Vec<u8>>> {
        let pred = one::<DepthMap>(inputs, 0)?;
        let refs: Vec<Option<DepthMap>> = (1..6).map(|i| maybe_one::<DepthMap>(inputs, i)).collect::<Result<_>>()?;
        let list: Vec<(&str, Option<&DepthMap>)> =
            REFERENCES.iter().zip(&refs).map(|(n, r)| (*n, r.as_ref())).collect();
        let scores = evaluate(&self.0, &pred, &list)?;
        use crate::artifact::Artifact;
        Ok(vec![File(serde_json::to_vec_pretty(&scores)?).encode()])
    }
}

pub fn def() -> StageDef {
    StageDef::new::<Params>(
        "EvalDepth",
        2,
        "Dense depth -> Abs Rel, Sq Rel, RMSE, RMSE log, delta<1.25^k (raw and median-scaled) per reference, as JSON",
        vec![
            crate::stage::input::<DepthMap>("depth", "the depth to score"),
            optional_input::<DepthMap>("gt", "dense ground truth (empty = the dataset has none)"),
            optional_input::<DepthMap>("lidar", "single-sweep LiDAR projection of the target frame"),
            optional_input::<DepthMap>("lidar_multi", "multi-frame aggregated LiDAR projection"),
            optional_input::<DepthMap>("holdout", "projection of held-out LiDAR points"),
            optional_input::<DepthMap>(
                "gt_above_lidar",
                "the ground truth above the LiDAR's field of view (AboveLidarFov of `gt`)",
            ),
        ],
        vec![PortSpec::one("json", "File", "scores per reference (JSON); `dist4d eval` tabulates them")],
        vec!["camera"],
        |p: Params| Ok(Box::new(Op(p))),
    )
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
        let refs = [("gt", Some(&gt)), ("lidar", None), ("gt_above_lidar", Some(&DepthMap::new(0, 0)))];
        let scores = evaluate(&Params::default(), &pred, &refs).unwrap();
        assert_eq!(scores.against.keys().collect::<Vec<_>>(), vec!["gt"]);
        let small = map(vec![1.0]);
        let err = evaluate(&Params::default(), &pred, &[("holdout", Some(&small))]).unwrap_err();
        assert!(format!("{err:#}").contains("against `holdout`"), "{err:#}");
    }
}

/// Per-image scores averaged per camera, then over cameras (SurroundDepth): for each reference
/// and for raw / median-scaled, rows `(camera, images, mean metrics)` and a final `mean` row.
pub fn tabulate(images: &[(String, ImageScores)]) -> String {
    use std::collections::BTreeMap;
    // reference -> camera -> (raw sums, scaled sums, count)
    let mut acc: BTreeMap<&str, BTreeMap<&str, ([f64; 7], [f64; 7], usize)>> = BTreeMap::new();
    let mut camera_order: Vec<&str> = Vec::new();
    for (camera, s) in images {
        if !camera_order.contains(&camera.as_str()) {
            camera_order.push(camera);
        }
        for (reference, scores) in &s.against {
            let e = acc.entry(reference).or_default().entry(camera).or_insert(([0.0; 7], [0.0; 7], 0));
            for k in 0..7 {
                e.0[k] += scores.raw.values()[k];
                e.1[k] += scores.median_scaled.values()[k];
            }
            e.2 += 1;
        }
    }
    let mut out = String::new();
    for (reference, cams) in &acc {
        for (mode, pick) in [("raw", 0usize), ("median-scaled", 1)] {
            out.push_str(&format!("\n{reference} ({mode})\n"));
            out.push_str("| camera | images | abs_rel | sq_rel | rmse | rmse_log | d<1.25 | d<1.25^2 | d<1.25^3 |\n");
            out.push_str("| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |\n");
            let mut mean = [0.0; 7];
            let mut n_cams = 0usize;
            let mut n_images = 0usize;
            for cam in camera_order.iter().filter(|c| cams.contains_key(*c)) {
                let (raw, scaled, n) = &cams[cam];
                let sums = if pick == 0 { raw } else { scaled };
                let m: Vec<f64> = sums.iter().map(|s| s / *n as f64).collect();
                for k in 0..7 {
                    mean[k] += m[k];
                }
                n_cams += 1;
                n_images += n;
                out.push_str(&format_row(cam, *n, &m));
            }
            let m: Vec<f64> = mean.iter().map(|s| s / n_cams.max(1) as f64).collect();
            out.push_str(&format_row("mean", n_images, &m));
        }
    }
    out
}

fn format_row(name: &str, n: usize, m: &[f64]) -> String {
    format!(
        "| {name} | {n} | {:.4} | {:.4} | {:.3} | {:.4} | {:.4} | {:.4} | {:.4} |\n",
        m[0], m[1], m[2], m[3], m[4], m[5], m[6]
    )
}

#[cfg(test)]
mod table_tests {
    use super::*;

    #[test]
    fn cameras_are_averaged_per_camera_then_together() {
        let s = |abs_rel: f64| {
            let m = DepthMetrics { abs_rel, a1: 1.0, pixels: 10, ..Default::default() };
            let mut x = ImageScores::default();
            x.against.insert("gt".into(), Scores { raw: m, median_scaled: m });
            x
        };
        // CAM_A: 0.1, 0.3 -> 0.2; CAM_B: 0.4 -> mean of cameras 0.3 (not 0.8 / 3).
        let t = tabulate(&[("CAM_A".into(), s(0.1)), ("CAM_A".into(), s(0.3)), ("CAM_B".into(), s(0.4))]);
        assert!(t.contains("| CAM_A | 2 | 0.2000 |"), "{t}");
        assert!(t.contains("| mean | 3 | 0.3000 |"), "{t}");
        assert!(t.contains("gt (median-scaled)"));
    }
}
