//! End-to-end: pipelines/curation.ron through the CLI on synthetic data (scored against exact
//! ground truth) and on the shared real recordings.

mod common;
use common::*;
use std::path::Path;

fn curation(data: &Path, dir: &Path, dataset_kind: Option<&str>, extra: &[&str]) -> std::process::Output {
    let pipeline = repo().join("pipelines/curation.ron");
    let (cache, out) = (dir.join("cache"), dir.join("out"));
    let root = format!("dataset.root={}", data.display());
    let mut args = vec!["eval", pipeline.to_str().unwrap(), "--set", &root];
    let kind_file;
    if let Some(kind) = dataset_kind {
        // Swap the dataset (same ports) by writing a copy of the pipeline with another dataset.
        let text = with_dataset("curation", &format!("{kind}(root: \"\")"));
        kind_file = dir.join("curation.ron");
        std::fs::write(&kind_file, text).unwrap();
        args[1] = kind_file.to_str().unwrap();
    }
    args.extend(["--cache", cache.to_str().unwrap(), "--out", out.to_str().unwrap()]);
    args.extend(extra);
    dist4d(&args)
}

/// The value of column `col` (0 = abs_rel) in the `mean` row of table `title`.
fn mean_of(report: &str, title: &str, col: usize) -> f64 {
    let at = report.find(&format!("\n{title}\n")).unwrap_or_else(|| panic!("no table {title} in\n{report}"));
    let row = report[at..].lines().find(|l| l.starts_with("| mean |")).unwrap();
    row.split('|').map(str::trim).filter(|s| !s.is_empty()).nth(2 + col).unwrap().parse().unwrap()
}

/// The first percentage in the row starting with `row` of table `title`.
fn table_row(report: &str, title: &str, row: &str) -> f64 {
    let at = report.find(&format!("\n{title}\n")).unwrap_or_else(|| panic!("no table {title} in\n{report}"));
    let line = report[at..].lines().find(|l| l.starts_with(row)).unwrap_or_else(|| panic!("no row {row} in\n{report}"));
    line.split('|').map(str::trim).find_map(|c| c.strip_suffix('%')?.parse().ok()).unwrap()
}

/// Executed count of `stage` in the run table.
fn executed(report: &str, stage: &str) -> u64 {
    let line = report.lines().find(|l| l.split_whitespace().next() == Some(stage)).unwrap();
    line.split_whitespace().nth(3).unwrap().parse().unwrap()
}

