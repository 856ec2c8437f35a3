//! End-to-end: pipeline stages served by external model workers (the reference workers of
//! workers/, numpy from the peer venv), from the CLI.

mod common;
use common::*;
use std::path::{Path, PathBuf};
use std::process::Output;

/// The executed count of `stage` in a run table.
fn executed(report: &str, stage: &str) -> u64 {
    let line = report
        .lines()
        .find(|l| l.split_whitespace().next() == Some(stage))
        .unwrap_or_else(|| panic!("{stage}\n{report}"));
    line.split_whitespace().nth(3).unwrap().parse().unwrap()
}

/// A 2-keyframe synthetic scene at 320 x 180 in a temporary folder, and runs of shipped
/// pipelines on it (from the repository, so that relative worker paths resolve) into one cache.
struct Scene {
    tmp: tempfile::TempDir,
    data: PathBuf,
}

impl Scene {
    fn new() -> Scene {
        let tmp = tempfile::tempdir().unwrap();
        let data = tmp.path().join("data");
        let o = dist4d(&[
            "synth",
            "--out",
            data.to_str().unwrap(),
            "--keyframes",
            "2",
            "--width",
            "320",
            "--height",
            "180",
        ]);
        assert!(o.status.success(), "{}", text(&o));
        Scene { tmp, data }
    }

    fn out(&self, name: &str) -> PathBuf {
        self.tmp.path().join(name)
    }

    /// `dist4d run pipelines/<pipeline>.ron` into output folder `out`, with `sets` and `env`.
    fn run(&self, pipeline: &str, out: &str, sets: &[&str], env: &[(&str, &str)]) -> Output {
        let root = format!("dataset.root={}", self.data.display());
        let (cache, out) = (self.out("cache"), self.out(out));
        let file = format!("pipelines/{pipeline}.ron");
        let mut args = vec![
            "run",
            file.as_str(),
            "--set",
            &root,
            "--cache",
            cache.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ];
        for s in sets {
            args.extend(["--set", s]);
        }
        std::process::Command::new(bin()).current_dir(repo()).args(&args).envs(env.iter().copied()).output().unwrap()
    }

    /// Like [`Scene::run`], which must succeed: its report.
    fn run_ok(&self, pipeline: &str, out: &str, sets: &[&str], env: &[(&str, &str)]) -> String {
        let o = self.run(pipeline, out, sets, env);
        let t = text(&o);
        assert!(o.status.success(), "{t}");
        t
    }
}

/// `<stage>.worker=Some(..)` for a program and its arguments.
fn worker_set(stage: &str, program: &Path, args: &[&str]) -> String {
    let args: Vec<String> = args.iter().map(|a| format!("{a:?}")).collect();
    format!("{stage}.worker=Some((program: {:?}, args: [{}]))", program.display().to_string(), args.join(", "))
}

/// The float32 values of an NPY file dist4d wrote.
fn npy_values(path: &Path) -> Vec<f32> {
    let npy = std::fs::read(path).unwrap();
    let header = u16::from_le_bytes([npy[8], npy[9]]) as usize;
    npy[10 + header..].chunks_exact(4).map(|c| f32::from_le_bytes(c.try_into().unwrap())).collect()
}

