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
    let small = ["--set", "pairs.width=384", "--set", "pairs.height=224"];
    let report = pairs_run(&pipeline, &data, tmp.path(), &small);
    // 6 frames x 6 cameras x 6 variants; t-2 / t+2 (and their voxel twins) have no target on two
    // frames each, t-4 / t+4 on four.
    assert_eq!(column(&report, "pairs", 3), 216, "{report}");
    assert_eq!(column(&report, "pairs", 7), 96, "{report}");
    assert_eq!(column(&report, "sheet", 3), 120, "{report}");
    let out = tmp.path().join("out");
    let pairs = index(&out);
    assert_eq!(pairs.len(), 120);
    for p in &pairs {
        for (_, f) in p["files"].as_object().unwrap() {
            assert!(out.join(f.as_str().unwrap()).is_file(), "{p}");
        }
        let (src, tgt) = (&p["source"], &p["target"]);
        let offset = p["offset"].as_i64().unwrap();
        let frame = |v: &Value| v["frame"].as_str().unwrap().parse::<i64>().unwrap();
        assert_eq!(frame(tgt) - frame(src), offset, "{p}");
        assert_eq!(p["size"], serde_json::json!([224, 384]));
        assert!(data.join(src["image"].as_str().unwrap()).is_file());
        assert_eq!(
            tgt["timestamp_us"].as_i64().unwrap() - src["timestamp_us"].as_i64().unwrap(),
            offset * 500_000,
            "{p}"
        );
    }
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
    let v = r#"pairs.variants={"t-2": (offset: -2), "t+2": (offset: 2), "t-4": (offset: -4), "t+4": (offset: 4), "t-2_voxel": (offset: -2, voxel: 0.2), "t+2_voxel": (offset: 2, voxel: 0.3)}"#;
    edited.extend(["--set", v]);
    let one = pairs_run(&pipeline, &data, tmp.path(), &edited);
    assert_eq!((column(&one, "pairs", 3), column(&one, "complete", 3)), (36, 0), "{one}");
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
/// frames; the single nuScenes keyframe has no second frame, so its pairs have nothing to make.
#[test]
fn dist_s_pairs_run_on_the_shared_real_data() {
    let (Some(nusc), Some(dgp)) = (shared_nuscenes(), shared_dgp()) else { return };
    let tmp = tempfile::tempdir().unwrap();
    let dgp_pipeline = tmp.path().join("dgp_pairs.ron");
    std::fs::write(&dgp_pipeline, with_dataset("dist_s_pairs", "Dgp(root: \"\")")).unwrap();
    let report = pairs_run(&dgp_pipeline, &dgp, &tmp.path().join("dgp"), &[]);
    let cameras = column(&report, "complete", 3) / 3;
    assert_eq!(column(&report, "sheet", 3), 4 * cameras, "t-2, t+2 and their voxel twins, one frame each\n{report}");
    assert_eq!(index(&tmp.path().join("dgp/out")).len() as u64, 4 * cameras);
    let pipeline = repo().join("pipelines/dist_s_pairs.ron");
    let report = pairs_run(&pipeline, &nusc, &tmp.path().join("nusc"), &[]);
    assert_eq!(column(&report, "pairs", 7), 36, "{report}");
}
