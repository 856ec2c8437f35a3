//! Objects that move between a source image's time and a target's: their pixels are drawn from
//! where their box is at the target's time, not where it was at the source's.
//!
//! A pixel belongs to an object when its point (in the source camera's frame) lies inside the
//! object's box at the source image's time (grown by `MARGIN`, its bottom raised by
//! `GROUND_CLEARANCE` so the road under a car stays road). Each object found in the target's boxes
//! (same track) moves rigidly with its box: the source pixels of that object are drawn as if the
//! source camera had moved by the box's motion (`T_target_box * T_source_box^-1`), which keeps the
//! splatting unchanged. An object the target's time has no box for (it left the annotated range) is
//! left out. The boxes are those of `dataset.image_info`, at each image's own time.

use super::splat::PinholeView;
use dist4d_types::artifact::Box3D;
use dist4d_types::geometry::Se3;
use glam::DVec3;
use serde::{Deserialize, Serialize};

/// What happens to objects that moved between the source and target times.
#[derive(Serialize, Deserialize, Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum Moving {
    /// Drawn where their box is at the target's time; an object without a box then is left out.
    #[default]
    Follow,
    /// Left out of the condition.
    Drop,
    /// Drawn where they were (no compensation).
    Keep,
}

/// Boxes grow by this much (m) sideways and on top: annotations are tight, depth edges are not.
const MARGIN: f64 = 0.1;
/// A box's bottom is raised by this much (m): the road under a car is not the car.
const GROUND_CLEARANCE: f64 = 0.15;
/// A box that moved less than this (m, and under ~0.5 degrees) did not move.
const STILL: f64 = 0.05;

/// A piece of a source to draw: its depth (0 outside the piece) and the camera to draw it from.
pub struct Piece {
    pub depth: Vec<f32>,
    pub view: PinholeView,
}

/// What a split did, for the pair's record.
#[derive(Default, Debug, PartialEq, Eq)]
pub struct Moved {
    /// Objects drawn where they are at the target's time.
    pub followed: usize,
    /// Objects left out.
    pub dropped: usize,
}

