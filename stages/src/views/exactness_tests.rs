//! Reprojection against the synthetic world's renderer: ground-truth RGB-D of one camera drawn
//! into the same camera moved sideways must agree with the renderer's exact view of that pose.

use super::splat::{reproject, PinholeView, RgbdView, SplatParams};
use dist4d_synth::{PinholeCamera, SynthConfig, CAMERA_RIG};
use dist4d_types::geometry::Se3;
use glam::DVec3;

/// What one shifted view scored.
struct Score {
    valid_share: f64,
    /// Of the valid pixels, the share with depth within 1% of the truth.
    within_1pct: f64,
    /// The same over the valid pixels whose true surface the source saw (see [`seen_by_source`]).
    within_1pct_seen: f64,
    /// The share of valid pixels whose true surface the source did not see.
    unseen: f64,
    psnr: f64,
}

/// Whether the surface the target's pixel `i` truly shows was visible in the source: its point,
/// moved into the source camera, lands on a source pixel whose depth is that point's (1%). A
/// surface the source never saw (hidden behind something, or outside its field of view) cannot
/// come out of a reprojection: where it lies in front of surfaces the source did see, the
/// reprojection shows those, and no method without a generator does better.
fn seen_by_source(i: usize, truth_depth: f32, tgt: &PinholeView, src: &PinholeView, src_depth: &[f32]) -> bool {
    let (x, y) = ((i % tgt.width as usize) as f64 + 0.5, (i / tgt.width as usize) as f64 + 0.5);
    let k = tgt.k;
    let z = truth_depth as f64;
    let yc = (y - k[1][2]) / k[1][1];
    let xc = (x - k[0][2] - k[0][1] * yc) / k[0][0];
    let world = tgt.world_from_cam.apply(DVec3::new(xc * z, yc * z, z));
    let c = src.world_from_cam.inverse().apply(world);
    if c.z <= 0.0 {
        return false;
    }
    let (u, v, zs) = src.project(c);
    if !(u >= 0.0 && v >= 0.0 && u < src.width as f64 && v < src.height as f64) {
        return false;
    }
    let d = src_depth[v as usize * src.width as usize + u as usize] as f64;
    ((d - zs) / zs).abs() <= 0.01
}

fn score(camera: usize, shift: f64, t: f64) -> Score {
    let config = SynthConfig { width: 800, height: 450, ..SynthConfig::default() };
    let world = config.world(0);
    let snapshot = dist4d_synth::Snapshot::new(&world, t);
    let (p, yaw) = world.ego_pose(t);
    let ego = Se3::from_yaw(yaw, p);
    // Sideways along the ego's left (+y), as SCC's novel trajectories move.
    let shifted = Se3::from_yaw(yaw, p + ego.matrix() * DVec3::new(0.0, shift, 0.0));
    let rig = &CAMERA_RIG[camera];
    let cam = |ego_to_world: &Se3| PinholeCamera {
        k: rig.intrinsics(config.width, config.height),
        width: config.width,
        height: config.height,
        camera_to_world: ego_to_world.then_from(&rig.sensor_to_ego()),
    };
    let (src_cam, tgt_cam) = (cam(&ego), cam(&shifted));
    let src = snapshot.render(&src_cam);
    let truth = snapshot.render(&tgt_cam);
    let view =
        |c: &PinholeCamera| PinholeView { k: c.k, width: c.width, height: c.height, world_from_cam: c.camera_to_world };
    let (sv, tv) = (view(&src_cam), view(&tgt_cam));
    let out =
        reproject(&[RgbdView { rgb: &src.rgb, depth: &src.depth, view: &sv }], &tv, &SplatParams::default()).unwrap();
    let (mut valid, mut good, mut seen, mut good_seen, mut se, mut n_se) =
        (0usize, 0usize, 0usize, 0usize, 0f64, 0usize);
    for i in 0..out.depth.len() {
        if out.valid[i] == 0 {
            continue;
        }
        valid += 1;
        let z = truth.depth[i] as f64;
        let ok = z.is_finite() && ((out.depth[i] as f64 - z) / z).abs() <= 0.01;
        good += ok as usize;
        if z.is_finite() && seen_by_source(i, truth.depth[i], &tv, &sv, &src.depth) {
            seen += 1;
            good_seen += ok as usize;
        }
        for k in 0..3 {
            let e = out.rgb[3 * i + k] as f64 - truth.rgb[3 * i + k] as f64;
            se += e * e;
            n_se += 1;
        }
    }
    if let Some(dir) = std::env::var_os("DIST4D_REPROJ_DEBUG") {
        // To look at: truth | ours, with depths off by more than 1% in red (too near) or magenta
        // (too far), as DIR/reproj_<camera>_<shift>.png.
        let (w, h) = (out.width as usize, out.height as usize);
        let mut img = vec![0u8; 2 * w * h * 3];
        for y in 0..h {
            for x in 0..w {
                let i = y * w + x;
                img[3 * (y * 2 * w + x)..][..3].copy_from_slice(&truth.rgb[3 * i..3 * i + 3]);
                let o = &mut img[3 * (y * 2 * w + w + x)..][..3];
                if out.valid[i] == 1 {
                    o.copy_from_slice(&out.rgb[3 * i..3 * i + 3]);
                    let z = truth.depth[i];
                    if !z.is_finite() || ((out.depth[i] - z) / z).abs() > 0.01 {
                        o.copy_from_slice(if out.depth[i] < z { &[255, 0, 0] } else { &[255, 0, 255] });
                    }
                }
            }
        }
        let path = std::path::Path::new(&dir).join(format!("reproj_{camera}_{shift}.png"));
        image::save_buffer(path, &img, 2 * w as u32, h as u32, image::ColorType::Rgb8).unwrap();
    }
    let n = out.depth.len() as f64;
    Score {
        valid_share: valid as f64 / n,
        within_1pct: good as f64 / valid.max(1) as f64,
        within_1pct_seen: good_seen as f64 / seen.max(1) as f64,
        unseen: 1.0 - seen as f64 / valid.max(1) as f64,
        psnr: 10.0 * (255.0f64 * 255.0 / (se / n_se.max(1) as f64)).log10(),
    }
}

