//! End-to-end tests: the real CLI on nuScenes-format data. The robustness tests (resume after
//! kills, two processes, incremental reruns, Ctrl-C, a truncated sweep) run on a multi-frame
//! dataset made from the shared real keyframe when it is there, and on a synthetic one otherwise,
//! so that they never silently pass on a machine without the shared data.

mod common;

use common::*;
use std::collections::BTreeMap;
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

fn pipeline() -> String {
    repo().join("pipelines/lidar_depth.ron").display().to_string()
}

fn run_args<'a>(root: &'a str, cache: &'a str, out: &'a str) -> Vec<&'a str> {
    vec!["run", "--progress", "off", "--cache", cache, "--out", out, "--set"]
        .into_iter()
        .chain(std::iter::once(Box::leak(format!("dataset.root={root}").into_boxed_str()) as &str))
        .collect()
}

#[test]
fn projected_point_counts_equal_the_nuscenes_devkit() {
    let Some(data) = shared_nuscenes() else { return };
    let tmp = tempfile::tempdir().unwrap();
    let (cache, out) = (tmp.path().join("c"), tmp.path().join("o"));
    let o = Command::new(bin())
        .args(["run", &pipeline(), "--progress", "off", "--set", &format!("dataset.root={}", data.display())])
        .args(["--cache", cache.to_str().unwrap(), "--out", out.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", text(&o));
    let front = read_npy_rows(&out.join("scene-0061/CAM_FRONT/000_uvz.npy"));
    assert_eq!(front.len(), 3053, "the devkit's count for CAM_FRONT");
    for f in ["000_depth.exr", "000_depth.png", "000_preview.png"] {
        assert!(out.join("scene-0061/CAM_FRONT").join(f).exists(), "{f}");
    }

    let Some(python) = peers_python() else { return };
    let checked = check_against_devkit(&python, &data, &tmp.path().join("peer"), |_, cam| {
        out.join(format!("scene-0061/{cam}/000_uvz.npy"))
    });
    assert_eq!(checked, 6);
}

#[test]
fn a_second_run_executes_nothing_and_explain_says_all_cached() {
    let s = multi_frame(1);
    let (cache, out) = (s.base.join("c"), s.base.join("o"));
    let root = s.root.clone();
    let args = run_args(&root, cache.to_str().unwrap(), out.to_str().unwrap());
    let mut first = vec![args[0]];
    first.push(Box::leak(pipeline().into_boxed_str()));
    first.extend(&args[1..]);
    assert!(dist4d(&first).status.success());
    let o = dist4d(&first);
    assert!(o.status.success());
    assert!(text(&o).contains("0 executed, 18 cached, 0 failed"), "{}", text(&o));
    let run = last_run(&cache);
    assert!(executed(&run).values().all(|&n| n == 0));
    let set = format!("dataset.root={root}");
    // The same --out as the run: the exported outputs are kept there, not in the store.
    let (cache, out) = (cache.to_str().unwrap(), out.to_str().unwrap());
    let o = dist4d(&["explain", &pipeline(), "--cache", cache, "--out", out, "--set", &set]);
    let t = text(&o);
    assert!(t.contains("project (ProjectLidar): 6 cached, 0 will run"), "{t}");
    assert!(t.contains("points (EncodePoints): 6 cached, 0 will run"), "{t}");
    assert!(t.contains("encode (EncodeDepth): 6 cached, 0 will run"), "{t}");
}

#[test]
fn a_bad_pipeline_exits_2_with_every_problem() {
    let tmp = tempfile::tempdir().unwrap();
    let bad = tmp.path().join("bad.ron");
    let text_in = std::fs::read_to_string(repo().join("pipelines/lidar_depth.ron"))
        .unwrap()
        .replace("min_depth: 1.0", "min_dept: 1.0")
        .replace("\"project.depth\"", "\"project.uvz\"");
    std::fs::write(&bad, text_in).unwrap();
    let o = dist4d(&["check", bad.to_str().unwrap()]);
    assert_eq!(o.status.code(), Some(2));
    let t = text(&o);
    assert!(t.contains("unknown param `min_dept`"), "{t}");
    assert!(t.contains("takes DepthMap but `project.uvz` gives ProjectedPoints"), "{t}");
    assert!(t.contains("bad.ron:"), "{t}");
    let o = dist4d(&["run", bad.to_str().unwrap()]);
    assert_eq!(o.status.code(), Some(2));
}

/// The clip index's paths are the pipeline's export templates: renaming an export without the
/// index (whose params are left at their defaults here) is a pipeline error, found before anything runs.
#[test]
fn a_clip_index_pointing_at_files_no_export_writes_is_a_pipeline_error() {
    let tmp = tempfile::tempdir().unwrap();
    let pipeline = tmp.path().join("video.ron");
    let shipped = std::fs::read_to_string(repo().join("pipelines/video_12hz.ron")).unwrap();
    let params = "\n            params: (depth: \"{scene}/{camera}/{frame}_depth.npy\", confidence: \"{scene}/{camera}/{frame}_support.npy\"),";
    assert!(shipped.contains(params));
    let edited = shipped
        .replace(params, "")
        .replace("\"{scene}/{camera}/{frame}_support.npy\"", "\"{scene}/{camera}/{frame}_conf.npy\"");
    std::fs::write(&pipeline, edited).unwrap();
    let o = dist4d(&["check", pipeline.to_str().unwrap()]);
    let t = text(&o);
    assert_eq!(o.status.code(), Some(2), "{t}");
    assert!(
        t.contains("param `confidence` of stage `clips` is `{scene}/{camera}/{frame}_support.npy`, which no export"),
        "{t}"
    );
    assert!(!t.contains("param `depth`"), "the depth default is exported: {t}");
    let o =
        dist4d(&["check", pipeline.to_str().unwrap(), "--set", "clips.confidence={scene}/{camera}/{frame}_conf.npy"]);
    assert!(o.status.success(), "{}", text(&o));
}

#[test]
fn eval_of_a_pipeline_that_exports_no_scores_fails_before_running() {
    let tmp = tempfile::tempdir().unwrap();
    let file = tmp.path().join("no_export.ron");
    let shipped = std::fs::read_to_string(repo().join("pipelines/curation.ron")).unwrap();
    let start = shipped.find("    export: {").expect("curation.ron has an export block");
    std::fs::write(&file, format!("{})\n", &shipped[..start])).unwrap();
    let o = dist4d(&["eval", file.to_str().unwrap(), "--progress", "off"]);
    assert_eq!(o.status.code(), Some(2));
    let t = text(&o);
    assert!(t.contains("stage `eval` (EvalDepth) is not exported"), "{t}");
    assert!(t.contains(r#""eval.json": "{scene}/{camera}/{frame}_metrics.json""#), "{t}");
    // Every scoring stage that is not exported is named at once.
    assert!(t.contains("stage `temporal` (EvalTemporal) is not exported"), "{t}");
    assert!(!tmp.path().join(".dist4d").exists(), "nothing may run: {t}");
}

struct Setup {
    _tmp: tempfile::TempDir,
    root: String,
    base: std::path::PathBuf,
}

/// A one-scene nuScenes dataset of `frames` keyframes: made from the shared real keyframe when it
/// is there, else synthesized (800x450 images, no sweeps between keyframes).
fn multi_frame(frames: usize) -> Setup {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path().join("nuscenes");
    if shared_nuscenes().is_some() {
        multi_frame_nuscenes(&root, frames);
    } else {
        eprintln!("using a synthetic dataset instead");
        let frames = frames.to_string();
        let args =
            ["synth", "--out", root.to_str().unwrap(), "--keyframes", &frames, "--width", "800", "--height", "450"];
        let o = dist4d(&[&args[..], &["--no-lidar-sweeps"]].concat());
        assert!(o.status.success(), "{}", text(&o));
    }
    let base = tmp.path().to_path_buf();
    Setup { _tmp: tmp, root: root.display().to_string(), base }
}

/// The LiDAR keyframe file of frame `frame` (keyframes in time order), as the tables name it.
fn lidar_file(s: &Setup, frame: usize) -> std::path::PathBuf {
    let root = Path::new(&s.root);
    let rows: serde_json::Value =
        serde_json::from_slice(&std::fs::read(root.join("v1.0-mini/sample_data.json")).unwrap()).unwrap();
    let mut keyframes: Vec<(i64, String)> = rows
        .as_array()
        .unwrap()
        .iter()
        .filter(|r| r["is_key_frame"] == true && r["filename"].as_str().unwrap().starts_with("samples/LIDAR_TOP/"))
        .map(|r| (r["timestamp"].as_i64().unwrap(), r["filename"].as_str().unwrap().to_string()))
        .collect();
    keyframes.sort();
    root.join(&keyframes[frame].1)
}

fn run_cmd(s: &Setup, cache: &str, out: &str, extra: &[&str]) -> Command {
    let mut c = Command::new(bin());
    c.args(["run", &pipeline()]);
    if !extra.contains(&"--progress") {
        c.args(["--progress", "off"]);
    }
    if !extra.contains(&"--jobs") {
        c.args(["--jobs", "2"]);
    }
    c.args(["--cache", s.base.join(cache).to_str().unwrap(), "--out", s.base.join(out).to_str().unwrap()])
        .args(["--set", &format!("dataset.root={}", s.root)])
        .args(extra);
    c
}

fn run_ok(s: &Setup, cache: &str, out: &str, extra: &[&str]) -> serde_json::Value {
    let o = run_cmd(s, cache, out, extra).output().unwrap();
    assert!(o.status.success(), "{}", text(&o));
    last_run(&s.base.join(cache))
}

fn counts(pairs: &[(&str, u64)]) -> BTreeMap<String, u64> {
    pairs.iter().map(|(s, n)| (s.to_string(), *n)).collect()
}

/// No temp file is left in the store or the output directory.
fn assert_no_partial_files(s: &Setup, cache: &str, out: &str) {
    let leftovers: Vec<String> = std::fs::read_dir(s.base.join(cache).join("tmp"))
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    assert!(leftovers.is_empty(), "store temp files left: {leftovers:?}");
    let out_tmp = s.base.join(out).join(".dist4d-tmp");
    let leftovers: Vec<_> =
        std::fs::read_dir(&out_tmp).map(|d| d.map(|e| e.unwrap().file_name()).collect()).unwrap_or_default();
    assert!(leftovers.is_empty(), "output temp files left: {leftovers:?}");
}

#[test]
fn runs_shows_a_run_in_progress_as_running_and_a_killed_one_as_killed() {
    let s = multi_frame(10);
    let cache = s.base.join("cache");
    let mut child =
        run_cmd(&s, "cache", "out", &["--jobs", "1"]).stdout(Stdio::null()).stderr(Stdio::null()).spawn().unwrap();
    let runs = || text(&dist4d(&["runs", "--cache", cache.to_str().unwrap()]));
    let t0 = Instant::now();
    while !runs().contains("Running") {
        assert!(t0.elapsed() < Duration::from_secs(30), "never shown running: {}", runs());
        std::thread::sleep(Duration::from_millis(20));
    }
    child.kill().unwrap(); // SIGKILL: no end recorded
    child.wait().unwrap();
    let listed = runs();
    assert!(listed.contains("Killed") && !listed.contains("Running"), "{listed}");
    let done = run_ok(&s, "cache", "out", &[]);
    assert_eq!(done["status"], "complete");
    assert!(runs().lines().last().unwrap().contains("Complete"), "{}", runs());
}

#[test]
fn a_run_whose_lease_others_removed_stops_and_a_rerun_finishes() {
    // Another process judged this one dead (it was suspended, or its filesystem stalled, for
    // longer than the lease timeout) and removed its lease: it may be redoing its scenes, so
    // this one stops instead of racing it. A short timeout makes the heartbeat notice quickly.
    let s = multi_frame(10);
    let cache = s.base.join("cache");
    let child = run_cmd(&s, "cache", "out", &["--jobs", "1"])
        .env("DIST4D_LEASE_TIMEOUT", "0.2")
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let t0 = Instant::now();
    let lease = loop {
        let found = std::fs::read_dir(cache.join("leases")).ok().and_then(|d| {
            d.filter_map(|e| e.ok()).map(|e| e.path()).find(|p| p.extension().is_some_and(|x| x == "lease"))
        });
        if let Some(l) = found {
            break l;
        }
        assert!(t0.elapsed() < Duration::from_secs(30), "no lease appeared");
        std::thread::sleep(Duration::from_millis(5));
    };
    std::fs::remove_file(&lease).unwrap();
    let o = child.wait_with_output().unwrap();
    let t = text(&o);
    assert_eq!(o.status.code(), Some(1), "{t}");
    assert!(t.contains("lease in the store was lost") && t.contains("rerun to finish"), "{t}");
    assert!(!lease.exists(), "not recreated");
    let done = run_ok(&s, "cache", "out", &[]);
    assert_eq!(done["status"], "complete");
    assert_no_partial_files(&s, "cache", "out");
}

#[test]
fn killed_runs_resume_to_byte_identical_outputs() {
    let s = multi_frame(10);
    let t0 = Instant::now();
    run_ok(&s, "ref-cache", "ref-out", &[]);
    let full = t0.elapsed();
    let reference = tree(&s.base.join("ref-out"));

    // Kill with SIGKILL at pseudo-random moments within the run's length, then finish it.
    let mut seed = (std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().as_nanos() as u64) | 1;
    let mut kills = Vec::new();
    for _ in 0..5 {
        seed ^= seed << 13;
        seed ^= seed >> 7;
        seed ^= seed << 17;
        let at = Duration::from_micros(seed % (full.as_micros() as u64).max(1));
        let mut child = run_cmd(&s, "cache", "out", &[]).stdout(Stdio::null()).stderr(Stdio::null()).spawn().unwrap();
        std::thread::sleep(at);
        child.kill().unwrap(); // SIGKILL
        child.wait().unwrap();
        kills.push(at);
    }
    let last = run_ok(&s, "cache", "out", &[]);
    assert_eq!(last["status"], "complete");
    assert_eq!(
        tree(&s.base.join("out")),
        reference,
        "outputs after kills at {kills:?} differ from an uninterrupted run"
    );
    assert_no_partial_files(&s, "cache", "out");
    // And nothing is left to do.
    let again = run_ok(&s, "cache", "out", &[]);
    assert!(executed(&again).values().all(|&n| n == 0));
}

#[test]
fn two_processes_on_one_store_both_finish_and_share_the_work() {
    let s = multi_frame(6);
    let reference = run_ok(&s, "ref-cache", "ref-out", &[]);
    let children: Vec<_> = (0..2)
        .map(|_| run_cmd(&s, "cache", "out", &[]).stdout(Stdio::piped()).stderr(Stdio::piped()).spawn().unwrap())
        .collect();
    for c in children {
        let o = c.wait_with_output().unwrap();
        assert!(o.status.success(), "{}", text(&o));
    }
    assert_eq!(tree(&s.base.join("out")), tree(&s.base.join("ref-out")));
    assert_no_partial_files(&s, "cache", "out");
    // Each task was executed by one of them: the other found it in the store.
    let o = dist4d(&["runs", "--cache", s.base.join("cache").to_str().unwrap(), "--json"]);
    let runs: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let total = |run: &serde_json::Value| executed(run).values().sum::<u64>();
    let both: u64 = runs.as_array().unwrap().iter().map(total).sum();
    assert_eq!(both, total(&reference), "{runs}");
}

#[test]
fn one_param_or_one_input_file_reruns_exactly_what_depends_on_it() {
    let s = multi_frame(4);
    let first = run_ok(&s, "cache", "out", &[]);
    assert_eq!(executed(&first), counts(&[("project", 24), ("points", 24), ("encode", 24)]));

    let r = run_ok(&s, "cache", "out", &["--set", "encode.preview_max_depth=50"]);
    assert_eq!(executed(&r), counts(&[("project", 0), ("points", 0), ("encode", 24)]));

    // A touch that does not change content reruns nothing (files are fingerprinted by content).
    let f = lidar_file(&s, 2);
    let bytes = std::fs::read(&f).unwrap();
    std::fs::write(&f, &bytes).unwrap();
    let r = run_ok(&s, "cache", "out", &["--set", "encode.preview_max_depth=50"]);
    assert_eq!(executed(&r), counts(&[("project", 0), ("points", 0), ("encode", 0)]));

    // Changing one frame's sweep reruns that frame's six projections, and only those. Moving a
    // point that no camera sees changes no projection: downstream work is cut off there.
    let mut changed = bytes.clone();
    changed[8..12].copy_from_slice(&(-50.0f32).to_le_bytes()); // point 0 far below the ground
    std::fs::write(&f, &changed).unwrap();
    let r = run_ok(&s, "cache", "out", &["--set", "encode.preview_max_depth=50"]);
    assert_eq!(executed(&r), counts(&[("project", 6), ("points", 0), ("encode", 0)]));
    // Lifting every point by 10 cm changes every camera of that frame.
    for p in changed.chunks_exact_mut(20) {
        let z = f32::from_le_bytes(p[8..12].try_into().unwrap());
        p[8..12].copy_from_slice(&(z + 0.1).to_le_bytes());
    }
    std::fs::write(&f, &changed).unwrap();
    let r = run_ok(&s, "cache", "out", &["--set", "encode.preview_max_depth=50"]);
    assert_eq!(executed(&r), counts(&[("project", 6), ("points", 6), ("encode", 6)]));
}

#[test]
fn outputs_are_byte_identical_for_one_and_several_jobs() {
    let s = multi_frame(3);
    run_ok(&s, "c1", "o1", &["--jobs", "1"]);
    run_ok(&s, "c2", "o2", &["--jobs", "4"]);
    assert_eq!(tree(&s.base.join("o1")), tree(&s.base.join("o2")));
}

#[test]
fn a_truncated_sweep_fails_its_frame_only() {
    let s = multi_frame(3);
    let f = lidar_file(&s, 1);
    let bytes = std::fs::read(&f).unwrap();
    std::fs::write(&f, &bytes[..bytes.len() - 7]).unwrap();
    let o = run_cmd(&s, "cache", "out", &[]).output().unwrap();
    assert_eq!(o.status.code(), Some(1), "{}", text(&o));
    let t = text(&o);
    assert!(t.contains("failed: project ") && t.contains("/001/CAM_FRONT: "), "{t}");
    let name = f.file_name().unwrap().to_string_lossy();
    assert!(t.contains(&format!("{name} is truncated")), "{t}");
    let run = last_run(&s.base.join("cache"));
    assert_eq!(executed(&run), counts(&[("project", 12), ("points", 12), ("encode", 12)]));
    assert_eq!(run["failures"].as_array().unwrap().len(), 6);
}

#[test]
fn ctrl_c_stops_cleanly_and_a_rerun_completes() {
    let s = multi_frame(10);
    let child =
        run_cmd(&s, "cache", "out", &["--jobs", "1"]).stdout(Stdio::piped()).stderr(Stdio::piped()).spawn().unwrap();
    std::thread::sleep(Duration::from_millis(400));
    let _ = Command::new("kill").args(["-INT", &child.id().to_string()]).status();
    let o = child.wait_with_output().unwrap();
    let t = text(&o);
    // Either the run ended before the signal, or it stopped cleanly with 130.
    if o.status.code() == Some(130) {
        assert!(t.contains("Interrupted"), "{t}");
        assert_no_partial_files(&s, "cache", "out");
    } else {
        assert!(o.status.success(), "{t}");
    }
    let o = run_cmd(&s, "cache", "out", &["--progress", "lines"]).env("DIST4D_PROGRESS_SECS", "1").output().unwrap();
    assert!(o.status.success());
    // Lines mode always ends with a line that shows every stage complete.
    let err = String::from_utf8_lossy(&o.stderr);
    let last = err.lines().filter(|l| l.starts_with("progress [")).last().unwrap_or_else(|| panic!("{err}"));
    for stage in ["project", "encode"] {
        assert!(last.contains(&format!("{stage} 60/60")), "{last}");
    }
    let full = run_ok(&s, "ref-cache", "ref-out", &[]);
    assert_eq!(full["status"], "complete");
    assert_eq!(tree(&s.base.join("out")), tree(&s.base.join("ref-out")));
}

#[test]
fn the_same_pipeline_runs_on_dgp_data() {
    let Some(dgp) = shared_dgp() else { return };
    let tmp = tempfile::tempdir().unwrap();
    // Only the dataset differs: both readers give the same items and artifact types.
    let file = tmp.path().join("dgp.ron");
    std::fs::write(&file, with_dataset("lidar_depth", &format!("Dgp(root: {:?})", dgp.display().to_string()))).unwrap();
    let out = tmp.path().join("out");
    let o = dist4d(&["run", file.to_str().unwrap(), "--progress", "off", "--out", out.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(text(&o).contains("54 executed"), "3 samples x 6 cameras x 3 stages: {}", text(&o));
    let front = read_npy_rows(&out.join("scene_02/CAMERA_01/001_uvz.npy"));
    assert!(front.len() > 2000, "{}", front.len());
}

/// Item keys are indices: the same pipeline run on a DGP scene into the store of a nuScenes run
/// has tasks of the same stage and item. `explain` of the nuScenes run compares with its own.
#[test]
fn explain_in_a_store_shared_with_another_dataset_gives_only_the_true_reason() {
    let (Some(nusc), Some(dgp)) = (shared_nuscenes(), shared_dgp()) else { return };
    let tmp = tempfile::tempdir().unwrap();
    let (cache, out) = (tmp.path().join("c"), tmp.path().join("o"));
    let o = run_lidar_depth(&nusc, &cache, &out);
    assert!(o.status.success(), "{}", text(&o));
    let file = tmp.path().join("lidar_depth.ron");
    std::fs::write(&file, with_dataset("lidar_depth", &format!("Dgp(root: {:?})", dgp.display().to_string()))).unwrap();
    let (cache, out) = (cache.to_str().unwrap(), out.to_str().unwrap());
    let o = dist4d(&["run", file.to_str().unwrap(), "--progress", "off", "--cache", cache]);
    assert!(o.status.success(), "{}", text(&o));
    let root = format!("dataset.root={}", nusc.display());
    let args = ["explain", &pipeline(), "--cache", cache, "--out", out, "--set", &root];
    let t = text(&dist4d(&[&args[..], &["--set", "project.min_depth=2"]].concat()));
    assert!(t.contains("project (ProjectLidar): 0 cached, 6 will run"), "{t}");
    assert!(t.contains("6 x param `min_depth` changed: 1.0 -> 2.0"), "{t}");
    assert!(!t.contains("input `"), "the DGP scene's inputs are not this run's: {t}");
}

/// `eval` runs the pipeline, often for minutes: it reports progress as `run` does, unasked.
#[test]
fn eval_reports_progress_by_default() {
    let Some(data) = shared_nuscenes() else { return };
    let tmp = tempfile::tempdir().unwrap();
    let curation = repo().join("pipelines/curation.ron");
    let o = Command::new(bin())
        .args(["eval", curation.to_str().unwrap(), "--jobs", "2"])
        .args(["--cache", tmp.path().join("c").to_str().unwrap(), "--out", tmp.path().join("o").to_str().unwrap()])
        .args(["--set", &format!("dataset.root={}", data.display())])
        .env("DIST4D_PROGRESS_SECS", "1")
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", text(&o));
    let err = String::from_utf8_lossy(&o.stderr);
    let last =
        err.lines().filter(|l| l.starts_with("progress [")).next_back().unwrap_or_else(|| panic!("no progress: {err}"));
    assert!(last.contains("complete 6/6"), "{last}");
}

/// `dist4d runs` run where `dist4d run pipelines/x.ron` was reads that run's store, and tells runs
/// of one pipeline apart by their dataset, output folder and --set values.
#[test]
fn runs_without_cache_reads_the_store_of_the_pipelines_and_tells_runs_apart() {
    let s = multi_frame(1);
    let dir = s.base.join("project");
    std::fs::create_dir_all(dir.join("pipelines")).unwrap();
    std::fs::copy(pipeline(), dir.join("pipelines/lidar_depth.ron")).unwrap();
    let in_project = |args: &[&str]| Command::new(bin()).args(args).current_dir(&dir).output().unwrap();
    let root = format!("dataset.root={}", s.root);
    let run = ["run", "pipelines/lidar_depth.ron", "--progress", "off", "--set", &root];
    let o = in_project(&run);
    assert!(o.status.success(), "{}", text(&o));
    let o = in_project(&[&run[..], &["--set", "encode.preview_max_depth=50", "--out", "other"]].concat());
    assert!(o.status.success(), "{}", text(&o));

    let o = in_project(&["runs"]);
    let t = text(&o);
    assert!(o.status.success() && t.contains("store: pipelines/.dist4d"), "{t}");
    let lines: Vec<&str> = t.lines().filter(|l| l.contains("lidar_depth")).collect();
    assert_eq!(lines.len(), 2, "{t}");
    for l in &lines {
        assert!(l.contains(&format!("dataset NuScenes {}", s.root)), "{l}");
    }
    assert!(lines[0].contains("out pipelines/out/lidar_depth") && !lines[0].contains("preview"), "{}", lines[0]);
    assert!(lines[1].contains("out other") && lines[1].contains("--set encode.preview_max_depth=50"), "{}", lines[1]);

    let o = in_project(&["runs", "--json"]);
    let runs: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let sets = &runs.as_array().unwrap()[1]["sets"];
    assert_eq!(sets, &serde_json::json!([root, "encode.preview_max_depth=50"]), "{runs}");
}

/// A finished output folder holds the exports and dist4d's lists, not an empty temp folder.
#[test]
fn a_finished_run_leaves_no_temp_folder_in_its_output() {
    let s = multi_frame(1);
    run_ok(&s, "cache", "out", &[]);
    assert!(!s.base.join("out/.dist4d-tmp").exists());
    assert!(s.base.join("out/index.json").is_file());
    run_ok(&s, "cache", "out", &["--set", "encode.preview_max_depth=50"]);
    assert!(!s.base.join("out/.dist4d-tmp").exists());
}

/// An `Option` param left unset (CompleteDepth's `worker`) is not set by default, not required.
#[test]
fn an_unset_option_param_is_listed_as_none_not_required() {
    let curation = repo().join("pipelines/curation.ron");
    let o = dist4d(&["check", curation.to_str().unwrap(), "--set", "complete.wrker=1"]);
    let t = text(&o);
    assert_eq!(o.status.code(), Some(2), "{t}");
    assert!(t.contains("worker (default None)") && !t.contains("(required)"), "{t}");
    let reference = std::fs::read_to_string(repo().join("docs/stages.md")).unwrap();
    assert!(!reference.contains("(required)"), "docs/stages.md is generated from the same defaults");
}

/// A nuScenes pipeline pointed at a path that does not exist, or at DGP data, says which.
#[test]
fn a_nuscenes_root_that_is_missing_or_dgp_data_says_so() {
    let tmp = tempfile::tempdir().unwrap();
    let run = |root: &Path| {
        let o = run_lidar_depth(root, &tmp.path().join("c"), &tmp.path().join("o"));
        assert_eq!(o.status.code(), Some(2), "refused before anything runs, as `check` refuses it");
        text(&o)
    };
    let missing = tmp.path().join("no-such-folder");
    let t = run(&missing);
    assert!(t.contains(&format!("{} does not exist", missing.display())), "{t}");
    let Some(dgp) = shared_dgp() else { return };
    let t = run(&dgp);
    assert!(t.contains("it looks like Dgp data: did you mean `Dgp(root: "), "{t}");
}

/// `dist4d runs --json | head` ends quietly when `head` has read enough, as Unix tools do: it
/// used to panic ("failed printing to stdout: Broken pipe").
#[test]
fn a_listing_whose_reader_went_away_ends_without_a_panic() {
    use std::os::unix::process::ExitStatusExt;
    let s = multi_frame(2);
    run_ok(&s, "cache", "out", &[]);
    let cache = s.base.join("cache");
    // A pipe whose reader is gone before dist4d starts (no race with its first write).
    let (reader, writer) = std::io::pipe().unwrap();
    drop(reader);
    let o = std::process::Command::new(bin())
        .args(["runs", "--json", "--cache", cache.to_str().unwrap()])
        .stdout(writer)
        .stderr(std::process::Stdio::piped())
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!err.contains("panicked"), "{err}");
    assert_eq!(o.status.signal(), Some(libc_sigpipe()), "ended by SIGPIPE, as `head` expects: {:?} {err}", o.status);
}

/// SIGPIPE's number on Linux.
fn libc_sigpipe() -> i32 {
    13
}
