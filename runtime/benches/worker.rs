//! The worker protocol's round trip: a request to a no-op worker (workers/protocol_test_worker.py,
//! which echoes its input) and its reply, at batch 1, over the pipes.
//!
//!   cargo bench -p dist4d-runtime --bench worker
//!
//! Issue 16's target: under 2 ms per item.

use dist4d_runtime::worker::{FileRef, Request, Worker, WorkerCommand};
use std::time::{Duration, Instant};

fn main() {
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
    let n = 5000;
    let mut times = Vec::with_capacity(n);
    for _ in 0..n {
        let t = Instant::now();
        w.call(&request, Duration::from_secs(10)).expect("a reply");
        times.push(t.elapsed().as_secs_f64() * 1e3);
    }
    times.sort_by(|a, b| a.total_cmp(b));
    let mean = times.iter().sum::<f64>() / n as f64;
    println!("## Worker round trip, no-op Python worker, batch 1, {n} calls");
    println!("| startup (hello) | mean | median | p99 |");
    println!("| ---: | ---: | ---: | ---: |");
    println!(
        "| {:.0} ms | {mean:.3} ms | {:.3} ms | {:.3} ms |",
        startup.as_secs_f64() * 1e3,
        times[n / 2],
        times[n * 99 / 100]
    );
    w.shutdown(Duration::from_secs(5));
}
