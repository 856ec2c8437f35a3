//! Depth-boundary errors (iBims-1: Koch, Liebel, Fraundorfer, Koerner 2018, "Evaluation of
//! CNN-based single-image depth estimation methods"): are the depth edges of the prediction where
//! the reference's are, and are all of the reference's there?
//!
//! Edges of both maps come from the same detector ([`super::canny`]) on log depth: sky (non-finite,
//! or at or beyond `sky_threshold`) is set to `sky_depth` (100 m) and every depth clamped to
//! [`min_depth`, `sky_depth`] first, so the horizon is one edge in both and the depth of a far
//! surface does not matter beyond 100 m. Log depth makes a threshold a depth *ratio*: the
//! thresholds are stated as sharp steps, `edge_high_step` (1.25: a 25% depth jump starts an edge)
//! and `edge_low_step` (1.1: an edge continues through 10% jumps), blurred by `edge_sigma` (sqrt 2 px,
//! as iBims-1). Distances are Euclidean in pixels (exact: the offsets within the cap are visited
//! nearest first, the same as a distance transform but cheaper for sparse edges), capped at
//! `max_distance` (10 px, at most 100 px):
//!
//! - accuracy: the mean over predicted edge pixels of the distance to the nearest reference edge
//!   (spurious edges, such as the streaks of a column-wise fill, cost up to 10 px each);
//! - completeness: the mean over reference edge pixels of the distance to the nearest predicted
//!   edge (missing or blurred edges).
//!
//! No reference edge: both undefined (`None`), as in iBims-1. No predicted edge: both 10 px.
//!
//! Followed: `compute_depth_boundary_error` of the official iBims-1 evaluation script
//! (`evaluate_ibims_error_metrics.py`, Tobias Koch 2018; read in the copy at
//! github.com/bulatko/DepthART, `mde/capsules/meter/ibims_official/`). Differences, on purpose:
//! iBims-1 compares with hand-drawn reference edges, here both edge maps come from the detector;
//! it runs Canny on linear depth normalized to [0, 1] per image (`skimage.feature.canny`, sigma
//! sqrt 2, thresholds 0.1 / 0.2), here on log depth with fixed step thresholds, so that the same
//! jump is an edge in every image whatever its depth range (normalized over a street's 0.1-100 m,
//! only jumps of about 10 m and more would start an edge: a car 8 m before a wall would not); and
//! it leaves predicted edges farther than 10 px out of the accuracy and does not cap completeness,
//! where here both are capped: a streak far from any true edge is the defect this metric is here
//! to see, and one missing edge should not outweigh all the others.

use super::canny::{canny, step_response};
use super::sky::is_sky;
use dist4d_types::artifact::DepthMap;
use serde::{Deserialize, Serialize};

/// How edges are found and distances measured.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EdgeParams {
    pub min_depth: f32,
    pub sky_threshold: f32,
    pub sky_depth: f32,
    pub sigma: f32,
    pub low_step: f32,
    pub high_step: f32,
    pub max_distance: f32,
}

/// The iBims-1 protocol as EvalDepth runs it by default: depths from 0.1 m, sky at or beyond 99 m
/// set to 100 m, Gaussian sigma sqrt 2, steps 1.25 / 1.1, distances capped at 10 px.
impl Default for EdgeParams {
    fn default() -> Self {
        EdgeParams {
            min_depth: 0.1,
            sky_threshold: 99.0,
            sky_depth: 100.0,
            sigma: std::f32::consts::SQRT_2,
            low_step: 1.1,
            high_step: 1.25,
            max_distance: 10.0,
        }
    }
}

/// One image's depth-boundary errors against one dense reference, in pixels.
#[derive(Serialize, Deserialize, Clone, Copy, Debug, PartialEq, Default)]
pub struct BoundaryMetrics {
    /// Mean distance of predicted edge pixels to the nearest reference edge (capped).
    pub accuracy: f64,
    /// Mean distance of reference edge pixels to the nearest predicted edge (capped).
    pub completeness: f64,
    pub predicted_edges: u64,
    pub reference_edges: u64,
}