/// Splits a source's `depth` (seen by `view`, with `boxes` at its time) into the pieces to draw
/// for a target whose time has `target_boxes`: the static rest first, then one piece per object
/// that moved. With [`Moving::Keep`], or when nothing moved, the one piece is the source itself.
pub fn split(
    depth: &[f32],
    view: &PinholeView,
    boxes: &[Box3D],
    target_boxes: &[Box3D],
    mode: Moving,
) -> (Vec<Piece>, Moved) {
    let whole = || vec![Piece { depth: depth.to_vec(), view: *view }];
    if mode == Moving::Keep {
        return (whole(), Moved::default());
    }
    let pose = |b: &Box3D| Se3::from_wxyz_t(b.rotation, b.center);
    // (box, its motion to the target's time: None = left out)
    let mut objects: Vec<(&Box3D, Option<Se3>)> = Vec::new();
    for b in boxes {
        let motion =
            target_boxes.iter().find(|t| t.instance == b.instance).map(|t| pose(t).then_from(&pose(b).inverse()));
        let still = motion
            .is_some_and(|m| m.translation.length() < STILL && m.rotation.angle_between(glam::DQuat::IDENTITY) < 0.01);
        if !still {
            objects.push((b, if mode == Moving::Follow { motion } else { None }));
        }
    }
    if objects.is_empty() {
        return (whole(), Moved::default());
    }
    let (w, h) = (view.width as usize, view.height as usize);
    let cam_from_world = view.world_from_cam.inverse();
    let mut owner = vec![u16::MAX; w * h];
    // Per object, its pixels (so that building its piece does not scan the whole image).
    let mut members: Vec<Vec<u32>> = vec![Vec::new(); objects.len()];
    let k = view.k;
    let unproject = |x: usize, y: usize, z: f64| {
        let yc = (y as f64 + 0.5 - k[1][2]) / k[1][1];
        let xc = (x as f64 + 0.5 - k[0][2] - k[0][1] * yc) / k[0][0];
        DVec3::new(xc * z, yc * z, z)
    };
    for (o, (b, _)) in objects.iter().enumerate() {
        let test = b.test(&cam_from_world, MARGIN, GROUND_CLEARANCE);
        // The pixels the box can cover: its corners' projections (a box partly behind the camera
        // may cover anything).
        let (lo, hi) = test.corners();
        let box_to_cam = cam_from_world.then_from(&pose(b));
        let (mut x0, mut y0, mut x1, mut y1) = (f64::INFINITY, f64::INFINITY, f64::NEG_INFINITY, f64::NEG_INFINITY);
        let mut behind = 0;
        for c in 0..8 {
            let corner = DVec3::new(
                if c & 1 == 0 { lo.x } else { hi.x },
                if c & 2 == 0 { lo.y } else { hi.y },
                if c & 4 == 0 { lo.z } else { hi.z },
            );
            let p = box_to_cam.apply(corner);
            if p.z <= 0.05 {
                behind += 1;
                continue;
            }
            let (u, v, _) = view.project(p);
            (x0, y0, x1, y1) = (x0.min(u), y0.min(v), x1.max(u), y1.max(v));
        }
        if behind == 8 {
            // Wholly behind the camera (most boxes of a scene, for any one camera).
            continue;
        }
        let (x0, y0, x1, y1) = if behind > 0 {
            (0, 0, w, h)
        } else {
            if x1 < 0.0 || y1 < 0.0 || x0 >= w as f64 || y0 >= h as f64 {
                continue;
            }
            (
                x0.max(0.0) as usize,
                y0.max(0.0) as usize,
                (x1.ceil() as usize + 1).min(w),
                (y1.ceil() as usize + 1).min(h),
            )
        };
        for y in y0..y1 {
            for x in x0..x1 {
                let i = y * w + x;
                let z = depth[i];
                if owner[i] == u16::MAX && z > 0.0 && z.is_finite() && test.contains(unproject(x, y, z as f64)) {
                    owner[i] = o as u16;
                    members[o].push(i as u32);
                }
            }
        }
    }
    let mut moved = Moved::default();
    let mut still_depth = depth.to_vec();
    let mut pieces = Vec::new();
    for ((_, motion), pixels) in objects.iter().zip(&members) {
        if pixels.is_empty() {
            continue;
        }
        for &i in pixels {
            still_depth[i as usize] = 0.0;
        }
        match motion {
            Some(m) => {
                let mut piece = vec![0.0f32; w * h];
                for &i in pixels {
                    piece[i as usize] = depth[i as usize];
                }
                moved.followed += 1;
                pieces.push(Piece {
                    depth: piece,
                    view: PinholeView { world_from_cam: m.then_from(&view.world_from_cam), ..*view },
                });
            }
            None => moved.dropped += 1,
        }
    }
    pieces.insert(0, Piece { depth: still_depth, view: *view });
    (pieces, moved)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn car(instance: &str, x: f64) -> Box3D {
        Box3D {
            center: [x, 0.0, 10.0],
            size: [2.0, 4.0, 1.5],
            rotation: [1.0, 0.0, 0.0, 0.0],
            velocity: [f64::NAN; 3],
            instance: instance.into(),
            category: "vehicle.car".into(),
            attributes: vec![],
            num_lidar_pts: 0,
            interpolated: false,
            extrapolated: false,
        }
    }

    #[test]
    fn a_moved_object_is_drawn_from_its_new_place_and_a_vanished_one_is_left_out() {
        // A camera at the origin looking along +z (world = camera frame); a wall at 20 m with two
        // boxes in front of it whose pixels sit at 10 m.
        let (w, h) = (40usize, 30usize);
        let view = PinholeView {
            k: [[20.0, 0.0, 20.0], [0.0, 20.0, 15.0], [0.0, 0.0, 1.0]],
            width: w as u32,
            height: h as u32,
            world_from_cam: Se3::default(),
        };
        let mut depth = vec![20.0f32; w * h];
        // Box "a" at x = -3 (pixel columns ~ 20 + 20 * (-3 +- 2) / 10), box "b" at x = +3.
        // Rows 13..17: y within +-1 m at 10 m, inside the boxes' 2 m width.
        for y in 13..17 {
            for x in 12..17 {
                depth[y * w + x] = 10.0;
            }
            for x in 24..29 {
                depth[y * w + x] = 10.0;
            }
        }
        let boxes = [car("a", -3.0), car("b", 3.0)];
        // "a" moved 1 m along x, "b" has no box at the target's time.
        let (pieces, moved) = split(&depth, &view, &boxes, &[car("a", -2.0)], Moving::Follow);
        assert_eq!(moved, Moved { followed: 1, dropped: 1 });
        assert_eq!(pieces.len(), 2);
        let count = |d: &[f32]| d.iter().filter(|&&z| z > 0.0).count();
        assert_eq!(count(&pieces[0].depth), w * h - 40, "the static rest lacks both objects");
        assert_eq!(count(&pieces[1].depth), 20);
        assert!((pieces[1].view.world_from_cam.translation - DVec3::new(1.0, 0.0, 0.0)).length() < 1e-9);
        // Nothing moved: the source as it is.
        let (pieces, moved) = split(&depth, &view, &boxes, &boxes, Moving::Follow);
        assert_eq!((pieces.len(), moved), (1, Moved::default()));
        let (pieces, _) = split(&depth, &view, &boxes, &[car("a", -2.0)], Moving::Keep);
        assert_eq!(count(&pieces[0].depth), w * h);
    }
}
