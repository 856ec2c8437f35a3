//! Scheduler behaviour on the synthetic grid: caching, incremental reruns, early cutoff,
//! failures, determinism.

use crate::exec::{Engine, RunOptions};
use crate::item::ItemKey;
use crate::operator::{Artifact, Operator, Output, Resource, TaskContext};
use crate::runs::{RunRecord, RunStatus};
use crate::store::{Access, Store};
use crate::testkit::{self, Grid};
use dist4d_graph::Pipeline;
use std::collections::BTreeMap;
use std::path::Path;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;

const CHAIN: &str = r#"Pipeline(
    dataset: Grid(scenes: 2, frames: 4, cameras: 3),
    stages: {
        "a": Echo(inputs: {"x": "dataset.camera_value"}),
        "b": Echo(inputs: {"x": "a.y"}, params: (size: 5000)),
        "per_frame": Merge(inputs: {"xs": Gather("b.y", camera)}),
        "window": Merge(inputs: {"xs": Window("per_frame.y", frame, -1, 1)}),
        "next": Echo(inputs: {"x": Offset("per_frame.y", frame, 1)}, grain: frame),
        "file": ToFile(inputs: {"x": "window.y"}, grain: frame),
    },
    export: {"file.file": "{scene}/{frame}.bin"},
)"#;

/// CHAIN where a stage reads the exported files: they are then kept in the store too.
fn chain_reading_its_files() -> String {
    let file = r#""file": ToFile(inputs: {"x": "window.y"}, grain: frame),"#;
    assert!(CHAIN.contains(file));
    CHAIN.replace(file, &format!(r#"{file} "reader": FromFile(inputs: {{"file": "file.file"}}),"#))
}

fn run_with(p: &Pipeline, grid: &Grid, store: &Path, opts: &RunOptions) -> RunRecord {
    let store = Store::open(store, Access::Shared).unwrap();
    let ops = testkit::operators(p);
    let engine = Engine { pipeline: p, dataset: grid, operators: &ops, store: &store };
    engine.run(opts).unwrap().record
}

fn run(p: &Pipeline, grid: &Grid, store: &Path) -> RunRecord {
    run_with(p, grid, store, &RunOptions { jobs: 2, ..Default::default() })
}

/// What `explain` says of `p` against the store in `store`.
fn explain(p: &Pipeline, grid: &Grid, store: &Path) -> Vec<crate::explain::StageExplain> {
    // As the CLI opens it: explain only reads.
    let store = Store::open(store, Access::ReadOnly).unwrap();
    let ops = testkit::operators(p);
    crate::explain::explain(&Engine { pipeline: p, dataset: grid, operators: &ops, store: &store }, None, None, None)
        .unwrap()
}

fn executed(r: &RunRecord) -> BTreeMap<String, u64> {
    r.stages.iter().map(|s| (s.stage.clone(), s.executed)).collect()
}

fn counts(pairs: &[(&str, u64)]) -> BTreeMap<String, u64> {
    pairs.iter().map(|(s, n)| (s.to_string(), *n)).collect()
}

#[test]
fn inputs_a_stage_does_not_read_with_its_params_are_never_loaded() {
    let pipeline = r#"Pipeline(
        dataset: Grid(scenes: 1, frames: 2, cameras: 3),
        stages: {"m": Merge(inputs: {"xs": Gather("dataset.camera_value", camera)}, params: (salt: SALT))},
        export: {},
    )"#;
    for (salt, loads) in [("1", 6), ("404", 0)] {
        let dir = tempfile::tempdir().unwrap();
        let p = testkit::load(&pipeline.replace("SALT", salt), &[]);
        let grid = testkit::grid_of(&p);
        assert_eq!(executed(&run(&p, &grid, dir.path())), counts(&[("m", 2)]));
        assert_eq!(grid.loads.load(Ordering::Relaxed), loads, "salt {salt}");
    }
}

#[test]
fn plans_every_selector_and_caches_the_second_run() {
    let dir = tempfile::tempdir().unwrap();
    let p = testkit::load(CHAIN, &[]);
    let grid = testkit::grid_of(&p);
    let first = run(&p, &grid, dir.path());
    assert_eq!(first.status, RunStatus::Complete);
    // 2 scenes x 4 frames x 3 cameras; `next` has no task for the last frame of each scene.
    assert_eq!(
        executed(&first),
        counts(&[("a", 24), ("b", 24), ("per_frame", 8), ("window", 8), ("next", 6), ("file", 8)])
    );
    assert_eq!(first.stages.iter().find(|s| s.stage == "next").unwrap().total, 6);
    let second = run(&p, &grid, dir.path());
    assert_eq!(second.executed(), 0);
    assert_eq!(second.cached(), first.executed());
    assert_eq!(grid.loads.load(std::sync::atomic::Ordering::Relaxed), 24, "cached runs read no sources");
}

#[test]
fn a_param_change_reruns_exactly_that_stage_and_its_descendants() {
    let dir = tempfile::tempdir().unwrap();
    let p = testkit::load(CHAIN, &[]);
    let grid = testkit::grid_of(&p);
    run(&p, &grid, dir.path());
    let changed = testkit::load(CHAIN, &["per_frame.salt=7"]);
    let r = run(&changed, &grid, dir.path());
    assert_eq!(executed(&r), counts(&[("a", 0), ("b", 0), ("per_frame", 8), ("window", 8), ("next", 6), ("file", 8)]));
    // Back to the old value: everything is still cached.
    assert_eq!(run(&p, &grid, dir.path()).executed(), 0);
}

#[test]
fn a_changed_source_reruns_exactly_the_items_that_read_it() {
    let dir = tempfile::tempdir().unwrap();
    let p = testkit::load(CHAIN, &[]);
    let grid = testkit::grid_of(&p);
    run(&p, &grid, dir.path());
    grid.bump("camera_value", ItemKey::new(&[1, 2, 0]));
    let r = run(&p, &grid, dir.path());
    // One camera of frame 2 of scene 1: its a, b; that frame's merge; the windows of frames
    // 1, 2, 3; `next` of frame 1 (reads frame 2); the files of the three windows.
    assert_eq!(executed(&r), counts(&[("a", 1), ("b", 1), ("per_frame", 1), ("window", 3), ("next", 1), ("file", 3)]));
}

#[test]
fn identical_upstream_bytes_cut_off_downstream_work() {
    let dir = tempfile::tempdir().unwrap();
    let p = testkit::load(CHAIN, &[]);
    let grid = testkit::grid_of(&p);
    run(&p, &grid, dir.path());
    // `note` changes a's key but not its output bytes.
    let r = run(&testkit::load(CHAIN, &["a.note=\"reworded\""]), &grid, dir.path());
    assert_eq!(executed(&r), counts(&[("a", 24), ("b", 0), ("per_frame", 0), ("window", 0), ("next", 0), ("file", 0)]));
}

#[test]
fn a_failing_item_skips_its_dependents_and_the_rest_goes_on() {
    let dir = tempfile::tempdir().unwrap();
    let p = testkit::load(CHAIN, &["b.fail_on=[\"s0/001/cam1\"]"]);
    let grid = testkit::grid_of(&p);
    let r = run(&p, &grid, dir.path());
    assert_eq!(r.status, RunStatus::Failed);
    assert_eq!(r.failures.len(), 1);
    assert_eq!(r.failures[0].stage, "b");
    assert_eq!(r.failures[0].item, "s0/001/cam1");
    assert!(r.failures[0].error.contains("asked to fail on s0/001/cam1"), "{}", r.failures[0].error);
    let by = |n: &str| r.stages.iter().find(|s| s.stage == n).unwrap().clone();
    assert_eq!((by("b").executed, by("b").failed), (23, 1));
    // Frame 1's merge, the windows of frames 0-2, `next` of frame 0 (reads frame 1), files of frames 0-2.
    assert_eq!((by("per_frame").executed, by("per_frame").skipped), (7, 1));
    assert_eq!((by("window").executed, by("window").skipped), (5, 3));
    assert_eq!((by("next").executed, by("next").skipped), (5, 1));
    assert_eq!((by("file").executed, by("file").skipped), (5, 3));
    // Failures are not cached: the rerun tries the failed task again and takes the rest from the cache.
    let again = run(&p, &grid, dir.path());
    let by = |n: &str| again.stages.iter().find(|s| s.stage == n).unwrap().clone();
    assert_eq!((by("b").executed, by("b").cached, by("b").failed), (0, 23, 1));
    assert_eq!((by("window").cached, by("window").skipped), (5, 3));
}

#[test]
fn an_output_of_the_wrong_type_fails_its_task_before_it_is_cached() {
    let dir = tempfile::tempdir().unwrap();
    let p = testkit::load(CHAIN, &["b.mistag=true"]);
    let grid = testkit::grid_of(&p);
    let r = run(&p, &grid, dir.path());
    assert_eq!(r.status, RunStatus::Failed);
    assert_eq!(r.failures.len(), 24);
    assert!(r.failures.iter().all(|f| f.stage == "b"));
    let err = &r.failures[0].error;
    assert!(
        err.contains(
            "stage `b` (Echo) returned a Mistagged for output `y`, which is declared Bytes; nothing was stored"
        ),
        "{err}"
    );
    // Nothing of b was cached: the same run again runs (and fails) every b task again.
    let again = run(&p, &grid, dir.path());
    assert_eq!(stat(&again, "b").failed, 24);
    assert_eq!(stat(&again, "b").cached, 0);
    assert_eq!(stat(&again, "a").cached, 24);
}

#[test]
fn fail_fast_stops_at_the_first_failure() {
    let dir = tempfile::tempdir().unwrap();
    let p = testkit::load(CHAIN, &["a.fail_on=[\"s0/000/cam0\"]"]);
    let grid = testkit::grid_of(&p);
    let r = run_with(&p, &grid, dir.path(), &RunOptions { jobs: 1, fail_fast: true, ..Default::default() });
    assert_eq!(r.status, RunStatus::Stopped);
    assert!(r.executed() + r.failed() < 20, "stopped early: {:?}", executed(&r));
}

#[test]
fn cancel_stops_cleanly_and_a_rerun_continues() {
    let dir = tempfile::tempdir().unwrap();
    let p = testkit::load(CHAIN, &[]);
    let grid = testkit::grid_of(&p);
    let opts = RunOptions { jobs: 1, ..Default::default() };
    opts.cancel.store(true, std::sync::atomic::Ordering::Relaxed);
    let r = run_with(&p, &grid, dir.path(), &opts);
    assert_eq!(r.status, RunStatus::Interrupted);
    let r = run(&p, &grid, dir.path());
    assert_eq!(r.status, RunStatus::Complete);
}

#[test]
fn outputs_are_identical_whatever_the_thread_count() {
    let p = testkit::load(CHAIN, &[]);
    let mut trees = Vec::new();
    for jobs in [1, 4] {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("out");
        let grid = testkit::grid_of(&p);
        run_with(
            &p,
            &grid,
            &dir.path().join("store"),
            &RunOptions { jobs, out_dir: Some(out.clone()), ..Default::default() },
        );
        let mut files: Vec<(String, Vec<u8>)> = Vec::new();
        for s in 0..2 {
            for f in 0..4 {
                let rel = format!("s{s}/{f:03}.bin");
                files.push((rel.clone(), std::fs::read(out.join(&rel)).unwrap()));
            }
        }
        files.push(("index.json".into(), std::fs::read(out.join("index.json")).unwrap()));
        trees.push(files);
    }
    assert_eq!(trees[0], trees[1]);
}

#[test]
fn a_missing_blob_is_recomputed_not_trusted() {
    let dir = tempfile::tempdir().unwrap();
    let p = testkit::load(CHAIN, &[]);
    let grid = testkit::grid_of(&p);
    run(&p, &grid, dir.path());
    // `b` outputs 5000 bytes: blobs in cas/. Remove them all.
    std::fs::remove_dir_all(dir.path().join("cas")).unwrap();
    let r = run(&p, &grid, dir.path());
    assert_eq!(r.status, RunStatus::Complete);
    assert_eq!(r.stages.iter().find(|s| s.stage == "b").unwrap().executed, 24);
}

/// Files under the store's `cas/` (blobs).
fn blobs(store: &Path) -> usize {
    fn count(dir: &Path) -> usize {
        std::fs::read_dir(dir)
            .map_or(0, |d| d.flatten().map(|e| if e.path().is_dir() { count(&e.path()) } else { 1 }).sum())
    }
    count(&store.join("cas"))
}

/// `a` makes its 5 000-byte output only when the run reads it.
const UNREAD: &str = r#"Pipeline(
    dataset: Grid(scenes: 1, frames: 2, cameras: 2),
    stages: {
        "a": Echo(inputs: {"x": "dataset.camera_value"}, params: (size: 5000, on_demand: true)),
        "b": Echo(inputs: {"x": "dataset.camera_value"}),
    },
)"#;

