//! `dist4d eval`'s tables: the scores every `EvalDepth` stage exported, read back from the run's
//! output folder and averaged per camera (the last dimension of each item) and over cameras.
//!
//! Per reference, up to three Markdown tables, each titled on a line of its own (scripts find a
//! table by its title and read its `mean` row by the header's column names):
//! `<reference> (raw)` and `<reference> (median-scaled)` (the Eigen et al. metrics and the
//! bad-pixel rates), and for a dense reference `<reference> (sky, boundaries)`, whose sky shares
//! pool a camera's pixels over its images (as a dataset's segmentation IoU is) while every other
//! metric is a mean of per-image values (as KITTI's and iBims-1's are). A metric an image
//! does not have (a share of no pixel, boundaries of a reference without edges) is left out of
//! its camera's mean; a camera without any value shows `-` and is left out of the mean row.

use super::depth::{ImageScores, Params, Scores};
use super::sky::SkyMetrics;
use anyhow::{ensure, Context, Result};
use dist4d_graph::Pipeline;
use std::collections::BTreeMap;
use std::path::Path;

/// The stage kind whose exported scores are tabulated.
const KIND: &str = "EvalDepth";

/// The `EvalDepth` stages of `pipeline` with their params; an error unless there is one and
/// each exports its scores (the tables are read from the exported files), so that a run that
/// could not be reported on is refused before it starts.
pub fn scored_stages(pipeline: &Pipeline) -> Result<Vec<(&str, Params)>> {
    // Every scoring stage, and every one that is not exported, named at once.
    let mut scoring = 0;
    let mut unexported = Vec::new();
    for (id, n) in pipeline.nodes.iter().enumerate() {
        let Some(kind) = n.stage().map(|s| s.kind.as_str()) else { continue };
        let Some((kind, template)) = SCORED.iter().find(|(k, _)| *k == kind) else { continue };
        scoring += 1;
        if !pipeline.exports.iter().any(|e| e.node == id) {
            unexported.push(format!(
                "{}: stage `{}` ({kind}) is not exported, and `dist4d eval` reads the scores from the exported \
                 files: add `\"{}.json\": \"{template}\"` to `export`",
                pipeline.path.display(),
                n.name,
                n.name
            ));
        }
    }
    ensure!(
        scoring > 0,
        "{}: the pipeline has no {} stage to report",
        pipeline.path.display(),
        SCORED.iter().map(|(k, _)| *k).collect::<Vec<_>>().join(", ")
    );
    ensure!(unexported.is_empty(), "{}", unexported.join("\n"));
    Ok(pipeline
        .nodes
        .iter()
        .filter_map(|n| {
            let s = n.stage().filter(|s| s.kind == KIND)?;
            Some((n.name.as_str(), s.params.get::<Params>().cloned().unwrap_or_default()))
        })
        .collect())
}

/// The kinds `dist4d eval` tabulates, each with the export template its scores are read from.
const SCORED: &[(&str, &str)] = &[
    (KIND, "{scene}/{camera}/{frame}_metrics.json"),
    (VIEW_KIND, "{scene}/{camera}/{frame}_{variant}_view.json"),
    (OCC_KIND, "{scene}/occupancy/{frame}_scores.json"),
    (TEMPORAL_KIND, "{scene}/{camera}/{frame}_temporal.json"),
    (CLOUD_KIND, "{scene}/bullet_time/{frame}_{variant}_{camera}_cloud.json"),
];

