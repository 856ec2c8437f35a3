//! The inner loops of the plane sweep, each in a portable version and an AVX2 version chosen at
//! run time ([`Isa::best`]); the census costs and the SGM passes also in an AVX-512 version.
//!
//! Why several: these loops are nearly all of MultiViewStereo's time (census costs along every
//! pixel's epipolar samples, the 8 SGM path passes, the search for the winning plane), and the
//! portable build targets x86-64-v2, whose 128-bit vectors and missing gathers leave most of an
//! AVX2 machine unused; yet the binary must still run everywhere. Every version gives the same
//! bytes: the vector ones do the same f32 operations in the same order (no fused multiply-add),
//! integer costs are exact, and the tests below compare each with the portable one on random data.
//! On a CPU with AVX-512 (and its VPOPCNTDQ popcount) the wider versions take ~0.7x the AVX2 ones'
//! time (docs/BENCHMARKS.md, "MultiViewStereo speed and memory").
//!
//! The AVX2 versions need at least [`AVX2_MIN_PLANES`] planes (a sweep has at least 8), the
//! AVX-512 ones [`AVX512_MIN_PLANES`]; below that the narrower ones run.

use glam::Vec3;

/// How the kernels run: chosen once per sweep.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Isa {
    /// Plain Rust, any target.
    Portable,
    /// 256-bit vectors, on a CPU that has AVX2: what makes calling the `unsafe` AVX2 kernels
    /// sound. Only [`Isa::available`] can make one (see [`Detected`]).
    #[cfg(target_arch = "x86_64")]
    Avx2(Detected),
    /// 512-bit vectors, on a CPU that has AVX-512 F, BW, VL and VPOPCNTDQ, and AVX2: the cost and
    /// aggregation kernels in their AVX-512 versions, the others in their AVX2 ones.
    #[cfg(target_arch = "x86_64")]
    Avx512(Detected),
}

/// Proof that the CPU was found to have the feature; made nowhere but in this module.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct Detected(());

/// Fewest planes the AVX2 kernels handle: one full vector of 16-bit path costs.
pub(crate) const AVX2_MIN_PLANES: usize = 16;

/// Fewest planes the AVX-512 kernels handle: one full vector of 16-bit path costs. Between
/// [`AVX2_MIN_PLANES`] and this, an AVX-512 CPU runs the AVX2 kernels.
pub(crate) const AVX512_MIN_PLANES: usize = 32;

impl Isa {
    /// The fastest kernels this CPU runs.
    pub(crate) fn best() -> Isa {
        *Isa::available().last().expect("the portable kernels are always available")
    }

    /// Every kind of kernel this CPU runs, portable first.
    pub(crate) fn available() -> Vec<Isa> {
        #[allow(unused_mut)]
        let mut all = vec![Isa::Portable];
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") {
            all.push(Isa::Avx2(Detected(())));
            if std::arch::is_x86_feature_detected!("avx512f")
                && std::arch::is_x86_feature_detected!("avx512bw")
                && std::arch::is_x86_feature_detected!("avx512vl")
                && std::arch::is_x86_feature_detected!("avx512vpopcntdq")
            {
                all.push(Isa::Avx512(Detected(())));
            }
        }
        all
    }

    /// The kernels for a sweep over `planes` planes.
    pub(crate) fn for_planes(self, planes: usize) -> Isa {
        match self {
            _ if planes < AVX2_MIN_PLANES => Isa::Portable,
            // An AVX-512 CPU has AVX2 too (checked with it).
            #[cfg(target_arch = "x86_64")]
            Isa::Avx512(detected) if planes < AVX512_MIN_PLANES => Isa::Avx2(detected),
            isa => isa,
        }
    }
}

/// One source as the cost kernel samples it: its census image and size.
pub(crate) struct SourceCensus<'a> {
    pub census: &'a [u64],
    pub width: usize,
    pub height: usize,
}

/// Census cost of one reference pixel (census `c0`) at every plane: `out[d]` = twice the mean
/// Hamming distance to the samples of the sources that see the plane-`d` point (the ray of
/// source `s` lands at `(a + b rho).xy / (a + b rho).z`, see `Warp`), or `cost_max` when none
/// sees it. `rays[s]` is `(a, b)` of source `s`; `rhos` and `out` have one entry per plane.
pub(crate) fn pixel_costs(
    isa: Isa,
    c0: u64,
    rays: &[(Vec3, Vec3)],
    sources: &[SourceCensus],
    rhos: &[f32],
    cost_max: u8,
    out: &mut [u8],
) {
    assert_eq!(rhos.len(), out.len());
    assert_eq!(rays.len(), sources.len());
    // What the AVX2 gathers rely on: every in-image sample indexes the census, in i32.
    assert!(sources.iter().all(|s| s.census.len() >= s.width * s.height && s.width * s.height <= i32::MAX as usize));
    match isa.for_planes(out.len()) {
        Isa::Portable => portable::pixel_costs(c0, rays, sources, rhos, cost_max, out),
        // SAFETY: `Isa::Avx2` exists only where the CPU has AVX2; the lengths are checked above
        // and `for_planes` guarantees at least 16 planes.
        #[cfg(target_arch = "x86_64")]
        Isa::Avx2(_) => unsafe { avx2::pixel_costs(c0, rays, sources, rhos, cost_max, out) },
        // SAFETY: as above, with AVX-512 F, BW, VL and VPOPCNTDQ present and at least 32 planes.
        #[cfg(target_arch = "x86_64")]
        Isa::Avx512(_) => unsafe { avx512::pixel_costs(c0, rays, sources, rhos, cost_max, out) },
    }
}

/// Semi-global aggregation over 8 paths of a `w` x `h` x `n` cost volume ([pixel][plane]):
/// `done(pixel, sums)` receives each pixel's summed path costs, once, in the order the backward
/// pass reaches them; `scratch` (as large as the volume, any content) holds the forward pass's
/// sums. See `stereo::aggregate` for the recurrence.
#[allow(clippy::too_many_arguments)]
pub(crate) fn aggregate(
    isa: Isa,
    cost: &[u8],
    scratch: &mut [u16],
    w: usize,
    h: usize,
    n: usize,
    p1: u16,
    p2: u16,
    done: impl FnMut(usize, &[u16]),
) {
    assert_eq!(cost.len(), w * h * n);
    assert_eq!(scratch.len(), w * h * n);
    match isa.for_planes(n) {
        Isa::Portable => portable::aggregate(cost, scratch, w, h, n, p1, p2, done),
        // SAFETY: AVX2 is present (see `Isa`), the volumes' sizes are checked above, n >= 16.
        #[cfg(target_arch = "x86_64")]
        Isa::Avx2(_) => unsafe { avx2::aggregate(cost, scratch, w, h, n, p1, p2, done) },
        // SAFETY: AVX-512 F, BW and VL are present (see `Isa`), the sizes are checked, n >= 32.
        #[cfg(target_arch = "x86_64")]
        Isa::Avx512(_) => unsafe { avx512::aggregate(cost, scratch, w, h, n, p1, p2, done) },
    }
}

