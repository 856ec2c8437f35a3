//! The refinement: a few conjugate-gradient steps towards the colour-affinity least squares of
//! Levin et al. 2004, in a band around the filled map's depth edges, so that they move onto the
//! image's colour edges.

use super::fill::grow_samples;
use super::kernels::map;
use super::Params;

/// A few conjugate-gradient steps on the colour-affinity least squares of Levin, Lischinski and
/// Weiss 2004 (the NYU Depth v2 toolbox's fill), in inverse depth x, near the filled map's depth
/// edges: minimise, over the pixels within `refine_band` px of a depth step of more than
/// `EDGE_STEP`, sum over 4-neighbour links of w_ij (x_i - x_j)^2 + `refine_weight` * sum over
/// samples of (x_i - 1/z_i)^2, with w_ij = exp(-|rgb_i - rgb_j|^2 / 2 `refine_sigma`^2) + 1e-4;
/// every other pixel keeps its value and holds its neighbours in the band (sky neither gives nor
/// takes). Started from the filled map, tens of steps (Jacobi-preconditioned) move depth edges
/// onto colour edges; solved to the end over the whole image it takes thousands and blurs real
/// images across like-coloured surfaces. Figures: docs/BENCHMARKS.md, "What the completion can
/// reach".
#[inline(always)]
pub(super) fn refine(p: &Params, x: &mut [f32], planes: &[u8], sparse: &[f32], sky: &[u8], w: usize, h: usize) {
    /// A depth step (ratio) that marks a depth edge of the filled map.
    const EDGE_STEP: f32 = 1.05;
    if p.refine_iterations == 0 || w < 2 || h < 2 {
        return;
    }
    let n = w * h;
    // Depth edges of the filled map (1 on both sides of a step), grown by the band (a
    // square-window maximum) into the active set.
    let (lo, hi) = (1.0 / EDGE_STEP, EDGE_STEP);
    // 1 where two neighbours (neither sky, both filled) differ by more than the step; no
    // branch, so that the passes below vectorise.
    let step = |a: f32, b: f32, sa: u8, sb: u8| -> u8 {
        ((sa | sb) == 0) as u8 & (a > 0.0) as u8 & (b > 0.0) as u8 & ((a > hi * b) | (a < lo * b)) as u8
    };
    let mut edge = vec![0u8; n];
    let mut flags = vec![0u8; w];
    for y in 0..h {
        let row = y * w;
        let (xr, sr) = (&x[row..row + w], &sky[row..row + w]);
        for (f, (xp, sp)) in flags.iter_mut().zip(xr.windows(2).zip(sr.windows(2))) {
            *f = step(xp[0], xp[1], sp[0], sp[1]);
        }
        flags[w - 1] = 0;
        let er = &mut edge[row..row + w];
        er[0] |= flags[0];
        for (e, f) in er[1..].iter_mut().zip(flags.windows(2)) {
            *e |= f[0] | f[1];
        }
        if y + 1 < h {
            let (xb, sb) = (&x[row + w..row + 2 * w], &sky[row + w..row + 2 * w]);
            for (f, ((&a, &b), (&sa, &sb))) in flags.iter_mut().zip(xr.iter().zip(xb).zip(sr.iter().zip(sb))) {
                *f = step(a, b, sa, sb);
            }
            let (top, bottom) = edge[row..row + 2 * w].split_at_mut(w);
            for ((t, b), &f) in top.iter_mut().zip(bottom.iter_mut()).zip(&flags) {
                *t |= f;
                *b |= f;
            }
        }
    }
    grow_samples(&mut edge, w, h, p.refine_band as usize);
    // Compact numbering of the active pixels, from 1; slot 0 and slot m + 1 hold 0 so that a
    // link leaving the band (or the image) reads a 0 weight and a 0 value without a branch.
    const OUT: u32 = 0;
    let mut at = vec![OUT; n];
    let mut index = Vec::new();
    // A stretch of pixels none of which is in the band is passed over with one test: most are
    // not in it, and the test per pixel, a branch on three maps, was 3% of the completion's time.
    const STRETCH: usize = 64;
    for (c, edges) in edge.chunks(STRETCH).enumerate() {
        if edges.iter().fold(0, |any, &e| any | e) == 0 {
            continue;
        }
        let first = c * STRETCH;
        let pixels = first..first + edges.len();
        let (at, sky, x) = (&mut at[pixels.clone()], &sky[pixels.clone()], &x[pixels]);
        for (t, &e) in edges.iter().enumerate() {
            if e != 0 && sky[t] == 0 && x[t] > 0.0 {
                index.push((first + t) as u32);
                at[t] = index.len() as u32;
            }
        }
    }
    let m = index.len();
    if m == 0 {
        return;
    }
    drop(edge);
    let mut factor = [0f32; 256];
    for (d, f) in factor.iter_mut().enumerate() {
        *f = (-((d * d) as f32) / (2.0 * p.refine_sigma * p.refine_sigma)).exp();
    }
    // The system A u = b over slots 1..=m, with a weight per link direction (0 where the
    // neighbour is outside the band: fixed, its value on the right-hand side). The diagonal holds
    // every link's weight and the sample's hold. Slots run in row-major order, so a run of
    // active pixels whose upper neighbours are all active has those neighbours in consecutive
    // slots too, and A v along such a run is arithmetic on contiguous slices (it vectorises).
    let len = m + 2;
    let [mut left, mut up] = [(); 2].map(|_| vec![0f32; len]);
    let mut diag = vec![1f32; len];
    let mut rhs = vec![0f32; len];
    let mut u = vec![0f32; len];
    // Runs of consecutive slots whose upper neighbours are active and consecutive too: (first
    // slot, length, first upper slot).
    let mut up_runs: Vec<[u32; 3]> = Vec::new();
    // The system is set up a segment at a time: a maximal run of active pixels along a row
    // (consecutive pixels, consecutive slots), whose links are arrays over it, so that the loops
    // are element-wise on contiguous slices and vectorise. `across[t]` joins its pixels t - 1 and
    // t (at both ends, to the fixed pixels beside it), `above` and `below` join each to the rows
    // above and below; 0 where there is no neighbour, which adds nothing to a sum.
    let (mut across, mut above, mut below) = (vec![0f32; w + 1], vec![0f32; w], vec![0f32; w]);
    let mut k = 1;
    while k <= m {
        let first = index[k - 1] as usize;
        let (y, c) = (first / w, first % w);
        let mut n = 1;
        while k + n <= m && index[k + n - 1] as usize == first + n && c + n < w {
            n += 1;
        }
        let (pixels, slots) = (first..first + n, k..k + n);
        let across = &mut across[..n + 1];
        across.fill(0.0);
        let (from, to) = (first - (c > 0) as usize, first + n - (c + n == w) as usize);
        link_affinities(&mut across[(c == 0) as usize..(to - from + (c == 0) as usize)], planes, sky, &factor, from, from + 1);
        let (above, below) = (&mut above[..n], &mut below[..n]);
        above.fill(0.0);
        below.fill(0.0);
        if y > 0 {
            link_affinities(above, planes, sky, &factor, first, first - w);
        }
        if y + 1 < h {
            link_affinities(below, planes, sky, &factor, first, first + w);
        }
        let (samples, start) = (&sparse[pixels.clone()], &x[pixels]);
        let (diag, rhs) = (&mut diag[slots.clone()], &mut rhs[slots.clone()]);
        u[slots.clone()].copy_from_slice(start);
        for t in 0..n {
            let z = samples[t];
            let held = if z > 0.0 && z.is_finite() { p.refine_weight } else { 0.0 };
            let d = held + across[t] + across[t + 1] + above[t] + below[t];
            diag[t] = if d > 0.0 { d } else { 1.0 };
            rhs[t] = if held > 0.0 { held / z } else { 0.0 };
        }
        // Fixed neighbours: a link's weight times their value goes to the right-hand side, in
        // the order left, right, up, down. Along the row only the segment's ends have them (it is
        // a maximal run of active pixels). A sky neighbour's weight is 0, but its value is not
        // read: 0 times a value that is not finite would be NaN.
        if c > 0 && sky[first - 1] == 0 {
            rhs[0] += across[0] * x[first - 1];
        }
        if c + n < w && sky[first + n] == 0 {
            rhs[n - 1] += across[n] * x[first + n];
        }
        if y > 0 {
            add_fixed(rhs, above, &at, sky, x, first - w);
        }
        if y + 1 < h {
            add_fixed(rhs, below, &at, sky, x, first + w);
        }
        left[k] = 0.0;
        left[k + 1..k + n].copy_from_slice(&across[1..n]);
        if y > 0 {
            let ats = &at[first - w..first - w + n];
            for (t, (o, &up_slot)) in up[slots].iter_mut().zip(ats).enumerate() {
                *o = if up_slot != OUT { above[t] } else { 0.0 };
                if up_slot != OUT {
                    let kt = (k + t) as u32;
                    match up_runs.last_mut() {
                        Some([first, n, above]) if *first + *n == kt && *above + *n == up_slot => *n += 1,
                        _ => up_runs.push([kt, 1, up_slot]),
                    }
                }
            }
        }
        k += n;
    }
    drop(at);
    // Conjugate gradients on the system scaled to a unit diagonal, S A S u' = S b with u = S u'
    // and S = diag^-1/2: the same iterates as the Jacobi-preconditioned system's, and no diagonal or
    // preconditioner to stream through every step. A link's weight in one direction is its
    // neighbour's in the other (the right link of a slot is the left one of the next slot, the
    // lower link the upper one of the slot below), so only two directions are stored. The loops
    // below are element-wise or sums in eight f32 lanes, so that they vectorise.
    let scale = map(&diag, |d| 1.0 / d.sqrt());
    drop(diag);
    // (0 where the neighbour is not active, whatever it is multiplied by.)
    for k in 1..=m {
        left[k] *= scale[k] * scale[k - 1];
    }
    for &[k, n, above] in &up_runs {
        let (k, n, above) = (k as usize, n as usize, above as usize);
        for t in 0..n {
            up[k + t] *= scale[k + t] * scale[above + t];
        }
    }
    for ((b, u), &s) in rhs.iter_mut().zip(u.iter_mut()).zip(&scale) {
        *b *= s;
        *u /= s;
    }
    let system = Stencil { up_runs: &up_runs, left: &left, up: &up };
    let mut r = vec![0f32; len];
    system.apply(&u, &mut r);
    for (r, &b) in r.iter_mut().zip(&rhs) {
        *r = b - *r;
    }
    r[0] = 0.0;
    r[m + 1] = 0.0;
    let mut rr = dot(&r, &r);
    let (mut dir, mut q) = (vec![0f32; len], vec![0f32; len]);
    let mut beta = 0f32;
    // A step's u += alpha dir is made in the next step's pass over dir, before dir is replaced
    // (one pass over dir fewer per step); `moved` is the alpha of the step not yet added to u.
    // After a break there is none: the direction made in the pass that broke may hold NaN or inf
    // (a subnormal sample's 1 / z), and 0 times it is NaN.
    let mut moved = None;
    for _ in 0..p.refine_iterations {
        // A cancellation point: the caller turns the stop into an error (see `dist4d_types::cancel`).
        if dist4d_types::cancel::requested() {
            break;
        }
        let pq = system.next_direction(&mut dir, &r, beta, &mut q, (&mut u, moved.unwrap_or(0.0)));
        moved = None;
        if !(pq > 0.0) || rr <= 0.0 {
            break;
        }
        let alpha = (rr / pq) as f32;
        let next = cg_residual(&mut r, &q, alpha);
        moved = Some(alpha);
        beta = (next / rr) as f32;
        rr = next;
    }
    if let Some(alpha) = moved {
        for (u, &d) in u.iter_mut().zip(&dir) {
            *u += alpha * d;
        }
    }
    for (k0, &i) in index.iter().enumerate() {
        x[i as usize] = u[k0 + 1] * scale[k0 + 1];
    }
}

