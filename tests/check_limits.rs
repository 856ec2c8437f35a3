//! Inputs that used to abort `dist4d` (a stack overflow, a 70 GB allocation, a thread bomb) or
//! pass `check` only for every task to fail: each is now refused up front, exit 2, with the file
//! (or `--set`), line and column.

mod common;

use common::{dist4d, repo, text};
use std::path::{Path, PathBuf};
use std::process::Output;

fn curation() -> String {
    repo().join("pipelines/curation.ron").display().to_string()
}

/// The shipped curation pipeline with `from` replaced by `to`, written to `dir/name`.
fn curation_with(dir: &Path, name: &str, from: &str, to: &str) -> PathBuf {
    let shipped = std::fs::read_to_string(curation()).unwrap();
    assert_eq!(shipped.matches(from).count(), 1, "curation.ron holds `{from}` once");
    let path = dir.join(name);
    std::fs::write(&path, shipped.replace(from, to)).unwrap();
    path
}

/// 1-based `line:column` of the first `needle` in the file at `path`.
fn position(path: &Path, needle: &str) -> String {
    let text = std::fs::read_to_string(path).unwrap();
    let at = text.find(needle).unwrap();
    let line = text[..at].matches('\n').count() + 1;
    let column = text[..at].rsplit('\n').next().unwrap().chars().count() + 1;
    format!("{line}:{column}")
}

/// Exit code 2 (a bad pipeline, said before anything ran), not a crash by signal nor a failed run.
fn assert_refused(o: &Output) -> String {
    let out = text(o);
    assert_eq!(o.status.code(), Some(2), "{out}");
    out
}

#[test]
fn values_nested_20000_deep_are_refused_at_their_position_instead_of_overflowing_the_stack() {
    let tmp = tempfile::tempdir().unwrap();
    let deep = tmp.path().join("deep.ron");
    std::fs::write(&deep, format!("Pipeline(name: {}{})", "[".repeat(20_000), "]".repeat(20_000))).unwrap();
    let out = assert_refused(&dist4d(&["check", deep.to_str().unwrap()]));
    assert!(out.contains("values nest deeper than 64 levels here"), "{out}");
    // `Pipeline(` is level 1: the 64th `[` (column 15 + 64) is level 65.
    assert!(out.contains("deep.ron:1:79"), "{out}");

    let set = format!("mvs.max_planes={}", "[".repeat(20_000));
    let out = assert_refused(&dist4d(&["check", &curation(), "--set", &set]));
    assert!(out.contains("values nest deeper than 64 levels here"), "{out}");
    // The value after `mvs.max_planes=` (15 characters) starts at level 1: its 65th `[` is refused.
    assert!(out.contains("--> --set:1:80"), "{out}");
    // The snippet shows the part of the 20,000-character line around the position.
    assert!(out.len() < 2000, "{out}");
}

#[test]
fn params_that_size_allocations_are_bounded_by_check_and_run() {
    let sets = ["--set", "mvs.max_planes=1000000000", "--set", "mvs.plane_step_px=0.000001"];
    let out = assert_refused(&dist4d(&[&["check", &curation()][..], &sets].concat()));
    assert!(
        out.contains("`max_planes` of stage `mvs` (MultiViewStereo) must be in 8..=1024, found 1000000000"),
        "{out}"
    );
    assert!(out.contains("--> --set:1:16"), "{out}");
    assert!(
        out.contains(
            "`plane_step_px` of stage `mvs` (MultiViewStereo) must be a number in [0.01, 100], found 0.000001"
        ),
        "{out}"
    );
    assert!(out.contains("2 problems found; nothing was run"), "{out}");

    // `run` refuses the same before opening the dataset (which does not exist here).
    let tmp = tempfile::tempdir().unwrap();
    let (cache, outdir) = (tmp.path().join("c"), tmp.path().join("o"));
    let root = format!("dataset.root={}", tmp.path().join("none").display());
    let run = [
        "run",
        &curation(),
        "--progress",
        "off",
        "--cache",
        cache.to_str().unwrap(),
        "--out",
        outdir.to_str().unwrap(),
        "--set",
        &root,
    ];
    let out = assert_refused(&dist4d(&[&run[..], &sets].concat()));
    assert!(out.contains("`max_planes` of stage `mvs`"), "{out}");

    // Written in the file: the diagnostic is at the value.
    let file = curation_with(
        tmp.path(),
        "planes.ron",
        "        \"mvs\": MultiViewStereo(\n",
        "        \"mvs\": MultiViewStereo(\n            params: (max_planes: 1000000000),\n",
    );
    let out = assert_refused(&dist4d(&["check", file.to_str().unwrap()]));
    assert!(out.contains(&format!("planes.ron:{}", position(&file, "1000000000"))), "{out}");
}

