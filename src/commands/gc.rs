//! `dist4d gc`: the records and blobs the last N runs did not use, removed from a store.

use crate::commands::existing_store;
use anyhow::Result;
use std::path::PathBuf;
use std::process::ExitCode;

/// Removes (or with `dry_run` lists) what the newest `keep_runs` runs did not use, within `max_size`.
pub fn run(cache: Option<PathBuf>, keep_runs: usize, max_size: Option<u64>, dry_run: bool) -> Result<ExitCode> {
    let cache = existing_store(cache)?;
    let r = dist4d_runtime::gc::gc(&cache, keep_runs, max_size, dry_run)?;
    println!(
        "{}kept {} runs, {} records, {} blobs ({} bytes); {} {} runs, {} records, {} blobs ({} bytes)",
        if dry_run { "--dry-run, nothing removed: would have " } else { "" },
        r.runs_kept,
        r.records_kept,
        r.blobs_kept,
        r.bytes_kept,
        if dry_run { "would remove" } else { "removed" },
        r.runs_dropped,
        r.records_dropped,
        r.blobs_dropped,
        r.bytes_freed
    );
    Ok(ExitCode::SUCCESS)
}