/// The score tables of every `EvalDepth` stage of `pipeline`, from the files its last run
/// exported into `out_dir`.
pub fn tables(pipeline: &Pipeline, out_dir: &Path) -> Result<String> {
    let index = dist4d_runtime::export::read_index(out_dir)?;
    let mut text = view_tables(pipeline, &index, out_dir)?;
    text.push_str(&cloud_tables(pipeline, &index, out_dir)?);
    text.push_str(&occupancy_tables(pipeline, &index, out_dir)?);
    text.push_str(&temporal_tables(pipeline, &index, out_dir)?);
    for (stage, p) in scored_stages(pipeline)? {
        let mut images = Vec::new();
        for entry in index.iter().filter(|e| e.stage == stage) {
            let path = out_dir.join(&entry.path);
            let bytes = std::fs::read(&path).with_context(|| format!("reading {}", path.display()))?;
            let scores: ImageScores = serde_json::from_slice(&bytes)
                .with_context(|| format!("{} is not an {KIND} score file", path.display()))?;
            let camera = entry.item.rsplit('/').next().unwrap_or_default().to_string();
            images.push((camera, scores));
        }
        ensure!(
            !images.is_empty(),
            "stage `{stage}` exported no scores to {}: export its `json` port",
            out_dir.display()
        );
        text.push_str(&format!(
            "\n# {stage}: {} images, depth range {}-{} m; rel>k: relative error above k; sky: depth >= {} m, \
             structure: < {} m; boundaries: Canny edges of log depth (steps {} / {}), distances in px capped at {}\n",
            images.len(),
            p.min_depth,
            p.max_depth,
            p.sky_threshold,
            p.structure_depth,
            p.edge_high_step,
            p.edge_low_step,
            p.edge_max_distance
        ));
        text.push_str(&tabulate(&images));
    }
    Ok(text)
}

/// A column of a table: its header, how many decimals, and its value over one camera's images.
struct Column {
    header: &'static str,
    decimals: usize,
    value: fn(&[&Scores]) -> Option<f64>,
}

/// The mean of the values the images have (`None` when none has one).
fn mean(values: impl Iterator<Item = f64>) -> Option<f64> {
    let (sum, n) = values.fold((0.0, 0usize), |(s, n), v| (s + v, n + 1));
    (n > 0).then(|| sum / n as f64)
}

/// Columns whose camera value is the mean of a per-image value.
macro_rules! columns {
    ($( $header:literal, $decimals:literal, |$s:ident| $value:expr );* $(;)?) => {
        &[$( Column {
            header: $header,
            decimals: $decimals,
            value: |images: &[&Scores]| mean(images.iter().filter_map(|$s: &&Scores| $value)),
        } ),*]
    };
}

const RAW: &[Column] = columns![
    "abs_rel", 4, |s| Some(s.raw.abs_rel);
    "sq_rel", 4, |s| Some(s.raw.sq_rel);
    "rmse", 3, |s| Some(s.raw.rmse);
    "rmse_log", 4, |s| Some(s.raw.rmse_log);
    "d<1.25", 4, |s| Some(s.raw.a1);
    "d<1.25^2", 4, |s| Some(s.raw.a2);
    "d<1.25^3", 4, |s| Some(s.raw.a3);
    "rel>10%", 4, |s| s.raw.bad_10;
    "rel>25%", 4, |s| s.raw.bad_25;
];

const SCALED: &[Column] = columns![
    "abs_rel", 4, |s| Some(s.median_scaled.abs_rel);
    "sq_rel", 4, |s| Some(s.median_scaled.sq_rel);
    "rmse", 3, |s| Some(s.median_scaled.rmse);
    "rmse_log", 4, |s| Some(s.median_scaled.rmse_log);
    "d<1.25", 4, |s| Some(s.median_scaled.a1);
    "d<1.25^2", 4, |s| Some(s.median_scaled.a2);
    "d<1.25^3", 4, |s| Some(s.median_scaled.a3);
    "rel>10%", 4, |s| s.median_scaled.bad_10;
    "rel>25%", 4, |s| s.median_scaled.bad_25;
];

/// A camera's sky scores with its images' pixels pooled ([`SkyMetrics::pooled`]).
fn pooled_sky(images: &[&Scores]) -> Option<SkyMetrics> {
    images.iter().any(|s| s.sky.is_some()).then(|| SkyMetrics::pooled(images.iter().filter_map(|s| s.sky.as_ref())))
}

