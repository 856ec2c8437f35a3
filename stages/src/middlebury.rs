//! The Middlebury stereo benchmark's rectified pairs as calibrated views, and its bad-pixel score:
//! the check that the plane-sweep stereo of [`crate::stereo`] measures disparity correctly.

use crate::stereo::{StereoView, SweepParams};
use anyhow::{ensure, Context, Result};
use dist4d_types::geometry::Se3;
use glam::DVec3;
use std::path::Path;

/// A rectified pair's calibration (Middlebury `calib.txt`): focal length and principal point of
/// the left camera (px), the right principal point's offset `doffs` (px) and the baseline (m).
/// Disparity d = f B / Z - doffs.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PairCalibration {
    pub f: f64,
    pub cx: f64,
    pub cy: f64,
    pub doffs: f64,
    pub baseline: f64,
}

impl PairCalibration {
    /// "Motorcycle" (Middlebury 2014) at the 741x500 size scikit-image ships.
    pub const MOTORCYCLE: PairCalibration =
        PairCalibration { f: 994.978, cx: 311.193, cy: 254.877, doffs: 31.086, baseline: 0.193001 };

    pub fn disparity(&self, depth: f64) -> f64 {
        self.f * self.baseline / depth - self.doffs
    }

    pub fn depth(&self, disparity: f64) -> f64 {
        self.f * self.baseline / (disparity + self.doffs)
    }

    /// Sweep parameters covering disparities `0.5..=max_disparity`, everything else as given.
    pub fn sweep(&self, max_disparity: f64, base: &SweepParams) -> SweepParams {
        SweepParams { min_depth: self.depth(max_disparity), max_depth: self.depth(0.5), ..base.clone() }
    }

    /// The pair as two views: the right camera `baseline` to the right, its principal point
    /// `doffs` further right.
    pub fn views(&self, left: (usize, usize, Vec<u8>), right: (usize, usize, Vec<u8>)) -> (StereoView, StereoView) {
        let view = |(width, height, grey): (usize, usize, Vec<u8>), cx: f64, x: f64| {
            let k = [[self.f, 0.0, cx], [0.0, self.f, self.cy], [0.0, 0.0, 1.0]];
            StereoView::new(width, height, grey, k, Se3::from_yaw(0.0, DVec3::new(x, 0.0, 0.0)))
        };
        (view(left, self.cx, 0.0), view(right, self.cx + self.doffs, self.baseline))
    }
}

/// A grey image (ITU-R 601 luma) of an image file.
pub fn read_grey(path: &Path) -> Result<(usize, usize, Vec<u8>)> {
    let img = dist4d_datasets::files::read_jpeg(path)?;
    Ok((img.width as usize, img.height as usize, crate::stereo::grey(&img.rgb)))
}

/// The Motorcycle pair of `dir` (`motorcycle_left.png`, `motorcycle_right.png`) and its ground-truth
/// disparity (`motorcycle_disp.npy`, non-finite = unknown).
pub fn read_motorcycle(dir: &Path) -> Result<((StereoView, StereoView), Vec<f64>)> {
    let left = read_grey(&dir.join("motorcycle_left.png"))?;
    let right = read_grey(&dir.join("motorcycle_right.png"))?;
    let gt_path = dir.join("motorcycle_disp.npy");
    let gt = dist4d_datasets::files::parse_npy(
        &std::fs::read(&gt_path).with_context(|| format!("reading {}", gt_path.display()))?,
    )
    .with_context(|| format!("parsing {}", gt_path.display()))?;
    ensure!(
        gt.shape == [left.1, left.0] && (right.0, right.1) == (left.0, left.1),
        "{}: ground truth {:?} and images {}x{} / {}x{} disagree in size",
        dir.display(),
        gt.shape,
        left.0,
        left.1,
        right.0,
        right.1
    );
    Ok((PairCalibration::MOTORCYCLE.views(left, right), gt.data))
}

/// Middlebury's bad-pixel rate: among pixels with finite ground-truth disparity, the fraction
/// whose estimate is off by more than `threshold` px, counting pixels without an estimate as bad
/// (`all`) and leaving them out (`valid`), with the density of estimates.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BadPixels {
    pub all: f64,
    pub valid: f64,
    pub density: f64,
}

/// Scores disparities (`None` = no estimate) against ground truth (non-finite = unknown).
pub fn bad_pixels(estimate: &[Option<f64>], truth: &[f64], threshold: f64) -> BadPixels {
    let (mut known, mut estimated, mut bad) = (0usize, 0usize, 0usize);
    for (e, t) in estimate.iter().zip(truth) {
        if !t.is_finite() {
            continue;
        }
        known += 1;
        if let Some(e) = e {
            estimated += 1;
            if (e - t).abs() > threshold {
                bad += 1;
            }
        }
    }
    let missing = known - estimated;
    BadPixels {
        all: (bad + missing) as f64 / known.max(1) as f64,
        valid: bad as f64 / estimated.max(1) as f64,
        density: estimated as f64 / known.max(1) as f64,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::stereo::{keep_consistent, sweep_depth};

    #[test]
    fn bad_pixels_count_missing_estimates_only_in_all() {
        let truth = [10.0, 20.0, f64::INFINITY, 30.0];
        let est = [Some(10.5), Some(25.0), Some(1.0), None];
        let s = bad_pixels(&est, &truth, 2.0);
        assert_eq!(s, BadPixels { all: 2.0 / 3.0, valid: 0.5, density: 2.0 / 3.0 });
    }

    /// The shared Middlebury Motorcycle pair (skipped with a message when absent).
    #[test]
    fn motorcycle_bad_pixel_rate() {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/middlebury-motorcycle");
        if !dir.exists() {
            eprintln!("skipped: {} is absent", dir.display());
            return;
        }
        let ((left, right), truth) = read_motorcycle(&dir).unwrap();
        let calib = PairCalibration::MOTORCYCLE;
        let p = calib.sweep(80.0, &crate::stereo::tests::params());
        let mut depth = sweep_depth(&left, &[&right], &p).unwrap();
        let back = sweep_depth(&right, &[&left], &p).unwrap();
        keep_consistent(&left, &mut depth, &[(&right, &back)], 1.0, 0.05);
        let disparity: Vec<Option<f64>> =
            depth.depth.iter().map(|&z| (z > 0.0).then(|| calib.disparity(z as f64))).collect();
        let score = bad_pixels(&disparity, &truth, 2.0);
        eprintln!("middlebury motorcycle: {score:?}");
        assert!(score.valid < 0.06 && score.density > 0.8, "{score:?}");
    }
}
