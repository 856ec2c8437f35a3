//! End-to-end: semantic occupancy (pipelines/occupancy.ron) from the CLI on synthetic data, its
//! labels.npz loaded with numpy exactly as Occ3D's loader does, side by side with the real
//! Occ3D-nuScenes frame of ../shared/data.

mod common;
use common::*;

/// A run table's column for `stage`: 3 = executed, 4 = cached.
fn column(report: &str, stage: &str, col: usize) -> u64 {
    let line = report
        .lines()
        .find(|l| l.split_whitespace().next() == Some(stage))
        .unwrap_or_else(|| panic!("no {stage} in\n{report}"));
    line.split_whitespace().nth(col).unwrap().parse().unwrap()
}

#[test]
fn occ3d_labels_from_the_cli_load_like_the_real_occ3d_frame_and_a_param_reruns_only_its_stage() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    let o =
        dist4d(&["synth", "--out", data.to_str().unwrap(), "--keyframes", "4", "--width", "320", "--height", "180"]);
    assert!(o.status.success(), "{}", text(&o));
    let root = format!("dataset.root={}", data.display());
    let (cache, out) = (tmp.path().join("cache"), tmp.path().join("out"));
    // The shipped pipeline with DynamicCity's windows of 4 frames (the scene has 4), one per frame.
    let shipped = std::fs::read_to_string(repo().join("pipelines/occupancy.ron")).unwrap();
    let windowed = shipped.replace("frame, 0, 15)", "frame, 0, 3)").replace("every: 16", "every: 4");
    assert_eq!(windowed.matches("frame, 0, 3)").count(), 4);
    // The conditions at every frame, as the released loader's sliding windows.
    let windowed = windowed.replacen("            every: 4,\n", "            every: 1,\n", 1);
    assert_eq!(windowed.matches("every: 1,").count(), 1);
    let pipeline = tmp.path().join("occupancy.ron");
    std::fs::write(&pipeline, windowed).unwrap();
    let pipeline = pipeline.to_str().unwrap().to_string();
    let run = |extra: &[&str]| {
        let mut args =
            vec!["run", pipeline.as_str(), "--set", &root, "--progress", "off", "--cache", cache.to_str().unwrap()];
        args.extend(["--set", "conditions.frames=4", "--set", "hexplane.frames=4"]);
        args.extend(["--set", "sheet.frames=4", "--set", "sheet.columns=2"]);
        args.extend(["--out", out.to_str().unwrap()]);
        args.extend(extra);
        let o = std::process::Command::new(bin()).current_dir(repo()).args(&args).output().unwrap();
        let t = text(&o);
        assert!(o.status.success(), "{t}");
        t
    };
    let first = run(&[]);
    assert_eq!(
        (column(&first, "scene", 3), column(&first, "occupancy", 3), column(&first, "occ3d", 3)),
        (1, 4, 4),
        "{first}"
    );
    let summary: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("synth-0000/aggregate.json")).unwrap()).unwrap();
    assert_eq!(summary["sweeps_with_labels"], 4, "the synthetic lidarseg files are read: {summary}");
    // The window's sheet: 4 bird's-eye views of 400 x 400 in 2 columns, 4 px apart.
    let sheet = image::open(out.join("synth-0000/occupancy/000_window_sheet.png")).unwrap();
    assert_eq!((sheet.width(), sheet.height()), (804, 804));
    assert!(!out.join("synth-0000/occupancy/001_window_sheet.png").exists(), "one sheet per window");
    assert!(summary["tracks"].as_u64().unwrap() > 0, "{summary}");
    // Occ3D's annotations.json, merged from the scenes' parts: every frame in time order, its
    // cameras, poses and the labels.npz it points at.
    let o = dist4d(&["occ3d-annotations", out.to_str().unwrap(), "--val", "synth-0000"]);
    assert!(o.status.success(), "{}", text(&o));
    let a: serde_json::Value = serde_json::from_slice(&std::fs::read(out.join("annotations.json")).unwrap()).unwrap();
    assert_eq!(
        (a["val_split"].clone(), a["train_split"].clone()),
        (serde_json::json!(["synth-0000"]), serde_json::json!([]))
    );
    let frames = a["scene_infos"]["synth-0000"].as_object().unwrap();
    assert_eq!(frames.len(), 4);
    let heads: Vec<_> = frames.values().filter(|f| f["prev"] == "").collect();
    assert_eq!(heads.len(), 1, "one first frame");
    for (token, f) in frames {
        assert!(out.join(f["gt_path"].as_str().unwrap()).is_file(), "{token}: {}", f["gt_path"]);
        assert_eq!(f["camera_sensor"].as_object().unwrap().len(), 6);
        if f["next"] != "" {
            assert_eq!(frames[f["next"].as_str().unwrap()]["prev"], token.as_str());
        }
        let cam = f["camera_sensor"].as_object().unwrap().values().next().unwrap();
        assert!(
            data.join(cam["img_path"].as_str().unwrap()).is_file()
                && cam["extrinsic"]["rotation"].as_array().unwrap().len() == 4
        );
    }
    let bad = dist4d(&["occ3d-annotations", out.to_str().unwrap(), "--val", "scene-nope"]);
    assert!(!bad.status.success() && text(&bad).contains("names scene scene-nope"), "{}", text(&bad));

    // `dist4d synth` writes the exact occupancy of its keyframes itself, in Occ3D's layout: the
    // same bytes as the pipeline's `exact` stage (same grid, classes and ray casting).
    let synth_gts = data.join("groundtruth/occupancy/gts/synth-0000");
    let tokens: Vec<_> = std::fs::read_dir(&synth_gts).unwrap().map(|e| e.unwrap().file_name()).collect();
    assert_eq!(tokens.len(), 4);
    for t in &tokens {
        let written = std::fs::read(synth_gts.join(t).join("labels.npz")).unwrap();
        let staged = std::fs::read(out.join("exact/gts/synth-0000").join(t).join("labels.npz")).unwrap();
        assert!(written == staged, "{t:?}: synth's and the pipeline's exact occupancy differ");
    }

    // A per-frame param: the scene's aggregate is reused.
    let again = run(&["--set", "occupancy.ground_fill=1"]);
    assert_eq!((column(&again, "scene", 3), column(&again, "occupancy", 3)), (0, 4), "{again}");

    // Scored against the synthetic world's exact occupancy (Occ3D's metric), and the ablation:
    // objects gathered in the world instead of their box frames smear the moving ones.
    let eval = |extra: &[&str]| {
        let mut args = vec!["eval", pipeline.as_str(), "--set", &root, "--progress", "off"];
        args.extend(["--set", "conditions.frames=4", "--set", "hexplane.frames=4", "--set", "sheet.frames=4"]);
        args.extend(["--set", "sheet.columns=2", "--cache", cache.to_str().unwrap()]);
        args.extend(extra);
        let o = std::process::Command::new(bin()).current_dir(repo()).args(&args).output().unwrap();
        let t = text(&o);
        assert!(o.status.success(), "{t}");
        let value = |row: &str| -> f64 {
            let line = t.lines().find(|l| l.starts_with(&format!("| {row} |"))).unwrap_or_else(|| panic!("{row}: {t}"));
            line.split('|').nth(2).unwrap().trim().parse().unwrap()
        };
        (value("mIoU"), value("geometry IoU"), value("car"), value("pedestrian"), t)
    };
    let ab_out = tmp.path().join("ablation");
    let (miou, geometry, car, pedestrian, t) = eval(&["--out", out.to_str().unwrap()]);
    assert!(miou > 0.6 && geometry > 0.7, "mIoU {miou}, geometry IoU {geometry}\n{t}");
    let (_, _, car_ab, pedestrian_ab, t_ab) =
        eval(&["--out", ab_out.to_str().unwrap(), "--set", "scene.objects=World"]);
    assert!(
        car > car_ab && pedestrian > pedestrian_ab,
        "box frames {car}/{pedestrian}, world {car_ab}/{pedestrian_ab}\n{t}\n{t_ab}"
    );

    let Some(python) = peers_python() else { return };
    let real = repo().join("../shared/data/occ3d-nuscenes-sample/29796060110c4163b07f06eff4af0753/labels.npz");
    if !real.is_file() {
        eprintln!("SKIPPED: the real Occ3D frame is not at {} (CI always has it)", real.display());
        return;
    }
    // Occ3D's layout: gts/<scene>/<sample token>/labels.npz (the export path's `{frame.token}`).
    let samples: serde_json::Value =
        serde_json::from_slice(&std::fs::read(data.join("v1.0-mini/sample.json")).unwrap()).unwrap();
    let second = samples.as_array().unwrap().iter().find(|s| s["prev"] != "" && s["next"] != "").unwrap();
    let ours = out.join(format!("gts/synth-0000/{}/labels.npz", second["token"].as_str().unwrap()));
    assert!(ours.is_file(), "{} (by sample token)", ours.display());
    // What Occ3D's loader does (projects/mmdet3d_plugin/datasets/pipelines/loading.py): np.load,
    // then the three keys; then what its metric does with the masks (astype(bool)).
    let script = r#"
