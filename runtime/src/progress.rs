//! Per-stage progress: bars on a terminal, periodic plain lines otherwise (logs, CI, Slurm).

use indicatif::{MultiProgress, ProgressBar, ProgressDrawTarget, ProgressStyle};
use std::io::IsTerminal;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ProgressMode {
    /// Bars if stderr is a terminal, else lines.
    Auto,
    /// Plain lines every so many seconds.
    Lines(u64),
    Off,
}

/// Counters shared by the scheduler and the reporter.
pub struct Counters {
    pub names: Vec<String>,
    pub total: Vec<AtomicU64>,
    pub done: Vec<AtomicU64>,
    pub failed: Vec<AtomicU64>,
}

impl Counters {
    pub fn new(names: Vec<String>) -> Counters {
        let n = names.len();
        let z = || (0..n).map(|_| AtomicU64::new(0)).collect::<Vec<_>>();
        Counters { names, total: z(), done: z(), failed: z() }
    }
}

/// Runs the reporter on its own thread until dropped.
pub struct Reporter {
    stop: Arc<AtomicBool>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl Reporter {
    pub fn start(counters: Arc<Counters>, mode: ProgressMode) -> Reporter {
        let stop = Arc::new(AtomicBool::new(false));
        let mode = match mode {
            ProgressMode::Auto if std::io::stderr().is_terminal() => ProgressMode::Auto,
            ProgressMode::Auto => ProgressMode::Lines(10),
            m => m,
        };
        let s = stop.clone();
        let thread = match mode {
            ProgressMode::Off => None,
            ProgressMode::Auto => Some(std::thread::spawn(move || bars(&counters, &s))),
            ProgressMode::Lines(secs) => Some(std::thread::spawn(move || lines(&counters, &s, secs.max(1)))),
        };
        Reporter { stop, thread }
    }
}

impl Drop for Reporter {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

fn bars(c: &Counters, stop: &AtomicBool) {
    let multi = MultiProgress::with_draw_target(ProgressDrawTarget::stderr_with_hz(10));
    let width = c.names.iter().map(|n| n.len()).max().unwrap_or(8);
    let style = ProgressStyle::with_template(&format!(
        "{{prefix:>{width}}} [{{bar:30}}] {{pos}}/{{len}} {{per_sec}} ETA {{eta}} {{msg}}"
    ))
    .unwrap_or_else(|_| ProgressStyle::default_bar())
    .progress_chars("=> ");
    let bars: Vec<ProgressBar> = c
        .names
        .iter()
        .map(|n| {
            let b = multi.add(ProgressBar::new(0));
            b.set_style(style.clone());
            b.set_prefix(n.clone());
            b
        })
        .collect();
    loop {
        let stopping = stop.load(Ordering::Relaxed);
        for (i, b) in bars.iter().enumerate() {
            b.set_length(c.total[i].load(Ordering::Relaxed));
            b.set_position(c.done[i].load(Ordering::Relaxed));
            let f = c.failed[i].load(Ordering::Relaxed);
            if f > 0 {
                b.set_message(format!("{f} failed"));
            }
        }
        if stopping {
            bars.iter().for_each(|b| b.abandon());
            return;
        }
        std::thread::sleep(Duration::from_millis(100));
    }
}

fn lines(c: &Counters, stop: &AtomicBool, secs: u64) {
    let start = Instant::now();
    let mut last = Instant::now();
    let prev: Vec<u64> = vec![0; c.names.len()];
    let mut prev = prev;
    while !stop.load(Ordering::Relaxed) {
        std::thread::sleep(Duration::from_millis(50));
        if last.elapsed() < Duration::from_secs(secs) {
            continue;
        }
        let dt = last.elapsed().as_secs_f64();
        last = Instant::now();
        let mut parts = Vec::new();
        for i in 0..c.names.len() {
            let (done, total) = (c.done[i].load(Ordering::Relaxed), c.total[i].load(Ordering::Relaxed));
            let rate = (done - prev[i]) as f64 / dt;
            prev[i] = done;
            let eta = if rate > 0.0 && total > done {
                format!(", ETA {:.0}s", (total - done) as f64 / rate)
            } else {
                String::new()
            };
            let failed = c.failed[i].load(Ordering::Relaxed);
            let failed = if failed > 0 { format!(", {failed} failed") } else { String::new() };
            parts.push(format!("{} {done}/{total} ({rate:.1}/s{eta}{failed})", c.names[i]));
        }
        eprintln!("progress [{:.0}s]: {}", start.elapsed().as_secs_f64(), parts.join("; "));
    }
}
