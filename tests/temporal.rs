//! End-to-end: DiST-T's temporal flow (pipelines/temporal.ron) from the CLI on synthetic data:
//! future RGB-D per step from the built-in baseline and from a reference worker, bullet-time
//! clouds as PLY that Open3D reads, previews, and the per-step scores against the exact views.

mod common;
use common::*;
use std::path::Path;

/// A run table's column for `stage`: 2 = total, 3 = executed, 4 = cached, 7 = n/a.
fn column(report: &str, stage: &str, col: usize) -> u64 {
    let line = report
        .lines()
        .find(|l| l.split_whitespace().next() == Some(stage))
        .unwrap_or_else(|| panic!("no {stage} in\n{report}"));
    line.split_whitespace().nth(col).unwrap().parse().unwrap()
}

fn temporal(cmd: &str, data: &Path, dir: &Path, out: &str, extra: &[&str]) -> String {
    let root = format!("dataset.root={}", data.display());
    let (cache, out) = (dir.join("cache"), dir.join(out));
    let mut args = vec![cmd, "pipelines/temporal.ron", "--set", &root, "--progress", "off"];
    args.extend(["--cache", cache.to_str().unwrap(), "--out", out.to_str().unwrap()]);
    args.extend(extra);
    let o = std::process::Command::new(bin()).current_dir(repo()).args(&args).output().unwrap();
    let t = text(&o);
    assert!(o.status.success(), "{t}");
    t
}

/// The row of `variant` in the eval table of `stage`: PSNR, SSIM, abs_rel (whole image).
fn scores(report: &str, stage: &str, variant: &str) -> (f64, f64, f64) {
    let table = &report[report.find(&format!("\n{stage}\n")).unwrap_or_else(|| panic!("{stage}: {report}"))..];
    let row = table.lines().find(|l| l.starts_with(&format!("| {variant} |"))).unwrap();
    let cells: Vec<f64> = row.split('|').filter_map(|c| c.trim().parse().ok()).collect();
    // views, PSNR, SSIM, PSNR valid, SSIM valid, abs_rel, ...
    (cells[1], cells[2], cells[5])
}

