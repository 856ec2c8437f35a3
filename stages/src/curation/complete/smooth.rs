//! The 2D fill (`smooth_unsupported`): pixels far from every sample take the edge-aware average
//! of the measured depths around them (a domain-transform filter over 2x2 blocks, spread back to
//! the pixels by colour likeness), corrected towards their column's continuation where the two
//! agree.

use super::fill::{CONTINUED, GROUND};
use super::Params;

/// Pixels farther than `smooth_from` px from every sample got their inverse depth from one
/// column (its highest sample continued up, or a long gap split at an edge), so neighbouring
/// columns disagree (vertical streaks), and a facade above a tree crown took the crown's depth.
/// They take instead the edge-aware average of the pixels within `smooth_from` of a sample,
/// spread in two dimensions: normalised convolution with the recursive filter of the domain
/// transform (Gastal and Oliveira 2011, section 4 and its iterations: rows then columns,
/// `smooth_iterations` times, the i-th with a spatial sigma falling as in their eq. 14). Weights
/// fall by exp(-sqrt 2 / sigma_i) per pixel and faster across colour steps (a step of
/// `smooth_edge` in the summed RGB difference of colours averaged over `smooth_texture` blocks
/// counts as `smooth_sigma` pixels, so that texture is not taken for edges); sky pixels
/// neither give nor pass on depth. Only measured depths are spread (and the ground below a
/// column's lowest sample, exact on flat ground), so the facade seen around a crown reaches the
/// pixels above it while the crown's green stops it. But an average cannot extrapolate: a
/// receding facade above its samples is too near at one end and too far at the other, where its
/// column's continuation is exact. So the result is the average plus the continuation's
/// correction, weighted by how well the two agree (`keep_planes`; split gaps get none) and
/// averaged along the row (so that noisy top samples do not make streaks again).
#[inline(always)]
pub(super) fn smooth_unsupported(p: &Params, inv: &mut [f32], planes: &[u8], near: &[u8], continued: &[u8], sky: &[u8], w: usize, h: usize) {
    if p.smooth_sigma <= 0.0 || p.smooth_iterations == 0 || w < 2 || h < 2 {
        return;
    }
    // Nothing to replace: every pixel is a source or sky.
    if !inv.iter().zip(near).zip(sky.iter().zip(continued)).any(|((&v, &d), (&s, &c))| !is_source(v, d, s, c) & (s == 0)) {
        return;
    }
    // The average reaches tens of px and changes slowly, so it is taken over 2x2 blocks (a quarter
    // of the pixels, the filter's passes being most of its time), then brought back to each pixel
    // from the blocks around it, weighed by colour likeness so that it does not cross the edges the
    // blocks blur.
    let ratio = p.smooth_sigma / p.smooth_edge.max(1e-3);
    let mut blocks = Blocks::of(inv, near, continued, planes, sky, w, h);
    // A block is 2 px, so the spatial sigma halves in its units. The colour ratio is kept, which
    // makes each colour step cut twice as hard as at full resolution: the units alone would halve
    // it too, and that measured worse (2.00% of seed 0's 8 keyframes off by more than 10% against
    // 1.95%, with the blocks' own colours).
    // The links compare texture-evened colours (`smooth_texture`): a 2x2 block's mean keeps most
    // of a facade's or a crown's texture, whose steps added up along every path. On seed 0's 40
    // keyframes this took the pixels off by more than 10% from 1.74% to 1.48% (docs/BENCHMARKS.md,
    // "Curation accuracy on synthetic scenes"). The spread back to the pixels keeps the blocks' own
    // colours.
    // (An `if`, not `then(|| ...)`: a closure is compiled apart, without this build's instructions.)
    let evened;
    let link_planes = if p.smooth_texture > 0 {
        evened = box_mean(&blocks.planes, blocks.w, blocks.h, p.smooth_texture as usize);
        &evened
    } else {
        &blocks.planes
    };
    domain_filter(p, &mut blocks.num, &mut blocks.den, link_planes, &blocks.sky, blocks.w, blocks.h, p.smooth_sigma / 2.0, ratio);
    let like = likeness(p, p.smooth_sigma / p.spread_edge.max(1e-3));
    let mut spread = Spread::new(w);
    let keep = p.keep_planes;
    // A pixel takes the average plus the continuation's correction to it (0 where not trusted)
    // averaged over the replaced pixels within this many px along its row: a receding facade's
    // correction changes smoothly along the row and survives; noisy top samples would give each
    // column its own correction, vertical streaks again, and average out (4 / 8 / 16 px: 2.11 /
    // 2.11 / 2.12% of seed 0's 8 keyframes off by more than 10%).
    const RADIUS: usize = 8;
    // Per row: what each pixel becomes and its correction, then the correction's mean over the
    // window from running sums. The sums run in registers: read back from the previous entry,
    // each addition waited on a store (3.9 ms of the completion's then ~58, now 0.7).
    let mut correction = vec![0f32; w];
    let mut replaced = vec![0f32; w];
    // Running sums of the correction and of the replaced pixels, 0 before the row's first.
    let (mut correction_sums, mut replaced_sums) = (vec![0f32; w + 1], vec![0f32; w + 1]);
    for y in 0..h {
        spread.row(&blocks, y, planes, w, h, &like);
        let row = y * w..(y + 1) * w;
        let (inv, num, den, near) = (&mut inv[row.clone()], &spread.num[..], &spread.den[..], &near[row.clone()]);
        let (sky, continued) = (&sky[row.clone()], &continued[row]);
        for x in 0..w {
            let (v, s, c) = (inv[x], sky[x], continued[x]);
            let replace = !is_source(v, near[x], s, c) & (s == 0) & (den[x] > 1e-8);
            let smooth = num[x] / den[x].max(1e-8);
            // NaN (no average, keep = 0) falls to 0 in `max`.
            let trust = (1.0 - (v - smooth).abs() / (keep * smooth)).max(0.0);
            let trusted = replace & (c == CONTINUED) & (v > 0.0) & (keep > 0.0);
            correction[x] = if trusted { trust * (v - smooth) } else { 0.0 };
            replaced[x] = replace as u8 as f32;
            inv[x] = if replace { smooth } else { v };
        }
        let (mut sum, mut n) = (0f32, 0f32);
        for ((s, k), (&c, &r)) in correction_sums[1..].iter_mut().zip(&mut replaced_sums[1..]).zip(correction.iter().zip(&replaced)) {
            sum += c;
            n += r;
            (*s, *k) = (sum, n);
        }
        let (sums, counts) = (&correction_sums[..], &replaced_sums[..]);
        // The pixels whose window lies inside the row, `inner`, as slices offset by the window
        // (a loop that vectorises; with the window's ends clipped for every pixel it did not);
        // the few at the row's ends with their windows clipped.
        let inner = if w > 2 * RADIUS { RADIUS..w - RADIUS } else { 0..0 };
        if !inner.is_empty() {
            let (lo, hi) = (inner.start - RADIUS..inner.end - RADIUS, inner.start + RADIUS + 1..inner.end + RADIUS + 1);
            let (sums_lo, sums_hi, counts_lo, counts_hi) = (&sums[lo.clone()], &sums[hi.clone()], &counts[lo], &counts[hi]);
            for (t, (v, &r)) in inv[inner.clone()].iter_mut().zip(&replaced[inner.clone()]).enumerate() {
                *v += r * ((sums_hi[t] - sums_lo[t]) / (counts_hi[t] - counts_lo[t]).max(1.0));
            }
        }
        for x in (0..inner.start).chain(inner.end..w) {
            let (lo, hi) = (x.saturating_sub(RADIUS), (x + RADIUS + 1).min(w));
            inv[x] += replaced[x] * ((sums[hi] - sums[lo]) / (counts[hi] - counts[lo]).max(1.0));
        }
    }
}