#[test]
fn curation_on_synthetic_data_is_scored_against_ground_truth_and_reruns_only_what_a_param_touches() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("synth");
    let o = dist4d(&[
        "synth",
        "--out",
        data.to_str().unwrap(),
        "--keyframes",
        "3",
        "--width",
        "640",
        "--height",
        "360",
        "--no-lidar-sweeps",
    ]);
    assert!(o.status.success(), "{}", text(&o));
    let o = curation(&data, tmp.path(), None, &[]);
    let report = text(&o);
    assert!(o.status.success(), "{report}");
    assert_eq!(executed(&report, "complete"), 18, "{report}");
    // Dense depth close to the exact ground truth; the loose bounds catch breakage, the
    // full-size figures are in docs/BENCHMARKS.md.
    let abs_rel = mean_of(&report, "gt (raw)", 0);
    let a1 = mean_of(&report, "gt (raw)", 4);
    assert!(abs_rel < 0.12 && a1 > 0.8, "abs_rel {abs_rel}, a1 {a1}\n{report}");
    assert!(report.contains("gt_above_lidar (raw)") && report.contains("lidar_multi (median-scaled)"));
    // Sky and boundary metrics against the dense ground truth only; an IoU and boundary errors
    // that a broken metric (0 or the cap everywhere) would not give.
    assert!(report.contains("\ngt (sky, boundaries)\n") && !report.contains("lidar (sky"), "{report}");
    let iou = mean_of(&report, "gt (sky, boundaries)", 0);
    let (accuracy, completeness) =
        (mean_of(&report, "gt (sky, boundaries)", 3), mean_of(&report, "gt (sky, boundaries)", 4));
    assert!(iou > 0.0 && iou <= 1.0, "{report}");
    assert!(accuracy > 0.0 && accuracy < 10.0 && completeness > 0.0 && completeness < 10.0, "{report}");
    assert!(!report.contains("holdout ("), "no hold-out unless asked");
    let out = tmp.path().join("out/synth-0000");
    for f in
        ["CAM_FRONT/001_depth.exr", "CAM_FRONT/001_depth.png", "CAM_FRONT/001_depth.npy", "CAM_BACK/002_preview.png"]
    {
        assert!(out.join(f).is_file(), "{f}");
    }
    // Four panels per camera: the synthetic dataset has ground truth, so the error column too.
    let sheet = image::open(out.join("sheets/001.png")).unwrap();
    assert_eq!((sheet.width(), sheet.height()), (4 * 320, 6 * 180));

    // A completion parameter reruns completion and what reads it, nothing upstream.
    let o = curation(&data, tmp.path(), None, &["--set", "complete.sky_depth=90"]);
    let report = text(&o);
    assert!(o.status.success(), "{report}");
    for (stage, n) in [
        ("aggregate", 0),
        ("mvs", 0),
        ("mvs_points", 0),
        ("fuse", 0),
        ("visible", 0),
        ("prompt", 0),
        ("lidar", 0),
        ("complete", 18),
    ] {
        assert_eq!(executed(&report, stage), n, "{stage}\n{report}");
    }
    // Readers of the depth rerun where it changed: an image without sky gives the same bytes,
    // and early cutoff keeps its readers cached.
    let changed = executed(&report, "encode");
    assert!(changed >= 12 && executed(&report, "eval") == changed, "{report}");
    assert!(executed(&report, "sheet") >= 1, "{report}");

    // Multi-view stereo fills what the LiDAR cannot see: without its points (a confidence no
    // pixel reaches), the error above the LiDAR's field of view grows (here, at 320x180 with MVS
    // at 80x45, by about 10%; the full-size figures are in docs/BENCHMARKS.md). Only mvs_points
    // onwards rerun.
    let above = |extra: &[&str]| {
        let o = curation(&data, tmp.path(), None, extra);
        let report = text(&o);
        assert!(o.status.success(), "{report}");
        assert_eq!(executed(&report, "mvs"), 0, "{report}");
        mean_of(&report, "gt_above_lidar (raw)", 0)
    };
    let with_mvs = above(&[]);
    let lidar_only = above(&["--set", "mvs_points.min_confidence=2"]);
    assert!(with_mvs < 0.95 * lidar_only, "above the LiDAR: with MVS {with_mvs}, LiDAR only {lidar_only}");

    // Hold-out: a seeded 20% of each target sweep is left out of curation and scored on.
    let o = curation(&data, tmp.path(), None, &["--set", "aggregate.holdout=0.2"]);
    let report = text(&o);
    assert!(o.status.success(), "{report}");
    let held = mean_of(&report, "holdout (raw)", 0);
    assert!(held > 0.0 && held < 0.15, "{held}\n{report}");
}

#[test]
fn curation_runs_on_the_shared_nuscenes_keyframe_and_dgp_scene() {
    let tmp = tempfile::tempdir().unwrap();
    if let Some(nus) = shared_nuscenes() {
        let dir = tmp.path().join("nus");
        let o = curation(&nus, &dir, None, &["--set", "aggregate.holdout=0.2"]);
        let report = text(&o);
        assert!(o.status.success(), "{report}");
        assert!(!report.contains("gt ("), "real data has no dense ground truth");
        let held = mean_of(&report, "holdout (raw)", 0);
        assert!(held > 0.0 && held < 0.5, "{held}\n{report}");
        assert!(dir.join("out/scene-0061/CAM_FRONT/000_depth.exr").is_file());
        let labelled = against_hand_labels(&dir.join("out"), "nuscenes-scene0061-kf0", 6);
        // Target 99%: the lattice over bluish glass of CAM_FRONT_RIGHT's overhanging building is
        // still taken for sky (97.8% in all; 89.7% before sky pixels had to be blue or neutral;
        // docs/BENCHMARKS.md, "Real images against hand labels").
        assert!(labelled.bright_not_sky.value().unwrap() >= 0.97, "{labelled:?}");
    }
    let Some(dgp) = shared_dgp() else { return };
    let dir = tmp.path().join("dgp");
    std::fs::create_dir_all(&dir).unwrap();
    let o = curation(&dgp, &dir, Some("Dgp"), &["--set", "aggregate.holdout=0.2"]);
    let report = text(&o);
    assert!(o.status.success(), "{report}");
    assert_eq!(executed(&report, "complete"), 18, "3 samples x 6 cameras\n{report}");
    let held = mean_of(&report, "holdout (raw)", 0);
    assert!(held > 0.0 && held < 0.5, "{held}\n{report}");
    // Static structure seen by two frames: the share whose depths agree within 10% (issue 42's
    // target is 95%; today 89% at +-1 frame, docs/BENCHMARKS.md "Depth over time").
    let agree = table_row(&report, "temporal (temporal agreement)", "| all | +1 |");
    assert!(agree >= 85.0, "{agree}\n{report}");
    let labelled = against_hand_labels(&dir.join("out"), "dgp-scene02", 18);
    assert!(labelled.bright_not_sky.value().unwrap() >= 0.99, "{labelled:?}");
}

