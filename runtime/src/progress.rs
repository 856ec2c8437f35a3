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
    /// Neither cached nor executed (a run that executes only some tasks: a merge job, a CPU array).
    pub missing: Vec<AtomicU64>,
}

impl Counters {
    pub fn new(names: Vec<String>) -> Counters {
        let n = names.len();
        let z = || (0..n).map(|_| AtomicU64::new(0)).collect::<Vec<_>>();
        Counters { names, total: z(), done: z(), failed: z(), missing: z() }
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
        "{{prefix:>{width}}} [{{bar:30}}] {{pos}}/{{len}} {{rate}} ETA {{eta}} {{msg}}"
    ))
    .map(|s| {
        s.with_key("rate", |st: &indicatif::ProgressState, w: &mut dyn std::fmt::Write| {
            let _ = write!(w, "{:.1}/s", st.per_sec());
        })
    })
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
            let (f, m) = (c.failed[i].load(Ordering::Relaxed), c.missing[i].load(Ordering::Relaxed));
            match (f, m) {
                (0, 0) => {}
                (f, 0) => b.set_message(format!("{f} failed")),
                (0, m) => b.set_message(format!("{m} missing")),
                (f, m) => b.set_message(format!("{f} failed, {m} missing")),
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
    let mut prev: Vec<u64> = vec![0; c.names.len()];
    loop {
        let stopping = stop.load(Ordering::Relaxed);
        // A final line at the end, so a log always shows where each stage ended even for short runs.
        if stopping || last.elapsed() >= Duration::from_secs(secs) {
            let dt = last.elapsed().as_secs_f64();
            last = Instant::now();
            let snapshot: Vec<StageCount> = (0..c.names.len())
                .map(|i| StageCount {
                    name: &c.names[i],
                    done: c.done[i].load(Ordering::Relaxed),
                    total: c.total[i].load(Ordering::Relaxed),
                    failed: c.failed[i].load(Ordering::Relaxed),
                    missing: c.missing[i].load(Ordering::Relaxed),
                })
                .collect();
            eprintln!("{}", progress_line(start.elapsed(), &snapshot, &prev, dt));
            prev = snapshot.iter().map(|s| s.done).collect();
        }
        if stopping {
            return;
        }
        std::thread::sleep(Duration::from_millis(50));
    }
}

struct StageCount<'a> {
    name: &'a str,
    done: u64,
    total: u64,
    failed: u64,
    missing: u64,
}

/// One log line: `progress [12s]: project 40/120 (3.3/s, ETA 24s); encode 12/120 (1.0/s, ETA 108s, 2 failed)`.
fn progress_line(elapsed: Duration, stages: &[StageCount], prev_done: &[u64], dt: f64) -> String {
    let parts: Vec<String> = stages
        .iter()
        .zip(prev_done)
        .map(|(s, &prev)| {
            let rate = if dt > 0.0 { s.done.saturating_sub(prev) as f64 / dt } else { 0.0 };
            let eta = if rate > 0.0 && s.total > s.done {
                format!(", ETA {:.0}s", (s.total - s.done) as f64 / rate)
            } else {
                String::new()
            };
            let failed = if s.failed > 0 { format!(", {} failed", s.failed) } else { String::new() };
            let missing = if s.missing > 0 { format!(", {} missing", s.missing) } else { String::new() };
            format!("{} {}/{} ({rate:.1}/s{eta}{failed}{missing})", s.name, s.done, s.total)
        })
        .collect();
    format!("progress [{:.0}s]: {}", elapsed.as_secs_f64(), parts.join("; "))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_line_names_every_stage_with_rate_eta_failures_and_missing_tasks() {
        let stages = [
            StageCount { name: "project", done: 40, total: 120, failed: 0, missing: 0 },
            StageCount { name: "encode", done: 12, total: 120, failed: 2, missing: 3 },
        ];
        let line = progress_line(Duration::from_secs(12), &stages, &[10, 2], 10.0);
        assert_eq!(
            line,
            "progress [12s]: project 40/120 (3.0/s, ETA 27s); encode 12/120 (1.0/s, ETA 108s, 2 failed, 3 missing)"
        );
    }

    #[test]
    fn a_finished_stage_has_no_eta() {
        let stages = [StageCount { name: "s", done: 5, total: 5, failed: 0, missing: 0 }];
        assert_eq!(progress_line(Duration::from_secs(1), &stages, &[5], 1.0), "progress [1s]: s 5/5 (0.0/s)");
    }
}