#[test]
fn complete_depth_through_a_worker_is_cached_and_reruns_when_the_worker_changes() {
    let Some(python) = peers_python() else { return };
    let scene = Scene::new();
    let script = repo().join("workers/fill_completer.py");
    let worker = worker_set("complete", &python, &[&script.display().to_string()]);
    let v1 = [("FILL_COMPLETER_VERSION", "1")];
    scene.run_ok("curation", "builtin", &[], &v1);
    let first = scene.run_ok("curation", "worker", &[&worker], &v1);
    assert_eq!((executed(&first, "complete"), executed(&first, "aggregate")), (12, 0), "{first}");
    let read = |dir: &str| std::fs::read(scene.out(dir).join("synth-0000/CAM_FRONT/000_depth.npy")).unwrap();
    assert_ne!(read("builtin"), read("worker"), "the worker's completion is its own");
    // Cached across runs: the worker is asked for its identity only.
    let again = scene.run_ok("curation", "worker", &[&worker], &v1);
    assert_eq!(executed(&again, "complete"), 0, "{again}");
    // A new version of the model: its stage reruns; the same bytes cut off what follows.
    let new = scene.run_ok("curation", "worker", &[&worker], &[("FILL_COMPLETER_VERSION", "2")]);
    assert_eq!((executed(&new, "complete"), executed(&new, "prompt"), executed(&new, "encode")), (12, 0, 0), "{new}");
    // A worker that fails an item fails that item only, with the worker's own words.
    let broken = format!(
        "complete.worker=Some((program: \"{}\", args: [\"-c\", \"import sys,json; print(json.dumps({{'type':'hello','protocol':1,'name':'broken','version':'1','ops':['complete_depth']}}), flush=True); [print(json.dumps({{'type':'reply','id':json.loads(l)['id'],'status':'error','message':'out of ideas'}}), flush=True) for l in sys.stdin if json.loads(l)['type']=='request']\"], tries: 1))",
        python.display()
    );
    let o = scene.run("curation", "broken", &[&broken], &[]);
    let t = text(&o);
    assert_eq!(o.status.code(), Some(1), "{t}");
    assert!(t.contains("could not do it: out of ideas"), "{t}");
    assert!(t.contains("failed: complete"), "{t}");
}

/// The SCC pipeline's novel-view generator through a worker (the reference generator of
/// workers/): the pairs are made from its views, and a rerun asks it nothing.
#[test]
fn scc_pairs_through_a_generator_worker() {
    let Some(python) = peers_python() else { return };
    let scene = Scene::new();
    let worker = worker_set("novel", &python, &[&repo().join("workers/fill_generator.py").display().to_string()]);
    scene.run_ok("scc", "baseline", &[], &[]);
    let first = scene.run_ok("scc", "worker", &[&worker], &[]);
    assert_eq!((executed(&first, "novel"), executed(&first, "complete")), (12, 0), "{first}");
    let pairs = std::fs::read_to_string(scene.out("worker/synth-0000/pairs.jsonl")).unwrap();
    assert_eq!(pairs.lines().count(), 12);
    let cond = |dir: &str| std::fs::read(scene.out(dir).join("synth-0000/CAM_FRONT/000_random_cond.png")).unwrap();
    assert_ne!(cond("baseline"), cond("worker"), "the condition comes back from the worker's view");
    let again = scene.run_ok("scc", "worker", &[&worker], &[]);
    assert_eq!(executed(&again, "novel"), 0, "{again}");
}

/// The sky from a segmenter worker (the reference one of workers/): the curation's sky follows
/// its ids, and the depth there is the sky depth.
#[test]
fn the_sky_from_a_segmenter_worker() {
    let Some(python) = peers_python() else { return };
    let scene = Scene::new();
    let worker = worker_set("sky", &python, &[&repo().join("workers/sky_segmenter.py").display().to_string()]);
    let t = scene.run_ok("curation", "out", &[&worker], &[]);
    assert_eq!(executed(&t, "sky"), 12, "{t}");
    let depth_of = |out: &str| npy_values(&scene.out(out).join("synth-0000/CAM_FRONT/000_depth.npy"));
    let top_sky = depth_of("out")[..320].iter().filter(|&&z| z == 100.0).count();
    assert!(top_sky > 0, "the reference segmenter finds the synthetic sky at the top");
    // A segmenter that calls exactly the top ten rows sky: the depth there is the sky depth.
    let ten_rows = worker_set(
        "sky",
        &python,
        &["-c", "import sys,json,numpy as np; print(json.dumps({'type':'hello','protocol':1,'name':'ten-rows','version':'1','ops':['segment']}), flush=True)\nfor l in sys.stdin:\n m=json.loads(l)\n if m['type']!='request': continue\n im=np.load(m['inputs'][0]['path']); ids=np.full(im.shape[:2],7,np.uint8); ids[:10]=23; p=m['out_dir']+'/s.npy'; np.save(p,ids); print(json.dumps({'type':'reply','id':m['id'],'status':'ok','outputs':[{'name':'semantic','path':p}]}), flush=True)"],
    );
    scene.run_ok("curation", "out2", &[&ten_rows], &[]);
    let depth = depth_of("out2");
    assert!(depth[..10 * 320].iter().all(|&z| z == 100.0), "the ten sky rows at 100 m");
    assert!(depth[10 * 320..].iter().filter(|&&z| z == 100.0).count() < 320, "below them, structure");
}