/// Each of the three `w` x `h` planes of `planes` averaged over the square of radius `r` around
/// each cell (cut at the borders), rounded to the nearest (as f32: sum x (1 / cells) + 0.5,
/// truncated; every build rounds it alike). Separable integer sums: a running sum down the
/// columns (a row added, a row taken off), then along each row the sum of the 2r + 1 shifted
/// copies of it; every loop is element-wise and vectorises.
#[inline(always)]
fn box_mean(planes: &[u8], w: usize, h: usize, r: usize) -> Vec<u8> {
    let n = w * h;
    if r == 0 || n == 0 {
        return planes.to_vec();
    }
    let mut out = vec![0u8; 3 * n];
    let (mut column, mut sum) = (vec![0u32; w], vec![0u32; w]);
    for (plane, out) in planes.chunks_exact(n).zip(out.chunks_exact_mut(n)) {
        column.fill(0);
        for row in plane[..(r + 1).min(h) * w].chunks_exact(w) {
            add_row(&mut column, row);
        }
        for y in 0..h {
            // `column` holds rows y - r ..= y + r (cut at the borders).
            sum.copy_from_slice(&column);
            for d in 1..=r.min(w - 1) {
                for (s, &c) in sum[..w - d].iter_mut().zip(&column[d..]) {
                    *s += c;
                }
                for (s, &c) in sum[d..].iter_mut().zip(&column[..w - d]) {
                    *s += c;
                }
            }
            let rows = ((y + r + 1).min(h) - y.saturating_sub(r)) as f32;
            let out = &mut out[y * w..(y + 1) * w];
            let inner = if w > 2 * r { r..w - r } else { 0..0 };
            let whole = 1.0 / (rows * (2 * r + 1) as f32);
            for (o, &s) in out[inner.clone()].iter_mut().zip(&sum[inner.clone()]) {
                *o = (s as f32 * whole + 0.5) as u8;
            }
            for x in (0..inner.start).chain(inner.end..w) {
                let cells = rows * ((x + r + 1).min(w) - x.saturating_sub(r)) as f32;
                out[x] = (sum[x] as f32 * (1.0 / cells) + 0.5) as u8;
            }
            if y + r + 1 < h {
                add_row(&mut column, &plane[(y + r + 1) * w..(y + r + 2) * w]);
            }
            if y >= r {
                for (c, &v) in column.iter_mut().zip(&plane[(y - r) * w..(y - r + 1) * w]) {
                    *c -= v as u32;
                }
            }
        }
    }
    out
}

#[inline(always)]
fn add_row(sums: &mut [u32], row: &[u8]) {
    for (s, &v) in sums.iter_mut().zip(row) {
        *s += v as u32;
    }
}

/// The 2D fill's sources: pixels beside a sample (within `smooth_from`), or on the ground below a
/// column's lowest one (inverse depth, near a sample, sky, how it was filled); not sky.
#[inline(always)]
fn is_source(v: f32, near: u8, sky: u8, continued: u8) -> bool {
    ((near != 0) | (continued == GROUND)) & (sky == 0) & (v > 0.0)
}