/// The refinement's weights of the links from the pixels `from..from + out.len()` to the pixels
/// `to..` (`planes`: red, green, blue planes of one image): the product of `factor` of each
/// plane's difference, + 1e-4; 0 where either pixel is sky (a link's weight does not depend on its
/// direction). A function inlined into the completion, not a closure: a closure was compiled
/// apart, for the portable build only, and ran without AVX-512 inside its build.
#[inline(always)]
fn link_affinities(out: &mut [f32], planes: &[u8], sky: &[u8], factor: &[f32; 256], from: usize, to: usize) {
    let (n, len) = (sky.len(), out.len());
    let plane = |c: usize, at: usize| &planes[c * n + at..c * n + at + len];
    let (r, g, b, s) = (plane(0, from), plane(1, from), plane(2, from), &sky[from..from + len]);
    let (r1, g1, b1, s1) = (plane(0, to), plane(1, to), plane(2, to), &sky[to..to + len]);
    for (t, o) in out.iter_mut().enumerate() {
        let a = factor[r[t].abs_diff(r1[t]) as usize] * factor[g[t].abs_diff(g1[t]) as usize] * factor[b[t].abs_diff(b1[t]) as usize]
            + 1e-4;
        *o = if (s[t] | s1[t]) != 0 { 0.0 } else { a };
    }
}