/// `complete.worker` set to workers/faulty_completer.py with `args`, 2 tries and a 3 s deadline.
fn faulty(python: &Path, args: &[&str]) -> String {
    let script = repo().join("workers/faulty_completer.py").display().to_string();
    let mut all = vec![script.as_str()];
    all.extend(args);
    worker_set("complete", python, &all).replace("]))", "], deadline_s: 3, tries: 2))")
}

/// The lines of a run's report that say an item failed.
fn failures(report: &str) -> Vec<&str> {
    report.lines().filter(|l| l.starts_with("failed: ")).collect()
}

/// A worker that crashes on some items, hangs on one and returns a malformed depth on another:
/// each of those items fails with what happened (and the worker's stderr), every other item
/// is made, and a worker crash mid-run is survived by a restart.
#[test]
fn a_misbehaving_worker_fails_its_items_only_and_a_crash_mid_run_is_survived() {
    let Some(python) = peers_python() else { return };
    let scene = Scene::new();
    let set = faulty(
        &python,
        &["--crash-on", "CAM_BACK_LEFT", "--hang-on", "001/CAM_FRONT_RIGHT", "--malformed-on", "000/CAM_BACK_RIGHT"],
    );
    let o = scene.run("curation", "faulty", &[&set], &[]);
    let t = text(&o);
    assert_eq!(o.status.code(), Some(1), "{t}");
    assert_eq!(executed(&t, "complete"), 8, "{t}");
    assert_eq!(executed(&t, "encode_support"), 6, "{t}");
    // The depth exported is the blend of frames t-1..t+1 (TemporalBlend): an item whose
    // neighbour's completion failed is skipped with it, here 000/CAM_FRONT_RIGHT (001 hung) and
    // 001/CAM_BACK_RIGHT (000 malformed); the other six the worker did are exported.
    assert_eq!(executed(&t, "encode"), 6, "the items the worker did are exported: {t}");
    let failed = failures(&t);
    assert_eq!(failed.len(), 4, "{t}");
    let says = |item: &str, what: &[&str]| {
        let line = failed.iter().find(|l| l.contains(item)).unwrap_or_else(|| panic!("{item}: {t}"));
        let at = t.find(line).unwrap();
        let chain = &t[at..t[at..].find("\nfailed: ").map_or(t.len(), |e| at + e)];
        for w in what {
            assert!(chain.contains(w), "{item}: `{w}` in\n{chain}");
        }
    };
    says(
        "000/CAM_BACK_LEFT",
        &["failed 2 times", "the worker died", "segmentation fault on synth-0000/000/CAM_BACK_LEFT"],
    );
    says("001/CAM_BACK_LEFT", &["failed 2 times", "segmentation fault on synth-0000/001/CAM_BACK_LEFT"]);
    says("001/CAM_FRONT_RIGHT", &["no reply within 3.0 s", "stuck on synth-0000/001/CAM_FRONT_RIGHT"]);
    says("000/CAM_BACK_RIGHT", &["the worker's `depth` has shape [320, 180], not [180, 320]"]);

    // The items made are cached: a rerun with a worker that crashes on its first request (the
    // marker file says it did) gets past the crash on a restarted worker and does the rest.
    let marker = scene.out("crashed-once");
    let set = faulty(&python, &["--crash-once", marker.to_str().unwrap()]);
    let t = scene.run_ok("curation", "faulty", &[&set], &[]);
    assert!(marker.exists(), "the worker crashed once");
    assert!(failures(&t).is_empty(), "{t}");
}