import sys, numpy as np
files = [np.load(p) for p in sys.argv[1:3]]
real, ours = files
assert sorted(real.files) == sorted(ours.files) == ['mask_camera', 'mask_lidar', 'semantics'], (real.files, ours.files)
for k in real.files:
    a, b = real[k], ours[k]
    assert a.dtype == b.dtype == np.uint8 and a.shape == b.shape == (200, 200, 16), (k, a.dtype, b.dtype, a.shape, b.shape)
for f in files:
    s, ml, mc = f['semantics'], f['mask_lidar'].astype(bool), f['mask_camera'].astype(bool)
    assert s.max() <= 17 and set(np.unique(f['mask_lidar'])) <= {0, 1} and set(np.unique(f['mask_camera'])) <= {0, 1}
    assert not (mc & ~ml).any(), 'mask_camera within mask_lidar'
    road = np.nonzero(s == 11)
    assert len(road[2]) > 1000 and (road[2] == 0).all(), ('the road is in z layer 0', np.bincount(road[2]))
    assert (s == 17).mean() > 0.8, (s == 17).mean()
    assert 0.02 < ml.mean() < 0.5 and mc.sum() > 1000, (ml.mean(), mc.sum())
    # The road runs along x through the ego: the centre column is road at the bottom.
    assert s[100, 100, 0] == 11 and (s[100, 100, 1:] == 17).all(), s[100, 100]