#[test]
fn an_output_nothing_reads_is_not_made_until_a_run_reads_it() {
    let dir = tempfile::tempdir().unwrap();
    let alone = testkit::load(UNREAD, &[]);
    let grid = testkit::grid_of(&alone);
    let r = run(&alone, &grid, dir.path());
    assert_eq!((r.status, executed(&r)), (RunStatus::Complete, counts(&[("a", 4), ("b", 4)])));
    // Not made, not stored: the same run with `a` making its output stores 4 blobs more.
    let unmade = blobs(dir.path());
    let made = tempfile::tempdir().unwrap();
    run(&testkit::load(UNREAD, &["a.on_demand=false"]), &grid, made.path());
    assert_eq!(blobs(made.path()), unmade + 4);
    assert_eq!(
        executed(&run(&alone, &grid, dir.path())),
        counts(&[("a", 0), ("b", 0)]),
        "an unmade output nobody reads is a hit"
    );
    // A reader added later: the records of `a` did not make what it reads, so `a` runs again.
    let read = UNREAD.replace(r#""b": Echo"#, r#""c": Echo(inputs: {"x": "a.y"}), "b": Echo"#);
    let read = testkit::load(&read, &[]);
    let e = explain(&read, &grid, dir.path());
    let a = e.iter().find(|s| s.stage == "a").unwrap();
    assert_eq!(a.will_run, 4);
    assert!(
        a.reasons.keys().any(|r| r.contains("output `y` is read now, and the cached task did not make it")),
        "{:?}",
        a.reasons
    );
    let r = run(&read, &grid, dir.path());
    assert_eq!(executed(&r), counts(&[("a", 4), ("b", 0), ("c", 4)]));
    assert_eq!(blobs(dir.path()), unmade + 4, "a's outputs (c's params are b's)");
    assert!(executed(&run(&read, &grid, dir.path())).values().all(|&n| n == 0));
    // The records now hold the made outputs: the first pipeline finds them too.
    assert!(executed(&run(&alone, &grid, dir.path())).values().all(|&n| n == 0));
}

/// Two pipelines on one store read different outputs of the same tasks (`p` has the same key in
/// both): each run makes what it reads and keeps what the record before it made, so the records
/// only gain outputs and both pipelines settle.
#[test]
fn pipelines_reading_different_outputs_of_one_task_settle() {
    let reading = |port: &str| {
        format!(
            r#"Pipeline(
                dataset: Grid(scenes: 1, frames: 2, cameras: 2),
                stages: {{
                    "p": Pair(inputs: {{"x": "dataset.camera_value"}}, params: (size: 5000, on_demand: true)),
                    "r": Echo(inputs: {{"x": "p.{port}"}}),
                }},
            )"#
        )
    };
    let dir = tempfile::tempdir().unwrap();
    let (y, z) = (testkit::load(&reading("y"), &[]), testkit::load(&reading("z"), &[]));
    let grid = testkit::grid_of(&y);
    let p_ran = |p: &Pipeline| executed(&run(p, &grid, dir.path()))["p"];
    assert_eq!(p_ran(&y), 4);
    assert_eq!(p_ran(&z), 4, "the records did not make z");
    assert_eq!(p_ran(&y), 0, "the rerun for z kept y");
    assert_eq!(p_ran(&z), 0);
}

#[test]
fn a_stage_that_does_not_make_an_output_the_run_reads_fails_and_stores_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let text = UNREAD
        .replace("on_demand: true", "never_make: true")
        .replace(r#""b": Echo(inputs: {"x": "dataset.camera_value"})"#, r#""b": Echo(inputs: {"x": "a.y"})"#);
    let p = testkit::load(&text, &[]);
    let grid = testkit::grid_of(&p);
    let r = run(&p, &grid, dir.path());
    assert_eq!(r.status, RunStatus::Failed);
    let a = r.stages.iter().find(|s| s.stage == "a").unwrap();
    assert_eq!((a.executed, a.failed), (0, 4));
    let b = r.stages.iter().find(|s| s.stage == "b").unwrap();
    assert_eq!(b.skipped, 4);
    assert!(
        r.failures.iter().any(|f| f.error.contains("did not make output `y`, which this run reads")),
        "{:?}",
        r.failures
    );
}

#[test]
fn scene_and_frame_filters_restrict_the_items() {
    let dir = tempfile::tempdir().unwrap();
    let p = testkit::load(CHAIN, &[]);
    let grid = testkit::grid_of(&p);
    let opts = RunOptions { jobs: 2, outer_items: Some(vec!["s1".into()]), limit: Some(2), ..Default::default() };
    let r = run_with(&p, &grid, dir.path(), &opts);
    assert_eq!(r.stages[0].executed, 6);
    let bad = RunOptions { outer_items: Some(vec!["nope".into()]), ..Default::default() };
    let store = Store::open(dir.path(), Access::Shared).unwrap();
    let ops = testkit::operators(&p);
    let err =
        Engine { pipeline: &p, dataset: &grid, operators: &ops, store: &store }.run(&bad).err().unwrap().to_string();
    assert!(err.contains("no scene `nope`"), "{err}");
}

#[test]
fn explain_says_what_changed() {
    let dir = tempfile::tempdir().unwrap();
    let p = testkit::load(CHAIN, &[]);
    let grid = testkit::grid_of(&p);
    let store = |d: &Path| Store::open(d, Access::Shared).unwrap();
    let explain = |p: &Pipeline| {
        let s = store(dir.path());
        let ops = testkit::operators(p);
        crate::explain::explain(&Engine { pipeline: p, dataset: &grid, operators: &ops, store: &s }, None, None, None)
            .unwrap()
    };
    let fresh = explain(&p);
    assert_eq!((fresh[0].cached, fresh[0].will_run), (0, 24));
    assert_eq!(fresh[0].reasons.keys().collect::<Vec<_>>(), vec!["never run"]);
    run(&p, &grid, dir.path());
    assert!(explain(&p).iter().all(|s| s.will_run == 0));
    let changed = testkit::load(CHAIN, &["b.salt=3"]);
    let e = explain(&changed);
    let b = e.iter().find(|s| s.stage == "b").unwrap();
    assert_eq!(b.will_run, 24);
    assert!(b.reasons.contains_key("param `salt` changed: 0 -> 3"), "{:?}", b.reasons);
    let pf = e.iter().find(|s| s.stage == "per_frame").unwrap();
    assert!(pf.reasons.contains_key("upstream `b` will run"), "{:?}", pf.reasons);
    grid.bump("camera_value", ItemKey::new(&[0, 0, 0]));
    let e = explain(&p);
    let a = e.iter().find(|s| s.stage == "a").unwrap();
    assert_eq!((a.cached, a.will_run), (23, 1));
    assert_eq!(a.reasons["input `x` (from `dataset.camera_value`) changed"].1, "s0/000/cam0");
}