/// The first plane of least cost and that cost.
pub(crate) fn argmin(isa: Isa, s: &[u16]) -> (usize, u16) {
    assert!(!s.is_empty());
    match isa.for_planes(s.len()) {
        Isa::Portable => portable::argmin(s),
        // SAFETY: AVX2 is present (see `Isa`), s.len() >= 16.
        #[cfg(target_arch = "x86_64")]
        Isa::Avx2(_) | Isa::Avx512(_) => unsafe { avx2::argmin(s) },
    }
}

/// The least cost among planes outside `lo..=hi`; `u16::MAX` when there are none.
pub(crate) fn min_outside(isa: Isa, s: &[u16], lo: usize, hi: usize) -> u16 {
    match isa.for_planes(s.len()) {
        Isa::Portable => portable::min_outside(s, lo, hi),
        // SAFETY: AVX2 is present (see `Isa`), s.len() >= 16.
        #[cfg(target_arch = "x86_64")]
        Isa::Avx2(_) | Isa::Avx512(_) => unsafe { avx2::min_outside(s, lo, hi) },
    }
}

/// Starts of the blocks of `lanes` lanes covering `n` lanes, the last one at `n - lanes`.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn blocks(n: usize, lanes: usize) -> impl Iterator<Item = usize> {
    debug_assert!(n >= lanes);
    let full = n / lanes;
    (0..full).map(move |i| i * lanes).chain((n % lanes != 0).then_some(n - lanes))
}

/// 7x7 census transform of a `w` x `h` grey image, edges clamped: per pixel 48 bits, one per
/// neighbour in row-major order (the first in bit 47), set where the neighbour is darker than
/// the centre.
///
/// One pass per neighbour over a whole row (its bit of every pixel, in one byte plane per 8
/// neighbours), over a copy of the image with its border repeated 3 pixels outward: loops the
/// compiler vectorises, 32 pixels at a time with AVX2.
pub(crate) fn census(isa: Isa, grey: &[u8], w: usize, h: usize) -> Vec<u64> {
    use rayon::prelude::*;
    assert_eq!(grey.len(), w * h);
    let mut out = vec![0u64; w * h];
    if w == 0 || h == 0 {
        return out;
    }
    let padded = pad3(grey, w, h);
    out.par_chunks_mut(w).enumerate().for_each_init(
        || vec![0u8; 6 * w],
        |planes, (y, row)| match isa {
            Isa::Portable => census_row(&padded, w, y, planes, row),
            // SAFETY: AVX2 is present (see `Isa`).
            #[cfg(target_arch = "x86_64")]
            Isa::Avx2(_) | Isa::Avx512(_) => unsafe { avx2::census_row(&padded, w, y, planes, row) },
        },
    );
    out
}

/// The image with its edge pixels repeated 3 times outward, (w + 6) x (h + 6).
fn pad3(grey: &[u8], w: usize, h: usize) -> Vec<u8> {
    let mut out = Vec::with_capacity((w + 6) * (h + 6));
    for py in 0..h + 6 {
        let row = &grey[py.saturating_sub(3).min(h - 1) * w..][..w];
        out.extend(std::iter::repeat_n(row[0], 3));
        out.extend_from_slice(row);
        out.extend(std::iter::repeat_n(row[w - 1], 3));
    }
    out
}

/// Row `y` of the census from the padded image; `planes` is scratch of 6 x w bytes.
#[inline(always)]
fn census_row(padded: &[u8], w: usize, y: usize, planes: &mut [u8], out: &mut [u64]) {
    let pw = w + 6;
    let centre = &padded[(y + 3) * pw + 3..][..w];
    planes.fill(0);
    let mut k = 0;
    for dy in 0..7 {
        for dx in 0..7 {
            if (dy, dx) == (3, 3) {
                continue;
            }
            let neighbour = &padded[(y + dy) * pw + dx..][..w];
            let bit = 0x80u8 >> (k % 8);
            let plane = &mut planes[k / 8 * w..][..w];
            for ((b, &n), &c) in plane.iter_mut().zip(neighbour).zip(centre) {
                *b |= if n < c { bit } else { 0 };
            }
            k += 1;
        }
    }
    let p: [&[u8]; 6] = std::array::from_fn(|g| &planes[g * w..][..w]);
    for (x, o) in out.iter_mut().enumerate() {
        *o = (p[0][x] as u64) << 40
            | (p[1][x] as u64) << 32
            | (p[2][x] as u64) << 24
            | (p[3][x] as u64) << 16
            | (p[4][x] as u64) << 8
            | p[5][x] as u64;
    }
}

/// The reference versions: what the AVX2 versions must equal.
mod portable {
    use super::SourceCensus;
    use crate::stereo::sample_at;
    use glam::Vec3;

    pub(super) fn pixel_costs(
        c0: u64,
        rays: &[(Vec3, Vec3)],
        sources: &[SourceCensus],
        rhos: &[f32],
        cost_max: u8,
        out: &mut [u8],
    ) {
        for (&rho, o) in rhos.iter().zip(out.iter_mut()) {
            let (mut sum, mut count) = (0u16, 0u16);
            for (&(a, b), src) in rays.iter().zip(sources) {
                if let Some((u, v)) = sample_at(a, b, rho, src.width as f32, src.height as f32) {
                    sum += (c0 ^ src.census[v * src.width + u]).count_ones() as u16;
                    count += 1;
                }
            }
            *o = (2 * sum).checked_div(count).map_or(cost_max, |q| q as u8);
        }
    }

