//! End-to-end tests of the store's robustness: data a newer dist4d wrote, damaged segments and
//! blobs (`verify --store`), a full disk, read-only stores and output folders. They drive the
//! real CLI on a small synthetic dataset; those that need a mount (a full tmpfs, a read-only bind
//! mount) say SKIPPED and return where mounting is not allowed.

mod common;

use common::*;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

struct Setup {
    _tmp: tempfile::TempDir,
    root: PathBuf,
    base: PathBuf,
}

/// A one-scene synthetic dataset, 3 keyframes of 320x180 (the reproduction data).
fn setup() -> Setup {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path().join("data");
    let o = dist4d(&[
        "synth",
        "--out",
        root.to_str().unwrap(),
        "--keyframes",
        "3",
        "--width",
        "320",
        "--height",
        "180",
        "--no-lidar-sweeps",
    ]);
    assert!(o.status.success(), "{}", text(&o));
    let base = tmp.path().to_path_buf();
    Setup { _tmp: tmp, root, base }
}

fn pipeline() -> String {
    repo().join("pipelines/lidar_depth.ron").display().to_string()
}

fn with_store(cmd: &str, s: &Setup, cache: &Path, out: &Path) -> Command {
    let mut c = Command::new(bin());
    c.args([cmd, &pipeline()]);
    if cmd == "run" {
        c.args(["--progress", "off", "--jobs", "2"]);
    }
    c.args(["--cache", cache.to_str().unwrap(), "--out", out.to_str().unwrap()])
        .args(["--set", &format!("dataset.root={}", s.root.display())]);
    c
}

fn run(s: &Setup, cache: &Path, out: &Path) -> Output {
    with_store("run", s, cache, out).output().unwrap()
}

fn the_segment(cache: &Path) -> PathBuf {
    let segs: Vec<PathBuf> = std::fs::read_dir(cache.join("ac"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|x| x == "seg"))
        .collect();
    assert_eq!(segs.len(), 1, "{segs:?}");
    segs[0].clone()
}

/// Every blob file of a store.
fn blobs(cache: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    for d in std::fs::read_dir(cache.join("cas")).unwrap() {
        for f in std::fs::read_dir(d.unwrap().path()).unwrap() {
            out.push(f.unwrap().path());
        }
    }
    out.sort();
    out
}

fn total_executed(run: &serde_json::Value) -> u64 {
    executed(run).values().sum()
}