/// The 2D fill's filter over (`num`, `den`) on a `w` x `h` grid whose colours are `planes` and sky
/// `sky`: `smooth_iterations` passes along rows and then columns, the first with spatial sigma
/// derived from `sigma_s` (px of this grid), a colour step of s counting as `ratio` s px.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn domain_filter(p: &Params, num: &mut [f32], den: &mut [f32], planes: &[u8], sky: &[u8], w: usize, h: usize, sigma_s: f32, ratio: f32) {
    let n = w * h;
    let iterations = p.smooth_iterations as i32;
    // The i-th iteration's spatial sigma (Gastal and Oliveira's eq. 14) halves from one iteration
    // to the next, so its link weights exp(-(sqrt 2 / sigma_i) (1 + ratio step)) are the previous
    // iteration's squared: the weights are looked up once, for the first iteration, and squared
    // in place after each use.
    let sigma = first_sigma(sigma_s, iterations);
    // Colour steps (summed RGB difference, 0-765) -> weight; the last entry, 0, is a link that
    // sky or the border cuts, so the passes below need no branch.
    let mut weight = [0f32; CUT + 1];
    for (s, c) in weight.iter_mut().enumerate().take(CUT) {
        *c = (-(2f32.sqrt() / sigma) * (1.0 + ratio * s as f32)).exp();
    }
    // Link weights to the left and to the upper neighbour.
    let mut left = vec![0f32; n];
    let mut up = vec![0f32; n];
    for y in 0..h {
        link_weights(&mut left[y * w + 1..(y + 1) * w], planes, sky, &weight, y * w + 1, 1);
        if y > 0 {
            link_weights(&mut up[y * w..(y + 1) * w], planes, sky, &weight, y * w, w);
        }
    }
    for k in 0..iterations {
        let last = k + 1 == iterations;
        // Along rows: causal, then anti-causal over the causal result. Each row is a chain of
        // dependent multiply-adds; four rows at a time, their running values in registers, keep
        // the core busy while one waits.
        for ((nums, dens), links) in num.chunks_mut(4 * w).zip(den.chunks_mut(4 * w)).zip(left.chunks_mut(4 * w)) {
            if nums.len() == 4 * w {
                filter_rows::<4>(nums, dens, links, w);
            } else {
                for ((nums, dens), links) in nums.chunks_mut(w).zip(dens.chunks_mut(w)).zip(links.chunks(w)) {
                    filter_rows::<1>(nums, dens, links, w);
                }
            }
            if !last {
                square(links);
            }
        }
        // Along columns, a whole row at a time (rows are contiguous, columns are not).
        for y in 1..h {
            let (nd, nr) = num.split_at_mut(y * w);
            let (dd, dr) = den.split_at_mut(y * w);
            let (np, dp) = (&nd[(y - 1) * w..], &dd[(y - 1) * w..]);
            let links = &up[y * w..(y + 1) * w];
            for x in 0..w {
                nr[x] += links[x] * np[x];
                dr[x] += links[x] * dp[x];
            }
        }
        for y in (0..h - 1).rev() {
            let (nh, nb) = num.split_at_mut((y + 1) * w);
            let (dh, db) = den.split_at_mut((y + 1) * w);
            let (nr, dr) = (&mut nh[y * w..], &mut dh[y * w..]);
            let links = &mut up[(y + 1) * w..(y + 2) * w];
            for x in 0..w {
                nr[x] += links[x] * nb[x];
                dr[x] += links[x] * db[x];
            }
            if !last {
                square(links);
            }
        }
    }
}

/// The spatial sigma of the first of `iterations` passes of a domain transform of sigma `sigma_s`
/// (Gastal and Oliveira's eq. 14; each later one is half the one before).
fn first_sigma(sigma_s: f32, iterations: i32) -> f32 {
    sigma_s * 3f32.sqrt() * 2f32.powi(iterations - 1) / (4f32.powi(iterations) - 1.0).sqrt()
}

/// How much a pixel takes of a block's average by their summed RGB difference (0-765; the pixel's
/// own colour against the block's own mean, not the texture-evened one, with `ratio` from
/// `spread_edge`): the full-resolution filter's first link weight, with the colour counting twice
/// as much (a pixel beside an edge, weighed against a block across it, should take nearly nothing;
/// once as much measured 1.96% of seed 0's 8 keyframes off by more than 10% against 1.95%). A pixel unlike
/// all four of its blocks (a 1 px pole or wire, which the blocks' means average away; a summed
/// difference over ~300) gets weights below the replacement's threshold and keeps its column's
/// value, which its own samples gave. Giving it the blocks' plain average instead (a floor of 1e-6
/// on the likeness) measured the same on the real hold-outs and 2.64 against 2.62 px boundary
/// accuracy on seed 0's 8 keyframes.
fn likeness(p: &Params, ratio: f32) -> [f32; CUT] {
    let sigma = first_sigma(p.smooth_sigma, p.smooth_iterations as i32);
    let mut like = [0f32; CUT];
    for (s, c) in like.iter_mut().enumerate() {
        *c = (-(2f32.sqrt() / sigma) * (1.0 + 2.0 * ratio * s as f32)).exp();
    }
    like
}

/// The 2D fill's grid: blocks of 2x2 pixels (fewer at an odd image's last row or column).
struct Blocks {
    w: usize,
    h: usize,
    /// Sums of the pixels' (num, den).
    num: Vec<f32>,
    den: Vec<f32>,
    /// Mean colours (red, green, blue planes, rounded).
    planes: Vec<u8>,
    /// 1 where every pixel of the block is sky.
    sky: Vec<u8>,
}

