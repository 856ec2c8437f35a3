//! Image-quality scores of a rendered novel view against the camera image it should reproduce:
//! PSNR and SSIM of two RGB8 images (row-major, 3 interleaved channels), optionally restricted to
//! a mask of the pixels that count (say, those the renderer had data for).
//!
//! Both follow scikit-image so that the numbers can be checked against a reference everyone can
//! run: PSNR as `skimage.metrics.peak_signal_noise_ratio(a, b, data_range=255)` and SSIM as
//! `skimage.metrics.structural_similarity(a, b, channel_axis=2, gaussian_weights=True,
//! sigma=1.5, use_sample_covariance=False, data_range=255)`, the settings that reproduce Wang,
//! Bovik, Sheikh and Simoncelli, "Image quality assessment: from error visibility to structural
//! similarity", IEEE TIP 13(4), 2004. The SSIM was matched against scikit-image 0.26's
//! `skimage/metrics/_structural_similarity.py` and agrees with it to about 1e-15 (the tests compare
//! when the peer venv is there). Other SSIMs in circulation differ at the borders: PyTorch ones
//! such as 3D Gaussian Splatting's pad with zeros and average the whole map, so they are not
//! comparable to this one digit for digit.
//!
//! Sizes that do not fit (`a`, `b` not `width * height * 3` bytes, a mask not `width * height`
//! long) give `None` rather than an error or a panic: a score is either there or not, and the
//! caller that knows which view it was scoring is the one that can say what went wrong.

use rayon::prelude::*;

/// The value range of 8-bit channels (`data_range` in scikit-image).
const DATA_RANGE: f64 = 255.0;
/// Standard deviation of the Gaussian window, pixels (Wang et al. 2004).
const SIGMA: f64 = 1.5;
/// Half-width of the Gaussian window: scipy's `int(truncate * sigma + 0.5)` with the
/// `truncate = 3.5` scikit-image passes to get Wang et al.'s 11 taps.
const RADIUS: usize = 5;
/// Taps of the Gaussian window (its side length, `win_size` in scikit-image).
const TAPS: usize = 2 * RADIUS + 1;
/// Stabilizer of the luminance term, `(K1 * L)^2` with K1 = 0.01 (Wang et al. 2004).
const C1: f64 = (0.01 * DATA_RANGE) * (0.01 * DATA_RANGE);
/// Stabilizer of the contrast-structure term, `(K2 * L)^2` with K2 = 0.03 (Wang et al. 2004).
const C2: f64 = (0.03 * DATA_RANGE) * (0.03 * DATA_RANGE);
/// Filtered maps per channel: the means of a and b, of a² + b², and of ab. SSIM only ever uses the
/// two variances as their sum, so one map of a² + b² replaces scikit-image's two.
const MAPS: usize = 4;

/// Peak signal-to-noise ratio in dB over the three channels of the counted pixels (all pixels
/// without a mask), with a peak of 255.
///
/// `f64::INFINITY` for identical counted pixels (scikit-image returns the same, with a warning);
/// `None` when no pixel counts or the sizes do not fit. The squared errors are summed as integers,
/// so the score is exact up to the final logarithm.
pub fn psnr(a: &[u8], b: &[u8], width: usize, height: usize, mask: Option<&[bool]>) -> Option<f64> {
    let pixels = checked_pixels(a, b, width, height, mask)?;
    let mut squared_error: u64 = 0;
    let mut counted: u64 = 0;
    for p in 0..pixels {
        if mask.is_some_and(|m| !m[p]) {
            continue;
        }
        counted += 1;
        for (&x, &y) in a[3 * p..3 * p + 3].iter().zip(&b[3 * p..3 * p + 3]) {
            let d = u64::from(x.abs_diff(y));
            squared_error += d * d;
        }
    }
    if counted == 0 {
        return None;
    }
    if squared_error == 0 {
        return Some(f64::INFINITY);
    }
    let mse = squared_error as f64 / (3 * counted) as f64;
    Some(10.0 * (DATA_RANGE * DATA_RANGE / mse).log10())
}

