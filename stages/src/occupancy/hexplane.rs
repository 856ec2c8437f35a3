//! HexPlanes (DynamicCity): a window of T occupancy frames (X x Y x Z voxels, C classes) as six
//! feature planes xy (X x Y), xz (X x Z), yz (Y x Z), tx (T x X), ty (T x Y), tz (T x Z), each
//! with C channels; their padded rollout into one 2D map, its inverse and mask, exactly as the
//! released `dynamic_city/utils/hexplane_utils.py` lays them out (`hexplane_to_rollout`,
//! `rollout_to_hexplane`, `get_rollout_mask`); and the Expansion & Squeeze product the decoder
//! forms before its learned convolutions (every plane broadcast to T x X x Y x Z and multiplied).
//!
//! The rollout is C x (X+T+Z) x (Y+Z+T):
//!
//! ```text
//!                cols 0..Y        Y..Y+Z      Y+Z..Y+Z+T
//! rows 0..X      xy               xz          tx transposed
//! rows X..X+T    ty               tz          zeros (T x T)
//! rows X+T..     yz transposed    zeros       zeros
//! ```
//!
//! `HexPlaneBaseline` is a baseline, not DynamicCity's VAE: its encoder takes each plane as the
//! mean of the window's one-hot volume over the two other axes, its decoder the class that
//! maximises the six planes' product at each voxel. It makes the chain from occupancy to rollout
//! files run without a GPU, and its reconstruction mIoU is the floor a learned VAE must clear.
//! The VAE itself runs as a worker (`worker`, op `encode_hexplane`: the window's classes in, the
//! rollout out; docs/workers.md); `workers/hexplane_means.py` is a numpy reference that computes
//! the baseline's planes and rolls them out as the released code does.

use dist4d_runtime::Made;
use super::classes::{FREE, NAMES};
use super::eval::scores;
use crate::stage::Stage;
use anyhow::{ensure, Result};
use dist4d_graph::{ParamChecks, ParamProblem, Validate};
use dist4d_runtime::TaskContext;
use dist4d_types::artifact::{File, OccupancyGrid};
use dist4d_types::formats::{npy_f32, npy_u8, npz};
use serde::{Deserialize, Serialize};
use serde_json::json;

/// The six planes, each channel-major (`[c][a][b]` for plane ab).
#[derive(Clone, Debug, PartialEq)]
pub struct HexPlane {
    /// C, T, X, Y, Z.
    pub c: usize,
    pub t: usize,
    pub x: usize,
    pub y: usize,
    pub z: usize,
    pub xy: Vec<f32>,
    pub xz: Vec<f32>,
    pub yz: Vec<f32>,
    pub tx: Vec<f32>,
    pub ty: Vec<f32>,
    pub tz: Vec<f32>,
}

impl HexPlane {
    pub fn zeros(c: usize, t: usize, x: usize, y: usize, z: usize) -> HexPlane {
        HexPlane {
            c,
            t,
            x,
            y,
            z,
            xy: vec![0.0; c * x * y],
            xz: vec![0.0; c * x * z],
            yz: vec![0.0; c * y * z],
            tx: vec![0.0; c * t * x],
            ty: vec![0.0; c * t * y],
            tz: vec![0.0; c * t * z],
        }
    }

    /// The rollout's height and width: X+T+Z, Y+Z+T.
    pub fn rollout_size(&self) -> (usize, usize) {
        (self.x + self.t + self.z, self.y + self.z + self.t)
    }
}

/// The padded rollout, C x H x W (see the module doc).
pub fn rollout(p: &HexPlane) -> Vec<f32> {
    let (h, w) = p.rollout_size();
    let (x, y, z, t) = (p.x, p.y, p.z, p.t);
    let mut r = vec![0.0f32; p.c * h * w];
    for c in 0..p.c {
        let at = |row: usize, col: usize| (c * h + row) * w + col;
        for i in 0..x {
            for j in 0..y {
                r[at(i, j)] = p.xy[(c * x + i) * y + j];
            }
            for k in 0..z {
                r[at(i, y + k)] = p.xz[(c * x + i) * z + k];
            }
            for s in 0..t {
                r[at(i, y + z + s)] = p.tx[(c * t + s) * x + i];
            }
        }
        for s in 0..t {
            for j in 0..y {
                r[at(x + s, j)] = p.ty[(c * t + s) * y + j];
            }
            for k in 0..z {
                r[at(x + s, y + k)] = p.tz[(c * t + s) * z + k];
            }
        }
        for k in 0..z {
            for j in 0..y {
                r[at(x + t + k, j)] = p.yz[(c * y + j) * z + k];
            }
        }
    }
    r
}