impl Blocks {
    /// The blocks of the filter's input: (inverse depth, 1) at sources, (0, 0) elsewhere.
    #[inline(always)]
    fn of(inv: &[f32], near: &[u8], continued: &[u8], planes: &[u8], sky: &[u8], w: usize, h: usize) -> Blocks {
        let (bw, bh) = (w.div_ceil(2), h.div_ceil(2));
        let (n, nb) = (w * h, bw * bh);
        let mut b = Blocks { w: bw, h: bh, num: vec![0f32; nb], den: vec![0f32; nb], planes: vec![0u8; 3 * nb], sky: vec![0u8; nb] };
        let pairs = w / 2;
        // A row's (num, den) of the filter's input.
        let (mut num, mut den) = ([vec![0f32; w], vec![0f32; w]], [vec![0f32; w], vec![0f32; w]]);
        for by in 0..bh {
            // The block's rows; an odd image's last block row has one, counted once.
            let (ya, yb) = (2 * by, (2 * by + 1).min(h - 1));
            let second = (yb != ya) as u8;
            let (rows, pixels) = (1 + second as u16, (1 + second as u16) * 2);
            let at = |y: usize| y * w..(y + 1) * w;
            let out = by * bw..(by + 1) * bw;
            // Sums of the two rows' pixel pairs (the second row weighed 0 when it is the first).
            for (k, y) in [ya, yb].into_iter().enumerate() {
                let row = at(y);
                let (v, d, s, c) = (&inv[row.clone()], &near[row.clone()], &sky[row.clone()], &continued[row]);
                for (x, (nu, de)) in num[k].iter_mut().zip(den[k].iter_mut()).enumerate() {
                    let source = is_source(v[x], d[x], s[x], c[x]) as u8 as f32;
                    *nu = v[x] * source;
                    *de = source;
                }
            }
            pair_sums(&mut b.num[out.clone()], &num, second);
            pair_sums(&mut b.den[out.clone()], &den, second);
            for c in 0..3 {
                let plane = &planes[c * n..(c + 1) * n];
                let (a, d) = (&plane[at(ya)], &plane[at(yb)]);
                let o = &mut b.planes[c * nb + out.start..c * nb + out.end];
                let s = second as u16;
                for (o, (p, q)) in o[..pairs].iter_mut().zip(a.chunks_exact(2).zip(d.chunks_exact(2))) {
                    let sum = p[0] as u16 + p[1] as u16 + s * (q[0] as u16 + q[1] as u16);
                    *o = ((sum + pixels / 2) / pixels) as u8;
                }
                if w % 2 == 1 {
                    o[pairs] = ((a[w - 1] as u16 + s * d[w - 1] as u16 + rows / 2) / rows) as u8;
                }
            }
            let (a, d) = (&sky[at(ya)], &sky[at(yb)]);
            let o = &mut b.sky[out];
            for (o, (p, q)) in o[..pairs].iter_mut().zip(a.chunks_exact(2).zip(d.chunks_exact(2))) {
                *o = ((p[0] != 0) & (p[1] != 0) & (q[0] != 0) & (q[1] != 0)) as u8;
            }
            if w % 2 == 1 {
                o[pairs] = ((a[w - 1] != 0) & (d[w - 1] != 0)) as u8;
            }
        }
        b
    }
}

/// Sums of the pixel pairs of two rows `v` into `out` (an odd row's last pixel alone), the second
/// row weighed 0 when `second` is 0 (an odd image's last block row is its first row counted once).
/// A function inlined into the completion: a closure was compiled apart, for the portable build.
#[inline(always)]
fn pair_sums(out: &mut [f32], v: &[Vec<f32>; 2], second: u8) {
    let (a, c) = (&v[0][..], &v[1][..]);
    let (w, pairs) = (a.len(), a.len() / 2);
    let f = second as f32;
    for (o, (p, q)) in out[..pairs].iter_mut().zip(a.chunks_exact(2).zip(c.chunks_exact(2))) {
        *o = (p[0] + p[1]) + f * (q[0] + q[1]);
    }
    if w % 2 == 1 {
        out[pairs] = a[w - 1] + f * c[w - 1];
    }
}

/// The filtered blocks brought back to a row of pixels at a time: each pixel's (num, den) from
/// the four blocks nearest it, bilinear weights between the blocks' centres (a pixel is a quarter
/// of a block from the nearest centre: 3/4 and 1/4 each way) times the likeness of the pixel's
/// colour and each block's.
struct Spread {
    /// Block rows spread to the image's width: block row j in slot j % 2 (a pixel row uses block
    /// rows j and j + 1).
    slots: [WideRow; 2],
    held: [usize; 2],
    /// The row's (num, den).
    num: Vec<f32>,
    den: Vec<f32>,
}

impl Spread {
    fn new(w: usize) -> Spread {
        Spread { slots: [WideRow::new(w), WideRow::new(w)], held: [usize::MAX; 2], num: vec![0f32; w], den: vec![0f32; w] }
    }

    /// (num, den) of pixel row `y`.
    #[inline(always)]
    fn row(&mut self, blocks: &Blocks, y: usize, planes: &[u8], w: usize, h: usize, like: &[f32; CUT]) {
        let n = w * h;
        // The block rows above and below the pixels' centres, and the first one's weight.
        let (a, wa) = if y.is_multiple_of(2) { (y as isize / 2 - 1, 0.25f32) } else { (y as isize / 2, 0.75) };
        let last = blocks.h as isize - 1;
        let (a, b) = (a.clamp(0, last) as usize, (a + 1).clamp(0, last) as usize);
        for by in [a, b] {
            if self.held[by % 2] != by {
                self.slots[by % 2].fill(blocks, by);
                self.held[by % 2] = by;
            }
        }
        let (top, bottom) = (&self.slots[a % 2], &self.slots[b % 2]);
        let row = y * w..(y + 1) * w;
        let (r, g, bl) = (&planes[row.clone()], &planes[n + row.start..n + row.end], &planes[2 * n + row.start..2 * n + row.end]);
        // The four blocks' terms over slices of the row's length (no bounds checks and no
        // closure, so that the loop vectorises, the likeness lookups as gathers).
        let (r, g, bl) = (&r[..w], &g[..w], &bl[..w]);
        let ([tr0, tg0, tb0], [tr2, tg2, tb2]) = (top.colour.each_ref().map(|c| &c[..w]), top.colour.each_ref().map(|c| &c[2..w + 2]));
        let ([br0, bg0, bb0], [br2, bg2, bb2]) = (bottom.colour.each_ref().map(|c| &c[..w]), bottom.colour.each_ref().map(|c| &c[2..w + 2]));
        let (tn0, tn2, td0, td2) = (&top.num[..w], &top.num[2..w + 2], &top.den[..w], &top.den[2..w + 2]);
        let (bn0, bn2, bd0, bd2) = (&bottom.num[..w], &bottom.num[2..w + 2], &bottom.den[..w], &bottom.den[2..w + 2]);
        let (num, den) = (&mut self.num[..w], &mut self.den[..w]);
        for x in 0..w {
            // x even: its farther block column at x (1/4), the nearer at x + 2 (3/4); odd:
            // the other way round.
            let wx = 0.25 + 0.5 * (x & 1) as f32;
            let s_tl = r[x].abs_diff(tr0[x]) as usize + g[x].abs_diff(tg0[x]) as usize + bl[x].abs_diff(tb0[x]) as usize;
            let s_tr = r[x].abs_diff(tr2[x]) as usize + g[x].abs_diff(tg2[x]) as usize + bl[x].abs_diff(tb2[x]) as usize;
            let s_bl = r[x].abs_diff(br0[x]) as usize + g[x].abs_diff(bg0[x]) as usize + bl[x].abs_diff(bb0[x]) as usize;
            let s_br = r[x].abs_diff(br2[x]) as usize + g[x].abs_diff(bg2[x]) as usize + bl[x].abs_diff(bb2[x]) as usize;
            let tl = (wa * wx) * like[s_tl];
            let tr = (wa * (1.0 - wx)) * like[s_tr];
            let bo = ((1.0 - wa) * wx) * like[s_bl];
            let br = ((1.0 - wa) * (1.0 - wx)) * like[s_br];
            num[x] = ((tl * tn0[x] + tr * tn2[x]) + bo * bn0[x]) + br * bn2[x];
            den[x] = ((tl * td0[x] + tr * td2[x]) + bo * bd0[x]) + br * bd2[x];
        }
    }
}