    /// Two scanline passes (forward: paths from the left, top-left, top, top-right; backward:
    /// their mirrors), each keeping one row of path costs per direction.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn aggregate(
        cost: &[u8],
        total: &mut [u16],
        w: usize,
        h: usize,
        n: usize,
        p1: u16,
        p2: u16,
        mut done: impl FnMut(usize, &[u16]),
    ) {
        total.fill(0);
        for backward in [false, true] {
            // Directions by neighbour offset in iteration order: left, up-left, up, up-right.
            let mut prev_rows = vec![vec![0u16; w * n]; 3];
            let mut cur_rows = vec![vec![0u16; w * n]; 3];
            let mut prev_mins = vec![vec![0u16; w]; 3];
            let mut cur_mins = vec![vec![0u16; w]; 3];
            let mut left = vec![0u16; n];
            let mut here = vec![0u16; n];
            for yi in 0..h {
                // A cancellation point (see `sweep_depth_with`): one relaxed load per row.
                if dist4d_types::cancel::requested() {
                    return;
                }
                let y = if backward { h - 1 - yi } else { yi };
                let mut left_min = 0u16;
                for xi in 0..w {
                    let x = if backward { w - 1 - xi } else { xi };
                    let pixel = y * w + x;
                    let c = &cost[pixel * n..(pixel + 1) * n];
                    let t = &mut total[pixel * n..(pixel + 1) * n];
                    // From the left (in iteration order).
                    let m = if xi == 0 { start(c, &mut here) } else { step(c, &left, left_min, p1, p2, &mut here) };
                    add(t, &here);
                    std::mem::swap(&mut left, &mut here);
                    left_min = m;
                    // From the previous row: up-left (dx = -1), up (0), up-right (+1).
                    for (dir, dx) in [-1i64, 0, 1].into_iter().enumerate() {
                        let nx = xi as i64 + dx;
                        let out = &mut cur_rows[dir][xi * n..(xi + 1) * n];
                        let m = if yi == 0 || nx < 0 || nx >= w as i64 {
                            start(c, out)
                        } else {
                            let nx = nx as usize;
                            step(c, &prev_rows[dir][nx * n..(nx + 1) * n], prev_mins[dir][nx], p1, p2, out)
                        };
                        cur_mins[dir][xi] = m;
                        add(t, out);
                    }
                    if backward {
                        done(pixel, t);
                    }
                }
                std::mem::swap(&mut prev_rows, &mut cur_rows);
                std::mem::swap(&mut prev_mins, &mut cur_mins);
            }
        }
    }

    #[inline]
    fn start(c: &[u8], out: &mut [u16]) -> u16 {
        let mut m = u16::MAX;
        for (o, &v) in out.iter_mut().zip(c) {
            *o = v as u16;
            m = m.min(*o);
        }
        m
    }

    /// One SGM path step: L(p, d) = C(p, d) + min(L(q, d), L(q, d +- 1) + P1, min L(q) + P2) - min L(q).
    #[inline]
    fn step(c: &[u8], prev: &[u16], prev_min: u16, p1: u16, p2: u16, out: &mut [u16]) -> u16 {
        let n = c.len();
        let jump = prev_min + p2;
        let mut m = u16::MAX;
        let edge = |v: u16, nb: u16, c: u8| (v.min(nb + p1).min(jump) - prev_min) + c as u16;
        out[0] = edge(prev[0], prev[1], c[0]);
        out[n - 1] = edge(prev[n - 1], prev[n - 2], c[n - 1]);
        let (lo, mid, hi) = (&prev[..n - 2], &prev[1..n - 1], &prev[2..]);
        for (((o, &cv), (&a, &b)), &d) in out[1..n - 1].iter_mut().zip(&c[1..n - 1]).zip(lo.iter().zip(mid)).zip(hi) {
            let v = b.min(a.min(d) + p1).min(jump);
            *o = v - prev_min + cv as u16;
        }
        for &o in out.iter() {
            m = m.min(o);
        }
        m
    }

    #[inline]
    fn add(t: &mut [u16], v: &[u16]) {
        for (a, &b) in t.iter_mut().zip(v) {
            *a += b;
        }
    }

    pub(super) fn argmin(s: &[u16]) -> (usize, u16) {
        let (best, &v) = s.iter().enumerate().min_by_key(|(_, &v)| v).expect("not empty");
        (best, v)
    }

    pub(super) fn min_outside(s: &[u16], lo: usize, hi: usize) -> u16 {
        s.iter().enumerate().filter(|&(d, _)| d < lo || d > hi).map(|(_, &v)| v).min().unwrap_or(u16::MAX)
    }
}

/// 32 lanes of u16 on a 64-byte boundary: the unit the vector kernels' path buffers are made of.
#[cfg(target_arch = "x86_64")]
#[derive(Clone, Copy)]
#[repr(C, align(64))]
struct Lanes([u16; 32]);

/// Rows of path costs for the vector SGM kernels, one pixel every `stride` lanes. A pixel's costs
/// start `PAD` lanes in (a vector's width), after a `u16::MAX` sentinel (plane -1) and before
/// another (plane n): the neighbours d +- 1 of every plane are then plain loads, and a missing one
/// never wins a minimum. Every pixel starts on a vector boundary.
#[cfg(target_arch = "x86_64")]
struct PathRows<const PAD: usize> {
    lanes: Vec<Lanes>,
    stride: usize,
}

#[cfg(target_arch = "x86_64")]
impl<const PAD: usize> PathRows<PAD> {
    fn new(pixels: usize, n: usize) -> PathRows<PAD> {
        let stride = n.div_ceil(PAD) * PAD + 2 * PAD;
        PathRows { lanes: vec![Lanes([u16::MAX; 32]); (pixels * stride).div_ceil(32)], stride }
    }

    #[inline(always)]
    fn pixel(&self, x: usize) -> *const u16 {
        (self.lanes.as_ptr() as *const u16).wrapping_add(x * self.stride)
    }

    #[inline(always)]
    fn pixel_mut(&mut self, x: usize) -> *mut u16 {
        (self.lanes.as_mut_ptr() as *mut u16).wrapping_add(x * self.stride)
    }
}