/// Adds to `rhs` each link's weight (`weights`) times the value in `x` of its neighbour, the pixels
/// `neighbours..neighbours + rhs.len()`, where that neighbour is fixed: outside the refinement's
/// band (`at` 0) and not sky. (Inlined, as `link_affinities`.)
#[inline(always)]
fn add_fixed(rhs: &mut [f32], weights: &[f32], at: &[u32], sky: &[u8], x: &[f32], neighbours: usize) {
    let n = rhs.len();
    let (ats, skies, values) = (&at[neighbours..neighbours + n], &sky[neighbours..neighbours + n], &x[neighbours..neighbours + n]);
    for t in 0..n {
        let fixed = (ats[t] == 0) & (skies[t] == 0);
        rhs[t] += if fixed { weights[t] * values[t] } else { 0.0 };
    }
}

/// The refinement's matrix scaled to a unit diagonal, by link direction (see `refine`).
struct Stencil<'a> {
    /// (first slot, length, first upper slot) of the runs of slots with active upper neighbours.
    up_runs: &'a [[u32; 3]],
    /// Scaled weight of each slot's link to its left neighbour, 0 where that one is not active.
    left: &'a [f32],
    /// Scaled weight of each slot's link to its upper neighbour, 0 where that one is not active.
    up: &'a [f32],
}