/// A row of blocks spread to the image's width `w`, padded: block k at indices 2k + 1 and 2k + 2,
/// block 0 at index 0 too and the last block to the end; a pixel x's two nearest block columns are
/// then at x and x + 2.
struct WideRow {
    num: Vec<f32>,
    den: Vec<f32>,
    colour: [Vec<u8>; 3],
}

impl WideRow {
    fn new(w: usize) -> WideRow {
        WideRow { num: vec![0f32; w + 2], den: vec![0f32; w + 2], colour: std::array::from_fn(|_| vec![0u8; w + 2]) }
    }

    /// Block row `by` of `blocks`.
    #[inline(always)]
    fn fill(&mut self, blocks: &Blocks, by: usize) {
        let (bw, at) = (blocks.w, by * blocks.w);
        spread_pairs(&mut self.num, &blocks.num[at..at + bw]);
        spread_pairs(&mut self.den, &blocks.den[at..at + bw]);
        for (c, out) in self.colour.iter_mut().enumerate() {
            let plane = c * blocks.w * blocks.h + at;
            spread_pairs(out, &blocks.planes[plane..plane + bw]);
        }
    }
}

/// `out[0]` = v[0], v[k] at 2k + 1 and 2k + 2, the last of `v` to the end of `out`.
#[inline(always)]
fn spread_pairs<T: Copy>(out: &mut [T], v: &[T]) {
    out[0] = v[0];
    // Whole pairs written as two stores: `fill` on a chunk of unknown length called memset once
    // per pair (1% of the chain's CPU). An odd last slot is the end's, set below.
    for (o, &x) in out[1..].chunks_exact_mut(2).zip(v) {
        o[0] = x;
        o[1] = x;
    }
    let end = out.len() - 1;
    out[end] = v[v.len() - 1];
}

/// The weights of the links from the pixels `from..from + out.len()` to the pixels `back` before
/// them: `weight` of their summed RGB difference (`planes`: red, green, blue planes of one image),
/// 0 where either pixel is sky.
#[inline(always)]
fn link_weights(out: &mut [f32], planes: &[u8], sky: &[u8], weight: &[f32; CUT + 1], from: usize, back: usize) {
    let (n, len) = (sky.len(), out.len());
    let plane = |c: usize, from: usize| &planes[c * n + from..c * n + from + len];
    let (r, g, b, s) = (plane(0, from), plane(1, from), plane(2, from), &sky[from..from + len]);
    let at = from - back;
    let (r0, g0, b0, s0) = (plane(0, at), plane(1, at), plane(2, at), &sky[at..at + len]);
    for (i, o) in out.iter_mut().enumerate() {
        let d = r[i].abs_diff(r0[i]) as usize + g[i].abs_diff(g0[i]) as usize + b[i].abs_diff(b0[i]) as usize;
        // A select, not a branch, so that the loop vectorises (with AVX2, the lookup too).
        *o = weight[if (s[i] | s0[i]) != 0 { CUT } else { d }];
    }
}

/// The slot of a cut link (sky, or the image's border) in the 2D fill's weight table, after the
/// 766 colour steps (summed RGB differences 0-765).
const CUT: usize = 766;

/// Each weight squared, in place: the next iteration's (see `smooth_unsupported`).
#[inline(always)]
fn square(weights: &mut [f32]) {
    weights.iter_mut().for_each(|c| *c *= *c);
}

/// The recursive filter along `R` rows of `w` pixels (row-major in `nums`, `dens`, `links`): causal
/// (x_i += c_i x_{i-1}, c_i the link to the left), then anti-causal over its result (x_i += c_{i+1}
/// x_{i+1}). The `R` chains run side by side with their last values in registers: read back from
/// memory, each step would wait on the store before it.
#[inline(always)]
fn filter_rows<const R: usize>(nums: &mut [f32], dens: &mut [f32], links: &[f32], w: usize) {
    let (nums, dens, links) = (&mut nums[..R * w], &mut dens[..R * w], &links[..R * w]);
    let (mut n, mut d) = ([0f32; R], [0f32; R]);
    for r in 0..R {
        (n[r], d[r]) = (nums[r * w], dens[r * w]);
    }
    for x in 1..w {
        for r in 0..R {
            let (i, c) = (r * w + x, links[r * w + x]);
            n[r] = nums[i] + c * n[r];
            d[r] = dens[i] + c * d[r];
            nums[i] = n[r];
            dens[i] = d[r];
        }
    }
    for x in (0..w - 1).rev() {
        for r in 0..R {
            let (i, c) = (r * w + x, links[r * w + x + 1]);
            n[r] = nums[i] + c * n[r];
            d[r] = dens[i] + c * d[r];
            nums[i] = n[r];
            dens[i] = d[r];
        }
    }
}

