//! End-to-end: a pipeline stage served by an external model worker (the reference completer of
//! workers/, numpy from the peer venv), from the CLI.

mod common;
use common::*;

/// The executed count of `stage` in a run table.
fn executed(report: &str, stage: &str) -> u64 {
    let line = report
        .lines()
        .find(|l| l.split_whitespace().next() == Some(stage))
        .unwrap_or_else(|| panic!("{stage}\n{report}"));
    line.split_whitespace().nth(3).unwrap().parse().unwrap()
}

#[test]
fn complete_depth_through_a_worker_is_cached_and_reruns_when_the_worker_changes() {
    let Some(python) = peers_python() else { return };
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    assert!(dist4d(&[
        "synth",
        "--out",
        data.to_str().unwrap(),
        "--keyframes",
        "2",
        "--width",
        "320",
        "--height",
        "180"
    ])
    .status
    .success());
    let script = repo().join("workers/fill_completer.py");
    let worker = format!("complete.worker=Some((program: \"{}\", args: [\"{}\"]))", python.display(), script.display());
    let run = |out: &str, sets: &[&str], version: &str| {
        let root = format!("dataset.root={}", data.display());
        let (cache, out) = (tmp.path().join("cache"), tmp.path().join(out));
        let mut args = vec![
            "run",
            "pipelines/curation.ron",
            "--set",
            &root,
            "--cache",
            cache.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ];
        args.extend(sets);
        let o = std::process::Command::new(bin())
            .current_dir(repo())
            .args(&args)
            .env("FILL_COMPLETER_VERSION", version)
            .output()
            .unwrap();
        let t = text(&o);
        assert!(o.status.success(), "{t}");
        t
    };
    let builtin = run("builtin", &[], "1");
    let first = run("worker", &["--set", &worker], "1");
    assert_eq!((executed(&first, "complete"), executed(&first, "aggregate")), (12, 0), "{first}");
    let read = |dir: &str| std::fs::read(tmp.path().join(dir).join("synth-0000/CAM_FRONT/000_depth.npy")).unwrap();
    assert_ne!(read("builtin"), read("worker"), "the worker's completion is its own");
    let _ = builtin;
    // Cached across runs: the worker is asked for its identity only.
    let again = run("worker", &["--set", &worker], "1");
    assert_eq!(executed(&again, "complete"), 0, "{again}");
    // A new version of the model: its stage reruns; the same bytes cut off what follows.
    let new = run("worker", &["--set", &worker], "2");
    assert_eq!((executed(&new, "complete"), executed(&new, "prompt"), executed(&new, "encode")), (12, 0, 0), "{new}");
    // A worker that fails an item fails that item only, with the worker's own words.
    let broken = format!(
        "complete.worker=Some((program: \"{}\", args: [\"-c\", \"import sys,json; print(json.dumps({{'type':'hello','protocol':1,'name':'broken','version':'1','ops':['complete_depth']}}), flush=True); [print(json.dumps({{'type':'reply','id':json.loads(l)['id'],'status':'error','message':'out of ideas'}}), flush=True) for l in sys.stdin if json.loads(l)['type']=='request']\"], tries: 1))",
        python.display()
    );
    let root = format!("dataset.root={}", data.display());
    let o = std::process::Command::new(bin())
        .current_dir(repo())
        .args([
            "run",
            "pipelines/curation.ron",
            "--set",
            &root,
            "--cache",
            tmp.path().join("cache").to_str().unwrap(),
            "--out",
            tmp.path().join("broken").to_str().unwrap(),
            "--set",
            &broken,
        ])
        .output()
        .unwrap();
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
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    assert!(dist4d(&[
        "synth",
        "--out",
        data.to_str().unwrap(),
        "--keyframes",
        "2",
        "--width",
        "320",
        "--height",
        "180"
    ])
    .status
    .success());
    let worker = format!(
        "novel.worker=Some((program: \"{}\", args: [\"{}\"]))",
        python.display(),
        repo().join("workers/fill_generator.py").display()
    );
    let run = |out: &str, sets: &[&str]| {
        let root = format!("dataset.root={}", data.display());
        let (cache, out) = (tmp.path().join("cache"), tmp.path().join(out));
        let mut args = vec![
            "run",
            "pipelines/scc.ron",
            "--set",
            &root,
            "--cache",
            cache.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ];
        args.extend(sets);
        let o = std::process::Command::new(bin()).current_dir(repo()).args(&args).output().unwrap();
        let t = text(&o);
        assert!(o.status.success(), "{t}");
        t
    };
    run("baseline", &[]);
    let first = run("worker", &["--set", &worker]);
    assert_eq!((executed(&first, "novel"), executed(&first, "complete")), (12, 0), "{first}");
    let pairs = std::fs::read_to_string(tmp.path().join("worker/synth-0000/pairs.jsonl")).unwrap();
    assert_eq!(pairs.lines().count(), 12);
    let cond =
        |dir: &str| std::fs::read(tmp.path().join(dir).join("synth-0000/CAM_FRONT/000_random_cond.png")).unwrap();
    assert_ne!(cond("baseline"), cond("worker"), "the condition comes back from the worker's view");
    let again = run("worker", &["--set", &worker]);
    assert_eq!(executed(&again, "novel"), 0, "{again}");
}

