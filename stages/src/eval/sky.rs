//! Sky metrics: does the dense depth put the sky where a dense reference has it?
//!
//! Depth alone says what is sky: the completion gives sky pixels `sky_depth` (100 m, the paper's
//! value), so a prediction at or beyond `sky_threshold` (99 m) is predicted sky. In the reference
//! a pixel is sky when it is not finite (the synthetic ground truth writes +inf where a ray meets
//! nothing within 1000 m). Finite reference depths at or beyond `sky_threshold` (far ground and
//! facades) are left out of every sky score, as are pixels of 0 (no reference): a completion
//! capped at 100 m may call them sky or structure and be right either way. (Counting them as
//! sky, as a first version did, charged every far facade completed at 75 m as "sky given a
//! structure depth": 2.4 of the 3.6 points of that share on synthetic seed 0.) Only a dense reference says where the sky
//! is; sparse ones (LiDAR) have no sky information and get no sky metrics.

use dist4d_types::artifact::DepthMap;
use serde::{Deserialize, Serialize};

/// One image's sky scores against one dense reference; a share is `None` when it would divide by 0.
#[derive(Serialize, Deserialize, Clone, Copy, Debug, PartialEq, Default)]
pub struct SkyMetrics {
    /// Intersection over union of predicted and reference sky (`None`: neither has sky).
    pub iou: Option<f64>,
    /// Share of reference-sky pixels predicted nearer than `structure_depth` (a wall in the sky).
    pub sky_as_structure: Option<f64>,
    /// Share of reference-structure pixels (depth in (`min_depth`, `structure_depth`)) predicted
    /// at or beyond `sky_threshold` (sky where there is something).
    pub structure_as_sky: Option<f64>,
    /// Reference-sky pixels.
    pub sky_pixels: u64,
    /// Predicted-sky pixels (where the reference has a value).
    pub predicted_sky_pixels: u64,
    /// Pixels sky in both (the IoU's intersection).
    pub both_sky_pixels: u64,
    /// Reference-sky pixels predicted nearer than `structure_depth`.
    pub sky_as_structure_pixels: u64,
    /// Reference-structure pixels.
    pub structure_pixels: u64,
    /// Reference-structure pixels predicted as sky.
    pub structure_as_sky_pixels: u64,
}

impl SkyMetrics {
    /// The scores of several images taken as one (their pixel counts summed), as a dataset's
    /// segmentation IoU is (Cityscapes, PASCAL VOC): an image with a sliver of sky weighs as
    /// much as its sliver, not as much as an image of open sky.
    pub fn pooled<'a>(images: impl IntoIterator<Item = &'a SkyMetrics>) -> SkyMetrics {
        let mut sum = SkyMetrics::default();
        for m in images {
            sum.sky_pixels += m.sky_pixels;
            sum.predicted_sky_pixels += m.predicted_sky_pixels;
            sum.both_sky_pixels += m.both_sky_pixels;
            sum.sky_as_structure_pixels += m.sky_as_structure_pixels;
            sum.structure_pixels += m.structure_pixels;
            sum.structure_as_sky_pixels += m.structure_as_sky_pixels;
        }
        sum.with_shares()
    }

    /// The shares from the pixel counts.
    fn with_shares(mut self) -> SkyMetrics {
        let share = |n: u64, of: u64| (of > 0).then(|| n as f64 / of as f64);
        self.iou = share(self.both_sky_pixels, self.sky_pixels + self.predicted_sky_pixels - self.both_sky_pixels);
        self.sky_as_structure = share(self.sky_as_structure_pixels, self.sky_pixels);
        self.structure_as_sky = share(self.structure_as_sky_pixels, self.structure_pixels);
        self
    }
}

/// Whether depth `z` means sky: not below `threshold` (+inf and NaN included, 0 not).
#[inline]
pub fn is_sky(z: f32, threshold: f32) -> bool {
    z >= threshold || z.is_nan()
}

