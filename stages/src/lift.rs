//! Which pixels of a depth map may become 3D points: the one rule every stage that lifts depth to
//! 3D applies first (`SurroundCloud`, `Reproject`, `FramePair`, `GenerateFuture`'s warp).
//!
//! A depth map is a surface only between its edges. Where two surfaces meet in one pixel, a
//! camera, a stereo match or a completion gives a depth between the two ("flying pixels"); lifted,
//! such pixels hang in the air along their viewing rays, and a bullet-time cloud made of them is
//! radial spikes. A pixel is lifted only when all of this holds:
//!
//! 1. **It has a depth**: finite and above 0. Depth 0 means "no depth" everywhere (the ego
//!    vehicle's mask writes 0 there), so 0, NaN and negative values are never lifted.
//! 2. **It is not the sky**: depth at least 99.5% of `sky_depth` (the curation's fill value, 100 m)
//!    is a direction, not a surface. Stages that draw the sky draw it as directions from the
//!    target camera (see [`crate::views::splat::draw_sky`]).
//! 3. **No neighbour across an edge is nearer.** Of a depth step between a pixel and one of its 8
//!    neighbours, the far side is dropped when the step is an edge: the neighbour is nearer by
//!    more than `max_jump` (relative), *and* the inverse depth changes by more than a plane at
//!    `min_plane_distance` metres from the camera can change from one pixel to the next
//!    (`f * |1/z_n - 1/z| > 1 / min_plane_distance`, f the focal length in px; diagonals by
//!    sqrt 2). The second test keeps grazing planes: the road seen from a camera 1.5 m above it
//!    steps by up to `1/1.5` in those units per row at any distance, which is 5% of the depth per
//!    row at 20 m in a 320 px wide image, while a car's silhouette against a facade 5 m behind it
//!    steps by 10 or more. Keeping the near side keeps objects whole: the pixel between a pole
//!    and the facade behind it has the pole as a nearer neighbour and goes, the pole stays.
//! 4. **It is not alone**: at least `min_neighbours` of its 8 neighbours have a depth that is no
//!    edge away (a lone pixel of another depth, a speckle of the completion, has no surface to
//!    belong to).
//! 5. **It has support**, where a support map is wired (`CompleteDepth`'s `support`: px to the
//!    nearest prompt sample): at most `max_support_px` (0 = no limit), and at most
//!    `max_support_m` metres at the pixel's own depth (`support * z / f`; 0 = no limit). Far from
//!    every sample the completion's depth is an extrapolation, and how far is a matter of metres
//!    on the surface, not of pixels: 5 px from a LiDAR return is 0.1 m on a wall at 5 m and 1.5 m
//!    on one at 60 m, where the completion has a whole gap between two LiDAR rings to bridge.
//!
//! The defaults and what they do on the synthetic and the DGP scenes are in docs/stages.md
//! ("Lifting depth to 3D") and docs/BENCHMARKS.md ("Flying pixels (issue 42)").

use dist4d_graph::ParamChecks;
use serde::{Deserialize, Serialize};

/// The rule's params (see the module doc); every lifting stage has them as `lift`.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct LiftParams {
    /// A neighbour nearer by more than this fraction of its depth may make the pixel an edge's
    /// far side; 0 turns tests 3 and 4 off.
    pub max_jump: f32,
    /// Metres: an inverse-depth step larger than a plane this far from the camera can make is an
    /// edge, a smaller one a slanted surface.
    pub min_plane_distance: f32,
    /// Of the 8 neighbours, at least this many must be on the pixel's surface.
    pub min_neighbours: u8,
    /// Px to the nearest prompt sample above which a pixel is not lifted (when a support map is
    /// wired); 0 = no limit.
    pub max_support_px: f32,
    /// Metres on the surface (support px times depth over the focal length) to the nearest prompt
    /// sample above which a pixel is not lifted (when a support map is wired); 0 = no limit.
    pub max_support_m: f32,
    /// The sky's fill value (m): depths at least 99.5% of it are sky.
    pub sky_depth: f32,
}