/// After switching an upstream stage to other params and back (the second run cached), the
/// reasons compare with what the last run used, not with the newer records of the switch.
#[test]
fn explain_compares_with_what_the_last_run_used() {
    let dir = tempfile::tempdir().unwrap();
    let grid = testkit::grid_of(&testkit::load(CHAIN, &[]));
    for sets in [&[][..], &["a.salt=9"][..], &[][..]] {
        run(&testkit::load(CHAIN, sets), &grid, dir.path());
    }
    let e = explain(&testkit::load(CHAIN, &["b.salt=3"]), &grid, dir.path());
    let b = e.iter().find(|s| s.stage == "b").unwrap();
    assert_eq!(b.reasons.keys().collect::<Vec<_>>(), vec!["param `salt` changed: 0 -> 3"], "{:?}", b.reasons);
}

/// Explain walks the key layer a run walks, so it predicts what the next run executes (up to
/// early cutoff, which only running can find: it counts a task downstream of one that will run).
#[test]
fn explain_predicts_what_the_next_run_executes() {
    let dir = tempfile::tempdir().unwrap();
    let p = testkit::load(CHAIN, &[]);
    let grid = testkit::grid_of(&p);
    run(&p, &grid, dir.path());
    let predicted = |p: &Pipeline| -> BTreeMap<String, u64> {
        let s = Store::open(dir.path(), Access::Shared).unwrap();
        let ops = testkit::operators(p);
        let e = crate::explain::explain(
            &Engine { pipeline: p, dataset: &grid, operators: &ops, store: &s },
            None,
            None,
            None,
        );
        e.unwrap().into_iter().map(|s| (s.stage, s.will_run)).collect()
    };
    grid.bump("camera_value", ItemKey::new(&[1, 2, 0]));
    let changed = testkit::load(CHAIN, &["window.salt=5"]);
    let will_run = predicted(&changed);
    assert_eq!(will_run, executed(&run(&changed, &grid, dir.path())));
    assert_eq!(will_run, counts(&[("a", 1), ("b", 1), ("per_frame", 1), ("window", 8), ("next", 1), ("file", 8)]));
    assert!(predicted(&changed).values().all(|&n| n == 0));
}

#[test]
fn gc_keeps_what_recent_runs_use() {
    let dir = tempfile::tempdir().unwrap();
    let grid = testkit::grid_of(&testkit::load(CHAIN, &[]));
    run(&testkit::load(CHAIN, &["b.salt=1"]), &grid, dir.path());
    run(&testkit::load(CHAIN, &["b.salt=2"]), &grid, dir.path());
    let report = crate::gc::gc(dir.path(), 1, None, false).unwrap();
    assert_eq!((report.runs_kept, report.runs_dropped), (1, 1));
    // salt=1's b, per_frame, window, next, file records go; a is shared by both runs.
    assert_eq!(report.records_dropped, 24 + 8 + 8 + 6 + 8);
    assert!(report.blobs_dropped >= 24, "{report:?}");
    let again = run(&testkit::load(CHAIN, &["b.salt=2"]), &grid, dir.path());
    assert_eq!(again.executed(), 0, "the kept run is still fully cached");
    let old = run(&testkit::load(CHAIN, &["b.salt=1"]), &grid, dir.path());
    assert_eq!(old.stages.iter().find(|s| s.stage == "b").unwrap().executed, 24);
}

/// The one record segment of a store.
fn the_segment(store: &Path) -> std::path::PathBuf {
    let segs = crate::segment::segment_paths(&store.join("ac")).unwrap();
    assert_eq!(segs.len(), 1, "{segs:?}");
    segs[0].clone()
}

#[test]
fn a_flipped_bit_in_a_record_reruns_that_task_only() {
    let dir = tempfile::tempdir().unwrap();
    let p = testkit::load(CHAIN, &[]);
    let grid = testkit::grid_of(&p);
    let first = run(&p, &grid, dir.path());
    assert!(first.executed() > 50, "{:?}", executed(&first));
    let seg = the_segment(dir.path());
    let mut bytes = std::fs::read(&seg).unwrap();
    // A bit in the payload of the third record: the records after it are recovered.
    let mut at = 8;
    for _ in 0..2 {
        at += 8 + u32::from_le_bytes(bytes[at..at + 4].try_into().unwrap()) as usize;
    }
    bytes[at + 8 + 5] ^= 0x04;
    std::fs::write(&seg, &bytes).unwrap();
    let again = run(&p, &grid, dir.path());
    assert_eq!(again.executed(), 1, "{:?}", executed(&again));
}

#[test]
fn gc_leaves_what_it_cannot_read() {
    let dir = tempfile::tempdir().unwrap();
    let p = testkit::load(CHAIN, &[]);
    let grid = testkit::grid_of(&p);
    run(&p, &grid, dir.path());
    let foreign = dir.path().join("ac/zz-foreign.seg");
    std::fs::write(&foreign, b"some other program's file").unwrap();
    // A blob no record names, packed by a newer dist4d (a codec this one does not know).
    let newer = dir.path().join("cas/ff").join("f".repeat(62));
    std::fs::create_dir_all(newer.parent().unwrap()).unwrap();
    let mut file = crate::blob::MAGIC.to_vec();
    file.extend_from_slice(&[9, 0, 0, 0, 3, 0, 0, 0, 0, 0, 0, 0, 1, 2, 3]);
    std::fs::write(&newer, &file).unwrap();
    let report = crate::gc::gc(dir.path(), 0, None, false).unwrap();
    assert!(report.records_dropped > 50 && report.blobs_dropped > 0, "{report:?}");
    assert!(foreign.exists() && newer.exists(), "gc never deletes what it cannot read");
    assert_eq!(crate::segment::segment_paths(&dir.path().join("ac")).unwrap().len(), 2, "its own compacted one too");
}

#[test]
fn gc_dry_run_reports_what_gc_removes_and_removes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let grid = testkit::grid_of(&testkit::load(CHAIN, &[]));
    run(&testkit::load(CHAIN, &["b.salt=1"]), &grid, dir.path());
    run(&testkit::load(CHAIN, &["b.salt=2"]), &grid, dir.path());
    let files = |d: &Path| walk(d).len();
    let before = files(dir.path());
    // Beside a run holding the store: a dry run takes no lease and waits for nobody.
    let holder = Store::open(dir.path(), Access::Shared).unwrap();
    let dry = crate::gc::gc(dir.path(), 1, None, true).unwrap();
    drop(holder);
    assert_eq!(files(dir.path()), before);
    let real = crate::gc::gc(dir.path(), 1, None, false).unwrap();
    assert_eq!(dry, real);
}

/// Every file under `dir`.
fn walk(dir: &Path) -> Vec<std::path::PathBuf> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else {
                out.push(p);
            }
        }
    }
    out
}

#[test]
fn gc_counts_the_shards_of_one_group_as_one_run() {
    let dir = tempfile::tempdir().unwrap();
    let grid = testkit::grid_of(&testkit::load(CHAIN, &[]));
    run(&testkit::load(CHAIN, &["b.salt=1"]), &grid, dir.path());
    // The newest "run" is a group of two shards, each with half the scenes.
    let p = testkit::load(CHAIN, &["b.salt=2"]);
    for i in 0..2 {
        let opts = RunOptions { jobs: 2, shard: Some((i, 2)), group: Some("g".into()), ..Default::default() };
        run_with(&p, &grid, dir.path(), &opts);
    }
    // A run that was killed before it recorded its end (still "running"; gc holds the store
    // alone, so it is dead) neither counts as a run nor stays.
    let mut killed = crate::runs::list_runs(&dir.path().join("runs")).unwrap().remove(0);
    (killed.id, killed.status, killed.started) = ("9999999999999-dead".into(), RunStatus::Running, u64::MAX / 2);
    let killed_path = dir.path().join("runs").join(format!("{}.json", killed.id));
    std::fs::write(&killed_path, serde_json::to_vec(&killed).unwrap()).unwrap();
    let report = crate::gc::gc(dir.path(), 1, None, false).unwrap();
    assert_eq!((report.runs_kept, report.runs_dropped), (2, 1), "both shards kept, the older run dropped");
    assert!(!killed_path.exists());
    assert_eq!(run(&p, &grid, dir.path()).executed(), 0, "both shards' work is still cached");
}

/// Every file under `dir` but the manifest (which holds file stats), relative path -> digest.
fn files_under(dir: &Path) -> BTreeMap<String, String> {
    walk(dir)
        .into_iter()
        .filter(|p| !p.ends_with(".dist4d-manifest"))
        .map(|p| {
            let digest = crate::Digest::of(&std::fs::read(&p).unwrap()).short();
            (p.strip_prefix(dir).unwrap().display().to_string(), digest)
        })
        .collect()
}

fn index_paths(out: &Path) -> Vec<String> {
    let index: serde_json::Value = serde_json::from_slice(&std::fs::read(out.join("index.json")).unwrap()).unwrap();
    index["files"].as_array().unwrap().iter().map(|f| f["path"].as_str().unwrap().to_string()).collect()
}