/// Sky scores of `pred` against the dense `reference` (same size, checked by the caller).
pub fn sky_metrics(
    pred: &DepthMap,
    reference: &DepthMap,
    sky_threshold: f32,
    structure_depth: f32,
    min_depth: f32,
) -> SkyMetrics {
    let (mut both, mut pred_sky, mut ref_sky, mut sky_near) = (0u64, 0u64, 0u64, 0u64);
    let (mut structure, mut structure_far) = (0u64, 0u64);
    for (&p, &r) in pred.data.iter().zip(&reference.data) {
        if r == 0.0 || r.is_finite() && r >= sky_threshold {
            continue;
        }
        let (ps, rs) = (is_sky(p, sky_threshold), !r.is_finite());
        pred_sky += ps as u64;
        ref_sky += rs as u64;
        both += (ps && rs) as u64;
        sky_near += (rs && p < structure_depth) as u64;
        if r > min_depth && r < structure_depth {
            structure += 1;
            structure_far += ps as u64;
        }
    }
    SkyMetrics {
        sky_pixels: ref_sky,
        predicted_sky_pixels: pred_sky,
        both_sky_pixels: both,
        sky_as_structure_pixels: sky_near,
        structure_pixels: structure,
        structure_as_sky_pixels: structure_far,
        ..Default::default()
    }
    .with_shares()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A `w x h` map whose rows above `sky_rows` are `sky`, the rest `ground`.
    fn rows(w: u32, h: u32, sky_rows: u32, sky: f32, ground: f32) -> DepthMap {
        let data = (0..w * h).map(|i| if i / w < sky_rows { sky } else { ground }).collect();
        DepthMap { width: w, height: h, data }
    }

    #[test]
    fn calling_the_top_half_sky_when_the_sky_is_the_top_third_scores_two_thirds() {
        // 12 rows: reference sky (+inf) in rows 0-3, prediction sky (100 m) in rows 0-5; rows
        // 4-5 are structure at 30 m predicted as sky.
        let reference = rows(10, 12, 4, f32::INFINITY, 30.0);
        let pred = rows(10, 12, 6, 100.0, 30.0);
        let m = sky_metrics(&pred, &reference, 99.0, 80.0, 0.1);
        assert_eq!(m.iou, Some(40.0 / 60.0));
        assert_eq!(m.sky_as_structure, Some(0.0));
        assert_eq!(m.structure_as_sky, Some(20.0 / 80.0));
        assert_eq!((m.sky_pixels, m.predicted_sky_pixels), (40, 60));
    }

    #[test]
    fn a_wall_in_the_sky_counts_and_undecided_depths_count_as_neither() {
        // Reference sky in rows 0-5; the prediction puts a wall at 40 m in rows 0-2 and 90 m
        // (beyond the structure range, short of the sky threshold) in rows 3-5.
        let reference = rows(4, 10, 6, f32::INFINITY, 20.0);
        let mut pred = rows(4, 10, 3, 40.0, 20.0);
        pred.data[12..24].fill(90.0);
        let m = sky_metrics(&pred, &reference, 99.0, 80.0, 0.1);
        assert_eq!(m.iou, Some(0.0));
        assert_eq!(m.sky_as_structure, Some(0.5));
        assert_eq!(m.structure_as_sky, Some(0.0));
    }

    #[test]
    fn no_sky_anywhere_leaves_the_iou_undefined_and_unreferenced_pixels_out() {
        let reference = rows(5, 5, 0, 0.0, 12.0);
        let m = sky_metrics(&rows(5, 5, 0, 0.0, 12.0), &reference, 99.0, 80.0, 0.1);
        assert_eq!((m.iou, m.sky_as_structure, m.structure_as_sky), (None, None, Some(0.0)));
        // Far reference pixels (finite, beyond the threshold) and pixels without a reference
        // count nowhere, whatever the prediction calls them.
        let mut reference = rows(5, 2, 1, 500.0, 0.0);
        reference.data[9] = 10.0;
        reference.data[0] = f32::INFINITY;
        let mut pred = rows(5, 2, 1, 100.0, 100.0);
        pred.data[1] = 60.0;
        let m = sky_metrics(&pred, &reference, 99.0, 80.0, 0.1);
        assert_eq!(m.iou, Some(1.0 / 2.0));
        assert_eq!((m.sky_pixels, m.predicted_sky_pixels, m.sky_as_structure), (1, 2, Some(0.0)));
        assert_eq!(m.structure_as_sky, Some(1.0));
        assert!(is_sky(f32::NAN, 99.0) && is_sky(f32::INFINITY, 99.0) && !is_sky(0.0, 99.0));
    }

    #[test]
    fn pooled_images_weigh_by_their_pixels() {
        // Image A: 40 sky pixels, all found (IoU 1); image B: 2 sky pixels, none found (IoU 0,
        // both a wall). Averaged per image IoU would be 0.5; pooled it is 40 / 42.
        let a = sky_metrics(&rows(10, 10, 4, 100.0, 20.0), &rows(10, 10, 4, f32::INFINITY, 20.0), 99.0, 80.0, 0.1);
        let mut b_ref = rows(10, 10, 0, 0.0, 20.0);
        b_ref.data[..2].fill(f32::INFINITY);
        let b = sky_metrics(&rows(10, 10, 0, 0.0, 20.0), &b_ref, 99.0, 80.0, 0.1);
        assert_eq!((a.iou, b.iou), (Some(1.0), Some(0.0)));
        let p = SkyMetrics::pooled([&a, &b]);
        assert_eq!(p.iou, Some(40.0 / 42.0));
        assert_eq!(p.sky_as_structure, Some(2.0 / 42.0));
        assert_eq!(p.structure_as_sky, Some(0.0));
        assert_eq!((p.sky_pixels, p.structure_pixels), (42, 158));
    }
}
