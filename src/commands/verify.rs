//! `dist4d verify`: an output folder's files checked against what dist4d wrote there, or (with
//! --store) every blob and record of a store.

use crate::commands::existing_store;
use anyhow::Result;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

/// Checks the store (with `store`), then the folder `out` (when given); exit code 1 when
/// anything is modified, missing or damaged.
pub fn run(out: Option<PathBuf>, store: bool, cache: Option<PathBuf>) -> Result<ExitCode> {
    let mut code = ExitCode::SUCCESS;
    if store {
        code = verify_store(&existing_store(cache)?)?;
    }
    let Some(out) = out else { return Ok(code) };
    let r = dist4d_runtime::export::verify(&out)?;
    for rel in &r.modified {
        println!("modified: {rel}");
    }
    for rel in &r.missing {
        println!("missing:  {rel}");
    }
    let owner = r.owner.as_deref().unwrap_or("?");
    println!(
        "{}: {} files intact, {} modified, {} missing (exports of pipeline `{owner}`)",
        out.display(),
        r.ok,
        r.modified.len(),
        r.missing.len()
    );
    if r.modified.is_empty() && r.missing.is_empty() {
        return Ok(code);
    }
    println!("rerun pipeline `{owner}` with the same --out to rewrite them");
    Ok(ExitCode::from(1))
}

/// `dist4d verify --store`: prints what is wrong, then a summary; exit code 1 unless all is sound.
fn verify_store(cache: &Path) -> Result<ExitCode> {
    let r = dist4d_runtime::verify::verify_store(cache)?;
    for line in &r.damaged {
        println!("damaged:  {line}");
    }
    for line in &r.unreadable {
        println!("unreadable: {line}");
    }
    for line in &r.notes {
        println!("note:     {line}");
    }
    println!(
        "{}: {} records in {} segments, {} fingerprints, {} blobs ({} bytes), {} run records checked; {} damaged, {} unreadable",
        cache.display(),
        r.records,
        r.segments,
        r.fingerprints,
        r.blobs,
        r.blob_bytes,
        r.runs,
        r.damaged.len(),
        r.unreadable.len()
    );
    if r.sound() {
        return Ok(ExitCode::SUCCESS);
    }
    if !r.damaged.is_empty() {
        println!("runs recompute what damaged blobs and records held (rerun the pipelines that use them)");
    }
    Ok(ExitCode::from(1))
}
