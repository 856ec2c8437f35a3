//! Canny edges (Canny 1986) of a float image, for the depth-boundary metrics.
//!
//! The four classic steps, as `skimage.feature.canny` does them (which the iBims-1 evaluation
//! calls): a Gaussian blur of standard deviation `sigma` (kernel cut at 4 sigma, borders
//! replicated), Sobel gradients (scaled by 1/8, so that a ramp of slope s gives magnitude s), non-maximum
//! suppression along the gradient direction quantized to 0, 45, 90 and 135 degrees (of two equal
//! maxima side by side the left or upper one is kept, so a step makes a line one pixel wide, and a
//! constant slope none; magnitudes within a relative 1e-4 count as equal), and
//! hysteresis: pixels at or above `high` start edges, which grow through 8-connected pixels at or
//! above `low`. The outermost pixel ring is never an edge (it has no neighbour on one side).
//!
//! Thresholds are gradient magnitudes in image units per pixel; [`step_response`] converts a step
//! height into the magnitude the blurred step peaks at, so that callers can state thresholds as
//! "a sharp step of at least this much".

/// Edge pixels (row-major, `w * h`) of `image`.
pub fn canny(image: &[f32], w: usize, h: usize, sigma: f32, low: f32, high: f32) -> Vec<bool> {
    assert_eq!(image.len(), w * h, "canny: the image is not {w}x{h}");
    let mut edges = vec![false; w * h];
    if w < 3 || h < 3 {
        return edges;
    }
    let smooth = gaussian_blur(image, w, h, sigma);
    let (gx, gy) = sobel(&smooth, w, h);
    let magnitude: Vec<f32> = gx.iter().zip(&gy).map(|(x, y)| (x * x + y * y).sqrt()).collect();
    // Non-maximum suppression: candidates are the local maxima at or above `low`.
    let mut candidate = vec![false; w * h];
    // tan(22.5 deg) and tan(67.5 deg): the borders of the four direction sectors.
    let (t1, t2) = (0.414_213_57f32, 2.414_213_6f32);
    for y in 1..h - 1 {
        for x in 1..w - 1 {
            let i = y * w + x;
            let m = magnitude[i];
            if m.is_nan() || m < low || m == 0.0 {
                continue;
            }
            let (ax, ay) = (gx[i].abs(), gy[i].abs());
            // The neighbours before and after the pixel along the gradient, "before" being the
            // one to the left (or above, for a vertical gradient).
            let (before, after) = if ay <= ax * t1 {
                (i - 1, i + 1)
            } else if ay >= ax * t2 {
                (i - w, i + w)
            } else if (gx[i] > 0.0) == (gy[i] > 0.0) {
                (i - w - 1, i + w + 1)
            } else {
                (i + w - 1, i - w + 1)
            };
            // Magnitudes within a relative 1e-4 are equal: a blurred step's two central pixels
            // differ only by rounding, and so do the pixels of a constant slope.
            let tie = 1e-4 * m;
            candidate[i] = m > magnitude[before] + tie && m + tie >= magnitude[after];
        }
    }
    // Hysteresis: flood from the strong candidates through 8-connected candidates.
    let mut stack: Vec<usize> = (0..w * h).filter(|&i| candidate[i] && magnitude[i] >= high).collect();
    for &i in &stack {
        edges[i] = true;
    }
    while let Some(i) = stack.pop() {
        let (x, y) = (i % w, i / w);
        for ny in y - 1..=y + 1 {
            for nx in x - 1..=x + 1 {
                let j = ny * w + nx;
                if candidate[j] && !edges[j] {
                    edges[j] = true;
                    stack.push(j);
                }
            }
        }
    }
    edges
}

/// The peak gradient magnitude [`canny`] sees at a sharp step of height 1 (between two pixels)
/// blurred with `sigma`; a step of height s peaks at s times this.
pub fn step_response(sigma: f32) -> f32 {
    let r = kernel_radius(sigma);
    let n = 2 * r + 4;
    let row: Vec<f32> = (0..n).map(|x| if x > n / 2 { 1.0 } else { 0.0 }).collect();
    let smooth = gaussian_blur(&row, n, 1, sigma);
    (1..n - 1).map(|x| (smooth[x + 1] - smooth[x - 1]) / 2.0).fold(0.0, f32::max)
}

fn kernel_radius(sigma: f32) -> usize {
    (4.0 * sigma).ceil().max(1.0) as usize
}

/// Separable Gaussian blur, borders replicated.
fn gaussian_blur(image: &[f32], w: usize, h: usize, sigma: f32) -> Vec<f32> {
    if sigma.is_nan() || sigma <= 0.0 {
        return image.to_vec();
    }
    let r = kernel_radius(sigma);
    let mut kernel: Vec<f32> =
        (0..=2 * r).map(|k| (-(((k as f32) - r as f32).powi(2)) / (2.0 * sigma * sigma)).exp()).collect();
    let sum: f32 = kernel.iter().sum();
    kernel.iter_mut().for_each(|k| *k /= sum);
    // Rows: each row padded with its end values, then a plain convolution.
    let mut rows = vec![0f32; w * h];
    let mut padded = vec![0f32; w + 2 * r];
    for y in 0..h {
        let line = &image[y * w..(y + 1) * w];
        padded[..r].fill(line[0]);
        padded[r..r + w].copy_from_slice(line);
        padded[r + w..].fill(line[w - 1]);
        let o = &mut rows[y * w..(y + 1) * w];
        for (k, &c) in kernel.iter().enumerate() {
            for (o, v) in o.iter_mut().zip(&padded[k..k + w]) {
                *o += c * v;
            }
        }
    }
    // Columns: whole rows at a time, the row index clamped.
    let mut out = vec![0f32; w * h];
    for y in 0..h {
        let o = &mut out[y * w..(y + 1) * w];
        for (k, &c) in kernel.iter().enumerate() {
            let sy = (y + k).saturating_sub(r).min(h - 1);
            for (o, s) in o.iter_mut().zip(&rows[sy * w..(sy + 1) * w]) {
                *o += c * s;
            }
        }
    }
    out
}