#[test]
fn item_names_that_are_not_plain_names_never_leave_the_output_folder() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("a/b/out");
    std::fs::create_dir_all(dir.path().join("victim")).unwrap();
    std::fs::write(dir.path().join("victim/000.bin"), b"mine").unwrap();
    for names in [r#"["../../../victim", "ok"]"#, r#"["..", "ok"]"#, r#"["/tmp", "ok"]"#, r#"["a/b", "ok"]"#] {
        let p = testkit::load(CHAIN, &[&format!("dataset.names={names}")]);
        let grid = testkit::grid_of(&p);
        let opts = RunOptions { jobs: 2, out_dir: Some(out.clone()), ..Default::default() };
        let r = run_with(&p, &grid, &dir.path().join("store"), &opts);
        assert_eq!(r.status, RunStatus::Failed, "{names}");
        assert_eq!(r.failures.len(), 4, "one per frame of the bad scene: {:?}", r.failures);
        let e = &r.failures[0].error;
        assert!(e.contains("the scene name") && e.contains("cannot export `{scene}/{frame}.bin`"), "{e}");
        assert_eq!(r.exported, 4, "{names}");
        assert_eq!(index_paths(&out), ["ok/000.bin", "ok/001.bin", "ok/002.bin", "ok/003.bin"]);
    }
    // Nothing outside `out` was written: the user's file is intact and no other folder appeared.
    assert_eq!(std::fs::read(dir.path().join("victim/000.bin")).unwrap(), b"mine");
    let mut top: Vec<String> =
        std::fs::read_dir(dir.path()).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into()).collect();
    top.sort();
    assert_eq!(top, ["a", "store", "victim"]);
    assert_eq!(files_under(&dir.path().join("a")).len(), 5, "4 exports and index.json");
}

#[test]
fn an_output_folder_belongs_to_one_pipeline() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    let store = dir.path().join("store");
    let opts = RunOptions { jobs: 2, out_dir: Some(out.clone()), ..Default::default() };
    let p = testkit::load(CHAIN, &[]);
    let grid = testkit::grid_of(&p);
    assert_eq!(run_with(&p, &grid, &store, &opts).status, RunStatus::Complete);
    let before = files_under(&out);
    // Another pipeline (another name) with the same --out is refused before it runs anything.
    let other = testkit::load(&CHAIN.replace("Pipeline(", "Pipeline(name: \"other\", "), &["file.salt=1"]);
    let s = Store::open(&store, Access::Shared).unwrap();
    let ops = testkit::operators(&other);
    let err = Engine { pipeline: &other, dataset: &grid, operators: &ops, store: &s }.run(&opts).err().unwrap();
    let e = format!("{err:#}");
    assert!(e.contains("holds the exports of pipeline `test`") && e.contains("pipeline `other` will not"), "{e}");
    assert_eq!(files_under(&out), before, "nothing was overwritten");
    // The same pipeline with another param may rewrite its own files.
    let changed = testkit::load(CHAIN, &["file.salt=1"]);
    assert_eq!(run_with(&changed, &grid, &store, &opts).status, RunStatus::Complete);
    assert_ne!(files_under(&out), before);
    // A folder that holds files but no manifest was not made by dist4d: refused too.
    let foreign = dir.path().join("home");
    std::fs::create_dir_all(&foreign).unwrap();
    std::fs::write(foreign.join("index.json"), b"the user's own").unwrap();
    let opts = RunOptions { jobs: 2, out_dir: Some(foreign.clone()), ..Default::default() };
    let err = Engine { pipeline: &p, dataset: &grid, operators: &ops, store: &s }.run(&opts).err().unwrap();
    assert!(format!("{err:#}").contains("is not empty (it holds index.json)"), "{err:#}");
    assert_eq!(std::fs::read(foreign.join("index.json")).unwrap(), b"the user's own");
}

/// Overwrites every blob of the store with bytes of the same length.
fn corrupt_every_blob(store: &Path) -> usize {
    let mut n = 0;
    for shard in std::fs::read_dir(store.join("cas")).unwrap() {
        for blob in std::fs::read_dir(shard.unwrap().path()).unwrap() {
            let p = blob.unwrap().path();
            let len = std::fs::metadata(&p).unwrap().len() as usize;
            std::fs::write(&p, vec![0x5a; len]).unwrap();
            n += 1;
        }
    }
    n
}

fn stat(r: &RunRecord, stage: &str) -> crate::runs::StageStats {
    r.stages.iter().find(|s| s.stage == stage).unwrap().clone()
}

#[test]
fn a_corrupt_input_blob_is_recomputed_in_the_same_run() {
    let dir = tempfile::tempdir().unwrap();
    let p = testkit::load(CHAIN, &[]);
    let grid = testkit::grid_of(&p);
    run(&p, &grid, dir.path());
    assert!(corrupt_every_blob(dir.path()) >= 24);
    // per_frame reruns and reads b's (5000-byte) outputs from the store: all corrupt.
    let changed = testkit::load(CHAIN, &["per_frame.salt=7"]);
    let r = run(&changed, &grid, dir.path());
    assert_eq!(r.status, RunStatus::Complete, "{:?}", r.failures);
    assert_eq!(stat(&r, "b").recomputed, 24);
    assert_eq!(stat(&r, "per_frame").executed, 8);
    // The store is healed: a fresh store gives the same outputs, and a rerun executes nothing.
    let fresh = tempfile::tempdir().unwrap();
    run(&changed, &grid, fresh.path());
    assert_eq!(run(&changed, &grid, dir.path()).executed(), 0);
}

#[test]
fn a_corrupt_exported_blob_is_recomputed_and_exported() {
    let dir = tempfile::tempdir().unwrap();
    let (store, out) = (dir.path().join("store"), dir.path().join("out"));
    // 3000-byte files, which a stage reads: kept as blobs, and exported from them on a rerun.
    let p = testkit::load(&chain_reading_its_files(), &["file.size=3000"]);
    let grid = testkit::grid_of(&p);
    let opts = RunOptions { jobs: 2, out_dir: Some(out.clone()), ..Default::default() };
    run_with(&p, &grid, &store, &opts);
    let reference = files_under(&out);
    corrupt_every_blob(&store);
    for f in 0..4 {
        std::fs::remove_file(out.join(format!("s1/{f:03}.bin"))).unwrap();
    }
    let r = run_with(&p, &grid, &store, &opts);
    assert_eq!(r.status, RunStatus::Complete, "{:?}", r.failures);
    assert_eq!(stat(&r, "file").recomputed, 4);
    assert_eq!(r.exported, 8);
    assert_eq!(files_under(&out), reference);
}

#[test]
fn exports_from_compressed_blobs_are_byte_identical_to_fresh_ones() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    // 3000-byte files of a repeated digest, which a stage reads: kept compressed, exported from the
    // blob on a cached run.
    let p = testkit::load(&chain_reading_its_files(), &["file.size=3000"]);
    let grid = testkit::grid_of(&p);
    let first = dir.path().join("first");
    run_with(&p, &grid, &store, &RunOptions { jobs: 2, out_dir: Some(first.clone()), ..Default::default() });
    let packed = std::fs::read_dir(store.join("cas"))
        .unwrap()
        .flat_map(|d| std::fs::read_dir(d.unwrap().path()).unwrap())
        .filter(|b| !crate::blob::is_raw_file(&b.as_ref().unwrap().path()))
        .count();
    assert!(packed >= 8, "{packed} packed blobs");
    let second = dir.path().join("second");
    let r = run_with(&p, &grid, &store, &RunOptions { jobs: 2, out_dir: Some(second.clone()), ..Default::default() });
    assert_eq!((r.executed(), r.exported), (0, 8));
    assert_eq!(files_under(&second), files_under(&first));
    assert_eq!(crate::export::verify(&second).unwrap().ok, 8);
}

#[test]
fn exports_edited_in_place_are_found_and_rewritten() {
    let dir = tempfile::tempdir().unwrap();
    let (store, out) = (dir.path().join("store"), dir.path().join("out"));
    let p = testkit::load(CHAIN, &[]);
    let grid = testkit::grid_of(&p);
    let opts = RunOptions { jobs: 2, out_dir: Some(out.clone()), ..Default::default() };
    run_with(&p, &grid, &store, &opts);
    let reference = files_under(&out);
    let report = crate::export::verify(&out).unwrap();
    assert_eq!((report.ok, report.modified.len(), report.missing.len()), (8, 0, 0));
    // Same size, same mtime: only ctime (and the bytes) tell.
    let f = out.join("s0/002.bin");
    let mtime = std::fs::metadata(&f).unwrap().modified().unwrap();
    let mut bytes = std::fs::read(&f).unwrap();
    bytes[0] ^= 0xff;
    std::fs::write(&f, &bytes).unwrap();
    std::fs::File::options().write(true).open(&f).unwrap().set_modified(mtime).unwrap();
    std::fs::remove_file(out.join("s1/003.bin")).unwrap();
    let report = crate::export::verify(&out).unwrap();
    assert_eq!(
        (report.ok, report.modified.clone(), report.missing.clone()),
        (6, vec!["s0/002.bin".to_string()], vec!["s1/003.bin".to_string()])
    );
    let r = run_with(&p, &grid, &store, &opts);
    assert_eq!(r.executed(), 0);
    assert_eq!(files_under(&out), reference);
    assert_eq!(crate::export::verify(&out).unwrap().ok, 8);
}

