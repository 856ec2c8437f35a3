//! Planning and cache-check cost, and memory, of the scheduler on a no-op pipeline.
//!
//!   cargo bench -p dist4d-runtime --bench plan              # 1,000,000 tasks: cold run, then fully cached run
//!   cargo bench -p dist4d-runtime --bench plan -- rss N     # peak RSS of an N-item no-op run (own process)
//!
//! The dataset is the runtime's synthetic grid (scenes of 40 frames x 6 cameras); each stage is a
//! no-op `Echo` (a 32-byte hash, kept inline in its record), so the figures are the engine's own
//! cost: planning, key hashing, record writes and cache lookups.

use dist4d_runtime::exec::{Engine, RunOptions};
use dist4d_runtime::store::{Access, Store};
use dist4d_runtime::testkit;
use std::time::Instant;

fn pipeline(scenes: u32) -> dist4d_graph::Pipeline {
    let text = format!(
        r#"Pipeline(
    dataset: Grid(scenes: {scenes}, frames: 40, cameras: 6),
    stages: {{
        "a": Echo(inputs: {{"x": "dataset.camera_value"}}),
        "b": Echo(inputs: {{"x": "a.y"}}),
        "c": Echo(inputs: {{"x": "b.y"}}),
    }},
)"#
    );
    testkit::load(&text, &[])
}

fn run(p: &dist4d_graph::Pipeline, store: &std::path::Path) -> (f64, u64, u64) {
    let grid = testkit::grid_of(p);
    let ops = testkit::operators(p);
    let t = Instant::now();
    let s = Store::open(store, Access::Shared).unwrap();
    let r = Engine { pipeline: p, dataset: &grid, operators: &ops, store: &s }
        .run(&RunOptions { jobs: 2, ..Default::default() })
        .unwrap()
        .record;
    drop(s);
    (t.elapsed().as_secs_f64(), r.executed(), r.cached())
}

fn peak_rss_kib() -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines().find(|l| l.starts_with("VmHWM:")).and_then(|l| l.split_whitespace().nth(1)?.parse().ok())
        })
        .unwrap_or(0)
}

fn main() {
    let args: Vec<String> = std::env::args().filter(|a| a != "--bench").collect();
    if args.get(1).map(String::as_str) == Some("rss") {
        let items: u64 = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(10_000);
        let scenes = (items / 240).max(1) as u32;
        let dir = tempfile::tempdir().unwrap();
        let (secs, executed, _) = run(&pipeline(scenes), dir.path());
        println!(
            "rss: {} items ({} tasks executed) in {secs:.2}s, peak RSS {} MiB",
            scenes as u64 * 240,
            executed,
            peak_rss_kib() / 1024
        );
        return;
    }
    let scenes = 1389; // 1389 x 240 items x 3 stages = 1,000,080 tasks
    let p = pipeline(scenes);
    let dir = tempfile::tempdir().unwrap();
    let (cold, executed, _) = run(&p, dir.path());
    println!("cold run:   {executed} tasks executed in {cold:.2}s ({:.2} us/task)", cold * 1e6 / executed as f64);
    let (warm, _, cached) = run(&p, dir.path());
    println!(
        "cached run: {cached} tasks planned and found cached in {warm:.2}s ({:.2} us/task), store open included",
        warm * 1e6 / cached as f64
    );
    for items in [10_000u64, 100_000] {
        let exe = std::env::current_exe().unwrap();
        let out = std::process::Command::new(exe).args(["rss", &items.to_string()]).output().unwrap();
        print!("{}", String::from_utf8_lossy(&out.stdout));
    }
}