/// The sky from a segmenter worker (the reference one of workers/): the curation's sky follows
/// its ids, and the depth there is the sky depth.
#[test]
fn the_sky_from_a_segmenter_worker() {
    let Some(python) = peers_python() else { return };
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    assert!(dist4d(&[
        "synth",
        "--out",
        data.to_str().unwrap(),
        "--keyframes",
        "2",
        "--width",
        "320",
        "--height",
        "180"
    ])
    .status
    .success());
    let worker = format!(
        "sky.worker=Some((program: \"{}\", args: [\"{}\"]))",
        python.display(),
        repo().join("workers/sky_segmenter.py").display()
    );
    let root = format!("dataset.root={}", data.display());
    let out = tmp.path().join("out");
    let o = std::process::Command::new(bin())
        .current_dir(repo())
        .args([
            "run",
            "pipelines/curation.ron",
            "--set",
            &root,
            "--cache",
            tmp.path().join("cache").to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--set",
            &worker,
        ])
        .output()
        .unwrap();
    let t = text(&o);
    assert!(o.status.success(), "{t}");
    assert_eq!(executed(&t, "sky"), 12, "{t}");
    let depth_of = |out: &std::path::Path| -> Vec<f32> {
        let npy = std::fs::read(out.join("synth-0000/CAM_FRONT/000_depth.npy")).unwrap();
        let header = u16::from_le_bytes([npy[8], npy[9]]) as usize;
        npy[10 + header..].chunks_exact(4).map(|c| f32::from_le_bytes(c.try_into().unwrap())).collect()
    };
    let top_sky = depth_of(&out)[..320].iter().filter(|&&z| z == 100.0).count();
    assert!(top_sky > 0, "the reference segmenter finds the synthetic sky at the top");
    // A segmenter that calls exactly the top ten rows sky: the depth there is the sky depth.
    let ten_rows = format!(
        "sky.worker=Some((program: \"{}\", args: [\"-c\", \"import sys,json,numpy as np; print(json.dumps({{'type':'hello','protocol':1,'name':'ten-rows','version':'1','ops':['segment']}}), flush=True)\\nfor l in sys.stdin:\\n m=json.loads(l)\\n if m['type']!='request': continue\\n im=np.load(m['inputs'][0]['path']); ids=np.full(im.shape[:2],7,np.uint8); ids[:10]=23; p=m['out_dir']+'/s.npy'; np.save(p,ids); print(json.dumps({{'type':'reply','id':m['id'],'status':'ok','outputs':[{{'name':'semantic','path':p}}]}}), flush=True)\"]))",
        python.display()
    );
    let out2 = tmp.path().join("out2");
    let o = std::process::Command::new(bin())
        .current_dir(repo())
        .args([
            "run",
            "pipelines/curation.ron",
            "--set",
            &root,
            "--cache",
            tmp.path().join("cache").to_str().unwrap(),
            "--out",
            out2.to_str().unwrap(),
            "--set",
            &ten_rows,
        ])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", text(&o));
    let depth = depth_of(&out2);
    assert!(depth[..10 * 320].iter().all(|&z| z == 100.0), "the ten sky rows at 100 m");
    assert!(depth[10 * 320..].iter().filter(|&&z| z == 100.0).count() < 320, "below them, structure");
}