#[test]
fn jobs_outside_1_to_1024_are_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let root = format!("dataset.root={}", tmp.path().join("none").display());
    let cache = tmp.path().join("c");
    for cmd in ["run", "eval"] {
        for (jobs, says) in [
            ("0", "at least 1 worker thread is needed"),
            ("100000", "100000 worker threads is over the limit of 1024"),
            ("1025", "over the limit of 1024"),
            ("many", "`many` is not a thread count"),
        ] {
            let o = dist4d(&[
                cmd,
                &curation(),
                "--progress",
                "off",
                "--cache",
                cache.to_str().unwrap(),
                "--set",
                &root,
                "--jobs",
                jobs,
            ]);
            let out = assert_refused(&o);
            assert!(out.contains("--jobs") && out.contains(says), "{cmd} --jobs {jobs}: {out}");
        }
        // The bound itself is accepted: the run goes on to the (missing) dataset.
        let o = dist4d(&[
            cmd,
            &curation(),
            "--progress",
            "off",
            "--cache",
            cache.to_str().unwrap(),
            "--set",
            &root,
            "-j",
            "1024",
        ]);
        let out = text(&o);
        assert_eq!(o.status.code(), Some(2), "{cmd}: {out}");
        assert!(!out.contains("--jobs") && out.contains("does not exist"), "{cmd}: {out}");
    }
}

#[test]
fn params_that_every_task_would_refuse_are_refused_by_check() {
    for (set, says) in [
        (
            "aggregate.holdout=NaN",
            "`holdout` of stage `aggregate` (AggregateLidar) must be a number in [0, 1], found NaN",
        ),
        ("aggregate.holdout=2", "`holdout` of stage `aggregate` (AggregateLidar) must be a number in [0, 1], found 2"),
        ("fuse.cell_px=0", "`cell_px` of stage `fuse` (FusePoints) must be in 1..=4096, found 0"),
        ("mvs.downscale=0", "`downscale` of stage `mvs` (MultiViewStereo) must be in 1..=64, found 0"),
    ] {
        let out = assert_refused(&dist4d(&["check", &curation(), "--set", set]));
        assert!(out.contains(says), "{set}: {out}");
        let value_at = set.find('=').unwrap() + 2;
        assert!(out.contains(&format!("--> --set:1:{value_at}")), "{set}: {out}");
    }
    // Written in the file.
    let tmp = tempfile::tempdir().unwrap();
    let file = curation_with(
        tmp.path(),
        "holdout.ron",
        "        \"aggregate\": AggregateLidar(\n",
        "        \"aggregate\": AggregateLidar(\n            params: (holdout: NaN),\n",
    );
    let out = assert_refused(&dist4d(&["check", file.to_str().unwrap()]));
    assert!(out.contains("`holdout` of stage `aggregate`"), "{out}");
    assert!(out.contains(&format!("holdout.ron:{}", position(&file, "NaN"))), "{out}");
}

#[test]
fn an_offset_of_the_most_negative_integer_is_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let file = curation_with(
        tmp.path(),
        "offset.ron",
        r#""sweeps": Window("dataset.lidar", frame, -1, 1)"#,
        r#""sweeps": Offset("dataset.lidar", frame, -9223372036854775808)"#,
    );
    let out = assert_refused(&dist4d(&["check", file.to_str().unwrap()]));
    assert!(out.contains("the offset -9223372036854775808 is out of range: offsets are within ±999999"), "{out}");
    assert!(out.contains(&format!("offset.ron:{}", position(&file, "-9223372036854775808"))), "{out}");
}

#[test]
fn a_pipeline_file_that_is_not_utf8_says_where() {
    let tmp = tempfile::tempdir().unwrap();
    let shipped = std::fs::read(curation()).unwrap();
    let at = shipped.windows(10).position(|w| w == b"\"curation\"").unwrap() + 4;
    let mut bytes = shipped.clone();
    bytes[at] = 0xFF;
    let file = tmp.path().join("latin1.ron");
    std::fs::write(&file, &bytes).unwrap();
    let out = assert_refused(&dist4d(&["check", file.to_str().unwrap()]));
    assert!(out.contains(&format!("the pipeline file is not valid UTF-8: byte {at} (0xFF)")), "{out}");
    let line = shipped[..at].iter().filter(|&&b| b == b'\n').count() + 1;
    let column = at - shipped[..at].iter().rposition(|&b| b == b'\n').unwrap();
    assert!(out.contains(&format!("latin1.ron:{line}:{column}")), "{out}");
}

