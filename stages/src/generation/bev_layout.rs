//! `BevLayout`: the bird's-eye-view layout a controllable generator (DiST-T, like MagicDrive or
//! Panacea before it) is conditioned on: the road from the dataset's map and the 3D boxes of one
//! time, drawn around the ego vehicle of one camera item (its pose and boxes, e.g. a future step's
//! through `Offset("dataset.image_info", frame, variant)`).
//!
//! The image is ego-centric: forward up, left to the left, `size` x `size` pixels over `range`
//! metres each way. Colours: drivable surface grey (80), off the map black; boxes filled by
//! category (vehicles blue, pedestrians red, cycles orange, anything else yellow); the ego white.
//! A dataset without a map (DGP, or a nuScenes log whose map file is absent) gives the boxes on
//! black.
//!
//! The map is nuScenes' map mask (`map.json`, the devkit's `MapMask`): an 8-bit PNG, drivable
//! where > 0, `map_resolution` metres per pixel, pixel (col, row) at world (x, y) = (col * res,
//! (height - row) * res).

use dist4d_runtime::Made;
use crate::stage::Stage;
use anyhow::{ensure, Context, Result};
use dist4d_graph::{ParamChecks, ParamProblem, Validate};
use dist4d_runtime::TaskContext;
use dist4d_types::artifact::{Box3D, File, Image, ImageInfo};
use dist4d_types::geometry::Se3;
use glam::DVec3;
use serde::{Deserialize, Serialize};
use std::sync::{Arc, Mutex};

#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// The layout's width and height (px).
    pub size: u32,
    /// It covers this many metres ahead, behind, left and right of the ego.
    pub range: f64,
    /// Metres per pixel of the dataset's map mask (nuScenes: 0.1).
    pub map_resolution: f64,
}

impl Default for Params {
    fn default() -> Self {
        Params { size: 256, range: 51.2, map_resolution: 0.1 }
    }
}

impl Validate for Params {
    fn validate(&self) -> Vec<ParamProblem> {
        let mut c = ParamChecks::new();
        c.count("size", self.size as u64, 16, 4096).above("range", self.range, 0.0, 1e4).above(
            "map_resolution",
            self.map_resolution,
            0.0,
            100.0,
        );
        c.done()
    }
}

crate::inputs! {
    pub struct Inputs {
        /// the scene's map mask (`dataset.map`; empty: no map)
        map: One<File>,
        /// the ego pose and boxes to draw (a camera item's `ImageInfo`)
        info: One<ImageInfo>,
    }
}

crate::outputs! {
    pub struct Outputs {
        /// the layout (RGB8, `size` x `size`)
        layout: One<Image>,
    }
}

/// A decoded map mask, kept for the next task of the same scene (decoding a city's map takes
/// seconds).
struct MapMask {
    digest: blake3::Hash,
    width: u32,
    height: u32,
    pixels: Vec<u8>,
}

pub struct BevLayout {
    params: Params,
    last_map: Mutex<Option<Arc<MapMask>>>,
}

impl Stage for BevLayout {
    const KIND: &'static str = "BevLayout";
    const VERSION: u32 = 1;
    const SUMMARY: &'static str =
        "the bird's-eye-view layout around an ego pose: road from the dataset's map, boxes by category";
    const GRAINS: &'static [&'static str] = &["variant", "camera"];
    type Params = Params;
    type Inputs = Inputs;
    type Outputs = Outputs;

    fn new(params: Params) -> Result<Self> {
        Ok(BevLayout { params, last_map: Mutex::new(None) })
    }

    fn run(&self, _: &TaskContext, i: Inputs) -> Result<Made<Outputs>> {
        ensure!(i.info.missing.is_none(), "the item has no image, so no pose: {}", i.info.missing.clone().unwrap_or_default());
        let map = if i.map.0.is_empty() { None } else { Some(self.map(&i.map.0)?) };
        Ok(Outputs { layout: draw(&self.params, map.as_deref(), &i.info.ego_to_world, &i.info.boxes.boxes) }.into())
    }
}

impl BevLayout {
    fn map(&self, png: &[u8]) -> Result<Arc<MapMask>> {
        let digest = blake3::hash(png);
        let mut last = self.last_map.lock().map_err(|_| anyhow::anyhow!("map cache poisoned"))?;
        if let Some(m) = last.as_ref().filter(|m| m.digest == digest) {
            return Ok(m.clone());
        }
        let mut reader = image::ImageReader::new(std::io::Cursor::new(png))
            .with_guessed_format()
            .context("reading the map mask")?;
        // A city's mask at 0.1 m is up to ~30 000 px a side: more than the decoder's default.
        let mut limits = image::Limits::default();
        limits.max_alloc = Some(2 << 30);
        reader.limits(limits);
        let gray = reader.decode().context("decoding the map mask (an 8-bit PNG)")?.into_luma8();
        let m = Arc::new(MapMask { digest, width: gray.width(), height: gray.height(), pixels: gray.into_raw() });
        *last = Some(m.clone());
        Ok(m)
    }
}

const DRIVABLE: [u8; 3] = [80, 80, 80];
const EGO: [u8; 3] = [255, 255, 255];