/// Sky shares pooled over a camera's images, boundary errors averaged per image (iBims-1).
const DENSE: &[Column] = &[
    Column { header: "sky IoU", decimals: 4, value: |i| pooled_sky(i).and_then(|k| k.iou) },
    Column { header: "sky as structure", decimals: 4, value: |i| pooled_sky(i).and_then(|k| k.sky_as_structure) },
    Column { header: "structure as sky", decimals: 4, value: |i| pooled_sky(i).and_then(|k| k.structure_as_sky) },
    Column {
        header: "boundary acc (px)",
        decimals: 2,
        value: |i| mean(i.iter().filter_map(|s| s.boundary.map(|b| b.accuracy))),
    },
    Column {
        header: "boundary comp (px)",
        decimals: 2,
        value: |i| mean(i.iter().filter_map(|s| s.boundary.map(|b| b.completeness))),
    },
];

/// Per-image scores averaged per camera, then over cameras (SurroundDepth): for each reference,
/// tables of rows `(camera, images, mean metrics)` and a final `mean` row.
pub fn tabulate(images: &[(String, ImageScores)]) -> String {
    let mut camera_order: Vec<&str> = Vec::new();
    // reference -> camera -> that camera's images' scores
    let mut by_reference: BTreeMap<&str, BTreeMap<&str, Vec<&Scores>>> = BTreeMap::new();
    for (camera, s) in images {
        if !camera_order.contains(&camera.as_str()) {
            camera_order.push(camera);
        }
        for (reference, scores) in &s.against {
            by_reference.entry(reference).or_default().entry(camera).or_default().push(scores);
        }
    }
    let mut out = String::new();
    for (reference, cams) in &by_reference {
        let cams: Vec<(&str, &[&Scores])> =
            camera_order.iter().filter_map(|c| cams.get(c).map(|s| (*c, s.as_slice()))).collect();
        let dense = cams.iter().any(|(_, s)| s.iter().any(|s| s.sky.is_some() || s.boundary.is_some()));
        for (mode, columns, shown) in
            [("raw", RAW, true), ("median-scaled", SCALED, true), ("sky, boundaries", DENSE, dense)]
        {
            if !shown {
                continue;
            }
            out.push_str(&format!("\n{reference} ({mode})\n"));
            out.push_str(&table(&cams, columns));
        }
    }
    out
}

/// One table: a row per camera (its images' mean of each column), then the mean over cameras.
fn table(cams: &[(&str, &[&Scores])], columns: &[Column]) -> String {
    let mut out = String::from("| camera | images |");
    let mut rule = String::from("| --- | ---: |");
    for c in columns {
        out.push_str(&format!(" {} |", c.header));
        rule.push_str(" ---: |");
    }
    out.push('\n');
    out.push_str(&rule);
    out.push('\n');
    let mut per_camera: Vec<Vec<Option<f64>>> = Vec::new();
    for (camera, scores) in cams {
        let row: Vec<Option<f64>> = columns.iter().map(|c| (c.value)(scores)).collect();
        out.push_str(&format_row(camera, scores.len(), columns, &row));
        per_camera.push(row);
    }
    let overall: Vec<Option<f64>> =
        (0..columns.len()).map(|k| mean(per_camera.iter().filter_map(|row| row[k]))).collect();
    let images = cams.iter().map(|(_, s)| s.len()).sum();
    out.push_str(&format_row("mean", images, columns, &overall));
    out
}

