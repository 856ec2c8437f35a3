//! The procedural world: a street (straight and curved) with lanes, kerbs and sidewalks,
//! buildings, poles, trees, parked and moving cars, pedestrians. Everything is a function of the
//! seed, so the world (and any rendering of it) can be rebuilt exactly from `synth.json`.

use crate::material::{class, Material};
use crate::shapes::{Prim, Shape};
use dist4d_types::rng::Rng;
use glam::DVec3;

/// Street cross-section, in metres from the centre line (positive to the left of travel).
pub const LANE_WIDTH: f64 = 3.5;
/// Lanes end here; the parking strip runs to the kerb.
pub const ROAD_HALF_WIDTH: f64 = 6.0;
pub const SIDEWALK_WIDTH: f64 = 4.0;
pub const KERB_HEIGHT: f64 = 0.15;
/// Ego drives the centre of the right-hand lane.
pub const EGO_LATERAL: f64 = -LANE_WIDTH / 2.0;

/// One piece of centre line: straight (curvature 0) or a circular arc.
#[derive(Clone, Copy, Debug)]
struct Segment {
    s0: f64,
    len: f64,
    x0: f64,
    y0: f64,
    heading0: f64,
    curvature: f64,
    /// x0, y0, x1, y1 of the points within `STATION_REACH` of this piece: a cheap reject before
    /// the trigonometry of `station`.
    reach: [f64; 4],
}

/// How far from the centre line `Path::station` answers.
const STATION_REACH: f64 = 40.0;

impl Segment {
    fn at(&self, ds: f64) -> (f64, f64, f64) {
        let k = self.curvature;
        let h = self.heading0 + k * ds;
        if k.abs() < 1e-12 {
            (self.x0 + ds * self.heading0.cos(), self.y0 + ds * self.heading0.sin(), h)
        } else {
            (self.x0 + (h.sin() - self.heading0.sin()) / k, self.y0 - (h.cos() - self.heading0.cos()) / k, h)
        }
    }

    /// (s, d) of a point if its foot lies on this segment.
    fn station(&self, x: f64, y: f64) -> Option<(f64, f64)> {
        let [x0, y0, x1, y1] = self.reach;
        if x < x0 || x > x1 || y < y0 || y > y1 {
            return None;
        }
        let k = self.curvature;
        if k.abs() < 1e-12 {
            let (c, s) = (self.heading0.cos(), self.heading0.sin());
            let (dx, dy) = (x - self.x0, y - self.y0);
            let along = dx * c + dy * s;
            (-1e-9..=self.len + 1e-9).contains(&along).then(|| (self.s0 + along, -dx * s + dy * c))
        } else {
            // Centre of the arc is to the left for k > 0.
            let r = 1.0 / k;
            let cx = self.x0 - r * self.heading0.sin();
            let cy = self.y0 + r * self.heading0.cos();
            let (dx, dy) = (x - cx, y - cy);
            let dist = dx.hypot(dy);
            // Angle of the point around the centre, relative to the start.
            let a0 = (self.y0 - cy).atan2(self.x0 - cx);
            let a = dy.atan2(dx);
            let mut da = a - a0;
            da = (da + std::f64::consts::PI).rem_euclid(2.0 * std::f64::consts::PI) - std::f64::consts::PI;
            let along = da * r;
            // Left of travel is towards the centre on a left turn, away from it on a right turn.
            let d = k.signum() * (r.abs() - dist);
            (-1e-9..=self.len + 1e-9).contains(&along).then_some((self.s0 + along, d))
        }
    }
}

/// The street's centre line, parameterised by arc length `s`.
#[derive(Clone, Debug)]
pub struct Path {
    segments: Vec<Segment>,
}

impl Path {
    pub fn length(&self) -> f64 {
        self.segments.last().map_or(0.0, |s| s.s0 + s.len)
    }

