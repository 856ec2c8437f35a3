//! The support map: how far (px) each pixel is from a sample of the prompt, by a chamfer distance
//! transform (a confidence a training loader thresholds; the 2D fill asks only which pixels are
//! within its reach of a sample).

use super::kernels::map;

/// The chamfer distance of a pixel without a sample in reach (x3, as the transform counts).
const FAR: u32 = u32::MAX / 2;

/// 1 where a pixel is within `reach` px of a sample by the support distance (`distance`, or made
/// here). The 2D fill asks only this of the support distance, and at its reach of 1 px (the
/// default) that is a sample or a 4-neighbour of one: the chamfer's 3 / 3 = 1 for those, 4 / 3 and
/// more for the rest. Without the support map wanted, that costs a pass over the samples instead
/// of the chamfer's four.
#[inline(always)]
pub(super) fn near_samples(sparse: &[f32], distance: Option<&[f32]>, reach: f32, w: usize, h: usize) -> Vec<u8> {
    const DIAGONAL: f32 = 4.0 / 3.0;
    if distance.is_some() || reach >= DIAGONAL {
        let made;
        let distance = match distance {
            Some(d) => d,
            None => {
                made = support_distance(sparse, w, h);
                &made
            }
        };
        return map(distance, |d| (d <= reach) as u8);
    }
    let sample = map(sparse, |z| (z > 0.0 && z.is_finite()) as u8);
    if reach < 1.0 || w == 0 {
        return sample;
    }
    let mut near = sample.clone();
    for (y, row) in near.chunks_exact_mut(w).enumerate() {
        let here = &sample[y * w..(y + 1) * w];
        for (n, s) in row[1..].iter_mut().zip(here) {
            *n |= s;
        }
        for (n, s) in row.iter_mut().zip(&here[1..]) {
            *n |= s;
        }
        if y > 0 {
            for (n, s) in row.iter_mut().zip(&sample[(y - 1) * w..y * w]) {
                *n |= s;
            }
        }
        if y + 1 < h {
            for (n, s) in row.iter_mut().zip(&sample[(y + 1) * w..(y + 2) * w]) {
                *n |= s;
            }
        }
    }
    near
}

/// Distance (px) from every pixel to the nearest valid sample: the 3-4 chamfer distance
/// (Borgefors 1986) divided by 3, within 8% of the Euclidean one; `f32::MAX` with no sample.
/// (NearestFill's exact transform costs about 40 ms per 1600x900 image, nearly this whole
/// completion's time; a confidence needs no better than 8%.)
#[inline(always)]
pub(super) fn support_distance(sparse: &[f32], w: usize, h: usize) -> Vec<f32> {
    let mut d = map(sparse, |z| if z > 0.0 && z.is_finite() { 0 } else { FAR });
    if w == 0 {
        return Vec::new();
    }
    // Each pass takes a row at a time: the links to the previous row first (element-wise, so
    // they vectorise), then the row's own chain along it.
    for y in 0..h {
        let (done, rest) = d.split_at_mut(y * w);
        let row = &mut rest[..w];
        if y > 0 {
            chamfer_from_row(row, &done[(y - 1) * w..]);
        }
        chain_along(row);
    }
    for y in (0..h).rev() {
        let (head, below) = d.split_at_mut((y + 1) * w);
        let row = &mut head[y * w..];
        if y + 1 < h {
            chamfer_from_row(row, &below[..w]);
        }
        row.reverse();
        chain_along(row);
        row.reverse();
    }
    map(&d, |v| if v >= FAR { f32::MAX } else { v as f32 / 3.0 })
}