/// Sobel gradients (x to the right, y down) scaled by 1/8, borders replicated.
fn sobel(image: &[f32], w: usize, h: usize) -> (Vec<f32>, Vec<f32>) {
    let (mut gx, mut gy) = (vec![0f32; w * h], vec![0f32; w * h]);
    for y in 0..h {
        let row = |yy: usize| &image[yy * w..(yy + 1) * w];
        let (up, mid, down) = (row(y.saturating_sub(1)), row(y), row((y + 1).min(h - 1)));
        for x in 0..w {
            let (l, r) = (x.saturating_sub(1), (x + 1).min(w - 1));
            gx[y * w + x] = ((up[r] - up[l]) + 2.0 * (mid[r] - mid[l]) + (down[r] - down[l])) / 8.0;
            gy[y * w + x] = ((down[l] - up[l]) + 2.0 * (down[x] - up[x]) + (down[r] - up[r])) / 8.0;
        }
    }
    (gx, gy)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn columns(edges: &[bool], w: usize, y: usize) -> Vec<usize> {
        (0..w).filter(|&x| edges[y * w + x]).collect()
    }

    #[test]
    fn a_vertical_step_is_found_at_its_column_one_pixel_wide() {
        // 0 left of column 12, 1 from column 12 on: the edge is column 11 (the left of the two
        // equal maxima), on every row but the outermost.
        let (w, h) = (30, 20);
        let image: Vec<f32> = (0..w * h).map(|i| if i % w >= 12 { 1.0 } else { 0.0 }).collect();
        let r = step_response(2f32.sqrt());
        let edges = canny(&image, w, h, 2f32.sqrt(), 0.5 * r, 0.9 * r);
        for y in 1..h - 1 {
            assert_eq!(columns(&edges, w, y), vec![11], "row {y}");
        }
        assert!(columns(&edges, w, 0).is_empty() && columns(&edges, w, h - 1).is_empty());
        // Above its peak response the step is not an edge.
        assert!(canny(&image, w, h, 2f32.sqrt(), 0.5 * r, 1.01 * r).iter().all(|&e| !e));
    }

    #[test]
    fn a_horizontal_step_is_found_at_its_row() {
        let (w, h) = (20, 30);
        let image: Vec<f32> = (0..w * h).map(|i| if i / w >= 7 { 3.0 } else { 1.0 }).collect();
        let r = step_response(1.0);
        let edges = canny(&image, w, h, 1.0, r, 1.5 * r);
        let rows: Vec<usize> = (0..h).filter(|&y| edges[y * w + 5]).collect();
        assert_eq!(rows, vec![6]);
        assert_eq!(edges.iter().filter(|&&e| e).count(), w - 2);
    }

    #[test]
    fn a_constant_slope_has_no_edge() {
        let (w, h) = (40, 20);
        let ramp: Vec<f32> = (0..w * h).map(|i| (i % w) as f32 * 0.1 + (i / w) as f32 * 0.02).collect();
        let edges = canny(&ramp, w, h, 1.0, 0.01, 0.02);
        // Only where the replicated border bends the slope (the outer 4 sigma).
        assert!((0..w * h).all(|i| !edges[i] || !(5..w - 5).contains(&(i % w))), "{:?}", columns(&edges, w, 10));
    }

    #[test]
    fn hysteresis_keeps_only_what_touches_a_strong_pixel() {
        let (w, h) = (40, 20);
        // A step whose height falls along it: strong at the top, weak below; a separate weak
        // step (right) touches no strong pixel and is dropped.
        let image: Vec<f32> = (0..w * h)
            .map(|i| {
                let (x, y) = (i % w, i / w);
                let left = if x >= 10 { 1.0 - y as f32 * 0.03 } else { 0.0 };
                let right = if x >= 30 { 0.5 } else { 0.0 };
                left + right
            })
            .collect();
        let r = step_response(1.0);
        let edges = canny(&image, w, h, 1.0, 0.4 * r, 0.9 * r);
        // The step lies between columns 9 and 10 (the slope on its right tips the tie to 10).
        let left: Vec<usize> = (1..h - 1).filter(|&y| edges[y * w + 9] || edges[y * w + 10]).collect();
        assert_eq!(left, (1..h - 1).collect::<Vec<_>>(), "the weak part continues the strong one");
        assert!((0..h).all(|y| !edges[y * w + 29]), "the weak step alone is not an edge");
    }

    #[test]
    fn the_step_response_is_the_blurred_steps_peak_slope() {
        // Without blur a unit step between two pixels gives (1 - 0) / 2.
        assert!((step_response(0.0) - 0.5).abs() < 1e-6);
        // sigma = sqrt(2): erf-shaped, about 0.25.
        let r = step_response(2f32.sqrt());
        assert!(r > 0.22 && r < 0.27, "{r}");
    }
}