print('ok')
"#;
    let o = std::process::Command::new(&python)
        .args(["-c", script, real.to_str().unwrap(), ours.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(o.status.success() && String::from_utf8_lossy(&o.stdout).contains("ok"), "{}", text(&o));

    // The voxel preview as Open3D reads it: one coloured point per occupied voxel, on the grid.
    let ply = out.join("synth-0000/occupancy/001_voxels.ply");
    let check = "import sys, numpy as np, open3d as o3d
p = o3d.io.read_point_cloud(sys.argv[1])
x, c = np.asarray(p.points), np.asarray(p.colors)
assert len(x) > 1000 and p.has_colors(), len(x)
v = (x[:, :2] + 40) / 0.4 - 0.5
assert np.abs(v - np.round(v)).max() < 1e-3, 'voxel centres'
assert np.isclose(x[:, 2].min(), 0, atol=1e-4), 'the lowest layer is centred on the road'
assert (np.abs(c - [1, 0, 1]).sum(1) < 1e-3).any(), 'driveable surface in magenta'
print('ok')";
    let o = std::process::Command::new(&python).args(["-c", check, ply.to_str().unwrap()]).output().unwrap();
    assert!(o.status.success() && String::from_utf8_lossy(&o.stdout).contains("ok"), "{}", text(&o));

    // DynamicCity's released loader (dynamic_city/dataset/carlasc.py), its path logic and reads
    // reimplemented on the output: sliding windows of `sequence_length` with `skip`, `.label` ->
    // `.bin` by name, and the trajectory and command of data_utils.py from poses.txt, which must be
    // the conditions dist4d wrote for the window.
    let loader = r#"
import sys, json, numpy as np
from pathlib import Path
data_path, T, skip, spatial = Path(sys.argv[1]), 4, 0, (200, 200, 16)
data_root = data_path / 'Train'
scene_roots = [p / 'cartesian/evaluation' for p in data_root.iterdir()]
span = T * (skip + 1) - skip
sequences = []
for scene_root in scene_roots:
    files = sorted(map(str, scene_root.glob('*.label')))
    assert len(files) == 4, files
    sequences += [files[s: s + span: skip + 1] for s in range(len(files) - (span - 1))]
assert len(sequences) == 1
for path in sequences[0]:
    voxel = np.fromfile(path, dtype=np.uint32).reshape(spatial)
    valid = np.fromfile(path.replace('label', 'bin'), dtype=np.float32).reshape(spatial)
    invalid = (valid == 0).astype(np.uint8)
    assert voxel.max() <= 17 and (voxel == 0).mean() > 0.8 and voxel[100, 100, 0] == 12, (voxel.max(), voxel[100, 100])
    assert 0.5 < invalid.mean() < 1.0
poses = np.loadtxt(data_root / 'synth-0000/cartesian/poses.txt')
assert poses.shape == (4, 12), poses.shape
traj = np.column_stack((poses[:, [3, 7]] - poses[0, [3, 7]], np.arctan2(poses[:, 4], poses[:, 0])))
rot = traj[:, 2] - traj[0, 2]
rot = (rot + np.pi) % (2 * np.pi) - np.pi
disp = np.sqrt((traj[:, 0] - traj[0, 0]) ** 2 + (traj[:, 1] - traj[0, 1]) ** 2)
command = 2 if np.any(rot > 0.0025) else 3 if np.any(rot < -0.0025) else 1 if np.any(disp > 0.03) else 0
ours = json.load(open(sys.argv[2]))
assert np.allclose(np.array(ours['trajectory']), traj, atol=1e-6), (ours['trajectory'], traj)
assert ours['command'] == command, (ours['command'], command)
layout = np.load(sys.argv[3])['layout']
assert layout.dtype == np.uint8 and layout.shape == (4, 100, 100) and layout.max() == 1, (layout.dtype, layout.shape)
# The DiT's read of a rollout (hexplane_dataset.py: np.load(path)['rollout'].squeeze()) and the
# released rollout_to_hexplane's slices, with (T, X, Y, Z) = (4, 200, 200, 16).
f = np.load(sys.argv[4])
r, mask = f['rollout'].squeeze(), f['mask']
T, X, Y, Z = 4, 200, 200, 16
assert r.dtype == np.float32 and r.shape == (18, X + T + Z, Y + Z + T) and mask.shape == r.shape[1:], (r.shape, mask.shape)
xy, tz = r[:, :X, :Y], r[:, X:X + T, Y:Y + Z]
assert np.allclose(xy.sum(0), 1, atol=1e-4), 'the baseline xy plane is a class distribution per cell'
assert (r[:, X:X + T, Y + Z:] == 0).all() and (mask[X:, Y + Z:] == 0).all() and (mask[:X, :Y] == 1).all()
print('ok')
"#;
    let dc = out.join("dynamiccity");
    let o = std::process::Command::new(&python)
        .args([
            "-c",
            loader,
            dc.join("Cartesian").to_str().unwrap(),
            dc.join("conditions/16/Train/synth-0000/000000.json").to_str().unwrap(),
            dc.join("layout/16/Train/synth-0000/000000.npz").to_str().unwrap(),
            dc.join("rollout/baseline/Train/synth-0000/000000.npz").to_str().unwrap(),
        ])
        .output()
        .unwrap();
    assert!(o.status.success() && String::from_utf8_lossy(&o.stdout).contains("ok"), "{}", text(&o));
    // The same window through the reference HexPlane worker (numpy, the released
    // hexplane_to_rollout's concatenations): the same rollout as the built-in baseline's.
    let worker = format!(
        "hexplane.worker=Some((program: {:?}, args: [{:?}]))",
        python.display().to_string(),
        repo().join("workers/hexplane_means.py").display().to_string()
    );
    let worker_out = tmp.path().join("worker");
    let mut args =
        vec!["run", pipeline.as_str(), "--set", &root, "--progress", "off", "--cache", cache.to_str().unwrap()];
    args.extend(["--set", "conditions.frames=4", "--set", "hexplane.frames=4"]);
    args.extend(["--set", "sheet.frames=4", "--set", &worker]);
    args.extend(["--out", worker_out.to_str().unwrap()]);
    let o = std::process::Command::new(bin()).current_dir(repo()).args(&args).output().unwrap();
    assert!(o.status.success(), "{}", text(&o));
    let compare = "import sys, numpy as np
a, b = np.load(sys.argv[1]), np.load(sys.argv[2])
assert a['rollout'].shape == b['rollout'].shape, (a['rollout'].shape, b['rollout'].shape)
assert np.allclose(a['rollout'], b['rollout'], atol=1e-6), np.abs(a['rollout'] - b['rollout']).max()
assert (a['mask'] == b['mask']).all()
print('ok')";
    let rel = "dynamiccity/rollout/baseline/Train/synth-0000/000000.npz";
    let o = std::process::Command::new(&python)
        .args(["-c", compare, out.join(rel).to_str().unwrap(), worker_out.join(rel).to_str().unwrap()])
        .output()
        .unwrap();
    assert!(o.status.success() && String::from_utf8_lossy(&o.stdout).contains("ok"), "{}", text(&o));

    // The baseline HexPlane's reconstruction of the window: the ground and the free air come back.
    let scores: serde_json::Value = serde_json::from_slice(
        &std::fs::read(dc.join("rollout/baseline/Train/synth-0000/000000_scores.json")).unwrap(),
    )
    .unwrap();
    let road = scores["iou"]["driveable_surface"].as_f64().unwrap();
    assert!(road > 0.7 && scores["miou"].as_f64().unwrap() > 0.3, "{scores}");
}

/// The shared real recordings: the nuScenes keyframe (folder named by its sample token) and the
/// DGP scene (by LiDAR datum key); neither has point labels: `run` warns once, naming the stage
/// and the dataset, and every frame's meta.json and the summary say the semantics are geometry.
#[test]
fn occupancy_runs_on_the_shared_nuscenes_and_dgp_recordings() {
    let (Some(nuscenes), Some(dgp)) = (shared_nuscenes(), shared_dgp()) else { return };
    let tmp = tempfile::tempdir().unwrap();
    let pipelines = [
        (
            "nuscenes",
            with_dataset(
                "occupancy",
                &format!("NuScenes(root: {:?}, version: \"v1.0-mini\")", nuscenes.display().to_string()),
            ),
        ),
        ("dgp", with_dataset("occupancy", &format!("Dgp(root: {:?})", dgp.display().to_string()))),
    ];
    for (name, pipeline) in pipelines {
        let file = tmp.path().join(format!("{name}.ron"));
        std::fs::write(&file, pipeline).unwrap();
        let out = tmp.path().join(format!("out-{name}"));
        let o = dist4d(&["run", file.to_str().unwrap(), "--progress", "off", "--out", out.to_str().unwrap()]);
        let t = text(&o);
        assert!(o.status.success(), "{name}: {t}");
        let warnings: Vec<&str> = t.lines().filter(|l| l.contains("geometry only")).collect();
        assert_eq!(warnings.len(), 1, "{name}: one warning line\n{t}");
        let dataset = if name == "dgp" { "Dgp at " } else { "NuScenes at " };
        assert!(
            warnings[0].starts_with("warning: stage `scene` (AggregateScene): dataset ")
                && warnings[0].contains(dataset),
            "{t}"
        );
        assert_eq!(
            column(&t, "exact", 7),
            column(&t, "exact", 2),
            "{name}: no exact occupancy off synthetic data\n{t}"
        );
        let scene = std::fs::read_dir(out.join("gts")).unwrap().next().unwrap().unwrap().path();
        let frames: Vec<_> = std::fs::read_dir(&scene).unwrap().map(|e| e.unwrap().path()).collect();
        assert_eq!(frames.len() as u64, column(&t, "occupancy", 3), "{name}");
        for f in &frames {
            assert!(f.join("labels.npz").is_file(), "{}", f.display());
            let meta: serde_json::Value = serde_json::from_slice(&std::fs::read(f.join("meta.json")).unwrap()).unwrap();
            assert_eq!(
                (meta["semantics_source"].as_str(), meta["geometry_only"].as_bool()),
                (Some("geometry"), Some(true))
            );
        }
        let summary = std::fs::read_to_string(out.join(scene.file_name().unwrap()).join("aggregate.json")).unwrap();
        assert!(summary.contains(r#""semantics_source": "geometry""#), "{name}: {summary}");
        // The report says so too.
        let o = dist4d(&["eval", file.to_str().unwrap(), "--progress", "off", "--out", out.to_str().unwrap()]);
        let t = text(&o);
        assert!(
            o.status.success() && t.contains("# labels of ") && t.contains("geometry only: no sweep"),
            "{name}: {t}"
        );
    }
    assert!(tmp.path().join("out-nuscenes/gts/scene-0061/ca9a282c9e77460f8360f564131a8af5/labels.npz").is_file());
}

/// Occupancy at the LiDAR's rate (`frames: Sweeps`, 20 Hz), which Occ3D lacks: the sweeps
/// between keyframes have no lidarseg labels and take the nearest labelled point's, and every
/// sweep gets its labels.npz, named by its LiDAR sample_data token.
#[test]
fn occupancy_at_every_sweep_takes_labels_from_the_keyframes() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    let o =
        dist4d(&["synth", "--out", data.to_str().unwrap(), "--keyframes", "3", "--width", "320", "--height", "180"]);
    assert!(o.status.success(), "{}", text(&o));
    let root = format!("dataset.root={}", data.display());
    let out = tmp.path().join("out");
    let o = std::process::Command::new(bin())
        .current_dir(repo())
        .args(["run", "pipelines/occupancy.ron", "--set", &root, "--set", "dataset.frames=Sweeps"])
        .args(["--set", "exact.samples=1", "--progress", "off", "--cache", tmp.path().join("cache").to_str().unwrap()])
        .args(["--out", out.to_str().unwrap()])
        .output()
        .unwrap();
    let t = text(&o);
    assert!(o.status.success(), "{t}");
    let frames = column(&t, "occupancy", 3);
    assert!(frames > 3 * 5, "20 Hz sweeps, not the 3 keyframes: {frames}\n{t}");
    let summary: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("synth-0000/aggregate.json")).unwrap()).unwrap();
    assert_eq!(summary["sweeps_with_labels"], 3, "{summary}");
    assert!(
        summary["static_labels_transferred"].as_u64().unwrap()
            > summary["static_labels_by_height"].as_u64().unwrap() * 4,
        "{summary}"
    );
    let written = std::fs::read_dir(out.join("gts/synth-0000")).unwrap().count() as u64;
    assert_eq!(written, frames);
}