impl Stencil<'_> {
    /// out = A v over the active slots (the pads stay 0): the links along rows over all slots at
    /// once, then each vertical link, to both of its slots, a run at a time.
    #[inline(always)]
    fn apply(&self, v: &[f32], out: &mut [f32]) {
        self.along_rows(v, out, 1..out.len() - 1);
        for &run in self.up_runs {
            self.vertical(run, v, out);
        }
    }

    /// out = v - the links along rows times v, over the slots `slots` (a slot's right link is the
    /// next slot's left one, 0 where they are not neighbours).
    #[inline(always)]
    fn along_rows(&self, v: &[f32], out: &mut [f32], slots: std::ops::Range<usize>) {
        let (start, end) = (slots.start, slots.end);
        let (centre, east, west) = (&v[start..end], &v[start + 1..end + 1], &v[start - 1..end - 1]);
        let (wl, wr) = (&self.left[start..end], &self.left[start + 1..end + 1]);
        for (t, o) in out[slots].iter_mut().enumerate() {
            *o = centre[t] - wl[t] * west[t] - wr[t] * east[t];
        }
    }

    /// Takes one run's vertical links times v off both of their slots.
    #[inline(always)]
    fn vertical(&self, [k, n, above]: [u32; 3], v: &[f32], out: &mut [f32]) {
        let (k, n, above) = (k as usize, n as usize, above as usize);
        let (links, here, up) = (&self.up[k..k + n], &v[k..k + n], &v[above..above + n]);
        for (t, o) in out[k..k + n].iter_mut().enumerate() {
            *o -= links[t] * up[t];
        }
        for (t, o) in out[above..above + n].iter_mut().enumerate() {
            *o -= links[t] * here[t];
        }
    }

    /// A step's first pass over the slots, a block at a time so that each block is worked on
    /// while it is in cache: the last step's move u += alpha dir (`moved`: (u, alpha)), the search
    /// direction dir = r + beta dir, q = A dir (as `apply`), and returns dir . q, summed by
    /// `BlockSum` where q is final: a run of vertical links writes to its own slots and to the row
    /// above's, so q is final before the next run's upper slots (at lower slot numbers: rows above
    /// in the image).
    #[inline(always)]
    fn next_direction(&self, dir: &mut [f32], r: &[f32], beta: f32, q: &mut [f32], moved: (&mut [f32], f32)) -> f64 {
        let (u, alpha) = moved;
        const BLOCK: usize = 2048;
        let m = q.len() - 2;
        let (mut run, mut updated, mut sum) = (0, 1, BlockSum::default());
        let mut start = 1;
        while start <= m {
            let end = (start + BLOCK).min(m + 1);
            // The direction one slot ahead of the block, its east neighbour.
            let ahead = (end + 1).min(m + 1);
            for ((d, u), &r) in dir[updated..ahead].iter_mut().zip(&mut u[updated..ahead]).zip(&r[updated..ahead]) {
                *u += alpha * *d;
                *d = r + beta * *d;
            }
            updated = ahead;
            self.along_rows(dir, q, start..end);
            while let Some(&[k, n, above]) = self.up_runs.get(run) {
                if (k + n) as usize > end {
                    break;
                }
                self.vertical([k, n, above], dir, q);
                run += 1;
            }
            let done = match self.up_runs.get(run) {
                _ if end == m + 1 => q.len(),
                Some(&[_, _, above]) => (above as usize).min(end) / 8 * 8,
                None => end / 8 * 8,
            };
            sum.add(dir, q, done);
            start = end;
        }
        sum.total
    }
}

