//! End-to-end: the DiST-S pair pipeline (pipelines/dist_s_pairs.ron) through the CLI on synthetic
//! data and on the shared real recordings, its index read by the numpy-only loader of the docs.

mod common;
use common::*;
use serde_json::Value;
use std::path::Path;

/// A run table's column for `stage`: 3 = executed, 4 = cached, 7 = n/a.
fn column(report: &str, stage: &str, col: usize) -> u64 {
    let line = report
        .lines()
        .find(|l| l.split_whitespace().next() == Some(stage))
        .unwrap_or_else(|| panic!("no {stage} in\n{report}"));
    line.split_whitespace().nth(col).unwrap().parse().unwrap()
}

fn pairs_run(pipeline: &Path, data: &Path, dir: &Path, extra: &[&str]) -> String {
    let root = format!("dataset.root={}", data.display());
    let (cache, out) = (dir.join("cache"), dir.join("out"));
    let mut args = vec!["run", pipeline.to_str().unwrap(), "--set", &root];
    args.extend(["--cache", cache.to_str().unwrap(), "--out", out.to_str().unwrap()]);
    args.extend(extra);
    let o = dist4d(&args);
    let t = text(&o);
    assert!(o.status.success(), "{t}");
    t
}

fn index(out: &Path) -> Vec<Value> {
    let mut all = Vec::new();
    for scene in std::fs::read_dir(out).unwrap() {
        let p = scene.unwrap().path().join("pairs.jsonl");
        if p.is_file() {
            all.extend(std::fs::read_to_string(p).unwrap().lines().map(|l| serde_json::from_str::<Value>(l).unwrap()));
        }
    }
    all
}

#[test]
fn dist_s_pairs_from_the_cli_on_synthetic_data_with_an_index_a_loader_reads() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    let o =
        dist4d(&["synth", "--out", data.to_str().unwrap(), "--keyframes", "6", "--width", "480", "--height", "270"]);
    assert!(o.status.success(), "{}", text(&o));
    let pipeline = repo().join("pipelines/dist_s_pairs.ron");
    let small =
        ["--set", "pairs.width=384", "--set", "pairs.height=224", "--set", "fit.width=384", "--set", "fit.height=224"];
    let report = pairs_run(&pipeline, &data, tmp.path(), &small);
    // 6 frames x 6 cameras x 7 variants, less those whose target frame is past the scene's ends
    // (not planned): t-2 / t+2 and their voxel twins lack two frames each, t-4 / t+4 four; the
    // cross-camera pairs are on every frame.
    assert_eq!(column(&report, "pairs", 2), 156, "{report}");
    assert_eq!(column(&report, "pairs", 3), 156, "{report}");
    assert_eq!(column(&report, "pairs", 7), 0, "{report}");
    assert_eq!(column(&report, "sheet", 3), 156, "{report}");
    let out = tmp.path().join("out");
    let pairs = index(&out);
    assert_eq!(pairs.len(), 156);
    for p in &pairs {
        for (_, f) in p["files"].as_object().unwrap() {
            assert!(out.join(f.as_str().unwrap()).is_file(), "{p}");
        }
        let (src, tgt) = (&p["sources"][0], &p["target"]);
        let offset = p["offset"].as_i64().unwrap();
        let frame = |v: &Value| v["frame"].as_str().unwrap().parse::<i64>().unwrap();
        assert_eq!(frame(tgt) - frame(src), offset, "{p}");
        let cross = p["variant"] == "cross";
        assert_eq!(p["sources"].as_array().unwrap().len(), if cross { 5 } else { 1 }, "{p}");
        assert_eq!(src["camera_to_ego"] != tgt["camera_to_ego"], cross, "{p}");
        assert_eq!(p["size"], serde_json::json!([224, 384]));
        assert!(data.join(src["image"].as_str().unwrap()).is_file());
        // Keyframes are 0.5 s apart; the cameras of one frame fire within 50 ms of each other.
        let dt = tgt["timestamp_us"].as_i64().unwrap() - src["timestamp_us"].as_i64().unwrap();
        assert!((dt - offset * 500_000).abs() < 50_000, "{p}");
    }
    // The synthetic agents drive: some pairs move their objects to the target's time.
    assert!(pairs.iter().any(|p| p["moving"]["followed"].as_u64().unwrap_or(0) > 0), "no object followed");
    // The voxel twins are sparser than their dense pairs.
    let valid = |label: &str| {
        let png = out.join(format!("synth-0000/CAM_FRONT/002_{label}_mask.png"));
        let m = image::open(png).unwrap().into_luma8();
        m.pixels().filter(|p| p.0[0] > 0).count()
    };
    let (dense, thinned) = (valid("t+2"), valid("t+2_voxel"));
    assert!(thinned * 2 < dense && thinned > 0, "voxel 0.2 m: {thinned} valid pixels, dense {dense}");
    // A rerun does nothing; one variant edited reruns that variant's pairs and what reads them.
    let again = pairs_run(&pipeline, &data, tmp.path(), &small);
    assert_eq!(column(&again, "pairs", 3), 0, "{again}");
    let mut edited = small.to_vec();
    let v = r#"pairs.variants={"t-2": (offset: -2), "t+2": (offset: 2), "t-4": (offset: -4), "t+4": (offset: 4), "t-2_voxel": (offset: -2, voxel: 0.2), "t+2_voxel": (offset: 2, voxel: 0.3), "cross": (offset: 0, from: Others)}"#;
    edited.extend(["--set", v]);
    let one = pairs_run(&pipeline, &data, tmp.path(), &edited);
    assert_eq!((column(&one, "pairs", 3), column(&one, "complete", 3)), (24, 0), "t+2 on 4 frames x 6 cameras\n{one}");
    // The numpy-only loader of the docs reads a pair in DiST-S's layout.
    let Some(python) = peers_python() else { return };
    let o =
        std::process::Command::new(python).arg(repo().join("docs/examples/pair_loader.py")).arg(&out).output().unwrap();
    let printed = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{printed}{}", String::from_utf8_lossy(&o.stderr));
    assert!(
        printed.contains("cond_image (224, 384, 3) uint8") && printed.contains("cond_depth (224, 384, 3) float32"),
        "{printed}"
    );
}