/// DynamicCity's DiT as a worker (the persistence reference of workers/hexplane_persist.py): the
/// window after the first gets a generated rollout from its conditions and the previous
/// window's; without a worker the stage has nothing to make.
#[test]
fn a_dit_worker_generates_the_next_windows_hexplane() {
    let Some(python) = peers_python() else { return };
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    let o =
        dist4d(&["synth", "--out", data.to_str().unwrap(), "--keyframes", "8", "--width", "320", "--height", "180"]);
    assert!(o.status.success(), "{}", text(&o));
    // Windows of 4 frames, one every 4: windows at frames 0 and 4.
    let shipped = std::fs::read_to_string(repo().join("pipelines/occupancy.ron")).unwrap();
    let windowed = shipped
        .replace("frame, 0, 15)", "frame, 0, 3)")
        .replace("every: 16", "every: 4")
        .replace("frame, -16)", "frame, -4)");
    let pipeline = tmp.path().join("occupancy.ron");
    std::fs::write(&pipeline, windowed).unwrap();
    let run = |out: &str, extra: &[&str]| {
        let root = format!("dataset.root={}", data.display());
        let mut args = vec!["run", pipeline.to_str().unwrap(), "--set", root.as_str(), "--progress", "off"];
        args.extend(["--set", "conditions.frames=4", "--set", "hexplane.frames=4", "--set", "sheet.frames=4"]);
        args.extend(["--set", "exact.samples=1"]);
        let cache = tmp.path().join("cache");
        let out = tmp.path().join(out);
        args.extend(["--cache", cache.to_str().unwrap(), "--out", out.to_str().unwrap()]);
        args.extend(extra);
        let o = dist4d(&args);
        let t = text(&o);
        assert!(o.status.success(), "{t}");
        t
    };
    let without = run("without", &[]);
    let line = without.lines().find(|l| l.starts_with("generate ")).unwrap().to_string();
    assert!(line.split_whitespace().nth(7) == Some("1"), "one window with a previous one, nothing to make: {line}");
    let worker = format!(
        "generate.worker=Some((program: {:?}, args: [{:?}]))",
        python.display().to_string(),
        repo().join("workers/hexplane_persist.py").display().to_string()
    );
    let with = run("with", &["--set", &worker]);
    let line = with.lines().find(|l| l.starts_with("generate ")).unwrap().to_string();
    assert!(line.split_whitespace().nth(3) == Some("1"), "{with}");
    let dc = tmp.path().join("with/dynamiccity/rollout");
    let check = "import sys, numpy as np
g, p = np.load(sys.argv[1]), np.load(sys.argv[2])
assert sorted(g.files) == ['hex_txyz', 'mask', 'rollout'], g.files
assert (g['rollout'] == p['rollout']).all() and (g['mask'] == p['mask']).all(), 'persistence: the previous window'
assert list(g['hex_txyz']) == [4, 200, 200, 16], g['hex_txyz']
print('ok')";
    let o = std::process::Command::new(&python)
        .args([
            "-c",
            check,
            dc.join("generated/Train/synth-0000/000004.npz").to_str().unwrap(),
            dc.join("baseline/Train/synth-0000/000000.npz").to_str().unwrap(),
        ])
        .output()
        .unwrap();
    assert!(o.status.success() && String::from_utf8_lossy(&o.stdout).contains("ok"), "{}", text(&o));
}