/// The two scanline passes of the vector SGM kernels, their buffers and their order (the
/// portable `aggregate`'s recurrence): `step(c, prev, prev_min, out, earlier, sums)` is the
/// kernel's work for one pixel's four paths, as its `pixel_paths` documents, and returns their
/// minima; `PAD` is its vector's width in lanes. The forward pass stores its four paths' sums per
/// pixel; the backward pass adds its own into one pixel's scratch and hands that to `done`: the
/// complete sums never go to memory.
///
/// # Safety
/// `cost` and `forward` hold `w * h * n` values and `step` may be called with pointers into them
/// and into buffers of `n` planes padded by `PAD` lanes each side.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
#[allow(clippy::too_many_arguments, clippy::type_complexity)]
unsafe fn scanline_passes<const PAD: usize>(
    cost: &[u8],
    forward: &mut [u16],
    w: usize,
    h: usize,
    n: usize,
    mut done: impl FnMut(usize, &[u16]),
    mut step: impl FnMut(*const u8, [*const u16; 4], [u16; 4], [*mut u16; 4], *const u16, *mut u16) -> [u16; 4],
) {
    use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
    /// How many pixels ahead the backward pass prefetches.
    const AHEAD: usize = 2;
    // Asks for the cache lines of `bytes` bytes from `p` into every cache level.
    let prefetch = |p: *const u8, bytes: usize| {
        for line in (0..bytes).step_by(64) {
            // SAFETY: a prefetch never faults; SSE is in every x86-64 CPU.
            unsafe { _mm_prefetch::<_MM_HINT_T0>(p.wrapping_add(line) as *const i8) };
        }
    };
    let mut sums = vec![Lanes([0; 32]); n.div_ceil(32)];
    for backward in [false, true] {
        // Path costs of the previous and the current row for up-left, up, up-right, with their
        // minima, and of the previous and the current pixel for the path from the left.
        let rows = || [PathRows::<PAD>::new(w, n), PathRows::new(w, n), PathRows::new(w, n)];
        let (mut prev_rows, mut cur_rows) = (rows(), rows());
        let mut prev_mins = [vec![0u16; w], vec![0u16; w], vec![0u16; w]];
        let mut cur_mins = [vec![0u16; w], vec![0u16; w], vec![0u16; w]];
        let mut left = PathRows::<PAD>::new(1, n);
        let mut here = PathRows::<PAD>::new(1, n);
        for yi in 0..h {
            // A cancellation point (see `sweep_depth_with`): one relaxed load per row.
            if dist4d_types::cancel::requested() {
                return;
            }
            let y = if backward { h - 1 - yi } else { yi };
            let mut left_min = 0u16;
            for xi in 0..w {
                let x = if backward { w - 1 - xi } else { xi };
                let pixel = y * w + x;
                let mut prev = [std::ptr::null(); 4];
                let mut prev_min = [0u16; 4];
                if xi > 0 {
                    prev[0] = left.pixel(0);
                    prev_min[0] = left_min;
                }
                for dir in 0..3 {
                    let nx = xi as i64 + dir as i64 - 1;
                    if yi > 0 && nx >= 0 && nx < w as i64 {
                        prev[dir + 1] = prev_rows[dir].pixel(nx as usize);
                        prev_min[dir + 1] = prev_mins[dir][nx as usize];
                    }
                }
                let [r0, r1, r2] = &mut cur_rows;
                let out = [here.pixel_mut(0), r0.pixel_mut(xi), r1.pixel_mut(xi), r2.pixel_mut(xi)];
                let (earlier, to) = if backward {
                    (forward.as_ptr().add(pixel * n), sums.as_mut_ptr() as *mut u16)
                } else {
                    (std::ptr::null(), forward.as_mut_ptr().add(pixel * n))
                };
                if backward && pixel >= AHEAD {
                    // The backward pass walks memory downwards, which the hardware prefetchers
                    // follow poorly: ask for the pixel after next.
                    prefetch(cost.as_ptr().add((pixel - AHEAD) * n), n);
                    prefetch(forward.as_ptr().add((pixel - AHEAD) * n) as *const u8, 2 * n);
                }
                let m = step(cost.as_ptr().add(pixel * n), prev, prev_min, out, earlier, to);
                if backward {
                    done(pixel, std::slice::from_raw_parts(sums.as_ptr() as *const u16, n));
                }
                std::mem::swap(&mut left, &mut here);
                left_min = m[0];
                for (mins, &m) in cur_mins.iter_mut().zip(&m[1..]) {
                    mins[xi] = m;
                }
            }
            std::mem::swap(&mut prev_rows, &mut cur_rows);
            std::mem::swap(&mut prev_mins, &mut cur_mins);
        }
    }
}

/// AVX2 versions. Every function requires AVX2 (the caller's `Isa::Avx2` proves it) and at least
/// 16 planes. A plane count that is not a multiple of the vector width is handled by a last
/// vector that overlaps the one before it: its lanes are recomputed to the same values.
#[cfg(target_arch = "x86_64")]
mod avx2 {
    use super::SourceCensus;
    use glam::Vec3;
    use std::arch::x86_64::*;

    use super::blocks;