fn format_row(name: &str, images: usize, columns: &[Column], values: &[Option<f64>]) -> String {
    let mut row = format!("| {name} | {images} |");
    for (c, v) in columns.iter().zip(values) {
        match v {
            Some(v) => row.push_str(&format!(" {v:.*} |", c.decimals)),
            None => row.push_str(" - |"),
        }
    }
    row.push('\n');
    row
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::eval::boundary::BoundaryMetrics;
    use crate::eval::depth::DepthMetrics;

    fn image(reference: &str, abs_rel: f64, sky_iou: Option<f64>) -> ImageScores {
        let m = DepthMetrics { abs_rel, a1: 1.0, bad_10: Some(abs_rel), pixels: 10, ..Default::default() };
        // 100 sky pixels in the reference, 100 * iou of them predicted (and nothing else).
        let sky = sky_iou.map(|iou| {
            let found = (100.0 * iou) as u64;
            SkyMetrics { sky_pixels: 100, predicted_sky_pixels: found, both_sky_pixels: found, ..Default::default() }
        });
        let boundary = sky_iou.map(|_| BoundaryMetrics { accuracy: 4.0, completeness: 2.0, ..Default::default() });
        let mut x = ImageScores::default();
        x.against.insert(reference.into(), Scores { raw: m, median_scaled: m, sky, boundary });
        x
    }

    #[test]
    fn cameras_are_averaged_per_camera_then_together() {
        // CAM_A: 0.1, 0.3 -> 0.2; CAM_B: 0.4 -> mean of cameras 0.3 (not 0.8 / 3).
        let t = tabulate(&[
            ("CAM_A".into(), image("gt", 0.1, Some(0.5))),
            ("CAM_A".into(), image("gt", 0.3, Some(1.0))),
            ("CAM_B".into(), image("gt", 0.4, Some(0.9))),
        ]);
        assert!(t.contains("| CAM_A | 2 | 0.2000 |"), "{t}");
        assert!(t.contains("| mean | 3 | 0.3000 |"), "{t}");
        assert!(t.contains("gt (median-scaled)"));
        // rel>10% the mean of abs_rel here, rel>25% absent; sky IoU (0.75 + 0.9) / 2.
        let raw_mean = "| mean | 3 | 0.3000 | 0.0000 | 0.000 | 0.0000 | 1.0000 | 0.0000 | 0.0000 | 0.3000 | - |\n";
        assert!(t.contains(raw_mean), "{t}");
        assert!(t.contains("\ngt (sky, boundaries)\n| camera | images | sky IoU |"), "{t}");
        assert!(t.contains("| CAM_A | 2 | 0.7500 | 0.0000 | - | 4.00 | 2.00 |"), "{t}");
        assert!(t.contains("| mean | 3 | 0.8250 | 0.0000 | - | 4.00 | 2.00 |"), "{t}");
    }

    #[test]
    fn a_cameras_sky_shares_pool_its_pixels() {
        // Open sky found whole (100 px, IoU 1) and a 4-pixel sliver predicted as a wall (IoU 0):
        // pooled 100 / 104, not the per-image mean 0.5.
        let mut sliver = image("gt", 0.1, Some(0.0));
        let s = sliver.against.get_mut("gt").unwrap().sky.as_mut().unwrap();
        (s.sky_pixels, s.sky_as_structure_pixels) = (4, 4);
        let t = tabulate(&[("CAM_A".into(), image("gt", 0.1, Some(1.0))), ("CAM_A".into(), sliver)]);
        assert!(t.contains("| CAM_A | 2 | 0.9615 | 0.0385 | - |"), "{t}");
    }

    #[test]
    fn sparse_references_have_no_sky_table_and_absent_values_are_left_out() {
        let t = tabulate(&[
            ("CAM_A".into(), image("lidar", 0.2, None)),
            ("CAM_B".into(), image("gt", 0.2, Some(0.6))),
            ("CAM_C".into(), image("gt", 0.2, None)),
        ]);
        assert!(!t.contains("lidar (sky, boundaries)"), "{t}");
        // CAM_C has no sky value: '-', and the mean is CAM_B's alone.
        assert!(t.contains("| CAM_C | 1 | - | - | - | - | - |"), "{t}");
        assert!(t.contains("| mean | 2 | 0.6000 |"), "{t}");
    }
}