/// A scene shorter than the 16-frame window (the shared DGP scene has 3) gets no window sheet,
/// HexPlane or DiT conditions: the run says so once per stage, with the reason.
#[test]
fn a_scene_shorter_than_the_window_says_why_its_window_stages_made_nothing() {
    let Some(dgp) = shared_dgp() else { return };
    let tmp = tempfile::tempdir().unwrap();
    let file = tmp.path().join("occupancy.ron");
    std::fs::write(&file, with_dataset("occupancy", &format!("Dgp(root: {:?})", dgp.display().to_string()))).unwrap();
    let out = tmp.path().join("out");
    let o = dist4d(&["run", file.to_str().unwrap(), "--progress", "off", "--out", out.to_str().unwrap()]);
    let t = text(&o);
    assert!(o.status.success(), "{t}");
    let why =
        "nothing made: the window of 16 frames runs past the scene's end (3 frame(s) from here) (e.g. scene_02/000)";
    for stage in ["sheet (OccupancySheet)", "hexplane (HexPlaneBaseline)", "conditions (DitConditions)"] {
        let line = format!("n/a: {stage}: 1 of 1, {why}");
        assert_eq!(t.matches(&line).count(), 1, "{line}\n{t}");
    }
    assert!(t.contains("n/a: sheet_png (EncodeImage): 1 of 1, nothing made: nothing came from `sheet`"), "{t}");
}

