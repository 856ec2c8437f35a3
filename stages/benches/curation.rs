//! Curation stages against their peer programs, on the same inputs, in the same run.
//!
//!   cargo bench -p dist4d-stages --bench curation -- [hpr] [stereo] [voxel] [mvs]
//!
//! Peers run from the venv made by ../shared/bench/peers/setup.sh (`.venv-peers/` in the
//! workspace, or DIST4D_PEERS_PYTHON); without it only dist4d's figures are printed.

// The allocator the dist4d binary uses, so that stage timings here match a run's.
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

use dist4d_stages::curation::hpr::hidden_point_removal;
use dist4d_types::formats::npy_f32;
use dist4d_types::rng::Rng;
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

/// CPU seconds this process has used (user + system, from /proc/self/stat; 0 elsewhere): on a
/// shared machine a busy neighbour stretches wall time but not the CPU time of the work itself.
fn cpu_seconds() -> f64 {
    let Ok(stat) = std::fs::read_to_string("/proc/self/stat") else { return 0.0 };
    // Fields after the command name (which may hold spaces, closed by the last ')'): utime and
    // stime are the 12th and 13th, in clock ticks (100 per second on Linux).
    let rest = stat.rsplit_once(')').map_or("", |(_, r)| r);
    let f: Vec<f64> = rest.split_whitespace().map(|v| v.parse().unwrap_or(0.0)).collect();
    (f.get(11).unwrap_or(&0.0) + f.get(12).unwrap_or(&0.0)) / 100.0
}

/// Like [`best_of`], with the CPU seconds of the fastest run by CPU too: (wall, cpu, output).
fn best_of_cpu<T>(n: usize, mut f: impl FnMut() -> T) -> (f64, f64, T) {
    let (mut wall, mut cpu) = (f64::INFINITY, f64::INFINITY);
    let mut out = None;
    for _ in 0..n {
        let (t, c) = (Instant::now(), cpu_seconds());
        let r = f();
        cpu = cpu.min(cpu_seconds() - c);
        wall = wall.min(t.elapsed().as_secs_f64());
        out = Some(r);
    }
    (wall, cpu, out.unwrap())
}

fn read_npy_i64(path: &Path) -> Vec<i64> {
    let bytes = std::fs::read(path).unwrap();
    let header_len = u16::from_le_bytes([bytes[8], bytes[9]]) as usize;
    bytes[10 + header_len..].chunks_exact(8).map(|c| i64::from_le_bytes(c.try_into().unwrap())).collect()
}

fn bench_hpr(tmp: &Path) {
    println!("## Hidden point removal vs Open3D");
    println!("| points | R / farthest | visible | dist4d | Open3D | speed-up | agreement |");
    println!("| ---: | ---: | ---: | ---: | ---: | ---: | ---: |");
    // 100: Open3D's tutorial value; 400: HiddenPointRemoval's default.
    for (n, factor) in [(100_000usize, 100.0), (300_000, 100.0), (100_000, 400.0), (300_000, 400.0)] {
        // Uniform in a 40 m cube around the camera, as f32 so both sides read the same numbers.
        let mut rng = Rng::new(n as u64);
        let flat: Vec<f32> = (0..n * 3).map(|_| rng.range(-20.0, 20.0) as f32).collect();
        let pts: Vec<DVec3> = flat.chunks_exact(3).map(|c| DVec3::new(c[0] as f64, c[1] as f64, c[2] as f64)).collect();
        let camera = DVec3::new(0.5, -0.25, 0.1);
        let max = pts.iter().map(|p| p.distance(camera)).fold(0.0, f64::max);
        let radius = factor * max;
        let (ours, vis) = best_of(5, || hidden_point_removal(&pts, camera, radius));
        let visible = vis.iter().filter(|&&v| v).count();
        let input = tmp.join(format!("hpr_{n}_{factor}.npy"));
        let output = tmp.join(format!("hpr_{n}_{factor}_visible.npy"));
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
                    "| {n} | {factor} | {visible} (Open3D {}) | {:.1} ms | {:.1} ms | {:.2}x | {:.4}% |",
                    peer_vis.iter().filter(|&&v| v).count(),
                    ours * 1e3,
                    theirs * 1e3,
                    theirs / ours,
                    agree * 100.0
                );
            }
            None => println!("| {n} | {factor} | {visible} | {:.1} ms | (no peer venv) | | |", ours * 1e3),
        }
    }
}