/// The stage kind whose exported novel-view scores are tabulated.
const VIEW_KIND: &str = "EvalNovelView";
/// ... and occupancy scores.
const OCC_KIND: &str = "EvalOccupancy";

/// The stages of `kind` in `pipeline`; an error when one does not export its scores (`template`:
/// the export to suggest).
fn stages_of<'p>(pipeline: &'p Pipeline, kind: &str, template: &str) -> Result<Vec<&'p str>> {
    let mut out = Vec::new();
    for (id, n) in pipeline.nodes.iter().enumerate() {
        if n.stage().is_some_and(|s| s.kind == kind) {
            ensure!(
                pipeline.exports.iter().any(|e| e.node == id),
                "{}: stage `{}` ({kind}) is not exported, and `dist4d eval` reads the scores from the \
                 exported files: add `\"{}.json\": \"{template}\"` to `export`",
                pipeline.path.display(),
                n.name,
                n.name
            );
            out.push(n.name.as_str());
        }
    }
    Ok(out)
}

/// The `EvalNovelView` stages of `pipeline`; an error when one does not export its scores.
fn view_stages(pipeline: &Pipeline) -> Result<Vec<&str>> {
    stages_of(pipeline, VIEW_KIND, "{scene}/{camera}/{frame}_{variant}_view.json")
}

const TEMPORAL_KIND: &str = "EvalTemporal";

fn temporal_stages(pipeline: &Pipeline) -> Result<Vec<&str>> {
    stages_of(pipeline, TEMPORAL_KIND, "{scene}/{camera}/{frame}_temporal.json")
}

/// Per `EvalTemporal` stage, a table `<stage> (temporal agreement)`: per camera and frame offset,
/// the share of static pixels seen by both frames whose depths agree, pooled over the camera's
/// images (and the ground truth's, when there is one).
fn temporal_tables(
    pipeline: &Pipeline,
    index: &[dist4d_runtime::export::IndexEntry],
    out_dir: &Path,
) -> Result<String> {
    use super::temporal::{Agreement, TemporalScores};
    let mut text = String::new();
    for stage in temporal_stages(pipeline)? {
        // (camera, offset) -> (depth, gt)
        let mut pooled: BTreeMap<(String, String), (Agreement, Agreement)> = BTreeMap::new();
        let mut images = 0;
        for entry in index.iter().filter(|e| e.stage == stage) {
            let path = out_dir.join(&entry.path);
            let bytes = std::fs::read(&path).with_context(|| format!("reading {}", path.display()))?;
            let t: TemporalScores = serde_json::from_slice(&bytes)
                .with_context(|| format!("{} is not an {TEMPORAL_KIND} score file", path.display()))?;
            let camera = entry.item.rsplit('/').next().unwrap_or_default().to_string();
            for (offset, a) in &t.depth {
                pooled.entry((camera.clone(), offset.clone())).or_default().0.add(a);
            }
            for (offset, a) in &t.gt {
                pooled.entry((camera.clone(), offset.clone())).or_default().1.add(a);
            }
            images += 1;
        }
        let p = pipeline
            .nodes
            .iter()
            .find(|n| n.name == stage)
            .and_then(|n| n.stage())
            .and_then(|s| s.params.get::<super::temporal::Params>().cloned())
            .unwrap_or_default();
        text.push_str(&format!(
            "\n# {stage}: {images} images; static pixels seen by two frames whose depths agree within {:.0}%\n\n\
             {stage} (temporal agreement)\n\n| camera | offset | depth | gt |\n| --- | --- | --- | --- |\n",
            100.0 * p.agree
        ));
        let cell = |a: &Agreement| a.share().map_or("-".to_string(), |v| format!("{:.2}%", 100.0 * v));
        let mut all: BTreeMap<String, (Agreement, Agreement)> = BTreeMap::new();
        for ((camera, offset), (d, g)) in &pooled {
            text.push_str(&format!("| {camera} | {offset} | {} | {} |\n", cell(d), cell(g)));
            let slot = all.entry(offset.clone()).or_default();
            slot.0.add(d);
            slot.1.add(g);
        }
        for (offset, (d, g)) in &all {
            text.push_str(&format!("| all | {offset} | {} | {} |\n", cell(d), cell(g)));
        }
    }
    Ok(text)
}