#[cfg(test)]
mod tests {
    use super::super::{complete, tests::grey};
    use super::*;
    use dist4d_types::artifact::DepthMap;

    #[test]
    fn surfaces_continue_beyond_their_samples_where_the_average_agrees() {
        // A facade at a grazing angle (inverse depth linear along rows: 1/z = 0.05 + 0.0006 x,
        // 20 m to 10 m) over rows 0..70, sampled on rows 45..70 only; below it a road sampled
        // down to row 84 (inverse depth linear down the rows), its last rows unsampled. One
        // colour on each, so the 2D average of measured depths reaches the unsampled pixels
        // unhindered: it cannot extrapolate (its values lie between the samples'), the
        // continuation of the column can.
        let (w, h) = (80u32, 100u32);
        let truth = |x: usize, y: usize| {
            if y < 70 {
                1.0 / (0.05 + 0.0006 * x as f32)
            } else {
                1.0 / (0.05 + 0.01 * (y as f32 - 69.0))
            }
        };
        let mut sparse = DepthMap::new(w, h);
        for y in (45..85).step_by(3) {
            for x in (0..w as usize).step_by(2) {
                sparse.data[y * w as usize + x] = truth(x, y);
            }
        }
        let image = grey(w, h, |_, y| if y < 70 { [100, 100, 100] } else { [60, 60, 60] });
        // The mean and the worst relative error over `rows`.
        let error = |keep_planes: f32, rows: std::ops::Range<usize>| {
            let p = Params { keep_planes, refine_iterations: 0, ..Params::default() };
            let d = complete(&p, &image, &sparse, None, false).depth;
            let (mut sum, mut worst, mut n) = (0f32, 0f32, 0);
            for y in rows {
                for x in 0..w as usize {
                    let e = (d.data[y * w as usize + x] - truth(x, y)).abs() / truth(x, y);
                    (sum, worst, n) = (sum + e, worst.max(e), n + 1);
                }
            }
            (sum / n as f32, worst)
        };
        let worst = |keep_planes, rows| error(keep_planes, rows).1;
        // The continuation is taken wholly only where the average agrees exactly (the weight
        // falls linearly with their difference, and the correction is averaged along rows), so
        // the facade's ends are not exact; but the error at least halves on the mean.
        let (kept, averaged) = (error(0.5, 0..40).0, error(0.0, 0..40).0);
        assert!(kept < 0.5 * averaged && averaged > 0.05, "facade above its samples: {kept} against {averaged}");
        assert!(worst(0.5, 88..100) < 1e-4, "road below its samples: {}", worst(0.5, 88..100));
    }

    #[test]
    fn the_facade_above_a_crown_takes_the_facade_s_depth_through_its_texture() {
        // A textured facade 20 m away (grey, each pixel +-30 per channel) behind a smooth green
        // crown 8 m away (a disc of radius 40 px centred at (120, 110)); LiDAR rings every 4 rows
        // from row 100 down, none above (the crown's top, row 70, is above the LiDAR), and two
        // patches of stereo depth on the facade beside the crown. A column through the crown
        // continues the crown's depth up to the image's top; only the 2D fill can give the
        // facade above the crown the facade's depth, from the patches 35-50 px away through the
        // facade's texture. Comparing raw block colours, the texture's steps along the way bring
        // the patches' weight under the fill's cut-off, and the crown's continuation stays (with
        // a flat grey facade, or without the patches, the two settings agree: a reviewer checked).
        let (w, h) = (240u32, 160u32);
        let crown = |x: usize, y: usize| (x as f32 - 120.0).powi(2) + (y as f32 - 110.0).powi(2) < 40.0 * 40.0;
        let mut rng = dist4d_types::rng::Rng::new(23);
        let noise: Vec<i32> = (0..w * h * 3).map(|_| rng.below(61) as i32 - 30).collect();
        let image = grey(w, h, |x, y| {
            if crown(x, y) {
                [40, 90, 40]
            } else {
                let i = 3 * (y * w as usize + x);
                [0, 1, 2].map(|k| (120 + noise[i + k]) as u8)
            }
        });
        let mut sparse = DepthMap::new(w, h);
        for y in (100..h as usize).step_by(4) {
            for x in (0..w as usize).step_by(2) {
                sparse.data[y * w as usize + x] = if crown(x, y) { 8.0 } else { 20.0 };
            }
        }
        // Stereo found the facade in two patches beside the crown, 35-50 px from it.
        for y in (10..60).step_by(3) {
            for x in (66..72).chain(168..174).step_by(2) {
                sparse.data[y * w as usize + x] = 20.0;
            }
        }
        // The mean relative error above the crown (rows 5..60, columns 105..135).
        let above = |p: &Params| {
            let d = complete(p, &image, &sparse, None, false).depth;
            let (mut sum, mut n) = (0f32, 0);
            for y in 5..60 {
                for x in 105..135 {
                    sum += (d.data[y * w as usize + x] - 20.0).abs() / 20.0;
                    n += 1;
                }
            }
            sum / n as f32
        };
        let evened = above(&Params::default());
        // CompleteDepth 14's fill: the blocks' own colours, a step of 40.
        let raw = above(&Params { smooth_texture: 0, smooth_edge: 40.0, ..Params::default() });
        assert!(evened < 0.05, "the facade above the crown is off by {evened} on average");
        assert!(raw > 0.3, "the test no longer tells: the fill without evened colours is off by {raw} only");
    }