#[test]
fn camera_names_must_be_one_path_component() {
    let out =
        assert_refused(&dist4d(&["check", &curation(), "--set", r#"dataset.cameras=["CAM_FRONT", "../../victim"]"#]));
    assert!(
        out.contains(
            "`cameras` of dataset NuScenes must be one file or folder name, without `/`, found `../../victim`"
        ),
        "{out}"
    );
    assert!(out.contains("--> --set:1:31"), "{out}");
    let out = assert_refused(&dist4d(&["check", &curation(), "--set", "dataset.cameras=[]"]));
    assert!(out.contains("`cameras` of dataset NuScenes must name at least one"), "{out}");
}

#[test]
fn the_shipped_pipelines_pass_check() {
    let mut checked = 0;
    for entry in std::fs::read_dir(repo().join("pipelines")).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_some_and(|e| e == "ron") {
            let o = dist4d(&["check", path.to_str().unwrap()]);
            assert!(o.status.success(), "{}: {}", path.display(), text(&o));
            checked += 1;
        }
    }
    assert!(checked >= 2, "{checked}");
}

#[test]
fn a_pipeline_name_and_export_paths_are_plain_path_names() {
    let tmp = tempfile::tempdir().unwrap();
    // The name is the default output folder `out/<name>/`: it may not climb out of `out/`.
    for (i, bad) in [r#"name: "../../victim""#, r#"name: "a\nb""#].iter().enumerate() {
        let file = curation_with(tmp.path(), &format!("name{i}.ron"), r#"name: "curation""#, bad);
        let out = assert_refused(&dist4d(&["check", file.to_str().unwrap()]));
        assert!(out.contains("the pipeline `name`") && out.contains(&position(&file, &bad[6..])), "{out}");
    }
    // Export templates: no `.` parts, no backslash, no control character (a newline would break
    // the manifest, one file per line).
    for (i, bad) in
        [r#""./{scene}/sheets/{frame}.png""#, r#""{scene}/she\nets/{frame}.png""#, r#""{scene}\\sheets\\{frame}.png""#]
            .iter()
            .enumerate()
    {
        let file = curation_with(tmp.path(), &format!("export{i}.ron"), r#""{scene}/sheets/{frame}.png""#, bad);
        let out = assert_refused(&dist4d(&["check", file.to_str().unwrap()]));
        assert!(out.contains("bad export path for `sheet.png`"), "{out}");
    }
    // Camera names with a control character (a terminal escape) are not file names either.
    let out = assert_refused(&dist4d(&["check", &curation(), "--set", "dataset.cameras=[\"CAM\\u{1b}[31mX\"]"]));
    assert!(out.contains("cameras"), "{out}");
    // A byte-order mark at the start of the file is not an error.
    let shipped = std::fs::read(curation()).unwrap();
    let bom = tmp.path().join("bom.ron");
    std::fs::write(&bom, [&[0xEF, 0xBB, 0xBF][..], &shipped].concat()).unwrap();
    let o = dist4d(&["check", bom.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o));
}

#[test]
fn inputs_a_stage_pairs_by_position_must_select_the_same_items() {
    // MultiViewStereo pairs each image with the calibration and pose at its position: images
    // over -1..999999 beside calibrations over -1..1 passed check and failed every task.
    let dir = tempfile::tempdir().unwrap();
    let from = r#""images": Window("dataset.image", frame, -1, 1),"#;
    let to = r#""images": Window("dataset.image", frame, -1, 999999),"#;
    let path = curation_with(dir.path(), "mvs.ron", from, to);
    let o = dist4d(&["check", path.to_str().unwrap()]);
    let out = assert_refused(&o);
    assert!(
        out.contains(
            "input `calibs` of stage `mvs` selects Window(frame, -1, 1) but `images` selects Window(frame, -1, 999999): \
             MultiViewStereo pairs `images`, `calibs`, `poses` up by position"
        ),
        "{out}"
    );
    assert!(out.contains("input `poses` of stage `mvs`"), "every mismatch is reported: {out}");
    // The line of the first mismatched input.
    assert!(out.contains(&position(&path, r#"Window("dataset.camera_calib", frame, -1, 1)"#)), "{out}");
    // The shipped pipelines pass.
    for p in std::fs::read_dir(repo().join("pipelines")).unwrap() {
        let p = p.unwrap().path();
        let o = dist4d(&["check", p.to_str().unwrap()]);
        assert!(o.status.success(), "{}: {}", p.display(), text(&o));
    }
}