const CLOUD_KIND: &str = "EvalCloud";

fn cloud_stages(pipeline: &Pipeline) -> Result<Vec<&str>> {
    stages_of(pipeline, CLOUD_KIND, "{scene}/bullet_time/{frame}_{variant}_{camera}_cloud.json")
}

/// Per `EvalCloud` stage, one table: a row per cloud (scene, frame and step) and a mean row (the
/// lone points summed, the shares averaged over the clouds).
fn cloud_tables(pipeline: &Pipeline, index: &[dist4d_runtime::export::IndexEntry], out_dir: &Path) -> Result<String> {
    use super::cloud::CloudScores;
    let mut text = String::new();
    for stage in cloud_stages(pipeline)? {
        let p: super::cloud::Params = pipeline
            .nodes
            .iter()
            .find(|n| n.name == stage)
            .and_then(|n| n.stage()?.params.get::<super::cloud::Params>().cloned())
            .unwrap_or_default();
        let mut rows = Vec::new();
        for entry in index.iter().filter(|e| e.stage == stage) {
            let path = out_dir.join(&entry.path);
            let bytes = std::fs::read(&path).with_context(|| format!("reading {}", path.display()))?;
            let s: CloudScores = serde_json::from_slice(&bytes)
                .with_context(|| format!("{} is not an {CLOUD_KIND} score file", path.display()))?;
            rows.push((entry.item.clone(), s));
        }
        rows.sort_by(|a, b| a.0.cmp(&b.0));
        text.push_str(&format!(
            "\n# {stage}: {} clouds; beyond {} m: share of the points; lone < {} m: points within that range whose \
             nearest neighbour is farther than {} m; on surface: share within {} m of the exact surface (synthetic data)\n\n{stage}\n",
            rows.len(),
            p.far_range,
            p.near_range,
            p.isolation,
            p.surface_tolerance
        ));
        text.push_str("| cloud | points | beyond far | lone near | on surface |\n|---|---:|---:|---:|---:|\n");
        let share = |v: Option<f64>| v.map_or("-".to_string(), |v| format!("{:.4}", v));
        for (item, s) in &rows {
            text.push_str(&format!(
                "| {item} | {} | {:.4} | {} | {} |\n",
                s.points,
                s.beyond_far,
                s.isolated_near,
                share(s.on_surface)
            ));
        }
        if !rows.is_empty() {
            let on: Vec<f64> = rows.iter().filter_map(|(_, s)| s.on_surface).collect();
            text.push_str(&format!(
                "| mean | {} | {:.4} | {} | {} |\n",
                rows.iter().map(|(_, s)| s.points).sum::<u64>() / rows.len() as u64,
                mean(rows.iter().map(|(_, s)| s.beyond_far)).unwrap_or(0.0),
                rows.iter().map(|(_, s)| s.isolated_near).sum::<u64>(),
                share(mean(on.into_iter()))
            ));
        }
    }
    Ok(text)
}

fn occupancy_stages(pipeline: &Pipeline) -> Result<Vec<&str>> {
    stages_of(pipeline, OCC_KIND, "{scene}/occupancy/{frame}_scores.json")
}