/// The chamfer's links along a row, left to right: row[x] = min(row[x], row[x - 1] + 3), that is
/// the least row[j] + 3 (x - j) over j <= x. Done in one chain, each step waits on the one
/// before; so the row's four quarters run as four chains side by side, and then each quarter
/// takes the end of the one before it as one more candidate, up to where it stops winning: past
/// there it never wins again, as it grows by 3 per pixel and the row, chained, by at most 3 (within
/// a quarter; at the next quarter's start it may not be, so the candidate may run on into that
/// quarter, and every quarter gets its own candidate after).
#[inline(always)]
fn chain_along(row: &mut [u32]) {
    let (w, q) = (row.len(), row.len() / 4);
    if q < 2 {
        for x in 1..w {
            row[x] = row[x].min(row[x - 1] + 3);
        }
        return;
    }
    for x in 1..q {
        for c in 0..4 {
            let i = c * q + x;
            row[i] = row[i].min(row[i - 1] + 3);
        }
    }
    // The last quarter takes the pixels the division left over.
    for x in 4 * q..w {
        row[x] = row[x].min(row[x - 1] + 3);
    }
    for c in 1..4 {
        let mut carried = row[c * q - 1];
        for v in &mut row[c * q..] {
            carried += 3;
            if carried >= *v {
                break;
            }
            *v = carried;
        }
    }
}

/// The 3-4 chamfer links from a row to its neighbour row `other` (element-wise, so they vectorise).
#[inline(always)]
fn chamfer_from_row(row: &mut [u32], other: &[u32]) {
    let w = row.len();
    row[0] = row[0].min(other[0] + 3).min(other.get(1).map_or(FAR, |v| v + 4));
    if w > 1 {
        row[w - 1] = row[w - 1].min(other[w - 1] + 3).min(other[w - 2] + 4);
    }
    for (v, o) in row[1..].iter_mut().zip(other.windows(3)) {
        *v = (*v).min(o[1] + 3).min(o[0] + 4).min(o[2] + 4);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn support_distance_is_the_chamfer_distance_to_the_nearest_sample() {
        let (w, h) = (11, 9);
        let mut sparse = vec![0f32; w * h];
        sparse[4 * w + 5] = 7.0;
        let d = support_distance(&sparse, w, h);
        assert_eq!(d[4 * w + 5], 0.0);
        assert_eq!(d[4 * w + 8], 3.0);
        assert_eq!(d[7 * w + 8], 4.0, "three diagonal steps: 3 x 4/3");
        assert!(support_distance(&[0.0; 4], 2, 2).iter().all(|&v| v == f32::MAX));
    }

    #[test]
    fn pixels_near_a_sample_are_those_the_support_distance_puts_within_reach() {
        let mut rng = dist4d_types::rng::Rng::new(17);
        for (w, h) in [(1, 1), (1, 7), (9, 1), (2, 2), (31, 17), (64, 40)] {
            for density in [0.0, 0.02, 0.3, 1.0] {
                let sparse: Vec<f32> = (0..w * h)
                    .map(|_| if rng.next_f64() < density { 1.0 + rng.next_f64() as f32 } else { 0.0 })
                    .collect();
                let distance = support_distance(&sparse, w, h);
                for reach in [0.0, 0.5, 1.0, 1.2, 4.0 / 3.0, 2.5] {
                    let from_distance = near_samples(&sparse, Some(&distance), reach, w, h);
                    let expected: Vec<u8> = distance.iter().map(|&d| (d <= reach) as u8).collect();
                    assert_eq!(from_distance, expected);
                    assert_eq!(near_samples(&sparse, None, reach, w, h), expected, "{w}x{h}, density {density}, reach {reach}");
                }
            }
        }
    }

    #[test]
    fn chaining_a_row_in_quarters_gives_what_one_chain_gives() {
        let mut rng = dist4d_types::rng::Rng::new(3);
        for len in (0..40).chain([97, 1600, 1601, 1603]) {
            for density in [0.0, 0.01, 0.2, 0.9] {
                let row: Vec<u32> = (0..len)
                    .map(|_| if rng.next_f64() < density { rng.below(12) as u32 } else { FAR })
                    .collect();
                let mut one = row.clone();
                for x in 1..len {
                    one[x] = one[x].min(one[x - 1] + 3);
                }
                let mut quarters = row;
                chain_along(&mut quarters);
                assert_eq!(quarters, one, "{len} px, density {density}");
            }
        }
    }
}