impl Default for LiftParams {
    fn default() -> Self {
        LiftParams {
            max_jump: 0.05,
            min_plane_distance: 1.0,
            min_neighbours: 2,
            max_support_px: 0.0,
            max_support_m: 0.0,
            sky_depth: 100.0,
        }
    }
}

impl LiftParams {
    /// Range checks, added to the stage's own.
    pub fn check(&self, c: &mut ParamChecks) {
        c.within("max_jump", self.max_jump as f64, 0.0, 100.0)
            .above("min_plane_distance", self.min_plane_distance as f64, 0.0, 1e4)
            .count("min_neighbours", self.min_neighbours as u64, 0, 8)
            .within("max_support_px", self.max_support_px as f64, 0.0, 1e6)
            .within("max_support_m", self.max_support_m as f64, 0.0, 1e6)
            .above("sky_depth", self.sky_depth as f64, 0.0, 1e6);
    }

    /// Whether depth `z` is the sky's fill value.
    #[inline]
    pub fn is_sky(&self, z: f32) -> bool {
        z >= self.sky_depth * 0.995
    }

    /// Whether `z` is a surface depth at all (tests 1 and 2).
    #[inline]
    pub fn is_surface(&self, z: f32) -> bool {
        z > 0.0 && z.is_finite() && !self.is_sky(z)
    }
}

/// Per pixel of a `w` x `h` depth map seen with focal length `focal_px` (px; the geometric mean
/// of fx and fy at the map's size), whether the rule of the module doc lifts it. `support`, when
/// given, is the map's support distance (px), the same size.
pub fn liftable(
    depth: &[f32],
    w: usize,
    h: usize,
    focal_px: f64,
    support: Option<&[f32]>,
    p: &LiftParams,
) -> Vec<bool> {
    assert_eq!(depth.len(), w * h, "the depth map is not {w}x{h}");
    let surface: Vec<bool> = depth.iter().map(|&z| p.is_surface(z)).collect();
    let mut out = surface.clone();
    if let (Some(s), true) = (support, p.max_support_px > 0.0 || p.max_support_m > 0.0) {
        assert_eq!(s.len(), w * h, "the support map is not {w}x{h}");
        let px = if p.max_support_px > 0.0 { p.max_support_px } else { f32::INFINITY };
        // support * z / f <= max_support_m, as support * z <= max_support_m * f.
        let m = if p.max_support_m > 0.0 { (p.max_support_m as f64 * focal_px) as f32 } else { f32::INFINITY };
        for ((o, &d), &z) in out.iter_mut().zip(s).zip(depth) {
            // NaN (no sample at all) is no support either.
            *o &= d <= px && d * z <= m;
        }
    }
    if p.max_jump <= 0.0 {
        return out;
    }
    let (jump, step) = (1.0 + p.max_jump as f64, 1.0 / (focal_px * p.min_plane_distance as f64));
    // An edge from a pixel at inverse depth `i` (depth `z`) to a nearer neighbour at `z_n`
    // (inverse `i_n`), `reach` px away.
    let nearer_across_edge = |z: f64, i: f64, z_n: f64, i_n: f64, reach: f64| z > jump * z_n && i_n - i > step * reach;
    const NEIGHBOURS: [(isize, isize, f64); 8] = [
        (-1, -1, std::f64::consts::SQRT_2),
        (0, -1, 1.0),
        (1, -1, std::f64::consts::SQRT_2),
        (-1, 0, 1.0),
        (1, 0, 1.0),
        (-1, 1, std::f64::consts::SQRT_2),
        (0, 1, 1.0),
        (1, 1, std::f64::consts::SQRT_2),
    ];
    for y in 0..h {
        for x in 0..w {
            let k = y * w + x;
            if !out[k] {
                continue;
            }
            let z = depth[k] as f64;
            let i = 1.0 / z;
            let mut same = 0u8;
            let mut far_side = false;
            for &(dx, dy, reach) in &NEIGHBOURS {
                let (nx, ny) = (x as isize + dx, y as isize + dy);
                if nx < 0 || ny < 0 || nx >= w as isize || ny >= h as isize {
                    continue;
                }
                let n = ny as usize * w + nx as usize;
                if !surface[n] {
                    // No depth, or the sky: nothing to compare with. (A surface's silhouette
                    // against the sky is its near side.)
                    continue;
                }
                let z_n = depth[n] as f64;
                let i_n = 1.0 / z_n;
                if nearer_across_edge(z, i, z_n, i_n, reach) {
                    far_side = true;
                    break;
                }
                same += !nearer_across_edge(z_n, i_n, z, i, reach) as u8;
            }
            out[k] = !far_side && same >= p.min_neighbours;
        }
    }
    out
}