/// A conjugate-gradient step's residual update r -= alpha q, returning the new r . r (summed as
/// `dot` sums), in one pass over r.
#[inline(always)]
fn cg_residual(r: &mut [f32], q: &[f32], alpha: f32) -> f64 {
    const BLOCK: usize = 4096;
    let mut total = 0f64;
    for (r, q) in r.chunks_mut(BLOCK).zip(q.chunks(BLOCK)) {
        let mut lanes = [0f32; 8];
        let mut tail = 0f32;
        let (mut rc, mut qc) = (r.chunks_exact_mut(8), q.chunks_exact(8));
        for (r, q) in (&mut rc).zip(&mut qc) {
            for l in 0..8 {
                r[l] -= alpha * q[l];
                lanes[l] += r[l] * r[l];
            }
        }
        for (r, &q) in rc.into_remainder().iter_mut().zip(qc.remainder()) {
            *r -= alpha * q;
            tail += *r * *r;
        }
        total += lanes.iter().map(|&l| l as f64).sum::<f64>() + tail as f64;
    }
    total
}

/// sum a_k b_k, in eight f32 lanes per block of 4096, blocks summed in f64: it vectorises, and no
/// lane sums more than 512 terms.
#[inline(always)]
fn dot(a: &[f32], b: &[f32]) -> f64 {
    let mut sum = BlockSum::default();
    sum.add(a, b, a.len());
    sum.total
}

/// `dot` taken a stretch at a time, in order: each lane and block sums the same terms in the
/// same order as over the whole, so the total is the same to the bit (stretches end on
/// multiples of 8, but the last).
#[derive(Default)]
struct BlockSum {
    lanes: [f32; 8],
    total: f64,
    /// The next index to add.
    next: usize,
}