/// A box's colour by its category (nuScenes `vehicle.car`, DGP `Car`, ...).
fn colour(b: &Box3D) -> [u8; 3] {
    let c = b.category.to_ascii_lowercase();
    if c.contains("bicycle") || c.contains("motorcycle") || c.contains("cycle") {
        [255, 160, 0]
    } else if c.starts_with("vehicle") || ["car", "truck", "bus", "van", "trailer"].iter().any(|v| c.contains(v)) {
        [0, 120, 255]
    } else if c.contains("pedestrian") || c.starts_with("human") || c.contains("person") {
        [255, 40, 40]
    } else {
        [255, 220, 0]
    }
}

/// The layout of the module doc.
fn draw(p: &Params, map: Option<&MapMask>, ego_to_world: &Se3, boxes: &[Box3D]) -> Image {
    let n = p.size as usize;
    let res = 2.0 * p.range / n as f64;
    let ego_point = |u: usize, v: usize| DVec3::new((n as f64 / 2.0 - v as f64 - 0.5) * res, (n as f64 / 2.0 - u as f64 - 0.5) * res, 0.0);
    let mut rgb = vec![0u8; n * n * 3];
    if let Some(m) = map {
        for v in 0..n {
            for u in 0..n {
                let w = ego_to_world.apply(ego_point(u, v));
                let col = (w.x / p.map_resolution).floor();
                let row = (m.height as f64 - w.y / p.map_resolution).floor();
                if col >= 0.0 && row >= 0.0 && col < m.width as f64 && row < m.height as f64 {
                    if m.pixels[row as usize * m.width as usize + col as usize] > 0 {
                        rgb[3 * (v * n + u)..3 * (v * n + u) + 3].copy_from_slice(&DRIVABLE);
                    }
                }
            }
        }
    }
    // Boxes: their footprint (x along the length, y across), in the ego frame.
    let world_to_ego = ego_to_world.inverse();
    for b in boxes {
        let to_box = world_to_ego.then_from(&Se3::from_wxyz_t(b.rotation, b.center)).inverse();
        let (hl, hw) = (b.size[1] / 2.0, b.size[0] / 2.0);
        let centre = world_to_ego.apply(DVec3::from_array(b.center));
        let reach = (hl * hl + hw * hw).sqrt();
        // Only the pixels around the box.
        let (uc, vc) = (n as f64 / 2.0 - centre.y / res, n as f64 / 2.0 - centre.x / res);
        let r = reach / res + 1.0;
        let (u0, u1) = ((uc - r).floor().max(0.0) as usize, ((uc + r).ceil().max(0.0) as usize).min(n));
        let (v0, v1) = ((vc - r).floor().max(0.0) as usize, ((vc + r).ceil().max(0.0) as usize).min(n));
        let c = colour(b);
        for v in v0..v1 {
            for u in u0..u1 {
                let mut q = ego_point(u, v);
                q.z = centre.z;
                let l = to_box.apply(q);
                if l.x.abs() <= hl && l.y.abs() <= hw {
                    rgb[3 * (v * n + u)..3 * (v * n + u) + 3].copy_from_slice(&c);
                }
            }
        }
    }
    // The ego: a 4.5 m x 1.9 m car at the centre.
    for v in 0..n {
        for u in 0..n {
            let q = ego_point(u, v);
            if q.x.abs() <= 2.25 && q.y.abs() <= 0.95 {
                rgb[3 * (v * n + u)..3 * (v * n + u) + 3].copy_from_slice(&EGO);
            }
        }
    }
    Image { width: p.size, height: p.size, rgb }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn car(x: f64, y: f64) -> Box3D {
        Box3D {
            center: [x, y, 1.0],
            size: [2.0, 4.0, 1.5],
            rotation: [1.0, 0.0, 0.0, 0.0],
            velocity: [0.0; 3],
            instance: "a".into(),
            category: "vehicle.car".into(),
            attributes: Vec::new(),
            num_lidar_pts: 0,
            interpolated: false,
            extrapolated: false,
        }
    }

    #[test]
    fn the_road_and_a_car_ahead_are_drawn_around_the_ego_facing_up() {
        // A map 200 m x 200 m at 1 m per pixel whose drivable part is the strip 95 <= y < 105.
        let (w, h) = (200u32, 200u32);
        let pixels =
            (0..h).flat_map(|row| (0..w).map(move |_| if (95..105).contains(&(h - row)) { 255 } else { 0 })).collect();
        let map = MapMask { digest: blake3::hash(b""), width: w, height: h, pixels };
        let p = Params { size: 100, range: 50.0, map_resolution: 1.0 };
        // The ego at (100, 100) facing +x (east), a car 20 m ahead.
        let ego = Se3::from_yaw(0.0, DVec3::new(100.0, 100.0, 0.0));
        let img = draw(&p, Some(&map), &ego, &[car(120.0, 100.0)]);
        let at = |u: u32, v: u32| &img.rgb[3 * (v * 100 + u) as usize..3 * (v * 100 + u) as usize + 3];
        assert_eq!(at(50, 50), EGO);
        assert_eq!(at(50, 30), [0, 120, 255], "the car 20 m ahead is 20 px up");
        assert_eq!(at(50, 10), DRIVABLE, "the road runs along the ego's heading: up");
        assert_eq!(at(53, 80), DRIVABLE, "30 m behind, 3 m to the right");
        assert_eq!(at(10, 50), [0, 0, 0], "the road is 10 m wide: 40 m to the left is off it");
        let none = draw(&p, None, &ego, &[]);
        assert_eq!(none.rgb.iter().filter(|&&c| c == 80).count(), 0);
    }
}