/// Scores the curated depth of an export against the hand labels of its real images
/// (tests/fixtures/real_labels, drawn on ../shared/data): every labelled image is scored; on each
/// the ego body is masked (>= 95% of its pixels at depth 0, <= 0.5% of the others) and, over all,
/// >= 95% of the labelled sky is at the sky depth. Returns the totals for the caller's targets.
fn against_hand_labels(out: &Path, dataset: &str, images: usize) -> dist4d_stages::eval::labels::LabelScores {
    use dist4d_stages::eval::labels::{score_export, LabelScores};
    let scored = score_export(out, &repo().join("tests/fixtures/real_labels").join(dataset), 100.0).unwrap();
    assert_eq!(scored.len(), images, "{scored:?}");
    let mut total = LabelScores::default();
    for s in &scored {
        if s.scores.ego_masked.of > 0 {
            assert!(s.scores.ego_masked.value().unwrap() >= 0.95, "{}: ego {}", s.depth, s.scores.ego_masked);
        }
        assert!(s.scores.other_masked.value().unwrap() <= 0.005, "{}: others {}", s.depth, s.scores.other_masked);
        total.add(&s.scores);
    }
    assert!(total.ego_masked.of > 0, "{dataset}: no labelled ego pixel");
    assert!(total.sky_at_sky.value().unwrap() >= 0.95, "{dataset}: sky {}", total.sky_at_sky);
    total
}

#[test]
fn the_12_hz_pipeline_curates_every_camera_image_and_moving_objects_follow_their_tracks() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    synth_camera_sweeps(&data, 320, 180);
    let pipeline = repo().join("pipelines/video_12hz.ron");
    // `dist4d eval` of the pipeline on `data` (its own store beside it), writing to `out`.
    let run_on = |data: &Path, out: &str, extra: &[&str]| {
        let root = format!("dataset.root={}", data.display());
        let (cache, out) = (data.with_extension("cache"), tmp.path().join(out));
        let mut args = vec!["eval", pipeline.to_str().unwrap(), "--set", &root];
        args.extend(["--cache", cache.to_str().unwrap(), "--out", out.to_str().unwrap(), "--progress", "off"]);
        args.extend(extra);
        let o = dist4d(&args);
        assert!(o.status.success(), "{}", text(&o));
        text(&o)
    };
    let run = |out: &str, extra: &[&str]| run_on(&data, out, extra);
    let report = run("out", &["--set", "clips.frames=4", "--set", "clips.stride=2"]);
    // 13 rounds x 6 cameras, each curated once; scored on moving objects too.
    assert_eq!(executed(&report, "complete"), 78, "{report}");
    let moving = mean_of(&report, "gt_moving (raw)", 0);
    assert!(moving > 0.0 && moving < 0.2, "Abs Rel on moving objects {moving}\n{report}");
    let depth_files = std::fs::read_dir(tmp.path().join("out/synth-0000/CAM_FRONT"))
        .unwrap()
        .filter(|e| e.as_ref().unwrap().file_name().to_string_lossy().ends_with("_depth.exr"))
        .count();
    assert_eq!(depth_files, 13);
    // Clips of 4 rounds every 2: 5 of the 13 rounds' clips, each image with its files.
    let jsonl = std::fs::read_to_string(tmp.path().join("out/synth-0000/clips.jsonl")).unwrap();
    let clips: Vec<serde_json::Value> = jsonl.lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    assert_eq!(clips.len(), 5);
    for clip in &clips {
        let frames = clip["frames"].as_array().unwrap();
        assert_eq!(frames.len(), 4);
        assert_eq!(clip["ego_trajectory"].as_array().unwrap().len(), 4);
        for frame in frames {
            let cameras = frame["cameras"].as_array().unwrap();
            assert_eq!(cameras.len(), 6);
            for c in cameras {
                assert!(data.join(c["image"].as_str().unwrap()).is_file(), "{c}");
                for file in ["depth", "confidence"] {
                    assert!(tmp.path().join("out").join(c[file].as_str().unwrap()).is_file(), "{file}: {c}");
                }
                assert_eq!(c["boxes_timestamp_us"], c["timestamp_us"], "boxes at the image's own time");
            }
        }
    }
    assert_eq!(clips[1]["frames"][0]["frame"], clips[0]["frames"][2]["frame"], "stride 2");
    // The numpy-only loader of docs/examples reads a clip.
    if let Some(python) = peers_python() {
        let o = std::process::Command::new(python)
            .arg(repo().join("docs/examples/clip_loader.py"))
            .arg(tmp.path().join("out"))
            .arg(&data)
            .output()
            .unwrap();
        let printed = String::from_utf8_lossy(&o.stdout);
        assert!(o.status.success(), "{printed}{}", String::from_utf8_lossy(&o.stderr));
        assert!(
            printed.contains("depth [4, 6, 180, 320]") && printed.contains("ego_trajectory [4, 4, 4]"),
            "{printed}"
        );
    } else {
        eprintln!("SKIPPED the clip loader: no peer venv (../shared/bench/peers/setup.sh)");
    }
    // Without following the tracks (the ablation) only FollowTracks and what depends on it rerun.
    let ablation = run("out_ablation", &["--set", "follow.moving_speed=1000"]);
    assert_eq!(executed(&ablation, "aggregate"), 0, "{ablation}");
    // And moving objects are scored worse. Not on the 3 keyframes above: their few moving agents
    // give the same error either way (0.139 / 0.139 at 320x180, 0.101 / 0.101 at 800x450), so
    // the comparison there tested noise. On 8 keyframes every camera is better with the tracks
    // (0.071 against 0.101 over cameras).
    let longer = tmp.path().join("data8");
    synth_camera_sweeps_of(&longer, 8, 320, 180);
    let moving_of = |out: &str, extra: &[&str]| mean_of(&run_on(&longer, out, extra), "gt_moving (raw)", 0);
    let (followed, unmoved) =
        (moving_of("out8", &[]), moving_of("out8_ablation", &["--set", "follow.moving_speed=1000"]));
    assert!(unmoved > 1.2 * followed, "without FollowTracks {unmoved}, with {followed}");
}

