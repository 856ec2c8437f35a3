//! CompleteDepth's built-in completer on NPY files, scored against a ground truth: the harness of
//! `bench/completion_oracle.py`, which asks what the completion reaches when every prompt sample
//! is exact (docs/BENCHMARKS.md, "What the completion can reach").
//!
//! ```sh
//! cargo run --release -p dist4d-stages --example complete_npy -- LIST [field=value ...]
//! ```
//!
//! Each line of LIST names five NPY files (float32, C order): `rgb` (HxWx3, 0-255), `prompt` (HxW
//! metric depth, 0 = none; `-` scores the depth already at `out` instead of completing), `sky`
//! (HxW, 1 = sky), `out` (the dense depth written) and `gt` (HxW, +inf = sky). `field=value` sets
//! a CompleteDepth parameter (`smooth_edge=40`). One line is printed per image: `out`, scored
//! pixels (ground truth in 0.1-80 m), those off by more than 10%, boundary accuracy and
//! completeness (px, EvalDepth's default edge parameters), and the completion's time (ms, one image).
use anyhow::{bail, ensure, Context, Result};
use dist4d_stages::curation::complete::{complete, Params};
use dist4d_stages::eval::boundary::{boundary_metrics, EdgeParams};
use dist4d_types::artifact::{DepthMap, Image, Mask};
use dist4d_types::formats::{npy_f32, read_npy_f32};
use rayon::prelude::*;

// dist4d's allocator, so that the completion's times include what they include there (run with
// MIMALLOC_PURGE_DELAY=-1, which dist4d sets for itself: freed maps are reused, not faulted in again).
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

fn read(path: &str) -> Result<(Vec<usize>, Vec<f32>)> {
    read_npy_f32(&std::fs::read(path).with_context(|| format!("reading {path}"))?).with_context(|| format!("in {path}"))
}

fn params(settings: &[String]) -> Result<Params> {
    let mut p = serde_json::to_value(Params::default())?;
    for kv in settings {
        let Some((k, v)) = kv.split_once('=') else { bail!("{kv:?} is not field=value") };
        let field = p.get_mut(k).with_context(|| format!("CompleteDepth has no parameter {k:?}"))?;
        *field = serde_json::from_str(v).with_context(|| format!("{k}={v}"))?;
    }
    Ok(serde_json::from_value(p)?)
}

fn run(p: &Params, line: &str) -> Result<String> {
    let f: Vec<&str> = line.split_whitespace().collect();
    ensure!(f.len() == 5, "expected rgb prompt sky out gt, got {line:?}");
    let (shape, rgb) = read(f[0])?;
    ensure!(shape.len() == 3 && shape[2] == 3, "{}: shape {shape:?} is not HxWx3", f[0]);
    let (h, w) = (shape[0], shape[1]);
    let image =
        Image { width: w as u32, height: h as u32, rgb: rgb.iter().map(|&v| v.clamp(0.0, 255.0) as u8).collect() };
    let (_, gt) = read(f[4])?;
    let (_, sky) = read(f[2])?;
    ensure!(gt.len() == w * h && sky.len() == w * h, "{line}: the maps are not all {w}x{h}");
    let (depth, ms) = if f[1] == "-" {
        (read(f[3])?.1, 0.0)
    } else {
        let (_, prompt) = read(f[1])?;
        ensure!(prompt.len() == w * h, "{}: not {w}x{h}", f[1]);
        let sparse = DepthMap { width: w as u32, height: h as u32, data: prompt };
        let sky = Mask { width: w as u32, height: h as u32, data: sky.iter().map(|&v| (v > 0.5) as u8).collect() };
        let t = std::time::Instant::now();
        let c = complete(p, &image, &sparse, Some(&sky), false).depth;
        let ms = t.elapsed().as_secs_f64() * 1e3;
        std::fs::write(f[3], npy_f32(&[h, w], &c.data)).with_context(|| format!("writing {}", f[3]))?;
        (c.data, ms)
    };
    let (mut scored, mut bad) = (0u64, 0u64);
    for (&g, &d) in gt.iter().zip(&depth) {
        if g.is_finite() && g > 0.1 && g < 80.0 {
            scored += 1;
            bad += ((d.clamp(0.1, 80.0) - g).abs() / g > 0.1) as u64;
        }
    }
    let pred = DepthMap { width: w as u32, height: h as u32, data: depth };
    let gt = DepthMap { width: w as u32, height: h as u32, data: gt };
    let b = boundary_metrics(&EdgeParams::default(), &pred, &gt).unwrap_or_default();
    Ok(format!("{} {scored} {bad} {:.4} {:.4} {ms:.2}", f[3], b.accuracy, b.completeness))
}

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let Some(list) = args.first() else { bail!("usage: complete_npy LIST [field=value ...]") };
    let p = params(&args[1..])?;
    let list = std::fs::read_to_string(list).with_context(|| format!("reading {list}"))?;
    let lines: Vec<&str> = list.lines().filter(|l| !l.trim().is_empty()).collect();
    let rows = lines.par_iter().map(|l| run(&p, l)).collect::<Result<Vec<_>>>()?;
    for r in rows {
        println!("{r}");
    }
    Ok(())
}