impl BlockSum {
    /// Adds a_k b_k over `self.next..to` (a multiple of 8, or the slices' end).
    #[inline(always)]
    fn add(&mut self, a: &[f32], b: &[f32], to: usize) {
        debug_assert!(to.is_multiple_of(8) || to == a.len(), "a stretch ends on a multiple of 8 or at the end");
        const BLOCK: usize = 4096;
        while self.next < to {
            let block_end = (self.next / BLOCK + 1) * BLOCK;
            let end = to.min(block_end);
            let whole = self.next + (end - self.next) / 8 * 8;
            let (ca, cb) = (a[self.next..whole].chunks_exact(8), b[self.next..whole].chunks_exact(8));
            for (x, y) in ca.zip(cb) {
                for l in 0..8 {
                    self.lanes[l] += x[l] * y[l];
                }
            }
            // What is left of the last block, summed on its own.
            let tail = a[whole..end].iter().zip(&b[whole..end]).map(|(x, y)| x * y).sum::<f32>();
            if end == block_end || end == a.len() {
                self.total += self.lanes.iter().map(|&l| l as f64).sum::<f64>() + tail as f64;
                self.lanes = [0.0; 8];
            }
            self.next = end;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::super::{kernels::colour_planes, tests::grey};
    use super::*;

    #[test]
    fn the_fused_cg_pass_gives_the_move_direction_product_and_sum_to_the_bit() {
        // 9 000 slots (blocks of 2 048 from slot 1), rows of 300 slots. Vertical runs: short
        // random ones, one across the first block boundary, and one longer than a block and than
        // a row (a band over whole rows: it overlaps its own upper slots); none in the last third,
        // where the product is final at each block's end.
        let mut rng = dist4d_types::rng::Rng::new(5);
        let (m, row) = (9_000usize, 300usize);
        let len = m + 2;
        let mut left: Vec<f32> = (0..len).map(|k| if k > 1 && k <= m && k % row != 1 { rng.range(0.0, 0.25) as f32 } else { 0.0 }).collect();
        left[0] = 0.0;
        let mut starts = Vec::new();
        let mut k = row + 1;
        while k + 40 <= 2_000 {
            let n = 1 + rng.below(40) as usize;
            starts.push((k, n));
            k += n + rng.below(20) as usize;
        }
        starts.extend([(2_040, 20), (2_100, 30), (4_000, 2_500)]);
        let mut up = vec![0f32; len];
        let mut up_runs = Vec::new();
        for (k, n) in starts {
            up_runs.push([k as u32, n as u32, (k - row) as u32]);
            for t in 0..n {
                up[k + t] = rng.range(0.0, 0.25) as f32;
            }
        }
        let system = Stencil { up_runs: &up_runs, left: &left, up: &up };
        let vector = |rng: &mut dist4d_types::rng::Rng| -> Vec<f32> {
            (0..len).map(|k| if k == 0 || k == m + 1 { 0.0 } else { rng.range(-1.0, 1.0) as f32 }).collect()
        };
        let (r, old) = (vector(&mut rng), vector(&mut rng));
        let beta = 0.37f32;
        let mut dir = old.clone();
        let mut q = vec![0f32; len];
        // The previous step's move along the old direction is made in the same pass.
        let (solution, alpha) = (vector(&mut rng), -0.61f32);
        let mut u = solution.clone();
        let pq = system.next_direction(&mut dir, &r, beta, &mut q, (&mut u, alpha));
        let moved: Vec<f32> = solution.iter().zip(&old).map(|(&u, &d)| u + alpha * d).collect();
        assert_eq!(u[1..=m], moved[1..=m]);
        let expected: Vec<f32> = r.iter().zip(&old).map(|(&r, &d)| r + beta * d).collect();
        let mut product = vec![0f32; len];
        system.apply(&expected, &mut product);
        assert_eq!(dir, expected);
        assert_eq!(q, product);
        assert_eq!(pq.to_bits(), dot(&expected, &product).to_bits());
        // And `dot` sums as the per-block dot product it replaced: eight f32 lanes over each
        // block of 4 096, the block's remainder on its own, blocks summed in f64.
        let mut blocks = 0f64;
        for (a, b) in expected.chunks(4096).zip(product.chunks(4096)) {
            let mut lanes = [0f32; 8];
            let (ca, cb) = (a.chunks_exact(8), b.chunks_exact(8));
            let tail: f32 = ca.remainder().iter().zip(cb.remainder()).map(|(x, y)| x * y).sum();
            for (x, y) in ca.zip(cb) {
                for l in 0..8 {
                    lanes[l] += x[l] * y[l];
                }
            }
            blocks += lanes.iter().map(|&l| l as f64).sum::<f64>() + tail as f64;
        }
        assert_eq!(dot(&expected, &product).to_bits(), blocks.to_bits());
    }

    #[test]
    fn refinement_moves_a_misplaced_depth_edge_onto_the_colour_edge() {
        // Columns 0..20 are dark (a pole 10 m away), 20..40 bright (a wall 20 m away); samples
        // every 6 px. The filled map starts with the edge 3 px too far left (columns 17..20 at
        // the wall's depth, as a grown band or a blurred fill leaves it).
        let (w, h) = (40usize, 30usize);
        let image = grey(w as u32, h as u32, |x, _| if x < 20 { [40, 40, 40] } else { [200, 190, 180] });
        let depth = |x: usize| if x < 20 { 10.0f32 } else { 20.0 };
        let mut sparse = vec![0f32; w * h];
        for y in (1..h).step_by(6) {
            for x in (1..w).step_by(6) {
                sparse[y * w + x] = depth(x);
            }
        }
        let start: Vec<f32> = (0..w * h).map(|i| 1.0 / if i % w < 17 { 10.0 } else { 20.0 }).collect();
        let mut inv = start.clone();
        let planes = colour_planes(&image.rgb);
        refine(&Params::default(), &mut inv, &planes, &sparse, &vec![0; w * h], w, h);
        for y in 0..h {
            for x in 15..25 {
                let z = 1.0 / inv[y * w + x];
                assert!((z - depth(x)).abs() < 0.05 * depth(x), "({x}, {y}): {z}");
            }
        }
        // Without iterations nothing moves.
        let mut same = start.clone();
        refine(
            &Params { refine_iterations: 0, ..Params::default() },
            &mut same,
            &planes,
            &sparse,
            &vec![0; w * h],
            w,
            h,
        );
        assert_eq!(same, start);
    }

    #[test]
    fn a_refinement_that_stops_at_once_leaves_its_band_as_it_was() {
        // One sample of a subnormal depth: its inverse depth is +inf, the residuals beside it
        // NaN, and the first step stops the refinement. The map stays as filled (a pending move
        // made after the stop, 0 times a direction holding NaN, made its neighbours NaN).
        let (w, h) = (40usize, 30usize);
        let image = grey(w as u32, h as u32, |x, _| if x < 20 { [40, 40, 40] } else { [200, 190, 180] });
        let mut sparse = vec![0f32; w * h];
        for y in (1..h).step_by(6) {
            for x in (1..w).step_by(6) {
                sparse[y * w + x] = if x < 20 { 10.0 } else { 20.0 };
            }
        }
        let odd = 13 * w + 19;
        sparse[odd] = 1e-42;
        let mut start: Vec<f32> = (0..w * h).map(|i| 1.0 / if i % w < 17 { 10.0 } else { 20.0 }).collect();
        start[odd] = 1.0 / sparse[odd];
        assert_eq!(start[odd], f32::INFINITY);
        let mut inv = start.clone();
        refine(&Params::default(), &mut inv, &colour_planes(&image.rgb), &sparse, &vec![0; w * h], w, h);
        // (To the rounding of the system's scaling, x / s * s.)
        for (i, (&v, &s)) in inv.iter().zip(&start).enumerate() {
            assert!((v - s).abs() <= 1e-6 * s || (i == odd && !v.is_finite()), "pixel {i}: {s} became {v}");
        }
    }
}