/// A worker that dies before its hello: every item of its stage fails with its stderr, and the
/// stages that do not need it finish.
#[test]
fn a_worker_that_dies_at_start_fails_its_stage_items_and_the_rest_of_the_run_finishes() {
    let Some(python) = peers_python() else { return };
    let scene = Scene::new();
    let o = scene.run("curation", "dead", &[&faulty(&python, &["--die-at-start"])], &[]);
    let t = text(&o);
    assert_eq!(o.status.code(), Some(1), "{t}");
    assert_eq!((executed(&t, "complete"), executed(&t, "prompt"), executed(&t, "eval")), (0, 12, 0), "{t}");
    assert_eq!(failures(&t).len(), 12, "{t}");
    assert!(t.contains("its worker is unavailable") && t.contains("no CUDA-capable device"), "{t}");
}

/// A worker that takes batches: the engine sends the waiting items together, and the depths are
/// the ones the same completion gives one item at a time.
#[test]
fn a_batching_worker_gets_items_together_and_gives_the_same_depths() {
    let Some(python) = peers_python() else { return };
    let scene = Scene::new();
    let one = worker_set("complete", &python, &[&repo().join("workers/fill_completer.py").display().to_string()]);
    scene.run_ok("curation", "one", &[&one], &[]);
    let log = scene.out("batches");
    let batch = faulty(&python, &["--max-batch", "4", "--batch-log", log.to_str().unwrap()]);
    let t = scene.run_ok("curation", "batch", &[&batch], &[]);
    assert_eq!(executed(&t, "complete"), 12, "{t}");
    let sizes: Vec<usize> = std::fs::read_to_string(&log).unwrap().lines().map(|l| l.parse().unwrap()).collect();
    assert!(sizes.iter().all(|&n| n <= 4) && sizes.iter().any(|&n| n > 1), "batch sizes {sizes:?}");
    for cam in ["CAM_FRONT", "CAM_BACK_LEFT"] {
        let read = |dir: &str| std::fs::read(scene.out(dir).join(format!("synth-0000/{cam}/001_depth.npy"))).unwrap();
        assert_eq!(read("one"), read("batch"), "{cam}");
    }
}

/// The CPU array of a GPU submission (`--defer-workers`) starts no model worker: a worker that
/// could not even start there (no GPU, no model environment) fails nothing; its tasks, and what
/// reads them, are missing; then the GPU array's run (the worker given) makes them.
#[test]
fn a_run_that_defers_workers_starts_none_and_leaves_their_tasks_missing() {
    let scene = Scene::new();
    let nowhere = worker_set("complete", Path::new("/nonexistent/model-worker"), &[]);
    let o = scene.run("curation", "out", &[&nowhere], &[]);
    let t = text(&o);
    assert_eq!(o.status.code(), Some(1), "without --defer-workers the worker is needed: {t}");
    assert!(t.contains("its worker is unavailable"), "{t}");
    let o = std::process::Command::new(bin())
        .current_dir(repo())
        .args(["run", "pipelines/curation.ron", "--defer-workers", "--set", &nowhere])
        .args(["--set", &format!("dataset.root={}", scene.data.display())])
        .args(["--cache", scene.out("cache").to_str().unwrap(), "--out", scene.out("out").to_str().unwrap()])
        .output()
        .unwrap();
    let t = text(&o);
    assert_eq!(o.status.code(), Some(0), "it did what it was asked (a Slurm array task that succeeded): {t}");
    assert!(!t.contains("failed:") && !t.contains("unavailable"), "nothing failed: {t}");
    assert!(t.contains("Complete") && t.contains("deferred:") && !t.contains("missing:"), "{t}");
    assert_eq!(executed(&t, "complete"), 0);
    // The GPU array: here the built-in completion stands in for the model.
    let gpu = scene.run_ok("curation", "out", &[], &[]);
    assert!(executed(&gpu, "complete") > 0 && executed(&gpu, "aggregate") == 0, "{gpu}");
}

