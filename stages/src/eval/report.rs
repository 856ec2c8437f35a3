//! `dist4d eval`'s tables: the scores every `EvalDepth` stage exported, read back from the run's
//! output folder and averaged per camera (the last dimension of each item) and over cameras.

use super::depth::{tabulate, ImageScores};
use anyhow::{ensure, Context, Result};
use dist4d_graph::Pipeline;
use std::path::Path;

/// The stage kind whose exported scores are tabulated.
const KIND: &str = "EvalDepth";

/// The `EvalDepth` stages of `pipeline`; an error unless there is one and each exports its scores
/// (the tables are read from the exported files), so that a run that could not be reported on
/// is refused before it starts.
pub fn scored_stages(pipeline: &Pipeline) -> Result<Vec<&str>> {
    let stages: Vec<(usize, &str)> = pipeline
        .nodes
        .iter()
        .enumerate()
        .filter(|(_, n)| n.stage().is_some_and(|s| s.kind == KIND))
        .map(|(id, n)| (id, n.name.as_str()))
        .collect();
    ensure!(!stages.is_empty(), "{}: the pipeline has no {KIND} stage to report", pipeline.path.display());
    for &(id, name) in &stages {
        ensure!(
            pipeline.exports.iter().any(|e| e.node == id),
            "{}: stage `{name}` ({KIND}) is not exported, and `dist4d eval` reads the scores from the \
             exported files: add `\"{name}.json\": \"{{scene}}/{{camera}}/{{frame}}_metrics.json\"` to `export`",
            pipeline.path.display()
        );
    }
    Ok(stages.into_iter().map(|(_, name)| name).collect())
}

/// The score tables of every `EvalDepth` stage of `pipeline`, from the files its last run
/// exported into `out_dir`.
pub fn tables(pipeline: &Pipeline, out_dir: &Path) -> Result<String> {
    let index = dist4d_runtime::export::read_index(out_dir)?;
    let mut text = String::new();
    for stage in scored_stages(pipeline)? {
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
        text.push_str(&format!("\n# {stage}: {} images, depth range 0.1-80 m\n", images.len()));
        text.push_str(&tabulate(&images));
    }
    Ok(text)
}