#[test]
fn the_index_and_the_manifest_list_only_files_that_exist() {
    let dir = tempfile::tempdir().unwrap();
    let (store, out) = (dir.path().join("store"), dir.path().join("out"));
    let p = testkit::load(CHAIN, &[]);
    let grid = testkit::grid_of(&p);
    let opts = RunOptions { jobs: 2, out_dir: Some(out.clone()), ..Default::default() };
    run_with(&p, &grid, &store, &opts);
    // A folder where a file should go: that export fails on the rerun (the task itself is cached).
    std::fs::remove_file(out.join("s1/002.bin")).unwrap();
    std::fs::create_dir_all(out.join("s1/002.bin/in-the-way")).unwrap();
    let r = run_with(&p, &grid, &store, &opts);
    assert_eq!(r.status, RunStatus::Failed);
    assert_eq!(r.failures.len(), 1, "{:?}", r.failures);
    assert!(r.failures[0].error.contains("s1/002.bin"), "{}", r.failures[0].error);
    assert_eq!(r.exported, 7);
    let listed = index_paths(&out);
    assert_eq!(listed.len(), 7);
    assert!(!listed.contains(&"s1/002.bin".to_string()));
    let report = crate::export::verify(&out).unwrap();
    assert_eq!((report.ok, report.missing.len(), report.modified.len()), (7, 0, 0));
}

#[test]
fn a_folder_from_an_older_or_newer_dist4d_is_taken_over_only_when_this_pipeline_wrote_it() {
    let dir = tempfile::tempdir().unwrap();
    let (store, out) = (dir.path().join("store"), dir.path().join("out"));
    let p = testkit::load(CHAIN, &[]);
    let grid = testkit::grid_of(&p);
    let opts = RunOptions { jobs: 2, out_dir: Some(out.clone()), ..Default::default() };
    let engine_run = |p: &Pipeline| {
        let s = Store::open(&store, Access::Shared).unwrap();
        let ops = testkit::operators(p);
        Engine { pipeline: p, dataset: &grid, operators: &ops, store: &s }.run(&opts).map(|r| r.record)
    };
    assert_eq!(engine_run(&p).unwrap().status, RunStatus::Complete);
    let manifest = out.join(".dist4d-manifest");
    let v2 = std::fs::read_to_string(&manifest).unwrap();
    // A version-1 manifest (no owner line, as older releases wrote): this pipeline's own index
    // lets it take the folder over; another pipeline's stages do not.
    let v1: String = v2
        .lines()
        .skip(1)
        .map(|l| {
            let f: Vec<&str> = l.splitn(4, ' ').collect();
            format!("{} {} {}\n", f[0], f[1], f[3])
        })
        .collect();
    std::fs::write(&manifest, &v1).unwrap();
    let other = testkit::load(
        &CHAIN.replace("\"file\": ToFile", "\"other\": ToFile").replace("\"file.file\"", "\"other.file\""),
        &[],
    );
    let err = format!("{:#}", engine_run(&other).err().unwrap());
    assert!(err.contains("holds exports of stages `file`"), "{err}");
    assert_eq!(engine_run(&p).unwrap().status, RunStatus::Complete);
    assert!(std::fs::read_to_string(&manifest).unwrap().starts_with("dist4d-manifest 2 test\n"));
    // An empty manifest is a version-1 one without files: the same rule.
    std::fs::write(&manifest, "").unwrap();
    assert!(engine_run(&other).is_err());
    // A manifest of an unknown version names no owner this dist4d can read: refused.
    std::fs::write(&manifest, "dist4d-manifest 99 test\n").unwrap();
    let err = format!("{:#}", engine_run(&p).err().unwrap());
    assert!(err.contains("a manifest this dist4d does not read"), "{err}");
}

#[test]
fn a_folder_where_a_blob_should_be_is_replaced() {
    let dir = tempfile::tempdir().unwrap();
    let p = testkit::load(CHAIN, &[]);
    let grid = testkit::grid_of(&p);
    run(&p, &grid, dir.path());
    let mut n = 0;
    for shard in std::fs::read_dir(dir.path().join("cas")).unwrap() {
        for blob in std::fs::read_dir(shard.unwrap().path()).unwrap() {
            let path = blob.unwrap().path();
            std::fs::remove_file(&path).unwrap();
            std::fs::create_dir_all(path.join("in-the-way")).unwrap();
            n += 1;
        }
    }
    assert!(n >= 24);
    let changed = testkit::load(CHAIN, &["per_frame.salt=7"]);
    let r = run(&changed, &grid, dir.path());
    assert_eq!(r.status, RunStatus::Complete, "{:?}", r.failures);
    assert_eq!(run(&changed, &grid, dir.path()).executed(), 0);
}

// Outputs kept only in the output folder: exported, read by no stage, so not stored as blobs.

/// `file` outputs of 20000 bytes: too big to live inside their records, or to be stored when
/// only exported (see [`crate::keys::STORED_EXPORT_MAX`]).
const BIG_FILES: &[&str] = &["file.size=20000"];

/// Exported path -> digest (hex), from the output folder's index.
fn exported_digests(out: &Path) -> BTreeMap<String, String> {
    let index: serde_json::Value = serde_json::from_slice(&std::fs::read(out.join("index.json")).unwrap()).unwrap();
    let files = index["files"].as_array().unwrap().iter();
    files.map(|f| (f["path"].as_str().unwrap().to_string(), f["digest"].as_str().unwrap().to_string())).collect()
}

fn has_blob(store: &Path, hex: &str) -> bool {
    store.join("cas").join(&hex[..2]).join(&hex[2..]).is_file()
}

fn inode(path: &Path) -> u64 {
    std::os::unix::fs::MetadataExt::ino(&std::fs::metadata(path).unwrap())
}

fn exporting(out: &Path) -> RunOptions {
    RunOptions { jobs: 2, out_dir: Some(out.to_path_buf()), ..Default::default() }
}

/// A fresh store and output folder (in a temporary directory the caller keeps alive) and the
/// chain whose `file` outputs are big enough to live only in the output folder.
fn big_file_chain() -> (tempfile::TempDir, std::path::PathBuf, std::path::PathBuf, Pipeline, Grid) {
    let dir = tempfile::tempdir().unwrap();
    let (store, out) = (dir.path().join("store"), dir.path().join("out"));
    let p = testkit::load(CHAIN, BIG_FILES);
    let grid = testkit::grid_of(&p);
    (dir, store, out, p, grid)
}

#[test]
fn outputs_only_exported_are_kept_in_the_output_folder_not_in_the_store() {
    let (_dir, store, out, p, grid) = big_file_chain();
    let first = run_with(&p, &grid, &store, &exporting(&out));
    assert_eq!((first.status, first.exported), (RunStatus::Complete, 8));
    let files = exported_digests(&out);
    assert_eq!(files.len(), 8);
    assert!(files.values().all(|d| !has_blob(&store, d)), "exported files are not also blobs");
    // b's 5000-byte outputs, which stages read, are blobs as before.
    let blobs =
        std::fs::read_dir(store.join("cas")).unwrap().flat_map(|d| std::fs::read_dir(d.unwrap().path()).unwrap());
    assert!(blobs.count() >= 24);

    // Their records are hits while the files are in place: nothing runs, nothing is rewritten.
    let manifest = std::fs::read_to_string(out.join(".dist4d-manifest")).unwrap();
    let again = run_with(&p, &grid, &store, &exporting(&out));
    assert_eq!((again.executed(), again.exported), (0, 8));
    assert_eq!(std::fs::read_to_string(out.join(".dist4d-manifest")).unwrap(), manifest);

    // gc keeps their records (it has no blob of theirs to keep).
    crate::gc::gc(&store, 1, None, false).unwrap();
    assert_eq!(run_with(&p, &grid, &store, &exporting(&out)).executed(), 0);

    // A run that exports nothing keeps every output in the store: its bytes would be nowhere else.
    let r = run(&p, &grid, &store);
    assert_eq!(executed(&r), counts(&[("a", 0), ("b", 0), ("per_frame", 0), ("window", 0), ("next", 0), ("file", 8)]));
    assert!(files.values().all(|d| has_blob(&store, d)));
}

#[test]
fn a_deleted_edited_or_elsewhere_export_reruns_just_its_task() {
    let (dir, store, out, p, grid) = big_file_chain();
    run_with(&p, &grid, &store, &exporting(&out));
    let reference = files_under(&out);
    let only_file = |n| counts(&[("a", 0), ("b", 0), ("per_frame", 0), ("window", 0), ("next", 0), ("file", n)]);

    std::fs::remove_file(out.join("s1/002.bin")).unwrap();
    let r = run_with(&p, &grid, &store, &exporting(&out));
    assert_eq!(executed(&r), only_file(1));
    assert_eq!(files_under(&out), reference);
    assert_eq!(crate::export::verify(&out).unwrap().ok, 8);

    // Edited in place with the same size and mtime (only ctime tells): its task runs again. Touched
    // (another stat, the same bytes): hashed, found intact, a hit, and the file is not rewritten.
    let edited = out.join("s0/001.bin");
    let mtime = std::fs::metadata(&edited).unwrap().modified().unwrap();
    let mut bytes = std::fs::read(&edited).unwrap();
    bytes[7] ^= 0x20;
    std::fs::write(&edited, &bytes).unwrap();
    std::fs::File::options().write(true).open(&edited).unwrap().set_modified(mtime).unwrap();
    let touched = out.join("s0/003.bin");
    let touched_inode = inode(&touched);
    let later = std::fs::metadata(&touched).unwrap().modified().unwrap() + std::time::Duration::from_secs(5);
    std::fs::File::options().write(true).open(&touched).unwrap().set_modified(later).unwrap();
    let r = run_with(&p, &grid, &store, &exporting(&out));
    assert_eq!(executed(&r), only_file(1));
    assert_eq!(files_under(&out), reference);
    assert_eq!(inode(&touched), touched_inode, "an intact file is left alone");
    assert_eq!(run_with(&p, &grid, &store, &exporting(&out)).executed(), 0);

    // Another folder does not hold them: every task that exports runs again, nothing upstream.
    let elsewhere = dir.path().join("elsewhere");
    let r = run_with(&p, &grid, &store, &exporting(&elsewhere));
    assert_eq!(executed(&r), only_file(8));
    assert_eq!(files_under(&elsewhere), reference);
}

