//! The worker protocol's round trip: a request to a no-op worker (workers/protocol_test_worker.py,
//! which echoes its input) and its reply, at batch 1, over the pipes.
//!
//!   cargo bench -p dist4d-runtime --bench worker
//!
//! Issue 16's targets: under 2 ms per item, and a worker kept busy >= 90% of the wall time when
//! the items are ready. The second is measured through the engine: a pipeline of one stage whose
//! tasks call a worker that sleeps a fixed time per request, as a resource class.

use dist4d_runtime::operator::{Artifact, Output, Resource, TaskContext};
use dist4d_runtime::worker::{FileRef, Request, Worker, WorkerCommand};
use dist4d_runtime::worker_pool::{PoolOptions, WorkerPool};
use dist4d_runtime::{testkit, Access, Engine, Operator, RunOptions, Store};
use std::time::{Duration, Instant};

fn main() {
    round_trip();
    println!();
    println!(
        "## Worker busy share through the engine: 240 ready items, a worker sleeping 20 ms per request, 2 CPU threads"
    );
    println!("| workers | max batch | items | sleep | ideal | wall | busy |");
    println!("| ---: | ---: | ---: | ---: | ---: | ---: | ---: |");
    busy(1, 1);
    busy(1, 4);
    busy(2, 1);
}

fn command(args: &[&str]) -> WorkerCommand {
    let script = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../workers/protocol_test_worker.py");
    let mut all = vec![script.display().to_string()];
    all.extend(args.iter().map(|a| a.to_string()));
    WorkerCommand { program: "python3".into(), args: all }
}

/// A stage served by the sleeping worker, as model-worker stages are: its tasks wait as a
/// resource class of processes x batch x 2 slots (a batch in the worker, the next one ready).
struct SleepStage {
    pool: WorkerPool,
    sleep_s: f64,
    slots: usize,
}

impl Operator for SleepStage {
    fn run(&self, ctx: &TaskContext, _: &[Vec<Artifact>]) -> anyhow::Result<Vec<Output>> {
        let request = Request {
            item: ctx.label.to_string(),
            op: "echo".into(),
            inputs: vec![FileRef { name: "x".into(), path: format!("sleep:{}", self.sleep_s), digest: None }],
            params: serde_json::json!({}),
            out_dir: "/tmp".into(),
        };
        self.pool.call(&request)?;
        Ok(vec![Output::new("Bytes", ctx.label.as_bytes().to_vec())])
    }
    fn resource(&self) -> Option<Resource> {
        Some(Resource { name: "sleeper".into(), slots: self.slots })
    }
}

/// Runs 240 items through `workers` sleeping workers taking batches of `batch`, on 2 CPU
/// threads; the workers' busy share is the sleep time they were given over the wall time.
fn busy(workers: usize, batch: usize) {
    let sleep_s = 0.02;
    let text = r#"Pipeline(
        dataset: Grid(scenes: 1, frames: 60, cameras: 4),
        stages: { "model": Echo(inputs: {"x": "dataset.camera_value"}) },
    )"#;
    let p = testkit::load(text, &[]);
    let grid = testkit::grid_of(&p);
    let dir = std::env::temp_dir().join(format!("dist4d-bench-busy-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let store = Store::open(&dir, Access::Shared).expect("a store");
    let pool = WorkerPool::new(
        command(&["--max-batch", &batch.to_string()]),
        PoolOptions { max_workers: workers, ..PoolOptions::default() },
    );
    // Started before the clock, as a run does when it asks the workers' identity.
    pool.hello().expect("the sleeping worker starts");
    let mut stage = Some(SleepStage { pool, sleep_s, slots: workers * batch * 2 });
    let ops: Vec<Option<Box<dyn Operator>>> = p
        .nodes
        .iter()
        .map(|n| n.stage().and_then(|_| stage.take()).map(|s| Box::new(s) as Box<dyn Operator>))
        .collect();
    let engine = Engine { pipeline: &p, dataset: &grid, operators: &ops, store: &store };
    let t = Instant::now();
    let r = engine.run(&RunOptions { jobs: 2, ..Default::default() }).expect("the run");
    assert_eq!(r.record.failed(), 0, "every item ran");
    let wall = t.elapsed().as_secs_f64();
    let items = r.record.executed() as f64;
    let share = items * sleep_s / workers as f64 / wall;
    println!(
        "| {workers} | {batch} | {items:.0} | {:.0} ms | {:.2} s | {:.2} s | {:.1}% |",
        sleep_s * 1e3,
        items * sleep_s / workers as f64,
        wall,
        share * 100.0
    );
    drop(ops);
    let _ = std::fs::remove_dir_all(&dir);
}

/// Each of `n` runs of `f`, in milliseconds, sorted.
fn timed(n: usize, mut f: impl FnMut()) -> Vec<f64> {
    let mut times: Vec<f64> = (0..n)
        .map(|_| {
            let t = Instant::now();
            f();
            t.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    times.sort_by(|a, b| a.total_cmp(b));
    times
}

fn row(what: &str, n: usize, startup: Duration, times: &[f64]) {
    let mean = times.iter().sum::<f64>() / n as f64;
    println!(
        "| {what} | {n} | {:.0} ms | {mean:.3} ms | {:.3} ms | {:.3} ms |",
        startup.as_secs_f64() * 1e3,
        times[n / 2],
        times[n * 99 / 100]
    );
}

fn round_trip() {
    let script = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../workers/protocol_test_worker.py");
    let command = WorkerCommand { program: "python3".into(), args: vec![script.display().to_string()] };
    let t = Instant::now();
    let mut w = Worker::start(&command, Duration::from_secs(30)).expect("the no-op worker starts");
    let startup = t.elapsed();
    let request = Request {
        item: String::new(),
        op: "echo".into(),
        inputs: vec![FileRef { name: "x".into(), path: "/tmp/input.npy".into(), digest: Some("0".repeat(64)) }],
        params: serde_json::json!({"scale": 1.0}),
        out_dir: "/tmp/out".into(),
    };
    for _ in 0..100 {
        w.call(&request, Duration::from_secs(10)).expect("warm-up");
    }
    println!("## Worker round trip, no-op Python worker, batch 1");
    println!("| what | calls | startup (hello) | mean | median | p99 |");
    println!("| --- | ---: | ---: | ---: | ---: | ---: |");
    let n = 5000;
    let times = timed(n, || {
        w.call(&request, Duration::from_secs(10)).expect("a reply");
    });
    row("the protocol alone", n, startup, &times);
    // With files on local disk, as a stage exchanges them: a 320 x 180 float32 depth map (225 KiB)
    // written and digested per request, and the file the reply names read back.
    let dir = std::env::temp_dir().join(format!("dist4d-bench-exchange-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("a folder");
    let bytes = vec![7u8; 320 * 180 * 4];
    let n = 2000;
    let times = timed(n, || {
        let path = dir.join("depth.npy");
        std::fs::write(&path, &bytes).expect("written");
        let digest = blake3::hash(&bytes).to_hex().to_string();
        let r = Request {
            inputs: vec![FileRef { name: "x".into(), path: path.display().to_string(), digest: Some(digest) }],
            out_dir: dir.display().to_string(),
            ..request.clone()
        };
        let reply = w.call(&r, Duration::from_secs(10)).expect("a reply");
        let back = std::fs::read(&reply.outputs[0].path).expect("the output");
        assert_eq!(back.len(), bytes.len());
    });
    row("with a 225 KiB file each way", n, startup, &times);
    let _ = std::fs::remove_dir_all(&dir);
    w.shutdown(Duration::from_secs(5));
}