/// The planes of a rollout made by [`rollout`] (`rollout_to_hexplane`).
pub fn unroll(r: &[f32], c: usize, t: usize, x: usize, y: usize, z: usize) -> Result<HexPlane> {
    let mut p = HexPlane::zeros(c, t, x, y, z);
    let (h, w) = p.rollout_size();
    ensure!(r.len() == c * h * w, "a rollout of {} values, not {c} x {h} x {w}", r.len());
    for ch in 0..c {
        let at = |row: usize, col: usize| (ch * h + row) * w + col;
        for i in 0..x {
            for j in 0..y {
                p.xy[(ch * x + i) * y + j] = r[at(i, j)];
            }
            for k in 0..z {
                p.xz[(ch * x + i) * z + k] = r[at(i, y + k)];
            }
            for s in 0..t {
                p.tx[(ch * t + s) * x + i] = r[at(i, y + z + s)];
            }
        }
        for s in 0..t {
            for j in 0..y {
                p.ty[(ch * t + s) * y + j] = r[at(x + s, j)];
            }
            for k in 0..z {
                p.tz[(ch * t + s) * z + k] = r[at(x + s, y + k)];
            }
        }
        for k in 0..z {
            for j in 0..y {
                p.yz[(ch * y + j) * z + k] = r[at(x + t + k, j)];
            }
        }
    }
    Ok(p)
}

/// `get_rollout_mask`: 1 where a plane lies in the rollout, 0 in the padding (H x W).
pub fn rollout_mask(t: usize, x: usize, y: usize, z: usize) -> Vec<u8> {
    let mut ones = HexPlane::zeros(1, t, x, y, z);
    for plane in [&mut ones.xy, &mut ones.xz, &mut ones.yz, &mut ones.tx, &mut ones.ty, &mut ones.tz] {
        plane.iter_mut().for_each(|v| *v = 1.0);
    }
    rollout(&ones).iter().map(|&v| (v != 0.0) as u8).collect()
}

/// The Expansion & Squeeze product at one voxel and channel: the six planes broadcast to the
/// volume and multiplied.
pub fn ess_product(p: &HexPlane, c: usize, s: usize, i: usize, j: usize, k: usize) -> f32 {
    let (t, x, y, z) = (p.t, p.x, p.y, p.z);
    p.xy[(c * x + i) * y + j]
        * p.xz[(c * x + i) * z + k]
        * p.yz[(c * y + j) * z + k]
        * p.tx[(c * t + s) * x + i]
        * p.ty[(c * t + s) * y + j]
        * p.tz[(c * t + s) * z + k]
}

/// The baseline encoder: each plane the mean of the window's one-hot volume over its two other
/// axes (`frames`: T semantic volumes of X x Y x Z, classes < `c`).
pub fn encode_baseline(frames: &[&[u8]], c: usize, x: usize, y: usize, z: usize) -> HexPlane {
    let t = frames.len();
    let mut p = HexPlane::zeros(c, t, x, y, z);
    for (s, f) in frames.iter().enumerate() {
        for i in 0..x {
            for j in 0..y {
                for k in 0..z {
                    let class = (f[(i * y + j) * z + k] as usize).min(c - 1);
                    p.xy[(class * x + i) * y + j] += 1.0;
                    p.xz[(class * x + i) * z + k] += 1.0;
                    p.yz[(class * y + j) * z + k] += 1.0;
                    p.tx[(class * t + s) * x + i] += 1.0;
                    p.ty[(class * t + s) * y + j] += 1.0;
                    p.tz[(class * t + s) * z + k] += 1.0;
                }
            }
        }
    }
    let scale = |v: &mut Vec<f32>, n: usize| v.iter_mut().for_each(|a| *a /= n as f32);
    scale(&mut p.xy, t * z);
    scale(&mut p.xz, t * y);
    scale(&mut p.yz, t * x);
    scale(&mut p.tx, y * z);
    scale(&mut p.ty, x * z);
    scale(&mut p.tz, x * y);
    p
}