/// `complete.worker` set to workers/protocol_test_worker.py (the system's `python3`: standard
/// library only) serving `complete_depth`, with `args` and the worker options `options`.
fn test_worker(args: &[&str], options: &str) -> String {
    let script = repo().join("workers/protocol_test_worker.py").display().to_string();
    let mut all = vec![script.as_str(), "--op", "complete_depth"];
    all.extend(args);
    worker_set("complete", Path::new("python3"), &all).replace("]))", &format!("], {options}))"))
}

/// The processes still alive (zombies are dead) that a test worker left: those whose pid or
/// process group is a worker's pid in `pid_file` (each line: a worker's pid and the pid of the
/// `sleep` it started in its group). Read from /proc.
fn survivors(pid_file: &Path) -> Vec<u32> {
    let listed: Vec<u32> =
        std::fs::read_to_string(pid_file).unwrap_or_default().split_whitespace().map(|p| p.parse().unwrap()).collect();
    let workers: Vec<u32> = listed.iter().step_by(2).copied().collect();
    let mut alive = Vec::new();
    for entry in std::fs::read_dir("/proc").unwrap().flatten() {
        let Some(pid) = entry.file_name().to_str().and_then(|n| n.parse::<u32>().ok()) else { continue };
        let Ok(stat) = std::fs::read_to_string(entry.path().join("stat")) else { continue };
        // `pid (comm) state ppid pgrp ...`: the command may hold spaces and parentheses.
        let fields: Vec<&str> = stat[stat.rfind(')').unwrap() + 1..].split_whitespace().collect();
        let (state, pgrp) = (fields[0], fields[2].parse::<u32>().unwrap());
        if state != "Z" && (listed.contains(&pid) || workers.contains(&pgrp)) {
            alive.push(pid);
        }
    }
    alive
}

/// Kills what [`survivors`] finds, so that a failing test leaves nothing running behind it.
fn kill_survivors(pid_file: &Path) {
    for pid in survivors(pid_file) {
        let _ = std::process::Command::new("kill").args(["-KILL", &pid.to_string()]).status();
    }
}

/// `dist4d run pipelines/curation.ron` on the first frame of `scene` (6 items to complete)
/// with `set`, started; its stdout and stderr go to files in the scene's folder (a pipe left
/// unread could stop it).
fn spawn_curation(scene: &Scene, out: &str, set: &str) -> std::process::Child {
    let file = |name: &str| std::fs::File::create(scene.out(&format!("{out}.{name}"))).unwrap();
    std::process::Command::new(bin())
        .current_dir(repo())
        .args(["run", "pipelines/curation.ron", "--limit", "1", "--progress", "off", "--set", set])
        .args(["--set", &format!("dataset.root={}", scene.data.display())])
        .args(["--cache", scene.out("cache").to_str().unwrap(), "--out", scene.out(out).to_str().unwrap()])
        .stdout(file("stdout"))
        .stderr(file("stderr"))
        .spawn()
        .unwrap()
}

/// Waits up to `limit` for `child` to end: its exit code and what it wrote. One still running
/// then is killed, with the worker processes it left, and the test fails (instead of hanging).
fn wait_within(
    scene: &Scene,
    out: &str,
    mut child: std::process::Child,
    limit: std::time::Duration,
    pid_file: &Path,
) -> (Option<i32>, String) {
    let t0 = std::time::Instant::now();
    let status = loop {
        if let Some(status) = child.try_wait().unwrap() {
            break status;
        }
        if t0.elapsed() > limit {
            let _ = child.kill();
            let _ = child.wait();
            kill_survivors(pid_file);
            panic!("the run was still going after {limit:?}");
        }
        std::thread::sleep(std::time::Duration::from_millis(50));
    };
    let read = |name: &str| std::fs::read_to_string(scene.out(&format!("{out}.{name}"))).unwrap_or_default();
    (status.code(), format!("{}{}", read("stdout"), read("stderr")))
}