/// Issue 42: occupancy semantics say where they come from. On a synthetic scene with its lidarseg
/// turned off, without a segmenter `run` warns once and every frame's meta.json says
/// `geometry`; with the oracle segmenter worker (the exact semantic images: it tests the
/// plumbing) the points take their pixels' classes, no warning, `camera` in every meta.json, and
/// the classes come back (sidewalk, manmade, vegetation: geometry cannot tell them apart).
#[test]
fn occupancy_semantics_from_a_segmenter_worker_or_geometry_only_with_a_warning() {
    let Some(python) = peers_python() else { return };
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    let o =
        dist4d(&["synth", "--out", data.to_str().unwrap(), "--keyframes", "2", "--width", "320", "--height", "180"]);
    assert!(o.status.success(), "{}", text(&o));
    let root = format!("dataset.root={}", data.display());
    let cache = tmp.path().join("cache");
    let run = |out: &str, extra: &[&str]| {
        let o = std::process::Command::new(bin())
            .current_dir(repo())
            .args(["run", "pipelines/occupancy.ron", "--set", &root, "--set", "scene.lidarseg=false"])
            .args(["--set", "exact.samples=1", "--progress", "off", "--cache", cache.to_str().unwrap()])
            .args(["--out", tmp.path().join(out).to_str().unwrap()])
            .args(extra)
            .output()
            .unwrap();
        let t = text(&o);
        assert!(o.status.success(), "{t}");
        t
    };
    let metas = |out: &str| -> Vec<serde_json::Value> {
        let dir = tmp.path().join(out).join("gts/synth-0000");
        let frames: Vec<_> = std::fs::read_dir(&dir).unwrap().map(|e| e.unwrap().path()).collect();
        assert_eq!(frames.len(), 2);
        frames.iter().map(|f| serde_json::from_slice(&std::fs::read(f.join("meta.json")).unwrap()).unwrap()).collect()
    };
    let classes = |out: &str| -> std::collections::BTreeSet<u8> {
        let dir = tmp.path().join(out).join("gts/synth-0000");
        let frame = std::fs::read_dir(&dir).unwrap().next().unwrap().unwrap().path();
        let code = "import sys, numpy as np; print(*sorted(set(np.load(sys.argv[1])['semantics'].ravel().tolist())))";
        let o = std::process::Command::new(&python).args(["-c", code]).arg(frame.join("labels.npz")).output().unwrap();
        assert!(o.status.success(), "{}", text(&o));
        String::from_utf8_lossy(&o.stdout).split_whitespace().map(|c| c.parse().unwrap()).collect()
    };
    let t = run("geometry", &[]);
    let warnings: Vec<&str> = t.lines().filter(|l| l.starts_with("warning: ")).collect();
    assert_eq!(warnings.len(), 1, "{t}");
    assert!(
        warnings[0].contains("stage `scene` (AggregateScene): dataset NuScenes at ")
            && warnings[0].contains("geometry only")
    );
    assert!(metas("geometry").iter().all(|m| m["semantics_source"] == "geometry" && m["geometry_only"] == true));
    let geometry = classes("geometry");
    assert!(!geometry.contains(&15) && !geometry.contains(&13) && !geometry.contains(&14), "{geometry:?}");
    assert!(geometry.contains(&0), "unlabelled structure is `others`: {geometry:?}");

    let worker = format!(
        "labels.worker=Some((program: {:?}, args: [{:?}, \"--root\", {:?}]))",
        python.display().to_string(),
        repo().join("workers/synth_semantic_oracle.py").display().to_string(),
        data.display().to_string()
    );
    let t = run("camera", &["--set", &worker]);
    assert!(!t.contains("warning: "), "{t}");
    assert!(metas("camera").iter().all(|m| m["semantics_source"] == "camera" && m["geometry_only"] == false));
    let camera = classes("camera");
    for class in [11, 13, 15, 16] {
        assert!(camera.contains(&class), "class {class} from the cameras: {camera:?}");
    }
    let summary: serde_json::Value =
        serde_json::from_slice(&std::fs::read(tmp.path().join("camera/synth-0000/aggregate.json")).unwrap()).unwrap();
    assert_eq!(summary["sweeps_with_camera_labels"], 2, "{summary}");
    assert!(summary["static_labels_camera"].as_u64().unwrap() > summary["static_labels_transferred"].as_u64().unwrap());
}