/// On the shared real data: DGP's 3 frames give the t-2 / t+2 pairs between its first and last
/// frames; the single nuScenes keyframe has no second frame, so only its cross-camera pairs are
/// planned; SCC pairs come from every image of both.
#[test]
fn dist_s_pairs_run_on_the_shared_real_data() {
    let (Some(nusc), Some(dgp)) = (shared_nuscenes(), shared_dgp()) else { return };
    let tmp = tempfile::tempdir().unwrap();
    let dgp_pipeline = tmp.path().join("dgp_pairs.ron");
    std::fs::write(&dgp_pipeline, with_dataset("dist_s_pairs", "Dgp(root: \"\")")).unwrap();
    let report = pairs_run(&dgp_pipeline, &dgp, &tmp.path().join("dgp"), &[]);
    let cameras = column(&report, "complete", 3) / 3;
    assert_eq!(
        column(&report, "sheet", 3),
        7 * cameras,
        "t-2, t+2 and their voxel twins, one frame each; cross on 3\n{report}"
    );
    assert_eq!(index(&tmp.path().join("dgp/out")).len() as u64, 7 * cameras);
    let pipeline = repo().join("pipelines/dist_s_pairs.ron");
    let report = pairs_run(&pipeline, &nusc, &tmp.path().join("nusc"), &[]);
    assert_eq!(column(&report, "pairs", 2), 6, "{report}");
    let cross = index(&tmp.path().join("nusc/out"));
    assert_eq!(cross.len(), 6, "the cross-camera pair of each camera\n{report}");
    assert!(cross.iter().all(|p| p["variant"] == "cross"));
    // SCC pairs need no second frame: one per image on both.
    let report = pairs_run(&repo().join("pipelines/scc.ron"), &nusc, &tmp.path().join("nusc_scc"), &[]);
    assert_eq!(index(&tmp.path().join("nusc_scc/out")).len(), 6, "{report}");
    let dgp_scc = tmp.path().join("dgp_scc.ron");
    std::fs::write(&dgp_scc, with_dataset("scc", "Dgp(root: \"\")")).unwrap();
    let report = pairs_run(&dgp_scc, &dgp, &tmp.path().join("dgp_scc"), &[]);
    assert_eq!(index(&tmp.path().join("dgp_scc/out")).len() as u64, column(&report, "complete", 3), "{report}");
}