#[test]
fn the_temporal_flow_makes_each_step_its_bullet_time_cloud_and_scores_with_the_baseline_and_a_worker() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    let o =
        dist4d(&["synth", "--out", data.to_str().unwrap(), "--keyframes", "4", "--width", "320", "--height", "180"]);
    assert!(o.status.success(), "{}", text(&o));
    let report = temporal("run", &data, tmp.path(), "baseline", &[]);
    // 4 frames x 6 cameras; t+1 on 3 frames, t+2 on 2, t+3 on 1 (the others are past the end).
    assert_eq!(column(&report, "future", 3), 36, "{report}");
    // One cloud per frame and step, by the first camera's task.
    assert_eq!((column(&report, "cloud", 3), column(&report, "cloud", 7)), (6, 30), "{report}");
    let out = tmp.path().join("baseline/synth-0000");
    for step in ["000_t+1", "000_t+3", "002_t+1"] {
        assert!(out.join(format!("CAM_BACK/{step}.png")).is_file());
        assert!(out.join(format!("bullet_time/{step}_CAM_FRONT.png")).is_file());
        assert!(out.join(format!("bullet_time/{step}_CAM_FRONT.ply")).is_file());
    }
    assert!(!out.join("bullet_time/003_t+1_CAM_FRONT.ply").exists(), "no frame after the last");
    // The six camera tasks of a step read the same views: a rerun must still find that exactly
    // the first camera's makes the cloud (its key says which task it is), into any folder.
    let again = temporal("run", &data, tmp.path(), "again", &[]);
    assert_eq!((column(&again, "future", 3), column(&again, "cloud", 3)), (0, 0), "{again}");
    let plys = |dir: &str| -> Vec<String> {
        let mut v: Vec<String> = std::fs::read_dir(tmp.path().join(dir).join("synth-0000/bullet_time"))
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .filter(|n| n.ends_with(".ply"))
            .collect();
        v.sort();
        v
    };
    assert_eq!(plys("again"), plys("baseline"));
    assert_eq!(plys("again").len(), 6);
    assert!(plys("again").iter().all(|n| n.ends_with("_CAM_FRONT.ply")), "{:?}", plys("again"));
    // The layout control: the synthetic map's road (grey 80) and the ego (white) at the centre.
    let layout = image::open(out.join("CAM_FRONT/000_t+1_layout.png")).unwrap().to_rgb8();
    assert_eq!(layout.dimensions(), (256, 256));
    assert_eq!(layout.get_pixel(128, 128).0, [255, 255, 255]);
    let road = layout.pixels().filter(|p| p.0 == [80, 80, 80]).count();
    assert!(road > 2000, "the road from the dataset's map: {road} px");

    // The PLY as Open3D reads it: coloured points around the ego (x forward, y left, z up).
    if let Some(python) = peers_python() {
        let ply = out.join("bullet_time/000_t+1_CAM_FRONT.ply");
        let script = "import sys, numpy as np, open3d as o3d
p = o3d.io.read_point_cloud(sys.argv[1])
x, c = np.asarray(p.points), np.asarray(p.colors)
print(len(x), int(p.has_colors()), float(np.median(np.abs(x[:, 0]))), float(np.median(x[:, 2])), float(c.std()))";
        let o = std::process::Command::new(&python).args(["-c", script, ply.to_str().unwrap()]).output().unwrap();
        assert!(o.status.success(), "{}", text(&o));
        let v: Vec<f64> = String::from_utf8_lossy(&o.stdout).split_whitespace().map(|s| s.parse().unwrap()).collect();
        assert!(v[0] > 10_000.0 && v[1] == 1.0, "points and colours: {v:?}");
        assert!(v[2] > 1.0 && v[2] < 60.0, "the surround spreads around the ego: {v:?}");
        assert!(v[3] > -3.0 && v[3] < 10.0, "from the road up: {v:?}");
        assert!(v[4] > 0.05, "real colours, not one: {v:?}");
    }

    // Scores per step against the exact future views: the warp is far better than chance, and
    // better one step ahead than three.
    let eval = temporal("eval", &data, tmp.path(), "baseline", &[]);
    let (psnr1, ssim1, rel1) = scores(&eval, "score", "t+1");
    let (psnr3, _, _) = scores(&eval, "score", "t+3");
    assert!(psnr1 > 15.0 && ssim1 > 0.6 && rel1 < 0.4, "t+1: {psnr1} dB, SSIM {ssim1}, abs_rel {rel1}\n{eval}");
    assert!(psnr1 > psnr3, "t+1 {psnr1} dB, t+3 {psnr3} dB\n{eval}");
    let (bullet_psnr, _, _) = scores(&eval, "bullet_score", "t+1");
    assert!(bullet_psnr > 13.0, "the bullet-time view 2 m left: {bullet_psnr} dB\n{eval}");

    // The same flow with a worker generating the future (the persistence baseline of
    // workers/future_copy.py): its views are the reference frame's, and a rerun asks it nothing.
    let Some(python) = peers_python() else { return };
    let worker = format!(
        "future.worker=Some((program: {:?}, args: [{:?}, \"--require-layout\"]))",
        python.display().to_string(),
        repo().join("workers/future_copy.py").display().to_string()
    );
    let report = temporal("run", &data, tmp.path(), "worker", &["--set", &worker]);
    assert_eq!((column(&report, "future", 3), column(&report, "complete", 3)), (36, 0), "{report}");
    let read = |dir: &str, file: &str| std::fs::read(tmp.path().join(dir).join("synth-0000").join(file)).unwrap();
    assert_ne!(read("worker", "CAM_FRONT/000_t+1.png"), read("baseline", "CAM_FRONT/000_t+1.png"));
    assert_eq!(
        read("worker", "CAM_FRONT/000_t+1.png"),
        read("worker", "CAM_FRONT/000_t+2.png"),
        "persistence: every step is the reference frame"
    );
    let again = temporal("run", &data, tmp.path(), "worker", &["--set", &worker]);
    assert_eq!(column(&again, "future", 3), 0, "{again}");
}

/// The temporal flow's curation is curation.ron's, stage for stage (docs/temporal.md): after a
/// curation run into the same store, none of its stages has anything left to do.
#[test]
fn the_temporal_curation_reuses_a_curation_runs_depth_from_the_cache() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    let args = ["synth", "--out", data.to_str().unwrap(), "--keyframes", "2", "--width", "160", "--height", "90"];
    let o = dist4d(&[&args[..], &["--no-ground-truth"]].concat());
    assert!(o.status.success(), "{}", text(&o));
    let root = format!("dataset.root={}", data.display());
    let cache = tmp.path().join("cache");
    let curation = repo().join("pipelines/curation.ron");
    let o = dist4d(&[
        "run",
        curation.to_str().unwrap(),
        "--progress",
        "off",
        "--set",
        &root,
        "--cache",
        cache.to_str().unwrap(),
        "--out",
        tmp.path().join("out-curation").to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", text(&o));
    let out = tmp.path().join("out");
    let o = std::process::Command::new(bin())
        .current_dir(repo())
        .args(["explain", "pipelines/temporal.ron", "--set", &root, "--cache", cache.to_str().unwrap()])
        .args(["--out", out.to_str().unwrap()])
        .output()
        .unwrap();
    let t = text(&o);
    assert!(o.status.success(), "{t}");
    let stages = ["aggregate", "sky", "mvs", "mvs_points", "fuse", "visible", "prompt", "complete", "follow"];
    for stage in stages {
        let line = t.lines().find(|l| l.starts_with(&format!("{stage} ("))).unwrap_or_else(|| panic!("{stage}: {t}"));
        assert!(line.ends_with("cached, 0 will run") && !line.contains(": 0 cached"), "{line}\n{t}");
    }
}