    /// Popcount of each 64-bit lane (a nibble table looked up by `vpshufb`, summed by `vpsadbw`).
    #[inline]
    #[target_feature(enable = "avx2")]
    unsafe fn popcount_u64x4(x: __m256i) -> __m256i {
        let table = _mm256_setr_epi8(
            0, 1, 1, 2, 1, 2, 2, 3, 1, 2, 2, 3, 2, 3, 3, 4, 0, 1, 1, 2, 1, 2, 2, 3, 1, 2, 2, 3, 2, 3, 3, 4,
        );
        let nibble = _mm256_set1_epi8(0x0f);
        let lo = _mm256_shuffle_epi8(table, _mm256_and_si256(x, nibble));
        let hi = _mm256_shuffle_epi8(table, _mm256_and_si256(_mm256_srli_epi16::<4>(x), nibble));
        _mm256_sad_epu8(_mm256_add_epi8(lo, hi), _mm256_setzero_si256())
    }

    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn pixel_costs(
        c0: u64,
        rays: &[(Vec3, Vec3)],
        sources: &[SourceCensus],
        rhos: &[f32],
        cost_max: u8,
        out: &mut [u8],
    ) {
        let n = out.len();
        let c0v = _mm256_set1_epi64x(c0 as i64);
        let (zero, one, near) = (_mm256_setzero_ps(), _mm256_set1_ps(1.0), _mm256_set1_ps(1e-9));
        // The 64-bit popcounts of the low and high four lanes, put back in lane order as i32.
        let order = _mm256_setr_epi32(0, 2, 4, 6, 1, 3, 5, 7);
        // Byte 0 of each i32 lane, to the low 4 bytes of each 128-bit half.
        let bytes = _mm256_setr_epi8(
            0, 4, 8, 12, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, 0, 4, 8, 12, -1, -1, -1, -1, -1, -1, -1, -1,
            -1, -1, -1, -1,
        );
        let max = _mm256_set1_epi32(cost_max as i32);
        for d in blocks(n, 8) {
            let rho = _mm256_loadu_ps(rhos.as_ptr().add(d));
            let (mut sum, mut count) = (_mm256_setzero_si256(), _mm256_setzero_si256());
            for (&(a, b), src) in rays.iter().zip(sources) {
                // z = a.z + b.z rho, u = (a.x + b.x rho) / z as in the portable code: the same
                // operations, each rounded the same way.
                let z = _mm256_add_ps(_mm256_set1_ps(a.z), _mm256_mul_ps(_mm256_set1_ps(b.z), rho));
                let inv = _mm256_div_ps(one, z);
                let u = _mm256_mul_ps(_mm256_add_ps(_mm256_set1_ps(a.x), _mm256_mul_ps(_mm256_set1_ps(b.x), rho)), inv);
                let v = _mm256_mul_ps(_mm256_add_ps(_mm256_set1_ps(a.y), _mm256_mul_ps(_mm256_set1_ps(b.y), rho)), inv);
                // A NaN z fails `> near` here and `z <= 1e-9` there, but then gives NaN u, v,
                // which fail the bounds in both.
                let inside = _mm256_and_ps(
                    _mm256_and_ps(_mm256_cmp_ps::<_CMP_GT_OQ>(z, near), _mm256_cmp_ps::<_CMP_GE_OQ>(u, zero)),
                    _mm256_and_ps(
                        _mm256_and_ps(
                            _mm256_cmp_ps::<_CMP_GE_OQ>(v, zero),
                            _mm256_cmp_ps::<_CMP_LT_OQ>(u, _mm256_set1_ps(src.width as f32)),
                        ),
                        _mm256_cmp_ps::<_CMP_LT_OQ>(v, _mm256_set1_ps(src.height as f32)),
                    ),
                );
                let inside = _mm256_castps_si256(inside);
                if _mm256_testz_si256(inside, inside) != 0 {
                    continue;
                }
                // Truncation toward zero, as `as usize` of a non-negative float; lanes outside
                // read pixel 0 and are masked off.
                let index = _mm256_add_epi32(
                    _mm256_mullo_epi32(_mm256_cvttps_epi32(v), _mm256_set1_epi32(src.width as i32)),
                    _mm256_cvttps_epi32(u),
                );
                let index = _mm256_and_si256(index, inside);
                let base = src.census.as_ptr() as *const i64;
                let lo = _mm256_i32gather_epi64::<8>(base, _mm256_castsi256_si128(index));
                let hi = _mm256_i32gather_epi64::<8>(base, _mm256_extracti128_si256::<1>(index));
                let lo = popcount_u64x4(_mm256_xor_si256(lo, c0v));
                let hi = popcount_u64x4(_mm256_xor_si256(hi, c0v));
                let bits = _mm256_permutevar8x32_epi32(_mm256_or_si256(lo, _mm256_slli_epi64::<32>(hi)), order);
                sum = _mm256_add_epi32(sum, _mm256_and_si256(bits, inside));
                count = _mm256_sub_epi32(count, inside);
            }
            let q = if rays.len() <= 2 {
                // 2 sum / count with count 1 or 2 where seen: a shift.
                _mm256_srlv_epi32(_mm256_add_epi32(sum, sum), _mm256_sub_epi32(count, _mm256_set1_epi32(1)))
            } else {
                // 2 sum / count, exactly: 2 sum <= 2 x 48 x 16 sources, so the f32 quotient is
                // within 2^-13 of the true one, whose fraction is at most 1 - 1/16: truncation
                // gives the integer quotient.
                _mm256_cvttps_epi32(_mm256_div_ps(
                    _mm256_cvtepi32_ps(_mm256_add_epi32(sum, sum)),
                    _mm256_cvtepi32_ps(count),
                ))
            };
            let seen = _mm256_cmpgt_epi32(count, _mm256_setzero_si256());
            let q = _mm256_blendv_epi8(max, q, seen);
            let packed =
                _mm256_permutevar8x32_epi32(_mm256_shuffle_epi8(q, bytes), _mm256_setr_epi32(0, 4, 1, 1, 1, 1, 1, 1));
            _mm_storel_epi64(out.as_mut_ptr().add(d) as *mut __m128i, _mm256_castsi256_si128(packed));
        }
    }

    /// Least of 16 u16 lanes.
    #[inline]
    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn hmin(v: __m256i) -> u16 {
        let m = _mm_min_epu16(_mm256_castsi256_si128(v), _mm256_extracti128_si256::<1>(v));
        _mm_extract_epi16::<0>(_mm_minpos_epu16(m)) as u16
    }

    /// Lanes of a vector, and so a path buffer's padding each side of a pixel (see `PathRows`).
    const PAD: usize = 16;

    /// A vector load, from a 32-byte aligned address if `ALIGNED` (the compiler splits
    /// unaligned 256-bit loads and stores in two for the x86-64-v2 baseline's tuning).
    #[inline]
    #[target_feature(enable = "avx2")]
    unsafe fn load<const ALIGNED: bool>(p: *const u16) -> __m256i {
        if ALIGNED {
            _mm256_load_si256(p as *const __m256i)
        } else {
            _mm256_loadu_si256(p as *const __m256i)
        }
    }

    #[inline]
    #[target_feature(enable = "avx2")]
    unsafe fn store<const ALIGNED: bool>(p: *mut u16, v: __m256i) {
        if ALIGNED {
            _mm256_store_si256(p as *mut __m256i, v)
        } else {
            _mm256_storeu_si256(p as *mut __m256i, v)
        }
    }

    /// One pixel's step of the four paths a scanline pass carries (left, and from the previous
    /// row up-left, up, up-right). `prev[k]` is the path's previous pixel (null: the path starts
    /// here, L = C) with its minimum `prev_min[k]`; `out[k]` receives L. `sums` receives the
    /// four L added (to `earlier`, the other pass's sums, unless null). Returns the minima of
    /// the four new L. `ALIGNED`: n is a multiple of 16 and `earlier`, `sums` are 32-byte aligned.
    ///
    /// A last block overlapping the one before recomputes its lanes to the same values, so
    /// every store here may be repeated.
    #[inline]
    #[target_feature(enable = "avx2")]
    #[allow(clippy::too_many_arguments)]
    unsafe fn pixel_paths<const ALIGNED: bool>(
        c: *const u8,
        n: usize,
        prev: [*const u16; 4],
        prev_min: [u16; 4],
        out: [*mut u16; 4],
        earlier: *const u16,
        sums: *mut u16,
        p1: __m256i,
        p2: u16,
    ) -> [u16; 4] {
        let jump: [__m256i; 4] = std::array::from_fn(|k| _mm256_set1_epi16(prev_min[k].wrapping_add(p2) as i16));
        let pm: [__m256i; 4] = std::array::from_fn(|k| _mm256_set1_epi16(prev_min[k] as i16));
        let mut mins = [_mm256_set1_epi16(-1); 4];
        for d in blocks(n, 16) {
            let cv = _mm256_cvtepu8_epi16(_mm_loadu_si128(c.add(d) as *const __m128i));
            let mut acc = if earlier.is_null() { _mm256_setzero_si256() } else { load::<ALIGNED>(earlier.add(d)) };
            for k in 0..4 {
                let l = if prev[k].is_null() {
                    cv
                } else {
                    let p = prev[k].add(PAD + d);
                    let (below, same, above) = (load::<false>(p.sub(1)), load::<ALIGNED>(p), load::<false>(p.add(1)));
                    let near = _mm256_adds_epu16(_mm256_min_epu16(below, above), p1);
                    let v = _mm256_min_epu16(_mm256_min_epu16(same, near), jump[k]);
                    _mm256_add_epi16(_mm256_sub_epi16(v, pm[k]), cv)
                };
                store::<ALIGNED>(out[k].add(PAD + d), l);
                mins[k] = _mm256_min_epu16(mins[k], l);
                acc = _mm256_add_epi16(acc, l);
            }
            store::<ALIGNED>(sums.add(d), acc);
        }
        [hmin(mins[0]), hmin(mins[1]), hmin(mins[2]), hmin(mins[3])]
    }