/// Per `EvalOccupancy` stage: the confusion matrices of its frames summed, each class's IoU, the
/// mIoU and the geometry IoU (Occ3D's metric, see `crate::occupancy::eval`).
/// Where each scene's occupancy classes came from, as the exported summaries of its
/// `AggregateScene` stages say (lidarseg, transferred, or the height fallback).
fn label_sources(pipeline: &Pipeline, index: &[dist4d_runtime::export::IndexEntry], out_dir: &Path) -> String {
    let mut text = String::new();
    for n in pipeline.nodes.iter().filter(|n| n.stage().is_some_and(|s| s.kind == "AggregateScene")) {
        for entry in index.iter().filter(|e| e.stage == n.name) {
            let Ok(bytes) = std::fs::read(out_dir.join(&entry.path)) else { continue };
            let Ok(v) = serde_json::from_slice::<serde_json::Value>(&bytes) else { continue };
            if let Some(labels) = v["labels"].as_str() {
                text.push_str(&format!("\n# labels of {} ({}): {labels}\n", entry.item, n.name));
            }
        }
    }
    text
}

fn occupancy_tables(
    pipeline: &Pipeline,
    index: &[dist4d_runtime::export::IndexEntry],
    out_dir: &Path,
) -> Result<String> {
    use crate::occupancy::eval::{scores, FrameConfusion};
    let mut text = String::new();
    for stage in occupancy_stages(pipeline)? {
        let mut sum: Option<Vec<Vec<u64>>> = None;
        let mut classes = Vec::new();
        let mut frames = 0;
        for entry in index.iter().filter(|e| e.stage == stage) {
            let path = out_dir.join(&entry.path);
            let bytes = std::fs::read(&path).with_context(|| format!("reading {}", path.display()))?;
            let f: FrameConfusion = serde_json::from_slice(&bytes)
                .with_context(|| format!("{} is not an {OCC_KIND} score file", path.display()))?;
            let s = sum.get_or_insert_with(|| vec![vec![0; f.confusion.len()]; f.confusion.len()]);
            ensure!(s.len() == f.confusion.len(), "{}: a confusion matrix of another size", path.display());
            for (row, add) in s.iter_mut().zip(&f.confusion) {
                for (a, b) in row.iter_mut().zip(add) {
                    *a += b;
                }
            }
            classes = f.classes;
            frames += 1;
        }
        text.push_str(&label_sources(pipeline, index, out_dir));
        let Some(m) = sum else {
            text.push_str(&format!("\n# {stage}: no frame has a reference (not a synthetic dataset)\n"));
            continue;
        };
        let (iou, miou, geometry) = scores(&m);
        let voxels: u64 = m.iter().flatten().sum();
        text.push_str(&format!(
            "\n# {stage}: {frames} frames, {voxels} camera-visible reference voxels; IoU per class (Occ3D's \
             Metric_mIoU: a confusion matrix over the frames), mIoU over classes 0-16, geometry IoU (occupied vs free)\n\n{stage}\n"
        ));
        text.push_str("| class | IoU | reference voxels |\n|---|---:|---:|\n");
        for (c, name) in classes.iter().enumerate() {
            let reference: u64 = m[c].iter().sum();
            if let Some(v) = iou[c] {
                text.push_str(&format!("| {name} | {v:.4} | {reference} |\n"));
            }
        }
        let f = |v: Option<f64>| v.map_or("-".to_string(), |v| format!("{v:.4}"));
        text.push_str(&format!("| mIoU | {} | |\n| geometry IoU | {} | |\n", f(miou), f(geometry)));
    }
    Ok(text)
}

/// Per `EvalNovelView` stage, one table: a row per variant (the item's last label: the shift),
/// each score the mean over the images that have it (or the median, where the column says so),
/// and a `mean` row over the variants.
/// The median of `v` (the mean of the middle two for an even count); None when empty.
fn median(mut v: Vec<f64>) -> Option<f64> {
    if v.is_empty() {
        return None;
    }
    v.sort_by(|a, b| a.total_cmp(b));
    let n = v.len();
    Some(if n % 2 == 1 { v[n / 2] } else { (v[n / 2 - 1] + v[n / 2]) / 2.0 })
}