#[test]
fn exported_outputs_that_a_stage_reads_are_still_stored() {
    let dir = tempfile::tempdir().unwrap();
    let (store, out) = (dir.path().join("store"), dir.path().join("out"));
    let p = testkit::load(&chain_reading_its_files(), BIG_FILES);
    let grid = testkit::grid_of(&p);
    run_with(&p, &grid, &store, &exporting(&out));
    let reference = files_under(&out);
    assert!(exported_digests(&out).values().all(|d| has_blob(&store, d)));
    // A deleted export is written again from its blob: nothing runs.
    std::fs::remove_file(out.join("s1/002.bin")).unwrap();
    let r = run_with(&p, &grid, &store, &exporting(&out));
    assert_eq!((r.executed(), r.exported), (0, 8));
    assert_eq!(files_under(&out), reference);
}

#[test]
fn small_outputs_only_exported_are_still_stored() {
    let dir = tempfile::tempdir().unwrap();
    let (store, out) = (dir.path().join("store"), dir.path().join("out"));
    // 3000 bytes: not inside their records, but small enough to cost nothing in the store.
    let p = testkit::load(CHAIN, &["file.size=3000"]);
    let grid = testkit::grid_of(&p);
    run_with(&p, &grid, &store, &exporting(&out));
    let reference = files_under(&out);
    assert!(exported_digests(&out).values().all(|d| has_blob(&store, d)));
    std::fs::remove_dir_all(&out).unwrap();
    let r = run_with(&p, &grid, &store, &exporting(&out));
    assert_eq!((r.executed(), r.exported), (0, 8), "exported again from the store");
    assert_eq!(files_under(&out), reference);
}

#[test]
fn a_run_killed_after_its_exports_but_before_its_manifest_resumes_without_running_them_again() {
    let (_dir, store, out, p, grid) = big_file_chain();
    run_with(&p, &grid, &store, &exporting(&out));
    let reference = files_under(&out);
    let inodes: Vec<u64> = exported_digests(&out).keys().map(|rel| inode(&out.join(rel))).collect();
    // A first run killed at its end leaves the files and records, and the manifest that claimed
    // the folder when the run began (the owner, no files).
    std::fs::write(out.join(".dist4d-manifest"), "dist4d-manifest 2 test\n").unwrap();
    std::fs::remove_file(out.join("index.json")).unwrap();
    let r = run_with(&p, &grid, &store, &exporting(&out));
    assert_eq!((r.status, r.executed(), r.exported), (RunStatus::Complete, 0, 8));
    assert_eq!(files_under(&out), reference);
    let after: Vec<u64> = exported_digests(&out).keys().map(|rel| inode(&out.join(rel))).collect();
    assert_eq!(after, inodes, "the files were hashed, not written again");
    assert_eq!(crate::export::verify(&out).unwrap().ok, 8);
}

#[test]
fn a_task_whose_export_failed_leaves_no_record_and_runs_again() {
    let dir = tempfile::tempdir().unwrap();
    let (store, out) = (dir.path().join("store"), dir.path().join("out"));
    let grid = testkit::grid_of(&testkit::load(CHAIN, BIG_FILES));
    run_with(&testkit::load(CHAIN, BIG_FILES), &grid, &store, &exporting(&out));
    // New bytes for every file; one cannot be written (a folder is in its way).
    let p = testkit::load(CHAIN, &["file.size=20000", "file.salt=1"]);
    std::fs::remove_file(out.join("s1/002.bin")).unwrap();
    std::fs::create_dir_all(out.join("s1/002.bin/in-the-way")).unwrap();
    let r = run_with(&p, &grid, &store, &exporting(&out));
    assert_eq!(r.status, RunStatus::Failed);
    assert_eq!((stat(&r, "file").executed, r.exported, r.failures.len()), (8, 7, 1));
    assert!(r.failures[0].error.contains("s1/002.bin"), "{}", r.failures[0].error);
    // Its bytes are nowhere, so no record says they are: the task runs again, alone.
    std::fs::remove_dir_all(out.join("s1/002.bin")).unwrap();
    let r = run_with(&p, &grid, &store, &exporting(&out));
    assert_eq!((r.status, stat(&r, "file").executed, r.executed()), (RunStatus::Complete, 1, 1));
    let fresh = dir.path().join("fresh");
    run_with(&p, &grid, &dir.path().join("fresh-store"), &exporting(&fresh));
    assert_eq!(files_under(&out), files_under(&fresh));
}

#[test]
fn explain_looks_for_outputs_kept_only_in_the_output_folder_where_the_run_would() {
    let (dir, store, out, p, grid) = big_file_chain();
    run_with(&p, &grid, &store, &exporting(&out));
    std::fs::remove_file(out.join("s1/002.bin")).unwrap();
    let explain = |out_dir: Option<&Path>| {
        let s = Store::open(&store, Access::Shared).unwrap();
        let ops = testkit::operators(&p);
        let engine = Engine { pipeline: &p, dataset: &grid, operators: &ops, store: &s };
        let e = crate::explain::explain(&engine, None, None, out_dir).unwrap();
        e.into_iter().find(|s| s.stage == "file").unwrap()
    };
    let file = explain(Some(&out));
    assert_eq!((file.cached, file.will_run), (7, 1));
    let why = "output `file` is kept only in the output folder, and its file there is missing or changed";
    assert_eq!(file.reasons[why], (1, "s1/002".to_string()), "{:?}", file.reasons);
    let file = explain(Some(&dir.path().join("elsewhere")));
    assert_eq!((file.cached, file.will_run), (0, 8));
    assert_eq!(executed(&run_with(&p, &grid, &store, &exporting(&out)))["file"], 1, "as explained");
}

/// Per camera: a task per variant (`a`, `b`), each exported, and a gather of the variants.
const VARIANTS: &str = r#"Pipeline(
    dataset: Grid(scenes: 1, frames: 3, cameras: 2),
    stages: {
        "vary": Vary(inputs: {"x": "dataset.camera_value"}, params: (variants: {"a": 1, "b": 2})),
        "after": Echo(inputs: {"x": "vary.y"}, grain: variant),
        "file": ToFile(inputs: {"x": "after.y"}, grain: variant),
        "both": Merge(inputs: {"xs": Gather("after.y", variant)}, grain: camera),
    },
    export: {"file.file": "{scene}/{frame}_{camera}_{variant}.bin"},
)"#;

fn with_variants(p: &Pipeline) -> crate::WithVariants {
    crate::WithVariants { inner: Box::new(testkit::grid_of(p)), depth: 3, labels: p.variants.clone() }
}

fn run_on(p: &Pipeline, dataset: &dyn crate::Dataset, store: &Path, opts: &RunOptions) -> RunRecord {
    let store = Store::open(store, Access::Shared).unwrap();
    let ops = testkit::operators(p);
    Engine { pipeline: p, dataset, operators: &ops, store: &store }.run(opts).unwrap().record
}

#[test]
fn a_stage_with_variants_runs_per_variant_and_an_edited_variant_reruns_alone() {
    let dir = tempfile::tempdir().unwrap();
    let (store, out) = (dir.path().join("store"), dir.path().join("out"));
    let p = testkit::load(VARIANTS, &[]);
    assert_eq!(p.variants, ["a", "b"]);
    assert_eq!(p.dims.last().unwrap().name, "variant");
    let ds = with_variants(&p);
    let r = run_on(&p, &ds, &store, &exporting(&out));
    assert_eq!(r.status, RunStatus::Complete);
    assert_eq!(executed(&r), counts(&[("vary", 12), ("after", 12), ("file", 12), ("both", 6)]));
    // The variants differ (their own salts), and the exports name them.
    let a = std::fs::read(out.join("s0/001_cam1_a.bin")).unwrap();
    let b = std::fs::read(out.join("s0/001_cam1_b.bin")).unwrap();
    assert_ne!(a, b);
    // Variant b's salt edited: explain names that variant; only b's tasks and the gathers run again.
    let edited = testkit::load(VARIANTS, &["vary.variants={\"a\": 1, \"b\": 3}"]);
    {
        let store = Store::open(&store, Access::Shared).unwrap();
        let ops = testkit::operators(&edited);
        let ds = with_variants(&edited);
        let engine = Engine { pipeline: &edited, dataset: &ds, operators: &ops, store: &store };
        let report = crate::explain::explain(&engine, None, None, Some(&out)).unwrap();
        let vary = report.iter().find(|s| s.stage == "vary").unwrap();
        assert_eq!((vary.cached, vary.will_run), (6, 6));
        let reasons: Vec<&String> = vary.reasons.keys().collect();
        assert_eq!(reasons, ["variant `b` changed: 2 -> 3"], "{reasons:?}");
    }
    let r = run_on(&edited, &with_variants(&edited), &store, &exporting(&out));
    assert_eq!(executed(&r), counts(&[("vary", 6), ("after", 6), ("file", 6), ("both", 6)]));
    assert_eq!(std::fs::read(out.join("s0/001_cam1_a.bin")).unwrap(), a);
    assert_ne!(std::fs::read(out.join("s0/001_cam1_b.bin")).unwrap(), b);
}