    /// The scanline passes (`scanline_passes`), each pixel's paths by `pixel_paths`.
    #[target_feature(enable = "avx2")]
    #[allow(clippy::too_many_arguments)]
    pub(super) unsafe fn aggregate(
        cost: &[u8],
        forward: &mut [u16],
        w: usize,
        h: usize,
        n: usize,
        p1: u16,
        p2: u16,
        done: impl FnMut(usize, &[u16]),
    ) {
        // Whole aligned vectors when every pixel's sums start on a vector boundary (the usual
        // 256 planes in a page-aligned buffer); the same arithmetic either way.
        if n % 16 == 0 && forward.as_ptr() as usize % 32 == 0 {
            aggregate_as::<true>(cost, forward, w, h, n, p1, p2, done)
        } else {
            aggregate_as::<false>(cost, forward, w, h, n, p1, p2, done)
        }
    }

    #[target_feature(enable = "avx2")]
    #[allow(clippy::too_many_arguments)]
    unsafe fn aggregate_as<const ALIGNED: bool>(
        cost: &[u8],
        forward: &mut [u16],
        w: usize,
        h: usize,
        n: usize,
        p1: u16,
        p2: u16,
        done: impl FnMut(usize, &[u16]),
    ) {
        let p1v = _mm256_set1_epi16(p1 as i16);
        super::scanline_passes::<PAD>(cost, forward, w, h, n, done, |c, prev, prev_min, out, earlier, to| {
            // SAFETY: AVX2 is present (this function's caller proves it); the pointers are the
            // passes' buffers, each with room for n planes and the padding.
            unsafe { pixel_paths::<ALIGNED>(c, n, prev, prev_min, out, earlier, to, p1v, p2) }
        })
    }

    /// The portable row census, compiled for AVX2.
    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn census_row(padded: &[u8], w: usize, y: usize, planes: &mut [u8], out: &mut [u64]) {
        super::census_row(padded, w, y, planes, out)
    }

    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn argmin(s: &[u16]) -> (usize, u16) {
        let p = s.as_ptr();
        let mut m = _mm256_set1_epi16(-1);
        for d in blocks(s.len(), 16) {
            m = _mm256_min_epu16(m, _mm256_loadu_si256(p.add(d) as *const __m256i));
        }
        let least = hmin(m);
        let target = _mm256_set1_epi16(least as i16);
        for d in blocks(s.len(), 16) {
            let hit = _mm256_movemask_epi8(_mm256_cmpeq_epi16(_mm256_loadu_si256(p.add(d) as *const __m256i), target));
            if hit != 0 {
                return (d + hit.trailing_zeros() as usize / 2, least);
            }
        }
        unreachable!("the least value is in the slice")
    }

    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn min_outside(s: &[u16], lo: usize, hi: usize) -> u16 {
        // Plane indices fit i16 (at most 1024 planes); the band is clamped to that range.
        let (lo, hi) = (lo.min(i16::MAX as usize) as i16, hi.min(i16::MAX as usize - 16) as i16);
        let (lo, hi) = (_mm256_set1_epi16(lo), _mm256_set1_epi16(hi));
        let lane = _mm256_setr_epi16(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
        let p = s.as_ptr();
        let ones = _mm256_set1_epi16(-1);
        let mut m = ones;
        for d in blocks(s.len(), 16) {
            let index = _mm256_add_epi16(lane, _mm256_set1_epi16(d as i16));
            let outside = _mm256_or_si256(_mm256_cmpgt_epi16(lo, index), _mm256_cmpgt_epi16(index, hi));
            // Planes inside the band read as u16::MAX.
            let v = _mm256_or_si256(_mm256_loadu_si256(p.add(d) as *const __m256i), _mm256_andnot_si256(outside, ones));
            m = _mm256_min_epu16(m, v);
        }
        hmin(m)
    }
}

/// AVX-512 versions of the cost and aggregation kernels: the AVX2 ones' operations on vectors
/// twice as wide (16 planes of f32 costs, 32 of u16 path costs), with the popcount of AVX-512
/// VPOPCNTDQ in place of the nibble table. Every function requires AVX-512 F, BW, VL and
/// VPOPCNTDQ and AVX2 (the caller's `Isa::Avx512` proves them) and at least 32 planes.
#[cfg(target_arch = "x86_64")]
mod avx512 {
    use super::{avx2::hmin, blocks, SourceCensus};
    use glam::Vec3;
    use std::arch::x86_64::*;