/// The baseline decoder: at every voxel of every frame, the class with the largest ESS product
/// of its planes each divided by the class's share of the window, times that share (reading the
/// six planes as independent marginals). Without the division the free air, ~90% of every plane,
/// wins every voxel (mIoU 0 on the synthetic street).
pub fn decode_baseline(p: &HexPlane) -> Vec<Vec<u8>> {
    // A class's share of the window: the mean of any of its planes.
    let prior: Vec<f32> = (0..p.c)
        .map(|c| p.xy[c * p.x * p.y..(c + 1) * p.x * p.y].iter().sum::<f32>() / (p.x * p.y) as f32)
        .collect();
    (0..p.t)
        .map(|s| {
            let mut out = vec![0u8; p.x * p.y * p.z];
            for i in 0..p.x {
                for j in 0..p.y {
                    for k in 0..p.z {
                        let (mut best, mut value) = (0usize, f32::NEG_INFINITY);
                        for (c, &share) in prior.iter().enumerate() {
                            if share <= 0.0 {
                                continue;
                            }
                            let v = ess_product(p, c, s, i, j, k) / share.powi(5);
                            if v > value {
                                (best, value) = (c, v);
                            }
                        }
                        out[(i * p.y + j) * p.z + k] = best as u8;
                    }
                }
            }
            out
        })
        .collect()
}

#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// Frames per window (T); wire `grids` with `Window(.., frame, 0, frames - 1)`.
    pub frames: u32,
    /// A learned HexPlane encoder (DynamicCity's VAE) as an external worker in place of the
    /// baseline: op `encode_hexplane` (docs/workers.md). Its name, version and weights enter the
    /// task keys. Its rollout has no reconstruction scores (the decoder is its model's).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub worker: Option<crate::model_worker::WorkerSpec>,
}

impl Default for Params {
    fn default() -> Self {
        Params { frames: 16, worker: None }
    }
}

impl Validate for Params {
    fn validate(&self) -> Vec<ParamProblem> {
        let mut c = ParamChecks::new();
        c.count("frames", self.frames as u64, 1, 1024);
        if let Some(w) = &self.worker {
            w.check(&mut c);
        }
        c.done()
    }
}

crate::inputs! {
    pub struct Inputs {
        /// the window's occupancy (`Window("occupancy.grid", frame, 0, 15)`)
        grids: Many<OccupancyGrid>,
    }
}

crate::outputs! {
    pub struct Outputs {
        /// rollout.npz: `rollout` (C, X+T+Z, Y+Z+T) float32, C = the 18 Occ3D classes, its
        /// `mask` (X+T+Z, Y+Z+T) uint8, and `hex_txyz` (T, X, Y, Z) as 4 float32
        rollout: One<File>,
        /// JSON: the baseline's reconstruction scores against the window (camera-visible voxels)
        scores: One<File>,
    }
}

pub struct HexPlaneBaseline(Params, crate::model_worker::ModelWorker);

impl Stage for HexPlaneBaseline {
    const KIND: &'static str = "HexPlaneBaseline";
    // 2: the decoder divides each class's planes by its share of the window.
    // 3: the rollout file names its HexPlane's sizes (`hex_txyz`).
    const VERSION: u32 = 3;
    const SUMMARY: &'static str =
        "baseline HexPlane of a window of occupancy (per-plane means of the one-hot volume) as DynamicCity's padded rollout, with its ESS-argmax reconstruction scores";
    const GRAINS: &'static [&'static str] = &["frame"];
    type Params = Params;
    type Inputs = Inputs;
    type Outputs = Outputs;

    fn new(params: Params) -> Result<Self> {
        let worker = crate::model_worker::ModelWorker::new(params.worker.clone());
        Ok(HexPlaneBaseline(params, worker))
    }
    fn identity(&self) -> Result<Option<String>> {
        self.1.identity()
    }
    fn resource(&self) -> Option<dist4d_runtime::Resource> {
        self.1.resource()
    }

    fn run(&self, ctx: &TaskContext, i: Inputs) -> Result<Made<Outputs>> {
        let t = self.0.frames as usize;
        let grids = crate::or_nothing!(super::window("grids", &i.grids, t)?);
        let dims = grids[0].dims;
        ensure!(grids.iter().all(|g| g.dims == dims), "the window's grids differ in size");
        let [x, y, z] = dims.map(|d| d as usize);
        let c = NAMES.len();
        let frames: Vec<&[u8]> = grids.iter().map(|g| g.semantics.as_slice()).collect();
        if self.1.is_set() {
            return encode_by_worker(ctx, &self.1, &frames, [t, x, y, z]).map(Made::from);
        }
        let planes = encode_baseline(&frames, c, x, y, z);
        let (h, w) = planes.rollout_size();
        let file = rollout_file(&[c, h, w], &rollout(&planes), [t, x, y, z]);
        // The reconstruction, scored as occupancy is (the camera-visible voxels of each frame).
        let decoded = decode_baseline(&planes);
        let mut m = vec![vec![0u64; c]; c];
        for (g, d) in grids.iter().zip(&decoded) {
            for v in 0..g.voxels() {
                if g.mask_camera[v] != 0 {
                    m[g.semantics[v] as usize % c][d[v] as usize % c] += 1;
                }
            }
        }
        let (iou, miou, geometry) = scores(&m);
        let per_class: serde_json::Map<String, serde_json::Value> = NAMES
            .iter()
            .zip(&iou)
            .filter_map(|(n, v)| v.map(|v| (n.to_string(), json!(v))))
            .collect();
        let scores = json!({
            "frames": t,
            "rollout_size": [c, h, w],
            "miou": miou,
            "geometry_iou": geometry,
            "iou": per_class,
            "free_class": FREE,
        });
        Ok(Outputs { rollout: File(file), scores: File(serde_json::to_vec_pretty(&scores)?) }.into())
    }
}