#[test]
fn variants_must_be_declared_once_and_agree() {
    let text = VARIANTS.replace(
        r#""after": Echo(inputs: {"x": "vary.y"}, grain: variant),"#,
        r#""after": Vary(inputs: {"x": "vary.y"}, params: (variants: {"a": 1, "c": 2})),"#,
    );
    let err = dist4d_graph::load_str(
        "t.ron",
        &text,
        Path::new("t.ron"),
        Path::new("."),
        &[],
        Path::new("."),
        &testkit::TestCatalog::default(),
    )
    .unwrap_err()
    .render();
    assert!(err.contains("declares the variants a, c, and stage `vary` a, b"), "{err}");
    let none = VARIANTS.replace(
        r#""vary": Vary(inputs: {"x": "dataset.camera_value"}, params: (variants: {"a": 1, "b": 2})),"#,
        r#""vary": Echo(inputs: {"x": "dataset.camera_value"}),"#,
    );
    let err = dist4d_graph::load_str(
        "t.ron",
        &none,
        Path::new("t.ron"),
        Path::new("."),
        &[],
        Path::new("."),
        &testkit::TestCatalog::default(),
    )
    .unwrap_err()
    .render();
    assert!(err.contains("stage `after` runs per `variant`, but no stage of this pipeline declares variants"), "{err}");
}

#[test]
fn a_task_with_nothing_to_make_is_recorded_its_gathers_go_on_without_it_and_its_readers_are_passed_over() {
    let dir = tempfile::tempdir().unwrap();
    let (store, out) = (dir.path().join("store"), dir.path().join("out"));
    // A first run (its own store) where every task has something to make exports them all.
    let all = testkit::load(VARIANTS, &[]);
    run_on(&all, &with_variants(&all), &dir.path().join("store0"), &exporting(&out));
    assert!(out.join("s0/002_cam0_b.bin").exists() && out.join("s0/001_cam1_a.bin").exists());
    // `file` (exported) also says so itself on one item: it has nothing to export there.
    let p = testkit::load(VARIANTS, &["after.nothing_on=[\"s0/002/cam0/b\"]", "file.nothing_on=[\"s0/001/cam1/a\"]"]);
    let ds = with_variants(&p);
    let r = run_on(&p, &ds, &store, &exporting(&out));
    assert_eq!(r.status, RunStatus::Complete, "nothing to make is not a failure: {:?}", r.failures);
    let by = |r: &RunRecord, n: &str| r.stages.iter().find(|s| s.stage == n).unwrap().clone();
    assert_eq!((by(&r, "after").executed, by(&r, "after").not_applicable), (11, 1));
    // Its file has nothing to make either; the gather of that camera runs on variant a alone.
    assert_eq!((by(&r, "file").executed, by(&r, "file").not_applicable), (10, 2));
    assert!(!out.join("s0/001_cam1_a.bin").exists() && out.join("s0/001_cam1_b.bin").exists());
    assert_eq!((by(&r, "both").executed, by(&r, "both").not_applicable), (6, 0));
    // What the first run exported for the tasks that now have nothing to make is gone.
    assert!(!out.join("s0/002_cam0_b.bin").exists() && out.join("s0/002_cam0_a.bin").exists());
    // Recorded: the rerun asks nobody again, and explain says so.
    let again = run_on(&p, &ds, &store, &exporting(&out));
    assert_eq!(again.executed(), 0);
    assert_eq!((by(&again, "after").cached, by(&again, "after").not_applicable), (11, 1));
    assert_eq!(by(&again, "file").not_applicable, 2);
    let store = Store::open(&store, Access::Shared).unwrap();
    let ops = testkit::operators(&p);
    let engine = Engine { pipeline: &p, dataset: &ds, operators: &ops, store: &store };
    let report = crate::explain::explain(&engine, None, None, Some(&out)).unwrap();
    let e = |n: &str| report.iter().find(|s| s.stage == n).unwrap().clone();
    assert_eq!((e("after").cached, e("after").not_applicable, e("after").will_run), (11, 1, 0));
    assert_eq!((e("file").cached, e("file").not_applicable, e("file").will_run), (10, 2, 0));
    assert_eq!((e("both").cached, e("both").will_run), (6, 0));
}

#[test]
fn across_gives_a_task_its_siblings_and_a_changed_sibling_reruns_them_all() {
    let text = r#"Pipeline(
        dataset: Grid(scenes: 1, frames: 2, cameras: 3),
        stages: {
            "a": Echo(inputs: {"x": "dataset.camera_value"}),
            "surround": Merge(inputs: {"xs": Across("a.y", camera)}, grain: camera),
        },
    )"#;
    let dir = tempfile::tempdir().unwrap();
    let p = testkit::load(text, &[]);
    let plan = crate::plan::plan_outer(&p, &crate::plan::View::all(&testkit::grid_of(&p)), 0);
    let surround: Vec<_> =
        plan.tasks.iter().filter(|t| t.node as usize == p.node_by_name("surround").unwrap()).collect();
    assert_eq!(surround.len(), 6);
    for t in &surround {
        let positions: Vec<i64> = t.inputs[0]
            .iter()
            .map(|s| match s {
                crate::plan::InputSrc::Task { pos, .. } => *pos,
                other => panic!("{other:?}"),
            })
            .collect();
        assert_eq!(positions, [0, 1, 2], "every camera of the frame, by camera index");
    }
    let grid = testkit::grid_of(&p);
    run(&p, &grid, dir.path());
    grid.bump("camera_value", ItemKey::new(&[0, 1, 2]));
    let r = run(&p, &grid, dir.path());
    assert_eq!(executed(&r), counts(&[("a", 1), ("surround", 3)]));
}

/// A stage whose tasks wait on an external resource: each holds its slot until a task of another
/// stage has finished (or gives up after a while), and counts how many wait at once.
struct Waiting {
    slots: usize,
    now: Arc<AtomicUsize>,
    most: Arc<AtomicUsize>,
    others_done: Arc<AtomicUsize>,
    saw_others: Arc<AtomicUsize>,
    inner: Box<dyn Operator>,
}

impl Operator for Waiting {
    fn run(&self, ctx: &TaskContext, inputs: &[Vec<Artifact>]) -> anyhow::Result<crate::Made<Vec<Output>>> {
        let now = self.now.fetch_add(1, Ordering::SeqCst) + 1;
        self.most.fetch_max(now, Ordering::SeqCst);
        let start = self.others_done.load(Ordering::SeqCst);
        let until = std::time::Instant::now() + std::time::Duration::from_secs(5);
        while self.others_done.load(Ordering::SeqCst) == start && std::time::Instant::now() < until {
            std::thread::sleep(std::time::Duration::from_millis(2));
        }
        if self.others_done.load(Ordering::SeqCst) > start {
            self.saw_others.fetch_add(1, Ordering::SeqCst);
        }
        self.now.fetch_sub(1, Ordering::SeqCst);
        self.inner.run(ctx, inputs)
    }
    fn resource(&self) -> Option<Resource> {
        Some(Resource { name: "gpu".into(), slots: self.slots })
    }
}

struct Counting {
    done: Arc<AtomicUsize>,
    inner: Box<dyn Operator>,
}

impl Operator for Counting {
    fn run(&self, ctx: &TaskContext, inputs: &[Vec<Artifact>]) -> anyhow::Result<crate::Made<Vec<Output>>> {
        let out = self.inner.run(ctx, inputs);
        std::thread::sleep(std::time::Duration::from_millis(5));
        self.done.fetch_add(1, Ordering::SeqCst);
        out
    }
}

#[test]
fn tasks_waiting_on_a_resource_take_its_slots_not_the_cpu_threads() {
    let text = r#"Pipeline(
        dataset: Grid(scenes: 2, frames: 4, cameras: 3),
        stages: {
            "model": Echo(inputs: {"x": "dataset.camera_value"}),
            "cpu": Echo(inputs: {"x": "dataset.camera_value"}, params: (salt: 1)),
        },
    )"#;
    let p = testkit::load(text, &[]);
    let grid = testkit::grid_of(&p);
    let dir = tempfile::tempdir().unwrap();
    let store = Store::open(dir.path(), Access::Shared).unwrap();
    let (now, most, others_done, saw_others) = Default::default();
    let mut ops = testkit::operators(&p);
    for (n, node) in p.nodes.iter().enumerate() {
        let Some(inner) = ops[n].take() else { continue };
        ops[n] = Some(match node.name.as_str() {
            "model" => Box::new(Waiting {
                slots: 2,
                now: Arc::clone(&now),
                most: Arc::clone(&most),
                others_done: Arc::clone(&others_done),
                saw_others: Arc::clone(&saw_others),
                inner,
            }),
            _ => Box::new(Counting { done: Arc::clone(&others_done), inner }),
        });
    }
    let engine = Engine { pipeline: &p, dataset: &grid, operators: &ops, store: &store };
    // One CPU thread: were the waiting tasks on it, the other stage could not run meanwhile.
    let r = engine.run(&RunOptions { jobs: 1, ..Default::default() }).unwrap().record;
    assert_eq!(r.status, RunStatus::Complete);
    assert_eq!(executed(&r), counts(&[("model", 24), ("cpu", 24)]));
    assert_eq!(most.load(Ordering::SeqCst), 2, "as many waiting at once as the resource has slots");
    assert!(
        saw_others.load(Ordering::SeqCst) >= 20,
        "the CPU stage ran while the model's tasks waited: {saw_others:?}"
    );
}