/// Mean structural similarity (Wang et al. 2004) of the counted pixels, per channel with an 11 x 11
/// Gaussian window of sigma 1.5 and population (co)variances, averaged over the three channels.
///
/// Like scikit-image, only pixels at least 5 pixels from every border are scored: their window
/// lies wholly inside the image, so no border rule (scikit-image filters with
/// `mode='reflect'`) enters the score, and this computes the filtered maps for those pixels only.
/// With a mask, the score is the mean SSIM over the counted pixels inside that cropped region:
/// the mask chooses whose similarity is averaged, not which pixels feed the windows, so a window
/// centred on a counted pixel still sees its uncounted neighbours. (That is scikit-image's
/// `full=True` map, cropped by 5, averaged over the mask; masking the windows instead would
/// change what SSIM measures near the mask's edge.)
///
/// `None` when the image is smaller than 11 x 11, no counted pixel is inside the cropped region,
/// or the sizes do not fit. Rows of the map are summed in order whatever the thread count, so the
/// score does not depend on how rayon splits the work.
pub fn ssim(a: &[u8], b: &[u8], width: usize, height: usize, mask: Option<&[bool]>) -> Option<f64> {
    match mask {
        None => ssim_with_mask(a, b, width, height, None).map(|(all, _)| all),
        Some(_) => ssim_with_mask(a, b, width, height, mask).and_then(|(_, masked)| masked),
    }
}

/// The SSIM over every scored pixel and over the counted ones (as [`ssim`] with and without the
/// mask), from one pass over the images: a novel view is scored both ways.
pub fn ssim_both(a: &[u8], b: &[u8], width: usize, height: usize, mask: &[bool]) -> (Option<f64>, Option<f64>) {
    match ssim_with_mask(a, b, width, height, Some(mask)) {
        Some((all, masked)) => (Some(all), masked),
        None => (None, None),
    }
}

/// (SSIM over all scored pixels, SSIM over the counted ones); `None` when the sizes do not fit
/// or the image is smaller than the window.
fn ssim_with_mask(
    a: &[u8],
    b: &[u8],
    width: usize,
    height: usize,
    mask: Option<&[bool]>,
) -> Option<(f64, Option<f64>)> {
    checked_pixels(a, b, width, height, mask)?;
    if width < TAPS || height < TAPS {
        return None;
    }
    let scored_rows = height - 2 * RADIUS;
    let threads = rayon::current_num_threads();
    // Each band refilters the 10 rows around it, so a single thread gets a single band and more
    // threads get a few bands each (for balance) of at least 32 rows.
    let band = if threads <= 1 { scored_rows } else { scored_rows.div_ceil(4 * threads).max(32) };
    let images = Pair { a, b, width, mask };
    let mut rows = vec![RowSum::default(); scored_rows];
    rows.par_chunks_mut(band).enumerate().for_each(|(i, sums)| images.score_band(RADIUS + i * band, sums));
    let total = rows.iter().fold(RowSum::default(), |t, r| RowSum {
        all: t.all + r.all,
        all_n: t.all_n + r.all_n,
        masked: t.masked + r.masked,
        masked_n: t.masked_n + r.masked_n,
    });
    let all = total.all / (3 * total.all_n.max(1)) as f64;
    Some((all, (total.masked_n > 0).then(|| total.masked / (3 * total.masked_n) as f64)))
}

/// The pixel count, if both images are `width * height * 3` bytes and the mask `width * height`.
fn checked_pixels(a: &[u8], b: &[u8], width: usize, height: usize, mask: Option<&[bool]>) -> Option<usize> {
    let pixels = width.checked_mul(height)?;
    let bytes = pixels.checked_mul(3)?;
    let fits = a.len() == bytes && b.len() == bytes && mask.is_none_or(|m| m.len() == pixels);
    fits.then_some(pixels)
}

/// The normalized 11-tap Gaussian, computed as scipy's `_gaussian_kernel1d` does.
fn gaussian_taps() -> [f64; TAPS] {
    let mut taps: [f64; TAPS] = std::array::from_fn(|k| {
        let x = k as f64 - RADIUS as f64;
        (-0.5 / (SIGMA * SIGMA) * x * x).exp()
    });
    let total: f64 = taps.iter().sum();
    taps.iter_mut().for_each(|t| *t /= total);
    taps
}

