//! The completion's builds (portable, AVX2, AVX-512; `complete` runs the widest the CPU has)
//! and the element-wise helpers the phases share, `#[inline(always)]` as every helper of the
//! completion is, so that each build compiles them for its own instruction set.

use super::{complete_portable, Completion, Params};
use dist4d_types::artifact::{DepthMap, Image, Mask};

/// The completion of `sparse` guided by `image`, with the support map when `support` asks for it.
pub fn complete(p: &Params, image: &Image, sparse: &DepthMap, sky: Option<&Mask>, support: bool) -> Completion {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx512f") && std::arch::is_x86_feature_detected!("avx512bw") {
        // SAFETY: the CPU has AVX-512 F and BW, checked just above.
        return unsafe { complete_avx512(p, image, sparse, sky, support) };
    }
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU has AVX2, checked just above.
        return unsafe { complete_avx2(p, image, sparse, sky, support) };
    }
    complete_portable(p, image, sparse, sky, support)
}

/// The same code compiled for AVX2: its element-wise loops and eight-lane sums run in 256-bit
/// vectors instead of two 128-bit ones, ~8% less time per image (docs/BENCHMARKS.md). Without FMA,
/// every operation rounds as in the portable build, so the outputs are bit-identical (a test
/// checks it): which machine of a cluster computed a cached map does not change it.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn complete_avx2(p: &Params, image: &Image, sparse: &DepthMap, sky: Option<&Mask>, support: bool) -> Completion {
    complete_portable(p, image, sparse, sky, support)
}

/// The same code for AVX-512 (F, BW, VL): ~13% less time per image than the AVX2 build on this
/// project's machine (docs/BENCHMARKS.md); bit-identical for the same reason (a test checks it).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512bw,avx512vl,avx2")]
unsafe fn complete_avx512(p: &Params, image: &Image, sparse: &DepthMap, sky: Option<&Mask>, support: bool) -> Completion {
    complete_portable(p, image, sparse, sky, support)
}

/// Luma (ITU-R BT.601 weights, 0-255) of every pixel.
#[inline(always)]
pub(crate) fn luminance(image: &Image) -> Vec<f32> {
    // Collected, not written into a zeroed map: the zeroing was a pass of its own.
    image.rgb.chunks_exact(3).map(|p| 0.299 * p[0] as f32 + 0.587 * p[1] as f32 + 0.114 * p[2] as f32).collect()
}

/// `f` of each element, as a loop inlined into the caller: `collect` would run code compiled once,
/// for the portable build, inside the AVX2 build of the completion too.
#[inline(always)]
pub(super) fn map<T: Copy, U: Copy + Default>(from: &[T], f: impl Fn(T) -> U) -> Vec<U> {
    let mut out = vec![U::default(); from.len()];
    for (o, &x) in out.iter_mut().zip(from) {
        *o = f(x);
    }
    out
}

/// The red, green and blue planes of an RGB8 image, one after the other: the colour differences
/// of the 2D fill and the refinement are then element-wise on contiguous slices, and vectorise.
#[inline(always)]
pub(super) fn colour_planes(rgb: &[u8]) -> Vec<u8> {
    let n = rgb.len() / 3;
    let mut planes = vec![0u8; 3 * n];
    let (red, rest) = planes.split_at_mut(n);
    let (green, blue) = rest.split_at_mut(n);
    for (((px, r), g), b) in rgb.chunks_exact(3).zip(red).zip(green).zip(blue) {
        (*r, *g, *b) = (px[0], px[1], px[2]);
    }
    planes
}

/// Luma (ITU-R BT.601 weights, 0-255) of every pixel of `planes` (as `colour_planes` makes them):
/// what `luminance` gives, to the bit, from contiguous planes (a loop inlined into each build; the
/// iterator `luminance` collects is compiled once, for the portable build).
#[inline(always)]
pub(super) fn luma_of_planes(planes: &[u8]) -> Vec<f32> {
    let n = planes.len() / 3;
    let (red, green, blue) = (&planes[..n], &planes[n..2 * n], &planes[2 * n..]);
    let mut luma = vec![0f32; n];
    for (l, ((&r, &g), &b)) in luma.iter_mut().zip(red.iter().zip(green).zip(blue)) {
        *l = 0.299 * r as f32 + 0.587 * g as f32 + 0.114 * b as f32;
    }
    luma
}

/// The largest positive depth of `depth` (+inf counts, NaN does not), 0 without any. Taken as
/// the largest bit pattern, positive floats ordering as their bits do, in sixteen lanes: an integer
/// maximum that vectorises, where a division per sample into a chained `min` of 1 / z took 7% of
/// the completion's time (1 / the farthest is that least 1 / z to the bit, division being
/// correctly rounded and so monotonic; overflowing to inf where the least was f32::MAX, for a
/// subnormal farthest sample, hence the caller's `min`).
#[inline(always)]
pub(super) fn farthest_sample(depth: &[f32]) -> f32 {
    // Bits of a positive float, subnormal to +inf: 1..=0x7f80_0000; 0 for the rest.
    let key = |z: f32| {
        let b = z.to_bits();
        if b.wrapping_sub(1) < 0x7f80_0000 {
            b
        } else {
            0
        }
    };
    let mut lanes = [0u32; 16];
    let chunks = depth.chunks_exact(16);
    let tail = chunks.remainder().iter().fold(0, |m, &z| key(z).max(m));
    for chunk in chunks {
        for (l, &z) in lanes.iter_mut().zip(chunk) {
            *l = key(z).max(*l);
        }
    }
    f32::from_bits(lanes.iter().fold(tail, |m, &l| m.max(l)))
}