#[test]
fn a_stage_with_every_runs_on_every_nth_item_and_its_readers_only_there() {
    let text = r#"Pipeline(
        dataset: Grid(scenes: 2, frames: 5, cameras: 3),
        stages: {
            "frames": Merge(inputs: {"xs": Gather("dataset.camera_value", camera)}),
            "windows": Merge(inputs: {"xs": Window("frames.y", frame, 0, 1)}, every: 2),
            "after": Echo(inputs: {"x": "windows.y"}, grain: frame),
        },
    )"#;
    let dir = tempfile::tempdir().unwrap();
    let p = testkit::load(text, &[]);
    let r = run(&p, &testkit::grid_of(&p), dir.path());
    // Frames 0, 2 and 4 of each of the 2 scenes; the window at frame 4 is clipped to one frame.
    assert_eq!(executed(&r), counts(&[("frames", 10), ("windows", 6), ("after", 6)]));
    assert_eq!(r.stages.iter().find(|s| s.stage == "windows").unwrap().total, 6, "the others are not planned");
}

#[test]
fn processes_sharing_a_store_share_the_work_instead_of_each_doing_all_of_it() {
    let text = r#"Pipeline(
        dataset: Grid(scenes: 8, frames: 2, cameras: 2),
        stages: {
            "a": Echo(inputs: {"x": "dataset.camera_value"}, params: (sleep_ms: 15)),
            "b": Echo(inputs: {"x": "a.y"}, params: (size: 100)),
        },
    )"#;
    let p = testkit::load(text, &[]);
    let grid = testkit::grid_of(&p);
    let alone = tempfile::tempdir().unwrap();
    let whole = run_with(&p, &grid, alone.path(), &RunOptions { jobs: 1, ..Default::default() });
    let total: u64 = whole.stages.iter().map(|s| s.executed).sum();
    assert_eq!(total, 8 * 2 * 2 * 2);

    let shared = tempfile::tempdir().unwrap();
    let records: Vec<RunRecord> = std::thread::scope(|scope| {
        let runs: Vec<_> = (0..2)
            .map(|_| scope.spawn(|| run_with(&p, &grid, shared.path(), &RunOptions { jobs: 1, ..Default::default() })))
            .collect();
        runs.into_iter().map(|r| r.join().unwrap()).collect()
    });
    let executed: Vec<u64> = records.iter().map(|r| r.stages.iter().map(|s| s.executed).sum()).collect();
    for r in &records {
        assert_eq!(r.status, RunStatus::Complete);
        let done: u64 = r.stages.iter().map(|s| s.executed + s.cached).sum();
        assert_eq!(done, total, "each run ends with every task done, by itself or by the other");
    }
    assert_eq!(executed.iter().sum::<u64>(), total, "no task was run twice: {executed:?}");
    assert!(executed.iter().all(|&n| n > 0), "both did some of the work: {executed:?}");
    assert!(!shared.path().join("leases/claims").read_dir().unwrap().any(|_| true), "claims are let go");
}

/// Wraps an operator as served by an external resource (a model worker).
struct OnGpu(Box<dyn Operator>);

impl Operator for OnGpu {
    fn run(&self, ctx: &TaskContext, inputs: &[Vec<Artifact>]) -> anyhow::Result<crate::Made<Vec<Output>>> {
        self.0.run(ctx, inputs)
    }
    fn resource(&self) -> Option<Resource> {
        Some(Resource { name: "gpu".into(), slots: 1 })
    }
}

#[test]
fn a_cpu_array_leaves_worker_stages_and_what_reads_them_to_the_gpu_array() {
    let text = r#"Pipeline(
        dataset: Grid(scenes: 2, frames: 2, cameras: 2),
        stages: {
            "prep": Echo(inputs: {"x": "dataset.camera_value"}),
            "model": Echo(inputs: {"x": "prep.y"}, params: (salt: 1)),
            "encode": Echo(inputs: {"x": "model.y"}, params: (salt: 2)),
        },
    )"#;
    let p = testkit::load(text, &[]);
    let grid = testkit::grid_of(&p);
    let dir = tempfile::tempdir().unwrap();
    let run_as = |defer: bool| {
        let store = Store::open(dir.path(), Access::Shared).unwrap();
        let mut ops = testkit::operators(&p);
        let model = p.nodes.iter().position(|n| n.name == "model").unwrap();
        ops[model] = Some(Box::new(OnGpu(ops[model].take().unwrap())));
        let engine = Engine { pipeline: &p, dataset: &grid, operators: &ops, store: &store };
        engine.run(&RunOptions { jobs: 2, defer_resources: defer, ..Default::default() }).unwrap().record
    };
    let cpu = run_as(true);
    assert_eq!(cpu.status, RunStatus::Complete, "it did what it was asked");
    assert_eq!(executed(&cpu), counts(&[("prep", 8), ("model", 0), ("encode", 0)]));
    let deferred: BTreeMap<String, u64> = cpu.stages.iter().map(|s| (s.stage.clone(), s.deferred)).collect();
    assert_eq!(deferred, counts(&[("prep", 0), ("model", 8), ("encode", 8)]));
    assert_eq!(cpu.missing(), 0);
    assert!(cpu.failures.is_empty(), "missing is not failed");
    let gpu = run_as(false);
    assert_eq!(gpu.status, RunStatus::Complete);
    assert_eq!(executed(&gpu), counts(&[("prep", 0), ("model", 8), ("encode", 8)]));
}

#[test]
fn a_merge_executes_only_the_items_it_retries_and_takes_the_rest_from_the_cache() {
    let p = testkit::load(CHAIN, &[]);
    let grid = testkit::grid_of(&p);
    let dir = tempfile::tempdir().unwrap();
    // Scene s0 was done by a shard; s1's shard was lost.
    let shard = run_with(&p, &grid, dir.path(), &RunOptions { jobs: 2, shard: Some((0, 2)), ..Default::default() });
    assert_eq!(shard.status, RunStatus::Complete);
    let merge = |retry: Vec<String>| {
        run_with(&p, &grid, dir.path(), &RunOptions { jobs: 2, execute_only: Some(retry), ..Default::default() })
    };
    let r = merge(vec![]);
    assert_eq!(r.status, RunStatus::Incomplete);
    assert_eq!(r.executed(), 0);
    assert_eq!(r.cached(), shard.executed(), "the shard's work is collected");
    assert_eq!(r.missing(), shard.executed(), "the lost shard's is reported, not redone");
    let lost = crate::item::ItemSpace::label(&grid, &ItemKey::new(&[1]));
    let r = merge(vec![lost]);
    assert_eq!((r.status, r.executed(), r.missing()), (RunStatus::Complete, shard.executed(), 0));
    // Blobs damaged since (a failing disk), found corrupt when a merge exports them: the tasks
    // that made them would be run again; a merge does not, for the items it does not execute,
    // and reports them missing, not failed.
    let p = testkit::load(
        r#"Pipeline(
            dataset: Grid(scenes: 2, frames: 2, cameras: 1),
            stages: {
                "b": Echo(inputs: {"x": "dataset.camera_value"}),
                "file": ToFile(inputs: {"x": "b.y"}, params: (size: 5000)),
                "reader": FromFile(inputs: {"file": "file.file"}),
            },
            export: {"file.file": "{scene}/{frame}_{camera}.bin"},
        )"#,
        &[],
    );
    let grid = testkit::grid_of(&p);
    let dir = tempfile::tempdir().unwrap();
    let out = |name: &str| RunOptions {
        jobs: 2,
        out_dir: Some(dir.path().join(name)),
        execute_only: Some(vec![]),
        ..Default::default()
    };
    let all = run_with(
        &p,
        &grid,
        dir.path(),
        &RunOptions { jobs: 2, out_dir: Some(dir.path().join("a")), ..Default::default() },
    );
    assert_eq!(all.status, RunStatus::Complete);
    for sub in std::fs::read_dir(dir.path().join("cas")).unwrap() {
        for blob in std::fs::read_dir(sub.unwrap().path()).unwrap() {
            let path = blob.unwrap().path();
            let bytes = std::fs::read(&path).unwrap();
            std::fs::write(&path, &bytes[..bytes.len() / 2]).unwrap();
        }
    }
    let r = run_with(&p, &grid, dir.path(), &out("b"));
    assert!(r.failures.is_empty(), "{:?}", r.failures);
    assert!(r.status == RunStatus::Incomplete && r.missing() > 0 && r.executed() == 0, "{r:?}");
    // And no damaged byte reached the folder: what is there is what the first run exported.
    let (first, merged) = (files_under(&dir.path().join("a")), files_under(&dir.path().join("b")));
    let exported = |files: &BTreeMap<String, String>| files.keys().filter(|p| p.ends_with(".bin")).count();
    assert!(exported(&merged) < exported(&first), "the damaged ones are not exported: {merged:?}");
    assert!(
        merged.iter().filter(|(p, _)| p.ends_with(".bin")).all(|(path, d)| first.get(path) == Some(d)),
        "{merged:?}"
    );
}

#[test]
fn an_item_another_process_finished_after_this_one_opened_the_store_is_not_run_again() {
    let p = testkit::load(CHAIN, &[]);
    let grid = testkit::grid_of(&p);
    let dir = tempfile::tempdir().unwrap();
    let late = Store::open(dir.path(), Access::Shared).unwrap();
    // Another process runs scene s1 whole, claims and all, while `late` is open and idle.
    let s1 = crate::item::ItemSpace::label(&grid, &ItemKey::new(&[1]));
    let other =
        run_with(&p, &grid, dir.path(), &RunOptions { jobs: 2, outer_items: Some(vec![s1]), ..Default::default() });
    assert!(other.executed() > 0);
    let ops = testkit::operators(&p);
    let r = Engine { pipeline: &p, dataset: &grid, operators: &ops, store: &late }
        .run(&RunOptions { jobs: 2, ..Default::default() })
        .unwrap()
        .record;
    assert_eq!(r.cached(), other.executed(), "s1's tasks are found in the store, not run again");
    assert_eq!(r.executed() + r.cached(), 2 * other.executed());
}