    /// Position and heading at arc length `s` (extrapolated straight beyond the ends).
    pub fn at(&self, s: f64) -> (f64, f64, f64) {
        let seg = self.segments.iter().rev().find(|g| s >= g.s0).unwrap_or(&self.segments[0]);
        if s < seg.s0 {
            let (x, y, h) = seg.at(0.0);
            let e = s - seg.s0;
            return (x + e * h.cos(), y + e * h.sin(), h);
        }
        if s > seg.s0 + seg.len {
            let (x, y, h) = seg.at(seg.len);
            let e = s - seg.s0 - seg.len;
            return (x + e * h.cos(), y + e * h.sin(), h);
        }
        seg.at(s - seg.s0)
    }

    /// The point at station `s`, lateral offset `d` (left positive).
    pub fn point(&self, s: f64, d: f64) -> (f64, f64, f64) {
        let (x, y, h) = self.at(s);
        (x - d * h.sin(), y + d * h.cos(), h)
    }

    /// Station and lateral offset of a ground point: the nearest foot on the centre line (`None`
    /// beyond 40 m from it, or in the wedge outside a bend with no perpendicular foot).
    pub fn station(&self, x: f64, y: f64) -> Option<(f64, f64)> {
        let mut best: Option<(f64, f64)> = None;
        for seg in &self.segments {
            if let Some((s, d)) = seg.station(x, y).filter(|(_, d)| d.abs() <= STATION_REACH) {
                if best.is_none_or(|b| d.abs() < b.1.abs()) {
                    best = Some((s, d));
                }
            }
        }
        best
    }
}

/// A moving or parked agent: an instance with a track along the street.
#[derive(Clone, Debug)]
pub struct Agent {
    pub instance: u32,
    pub kind: AgentKind,
    /// Station at t = 0 and speed along the street (negative: against `s`).
    pub s0: f64,
    pub speed: f64,
    pub lateral: f64,
    /// Length, width, height of its box (nuScenes `size` is [width, length, height]).
    pub size: [f64; 3],
    pub colour: [f32; 3],
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum AgentKind {
    Car,
    Pedestrian,
}

impl Agent {
    pub fn moving(&self) -> bool {
        self.speed != 0.0
    }

    /// Box centre, yaw and velocity (m/s, world) at time `t` seconds; `None` outside the street.
    pub fn state(&self, path: &Path, t: f64) -> Option<(DVec3, f64, DVec3)> {
        let s = self.s0 + self.speed * t;
        if s < -20.0 || s > path.length() + 20.0 {
            return None;
        }
        let (x, y, h) = path.point(s, self.lateral);
        let yaw = if self.speed < 0.0 { h + std::f64::consts::PI } else { h };
        let base = if self.kind == AgentKind::Pedestrian { KERB_HEIGHT } else { 0.0 };
        // Velocity of the offset point: the centre line's heading rate bends it on curves; a
        // finite difference keeps that exact enough for annotations.
        let (x2, y2, _) = path.point(s + self.speed * 1e-3, self.lateral);
        let v = DVec3::new((x2 - x) / 1e-3, (y2 - y) / 1e-3, 0.0);
        Some((DVec3::new(x, y, base + self.size[2] / 2.0), yaw, v))
    }

