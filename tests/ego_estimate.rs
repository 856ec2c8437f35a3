//! End-to-end: the ego-mask estimate (`EstimateEgo`, wired into `EgoMask` as docs/stages.md shows)
//! through the CLI on the shared real DGP scene, with the built-in rig off so that the estimate is
//! what masks the body, scored against the hand labels (tests/fixtures/real_labels).

mod common;
use common::*;

/// pipelines/curation.ron reading DGP, with the estimate wired into `ego` and its preview exported.
fn curation_with_estimate() -> String {
    let text = with_dataset("curation", "Dgp(root: \"\")");
    let ego = r#""ego": EgoMask(inputs: {"info": "dataset.image_info", "image": "dataset.image"}),"#;
    assert!(text.contains(ego), "curation.ron wires `ego` as this test expects");
    let estimate = r#""ego_estimate": EstimateEgo(
            inputs: {
                "images": Window("dataset.image", frame, -2, 2),
                "calibs": Window("dataset.camera_calib", frame, -2, 2),
                "poses": Window("dataset.camera_pose", frame, -2, 2),
                "depth": "lidar_multi.depth",
            },
        ),
        "ego_estimate_png": EncodeImage(inputs: {"image": "ego_estimate.preview"}),
        "ego": EgoMask(inputs: {"info": "dataset.image_info", "image": "dataset.image", "estimate": "ego_estimate.mask"}),"#;
    let export = r#""ego_png.png": "{scene}/{camera}/{frame}_ego.png","#;
    text.replace(ego, estimate).replace(
        export,
        &format!("{export}\n        \"ego_estimate_png.png\": \"{{scene}}/{{camera}}/{{frame}}_ego_estimate.png\","),
    )
}

#[test]
fn the_estimate_masks_most_of_the_dgp_body_and_little_else() {
    let Some(dgp) = shared_dgp() else { return };
    let tmp = tempfile::tempdir().unwrap();
    let pipeline = tmp.path().join("curation.ron");
    std::fs::write(&pipeline, curation_with_estimate()).unwrap();
    let (cache, out) = (tmp.path().join("cache"), tmp.path().join("out"));
    let root = format!("dataset.root={}", dgp.display());
    let o = dist4d(&[
        "run",
        pipeline.to_str().unwrap(),
        "--set",
        &root,
        "--set",
        "ego.rig=\"none\"",
        "--cache",
        cache.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--progress",
        "off",
    ]);
    let report = text(&o);
    assert!(o.status.success(), "{report}");
    assert!(out.join("scene_02/CAMERA_05/001_ego_estimate.png").is_file(), "the preview is exported");

    use dist4d_stages::eval::labels::{score_export, LabelScores};
    let scored = score_export(&out, &repo().join("tests/fixtures/real_labels/dgp-scene02"), 100.0).unwrap();
    assert_eq!(scored.len(), 18, "{scored:?}");
    let mut total = LabelScores::default();
    for s in &scored {
        total.add(&s.scores);
        // CAMERA_01 sees none of the car: nothing of it may be masked.
        if s.depth.contains("CAMERA_01") {
            assert_eq!(s.scores.other_masked.part, 0, "{}: {}", s.depth, s.scores.other_masked);
        }
    }
    // Issue 42's targets are >= 95% of the body and <= 0.5% of the rest per image; the estimate
    // reaches 66% and 1.24% in all (docs/BENCHMARKS.md, "Ego mask estimate"), so it is not the
    // default. These floors keep what it reaches.
    let (ego, others) = (total.ego_masked.value().unwrap(), total.other_masked.value().unwrap());
    assert!(ego >= 0.60, "ego masked {}", total.ego_masked);
    assert!(others <= 0.02, "others masked {}", total.other_masked);
}
