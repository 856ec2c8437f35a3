//! `dist4d depthroot`: the index of the DiST-4D depth files an export wrote.

use anyhow::Result;
use std::path::PathBuf;
use std::process::ExitCode;

/// Writes OUT/nus_sampletoken2depthroot.json for the samples that have their depth files.
pub fn run(out: PathBuf) -> Result<ExitCode> {
    let r = dist4d_stages::output::depthroot::write_depthroot(&out)?;
    println!(
        "{}: {} samples ({} depth files)",
        out.join(dist4d_stages::output::depthroot::INDEX).display(),
        r.samples,
        r.files
    );
    Ok(ExitCode::SUCCESS)
}