/// Our plane-sweep stereo (both directions + consistency, as the MVS stage runs it) and OpenCV
/// StereoSGBM on the shared Middlebury Motorcycle pair: bad-pixel rate (> 2 px) and time.
fn bench_stereo(tmp: &Path) {
    use dist4d_stages::middlebury::{bad_pixels, read_motorcycle, PairCalibration};
    use dist4d_stages::stereo::{keep_consistent, sweep_depth_with, SweepBuffers};
    let dir = workspace().join("../shared/data/middlebury-motorcycle");
    if !dir.is_dir() {
        println!("(stereo: {} is absent, skipped)", dir.display());
        return;
    }
    let ((left, right), truth) = read_motorcycle(&dir).unwrap();
    let calib = PairCalibration::MOTORCYCLE;
    let mvs = dist4d_stages::curation::mvs::Params::default();
    let p = calib.sweep(80.0, &mvs.sweep());
    // One thread, as OpenCV runs below.
    let one = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap();
    let (ours, depth) = one.install(|| {
        best_of(3, || {
            let mut buffers = SweepBuffers::default();
            let mut d =
                sweep_depth_with(&mut buffers, &left, &[&right], &p).expect("the benchmark sweep fits the budget");
            let back =
                sweep_depth_with(&mut buffers, &right, &[&left], &p).expect("the benchmark sweep fits the budget");
            keep_consistent(&left, &mut d, &[(&right, &back)], mvs.consistency_px, mvs.consistency_depth);
            d
        })
    });
    let disparity: Vec<Option<f64>> =
        depth.depth.iter().map(|&z| (z > 0.0).then(|| calib.disparity(z as f64))).collect();
    let score = bad_pixels(&disparity, &truth, 2.0);
    println!("## Stereo on Middlebury Motorcycle (741x500, disparities 0-80 px), bad pixels > 2 px");
    println!("| method | bad (estimates) | density | bad (missing = bad) | time |");
    println!("| --- | ---: | ---: | ---: | ---: |");
    println!(
        "| dist4d plane sweep, census 7x7, SGM 8 paths, consistency check, 1 thread | {:.2}% | {:.1}% | {:.2}% | {:.0} ms |",
        score.valid * 100.0,
        score.density * 100.0,
        score.all * 100.0,
        ours * 1e3
    );
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("benches/peers/sgbm_cv2.py");
    for mode in ["sgbm", "hh"] {
        let out = tmp.join(format!("sgbm_{mode}.npy"));
        let Some(py) = peer_python() else {
            println!("| OpenCV StereoSGBM | (no peer venv) | | | |");
            return;
        };
        let o = Command::new(py)
            .arg(&script)
            .arg(dir.join("motorcycle_left.png"))
            .arg(dir.join("motorcycle_right.png"))
            .args(["--num-disp", "80", "--mode", mode, "--out"])
            .arg(&out)
            .output()
            .unwrap();
        if !o.status.success() {
            println!("| OpenCV StereoSGBM {mode} | failed: {} | | | |", String::from_utf8_lossy(&o.stderr).trim());
            continue;
        }
        let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
        let theirs = j["best_seconds"].as_f64().unwrap();
        let disp = dist4d_datasets::files::parse_npy(&std::fs::read(&out).unwrap()).unwrap().data;
        let est: Vec<Option<f64>> = disp.iter().map(|&d| d.is_finite().then_some(d)).collect();
        let s = bad_pixels(&est, &truth, 2.0);
        println!(
            "| OpenCV StereoSGBM ({}, block 5, LR check, speckle filter), 1 thread | {:.2}% | {:.1}% | {:.2}% | {:.0} ms ({:.2}x ours) |",
            if mode == "hh" { "8 paths" } else { "5 paths" },
            s.valid * 100.0,
            s.density * 100.0,
            s.all * 100.0,
            theirs * 1e3,
            theirs / ours
        );
    }
}

