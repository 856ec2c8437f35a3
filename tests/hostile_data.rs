//! End-to-end tests of datasets written carelessly or with malice (issue 41): sizes that would
//! allocate hundreds of gigabytes, files that never end or never open, values that are not
//! numbers. Each must fail its items, naming the file, row and field, in bounded time, while the
//! rest of the run goes on.

mod common;

use common::*;
use serde_json::{json, Value};
use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::time::{Duration, Instant};

fn synthetic() -> (tempfile::TempDir, PathBuf) {
    synthetic_nuscenes(3)
}

/// Runs `dist4d args`; a run still going after `limit` is killed and the test fails (a hang must
/// fail the test, not hang the suite).
fn dist4d_within(args: &[&str], limit: Duration) -> Output {
    let mut command = Command::new(bin());
    command.args(args);
    finish_within(command, limit, |_| {})
}

/// Starts `command` with its output going to files (a pipe nobody reads would block a chatty run
/// and pass for a hang), calls `meanwhile` with the child, and waits at most `limit` after that.
fn finish_within(mut command: Command, limit: Duration, meanwhile: impl FnOnce(&std::process::Child)) -> Output {
    let logs = tempfile::tempdir().unwrap();
    let (out, err) = (logs.path().join("stdout"), logs.path().join("stderr"));
    command.stdout(std::fs::File::create(&out).unwrap()).stderr(std::fs::File::create(&err).unwrap());
    let mut child = command.spawn().unwrap();
    meanwhile(&child);
    let start = Instant::now();
    let status = loop {
        if let Some(status) = child.try_wait().unwrap() {
            break status;
        }
        if start.elapsed() > limit {
            child.kill().unwrap();
            let status = child.wait().unwrap();
            let o = Output { status, stdout: std::fs::read(&out).unwrap(), stderr: std::fs::read(&err).unwrap() };
            panic!("{command:?} still ran {limit:?} later:\n{}", text(&o));
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    Output { status, stdout: std::fs::read(&out).unwrap(), stderr: std::fs::read(&err).unwrap() }
}

/// `pipeline` (a shipped one) on `root`, with a fresh store and output folder under `tmp`.
fn run(tmp: &Path, root: &Path, pipeline: &str) -> Output {
    let p = repo().join(format!("pipelines/{pipeline}.ron"));
    let set_root = format!("dataset.root={}", root.display());
    let (cache, out) = (tmp.join("cache"), tmp.join("out"));
    let args = ["run", p.to_str().unwrap(), "--progress", "off", "--set", &set_root];
    let mut args = args.to_vec();
    args.extend(["--cache", cache.to_str().unwrap(), "--out", out.to_str().unwrap()]);
    dist4d_within(&args, Duration::from_secs(120))
}

/// Rows of `sample_data` whose file is of `channel` and a keyframe.
fn keyframe_rows(rows: &[Value], channel: &str) -> Vec<usize> {
    (0..rows.len())
        .filter(|&i| {
            rows[i]["is_key_frame"] == true && rows[i]["filename"].as_str().unwrap().contains(&format!("/{channel}/"))
        })
        .collect()
}

#[test]
fn image_sizes_beyond_the_bound_fail_their_items_naming_row_and_field() {
    for (w, h) in [(200_000u64, 200_000u64), (4_294_967_295, 4_294_967_295), (1000, 600)] {
        let (tmp, root) = synthetic();
        let mut rows = table(&root, "sample_data");
        let front = keyframe_rows(&rows, "CAM_FRONT");
        for &i in &front {
            rows[i]["width"] = json!(w);
            rows[i]["height"] = json!(h);
        }
        write_table(&root, "sample_data", &rows);
        let o = run(tmp.path(), &root, "lidar_depth");
        let t = text(&o);
        assert_eq!(o.status.code(), Some(1), "{w}x{h}: {t}");
        assert_eq!(t.matches("failed: project synth-0000/").count(), 3, "{t}");
        let token = rows[front[0]]["token"].as_str().unwrap();
        if w > 16384 {
            assert!(
                t.contains(&format!(
                    "sample_data.json row {} (token {token}): fields width, height {w}x{h} has a side over \
                     MAX_IMAGE_SIDE (16384 px)",
                    front[0]
                )),
                "{t}"
            );
        } else {
            // Within the bound but not the file's size: caught from the JPEG header, though the
            // LiDAR projection never decodes the image.
            assert!(
                t.contains(&format!("is 160x90 but sample_data {token} (fields width, height) says 1000x600")),
                "{t}"
            );
        }
        // The other cameras went on.
        assert!(tmp.path().join("out/synth-0000/CAM_BACK/000_depth.exr").exists(), "{t}");
    }
}

#[test]
fn a_fifo_or_a_link_to_dev_zero_in_the_dataset_fails_its_item_at_once() {
    let (tmp, root) = synthetic();
    let rows = table(&root, "sample_data");
    // Keyframe 1's sweep becomes a FIFO nobody writes to; keyframe 2's CAM_FRONT image a link to
    // /dev/zero.
    let lidar = keyframe_rows(&rows, "LIDAR_TOP");
    let sweep = root.join(rows[lidar[1]]["filename"].as_str().unwrap());
    std::fs::remove_file(&sweep).unwrap();
    let made = Command::new("mkfifo").arg(&sweep).status().unwrap();
    assert!(made.success());
    let image = root.join(rows[keyframe_rows(&rows, "CAM_FRONT")[2]]["filename"].as_str().unwrap());
    std::fs::remove_file(&image).unwrap();
    std::os::unix::fs::symlink("/dev/zero", &image).unwrap();

    for pipeline in ["lidar_depth", "curation"] {
        let _ = std::fs::remove_dir_all(tmp.path().join("out"));
        let o = run(tmp.path(), &root, pipeline);
        let t = text(&o);
        assert_eq!(o.status.code(), Some(1), "{pipeline}: {t}");
        // Named, with what it is, whether the store's fingerprinting or the reader met it first.
        let named = |path: &Path, kind: &str| {
            t.lines().any(|l| {
                l.contains(&path.display().to_string()) && l.contains("not a regular file") && l.contains(kind)
            })
        };
        assert!(named(&sweep, "FIFO"), "{pipeline}: {t}");
        if pipeline == "curation" {
            assert!(named(&image, "device"), "{t}");
        }
        if pipeline == "lidar_depth" {
            // (curation's frame 0 reads frame 1's sweep through its window.)
            assert!(tmp.path().join("out/synth-0000/CAM_FRONT/000_depth.exr").exists(), "frame 0 is fine: {t}");
        }
    }
}

/// Writes `points` as the `.pcd.bin` of keyframe `k`'s sweep (x, y, z, intensity, ring).
fn write_sweep(root: &Path, k: usize, points: &[[f32; 4]]) -> PathBuf {
    let rows = table(root, "sample_data");
    let path = root.join(rows[keyframe_rows(&rows, "LIDAR_TOP")[k]]["filename"].as_str().unwrap());
    let mut bytes = Vec::new();
    for p in points {
        for v in p.iter().chain([&0.0f32]) {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
    }
    std::fs::write(&path, bytes).unwrap();
    // Its lidarseg labels, one per point, so that only the points are wrong.
    let token = &rows[keyframe_rows(&rows, "LIDAR_TOP")[k]]["token"];
    let seg = table(root, "lidarseg").into_iter().find(|l| l["sample_data_token"] == *token).unwrap();
    std::fs::write(root.join(seg["filename"].as_str().unwrap()), vec![0u8; points.len()]).unwrap();
    path
}

#[test]
fn lidar_sweeps_of_nan_inf_or_1e30_fail_their_frame() {
    for (bad, why) in
        [(f32::NAN, "is NaN (not finite)"), (f32::INFINITY, "is inf (not finite)"), (1e30, "beyond MAX_LIDAR_RANGE_M")]
    {
        let (tmp, root) = synthetic();
        let all_bad = bad.is_nan();
        let points: Vec<[f32; 4]> = (0..100)
            .map(|i| if all_bad || i == 37 { [bad, 1.0, 1.0, 0.0] } else { [5.0 + i as f32 * 0.1, 1.0, 0.5, 10.0] })
            .collect();
        let path = write_sweep(&root, 1, &points);
        let o = run(tmp.path(), &root, "lidar_depth");
        let t = text(&o);
        assert_eq!(o.status.code(), Some(1), "{t}");
        let first = if all_bad { 0 } else { 37 };
        let count = if all_bad { 100 } else { 1 };
        assert!(
            t.contains(&format!("{}", path.display()))
                && t.contains(&format!("point {first}, field x, is"))
                && t.contains(why)
                && t.contains(&format!("{count} of its 100 points are bad")),
            "{t}"
        );
        assert_eq!(t.matches("failed: project synth-0000/001/").count(), 6, "{t}");
        assert!(!t.contains("failed: project synth-0000/000/"), "{t}");
    }
}

/// The sample rows of the scene in `next` order.
fn samples_in_order(root: &Path) -> Vec<usize> {
    let samples = table(root, "sample");
    let mut order = vec![samples.iter().position(|s| s["prev"] == "").unwrap()];
    while samples[*order.last().unwrap()]["next"] != "" {
        let next = samples[*order.last().unwrap()]["next"].clone();
        order.push(samples.iter().position(|s| s["token"] == next).unwrap());
    }
    order
}

#[test]
fn keyframe_timestamps_out_of_order_or_negative_fail_their_frames() {
    // (what is done to the three keyframes' timestamps, the frames that must fail)
    for (case, failing) in
        [("swapped", vec![0, 1, 2]), ("reversed", vec![0, 1, 2]), ("duplicated", vec![0, 1, 2]), ("negative", vec![0])]
    {
        let (tmp, root) = synthetic();
        let mut samples = table(&root, "sample");
        let order = samples_in_order(&root);
        let t: Vec<i64> = order.iter().map(|&i| samples[i]["timestamp"].as_i64().unwrap()).collect();
        let new = match case {
            "swapped" => vec![t[0], t[2], t[1]],
            "reversed" => vec![t[2], t[1], t[0]],
            "duplicated" => vec![t[0], t[0], t[2]],
            _ => vec![-t[0], t[1], t[2]],
        };
        for (k, &i) in order.iter().enumerate() {
            samples[i]["timestamp"] = json!(new[k]);
        }
        write_table(&root, "sample", &samples);
        let o = run(tmp.path(), &root, "lidar_depth");
        let text = text(&o);
        assert_eq!(o.status.code(), Some(1), "{case}: {text}");
        for k in 0..3 {
            let failed = text.contains(&format!("failed: project synth-0000/00{k}/"));
            assert_eq!(failed, failing.contains(&k), "{case}: frame {k}: {text}");
        }
        // The keyframe named: the first not after the one before it (or the negative one).
        let k = match case {
            "swapped" => 2,
            "negative" => 0,
            _ => 1,
        };
        let row = order[k];
        let token = samples[row]["token"].as_str().unwrap();
        let why = if case == "negative" { "is negative" } else { "is not after that of the keyframe before it" };
        assert!(
            text.contains(&format!("sample.json row {row} (token {token}): field timestamp {} {why}", new[k])),
            "{case}: {text}"
        );
    }
}

#[test]
fn focal_lengths_of_1e_300_or_1e300_fail_the_camera() {
    for f in [1e-300, 1e300] {
        let (tmp, root) = synthetic();
        let mut calibs = table(&root, "calibrated_sensor");
        let sensors = table(&root, "sensor");
        let front = sensors.iter().find(|s| s["channel"] == "CAM_FRONT").unwrap()["token"].clone();
        let c = calibs.iter().position(|c| c["sensor_token"] == front).unwrap();
        calibs[c]["camera_intrinsic"][0][0] = json!(f);
        write_table(&root, "calibrated_sensor", &calibs);
        let o = run(tmp.path(), &root, "lidar_depth");
        let t = text(&o);
        assert_eq!(o.status.code(), Some(1), "{t}");
        assert!(t.contains(&format!("calibrated_sensor.json row {c}")) && t.contains("field camera_intrinsic"), "{t}");
        assert!(t.contains(&format!("has focal lengths fx {f:e}")) && t.contains("FOCAL_PX"), "{t}");
        assert_eq!(t.matches("failed: project").count(), 3, "only CAM_FRONT: {t}");
    }
}

#[test]
fn boxes_with_a_zero_quaternion_or_a_negative_size_fail_the_frames_that_use_them() {
    for (field, value, why) in [
        ("rotation", json!([0.0, 0.0, 0.0, 0.0]), "field rotation [0, 0, 0, 0] is not a rotation"),
        ("size", json!([1.8, -4.5, 1.6]), "field size [1.8, -4.5, 1.6] has a side that is not positive"),
        ("translation", json!([f64::MAX, 0.0, 0.0]), "field translation [1.7976931348623157e308, 0, 0] is"),
    ] {
        let (tmp, root) = synthetic();
        let mut anns = table(&root, "sample_annotation");
        let order = samples_in_order(&root);
        let sample = table(&root, "sample")[order[1]]["token"].clone();
        let a = anns.iter().position(|a| a["sample_token"] == sample).unwrap();
        anns[a][field] = value;
        write_table(&root, "sample_annotation", &anns);
        let o = run(tmp.path(), &root, "curation");
        let t = text(&o);
        assert_eq!(o.status.code(), Some(1), "{field}: {t}");
        let token = anns[a]["token"].as_str().unwrap();
        assert!(t.contains(&format!("sample_annotation.json row {a} (token {token}): {why}")), "{field}: {t}");
        assert!(!t.contains("artifact is malformed"), "{field}: the bad value never reaches an artifact: {t}");
        assert!(!t.contains("null"), "{field}: {t}");
    }
}

#[test]
fn a_jpeg_with_corrupt_scan_data_fails_its_item() {
    let (tmp, root) = synthetic();
    let rows = table(&root, "sample_data");
    let path = root.join(rows[keyframe_rows(&rows, "CAM_FRONT")[1]]["filename"].as_str().unwrap());
    let mut jpeg = std::fs::read(&path).unwrap();
    // The scan starts after the last SOS marker (FF DA); garbage in its middle, markers intact.
    let sos = jpeg.windows(2).rposition(|w| w == [0xFF, 0xDA]).unwrap();
    let (start, end) = (sos + 20, jpeg.len() - 4);
    for i in (start..end).step_by(7) {
        jpeg[i] = if jpeg[i] == 0xFF || jpeg[i - 1] == 0xFF { jpeg[i] } else { jpeg[i] ^ 0x5A };
    }
    std::fs::write(&path, &jpeg).unwrap();
    let o = run(tmp.path(), &root, "curation");
    let t = text(&o);
    assert_eq!(o.status.code(), Some(1), "{t}");
    assert!(t.contains(&format!("{} is not a readable JPEG", path.display())), "{t}");
    assert!(t.contains("synth-0000/001/CAM_FRONT"), "{t}");
}

#[test]
fn sigterm_stops_a_run_inside_a_long_task_within_seconds() {
    // Each of these tasks runs for minutes (the exact occupancy at 0.1 m with 16^3 samples per
    // voxel), or tens of seconds (MultiViewStereo at full size with 900 planes; the completion's
    // refinement with 10,000 steps); a run used to wait for its running tasks before it stopped.
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path().join("data");
    let o =
        dist4d(&["synth", "--out", root.to_str().unwrap(), "--keyframes", "3", "--width", "800", "--height", "450"]);
    assert!(o.status.success(), "{}", text(&o));
    let grid = "exact.grid=(range: [-40.0, -40.0, -1.0, 40.0, 40.0, 5.4], voxel: 0.1, lift: 0.0)";
    let cases: [(&str, &str, &[&str]); 3] = [
        ("occupancy", "exact", &["exact.samples=16", grid]),
        ("curation", "mvs", &["mvs.downscale=1", "mvs.max_planes=900", "mvs.plane_step_px=0.05"]),
        ("curation", "complete", &["complete.refine_iterations=10000"]),
    ];
    for (pipeline, stage, sets) in cases {
        let p = repo().join(format!("pipelines/{pipeline}.ron"));
        let set_root = format!("dataset.root={}", root.display());
        let (cache, out) = (tmp.path().join(format!("cache-{stage}")), tmp.path().join(format!("out-{stage}")));
        let mut command = Command::new(bin());
        command.args(["run", p.to_str().unwrap(), "--progress", "off", "--jobs", "1", "--set", &set_root]).args([
            "--cache",
            cache.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ]);
        for set in sets {
            command.args(["--set", set]);
        }
        // SIGTERM once the run is in its long tasks; it must be over within 10 s of it.
        let o = finish_within(command, Duration::from_secs(10), |child| {
            std::thread::sleep(Duration::from_secs(8));
            let term = Command::new("kill").args(["-TERM", &child.id().to_string()]).status().unwrap();
            assert!(term.success());
        });
        let t = text(&o);
        assert_eq!(o.status.code(), Some(143), "{stage}: {t}");
        assert!(t.contains("Interrupted") && t.contains("rerun the same command to finish"), "{stage}: {t}");
        assert!(!t.contains("failed:"), "{stage}: a task cut short is not a failure: {t}");
        let run = last_run(&cache);
        assert_eq!(run["status"], "interrupted", "{stage}: {run}");
        let stats = run["stages"].as_array().unwrap().iter().find(|s| s["stage"] == stage).unwrap().clone();
        assert_eq!(stats["failed"], 0, "{stage}: {stats}");
    }
}

#[test]
fn jobs_times_the_mvs_budget_beyond_the_machine_s_memory_is_warned_about() {
    let (tmp, root) = synthetic();
    let meminfo = std::fs::read_to_string("/proc/meminfo").unwrap();
    let kib: u64 = meminfo
        .lines()
        .find_map(|l| l.strip_prefix("MemTotal:"))
        .unwrap()
        .trim()
        .trim_end_matches("kB")
        .trim()
        .parse()
        .unwrap();
    let over = (kib * 1024 / (4 << 30) + 1).min(1024);
    let p = repo().join("pipelines/curation.ron");
    let set_root = format!("dataset.root={}", root.display());
    for (jobs, warned) in [(over, true), (1, false)] {
        let (cache, out) = (tmp.path().join("cache"), tmp.path().join("out"));
        let jobs = jobs.to_string();
        let o = dist4d_within(
            &[
                "run",
                p.to_str().unwrap(),
                "--progress",
                "off",
                "--jobs",
                &jobs,
                "--set",
                &set_root,
                "--cache",
                cache.to_str().unwrap(),
                "--out",
                out.to_str().unwrap(),
            ],
            Duration::from_secs(120),
        );
        let t = text(&o);
        assert!(o.status.success(), "{t}");
        let expected = format!("warning: --jobs {jobs} x 4.0 GiB per task of stage `mvs`");
        assert_eq!(t.contains(&expected), warned, "{t}");
    }
}
