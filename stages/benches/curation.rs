//! Curation stages against their peer programs, on the same inputs, in the same run.
//!
//!   cargo bench -p dist4d-stages --bench curation -- [hpr] [complete] [stereo]
//!
//! Peers run from the venv made by ../shared/bench/peers/setup.sh (`.venv-peers/` in the
//! workspace, or DIST4D_PEERS_PYTHON); without it only dist4d's figures are printed.

use dist4d_stages::stages::encode::npy_f32;
use dist4d_stages::stages::hpr::hidden_point_removal;
use dist4d_stages::synth::rng::Rng;
use glam::DVec3;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

fn workspace() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).parent().unwrap().to_path_buf()
}

fn peer_python() -> Option<PathBuf> {
    let p = std::env::var_os("DIST4D_PEERS_PYTHON")
        .map(PathBuf::from)
        .unwrap_or_else(|| workspace().join(".venv-peers/bin/python"));
    p.exists().then_some(p)
}

fn peers_dir() -> PathBuf {
    workspace().join("../shared/bench/peers")
}

/// Runs a peer script; returns its JSON line.
fn peer(script: &str, args: &[String]) -> Option<serde_json::Value> {
    let py = peer_python()?;
    let out = Command::new(py).arg(peers_dir().join(script)).args(args).output().ok()?;
    if !out.status.success() {
        eprintln!("peer {script} failed: {}", String::from_utf8_lossy(&out.stderr));
        return None;
    }
    serde_json::from_slice(out.stdout.split(|&b| b == b'\n').find(|l| !l.is_empty())?).ok()
}

fn best_of<T>(n: usize, mut f: impl FnMut() -> T) -> (f64, T) {
    let mut best = f64::INFINITY;
    let mut out = None;
    for _ in 0..n {
        let t = Instant::now();
        let r = f();
        best = best.min(t.elapsed().as_secs_f64());
        out = Some(r);
    }
    (best, out.unwrap())
}

fn read_npy_i64(path: &Path) -> Vec<i64> {
    let bytes = std::fs::read(path).unwrap();
    let header_len = u16::from_le_bytes([bytes[8], bytes[9]]) as usize;
    bytes[10 + header_len..].chunks_exact(8).map(|c| i64::from_le_bytes(c.try_into().unwrap())).collect()
}

fn bench_hpr(tmp: &Path) {
    println!("## Hidden point removal vs Open3D");
    println!("| points | visible | dist4d | Open3D | speed-up | agreement |");
    println!("| ---: | ---: | ---: | ---: | ---: | ---: |");
    for n in [100_000usize, 300_000] {
        // Uniform in a 40 m cube around the camera, as f32 so both sides read the same numbers.
        let mut rng = Rng::new(n as u64);
        let flat: Vec<f32> = (0..n * 3).map(|_| rng.range(-20.0, 20.0) as f32).collect();
        let pts: Vec<DVec3> = flat.chunks_exact(3).map(|c| DVec3::new(c[0] as f64, c[1] as f64, c[2] as f64)).collect();
        let camera = DVec3::new(0.5, -0.25, 0.1);
        let max = pts.iter().map(|p| p.distance(camera)).fold(0.0, f64::max);
        let radius = 100.0 * max;
        let (ours, vis) = best_of(5, || hidden_point_removal(&pts, camera, radius));
        let visible = vis.iter().filter(|&&v| v).count();
        let input = tmp.join(format!("hpr_{n}.npy"));
        let output = tmp.join(format!("hpr_{n}_visible.npy"));
        std::fs::write(&input, npy_f32(&[n, 3], &flat)).unwrap();
        let args: Vec<String> = vec![
            input.display().to_string(),
            camera.x.to_string(),
            camera.y.to_string(),
            camera.z.to_string(),
            radius.to_string(),
            "--out".into(),
            output.display().to_string(),
        ];
        match peer("hpr_open3d.py", &args) {
            Some(j) => {
                let theirs = j["best_seconds"].as_f64().unwrap();
                let mut peer_vis = vec![false; n];
                for i in read_npy_i64(&output) {
                    peer_vis[i as usize] = true;
                }
                let agree = vis.iter().zip(&peer_vis).filter(|(a, b)| a == b).count() as f64 / n as f64;
                println!(
                    "| {n} | {visible} (Open3D {}) | {:.1} ms | {:.1} ms | {:.2}x | {:.4}% |",
                    peer_vis.iter().filter(|&&v| v).count(),
                    ours * 1e3,
                    theirs * 1e3,
                    theirs / ours,
                    agree * 100.0
                );
            }
            None => println!("| {n} | {visible} | {:.1} ms | (no peer venv) | | |", ours * 1e3),
        }
    }
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).filter(|a| !a.starts_with("--")).collect();
    let all = args.is_empty();
    let tmp = tempfile::tempdir().unwrap();
    if all || args.iter().any(|a| a == "hpr") {
        bench_hpr(tmp.path());
    }
}