/// The rollout from the stage's worker (op `encode_hexplane`: input `semantics`, NPY uint8
/// (T, X, Y, Z), the Occ3D classes, 17 = free; output `rollout`, NPY float32 (C, H, W), which the
/// engine checks to be finite and three-dimensional, and `hexplane`, a JSON file with the
/// HexPlane's `[T, X, Y, Z]` (`hex_txyz`), from which the mask is made and the rollout's H and W
/// are checked: H = X + T + Z, W = Y + Z + T).
fn encode_by_worker(
    ctx: &TaskContext,
    worker: &crate::model_worker::ModelWorker,
    frames: &[&[u8]],
    [t, x, y, z]: [usize; 4],
) -> Result<Outputs> {
    let ex = crate::model_worker::Exchange::new()?;
    let volume: Vec<u8> = frames.concat();
    let inputs = vec![ex.put("semantics", "semantics.npy", &npy_u8(&[t, x, y, z], &volume))?];
    let outputs = worker.call(ctx, &ex, "encode_hexplane", inputs, json!({ "classes": NAMES, "free": FREE }))?;
    let (shape, txyz, file) = worker_rollout(&ex, &outputs)?;
    let scores = json!({ "frames": t, "rollout_size": shape, "hex_txyz": txyz, "encoder": "worker" });
    Ok(Outputs { rollout: File(file), scores: File(serde_json::to_vec_pretty(&scores)?) })
}

/// A rollout file as the HexPlane stages write it: `rollout` (C, H, W) float32, its padding
/// `mask` and the planes' sizes `hex_txyz` (T, X, Y, Z) as 4 float32.
pub fn rollout_file(shape: &[usize], rollout: &[f32], [t, x, y, z]: [usize; 4]) -> Vec<u8> {
    npz(&[
        ("rollout", npy_f32(shape, rollout)),
        ("mask", npy_u8(&[x + t + z, y + z + t], &rollout_mask(t, x, y, z))),
        ("hex_txyz", npy_f32(&[4], &[t as f32, x as f32, y as f32, z as f32])),
    ])
}