/// One scored row's SSIM summed over the three channels: over all its pixels and over its counted
/// ones (all of them without a mask), with the pixel counts.
#[derive(Clone, Copy, Default)]
struct RowSum {
    all: f64,
    all_n: usize,
    masked: f64,
    masked_n: usize,
}

/// The two images (validated) and the mask.
struct Pair<'a> {
    a: &'a [u8],
    b: &'a [u8],
    width: usize,
    mask: Option<&'a [bool]>,
}

impl Pair<'_> {
    /// Scores the image rows `first..first + sums.len()` into `sums`, channel by channel.
    ///
    /// The Gaussian is separable: each input row is filtered horizontally once into a ring of the
    /// last 11 rows, and each scored row combines those 11 vertically. The ring (4 maps x 11 rows)
    /// stays in cache where whole-image intermediate maps would not.
    fn score_band(&self, first: usize, sums: &mut [RowSum]) {
        let (width, taps) = (self.width, gaussian_taps());
        let scored_width = width - 2 * RADIUS;
        let mut line = vec![0.0; MAPS * width];
        let mut ring = vec![0.0; TAPS * MAPS * scored_width];
        let mut moments = vec![0.0; MAPS * scored_width];
        for channel in 0..3 {
            for row in first - RADIUS..first + sums.len() + RADIUS {
                self.load_line(row, channel, &mut line);
                let slot = row % TAPS;
                for m in 0..MAPS {
                    let input = &line[m * width..(m + 1) * width];
                    let shifted: [&[f64]; TAPS] = std::array::from_fn(|k| &input[k..k + scored_width]);
                    let start = (slot * MAPS + m) * scored_width;
                    weighted_sum(&shifted, &taps, &mut ring[start..start + scored_width]);
                }
                let Some(centre) = row.checked_sub(RADIUS).filter(|&c| c >= first) else { continue };
                for m in 0..MAPS {
                    let rows: [&[f64]; TAPS] = std::array::from_fn(|k| {
                        let start = (((centre - RADIUS + k) % TAPS) * MAPS + m) * scored_width;
                        &ring[start..start + scored_width]
                    });
                    weighted_sum(&rows, &taps, &mut moments[m * scored_width..(m + 1) * scored_width]);
                }
                let mask = self.mask.map(|m| &m[centre * width + RADIUS..][..scored_width]);
                let (all, masked, counted) = ssim_row(&moments, scored_width, mask);
                let sum = &mut sums[centre - first];
                sum.all += all;
                sum.all_n = scored_width;
                sum.masked += masked;
                sum.masked_n = counted;
            }
        }
    }

    /// One channel of image row `row` as the four maps to filter: a, b, a² + b², ab.
    fn load_line(&self, row: usize, channel: usize, line: &mut [f64]) {
        let width = self.width;
        let (means, products) = line.split_at_mut(2 * width);
        let (mean_a, mean_b) = means.split_at_mut(width);
        let (squares, cross) = products.split_at_mut(width);
        let start = 3 * row * width + channel;
        let a = self.a[start..].iter().step_by(3);
        let b = self.b[start..].iter().step_by(3);
        for (j, (&x, &y)) in a.zip(b).take(width).enumerate() {
            let (x, y) = (f64::from(x), f64::from(y));
            mean_a[j] = x;
            mean_b[j] = y;
            squares[j] = x * x + y * y;
            cross[j] = x * y;
        }
    }
}

/// `out[i] = sum_k taps[k] * inputs[k][i]` for a symmetric kernel, pairing the taps that share a
/// weight, outermost pair first, as scipy's `correlate1d` does for symmetric kernels (half the
/// multiplications, and its rounding).
fn weighted_sum(inputs: &[&[f64]; TAPS], taps: &[f64; TAPS], out: &mut [f64]) {
    let n = out.len();
    // Cut to the output's length so that the indexing below needs no bounds checks.
    let inputs: [&[f64]; TAPS] = std::array::from_fn(|k| &inputs[k][..n]);
    for (i, o) in out.iter_mut().enumerate() {
        let mut total = taps[RADIUS] * inputs[RADIUS][i];
        for k in 0..RADIUS {
            total += taps[k] * (inputs[k][i] + inputs[TAPS - 1 - k][i]);
        }
        *o = total;
    }
}