/// `depth` with every pixel [`liftable`] does not lift set to 0 (no depth), ready for a splat or
/// a cloud; the sky is 0 too.
pub fn surface_only(
    depth: &[f32],
    w: usize,
    h: usize,
    focal_px: f64,
    support: Option<&[f32]>,
    p: &LiftParams,
) -> Vec<f32> {
    let keep = liftable(depth, w, h, focal_px, support, p);
    depth.iter().zip(&keep).map(|(&z, &k)| if k { z } else { 0.0 }).collect()
}

/// The geometric mean of a pinhole camera matrix's focal lengths (px).
pub fn focal_of(k: &[[f64; 3]; 3]) -> f64 {
    (k[0][0] * k[1][1]).abs().sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn lift(depth: &[f32], w: usize, h: usize, f: f64) -> Vec<bool> {
        liftable(depth, w, h, f, None, &LiftParams::default())
    }

    /// A fronto-parallel board at 10 m in front of a wall at 30 m, with a column of mixed depths
    /// (20 m) between them, as a camera or a completion leaves at the silhouette.
    fn board(w: usize, h: usize) -> Vec<f32> {
        let mut d = vec![30.0f32; w * h];
        for y in 0..h {
            for x in 0..w / 2 {
                d[y * w + x] = 10.0;
            }
            d[y * w + w / 2] = 20.0;
        }
        d
    }

    #[test]
    fn the_mixed_pixels_and_the_far_side_of_an_edge_go_and_the_near_side_stays() {
        let (w, h) = (12, 6);
        let d = board(w, h);
        let keep = lift(&d, w, h, 500.0);
        for y in 0..h {
            for x in 0..w / 2 {
                assert!(keep[y * w + x], "the board at ({x}, {y}) stays");
            }
            assert!(!keep[y * w + w / 2], "the mixed pixel at row {y} goes");
            assert!(!keep[y * w + w / 2 + 1], "the wall next to the mixed pixel (its far side) goes");
            for x in w / 2 + 2..w {
                assert!(keep[y * w + x], "the wall at ({x}, {y}) stays");
            }
        }
        // Without the rule everything but nothing would be lifted: this test needs the rule.
        let off = liftable(&d, w, h, 500.0, None, &LiftParams { max_jump: 0.0, ..LiftParams::default() });
        assert!(off.iter().all(|&k| k));
    }

    #[test]
    fn a_road_seen_at_a_grazing_angle_is_a_surface_not_a_stack_of_edges() {
        // The ground 1.5 m below a camera of focal length f: row v (below the horizon at row 0)
        // sees it at depth f * 1.5 / (v + 0.5). Far rows step by far more than `max_jump`.
        let (w, h, f) = (8usize, 60usize, 250.0);
        let d: Vec<f32> = (0..w * h).map(|k| (f * 1.5 / ((k / w) as f64 + 0.5)) as f32).collect();
        assert!(d[w] / d[2 * w] > 1.3, "the test's steps are large: {} -> {}", d[w], d[2 * w]);
        // The inverse depth steps by 1 / (1.5 f) per row: f times that is 0.67, under 1 / 1 m.
        let keep = lift(&d, w, h, f);
        for (k, &ok) in keep.iter().enumerate() {
            // The first rows are beyond the sky's 100 m: the sky by convention, never lifted.
            assert_eq!(ok, d[k] < 99.5, "road pixel ({}, {}) at {:.1} m", k % w, k / w, d[k]);
        }
        // Without the plane test, the far road is a stack of edges.
        let plain = liftable(&d, w, h, f, None, &LiftParams { min_plane_distance: 1e4, ..LiftParams::default() });
        assert!(plain.iter().zip(&d).any(|(&k, &z)| !k && z < 99.5 && z > 20.0));
    }

    #[test]
    fn zero_nan_negative_and_sky_are_never_lifted_and_do_not_make_edges() {
        let (w, h) = (5, 5);
        let mut d = vec![10.0f32; w * h];
        d[6] = 0.0;
        d[8] = f32::NAN;
        d[16] = -3.0;
        d[18] = 100.0;
        d[12] = 99.6; // the sky after a fill's rounding
        let keep = lift(&d, w, h, 500.0);
        for k in [6, 8, 12, 16, 18] {
            assert!(!keep[k], "pixel {k} ({}) lifted", d[k]);
        }
        // The wall around them has neighbours enough and no nearer one across an edge.
        for k in [0, 2, 4, 7, 11, 13, 17, 20, 24] {
            assert!(keep[k], "pixel {k} dropped");
        }
        // Every path that lifts reads a 0 as nothing: surface_only keeps it 0.
        let s = surface_only(&d, w, h, 500.0, None, &LiftParams::default());
        assert!(s[6] == 0.0 && s[8] == 0.0 && s[16] == 0.0 && s[18] == 0.0 && s[12] == 0.0);
    }

    #[test]
    fn a_lone_pixel_is_not_a_surface_but_a_one_pixel_pole_is() {
        let (w, h) = (7, 7);
        let mut d = vec![40.0f32; w * h];
        d[3 * w + 3] = 8.0; // a speckle
        let keep = lift(&d, w, h, 500.0);
        assert!(!keep[3 * w + 3], "a lone near pixel has no surface");
        let mut d = vec![40.0f32; w * h];
        for y in 0..h {
            d[y * w + 3] = 8.0; // a pole one pixel wide
        }
        let keep = lift(&d, w, h, 500.0);
        // Its end pixels have one neighbour on the pole: below `min_neighbours`.
        assert!((1..h - 1).all(|y| keep[y * w + 3]), "the pole stays");
        assert!((0..h).all(|y| !keep[y * w + 2] && !keep[y * w + 4]), "the facade beside it is its far side");
    }

    #[test]
    fn pixels_far_from_every_prompt_sample_go_when_a_support_map_is_wired() {
        let (w, h) = (4, 4);
        let d = vec![10.0f32; w * h];
        let support: Vec<f32> = (0..w * h).map(|k| k as f32).collect();
        let p = LiftParams { max_support_px: 7.5, ..LiftParams::default() };
        let keep = liftable(&d, w, h, 500.0, Some(&support), &p);
        assert_eq!(keep.iter().filter(|&&k| k).count(), 8);
        assert!(keep[7] && !keep[8]);
        // 0 = no limit.
        assert!(liftable(&d, w, h, 500.0, Some(&support), &LiftParams::default()).iter().all(|&k| k));
    }

    #[test]
    fn support_in_metres_asks_more_of_far_pixels_than_of_near_ones() {
        // Two walls, at 5 m (top rows) and 50 m (bottom rows), every pixel 4 px from a sample;
        // f = 500 px: 4 px is 0.04 m on the near wall and 0.4 m on the far one.
        let (w, h) = (6, 6);
        let d: Vec<f32> = (0..w * h).map(|k| if k / w < 3 { 5.0 } else { 50.0 }).collect();
        let support = vec![4.0f32; w * h];
        let p = LiftParams { max_support_m: 0.25, max_jump: 0.0, ..LiftParams::default() };
        let keep = liftable(&d, w, h, 500.0, Some(&support), &p);
        for (k, &ok) in keep.iter().enumerate() {
            assert_eq!(ok, d[k] < 10.0, "pixel {k} at {} m", d[k]);
        }
        // The same support in px alone keeps both walls or neither.
        let px = LiftParams { max_support_px: 4.0, max_jump: 0.0, ..LiftParams::default() };
        assert!(liftable(&d, w, h, 500.0, Some(&support), &px).iter().all(|&k| k));
    }
}