    #[test]
    fn a_box_mean_is_the_mean_of_the_square_cut_at_the_borders() {
        let mut rng = dist4d_types::rng::Rng::new(29);
        for (w, h, r) in [(9usize, 7usize, 2usize), (1, 5, 1), (6, 1, 3), (4, 4, 0), (5, 6, 9)] {
            let planes: Vec<u8> = (0..3 * w * h).map(|_| rng.below(256) as u8).collect();
            let got = box_mean(&planes, w, h, r);
            for k in 0..3 {
                for y in 0..h {
                    for x in 0..w {
                        let (mut sum, mut cells) = (0u32, 0u32);
                        for yy in y.saturating_sub(r)..(y + r + 1).min(h) {
                            for xx in x.saturating_sub(r)..(x + r + 1).min(w) {
                                sum += planes[k * w * h + yy * w + xx] as u32;
                                cells += 1;
                            }
                        }
                        let expected = (sum as f32 * (1.0 / cells as f32) + 0.5) as u8;
                        assert_eq!(got[k * w * h + y * w + x], expected, "{w}x{h}, r {r}, plane {k}, ({x}, {y})");
                    }
                }
            }
        }
    }

    /// Red, green and blue planes of a `w` x `h` image from a colour per pixel.
    fn planes_of(w: usize, h: usize, f: impl Fn(usize, usize) -> [u8; 3]) -> Vec<u8> {
        let mut planes = vec![0u8; 3 * w * h];
        for y in 0..h {
            for x in 0..w {
                let c = f(x, y);
                for k in 0..3 {
                    planes[k * w * h + y * w + x] = c[k];
                }
            }
        }
        planes
    }

    #[test]
    fn blocks_sum_the_sources_and_average_the_colours_of_their_pixels() {
        // Odd sizes: the last block row and column hold 2 or 1 pixels.
        let (w, h) = (5usize, 3usize);
        let inv: Vec<f32> = (0..w * h).map(|i| 0.1 * (i + 1) as f32).collect();
        // Sources: near a sample (every other pixel), or ground (pixel 7); the last column is sky.
        let near: Vec<u8> = (0..w * h).map(|i| (i % 2 == 0) as u8).collect();
        let continued: Vec<u8> = (0..w * h).map(|i| if i == 7 { GROUND } else { CONTINUED }).collect();
        let sky: Vec<u8> = (0..w * h).map(|i| (i == 4 || i == 9 || i == 14) as u8).collect();
        let planes = planes_of(w, h, |x, y| [(10 * x + y) as u8, 7, (x * y) as u8]);
        let b = Blocks::of(&inv, &near, &continued, &planes, &sky, w, h);
        assert_eq!((b.w, b.h), (3, 2));
        for (by, bx) in (0..2).flat_map(|by| (0..3).map(move |bx| (by, bx))) {
            let pixels: Vec<usize> =
                [(2 * by, 2 * bx), (2 * by, 2 * bx + 1), (2 * by + 1, 2 * bx), (2 * by + 1, 2 * bx + 1)]
                    .into_iter()
                    .filter(|&(y, x)| y < h && x < w)
                    .map(|(y, x)| y * w + x)
                    .collect();
            let source = |i: usize| is_source(inv[i], near[i], sky[i], continued[i]);
            let j = by * 3 + bx;
            let num: f32 = pixels.iter().filter(|&&i| source(i)).map(|&i| inv[i]).sum();
            let den = pixels.iter().filter(|&&i| source(i)).count() as f32;
            assert!((b.num[j] - num).abs() < 1e-6 && b.den[j] == den, "block {j}: {} {} against {num} {den}", b.num[j], b.den[j]);
            for k in 0..3 {
                let sum: u32 = pixels.iter().map(|&i| planes[k * w * h + i] as u32).sum();
                let n = pixels.len() as u32;
                assert_eq!(b.planes[k * 6 + j] as u32, (sum + n / 2) / n, "block {j}, colour {k}");
            }
            assert_eq!(b.sky[j], pixels.iter().all(|&i| sky[i] != 0) as u8, "block {j}");
        }
    }

    #[test]
    fn spreading_blocks_keeps_their_value_on_each_side_of_a_colour_edge() {
        // Blocks left of x = 10 red with inverse depth 0.5, right of it blue with 0.1; a pixel
        // row spread from them takes its own side's value, up to the edge, and a uniform region
        // exactly its value.
        let (w, h) = (20usize, 8usize);
        let planes = planes_of(w, h, |x, _| if x < 10 { [200, 30, 30] } else { [30, 30, 200] });
        let (bw, bh) = (10usize, 4usize);
        let mut blocks = Blocks { w: bw, h: bh, num: vec![0.0; bw * bh], den: vec![4.0; bw * bh], planes: vec![0; 3 * bw * bh], sky: vec![0; bw * bh] };
        for by in 0..bh {
            for bx in 0..bw {
                let j = by * bw + bx;
                blocks.num[j] = 4.0 * if bx < 5 { 0.5 } else { 0.1 };
                let c: [u8; 3] = if bx < 5 { [200, 30, 30] } else { [30, 30, 200] };
                for k in 0..3 {
                    blocks.planes[k * bw * bh + j] = c[k];
                }
            }
        }
        let p = Params::default();
        let like = likeness(&p, p.smooth_sigma / p.spread_edge);
        let mut spread = Spread::new(w);
        for y in 0..h {
            spread.row(&blocks, y, &planes, w, h, &like);
            for x in 0..w {
                let v = spread.num[x] / spread.den[x];
                let expected = if x < 10 { 0.5 } else { 0.1 };
                assert!((v - expected).abs() < 1e-4 * expected, "row {y}, pixel {x}: {v}");
            }
        }
        // Without the colour likeness (a grey image), the pixels beside the edge mix both sides.
        let grey = planes_of(w, h, |_, _| [100, 100, 100]);
        let flat = Blocks { planes: vec![100; 3 * bw * bh], ..blocks };
        let mut spread = Spread::new(w);
        spread.row(&flat, 3, &grey, w, h, &like);
        // Pixel 9 is 3/4 on block 4 (0.5) and 1/4 on block 5 (0.1), pixel 10 the other way.
        assert!((spread.num[9] / spread.den[9] - 0.4).abs() < 1e-6);
        assert!((spread.num[10] / spread.den[10] - 0.2).abs() < 1e-6);
    }