/// Voxel-mean downsampling at 0.1 m against Open3D's `voxel_down_sample` on the same points.
fn bench_voxel(tmp: &Path) {
    use dist4d_stages::curation::mvs_points::voxel_mean;
    println!("## Voxel downsampling (0.1 m, mean per voxel) vs Open3D");
    println!("| points | kept (dist4d / Open3D) | dist4d | Open3D | speed-up | max coordinate difference |");
    println!("| ---: | ---: | ---: | ---: | ---: | ---: |");
    let n = 300_000usize;
    let mut rng = Rng::new(7);
    // A 20 x 20 x 5 m block: about 1 point per 0.1 m voxel on average, many shared.
    let pts: Vec<[f32; 4]> = (0..n)
        .map(|_| [rng.range(0.0, 20.0) as f32, rng.range(0.0, 20.0) as f32, rng.range(0.0, 5.0) as f32, 0.0])
        .collect();
    let (ours, kept) = best_of(5, || voxel_mean(&pts, 0.1));
    let input = tmp.join("voxel.npy");
    let output = tmp.join("voxel_out.npy");
    let flat: Vec<f32> = pts.iter().flat_map(|p| [p[0], p[1], p[2]]).collect();
    std::fs::write(&input, npy_f32(&[n, 3], &flat)).unwrap();
    let args = vec![input.display().to_string(), "0.1".into(), "--out".into(), output.display().to_string()];
    match peer("voxel_open3d.py", &args) {
        Some(j) => {
            let theirs = j["best_seconds"].as_f64().unwrap();
            let mut peer_pts: Vec<[f64; 3]> = dist4d_datasets::files::parse_npy(&std::fs::read(&output).unwrap())
                .unwrap()
                .data
                .chunks_exact(3)
                .map(|c| [c[0], c[1], c[2]])
                .collect();
            // A voxel's mean lies inside it: compare the two outputs voxel by voxel.
            let origin = pts
                .iter()
                .fold([f64::INFINITY; 3], |m, p| [m[0].min(p[0] as f64), m[1].min(p[1] as f64), m[2].min(p[2] as f64)]);
            let key = |p: &[f64; 3]| -> [i64; 3] {
                std::array::from_fn(|k| ((p[k] - origin[k] + 0.05) / 0.1).floor() as i64)
            };
            let mut mine: Vec<[f64; 3]> = kept.iter().map(|p| [p[0] as f64, p[1] as f64, p[2] as f64]).collect();
            peer_pts.sort_by_key(key);
            mine.sort_by_key(key);
            let diff = if mine.len() == peer_pts.len() && mine.iter().zip(&peer_pts).all(|(a, b)| key(a) == key(b)) {
                let d = mine
                    .iter()
                    .zip(&peer_pts)
                    .map(|(a, b)| (a[0] - b[0]).abs().max((a[1] - b[1]).abs()).max((a[2] - b[2]).abs()))
                    .fold(0.0, f64::max);
                format!("{d:.1e} m")
            } else {
                "voxels differ".into()
            };
            println!(
                "| {n} | {} / {} | {:.1} ms | {:.1} ms | {:.2}x | {diff} |",
                kept.len(),
                peer_pts.len(),
                ours * 1e3,
                theirs * 1e3,
                theirs / ours
            );
        }
        None => println!("| {n} | {} | {:.1} ms | (no peer venv) | | |", kept.len(), ours * 1e3),
    }
}