/// pipelines/scc.ron: a seeded shift per image, the novel view generated and reprojected back;
/// the same seed gives the same bytes, another seed other shifts.
#[test]
fn scc_pairs_are_deterministic_per_seed_and_share_the_pair_format() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    let o =
        dist4d(&["synth", "--out", data.to_str().unwrap(), "--keyframes", "3", "--width", "480", "--height", "270"]);
    assert!(o.status.success(), "{}", text(&o));
    let pipeline = repo().join("pipelines/scc.ron");
    let small = [
        "--set",
        "pairs.width=384",
        "--set",
        "pairs.height=224",
        "--set",
        "back.width=384",
        "--set",
        "back.height=224",
    ];
    let report = pairs_run(&pipeline, &data, &tmp.path().join("a"), &small);
    assert_eq!(column(&report, "sheet", 3), 18, "3 frames x 6 cameras, one random shift each\n{report}");
    let pairs = index(&tmp.path().join("a/out"));
    assert_eq!(pairs.len(), 18);
    let mut shifts = Vec::new();
    for p in &pairs {
        assert_eq!(p["kind"], "scc");
        let tau = p["shift"].as_f64().unwrap();
        assert!((-3.0..=3.0).contains(&tau), "{p}");
        shifts.push(tau);
        assert_eq!(p["sources"][0]["frame"], p["target"]["frame"]);
        for (_, f) in p["files"].as_object().unwrap() {
            assert!(tmp.path().join("a/out").join(f.as_str().unwrap()).is_file(), "{p}");
        }
    }
    // One shift per frame, shared by its six cameras.
    for p in &pairs {
        let same_frame: Vec<f64> =
            pairs.iter().filter(|q| q["frame"] == p["frame"]).map(|q| q["shift"].as_f64().unwrap()).collect();
        assert!(same_frame.iter().all(|t| (t - same_frame[0]).abs() < 1e-9), "{same_frame:?}");
    }
    let frames: std::collections::BTreeSet<String> =
        pairs.iter().map(|p| format!("{:.6}", p["shift"].as_f64().unwrap())).collect();
    assert_eq!(frames.len(), 3, "three frames, three shifts: {shifts:?}");
    // Another store, the same seed: the same bytes.
    pairs_run(&pipeline, &data, &tmp.path().join("b"), &small);
    let bytes = |dir: &str, f: &str| std::fs::read(tmp.path().join(dir).join("out/synth-0000").join(f)).unwrap();
    assert_eq!(bytes("a", "pairs.jsonl"), bytes("b", "pairs.jsonl"));
    assert_eq!(bytes("a", "CAM_FRONT/001_random_cond.png"), bytes("b", "CAM_FRONT/001_random_cond.png"));
    // A new seed: new shifts; the curation is reused.
    let mut seeded = small.to_vec();
    seeded.extend(["--set", "shift.seed=1"]);
    let again = pairs_run(&pipeline, &data, &tmp.path().join("a"), &seeded);
    assert_eq!((column(&again, "complete", 3), column(&again, "shift", 3)), (0, 18), "{again}");
    let reseeded: Vec<f64> = index(&tmp.path().join("a/out")).iter().map(|p| p["shift"].as_f64().unwrap()).collect();
    assert!(reseeded.iter().zip(&shifts).all(|(a, b)| a != b), "{reseeded:?} vs {shifts:?}");
}

