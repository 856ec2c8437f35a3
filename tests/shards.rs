//! End-to-end: `dist4d run --shard I/N` splits the scenes between processes that share one store;
//! the shards, run at the same time, give the bytes one process gives.

mod common;
use common::*;
use std::collections::BTreeMap;
use std::path::Path;

#[test]
fn shards_run_at_once_on_one_store_give_the_bytes_of_one_process() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    let o = dist4d(&[
        "synth",
        "--out",
        data.to_str().unwrap(),
        "--scenes",
        "3",
        "--keyframes",
        "2",
        "--width",
        "320",
        "--height",
        "180",
    ]);
    assert!(o.status.success(), "{}", text(&o));
    let root = format!("dataset.root={}", data.display());
    let pipeline = repo().join("pipelines/lidar_depth.ron");
    let args = |cache: &Path, out: &Path, shard: Option<&str>| {
        let mut a: Vec<String> = ["run", pipeline.to_str().unwrap(), "--set", &root, "--progress", "off"]
            .iter()
            .map(|s| s.to_string())
            .collect();
        a.extend(["--cache".into(), cache.display().to_string(), "--out".into(), out.display().to_string()]);
        if let Some(s) = shard {
            a.extend(["--shard".into(), s.into()]);
        }
        a
    };
    let one = tmp.path().join("one");
    let o = std::process::Command::new(bin()).args(args(&tmp.path().join("cache-one"), &one, None)).output().unwrap();
    assert!(o.status.success(), "{}", text(&o));

    // Two shards at once against one store, exporting into one folder.
    let shared = tmp.path().join("cache-shared");
    let together = tmp.path().join("together");
    let children: Vec<_> = ["0/2", "1/2"]
        .iter()
        .map(|s| {
            std::process::Command::new(bin())
                .args(args(&shared, &together, Some(s)))
                .stdout(std::process::Stdio::piped())
                .stderr(std::process::Stdio::piped())
                .spawn()
                .unwrap()
        })
        .collect();
    for (k, c) in children.into_iter().enumerate() {
        let o = c.wait_with_output().unwrap();
        assert!(o.status.success(), "shard {k}: {}", text(&o));
    }
    let whole: BTreeMap<String, Vec<u8>> = tree(&one).into_iter().collect();
    let union: BTreeMap<String, Vec<u8>> = tree(&together).into_iter().collect();
    assert_eq!(whole.keys().collect::<Vec<_>>(), union.keys().collect::<Vec<_>>());
    for (path, bytes) in &whole {
        assert!(union[path] == *bytes, "{path} differs between one process and the shards");
    }
    // Each shard left its part of the index; the folder's index.json lists both, byte for byte
    // the index of one process (neither shard's index overwrote the other's).
    let parts: Vec<String> = std::fs::read_dir(together.join(".dist4d-index.d"))
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    assert_eq!(parts.len(), 2, "{parts:?}");
    let index = |dir: &Path| std::fs::read_to_string(dir.join("index.json")).unwrap();
    assert!(index(&together) == index(&one), "the merged index is the whole run's");
    // Each shard exported only its own scenes.
    let scenes = |part: &str| -> std::collections::BTreeSet<String> {
        let v: serde_json::Value =
            serde_json::from_slice(&std::fs::read(together.join(".dist4d-index.d").join(part)).unwrap()).unwrap();
        v["files"]
            .as_array()
            .unwrap()
            .iter()
            .map(|f| f["item"].as_str().unwrap().split('/').next().unwrap().into())
            .collect()
    };
    let (s0, s1) = (scenes("shard-0-of-2.json"), scenes("shard-1-of-2.json"));
    assert!(s0.is_disjoint(&s1) && s0.len() + s1.len() == 3, "{s0:?} {s1:?}");

    // A rerun of one shard finds its work done in the shared store, and its files in place.
    let o = std::process::Command::new(bin()).args(args(&shared, &together, Some("0/2"))).output().unwrap();
    let t = text(&o);
    assert!(o.status.success() && t.contains(" 0 executed"), "{t}");
    assert!(index(&together) == index(&one));
    // A run over the whole dataset (the merge job) folds the shards' parts into one index and
    // one manifest, executing nothing.
    let o = std::process::Command::new(bin()).args(args(&shared, &together, None)).output().unwrap();
    let t = text(&o);
    assert!(o.status.success() && t.contains(" 0 executed"), "{t}");
    assert!(!together.join(".dist4d-index.d").exists());
    assert_eq!(std::fs::read_dir(together.join(".dist4d-manifest.d")).unwrap().count(), 0);
    assert!(index(&together) == index(&one));
    assert!(tree(&together).into_iter().collect::<BTreeMap<_, _>>() == whole);
    // `explain` with the same --shard looks at that shard's scenes (all cached now); without it,
    // at every scene.
    let cached = |shard: Option<&str>| -> (u64, u64) {
        let cache = shared.display().to_string();
        let mut a = vec!["explain", pipeline.to_str().unwrap(), "--set", &root, "--cache", &cache];
        if let Some(s) = shard {
            a.extend(["--shard", s]);
        }
        let o = dist4d(&a);
        let t = text(&o);
        assert!(o.status.success(), "{t}");
        // "project (ProjectLidar): N cached, M will run"
        let line = t.lines().next().unwrap().to_string();
        let n = |w: &str| {
            line.split(": ")
                .nth(1)
                .unwrap()
                .split(", ")
                .find(|p| p.ends_with(w))
                .unwrap()
                .split(' ')
                .next()
                .unwrap()
                .parse()
                .unwrap()
        };
        (n("cached"), n("will run"))
    };
    let (all, _) = cached(None);
    let (c0, r0) = cached(Some("0/2"));
    let (c1, r1) = cached(Some("1/2"));
    assert_eq!((r0, r1, c0 + c1), (0, 0, all), "shard 0 {c0}, shard 1 {c1}, all {all}");
    assert!(c0 > 0 && c1 > 0);
    // A bad shard is refused before anything runs.
    let o = std::process::Command::new(bin()).args(args(&shared, &tmp.path().join("x"), Some("2/2"))).output().unwrap();
    assert!(!o.status.success() && text(&o).contains("I must be 0 to N - 1"), "{}", text(&o));
}
