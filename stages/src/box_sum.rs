//! Sums over a square box around each pixel, in time independent of the box: a summed-area
//! table. Used to average per-pixel values over a neighbourhood (TemporalBlend's corrections,
//! EstimateSky's local texture).

/// The sum of `values` over the (2r+1)^2 box around each pixel (clipped at the image's edges).
pub fn box_sum(values: &[f64], w: usize, h: usize, r: usize) -> Vec<f64> {
    // Summed-area table with a zero row and column in front.
    let mut table = vec![0.0f64; (w + 1) * (h + 1)];
    for y in 0..h {
        let mut row = 0.0;
        for x in 0..w {
            row += values[y * w + x];
            table[(y + 1) * (w + 1) + x + 1] = table[y * (w + 1) + x + 1] + row;
        }
    }
    let mut out = vec![0.0f64; w * h];
    for y in 0..h {
        let (y0, y1) = (y.saturating_sub(r), (y + r + 1).min(h));
        for x in 0..w {
            let (x0, x1) = (x.saturating_sub(r), (x + r + 1).min(w));
            out[y * w + x] = table[y1 * (w + 1) + x1] - table[y0 * (w + 1) + x1] - table[y1 * (w + 1) + x0]
                + table[y0 * (w + 1) + x0];
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_pixel_gets_the_sum_of_its_box_clipped_at_the_edges() {
        let (w, h) = (5, 4);
        let values: Vec<f64> = (0..w * h).map(|i| i as f64).collect();
        let brute = |x: usize, y: usize, r: usize| {
            let mut s = 0.0;
            for yy in y.saturating_sub(r)..(y + r + 1).min(h) {
                for xx in x.saturating_sub(r)..(x + r + 1).min(w) {
                    s += values[yy * w + xx];
                }
            }
            s
        };
        for r in [0, 1, 2, 7] {
            let sums = box_sum(&values, w, h, r);
            for y in 0..h {
                for x in 0..w {
                    assert_eq!(sums[y * w + x], brute(x, y, r), "r {r} at ({x}, {y})");
                }
            }
        }
    }
}