/// The rollout a HexPlane worker returned (`rollout`, NPY float32, and `hexplane`, JSON with its
/// `hex_txyz`), checked: three-dimensional, shaped (C, X+T+Z, Y+Z+T) as its sizes say, finite.
/// Its shape, sizes and [`rollout_file`].
pub fn worker_rollout(
    ex: &crate::model_worker::Exchange,
    outputs: &[dist4d_runtime::worker::FileRef],
) -> Result<(Vec<usize>, [usize; 4], Vec<u8>)> {
    use anyhow::Context;
    let (shape, rollout) = dist4d_types::formats::read_npy_f32(&ex.get(outputs, "rollout")?)
        .context("the worker's `rollout` (float32 NPY)")?;
    let txyz: [usize; 4] = serde_json::from_slice::<serde_json::Value>(&ex.get(outputs, "hexplane")?)
        .ok()
        .and_then(|v| serde_json::from_value(v["hex_txyz"].clone()).ok())
        .context("the worker's `hexplane` JSON names no `hex_txyz` [T, X, Y, Z]")?;
    let [t, x, y, z] = txyz;
    ensure!(
        shape.len() == 3 && shape[1] == x + t + z && shape[2] == y + z + t,
        "the worker's rollout has shape {shape:?}, not (C, X+T+Z, Y+Z+T) = (C, {}, {}) for hex_txyz {txyz:?}",
        x + t + z,
        y + z + t
    );
    if let Some(bad) = rollout.iter().position(|v| !v.is_finite()) {
        anyhow::bail!("the worker's rollout holds {} at {bad}", rollout[bad]);
    }
    let file = rollout_file(&shape, &rollout, txyz);
    Ok((shape, txyz, file))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Planes whose every value says where it is: plane, channel, both coordinates.
    fn distinct(c: usize, t: usize, x: usize, y: usize, z: usize) -> HexPlane {
        let mut p = HexPlane::zeros(c, t, x, y, z);
        let fill = |v: &mut Vec<f32>, plane: usize, a: usize, b: usize| {
            for ch in 0..c {
                for i in 0..a {
                    for j in 0..b {
                        v[(ch * a + i) * b + j] = (plane * 1_000_000 + ch * 10_000 + i * 100 + j) as f32;
                    }
                }
            }
        };
        fill(&mut p.xy, 1, x, y);
        fill(&mut p.xz, 2, x, z);
        fill(&mut p.yz, 3, y, z);
        fill(&mut p.tx, 4, t, x);
        fill(&mut p.ty, 5, t, y);
        fill(&mut p.tz, 6, t, z);
        p
    }

    #[test]
    fn the_rollout_puts_every_plane_where_the_released_layout_does_and_unrolls_exactly() {
        let (c, t, x, y, z) = (2, 3, 5, 4, 2);
        let p = distinct(c, t, x, y, z);
        let r = rollout(&p);
        let (h, w) = p.rollout_size();
        assert_eq!((h, w), (x + t + z, y + z + t));
        let at = |ch: usize, row: usize, col: usize| r[(ch * h + row) * w + col];
        let v = |plane: usize, ch: usize, i: usize, j: usize| (plane * 1_000_000 + ch * 10_000 + i * 100 + j) as f32;
        for ch in 0..c {
            for row in 0..h {
                for col in 0..w {
                    let want = if row < x && col < y {
                        v(1, ch, row, col)
                    } else if row < x && col < y + z {
                        v(2, ch, row, col - y)
                    } else if row < x {
                        v(4, ch, col - y - z, row) // tx transposed
                    } else if row < x + t && col < y {
                        v(5, ch, row - x, col)
                    } else if row < x + t && col < y + z {
                        v(6, ch, row - x, col - y)
                    } else if row >= x + t && col < y {
                        v(3, ch, col, row - x - t) // yz transposed
                    } else {
                        0.0
                    };
                    assert_eq!(at(ch, row, col), want, "channel {ch}, row {row}, col {col}");
                }
            }
        }
        assert_eq!(unroll(&r, c, t, x, y, z).unwrap(), p);
        let mask = rollout_mask(t, x, y, z);
        for row in 0..h {
            for col in 0..w {
                let padding = (row >= x && col >= y + z) || (row >= x + t && col >= y);
                assert_eq!(mask[row * w + col], !padding as u8, "row {row}, col {col}");
            }
        }
    }

    #[test]
    fn the_baseline_reconstructs_a_floor_free_air_and_a_lone_column() {
        // Two frames of a 4 x 3 x 2 volume: a floor of class 1 at z = 0, free (2) above, and one
        // column of class 0 that only exists in frame 1.
        let (x, y, z) = (4, 3, 2);
        let frame = |col: bool| -> Vec<u8> {
            let mut v = vec![0u8; x * y * z];
            for i in 0..x {
                for j in 0..y {
                    v[(i * y + j) * z] = 1;
                    v[(i * y + j) * z + 1] = if col && i == 2 && j == 1 { 0 } else { 2 };
                }
            }
            v
        };
        let (a, b) = (frame(false), frame(true));
        let p = encode_baseline(&[&a, &b], 3, x, y, z);
        assert!((p.xy.iter().sum::<f32>() - (x * y) as f32).abs() < 1e-4, "each xy cell's classes sum to 1");
        let d = decode_baseline(&p);
        assert_eq!(d[0], a, "the floor and the free air are explained by the planes");
        // The lone column too: divided by its class's share, its planes outweigh the free air's.
        assert_eq!(d[1], b);
    }
}