    /// The primitives of this agent at time `t`.
    pub fn prims(&self, path: &Path, t: f64, out: &mut Vec<Prim>) {
        let Some((c, yaw, _)) = self.state(path, t) else { return };
        let [l, w, h] = self.size;
        let fwd = DVec3::new(yaw.cos(), yaw.sin(), 0.0);
        match self.kind {
            AgentKind::Car => {
                let body_h = h * 0.55;
                let z0 = c.z - h / 2.0;
                out.push(Prim::new(
                    Shape::oriented_box(
                        DVec3::new(c.x, c.y, z0 + 0.2 + (body_h - 0.2) / 2.0),
                        [l / 2.0, w / 2.0, (body_h - 0.2) / 2.0],
                        yaw,
                    ),
                    Material::CarPaint(self.colour),
                    class::CAR,
                    self.instance,
                ));
                // Wheels as a lower, narrower box so the body floats realistically above the road.
                out.push(Prim::new(
                    Shape::oriented_box(DVec3::new(c.x, c.y, z0 + 0.1), [l / 2.0 - 0.4, w / 2.0 - 0.05, 0.1], yaw),
                    Material::Cloth([0.05, 0.05, 0.05]),
                    class::CAR,
                    self.instance,
                ));
                let cabin = c - fwd * (l * 0.08);
                out.push(Prim::new(
                    Shape::oriented_box(
                        DVec3::new(cabin.x, cabin.y, z0 + body_h + (h - body_h) / 2.0),
                        [l * 0.28, w / 2.0 - 0.08, (h - body_h) / 2.0],
                        yaw,
                    ),
                    Material::Glass,
                    class::CAR,
                    self.instance,
                ));
            }
            AgentKind::Pedestrian => {
                let z0 = c.z - h / 2.0;
                out.push(Prim::new(
                    Shape::Cylinder { x: c.x, y: c.y, r: w * 0.4, z0, z1: z0 + h * 0.86 },
                    Material::Cloth(self.colour),
                    class::PERSON,
                    self.instance,
                ));
                out.push(Prim::new(
                    Shape::Sphere { c: DVec3::new(c.x, c.y, z0 + h * 0.93), r: h * 0.07 },
                    Material::Skin,
                    class::PERSON,
                    self.instance,
                ));
            }
        }
    }
}

/// Everything that does not move, and the agents.
pub struct World {
    pub path: Path,
    pub statics: Vec<Prim>,
    pub agents: Vec<Agent>,
    /// Ego's station and speed law: s(t) = a t - (b/w)(cos(w t + p) - cos p), speed a + b sin(w t + p).
    ego: [f64; 4],
}

/// Knobs of the world generator; defaults make a believable urban street.
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct WorldParams {
    /// Seconds of driving the world must cover.
    pub duration: f64,
    pub parked_cars_per_100m: f64,
    pub moving_cars: u32,
    pub pedestrians_per_100m: f64,
}

impl Default for WorldParams {
    fn default() -> Self {
        WorldParams { duration: 20.0, parked_cars_per_100m: 5.0, moving_cars: 8, pedestrians_per_100m: 6.0 }
    }
}

impl World {
    pub fn generate(seed: u64, params: &WorldParams) -> World {
        let mut rng = Rng::new(seed);
        // Ego speed between 5 and 12 m/s.
        let a = rng.range(7.0, 9.5);
        let b = (12.0 - a).min(a - 5.0) * rng.range(0.5, 1.0);
        let w = rng.range(0.15, 0.4);
        let p = rng.range(0.0, std::f64::consts::TAU);
        let ego = [a, b, w, p];
        let drive = a * params.duration + 2.0 * b / w + 60.0;
        let margin = 120.0;

        // Centre line: straights and arcs (radius 60-150 m), starting before the ego and ending
        // well beyond where the ego stops, so the cameras never see the street's end nearby.
        let mut segments = Vec::new();
        let (mut x, mut y, mut h) = (0.0, 0.0, rng.range(-3.1, 3.1));
        let mut s0 = -margin;
        // Move the start back by `margin` so that s = 0 is at (bx, by).
        x -= margin * h.cos();
        y -= margin * h.sin();
        let mut first = true;
        let mut straight = true;
        // Alternate straights and arcs, so every drive has both within its first 40 m.
        while s0 < drive + margin {
            let (len, k) = if straight {
                (if first { margin + rng.range(10.0, 40.0) } else { rng.range(30.0, 80.0) }, 0.0)
            } else {
                let r = rng.range(60.0, 150.0);
                let sign = if rng.next_f64() < 0.5 { -1.0 } else { 1.0 };
                (rng.range(0.3, 0.8) * r, sign / r)
            };
            first = false;
            straight = !straight;
            let seg = Segment { s0, len, x0: x, y0: y, heading0: h, curvature: k, reach: [0.0; 4] };
            let (x1, y1, h1) = seg.at(len);
            segments.push(seg);
            (x, y, h) = (x1, y1, h1);
            s0 += len;
        }
        // Global coordinates: the street's surroundings start 60 m from the origin, so the map
        // mask (which covers x, y >= 0) stays small.
        let mut path = Path { segments };
        let (mut min_x, mut min_y) = (f64::INFINITY, f64::INFINITY);
        let mut s = -margin;
        while s <= path.length() - margin {
            let (px, py, _) = path.at(s);
            (min_x, min_y) = (min_x.min(px), min_y.min(py));
            s += 2.0;
        }
        for seg in &mut path.segments {
            seg.x0 += 100.0 - min_x;
            seg.y0 += 100.0 - min_y;
            let mut r = [f64::INFINITY, f64::INFINITY, f64::NEG_INFINITY, f64::NEG_INFINITY];
            let steps = (seg.len / 1.0).ceil().max(1.0) as usize;
            for i in 0..=steps {
                let (px, py, _) = seg.at(seg.len * i as f64 / steps as f64);
                r = [r[0].min(px), r[1].min(py), r[2].max(px), r[3].max(py)];
            }
            // Chords between samples 1 m apart sag well under a metre on these radii.
            seg.reach = [
                r[0] - STATION_REACH - 1.0,
                r[1] - STATION_REACH - 1.0,
                r[2] + STATION_REACH + 1.0,
                r[3] + STATION_REACH + 1.0,
            ];
        }
        let (s_min, s_max) = (-margin, path.length() - margin);
        let mut statics = Vec::new();

        // Sidewalks (raised 0.15 m; their road-side face is the kerb): one box per side of a
        // straight, short pieces along arcs. Pieces on the outside of a curve overlap a little so
        // no gap opens.
        for seg in &path.segments {
            let (a, b) = (seg.s0.max(s_min), (seg.s0 + seg.len).min(s_max));
            if b <= a {
                continue;
            }
            let piece = if seg.curvature == 0.0 { b - a } else { 2.0 };
            let stretch =
                if seg.curvature == 0.0 { 1.0 } else { 1.0 + (ROAD_HALF_WIDTH + SIDEWALK_WIDTH) * seg.curvature.abs() };
            let mut s = a;
            while s < b - 1e-9 {
                let len = piece.min(b - s);
                let (_, _, h) = path.at(s + len / 2.0);
                for side in [-1.0, 1.0] {
                    let d = side * (ROAD_HALF_WIDTH + SIDEWALK_WIDTH / 2.0);
                    let (cx, cy, _) = path.point(s + len / 2.0, d);
                    statics.push(Prim::new(
                        Shape::oriented_box(
                            DVec3::new(cx, cy, KERB_HEIGHT / 2.0),
                            [len * stretch / 2.0 + 0.01, SIDEWALK_WIDTH / 2.0, KERB_HEIGHT / 2.0],
                            h,
                        ),
                        Material::Sidewalk,
                        class::SIDEWALK,
                        0,
                    ));
                }
                s += len;
            }
        }

        // Buildings on both sides: varied width, depth, height (some far taller than the LiDAR's
        // upward field of view reaches) and setback; rejected if a corner would reach the street.
        for side in [-1.0f64, 1.0] {
            let mut s = s_min + rng.range(0.0, 5.0);
            while s < s_max {
                let width = rng.range(8.0, 24.0);
                let depth = rng.range(10.0, 18.0);
                let height = if rng.next_f64() < 0.3 { rng.range(20.0, 45.0) } else { rng.range(6.0, 18.0) };
                let setback = rng.range(0.0, 2.0);
                let facade = ROAD_HALF_WIDTH + SIDEWALK_WIDTH + setback;
                let (cx, cy, h) = path.point(s + width / 2.0, side * (facade + depth / 2.0));
                let shape =
                    Shape::oriented_box(DVec3::new(cx, cy, height / 2.0), [width / 2.0, depth / 2.0, height / 2.0], h);
                let clear = shape.footprint_corners().iter().all(|&(px, py)| {
                    path.station(px, py).is_none_or(|(_, d)| d.abs() > ROAD_HALF_WIDTH + SIDEWALK_WIDTH - 0.3)
                });
                if clear {
                    let hue = [rng.range(0.35, 0.8) as f32, rng.range(0.3, 0.7) as f32, rng.range(0.25, 0.65) as f32];
                    statics.push(Prim::new(
                        shape,
                        Material::Facade {
                            hue,
                            floor_height: rng.range(2.8, 3.6) as f32,
                            window_width: rng.range(1.0, 2.0) as f32,
                        },
                        class::BUILDING,
                        0,
                    ));
                }
                s += width + rng.range(0.0, 6.0);
            }
        }

        // Street lights at the kerb, trees between them.
        for side in [-1.0f64, 1.0] {
            let mut s = s_min + rng.range(0.0, 10.0);
            while s < s_max {
                let (px, py, _) = path.point(s, side * (ROAD_HALF_WIDTH + 0.5));
                let hgt = rng.range(6.0, 8.0);
                statics.push(Prim::new(
                    Shape::Cylinder { x: px, y: py, r: 0.09, z0: KERB_HEIGHT, z1: hgt },
                    Material::Metal,
                    class::POLE,
                    0,
                ));
                let (ax, ay, h) = path.point(s, side * (ROAD_HALF_WIDTH - 0.7));
                let (mx, my) = ((px + ax) / 2.0, (py + ay) / 2.0);
                statics.push(Prim::new(
                    Shape::oriented_box(DVec3::new(mx, my, hgt - 0.05), [0.25, 0.7, 0.06], h),
                    Material::Metal,
                    class::POLE,
                    0,
                ));
                let mut t = s + rng.range(6.0, 9.0);
                let next = s + rng.range(22.0, 30.0);
                while t < next - 5.0 {
                    if rng.next_f64() < 0.7 {
                        let (tx, ty, _) = path.point(t, side * (ROAD_HALF_WIDTH + 1.2));
                        let trunk = rng.range(2.0, 3.0);
                        let crown = rng.range(1.4, 2.4);
                        statics.push(Prim::new(
                            Shape::Cylinder { x: tx, y: ty, r: 0.15, z0: KERB_HEIGHT, z1: trunk + crown * 0.5 },
                            Material::Bark,
                            class::VEGETATION,
                            0,
                        ));
                        statics.push(Prim::new(
                            Shape::Sphere { c: DVec3::new(tx, ty, trunk + crown), r: crown },
                            Material::Foliage,
                            class::VEGETATION,
                            0,
                        ));
                    }
                    t += rng.range(7.0, 10.0);
                }
                s = next;
            }
        }

        // Agents. Instance ids start at 1 (0 = no instance).
        let mut agents = Vec::new();
        let mut next_instance = 1;
        let car_colour = |rng: &mut Rng| {
            let palette = [
                [0.8, 0.1, 0.1],
                [0.1, 0.2, 0.6],
                [0.85, 0.85, 0.85],
                [0.1, 0.1, 0.1],
                [0.5, 0.5, 0.55],
                [0.9, 0.7, 0.1],
            ];
            let c = palette[rng.below(palette.len() as u64) as usize];
            [c[0] as f32, c[1] as f32, c[2] as f32]
        };
        let parked = (params.parked_cars_per_100m * (s_max - s_min) / 100.0) as usize;
        for _ in 0..parked {
            let side = if rng.next_f64() < 0.5 { -1.0 } else { 1.0 };
            let s = rng.range(s_min + 10.0, s_max - 10.0);
            let size = [rng.range(3.9, 4.9), rng.range(1.7, 1.95), rng.range(1.4, 1.7)];
            // Keep parked cars apart.
            let lateral = side * (LANE_WIDTH + (ROAD_HALF_WIDTH - LANE_WIDTH) / 2.0);
            if agents.iter().any(|a: &Agent| a.lateral == lateral && (a.s0 - s).abs() < 6.0) {
                continue;
            }
            let colour = car_colour(&mut rng);
            agents.push(Agent {
                instance: next_instance,
                kind: AgentKind::Car,
                s0: s,
                speed: 0.0,
                lateral,
                size,
                colour,
            });
            next_instance += 1;
        }
        for i in 0..params.moving_cars {
            // Same direction as ego: start ahead and drive faster than ego ever does, so no
            // collision; oncoming lane: anywhere, any urban speed.
            let oncoming = i % 2 == 1;
            let (s0, speed, lateral) = if oncoming {
                (rng.range(20.0, drive + 40.0), -rng.range(6.0, 13.0), LANE_WIDTH / 2.0)
            } else {
                (rng.range(15.0, 80.0) + i as f64 * 10.0, rng.range(12.5, 15.0), EGO_LATERAL)
            };
            let size = [rng.range(3.9, 4.9), rng.range(1.7, 1.95), rng.range(1.4, 1.7)];
            let colour = car_colour(&mut rng);
            agents.push(Agent { instance: next_instance, kind: AgentKind::Car, s0, speed, lateral, size, colour });
            next_instance += 1;
        }
        let walkers = (params.pedestrians_per_100m * (s_max - s_min) / 100.0) as usize;
        for _ in 0..walkers {
            let side = if rng.next_f64() < 0.5 { -1.0 } else { 1.0 };
            let lateral = side * (ROAD_HALF_WIDTH + rng.range(1.8, 3.6));
            let speed = if rng.next_f64() < 0.3 {
                0.0
            } else {
                rng.range(0.9, 1.6) * if rng.next_f64() < 0.5 { -1.0 } else { 1.0 }
            };
            let size = [rng.range(0.5, 0.7), rng.range(0.5, 0.7), rng.range(1.55, 1.9)];
            let colour = [rng.range(0.1, 0.9) as f32, rng.range(0.1, 0.9) as f32, rng.range(0.1, 0.9) as f32];
            agents.push(Agent {
                instance: next_instance,
                kind: AgentKind::Pedestrian,
                s0: rng.range(s_min + 10.0, s_max - 10.0),
                speed,
                lateral,
                size,
                colour,
            });
            next_instance += 1;
        }
        World { path, statics, agents, ego }
    }

