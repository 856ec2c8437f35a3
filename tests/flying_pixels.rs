//! End-to-end: the bullet-time clouds of pipelines/temporal.ron on synthetic data, scored by its
//! `EvalCloud` stage through `dist4d eval`, with the rules that keep flying pixels out (the
//! lifting rule, stages/src/lift.rs; `GenerateFuture`'s `trusted` mask, support in metres; the
//! cloud's lone points, stages/src/lone_points.rs) and without them: they take the lone points
//! near the ego out and the share of points on the world's exact surface up.

mod common;
use common::*;
use std::path::Path;

fn eval(data: &Path, dir: &Path, out: &str, extra: &[&str]) -> String {
    let root = format!("dataset.root={}", data.display());
    let (cache, out) = (dir.join("cache"), dir.join(out));
    let mut args = vec!["eval", "pipelines/temporal.ron", "--set", &root, "--progress", "off"];
    args.extend(["--cache", cache.to_str().unwrap(), "--out", out.to_str().unwrap()]);
    args.extend(extra);
    let o = std::process::Command::new(bin()).current_dir(repo()).args(&args).output().unwrap();
    let t = text(&o);
    assert!(o.status.success(), "{t}");
    t
}

/// The `mean` row of the `cloud_score` table: points, beyond 50 m, lone within 30 m (summed over
/// the clouds), on the exact surface.
fn cloud_scores(report: &str) -> (f64, f64, f64, f64) {
    let table = &report[report.find("\ncloud_score\n").unwrap_or_else(|| panic!("no cloud table in\n{report}"))..];
    let row = table.lines().find(|l| l.starts_with("| mean |")).unwrap();
    let cells: Vec<f64> = row.split('|').filter_map(|c| c.trim().parse().ok()).collect();
    (cells[0], cells[1], cells[2], cells[3])
}

#[test]
fn the_lifting_rule_takes_the_flying_pixels_out_of_the_bullet_time_clouds() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    let o = dist4d(&[
        "synth",
        "--out",
        data.to_str().unwrap(),
        "--keyframes",
        "4",
        "--width",
        "320",
        "--height",
        "180",
        "--seed",
        "3",
    ]);
    assert!(o.status.success(), "{}", text(&o));
    let with = eval(&data, tmp.path(), "with", &[]);
    let off = [
        "--set",
        "future.lift=(max_jump: 0)",
        "--set",
        "cloud.lift=(max_jump: 0)",
        "--set",
        "future.trusted_support_m=0",
        "--set",
        "cloud.lone=(min_neighbours: 0)",
    ];
    let without = eval(&data, tmp.path(), "without", &off);
    let (points, beyond, lone, on) = cloud_scores(&with);
    let (points_off, _, lone_off, on_off) = cloud_scores(&without);
    assert!(points > 10_000.0 && points < points_off, "{points} points with the rule, {points_off} without");
    assert!(beyond < 0.1, "share beyond 50 m: {beyond}\n{with}");
    assert!(lone == 0.0 && lone_off > 0.0, "lone points within 30 m: {lone} with the rules, {lone_off} without");
    assert!(on > on_off + 0.05, "share on the exact surface: {on} with the rules, {on_off} without");
    // Every bullet-time cloud has its row.
    let table = &with[with.find("\ncloud_score\n").unwrap()..];
    let rows = table.lines().take_while(|l| !l.starts_with("| mean |")).filter(|l| l.contains("/CAM_FRONT/t+")).count();
    assert_eq!(rows, 6, "{with}");
}