/// The condition of an SCC pair is the original view come back: where it has a point, its depth
/// agrees with the target's (both the curated depth, through a shift and back).
#[test]
fn an_scc_condition_lands_on_its_own_target() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    assert!(dist4d(&[
        "synth",
        "--out",
        data.to_str().unwrap(),
        "--keyframes",
        "2",
        "--width",
        "480",
        "--height",
        "270"
    ])
    .status
    .success());
    let shift = r#"shift.variants={"left_2m": (lateral: 2)}"#;
    pairs_run(&repo().join("pipelines/scc.ron"), &data, tmp.path(), &["--set", shift]);
    let out = tmp.path().join("out/synth-0000/CAM_FRONT");
    let cond = read_npy(&out.join("000_left_2m_cond_depth.npy"));
    let target = read_npy(&out.join("000_left_2m_target_depth.npy"));
    let (mut n, mut good) = (0, 0);
    for (&c, &t) in cond.iter().zip(&target) {
        if c > 0.0 && t > 0.0 && t < 80.0 {
            n += 1;
            good += (((c - t) / t).abs() < 0.05) as usize;
        }
    }
    assert!(n > 100_000 && good as f64 > 0.9 * n as f64, "{good} of {n} condition depths within 5% of the target");
}

/// A float32 NPY's values (the files dist4d writes: little endian, C order).
fn read_npy(path: &Path) -> Vec<f32> {
    let b = std::fs::read(path).unwrap();
    let header = u16::from_le_bytes([b[8], b[9]]) as usize;
    b[10 + header..].chunks_exact(4).map(|c| f32::from_le_bytes(c.try_into().unwrap())).collect()
}

/// pipelines/novel_views.ron: the baseline's scores against the exact views, per shift, from
/// `dist4d eval`; farther shifts score worse.
#[test]
fn novel_view_scores_are_tabulated_per_shift() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    assert!(dist4d(&[
        "synth",
        "--out",
        data.to_str().unwrap(),
        "--keyframes",
        "2",
        "--width",
        "480",
        "--height",
        "270"
    ])
    .status
    .success());
    let root = format!("dataset.root={}", data.display());
    let (cache, out) = (tmp.path().join("cache"), tmp.path().join("out"));
    let o = dist4d(&[
        "eval",
        repo().join("pipelines/novel_views.ron").to_str().unwrap(),
        "--set",
        &root,
        "--cache",
        cache.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    let t = text(&o);
    assert!(o.status.success(), "{t}");
    let row = |variant: &str| -> Vec<f64> {
        let line =
            t.lines().find(|l| l.starts_with(&format!("| {variant} |"))).unwrap_or_else(|| panic!("{variant}\n{t}"));
        line.split('|').map(str::trim).filter(|s| !s.is_empty()).skip(1).map(|s| s.parse().unwrap()).collect()
    };
    // Columns: views, PSNR, SSIM, PSNR valid, SSIM valid, abs_rel, d<1.25, ...
    for side in ["left", "right"] {
        let (near, far) = (row(&format!("{side}_1m")), row(&format!("{side}_4m")));
        assert_eq!(near[0], 12.0);
        assert!(near[1] > far[1] && near[2] > far[2], "{side}: PSNR/SSIM at 1 m {near:?}, at 4 m {far:?}");
        assert!(near[3] > 24.0 && near[4] > 0.8, "{side} 1 m on valid pixels: {near:?}");
    }
}

/// A cross-camera variant without the other cameras wired is refused by `check`, before anything
/// runs (not by every task of the run).
#[test]
fn a_variant_that_needs_the_other_cameras_is_checked_to_have_them() {
    let tmp = tempfile::tempdir().unwrap();
    let shipped = std::fs::read_to_string(repo().join("pipelines/dist_s_pairs.ron")).unwrap();
    let cut: String = shipped.lines().filter(|l| !l.contains("\"surround_")).map(|l| format!("{l}\n")).collect();
    assert!(cut.len() < shipped.len());
    let file = tmp.path().join("pairs.ron");
    std::fs::write(&file, cut).unwrap();
    let o = dist4d(&["check", file.to_str().unwrap(), "--set", &format!("dataset.root={}", tmp.path().display())]);
    let t = text(&o);
    assert!(!o.status.success(), "{t}");
    assert!(t.contains("variant `cross` of stage `pairs` reads input `surround_images`, which is not wired"), "{t}");
    // Without the cross-camera variant, the other cameras are not needed.
    let o = dist4d(&[
        "check",
        file.to_str().unwrap(),
        "--set",
        &format!("dataset.root={}", tmp.path().display()),
        "--set",
        r#"pairs.variants={"t+2": (offset: 2)}"#,
    ]);
    assert!(o.status.success(), "{}", text(&o));
}