    #[target_feature(enable = "avx2,avx512f,avx512bw,avx512vl,avx512vpopcntdq")]
    pub(super) unsafe fn pixel_costs(
        c0: u64,
        rays: &[(Vec3, Vec3)],
        sources: &[SourceCensus],
        rhos: &[f32],
        cost_max: u8,
        out: &mut [u8],
    ) {
        let n = out.len();
        let c0v = _mm512_set1_epi64(c0 as i64);
        let (zero, one, near) = (_mm512_setzero_ps(), _mm512_set1_ps(1.0), _mm512_set1_ps(1e-9));
        let max = _mm512_set1_epi32(cost_max as i32);
        let ones = _mm512_set1_epi32(1);
        for d in blocks(n, 16) {
            let rho = _mm512_loadu_ps(rhos.as_ptr().add(d));
            let (mut sum, mut count) = (_mm512_setzero_si512(), _mm512_setzero_si512());
            for (&(a, b), src) in rays.iter().zip(sources) {
                // The portable code's operations, each rounded the same way (see the AVX2 one).
                let z = _mm512_add_ps(_mm512_set1_ps(a.z), _mm512_mul_ps(_mm512_set1_ps(b.z), rho));
                let inv = _mm512_div_ps(one, z);
                let u = _mm512_mul_ps(_mm512_add_ps(_mm512_set1_ps(a.x), _mm512_mul_ps(_mm512_set1_ps(b.x), rho)), inv);
                let v = _mm512_mul_ps(_mm512_add_ps(_mm512_set1_ps(a.y), _mm512_mul_ps(_mm512_set1_ps(b.y), rho)), inv);
                let inside = _mm512_cmp_ps_mask::<_CMP_GT_OQ>(z, near)
                    & _mm512_cmp_ps_mask::<_CMP_GE_OQ>(u, zero)
                    & _mm512_cmp_ps_mask::<_CMP_GE_OQ>(v, zero)
                    & _mm512_cmp_ps_mask::<_CMP_LT_OQ>(u, _mm512_set1_ps(src.width as f32))
                    & _mm512_cmp_ps_mask::<_CMP_LT_OQ>(v, _mm512_set1_ps(src.height as f32));
                if inside == 0 {
                    continue;
                }
                // Truncation toward zero, as `as usize` of a non-negative float; lanes outside
                // read pixel 0 and are masked off.
                let index = _mm512_maskz_mov_epi32(
                    inside,
                    _mm512_add_epi32(
                        _mm512_mullo_epi32(_mm512_cvttps_epi32(v), _mm512_set1_epi32(src.width as i32)),
                        _mm512_cvttps_epi32(u),
                    ),
                );
                let base = src.census.as_ptr() as *const i64;
                let lo = _mm512_i32gather_epi64::<8>(_mm512_castsi512_si256(index), base);
                let hi = _mm512_i32gather_epi64::<8>(_mm512_extracti64x4_epi64::<1>(index), base);
                let lo = _mm512_cvtepi64_epi32(_mm512_popcnt_epi64(_mm512_xor_si512(lo, c0v)));
                let hi = _mm512_cvtepi64_epi32(_mm512_popcnt_epi64(_mm512_xor_si512(hi, c0v)));
                let bits = _mm512_inserti64x4::<1>(_mm512_castsi256_si512(lo), hi);
                sum = _mm512_mask_add_epi32(sum, inside, sum, bits);
                count = _mm512_mask_add_epi32(count, inside, count, ones);
            }
            let q = if rays.len() <= 2 {
                // 2 sum / count with count 1 or 2 where seen: a shift.
                _mm512_srlv_epi32(_mm512_add_epi32(sum, sum), _mm512_sub_epi32(count, ones))
            } else {
                // Exact, as in the AVX2 kernel.
                _mm512_cvttps_epi32(_mm512_div_ps(
                    _mm512_cvtepi32_ps(_mm512_add_epi32(sum, sum)),
                    _mm512_cvtepi32_ps(count),
                ))
            };
            let seen = _mm512_cmpgt_epi32_mask(count, _mm512_setzero_si512());
            let q = _mm512_mask_blend_epi32(seen, max, q);
            _mm_storeu_si128(out.as_mut_ptr().add(d) as *mut __m128i, _mm512_cvtepi32_epi8(q));
        }
    }

    /// Lanes of a vector, and so a path buffer's padding each side of a pixel (see `PathRows`):
    /// each pixel's costs then start on a 64-byte boundary.
    const PAD: usize = 32;

    #[inline]
    #[target_feature(enable = "avx2,avx512f,avx512bw,avx512vl")]
    unsafe fn load(p: *const u16) -> __m512i {
        _mm512_loadu_si512(p as *const _)
    }

    #[inline]
    #[target_feature(enable = "avx2,avx512f,avx512bw,avx512vl")]
    unsafe fn store(p: *mut u16, v: __m512i) {
        _mm512_storeu_si512(p as *mut _, v)
    }

    /// Least of 32 u16 lanes.
    #[inline]
    #[target_feature(enable = "avx2,avx512f,avx512bw,avx512vl")]
    unsafe fn hmin32(v: __m512i) -> u16 {
        hmin(_mm256_min_epu16(_mm512_castsi512_si256(v), _mm512_extracti64x4_epi64::<1>(v)))
    }

    /// One pixel's step of the four paths of a scanline pass: the AVX2 kernel's `pixel_paths`.
    #[inline]
    #[target_feature(enable = "avx2,avx512f,avx512bw,avx512vl")]
    #[allow(clippy::too_many_arguments)]
    unsafe fn pixel_paths(
        c: *const u8,
        n: usize,
        prev: [*const u16; 4],
        prev_min: [u16; 4],
        out: [*mut u16; 4],
        earlier: *const u16,
        sums: *mut u16,
        p1: __m512i,
        p2: u16,
    ) -> [u16; 4] {
        let jump: [__m512i; 4] = std::array::from_fn(|k| _mm512_set1_epi16(prev_min[k].wrapping_add(p2) as i16));
        let pm: [__m512i; 4] = std::array::from_fn(|k| _mm512_set1_epi16(prev_min[k] as i16));
        let mut mins = [_mm512_set1_epi16(-1); 4];
        for d in blocks(n, 32) {
            let cv = _mm512_cvtepu8_epi16(_mm256_loadu_si256(c.add(d) as *const __m256i));
            let mut acc = if earlier.is_null() { _mm512_setzero_si512() } else { load(earlier.add(d)) };
            for k in 0..4 {
                let l = if prev[k].is_null() {
                    cv
                } else {
                    let p = prev[k].add(PAD + d);
                    let (below, same, above) = (load(p.sub(1)), load(p), load(p.add(1)));
                    let near = _mm512_adds_epu16(_mm512_min_epu16(below, above), p1);
                    let v = _mm512_min_epu16(_mm512_min_epu16(same, near), jump[k]);
                    _mm512_add_epi16(_mm512_sub_epi16(v, pm[k]), cv)
                };
                store(out[k].add(PAD + d), l);
                mins[k] = _mm512_min_epu16(mins[k], l);
                acc = _mm512_add_epi16(acc, l);
            }
            store(sums.add(d), acc);
        }
        [hmin32(mins[0]), hmin32(mins[1]), hmin32(mins[2]), hmin32(mins[3])]
    }