#[test]
fn ground_truth_reprojected_sideways_matches_the_renderers_view() {
    // CAM_FRONT, CAM_FRONT_LEFT and CAM_BACK, 8 s into the default world, moved 1, 2 and 4 m.
    for camera in [0usize, 5, 3] {
        for shift in [1.0, -2.0, 4.0] {
            let s = score(camera, shift, 8.0);
            eprintln!(
                "{} shift {shift:+} m: valid {:.3}, depth within 1% {:.4} of valid pixels, {:.4} of those \
                 the source saw ({:.4} it did not), PSNR {:.2} dB",
                CAMERA_RIG[camera].channel, s.valid_share, s.within_1pct, s.within_1pct_seen, s.unseen, s.psnr
            );
            assert!(
                s.within_1pct_seen >= 0.99,
                "{} {shift}: {:.4} of the valid pixels the source saw are within 1%",
                CAMERA_RIG[camera].channel,
                s.within_1pct_seen
            );
            assert!(s.valid_share > 0.3, "{} {shift}: only {:.3} valid", CAMERA_RIG[camera].channel, s.valid_share);
        }
    }
}

/// The peer venv's Python (`DIST4D_PEERS_PYTHON`, else `.venv-peers/` at the workspace root).
fn peers_python() -> Option<std::path::PathBuf> {
    let p = std::env::var_os("DIST4D_PEERS_PYTHON")
        .map(std::path::PathBuf::from)
        .unwrap_or_else(|| std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../.venv-peers/bin/python"));
    p.exists().then_some(p)
}

/// An independent implementation in numpy: a few hundred scattered points of a source camera,
/// moved into a target at another pose and focal length, nearest point per pixel. With the soft
/// z-buffer's tolerance at 0 and points too sparse to have neighbours, each point covers exactly
/// the target pixel it falls in, so the two must agree pixel for pixel.
#[test]
fn scattered_points_land_where_numpy_puts_them() {
    let Some(python) = peers_python() else {
        eprintln!("SKIPPED: no peer venv (make it with ../shared/bench/peers/setup.sh .venv-peers)");
        return;
    };
    let (w, h) = (60u32, 40u32);
    let src = PinholeView {
        k: [[50.0, 0.0, 31.0], [0.0, 48.0, 19.5], [0.0, 0.0, 1.0]],
        width: w,
        height: h,
        world_from_cam: Se3::from_wxyz_t([0.9, 0.1, -0.2, 0.05], [1.0, -2.0, 0.5]),
    };
    let tgt = PinholeView {
        k: [[30.0, 0.0, 24.0], [0.0, 31.0, 17.0], [0.0, 0.0, 1.0]],
        width: 50,
        height: 36,
        world_from_cam: Se3::from_wxyz_t([0.88, 0.12, -0.25, 0.1], [1.6, -1.5, 0.2]),
    };
    // Every third pixel of every third row: ~260 points, none a grid neighbour of another.
    let mut rng = dist4d_types::rng::Rng::new(7);
    let mut depth = vec![0f32; (w * h) as usize];
    let mut rgb = vec![0u8; 3 * (w * h) as usize];
    for y in (0..h as usize).step_by(3) {
        for x in (0..w as usize).step_by(3) {
            let i = y * w as usize + x;
            depth[i] = rng.range(3.0, 33.0) as f32;
            for c in 0..3 {
                rgb[3 * i + c] = rng.below(256) as u8;
            }
        }
    }
    let params = SplatParams { surface_tolerance: 0.0, ..SplatParams::default() };
    let out = reproject(&[RgbdView { rgb: &rgb, depth: &depth, view: &src }], &tgt, &params).unwrap();

    let dir = tempfile::tempdir().unwrap();
    let f32s = |v: &[f32]| v.iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<u8>>();
    let mat = |s: &Se3| {
        let m = s.matrix();
        let t = s.translation;
        [
            m.x_axis.x, m.y_axis.x, m.z_axis.x, t.x, m.x_axis.y, m.y_axis.y, m.z_axis.y, t.y, m.x_axis.z, m.y_axis.z,
            m.z_axis.z, t.z,
        ]
    };
    std::fs::write(dir.path().join("depth.f32"), f32s(&depth)).unwrap();
    let cams: Vec<f64> = src
        .k
        .as_flattened()
        .iter()
        .chain(tgt.k.as_flattened())
        .copied()
        .chain(mat(&src.world_from_cam))
        .chain(mat(&tgt.world_from_cam))
        .collect();
    std::fs::write(dir.path().join("cams.f64"), cams.iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<u8>>())
        .unwrap();
    let script = r#"
import numpy as np, sys
d = sys.argv[1]
depth = np.fromfile(d + '/depth.f32', dtype='<f4').reshape(40, 60)
c = np.fromfile(d + '/cams.f64', dtype='<f8')
Ks, Kt = c[0:9].reshape(3, 3), c[9:18].reshape(3, 3)
Ms = np.vstack([c[18:30].reshape(3, 4), [0, 0, 0, 1]])
Mt = np.vstack([c[30:42].reshape(3, 4), [0, 0, 0, 1]])
ys, xs = np.nonzero(depth > 0)
z = depth[ys, xs].astype(np.float64)
pix = np.stack([xs + 0.5, ys + 0.5, np.ones_like(z)])
cam = np.linalg.inv(Ks) @ pix * z
world = Ms @ np.vstack([cam, np.ones_like(z)])
t = (np.linalg.inv(Mt) @ world)[:3]
uv = Kt @ t
u, v, zt = uv[0] / uv[2], uv[1] / uv[2], t[2]
best = np.zeros((36, 50))
keep = (zt > 0.1) & (u >= 0) & (v >= 0) & (u < 50) & (v < 36)
for ui, vi, zi in zip(np.floor(u[keep]).astype(int), np.floor(v[keep]).astype(int), zt[keep]):
    if best[vi, ui] == 0 or zi < best[vi, ui]:
        best[vi, ui] = zi
best.astype('<f4').tofile(d + '/best.f32')
print(int(keep.sum()))
"#;
    let run = std::process::Command::new(&python).arg("-c").arg(script).arg(dir.path()).output().unwrap();
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
    let landed: usize = String::from_utf8_lossy(&run.stdout).trim().parse().unwrap();
    let best: Vec<f32> = std::fs::read(dir.path().join("best.f32"))
        .unwrap()
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes(c.try_into().unwrap()))
        .collect();
    assert!(landed > 100, "only {landed} of the points land in the target: a poor test");
    let mut compared = 0;
    for (i, (&ours, &theirs)) in out.depth.iter().zip(&best).enumerate() {
        assert_eq!(out.valid[i] == 1, theirs > 0.0, "pixel {i}: ours {ours}, numpy {theirs}");
        if theirs > 0.0 {
            assert!((ours - theirs).abs() <= 1e-4 * theirs, "pixel {i}: ours {ours}, numpy {theirs}");
            compared += 1;
        }
    }
    eprintln!("{landed} points landed, {compared} pixels agree with numpy");
}
