//! One module per command, each with its `run`; `main` dispatches to them. Here: what several
//! commands share to find their store (the pipeline is loaded by [`crate::load`]).

pub mod check;
pub mod demo;
pub mod depthroot;
pub mod eval;
pub mod explain;
pub mod export_12hz;
pub mod export_infos;
pub mod gc;
pub mod graph;
pub mod merge;
pub mod occ3d_annotations;
pub mod run;
pub mod runs;
pub mod slurm;
pub mod synth;
pub mod verify;

use anyhow::Result;
use std::path::PathBuf;

/// The store `dist4d runs`, `gc` and `verify --store` read without --cache: the one `dist4d run pipelines/x.ron` uses
/// (`.dist4d/` beside the pipeline files), else `.dist4d/` here, whichever has runs first.
pub fn default_store() -> PathBuf {
    let candidates = [PathBuf::from("pipelines/.dist4d"), PathBuf::from(".dist4d")];
    let has_runs = |c: &PathBuf| c.join("runs").is_dir();
    candidates.iter().find(|c| has_runs(c)).unwrap_or(&candidates[0]).clone()
}

/// The store a command that only works on an existing store (gc, verify --store) was given, or
/// [`default_store`] (said on stderr); a folder that does not exist is an error, not a new store.
pub fn existing_store(cache: Option<PathBuf>) -> Result<PathBuf> {
    let cache = cache.unwrap_or_else(|| {
        let found = default_store();
        eprintln!("store: {} (--cache for another)", found.display());
        found
    });
    anyhow::ensure!(cache.is_dir(), "there is no store at {} (--cache names it)", cache.display());
    Ok(cache)
}