#[cfg(test)]
mod tests {
    use super::super::tests::grey;
    use super::*;

    #[test]
    fn the_farthest_sample_gives_the_least_inverse_depth_to_the_bit() {
        // What it replaced: the least 1 / z over the positive depths (f32::MAX without any).
        let least_inverse = |depth: &[f32]| depth.iter().filter(|&&z| z > 0.0).fold(f32::MAX, |m, &z| m.min(1.0 / z));
        // As `complete_portable` takes it.
        let of = |depth: &[f32]| {
            let z = farthest_sample(depth);
            if z > 0.0 {
                (1.0 / z).min(f32::MAX)
            } else {
                f32::MAX
            }
        };
        let mut rng = dist4d_types::rng::Rng::new(11);
        let odd = [0.0, -0.0, -3.0, f32::NAN, -f32::NAN, f32::NEG_INFINITY, 1e-42, f32::MAX];
        for len in [0, 1, 15, 16, 17, 100, 1_000] {
            let mut depth: Vec<f32> = (0..len).map(|_| rng.range(0.5, 120.0) as f32).collect();
            for (k, &v) in odd.iter().enumerate() {
                if k < len {
                    depth[(k * 7) % len] = v;
                }
            }
            assert_eq!(of(&depth).to_bits(), least_inverse(&depth).to_bits(), "{len} depths");
            if len > 3 {
                depth[len - 2] = f32::INFINITY;
                assert_eq!(of(&depth), 0.0);
                assert_eq!(of(&depth).to_bits(), least_inverse(&depth).to_bits(), "{len} depths, one +inf");
            }
        }
        assert_eq!(farthest_sample(&[0.0, -1.0, f32::NAN]), 0.0);
        // Only subnormal samples: 1 / z overflows; the old least was f32::MAX.
        for depth in [&[1e-42f32][..], &[1e-42, 0.0, 3e-39][..]] {
            assert_eq!(of(depth).to_bits(), least_inverse(depth).to_bits(), "{depth:?}");
        }
    }

    #[test]
    fn the_avx2_and_avx512_builds_compute_bit_for_bit_what_the_portable_one_does() {
        #[cfg(target_arch = "x86_64")]
        {
            if !std::arch::is_x86_feature_detected!("avx2") {
                eprintln!("skipped: this CPU has no AVX2");
                return;
            }
            // A textured scene with a near box, far ground, sky at the top and LiDAR-like rows,
            // large enough for every phase (fill, 2D fill, refinement) to run its vector loops.
            let (w, h) = (160u32, 120u32);
            let mut sparse = DepthMap::new(w, h);
            for y in (40..h as usize).step_by(6) {
                for x in (y % 3..w as usize).step_by(2) {
                    let near = (50..90).contains(&x) && y < 80;
                    sparse.data[y * w as usize + x] = if near { 6.0 + 0.01 * x as f32 } else { 30.0 - 0.1 * y as f32 };
                }
            }
            let image = grey(w, h, |x, y| {
                if y < 20 {
                    [150, 190, 240]
                } else if (50..90).contains(&x) && y < 80 {
                    [40 + (x % 7) as u8, 30, 30 + (y % 5) as u8]
                } else {
                    [120 + ((x * 7 + y * 3) % 23) as u8, 110, 100]
                }
            });
            let sky = Mask { width: w, height: h, data: (0..w * h).map(|i| u8::from(i < 20 * w)).collect() };
            let p = Params::default();
            let portable = complete_portable(&p, &image, &sparse, Some(&sky), true);
            // SAFETY: AVX2 is present, checked above.
            let avx2 = unsafe { complete_avx2(&p, &image, &sparse, Some(&sky), true) };
            let bits = |m: &DepthMap| m.data.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
            let support = |c: &Completion| bits(c.support.as_ref().expect("asked for"));
            assert_eq!(bits(&portable.depth), bits(&avx2.depth));
            assert_eq!(support(&portable), support(&avx2));
            assert!(portable.depth.data.iter().all(|z| z.is_finite() && *z > 0.0));
            if std::arch::is_x86_feature_detected!("avx512f") && std::arch::is_x86_feature_detected!("avx512bw") {
                // SAFETY: AVX-512 F and BW are present, checked just above.
                let avx512 = unsafe { complete_avx512(&p, &image, &sparse, Some(&sky), true) };
                assert_eq!(bits(&portable.depth), bits(&avx512.depth));
                assert_eq!(support(&portable), support(&avx512));
            } else {
                eprintln!("AVX-512 part skipped: this CPU has no AVX-512");
            }
        }
    }
}