/// pipelines/video_12hz.ron from the CLI on the shared real data: DGP's 10 Hz samples are its
/// camera clock (`--set dataset=Dgp(..)` swaps the reader), and the nuScenes keyframe, which has
/// no camera sweeps, gives one round and says so.
#[test]
fn the_12_hz_pipeline_runs_on_the_shared_dgp_scene_and_nuscenes_keyframe() {
    let tmp = tempfile::tempdir().unwrap();
    let pipeline = repo().join("pipelines/video_12hz.ron");
    let run = |name: &str, dataset: &str| {
        let (cache, out) = (tmp.path().join(name).join("cache"), tmp.path().join(name).join("out"));
        let mut args = vec!["run", pipeline.to_str().unwrap(), "--set", dataset, "--progress", "off"];
        args.extend(["--cache", cache.to_str().unwrap(), "--out", out.to_str().unwrap()]);
        args.extend(["--set", "clips.frames=3", "--set", "clips.stride=1"]);
        let o = dist4d(&args);
        assert!(o.status.success(), "{}", text(&o));
        (text(&o), out)
    };
    if let Some(nus) = shared_nuscenes() {
        let (report, out) = run("nus", &format!("dataset.root={}", nus.display()));
        assert!(report.contains("at keyframes only") && report.contains("(first: scene-0061, 1 round(s))"), "{report}");
        assert_eq!(executed(&report, "complete"), 6, "{report}");
        // 1 round: no clip of 3, and no empty file nobody is told about.
        assert!(!out.join("scene-0061/clips.jsonl").exists(), "{report}");
        let why =
            "n/a: clips (ClipIndex): 1 of 1, nothing made: no clip: the scene has 1 frame(s), fewer than a clip's 3";
        assert!(report.contains(why), "{report}");
    }
    let Some(dgp) = shared_dgp() else { return };
    let (report, out) = run("dgp", &format!("dataset=Dgp(root: \"{}\")", dgp.display()));
    assert_eq!(executed(&report, "complete"), 18, "3 samples x 6 cameras\n{report}");
    let jsonl = std::fs::read_to_string(out.join("scene_02/clips.jsonl")).unwrap();
    let clips: Vec<serde_json::Value> = jsonl.lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    assert_eq!(clips.len(), 1, "{jsonl}");
    let frames = clips[0]["frames"].as_array().unwrap();
    assert_eq!(frames.len(), 3);
    for frame in frames {
        for c in frame["cameras"].as_array().unwrap() {
            assert!(dgp.join(c["image"].as_str().unwrap()).is_file(), "{c}");
            assert!(out.join(c["depth"].as_str().unwrap()).is_file(), "{c}");
        }
    }
}