    /// Ego station at time `t` (seconds from the scene start).
    pub fn ego_station(&self, t: f64) -> f64 {
        let [a, b, w, p] = self.ego;
        a * t - (b / w) * ((w * t + p).cos() - p.cos())
    }

    pub fn ego_speed(&self, t: f64) -> f64 {
        let [a, b, w, p] = self.ego;
        a + b * (w * t + p).sin()
    }

    /// Ego pose at `t`: position of the rear axle on the ground, and yaw.
    pub fn ego_pose(&self, t: f64) -> (DVec3, f64) {
        let (x, y, h) = self.path.point(self.ego_station(t), EGO_LATERAL);
        (DVec3::new(x, y, 0.0), h)
    }

    /// Moving things at time `t`.
    pub fn dynamic_prims(&self, t: f64) -> Vec<Prim> {
        let mut out = Vec::new();
        for a in &self.agents {
            a.prims(&self.path, t, &mut out);
        }
        out
    }
}

/// The ego vehicle's body in its own frame (rear axle origin, x forward): a small hatchback, so
/// the lowest LiDAR beams graze it as they do on the real car.
pub fn ego_body() -> Vec<Prim> {
    vec![
        Prim::new(
            Shape::oriented_box(DVec3::new(1.2, 0.0, 0.6), [2.05, 0.87, 0.45], 0.0),
            Material::EgoBody,
            class::EGO,
            0,
        ),
        Prim::new(
            Shape::oriented_box(DVec3::new(1.2, 0.0, 1.25), [0.9, 0.7, 0.2], 0.0),
            Material::EgoBody,
            class::EGO,
            0,
        ),
    ]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stations_invert_points_along_the_whole_street() {
        for seed in 0..20 {
            let w = World::generate(seed, &WorldParams::default());
            let mut s = -110.0;
            while s < w.path.length() - 130.0 {
                for d in [-9.0, -1.75, 0.0, 4.0, 9.0] {
                    let (x, y, _) = w.path.point(s, d);
                    let (s2, d2) =
                        w.path.station(x, y).unwrap_or_else(|| panic!("seed {seed}: no station at s {s} d {d}"));
                    assert!((s2 - s).abs() < 1e-6 && (d2 - d).abs() < 1e-6, "seed {seed}: ({s}, {d}) -> ({s2}, {d2})");
                }
                s += 3.7;
            }
        }
    }

    #[test]
    fn ego_speed_stays_in_the_urban_range_and_the_world_is_deterministic() {
        for seed in 0..50 {
            let w = World::generate(seed, &WorldParams::default());
            for i in 0..=400 {
                let t = i as f64 * 0.05;
                let v = w.ego_speed(t);
                assert!((5.0..=12.0).contains(&v), "seed {seed} t {t}: {v} m/s");
                // Station is the integral of speed.
                let ds = (w.ego_station(t + 1e-3) - w.ego_station(t)) / 1e-3;
                assert!((ds - v).abs() < 1e-3);
            }
        }
        let (a, b) = (World::generate(9, &WorldParams::default()), World::generate(9, &WorldParams::default()));
        assert_eq!(format!("{:?}", a.statics), format!("{:?}", b.statics));
        assert_ne!(format!("{:?}", a.statics), format!("{:?}", World::generate(10, &WorldParams::default()).statics));
    }

    #[test]
    fn the_street_has_everything_the_issue_asks_for() {
        let w = World::generate(3, &WorldParams::default());
        let count = |c: u8| w.statics.iter().filter(|p| p.class == c).count();
        assert!(count(class::SIDEWALK) > 20);
        assert!(count(class::BUILDING) > 20);
        assert!(count(class::POLE) > 10 && count(class::VEGETATION) > 10);
        // Some buildings are far taller than the LiDAR's top beam reaches nearby (+10.67 degrees
        // from 1.84 m gives under 6 m at 20 m).
        let tall = w.statics.iter().filter(|p| p.class == class::BUILDING && p.shape.bounds().1.z > 20.0).count();
        assert!(tall > 3, "{tall}");
        let curved = w.path.segments.iter().filter(|s| s.curvature != 0.0).count();
        let cars = w.agents.iter().filter(|a| a.kind == AgentKind::Car);
        assert!(cars.clone().any(|a| a.moving()) && cars.clone().any(|a| !a.moving()));
        assert!(w.agents.iter().any(|a| a.kind == AgentKind::Pedestrian && a.moving()));
        assert!(curved >= 1);
        assert!(w.path.segments.iter().any(|s| s.curvature != 0.0 && s.s0 < 40.0));
        // No building reaches into the street or the sidewalk.
        for p in w.statics.iter().filter(|p| p.class == class::BUILDING) {
            for (x, y) in p.shape.footprint_corners() {
                if let Some((_, d)) = w.path.station(x, y) {
                    assert!(d.abs() > ROAD_HALF_WIDTH + SIDEWALK_WIDTH - 0.5, "corner at d = {d}");
                }
            }
        }
    }
}