    #[test]
    fn spreading_blocks_is_bilinear_between_block_centres_and_clamped_at_the_borders() {
        // One colour, block values a ramp in both directions; odd sizes, so that the last block
        // row and column are half blocks.
        for (w, h) in [(9usize, 7usize), (10, 8), (2, 5), (5, 2)] {
            let (bw, bh) = (w.div_ceil(2), h.div_ceil(2));
            let value = |bx: usize, by: usize| bx as f32 + 10.0 * by as f32;
            let blocks = Blocks {
                w: bw,
                h: bh,
                num: (0..bw * bh).map(|j| 4.0 * value(j % bw, j / bw)).collect(),
                den: vec![4.0; bw * bh],
                planes: vec![90; 3 * bw * bh],
                sky: vec![0; bw * bh],
            };
            let planes = planes_of(w, h, |_, _| [90, 90, 90]);
            let p = Params::default();
            let like = likeness(&p, p.smooth_sigma / p.spread_edge);
            let mut spread = Spread::new(w);
            // A pixel's centre in block units is (x - 0.5) / 2, clamped to the first and last
            // block centres.
            let at = |x: usize, n: usize| ((x as f32 - 0.5) / 2.0).clamp(0.0, (n - 1) as f32);
            for y in 0..h {
                spread.row(&blocks, y, &planes, w, h, &like);
                for x in 0..w {
                    let expected = at(x, bw) + 10.0 * at(y, bh);
                    let v = spread.num[x] / spread.den[x];
                    assert!((v - expected).abs() < 1e-4, "{w}x{h}, pixel ({x}, {y}): {v} against {expected}");
                }
            }
        }
    }

    #[test]
    fn a_facade_above_a_tree_crown_takes_the_facade_depth_seen_beside_the_crown() {
        // A facade 20 m away (grey-blue) behind a crown 8 m away (green) covering columns
        // 12..28, rows 12..30. The LiDAR sees the crown and the facade beside it and below it,
        // but nothing above the crown: its column's highest sample is the crown's.
        let (w, h) = (40u32, 40u32);
        let crown = |x: usize, y: usize| (12..28).contains(&x) && (12..30).contains(&y);
        let image = grey(w, h, |x, y| if crown(x, y) { [30, 90, 30] } else { [100, 100, 120] });
        let mut sparse = DepthMap::new(w, h);
        for y in (2..h as usize).step_by(3) {
            for x in (0..w as usize).step_by(2) {
                let beside = !(10..30).contains(&x) || y >= 32;
                if crown(x, y) {
                    sparse.data[y * w as usize + x] = 8.0;
                } else if beside {
                    sparse.data[y * w as usize + x] = 20.0;
                }
            }
        }
        let at = |d: &DepthMap, x: usize, y: usize| d.data[y * w as usize + x];
        let d = complete(&Params::default(), &image, &sparse, None, false).depth;
        for x in 14..26 {
            let z = at(&d, x, 4);
            assert!((z - 20.0).abs() < 0.05 * 20.0, "({x}, 4): {z}");
        }
        assert!((at(&d, 20, 20) - 8.0).abs() < 0.05 * 8.0, "the crown keeps its depth: {}", at(&d, 20, 20));
        // The column alone (neither average nor refinement) would continue the crown up.
        let column = Params { smooth_sigma: 0.0, refine_iterations: 0, ..Params::default() };
        let column = complete(&column, &image, &sparse, None, false).depth;
        assert!((at(&column, 20, 4) - 8.0).abs() < 0.5, "{}", at(&column, 20, 4));
    }

    #[test]
    fn a_facade_above_its_highest_samples_has_no_vertical_streaks() {
        // One uniform wall; the top samples alternate between 10 m and 12 m every 4 columns
        // (noisy MVS points), at row 40. Above them each column used to continue its own
        // sample upwards: stripes of 10 and 12 m. Far from the samples the row is now one
        // surface.
        let (w, h) = (64u32, 60u32);
        let mut sparse = DepthMap::new(w, h);
        for x in 0..w as usize {
            for y in (40..h as usize).step_by(3) {
                sparse.data[y * w as usize + x] = if (x / 4) % 2 == 0 || y > 40 { 10.0 } else { 12.0 };
            }
        }
        let image = grey(w, h, |_, _| [120, 110, 100]);
        let p = Params { grow: 0.0, ..Params::default() };
        // The depths of row 5 between columns 8 and 56: (least, greatest).
        let span = |p: &Params| {
            let d = complete(p, &image, &sparse, None, false).depth;
            (8..56).map(|x| d.data[5 * w as usize + x]).fold((f32::MAX, 0f32), |(a, b), v| (a.min(v), b.max(v)))
        };
        let (lo, hi) = span(&p);
        assert!(hi / lo < 1.02, "row 5 spans {lo}..{hi} m");
        // Kept continuations of noisy top samples would be streaks again: each column's
        // correction to the average is averaged along the row first (without the refinement,
        // which smooths steps over 5%, to see it).
        let (lo, hi) = span(&Params { refine_iterations: 0, ..p.clone() });
        assert!(hi / lo < 1.02, "without the refinement, row 5 spans {lo}..{hi} m");
        let streaky = complete(&Params { smooth_sigma: 0.0, refine_iterations: 0, ..p }, &image, &sparse, None, false).depth;
        assert_eq!(streaky.data[5 * w as usize + 5], 12.0, "without the row average: a streak");
    }
}