#[test]
fn occ3d_waymo_files_only_for_waymo_scenes_unless_forced_and_numpy_reads_them_as_occ3ds_waymo_loader_does() {
    use dist4d_datasets::files::npz_member;
    use dist4d_stages::occupancy::encode_occ3d_waymo::{of_occ3d, WAYMO_FREE};
    use dist4d_types::formats::read_npy_u8;
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    let o =
        dist4d(&["synth", "--out", data.to_str().unwrap(), "--keyframes", "2", "--width", "320", "--height", "180"]);
    assert!(o.status.success(), "{}", text(&o));
    let (cache, out) = (tmp.path().join("cache"), tmp.path().join("out"));
    let run = |extra: &[&str]| {
        let mut args = vec!["run", "pipelines/occupancy.ron", "--progress", "off"];
        let root = format!("dataset.root={}", data.display());
        args.extend(["--set", &root, "--cache", cache.to_str().unwrap(), "--out", out.to_str().unwrap()]);
        args.extend(extra);
        let o = std::process::Command::new(bin()).current_dir(repo()).args(&args).output().unwrap();
        let t = text(&o);
        assert!(o.status.success(), "{t}");
        t
    };
    // A nuScenes-format scene: nothing in Occ3D-Waymo's layout, and the run says why once.
    let first = run(&[]);
    assert_eq!(column(&first, "occ3d_waymo", 3), 0, "{first}");
    let said: Vec<&str> = first.lines().filter(|l| l.starts_with("n/a: occ3d_waymo")).collect();
    assert_eq!(said.len(), 1, "{first}");
    assert!(said[0].contains("`nuscenes`, not Waymo Perception") && said[0].contains("when: Always"), "{}", said[0]);
    assert!(!out.join("occ3d-waymo").exists());
    // Forced: one file per frame, named by frame index; Occ3D-nuScenes' files are not remade.
    let forced = run(&["--set", "occ3d_waymo.when=Always"]);
    assert_eq!((column(&forced, "occ3d_waymo", 3), column(&forced, "occ3d", 3)), (2, 0), "{forced}");
    let dir = out.join("occ3d-waymo/synth-0000");
    let mut names: Vec<String> =
        std::fs::read_dir(&dir).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect();
    names.sort();
    assert_eq!(names, ["000_04.npz", "001_04.npz"]);
    // Read back with dist4d's npz reader: the Occ3D-nuScenes frame two layers up, classes mapped.
    let samples: serde_json::Value =
        serde_json::from_slice(&std::fs::read(data.join("v1.0-mini/sample.json")).unwrap()).unwrap();
    let first_token = samples.as_array().unwrap().iter().find(|s| s["prev"] == "").unwrap()["token"].clone();
    let nuscenes =
        std::fs::read(out.join(format!("gts/synth-0000/{}/labels.npz", first_token.as_str().unwrap()))).unwrap();
    let waymo = std::fs::read(dir.join("000_04.npz")).unwrap();
    let array = |npz: &[u8], key: &str| read_npy_u8(&npz_member(npz, key).unwrap()).unwrap();
    let (shape, semantics) = array(&nuscenes, "semantics");
    let (wshape, labels) = array(&waymo, "voxel_label");
    assert_eq!((shape.as_slice(), wshape.as_slice()), ([200, 200, 16].as_slice(), [200, 200, 16].as_slice()));
    for i in (0..labels.len()).step_by(7) {
        let k = i % 16;
        let want = if k < 2 { WAYMO_FREE } else { of_occ3d(semantics[i - 2]) };
        assert_eq!(labels[i], want, "voxel {i}");
    }
    numpy_reads_occ3d_waymo(&[dir.join("000_04.npz"), dir.join("001_04.npz")]);

    // `from_grid` left behind a changed occupancy grid: run says so.
    let moved = run(&["--set", "occ3d_waymo.when=Always", "--set", "occupancy.grid=(lift: 0.4)"]);
    assert!(moved.contains("warning: stage `occ3d_waymo` (EncodeOcc3dWaymo): `from_grid`"), "{moved}");
}