/// The edge pixels of `depth` (row-major).
pub fn depth_edges(p: &EdgeParams, depth: &DepthMap) -> Vec<bool> {
    let log: Vec<f32> = depth
        .data
        .iter()
        .map(|&z| {
            let z = if is_sky(z, p.sky_threshold) { p.sky_depth } else { z.clamp(p.min_depth, p.sky_depth) };
            z.ln()
        })
        .collect();
    let unit = step_response(p.sigma);
    let (low, high) = (p.low_step.ln() * unit, p.high_step.ln() * unit);
    canny(&log, depth.width as usize, depth.height as usize, p.sigma, low, high)
}

/// The mean over the pixels of `from` of the Euclidean distance (px) to the nearest pixel of `to`,
/// capped at `cap` (both masks `w x h`; 0 when `from` is empty). Exactly what a distance transform
/// of `to` would give, found by visiting the offsets within `cap` nearest first, which costs less
/// than a whole transform when edges are a few percent of the pixels.
pub fn mean_capped_distance(from: &[bool], to: &[bool], w: usize, h: usize, cap: f32) -> f64 {
    let reach = cap.floor() as i64;
    let mut offsets: Vec<(i64, i64, i64)> = (-reach..=reach)
        .flat_map(|dy| (-reach..=reach).map(move |dx| (dx * dx + dy * dy, dx, dy)))
        .filter(|&(d2, _, _)| (d2 as f32) <= cap * cap)
        .collect();
    offsets.sort_unstable();
    let (mut sum, mut n) = (0f64, 0u64);
    for (i, _) in from.iter().enumerate().filter(|(_, &f)| f) {
        let (x, y) = ((i % w) as i64, (i / w) as i64);
        let nearest = offsets.iter().find(|&&(_, dx, dy)| {
            let (nx, ny) = (x + dx, y + dy);
            nx >= 0 && ny >= 0 && nx < w as i64 && ny < h as i64 && to[ny as usize * w + nx as usize]
        });
        sum += nearest.map_or(cap as f64, |&(d2, _, _)| (d2 as f64).sqrt().min(cap as f64));
        n += 1;
    }
    if n == 0 {
        0.0
    } else {
        sum / n as f64
    }
}