    /// The AVX2 kernel's `aggregate` (the same passes, buffers and order), 32 planes a vector.
    #[target_feature(enable = "avx2,avx512f,avx512bw,avx512vl")]
    #[allow(clippy::too_many_arguments)]
    pub(super) unsafe fn aggregate(
        cost: &[u8],
        forward: &mut [u16],
        w: usize,
        h: usize,
        n: usize,
        p1: u16,
        p2: u16,
        done: impl FnMut(usize, &[u16]),
    ) {
        let p1v = _mm512_set1_epi16(p1 as i16);
        super::scanline_passes::<PAD>(cost, forward, w, h, n, done, |c, prev, prev_min, out, earlier, to| {
            // SAFETY: AVX-512 F, BW and VL are present (this function's caller proves it); the
            // pointers are the passes' buffers, each with room for n planes and the padding.
            unsafe { pixel_paths(c, n, prev, prev_min, out, earlier, to, p1v, p2) }
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use dist4d_types::rng::Rng;

    /// Every available kind of kernel, with what the portable one gives first.
    /// Returns the portable kernel's result.
    fn each_isa<T: PartialEq + std::fmt::Debug>(what: &str, f: impl Fn(Isa) -> T) -> T {
        let isas = Isa::available();
        let reference = f(Isa::Portable);
        for isa in &isas[1..] {
            assert_eq!(f(*isa), reference, "{what}: {isa:?} differs from the portable kernel");
        }
        reference
    }

    #[test]
    fn the_portable_kernels_are_always_available_and_come_first() {
        assert_eq!(Isa::available()[0], Isa::Portable);
        assert_eq!(Isa::best().for_planes(AVX2_MIN_PLANES - 1), Isa::Portable);
        #[cfg(target_arch = "x86_64")]
        assert!(!matches!(Isa::best().for_planes(AVX512_MIN_PLANES - 1), Isa::Avx512(_)));
    }

    /// The census as first written: 48 comparisons per pixel, coordinates clamped.
    fn census_by_pixel(grey: &[u8], w: usize, h: usize) -> Vec<u64> {
        let mut out = vec![0u64; w * h];
        for y in 0..h {
            for x in 0..w {
                let c = grey[y * w + x];
                let mut bits = 0u64;
                for dy in -3i32..=3 {
                    let yy = (y as i32 + dy).clamp(0, h as i32 - 1) as usize;
                    for dx in -3i32..=3 {
                        if dx == 0 && dy == 0 {
                            continue;
                        }
                        let xx = (x as i32 + dx).clamp(0, w as i32 - 1) as usize;
                        bits = (bits << 1) | (grey[yy * w + xx] < c) as u64;
                    }
                }
                out[y * w + x] = bits;
            }
        }
        out
    }

    #[test]
    fn the_census_is_the_same_with_every_kernel_and_as_first_written() {
        let mut rng = Rng::new(11);
        for (w, h) in [(1, 1), (2, 9), (9, 2), (7, 7), (33, 17), (64, 5), (401, 13)] {
            // Full range, and few levels (many equal neighbours).
            for levels in [256, 3] {
                let grey: Vec<u8> =
                    (0..w * h).map(|_| (rng.next_u64() % levels) as u8 * (255 / (levels - 1)) as u8).collect();
                let expected = census_by_pixel(&grey, w, h);
                each_isa("census", |isa| {
                    let c = census(isa, &grey, w, h);
                    assert_eq!(c, expected, "{w}x{h}, {levels} levels, {isa:?}");
                    c
                });
            }
        }
        assert!(census(Isa::best(), &[], 0, 0).is_empty());
    }

    #[test]
    fn census_costs_are_the_same_with_every_kernel() {
        let mut rng = Rng::new(3);
        let (mut seen, mut planes) = (0, 0);
        for case in 0..40usize {
            let n = [16, 17, 23, 33, 64, 126, 256][case % 7];
            let sources: Vec<(usize, usize, Vec<u64>)> = (0..1 + case % 4)
                .map(|_| {
                    let (w, h) = (40 + (rng.next_u64() % 30) as usize, 20 + (rng.next_u64() % 20) as usize);
                    (w, h, (0..w * h).map(|_| rng.next_u64() & ((1 << 48) - 1)).collect())
                })
                .collect();
            let views: Vec<SourceCensus> =
                sources.iter().map(|(w, h, c)| SourceCensus { census: c, width: *w, height: *h }).collect();
            // Rays that enter and leave the images, pass behind the camera, and one that starts
            // exactly on a pixel boundary.
            let rays: Vec<(Vec3, Vec3)> = views
                .iter()
                .map(|v| {
                    let z = rng.range(-0.2, 1.0) as f32;
                    let a = Vec3::new(
                        rng.range(-10.0, v.width as f64 + 10.0) as f32,
                        rng.range(-5.0, v.height as f64) as f32,
                        1.0,
                    );
                    let b = Vec3::new(rng.range(-200.0, 200.0) as f32, rng.range(-50.0, 50.0) as f32, z);
                    if case % 7 == 0 {
                        (Vec3::new(0.0, 0.0, 1.0), Vec3::new(8.0, 0.0, 0.0))
                    } else {
                        (a, b)
                    }
                })
                .collect();
            let rhos: Vec<f32> = (0..n).map(|i| 0.01 + 0.3 * i as f32 / n as f32).collect();
            let c0 = rng.next_u64() & ((1 << 48) - 1);
            let costs = each_isa("pixel_costs", |isa| {
                let mut out = vec![0u8; n];
                pixel_costs(isa, c0, &rays, &views, &rhos, 96, &mut out);
                out
            });
            seen += costs.iter().filter(|&&c| c != 96).count();
            planes += n;
        }
        // The rays do cross the images for a good part of the planes.
        assert!(seen > planes / 5, "{seen} of {planes}");
    }

    #[test]
    fn sgm_aggregation_is_the_same_with_every_kernel() {
        let mut rng = Rng::new(5);
        for (w, h, n, p1, p2) in
            [(13, 9, 16, 8, 48), (11, 7, 37, 8, 48), (20, 6, 64, 3, 200), (5, 17, 9, 8, 48), (6, 5, 100, 8, 48)]
        {
            // Smooth stretches (long runs of path minima) and noise.
            let cost: Vec<u8> = (0..w * h * n)
                .map(|i| if (i / n) % 3 == 0 { ((i % n) * 2).min(96) as u8 } else { (rng.next_u64() % 97) as u8 })
                .collect();
            // Scratch with stale content, as a reused buffer has, starting on a vector boundary
            // and off it (the AVX2 kernel's aligned and unaligned variants; the AVX-512 kernel
            // takes both alike).
            for misaligned in [0, 1] {
                each_isa("aggregate", |isa| {
                    let mut sums = vec![None; w * h];
                    let mut buffer = vec![7u16; w * h * n + 32];
                    let start = buffer.as_ptr().align_offset(32) + misaligned;
                    let scratch = &mut buffer[start..start + w * h * n];
                    aggregate(isa, &cost, scratch, w, h, n, p1, p2, |i, s| {
                        assert!(sums[i].replace(s.to_vec()).is_none(), "pixel {i} twice");
                    });
                    sums
                });
            }
        }
    }

    #[test]
    fn winner_searches_are_the_same_with_every_kernel() {
        let mut rng = Rng::new(7);
        for case in 0..200usize {
            let n = 16 + case % 50;
            // Few distinct values, so that ties (the first must win) are common.
            let s: Vec<u16> = (0..n).map(|_| (rng.next_u64() % 6) as u16 * 1000).collect();
            each_isa("argmin", |isa| argmin(isa, &s));
            let best = case % n;
            let apart = case % 9;
            let (lo, hi) = (best.saturating_sub(apart), best + apart);
            each_isa("min_outside", |isa| min_outside(isa, &s, lo, hi));
        }
        assert_eq!(min_outside(Isa::best(), &[5; 16], 0, 20), u16::MAX);
    }
}