/// What Occ3D's `LoadOccGTFromFileWaymo` (its `code` branch; CVT-Occ's copy) does with `files`:
/// np.load, the four keys, masks as bool, free 23 -> 15; and `ego2global` as Occ3D's viewer
/// reads it. Skipped (said) without a venv that has numpy.
fn numpy_reads_occ3d_waymo(files: &[std::path::PathBuf]) {
    let Some(python) = py123d_python().or_else(peers_python) else {
        eprintln!("SKIPPED: no venv with numpy for the Occ3D-Waymo loader check");
        return;
    };
    let script = r#"
import sys, numpy as np
for path in sys.argv[1:]:
    occ = np.load(path)
    assert sorted(occ.files) == sorted(['voxel_label', 'origin_voxel_state', 'final_voxel_state', 'infov', 'ego2global']), occ.files
    semantics = occ['voxel_label']
    mask_infov = occ['infov'].astype(bool)
    mask_lidar = occ['origin_voxel_state'].astype(bool)
    mask_camera = occ['final_voxel_state'].astype(bool)
    for k in ['voxel_label', 'origin_voxel_state', 'final_voxel_state', 'infov']:
        assert occ[k].dtype == np.uint8 and occ[k].shape == (200, 200, 16), (k, occ[k].dtype, occ[k].shape)
    assert occ['ego2global'].dtype == np.float64 and occ['ego2global'].shape == (4, 4)
    assert np.allclose(occ['ego2global'][3], [0, 0, 0, 1])
    assert set(np.unique(semantics)) <= set(range(15)) | {23}, np.unique(semantics)
    assert {1, 13, 23} <= set(np.unique(semantics)), ('vehicles, road, free', np.unique(semantics))
    assert not (mask_camera & ~mask_lidar).any(), 'final_voxel_state within origin_voxel_state'
    assert 0.5 < mask_infov.mean() <= 1.0 and mask_camera.sum() > 1000, (mask_infov.mean(), mask_camera.sum())
    # The vehicle frame's ground (z = 0) is in layer 2 of [-1, 5.4] m; the street runs along x
    # through the ego (y index 100); the two layers below the ground are free and unobserved.
    road = np.nonzero(semantics == 13)
    assert len(road[2]) > 1000 and (road[2] == 2).all(), np.bincount(road[2])
    assert (semantics[:, 100, 2] == 13).sum() > 100, semantics[:, 100, 2]
    assert (semantics[:, :, :2] == 23).all() and not mask_lidar[:, :, :2].any()
    semantics[semantics == 23] = 15
    assert semantics.max() <= 15
print('ok')
"#;
    let o = std::process::Command::new(&python).arg("-c").arg(script).args(files).output().unwrap();
    assert!(o.status.success() && String::from_utf8_lossy(&o.stdout).contains("ok"), "{}", text(&o));
}