/// Boundary errors of `pred` against the dense `reference` (same size, checked by the caller);
/// `None` when the reference has no edge.
pub fn boundary_metrics(p: &EdgeParams, pred: &DepthMap, reference: &DepthMap) -> Option<BoundaryMetrics> {
    let (w, h) = (reference.width as usize, reference.height as usize);
    let ref_edges = depth_edges(p, reference);
    let reference_edges = ref_edges.iter().filter(|&&e| e).count() as u64;
    if reference_edges == 0 {
        return None;
    }
    let pred_edges = depth_edges(p, pred);
    let predicted_edges = pred_edges.iter().filter(|&&e| e).count() as u64;
    if predicted_edges == 0 {
        let cap = p.max_distance as f64;
        return Some(BoundaryMetrics { accuracy: cap, completeness: cap, predicted_edges, reference_edges });
    }
    let cap = p.max_distance;
    Some(BoundaryMetrics {
        accuracy: mean_capped_distance(&pred_edges, &ref_edges, w, h, cap),
        completeness: mean_capped_distance(&ref_edges, &pred_edges, w, h, cap),
        predicted_edges,
        reference_edges,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn params() -> EdgeParams {
        EdgeParams {
            min_depth: 0.1,
            sky_threshold: 99.0,
            sky_depth: 100.0,
            sigma: 2f32.sqrt(),
            low_step: 1.1,
            high_step: 1.25,
            max_distance: 10.0,
        }
    }

    /// A 120 x 60 scene: sky in the top 15 rows, a wall at 40 m, a box at 10 m in columns 40-79
    /// from row 30 down.
    fn scene() -> DepthMap {
        let (w, h) = (120u32, 60u32);
        let data = (0..w * h)
            .map(|i| {
                let (x, y) = (i % w, i / w);
                if y < 15 {
                    f32::INFINITY
                } else if y >= 30 && (40..80).contains(&x) {
                    10.0
                } else {
                    40.0
                }
            })
            .collect();
        DepthMap { width: w, height: h, data }
    }

    #[test]
    fn a_prediction_equal_to_the_reference_has_no_boundary_error() {
        let gt = scene();
        let mut pred = gt.clone();
        // The completion's sky value instead of +inf: the same sky.
        pred.data.iter_mut().filter(|z| z.is_infinite()).for_each(|z| *z = 100.0);
        let m = boundary_metrics(&params(), &pred, &gt).unwrap();
        assert_eq!((m.accuracy, m.completeness), (0.0, 0.0));
        assert_eq!(m.predicted_edges, m.reference_edges);
        // The horizon, the box's top and its two sides are edges.
        let edges = depth_edges(&params(), &gt);
        let w = 120;
        assert!(edges[20 * w + 20..].iter().step_by(w).all(|&e| !e), "the plain wall below the horizon has none");
        assert!(edges[45 * w + 39] || edges[45 * w + 40], "the box's left side");
        assert!(edges[14 * w + 60] && edges[29 * w + 60], "the horizon and the box top");
    }

    #[test]
    fn vertical_streaks_cost_accuracy_a_shifted_edge_costs_both() {
        let gt = scene();
        let w = 120;
        // Streaks: bands 3 px wide every 12 columns of the wall 50% too far, as a column-wise
        // fill leaves them.
        let mut streaky = gt.clone();
        for (i, z) in streaky.data.iter_mut().enumerate() {
            if *z == 40.0 && (4..7).contains(&((i % w) % 12)) {
                *z = 60.0;
            }
        }
        let clean = boundary_metrics(&params(), &gt, &gt).unwrap();
        let streaks = boundary_metrics(&params(), &streaky, &gt).unwrap();
        assert!(streaks.accuracy > clean.accuracy + 3.0, "{streaks:?}");
        assert!(streaks.completeness < 1.0, "the true edges are all still there: {streaks:?}");
        // The box 3 px to the right: its sides 3 px off, its top along it unchanged.
        let shifted = DepthMap {
            data: (0..gt.data.len()).map(|i| if i % w >= 3 { gt.data[i - 3] } else { gt.data[i] }).collect(),
            ..gt.clone()
        };
        let m = boundary_metrics(&params(), &shifted, &gt).unwrap();
        assert!(m.accuracy > 0.3 && m.accuracy < 3.0 && m.completeness > 0.3 && m.completeness < 3.0, "{m:?}");
    }

    #[test]
    fn no_reference_edge_is_undefined_and_no_predicted_edge_costs_the_cap() {
        let flat = DepthMap { width: 30, height: 20, data: vec![20.0; 600] };
        assert_eq!(boundary_metrics(&params(), &flat, &flat), None);
        let m = boundary_metrics(&params(), &flat, &scene_small()).unwrap();
        assert_eq!((m.accuracy, m.completeness, m.predicted_edges), (10.0, 10.0, 0));
    }

    fn scene_small() -> DepthMap {
        DepthMap { width: 30, height: 20, data: (0..600).map(|i| if i % 30 < 15 { 5.0 } else { 20.0 }).collect() }
    }

    #[test]
    fn distances_are_euclidean_capped_and_agree_with_a_distance_transform() {
        let (w, h) = (30, 20);
        let mut to = vec![false; w * h];
        to[10 * w + 5] = true;
        let at = |x: usize, y: usize| {
            let mut from = vec![false; w * h];
            from[y * w + x] = true;
            mean_capped_distance(&from, &to, w, h, 10.0)
        };
        assert_eq!((at(5, 10), at(9, 13), at(29, 10)), (0.0, 5.0, 10.0));
        assert_eq!(mean_capped_distance(&to, &vec![false; w * h], w, h, 10.0), 10.0);
        // Random masks: the same as the exact transform NearestFill uses, capped.
        let mut rng = dist4d_types::rng::Rng::new(4);
        let mut seeds = DepthMap::new(w as u32, h as u32);
        let from: Vec<bool> = seeds
            .data
            .iter_mut()
            .map(|s| {
                *s = (rng.below(40) == 0) as u8 as f32;
                rng.below(5) == 0
            })
            .collect();
        let to: Vec<bool> = seeds.data.iter().map(|&s| s > 0.0).collect();
        let nearest = crate::curation::nearest_fill::nearest_seed(&seeds);
        let (mut sum, mut n) = (0.0, 0);
        for i in (0..w * h).filter(|&i| from[i]) {
            let s = nearest[i] as usize;
            let d = ((i % w) as f64 - (s % w) as f64).hypot((i / w) as f64 - (s / w) as f64);
            sum += d.min(4.5);
            n += 1;
        }
        assert!((mean_capped_distance(&from, &to, w, h, 4.5) - sum / n as f64).abs() < 1e-9);
    }
}