/// The SSIM of one channel's scored row summed over all pixels and over the counted ones, and
/// the count of those.
fn ssim_row(moments: &[f64], scored_width: usize, mask: Option<&[bool]>) -> (f64, f64, usize) {
    let (means, products) = moments.split_at(2 * scored_width);
    let (mean_a, mean_b) = means.split_at(scored_width);
    let (squares, cross) = products.split_at(scored_width);
    let (mut all, mut sum, mut counted) = (0.0, 0.0, 0);
    for i in 0..scored_width {
        let (ma, mb) = (mean_a[i], mean_b[i]);
        let luminance = (2.0 * ma * mb + C1) / (ma * ma + mb * mb + C1);
        let structure = (2.0 * (cross[i] - ma * mb) + C2) / (squares[i] - ma * ma - mb * mb + C2);
        let v = luminance * structure;
        all += v;
        if mask.is_none_or(|m| m[i]) {
            sum += v;
            counted += 1;
        }
    }
    (all, sum, counted)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::PathBuf;
    use std::process::Command;
    use std::time::Instant;

    /// A deterministic stream of pseudo-random numbers (splitmix64).
    struct Rng(u64);

    impl Rng {
        fn next(&mut self) -> u64 {
            self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
            let mut z = self.0;
            z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
            z ^ (z >> 31)
        }

        /// Uniform in `-amplitude..=amplitude`.
        fn offset(&mut self, amplitude: i32) -> i32 {
            (self.next() % (2 * amplitude as u64 + 1)) as i32 - amplitude
        }
    }

    /// A smooth gradient with stripes, rings and a hard-edged block, saturating in places.
    fn scene(w: usize, h: usize) -> Vec<u8> {
        let mut img = Vec::with_capacity(w * h * 3);
        for y in 0..h {
            for x in 0..w {
                let (fx, fy) = (x as f64 / w as f64, y as f64 / h as f64);
                let ring = ((fx - 0.4).hypot(fy - 0.6) * 40.0).sin();
                let block = if (w / 4..w / 2).contains(&x) && (h / 3..2 * h / 3).contains(&y) { 90.0 } else { 0.0 };
                let r = 280.0 * fx + 30.0 * ring - 10.0;
                let g = 200.0 * fy + 60.0 * (x as f64 * 0.7).sin() + block;
                let b = 128.0 + 120.0 * ring * fx + if (x / 8 + y / 8) % 2 == 0 { 20.0 } else { -20.0 };
                img.extend([r, g, b].map(|v| v.round().clamp(0.0, 255.0) as u8));
            }
        }
        img
    }

    fn noisy(img: &[u8], amplitude: i32, seed: u64) -> Vec<u8> {
        let mut rng = Rng(seed);
        img.iter().map(|&v| (i32::from(v) + rng.offset(amplitude)).clamp(0, 255) as u8).collect()
    }

    /// `img` moved right by `dx` and down by `dy`, the first columns and rows repeated.
    fn shifted(img: &[u8], w: usize, h: usize, dx: usize, dy: usize) -> Vec<u8> {
        let mut out = vec![0; img.len()];
        for y in 0..h {
            for x in 0..w {
                let src = (y.saturating_sub(dy) * w + x.saturating_sub(dx)) * 3;
                out[(y * w + x) * 3..][..3].copy_from_slice(&img[src..src + 3]);
            }
        }
        out
    }

    /// A 3 x 3 box blur, borders replicated.
    fn blurred(img: &[u8], w: usize, h: usize) -> Vec<u8> {
        let mut out = vec![0; img.len()];
        for y in 0..h {
            for x in 0..w {
                for c in 0..3 {
                    let mut total = 0u32;
                    for dy in -1i64..=1 {
                        for dx in -1i64..=1 {
                            let sy = (y as i64 + dy).clamp(0, h as i64 - 1) as usize;
                            let sx = (x as i64 + dx).clamp(0, w as i64 - 1) as usize;
                            total += u32::from(img[(sy * w + sx) * 3 + c]);
                        }
                    }
                    out[(y * w + x) * 3 + c] = ((total + 4) / 9) as u8;
                }
            }
        }
        out
    }

    fn random(w: usize, h: usize, seed: u64) -> Vec<u8> {
        let mut rng = Rng(seed);
        (0..w * h * 3).map(|_| rng.next() as u8).collect()
    }

    /// SSIM the slow, literal way: each map filtered over the whole image with a 2-D 11 x 11
    /// window and scipy's `reflect` border (d c b a | a b c d), then the map cropped by 5 and
    /// averaged over the counted pixels. Checks the band/ring bookkeeping and the claim that the
    /// border rule never reaches a scored pixel.
    fn ssim_literal(a: &[u8], b: &[u8], w: usize, h: usize, mask: Option<&[bool]>) -> Option<f64> {
        let taps = gaussian_taps();
        let reflect = |i: i64, n: usize| -> usize {
            let n = n as i64;
            (if i < 0 {
                -i - 1
            } else if i >= n {
                2 * n - 1 - i
            } else {
                i
            }) as usize
        };
        let (mut sum, mut counted) = (0.0, 0usize);
        for c in 0..3 {
            let filter = |f: &dyn Fn(f64, f64) -> f64, x: usize, y: usize| -> f64 {
                let mut total = 0.0;
                for (i, ty) in taps.iter().enumerate() {
                    for (j, tx) in taps.iter().enumerate() {
                        let sy = reflect(y as i64 + i as i64 - RADIUS as i64, h);
                        let sx = reflect(x as i64 + j as i64 - RADIUS as i64, w);
                        let p = (sy * w + sx) * 3 + c;
                        total += ty * tx * f(f64::from(a[p]), f64::from(b[p]));
                    }
                }
                total
            };
            for y in RADIUS..h - RADIUS {
                for x in RADIUS..w - RADIUS {
                    if mask.is_some_and(|m| !m[y * w + x]) {
                        continue;
                    }
                    let ux = filter(&|p, _| p, x, y);
                    let uy = filter(&|_, q| q, x, y);
                    let vx = filter(&|p, _| p * p, x, y) - ux * ux;
                    let vy = filter(&|_, q| q * q, x, y) - uy * uy;
                    let vxy = filter(&|p, q| p * q, x, y) - ux * uy;
                    sum += (2.0 * ux * uy + C1) * (2.0 * vxy + C2) / ((ux * ux + uy * uy + C1) * (vx + vy + C2));
                    counted += usize::from(c == 0);
                }
            }
        }
        (counted > 0).then(|| sum / (3 * counted) as f64)
    }

    #[test]
    fn identical_images_score_perfectly() {
        let (w, h) = (40, 30);
        let img = scene(w, h);
        assert_eq!(psnr(&img, &img, w, h, None), Some(f64::INFINITY));
        let s = ssim(&img, &img, w, h, None).unwrap();
        assert!((s - 1.0).abs() < 1e-12, "SSIM of an image with itself: {s}");
    }

    #[test]
    fn psnr_of_a_constant_error_is_analytic() {
        let (w, h) = (23, 17);
        let a: Vec<u8> = scene(w, h).iter().map(|&v| v.clamp(5, 250)).collect();
        // Every value off by exactly 5, half up and half down: MSE 25.
        let b: Vec<u8> = a.iter().enumerate().map(|(i, &v)| if i % 2 == 0 { v + 5 } else { v - 5 }).collect();
        let expected = 20.0 * (255.0f64 / 5.0).log10();
        let got = psnr(&a, &b, w, h, None).unwrap();
        assert!((got - expected).abs() < 1e-12, "{got} vs {expected}");
        // One channel in three off by 3 (the others exact): MSE 3.
        let c: Vec<u8> = a.iter().enumerate().map(|(i, &v)| if i % 3 == 1 { v + 3 } else { v }).collect();
        let expected = 10.0 * (255.0f64 * 255.0 / 3.0).log10();
        let got = psnr(&a, &c, w, h, None).unwrap();
        assert!((got - expected).abs() < 1e-12, "{got} vs {expected}");
    }

    #[test]
    fn ssim_drops_for_degraded_images() {
        let (w, h) = (64, 48);
        let img = scene(w, h);
        let shift = ssim(&img, &shifted(&img, w, h, 2, 1), w, h, None).unwrap();
        let blur = ssim(&img, &blurred(&img, w, h), w, h, None).unwrap();
        let noise = ssim(&img, &noisy(&img, 20, 7), w, h, None).unwrap();
        let unrelated = ssim(&img, &random(w, h, 3), w, h, None).unwrap();
        for (name, s) in [("shifted", shift), ("blurred", blur), ("noisy", noise)] {
            assert!(s < 0.99 && s > unrelated, "{name}: SSIM {s} (unrelated image: {unrelated})");
        }
        assert!(unrelated < 0.1, "SSIM against noise: {unrelated}");
    }

    #[test]
    fn ssim_matches_the_literal_definition() {
        for (w, h, seed) in [(11, 11, 1), (12, 30, 2), (37, 14, 3), (64, 48, 4)] {
            let a = scene(w, h);
            let b = noisy(&blurred(&a, w, h), 9, seed);
            let ours = ssim(&a, &b, w, h, None).unwrap();
            let literal = ssim_literal(&a, &b, w, h, None).unwrap();
            assert!((ours - literal).abs() < 1e-12, "{w}x{h}: {ours} vs literal {literal}");
            // Every fifth pixel left out, on a diagonal pattern that spares the image centre (the
            // only scored pixel of an 11 x 11 image).
            let mask: Vec<bool> = (0..w * h).map(|i| i == (h / 2) * w + w / 2 || (i * 7 + i / w) % 5 != 0).collect();
            let ours = ssim(&a, &b, w, h, Some(&mask)).unwrap();
            let literal = ssim_literal(&a, &b, w, h, Some(&mask)).unwrap();
            assert!((ours - literal).abs() < 1e-12, "{w}x{h} masked: {ours} vs literal {literal}");
        }
    }

    #[test]
    fn ssim_does_not_depend_on_the_thread_count() {
        let (w, h) = (150, 301);
        let a = scene(w, h);
        let b = noisy(&a, 15, 11);
        let in_pool = |threads| {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
            pool.install(|| ssim(&a, &b, w, h, None).unwrap())
        };
        let one = in_pool(1);
        for threads in [2, 3, 8] {
            assert_eq!(one.to_bits(), in_pool(threads).to_bits(), "{threads} threads");
        }
    }

    #[test]
    fn masks_ignore_uncounted_pixels() {
        let (w, h) = (60, 40);
        let a = scene(w, h);
        let b = noisy(&a, 10, 5);
        // The left half counts; the pixel changed is 10 columns right of it, beyond any window.
        let mask: Vec<bool> = (0..w * h).map(|i| i % w < 30).collect();
        let mut changed = b.clone();
        let p = (20 * w + 40) * 3;
        changed[p..p + 3].copy_from_slice(&[255, 0, 255]);
        assert_eq!(psnr(&a, &b, w, h, Some(&mask)), psnr(&a, &changed, w, h, Some(&mask)));
        assert_eq!(ssim(&a, &b, w, h, Some(&mask)), ssim(&a, &changed, w, h, Some(&mask)));
        assert_ne!(psnr(&a, &b, w, h, None), psnr(&a, &changed, w, h, None));
        assert_ne!(ssim(&a, &b, w, h, None), ssim(&a, &changed, w, h, None));
        // A mask of every pixel is no mask.
        let all = vec![true; w * h];
        assert_eq!(psnr(&a, &b, w, h, Some(&all)), psnr(&a, &b, w, h, None));
        assert_eq!(ssim(&a, &b, w, h, Some(&all)), ssim(&a, &b, w, h, None));
        // Only errors inside the mask: PSNR over the mask is that of the errors there alone.
        let mut one_off = a.clone();
        one_off[(5 * w + 5) * 3] ^= 1;
        one_off[(5 * w + 50) * 3] ^= 1;
        let counted = mask.iter().filter(|&&m| m).count() as f64;
        let expected = 10.0 * (255.0f64 * 255.0 * 3.0 * counted).log10();
        let got = psnr(&a, &one_off, w, h, Some(&mask)).unwrap();
        assert!((got - expected).abs() < 1e-12, "{got} vs {expected}");
    }

    #[test]
    fn nothing_to_score_gives_none() {
        let (w, h) = (20, 20);
        let a = scene(w, h);
        let none = vec![false; w * h];
        assert_eq!(psnr(&a, &a, w, h, Some(&none)), None);
        assert_eq!(ssim(&a, &a, w, h, Some(&none)), None);
        // Only the 5-pixel border counts: PSNR scores it, SSIM crops it away.
        let border: Vec<bool> = (0..w * h).map(|i| i % w < 5 || i / w >= h - 5).collect();
        assert!(psnr(&a, &a, w, h, Some(&border)).is_some());
        assert_eq!(ssim(&a, &a, w, h, Some(&border)), None);
        // Smaller than the window.
        let small = scene(10, 30);
        assert_eq!(ssim(&small, &small, 10, 30, None), None);
        assert_eq!(ssim(&small, &small, 30, 10, None), None);
        assert_eq!(psnr(&small, &small, 10, 30, None), Some(f64::INFINITY));
        assert_eq!(psnr(&[], &[], 0, 0, None), None);
    }

    #[test]
    fn mismatched_sizes_give_none() {
        let (w, h) = (20, 20);
        let a = scene(w, h);
        let short = &a[..a.len() - 3];
        let mask = vec![true; w * h - 1];
        for score in [psnr, ssim] {
            assert_eq!(score(&a, short, w, h, None), None);
            assert_eq!(score(short, &a, w, h, None), None);
            assert_eq!(score(&a, &a, w + 1, h, None), None);
            assert_eq!(score(&a, &a, w, h, Some(&mask)), None);
            assert_eq!(score(&a, &a, usize::MAX, 2, None), None);
        }
    }

    /// The peer venv's python, or why the comparison is skipped.
    fn peers_python() -> Result<PathBuf, String> {
        let python = std::env::var_os("DIST4D_PEERS_PYTHON")
            .map(PathBuf::from)
            .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../.venv-peers/bin/python"));
        if !python.exists() {
            return Err(format!(
                "no peer python at {} (set DIST4D_PEERS_PYTHON, or make the venv with \
                 ../shared/bench/peers/setup.sh .venv-peers)",
                python.display()
            ));
        }
        match Command::new(&python).args(["-c", "import skimage, numpy"]).output() {
            Ok(out) if out.status.success() => Ok(python),
            Ok(out) => Err(format!(
                "`import skimage, numpy` fails in {}: {}",
                python.display(),
                String::from_utf8_lossy(&out.stderr).trim()
            )),
            Err(e) => Err(format!("cannot run {}: {e}", python.display())),
        }
    }

    const SKIMAGE_SCORES: &str = "
import sys
import numpy as np
from skimage.metrics import peak_signal_noise_ratio, structural_similarity
folder = sys.argv[1]
for spec in sys.argv[2:]:
    name, w, h = spec.split(':')
    shape = (int(h), int(w), 3)
    a = np.fromfile(f'{folder}/{name}.a', dtype=np.uint8).reshape(shape)
    b = np.fromfile(f'{folder}/{name}.b', dtype=np.uint8).reshape(shape)
    s = structural_similarity(a, b, channel_axis=2, gaussian_weights=True, sigma=1.5,
                              use_sample_covariance=False, data_range=255)
    p = peak_signal_noise_ratio(a, b, data_range=255)
    print(name, repr(float(s)), repr(float(p)))
";

    /// One image pair for the comparison with scikit-image.
    struct Case {
        name: &'static str,
        w: usize,
        h: usize,
        a: Vec<u8>,
        b: Vec<u8>,
    }

    #[test]
    fn matches_scikit_image() {
        let python = match peers_python() {
            Ok(p) => p,
            Err(reason) => {
                println!("SKIPPED: comparison with scikit-image: {reason}");
                return;
            }
        };
        let pair = |name, w, h, a: Vec<u8>, b: Vec<u8>| Case { name, w, h, a, b };
        let pairs = [
            pair("noisy", 64, 48, scene(64, 48), noisy(&scene(64, 48), 12, 1)),
            pair("shifted", 97, 61, scene(97, 61), noisy(&shifted(&scene(97, 61), 97, 61, 1, 1), 4, 2)),
            pair("blurred", 200, 120, scene(200, 120), blurred(&scene(200, 120), 200, 120)),
            pair("random_11x17", 11, 17, random(11, 17, 3), random(11, 17, 4)),
        ];
        let folder = tempfile::tempdir().expect("a temporary folder");
        let mut specs = Vec::new();
        for Case { name, w, h, a, b } in &pairs {
            std::fs::write(folder.path().join(format!("{name}.a")), a).unwrap();
            std::fs::write(folder.path().join(format!("{name}.b")), b).unwrap();
            specs.push(format!("{name}:{w}:{h}"));
        }
        let out = Command::new(&python)
            .args(["-c", SKIMAGE_SCORES])
            .arg(folder.path())
            .args(&specs)
            .output()
            .expect("the peer python runs");
        let stdout = String::from_utf8_lossy(&out.stdout);
        assert!(out.status.success(), "the scikit-image script failed: {}", String::from_utf8_lossy(&out.stderr));
        for Case { name, w, h, a, b } in &pairs {
            let line = stdout.lines().find(|l| l.split(' ').next() == Some(name)).expect("a line per pair");
            let theirs: Vec<f64> = line.split(' ').skip(1).map(|v| v.parse().unwrap()).collect();
            let ours_ssim = ssim(a, b, *w, *h, None).unwrap();
            let ours_psnr = psnr(a, b, *w, *h, None).unwrap();
            let (ssim_diff, psnr_rel) = ((ours_ssim - theirs[0]).abs(), (ours_psnr - theirs[1]).abs() / theirs[1]);
            println!(
                "{name} {w}x{h}: SSIM ours {ours_ssim:.12} skimage {:.12} |diff| {ssim_diff:.2e}; \
                 PSNR ours {ours_psnr:.9} skimage {:.9} rel diff {psnr_rel:.2e}",
                theirs[0], theirs[1]
            );
            assert!(ssim_diff <= 1e-3, "{name}: SSIM {ours_ssim} vs scikit-image {}", theirs[0]);
            assert!(psnr_rel <= 1e-6, "{name}: PSNR {ours_psnr} vs scikit-image {}", theirs[1]);
        }
    }

    #[test]
    fn ssim_time_at_1600x900() {
        let (w, h) = (1600, 900);
        let a = scene(w, h);
        let b = noisy(&a, 10, 9);
        let best_of_3 = || {
            (0..3)
                .map(|_| {
                    let start = Instant::now();
                    std::hint::black_box(ssim(&a, &b, w, h, None));
                    start.elapsed()
                })
                .min()
                .unwrap()
        };
        let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap();
        let one_thread = pool.install(best_of_3);
        let all_threads = best_of_3();
        let start = Instant::now();
        std::hint::black_box(psnr(&a, &b, w, h, None));
        let psnr_time = start.elapsed();
        println!(
            "SSIM {w}x{h}: {one_thread:?} on 1 thread, {all_threads:?} on {} threads; PSNR {psnr_time:?}",
            rayon::current_num_threads()
        );
    }

    #[test]
    fn both_ssims_from_one_pass_equal_the_two_calls() {
        let (w, h) = (64, 48);
        let a = scene(w, h);
        let b = noisy(&a, 20, 3);
        let mask: Vec<bool> = (0..w * h).map(|i| (i / w) % 3 != 0).collect();
        let (all, masked) = ssim_both(&a, &b, w, h, &mask);
        assert_eq!(all, ssim(&a, &b, w, h, None));
        assert_eq!(masked, ssim(&a, &b, w, h, Some(&mask)));
        assert_ne!(all, masked);
    }
}