#[test]
fn a_store_a_newer_dist4d_wrote_is_refused_and_never_deleted() {
    let s = setup();
    let (cache, out) = (s.base.join("cache"), s.base.join("out"));
    let o = run(&s, &cache, &out);
    assert!(o.status.success(), "{}", text(&o));
    let runs_before = std::fs::read_dir(cache.join("runs")).unwrap().count();

    // Its records as a newer dist4d would write them: a segment of format 02.
    let seg = the_segment(&cache);
    let mut bytes = std::fs::read(&seg).unwrap();
    assert!(bytes.starts_with(b"D4SEG01\n"));
    bytes[6] = b'2';
    std::fs::write(&seg, &bytes).unwrap();
    let o = run(&s, &cache, &out);
    let t = text(&o);
    assert!(!o.status.success(), "{t}");
    assert!(t.contains("written by a newer dist4d (segment format 02"), "{t}");
    assert_eq!(std::fs::read_dir(cache.join("runs")).unwrap().count(), runs_before, "nothing ran: {t}");
    let o = dist4d(&["gc", "--cache", cache.to_str().unwrap(), "--keep-runs", "0"]);
    let t = text(&o);
    assert!(!o.status.success() && t.contains("newer dist4d"), "{t}");
    assert_eq!(std::fs::read(&seg).unwrap(), bytes, "gc never deletes what it cannot read");
    let o = dist4d(&["verify", "--store", "--cache", cache.to_str().unwrap()]);
    let t = text(&o);
    assert_eq!(o.status.code(), Some(1), "{t}");
    assert!(t.contains("unreadable: ac/") && t.contains("newer dist4d"), "{t}");

    // Back to our format; then a blob packed with a codec this dist4d does not know.
    bytes[6] = b'1';
    std::fs::write(&seg, &bytes).unwrap();
    let packed = blobs(&cache)
        .into_iter()
        .find(|b| std::fs::read(b).unwrap().starts_with(b"\xd4BLB"))
        .expect("a packed blob (the projected depth map)");
    let mut blob = std::fs::read(&packed).unwrap();
    blob[4] = 9;
    std::fs::write(&packed, &blob).unwrap();
    // With the output folder gone, every blob is read again (as an input, or to export it).
    std::fs::remove_dir_all(&out).unwrap();
    let o = run(&s, &cache, &out);
    let t = text(&o);
    assert_eq!(o.status.code(), Some(1), "{t}");
    assert!(t.contains("was written by a newer dist4d (blob codec 9"), "{t}");
    assert_eq!(std::fs::read(&packed).unwrap(), blob, "left as it is, not removed nor rewritten: {t}");
    let o = dist4d(&["gc", "--cache", cache.to_str().unwrap(), "--keep-runs", "0"]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(packed.exists(), "no record names it, but gc cannot read it: kept. {}", text(&o));
}

#[test]
fn a_flipped_bit_in_a_segment_reruns_one_task_and_verify_store_finds_it() {
    let s = setup();
    let (cache, out) = (s.base.join("cache"), s.base.join("out"));
    let o = run(&s, &cache, &out);
    assert!(o.status.success(), "{}", text(&o));
    let first = last_run(&cache);
    assert!(total_executed(&first) >= 9, "{first}");

    // One bit in the payload of the second record: the rerun finds every record but that one.
    let seg = the_segment(&cache);
    let mut bytes = std::fs::read(&seg).unwrap();
    let len0 = u32::from_le_bytes(bytes[8..12].try_into().unwrap()) as usize;
    let second = 8 + 8 + len0;
    bytes[second + 8 + 20] ^= 0x10;
    std::fs::write(&seg, &bytes).unwrap();
    let o = run(&s, &cache, &out);
    assert!(o.status.success(), "{}", text(&o));
    assert_eq!(total_executed(&last_run(&cache)), 1, "only the task of the damaged record runs again: {}", text(&o));

    // And a blob nothing will read: damage no run would notice.
    let victim = blobs(&cache).into_iter().max_by_key(|b| std::fs::metadata(b).unwrap().len()).unwrap();
    let mut blob = std::fs::read(&victim).unwrap();
    let at = blob.len() / 2;
    blob[at] ^= 1;
    std::fs::write(&victim, &blob).unwrap();
    let o = dist4d(&["verify", "--store", "--cache", cache.to_str().unwrap()]);
    let t = text(&o);
    assert_eq!(o.status.code(), Some(1), "{t}");
    let name = seg.file_name().unwrap().to_str().unwrap();
    assert!(t.contains(&format!("damaged:  ac/{name}: bytes {second}..")), "{t}");
    let hex = victim.strip_prefix(cache.join("cas")).unwrap().display().to_string();
    assert!(t.contains(&format!("cas/{hex}: is corrupt")), "{t}");
    assert!(t.contains("2 damaged, 0 unreadable"), "{t}");
    assert_eq!(std::fs::read(&victim).unwrap(), blob, "verify changes nothing");
}

/// A mount made for a test, undone when dropped.
struct Mount(PathBuf);

impl Mount {
    fn tmpfs(dir: &Path, size: &str) -> Option<Mount> {
        std::fs::create_dir_all(dir).unwrap();
        Mount::run(&["-t", "tmpfs", "-o", &format!("size={size}"), "tmpfs", dir.to_str().unwrap()])
            .then(|| Mount(dir.into()))
    }

    /// `dir` mounted read-only over itself.
    fn read_only(dir: &Path) -> Option<Mount> {
        let d = dir.to_str().unwrap();
        if !Mount::run(&["--bind", d, d]) {
            return None;
        }
        let m = Mount(dir.into());
        Mount::run(&["-o", "remount,ro,bind", d]).then_some(m)
    }

    fn run(args: &[&str]) -> bool {
        let ok = Command::new("mount").args(args).output().is_ok_and(|o| o.status.success());
        if !ok {
            eprintln!(
                "SKIPPED: `mount {}` is not allowed here (the test needs root in a mount namespace)",
                args.join(" ")
            );
        }
        ok
    }
}

impl Drop for Mount {
    fn drop(&mut self) {
        let _ = Command::new("umount").arg(&self.0).output();
    }
}

#[test]
fn a_run_stopped_by_a_full_disk_is_recorded_as_failed_and_leaves_no_temp_files() {
    let s = setup();
    let disk = s.base.join("small");
    let Some(_mount) = Mount::tmpfs(&disk, "2M") else { return };
    let (cache, out) = (disk.join("cache"), disk.join("out"));
    let o = run(&s, &cache, &out);
    let t = text(&o);
    assert_eq!(o.status.code(), Some(1), "{t}");
    assert!(t.contains("No space left on device"), "{t}");
    let rec = last_run(&cache);
    assert_eq!(rec["status"], "failed", "{rec}");
    let errors = rec["failures"].to_string();
    assert!(errors.contains("No space left on device"), "{rec}");
    let listed = text(&dist4d(&["runs", "--cache", cache.to_str().unwrap()]));
    assert!(listed.contains("Failed") && !listed.contains("Killed"), "{listed}");
    for dir in [cache.join("tmp"), out.join(".dist4d-tmp")] {
        let left: Vec<_> =
            std::fs::read_dir(&dir).map(|d| d.map(|e| e.unwrap().file_name()).collect()).unwrap_or_default();
        assert!(left.is_empty(), "temp files left in {}: {left:?}", dir.display());
    }
}

#[test]
fn a_read_only_store_can_be_explained_gc_dry_run_and_verified_and_a_finished_read_only_out_reruns() {
    let s = setup();
    let (cache, out) = (s.base.join("cache"), s.base.join("out"));
    let o = run(&s, &cache, &out);
    assert!(o.status.success(), "{}", text(&o));
    let before = tree(&cache);
    {
        let Some(_ro) = Mount::read_only(&cache) else { return };
        assert!(std::fs::write(cache.join("probe"), b"x").is_err(), "the store is read-only");
        let o = with_store("explain", &s, &cache, &out).output().unwrap();
        let t = text(&o);
        assert!(o.status.success(), "{t}");
        assert!(t.contains("encode (EncodeDepth): 18 cached, 0 will run"), "{t}");
        let o = dist4d(&["gc", "--dry-run", "--cache", cache.to_str().unwrap(), "--keep-runs", "0"]);
        let t = text(&o);
        assert!(o.status.success(), "{t}");
        assert!(t.contains("nothing removed") && t.contains("would remove 1 runs"), "{t}");
        let o = dist4d(&["verify", "--store", "--cache", cache.to_str().unwrap()]);
        assert!(o.status.success(), "{}", text(&o));
    }
    assert!(tree(&cache) == before, "nothing in the store changed");

    // A finished output folder on a read-only mount: a run with nothing to do succeeds.
    let Some(_ro) = Mount::read_only(&out) else { return };
    let o = run(&s, &cache, &out);
    let t = text(&o);
    assert!(o.status.success(), "{t}");
    let rec = last_run(&cache);
    assert_eq!((rec["status"].as_str(), total_executed(&rec)), (Some("complete"), 0), "{rec}");
}

#[test]
fn gc_and_verify_store_on_a_missing_store_say_so_and_create_nothing() {
    let tmp = tempfile::tempdir().unwrap();
    let missing = tmp.path().join("no-store");
    for args in [vec!["gc", "--cache"], vec!["gc", "--dry-run", "--cache"], vec!["verify", "--store", "--cache"]] {
        let o = dist4d(&[&args[..], &[missing.to_str().unwrap()]].concat());
        let t = text(&o);
        assert!(!o.status.success(), "{args:?}: {t}");
        assert!(t.contains(&format!("there is no store at {}", missing.display())), "{args:?}: {t}");
        assert!(!missing.exists(), "{args:?} made a store");
    }
}