/// MultiViewStereo as the stage runs it, on full-size synthetic camera triples (frames t-1, t,
/// t+1 of each camera of the middle keyframe), one thread: seconds per image, and a digest of
/// the depth and confidence outputs so that two builds can be compared for both speed and bytes.
/// Data: `DIST4D_MVS_DATA`, else /tmp/syn8s0 (`dist4d synth --keyframes 8 --seed 0 --out
/// /tmp/syn8s0`); `DIST4D_MVS_REPS` repetitions per image (best taken, default 3).
fn bench_mvs() {
    use dist4d_datasets::files::read_camera_image;
    use dist4d_datasets::nuscenes::{NuScenes, NuScenesConfig};
    use dist4d_datasets::surround::SurroundReader;
    use dist4d_stages::curation::mvs::{multi_view_stereo, Frame, Params};
    let root = std::env::var("DIST4D_MVS_DATA").unwrap_or_else(|_| "/tmp/syn8s0".into());
    if !Path::new(&root).is_dir() {
        println!("(mvs: {root} is absent, skipped; make it with `dist4d synth --keyframes 8 --seed 0 --out {root}`)");
        return;
    }
    let reps: usize = std::env::var("DIST4D_MVS_REPS").ok().and_then(|r| r.parse().ok()).unwrap_or(3);
    let data = NuScenes::open(NuScenesConfig { root: root.clone(), ..NuScenesConfig::default() }).unwrap();
    let tree = data.tree();
    let scene = &tree.scenes[0];
    let t = scene.frames.len() / 2;
    assert!(t >= 1 && t + 1 < scene.frames.len(), "{root}: the scene needs 3 keyframes or more");
    let params = Params::default();
    let one = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap();
    println!("## MultiViewStereo, {root} keyframes {}..{}, 1 thread, best of {reps}", t - 1, t + 1);
    println!("| camera | size | wall | CPU | depth pixels | digest of depth + confidence |");
    println!("| --- | ---: | ---: | ---: | ---: | --- |");
    let (mut total, mut total_cpu) = (0.0, 0.0);
    for (c, camera) in tree.cameras.iter().enumerate() {
        let readings: Vec<_> = (t - 1..=t + 1).map(|f| scene.frames[f].cameras[c].as_ref().unwrap()).collect();
        let images: Vec<_> = readings
            .iter()
            .map(|r| read_camera_image(&r.file, r.calib.width, r.calib.height, &r.what).unwrap())
            .collect();
        let frames: Vec<Frame> = readings
            .iter()
            .zip(&images)
            .zip(-1i64..)
            .map(|((r, image), position)| Frame { position, image, calib: &r.calib, pose: &r.pose })
            .collect();
        let (secs, cpu, (depth, confidence)) =
            one.install(|| best_of_cpu(reps, || multi_view_stereo(&params, &frames).unwrap()));
        total += secs;
        total_cpu += cpu;
        let mut h = blake3::Hasher::new();
        for v in depth.data.iter().chain(&confidence.data) {
            h.update(&v.to_le_bytes());
        }
        let valid = depth.data.iter().filter(|&&z| z > 0.0).count() as f64 / depth.data.len() as f64;
        println!(
            "| {camera} | {}x{} | {:.0} ms | {:.0} ms | {:.1}% | {} |",
            images[1].width,
            images[1].height,
            secs * 1e3,
            cpu * 1e3,
            valid * 100.0,
            &h.finalize().to_hex()[..16]
        );
    }
    let n = tree.cameras.len() as f64;
    println!("mean per image: {:.0} ms wall, {:.0} ms CPU", total / n * 1e3, total_cpu / n * 1e3);
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).filter(|a| !a.starts_with("--")).collect();
    let all = args.is_empty();
    let tmp = tempfile::tempdir().unwrap();
    if all || args.iter().any(|a| a == "hpr") {
        bench_hpr(tmp.path());
    }
    if all || args.iter().any(|a| a == "stereo") {
        bench_stereo(tmp.path());
    }
    if all || args.iter().any(|a| a == "voxel") {
        bench_voxel(tmp.path());
    }
    if all || args.iter().any(|a| a == "mvs") {
        bench_mvs();
    }
}