/// Waits up to 5 s for the processes a run's workers left to be gone (SIGKILL takes a moment to
/// end them); those left then (killed after the look).
fn survivors_after_a_moment(pid_file: &Path) -> Vec<u32> {
    let t0 = std::time::Instant::now();
    while !survivors(pid_file).is_empty() && t0.elapsed() < std::time::Duration::from_secs(5) {
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    let left = survivors(pid_file);
    kill_survivors(pid_file);
    left
}

/// A worker that closes its stdout and keeps running is a dead worker: its items fail (saying
/// so) long before any deadline, and nothing of it (its process group) outlives the run. It used
/// to hang the run forever.
#[test]
fn a_worker_that_closes_its_stdout_fails_its_items_and_leaves_no_process() {
    let scene = Scene::new();
    let pids = scene.out("pids");
    let set =
        test_worker(&["--every", "close-stdout", "--pid-file", pids.to_str().unwrap()], "deadline_s: 30, tries: 1");
    let child = spawn_curation(&scene, "out", &set);
    let t0 = std::time::Instant::now();
    let (code, t) = wait_within(&scene, "out", child, std::time::Duration::from_secs(60), &pids);
    assert_eq!(code, Some(1), "{t}");
    assert!(t0.elapsed() < std::time::Duration::from_secs(30), "within one deadline: {:?}", t0.elapsed());
    assert_eq!(failures(&t).len(), 6, "{t}");
    assert!(t.contains("closed its stdout"), "{t}");
    // A fresh worker for each item, until three items in a row failed every try: then the pool
    // gives up on it and the rest fail at once.
    assert_eq!(std::fs::read_to_string(&pids).unwrap().lines().count(), 3, "{t}");
    assert!(t.contains("failed every try of 3 items in a row"), "{t}");
    assert_eq!(survivors_after_a_moment(&pids), Vec::<u32>::new(), "worker processes left after the run");
}

/// A run stopped by a signal leaves no worker process: one SIGTERM stops it cleanly once the
/// hanging worker's deadline has passed; a second one ends it at once, and ends the workers too
/// (it used to leave them running).
#[test]
fn a_run_stopped_by_one_signal_or_two_leaves_no_worker_process() {
    let scene = Scene::new();
    // One signal with a deadline of 600 s and 3 tries: the calls end at once (a cancel, then the
    // kill) and nothing is tried again, instead of holding the stop for half an hour.
    for (signals, options) in [(1, "deadline_s: 600, tries: 3"), (2, "deadline_s: 600, tries: 1")] {
        let pids = scene.out(&format!("pids-{signals}"));
        let set = test_worker(&["--every", "hang", "--pid-file", pids.to_str().unwrap()], options);
        let out = format!("out-{signals}");
        let child = spawn_curation(&scene, &out, &set);
        let t0 = std::time::Instant::now();
        // Once the worker has its first request (and hangs on it).
        let requests = scene.out(&format!("pids-{signals}.requests"));
        while !requests.exists() {
            assert!(t0.elapsed() < std::time::Duration::from_secs(60), "no request reached the worker");
            std::thread::sleep(std::time::Duration::from_millis(20));
        }
        for _ in 0..signals {
            let _ = std::process::Command::new("kill").args(["-TERM", &child.id().to_string()]).status();
            std::thread::sleep(std::time::Duration::from_millis(200));
        }
        let (code, t) = wait_within(&scene, &out, child, std::time::Duration::from_secs(30), &pids);
        assert_eq!(code, Some(143), "{signals} signals: {t}");
        assert_eq!(survivors_after_a_moment(&pids), Vec::<u32>::new(), "{signals} signals: workers left\n{t}");
    }
}