fn view_tables(pipeline: &Pipeline, index: &[dist4d_runtime::export::IndexEntry], out_dir: &Path) -> Result<String> {
    use super::novel_view::ViewScores;
    let mut text = String::new();
    for stage in view_stages(pipeline)? {
        let mut by_variant: BTreeMap<String, Vec<ViewScores>> = BTreeMap::new();
        for entry in index.iter().filter(|e| e.stage == stage) {
            let path = out_dir.join(&entry.path);
            let bytes = std::fs::read(&path).with_context(|| format!("reading {}", path.display()))?;
            let scores: ViewScores = serde_json::from_slice(&bytes)
                .with_context(|| format!("{} is not an {VIEW_KIND} score file", path.display()))?;
            let variant = entry.item.rsplit('/').next().unwrap_or_default().to_string();
            by_variant.entry(variant).or_default().push(scores);
        }
        if by_variant.is_empty() {
            // Its references are exact views: a dataset that is not synthetic has none, and the
            // other tables (the clouds') still have something to say.
            text.push_str(&format!("\n# {stage}: no view has a reference (not a synthetic dataset)\n"));
            continue;
        }
        let n: usize = by_variant.values().map(Vec::len).sum();
        text.push_str(&format!(
            "\n# {stage}: {n} views; PSNR (dB) and SSIM (Wang et al. 2004, 11x11 Gaussian, sigma 1.5) on RGB over the \
             whole image and over the condition's valid pixels; depth where the reference is structure\n\n{stage}\n"
        ));
        type Get = fn(&ViewScores) -> Option<f64>;
        type Over = fn(Vec<f64>) -> Option<f64>;
        let avg: Over = |v| mean(v.into_iter());
        // The median view's abs_rel beside the mean: one view whose exact camera sits inside a
        // parked car (depth 0.1 m) has an abs_rel of 100 and would be the whole mean.
        let med: Over = median;
        let cols: [(&str, usize, Get, Over); 10] = [
            ("PSNR", 2, |s| s.psnr.filter(|p| p.is_finite()), avg),
            ("SSIM", 4, |s| s.ssim, avg),
            ("PSNR valid", 2, |s| s.psnr_valid.filter(|p| p.is_finite()), avg),
            ("SSIM valid", 4, |s| s.ssim_valid, avg),
            ("abs_rel", 4, |s| s.abs_rel, avg),
            ("abs_rel median view", 4, |s| s.abs_rel, med),
            ("d<1.25", 4, |s| s.delta1, avg),
            ("abs_rel valid", 4, |s| s.abs_rel_valid, avg),
            ("d<1.25 valid", 4, |s| s.delta1_valid, avg),
            ("valid", 4, |s| Some(s.valid_share), avg),
        ];
        text.push_str("| variant | views |");
        for (h, _, _, _) in &cols {
            text.push_str(&format!(" {h} |"));
        }
        text.push_str("\n|---|---:|");
        text.push_str(&"---:|".repeat(cols.len()));
        text.push('\n');
        let mut means: Vec<Vec<f64>> = vec![Vec::new(); cols.len()];
        for (variant, scores) in &by_variant {
            text.push_str(&format!("| {variant} | {} |", scores.len()));
            for (k, (_, decimals, get, over)) in cols.iter().enumerate() {
                match over(scores.iter().filter_map(get).collect()) {
                    Some(v) => {
                        means[k].push(v);
                        text.push_str(&format!(" {v:.decimals$} |"));
                    }
                    None => text.push_str(" - |"),
                }
            }
            text.push('\n');
        }
        text.push_str(&format!("| mean | {n} |"));
        for (k, (_, decimals, _, _)) in cols.iter().enumerate() {
            match mean(means[k].iter().copied()) {
                Some(v) => text.push_str(&format!(" {v:.decimals$} |")),
                None => text.push_str(" - |"),
            }
        }
        text.push('\n');
    }
    Ok(text)
}
