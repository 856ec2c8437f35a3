//! `dist4d verify --store`: checks every blob and record of a store without changing it.
//!
//! A run checks a blob only when it reads it, and a damaged record only costs its task a rerun,
//! so damage nothing reads goes unnoticed until the day it is needed (a cache moved to new disks,
//! a store shared between sites). This reads everything once: each segment entry's checksum, each
//! task record's encoding, each blob against the digest it is named by, each run record. It
//! opens no lease and writes nothing (a corrupt blob is reported, not removed: the run that
//! needs it removes and remakes it), so it works on a read-only store and beside running runs.

use crate::blob::{self, Unreadable};
use crate::digest::Digest;
use crate::record::TaskRecord;
use crate::segment::{segment_paths, Header, Segment};
use anyhow::{Context, Result};
use rayon::prelude::*;
use std::path::{Path, PathBuf};

/// What [`verify_store`] found. Paths are relative to the store.
#[derive(Debug, Default)]
pub struct StoreReport {
    pub segments: usize,
    pub records: usize,
    pub fingerprints: usize,
    pub blobs: usize,
    pub blob_bytes: u64,
    pub runs: usize,
    /// Damage: what a run cannot use (and would recompute, or loses).
    pub damaged: Vec<String>,
    /// What this dist4d cannot check: written by a newer one, or not dist4d's.
    pub unreadable: Vec<String>,
    /// Harmless: the torn last entry a killed writer leaves.
    pub notes: Vec<String>,
}

impl StoreReport {
    /// Whether everything was checked and found sound.
    pub fn sound(&self) -> bool {
        self.damaged.is_empty() && self.unreadable.is_empty()
    }
}

pub fn verify_store(root: &Path) -> Result<StoreReport> {
    anyhow::ensure!(
        root.join("ac").is_dir() || root.join("cas").is_dir(),
        "{} is not a dist4d store (it has no ac/ nor cas/)",
        root.display()
    );
    let mut r = StoreReport::default();
    let rel = |p: &Path| p.strip_prefix(root).unwrap_or(p).display().to_string();
    for (dir, records) in [("ac", true), ("fp", false)] {
        for path in segment_paths(&root.join(dir))? {
            r.segments += 1;
            let seg = Segment::open(&path)?;
            let check = seg.check();
            if let Some(problem) = check.header.problem() {
                r.unreadable.push(format!("{}: it {problem}", rel(&path)));
                continue;
            }
            if check.header == Header::Torn {
                continue;
            }
            for (start, end) in &check.damaged {
                r.damaged.push(format!(
                    "{}: bytes {start}..{end} fail their checksum (the records there are lost; those after them are read)",
                    rel(&path)
                ));
            }
            if check.tail > 0 {
                r.notes.push(format!(
                    "{}: its last {} bytes are a torn entry (a writer killed mid-append), ignored",
                    rel(&path),
                    check.tail
                ));
            }
            if records {
                for (off, payload) in seg.entries() {
                    match TaskRecord::decode(payload) {
                        Ok(_) => r.records += 1,
                        Err(e) => {
                            r.damaged.push(format!("{}: the record at byte {off} does not decode: {e}", rel(&path)))
                        }
                    }
                }
            } else {
                r.fingerprints += check.entries;
            }
        }
    }

    let blobs = blob_files(&root.join("cas"))?;
    r.blobs = blobs.len();
    let found: Vec<(u64, Option<Result<String, String>>)> = blobs
        .par_iter()
        .map(|(path, digest)| {
            let (size, problem) = check_blob(path, digest.as_ref());
            (
                size,
                problem.map(|p| {
                    p.map(|why| format!("{}: {why}", rel(path))).map_err(|why| format!("{}: {why}", rel(path)))
                }),
            )
        })
        .collect();
    for (size, problem) in found {
        r.blob_bytes += size;
        match problem {
            None => {}
            Some(Ok(damage)) => r.damaged.push(damage),
            Some(Err(newer)) => r.unreadable.push(newer),
        }
    }

    if let Ok(rd) = std::fs::read_dir(root.join("runs")) {
        for e in rd.filter_map(|e| e.ok()) {
            let p = e.path();
            let ext = p.extension().and_then(|x| x.to_str()).unwrap_or("");
            let len = e.metadata().map(|m| m.len()).unwrap_or(0);
            match ext {
                "json" => match std::fs::read(&p).map(|t| serde_json::from_slice::<crate::runs::RunRecord>(&t)) {
                    Ok(Ok(_)) => r.runs += 1,
                    Ok(Err(e)) => r.damaged.push(format!("{}: not a run record: {e}", rel(&p))),
                    Err(e) => r.damaged.push(format!("{}: cannot be read: {e}", rel(&p))),
                },
                "keys" if len % 32 != 0 => {
                    r.damaged.push(format!("{}: {len} bytes, not a whole number of 32-byte task keys", rel(&p)))
                }
                _ => {}
            }
        }
    }
    Ok(r)
}

/// Every file under `cas/`, with the digest its path names (None: not a blob name).
fn blob_files(cas: &Path) -> Result<Vec<(PathBuf, Option<Digest>)>> {
    let mut out = Vec::new();
    let rd = match std::fs::read_dir(cas) {
        Ok(rd) => rd,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(out),
        Err(e) => return Err(e).with_context(|| format!("listing {}", cas.display())),
    };
    for dir in rd {
        let dir = dir?.path();
        let prefix = dir.file_name().and_then(|n| n.to_str()).unwrap_or("").to_string();
        let files = std::fs::read_dir(&dir).with_context(|| format!("listing {}", dir.display()))?;
        for f in files {
            let f = f?.path();
            let name = f.file_name().and_then(|n| n.to_str()).unwrap_or("");
            out.push((f.clone(), Digest::from_hex(&format!("{prefix}{name}"))));
        }
    }
    out.sort();
    Ok(out)
}

/// The blob file's size, and what is wrong with it: Ok(damage) or Err(written by a newer dist4d).
fn check_blob(path: &Path, digest: Option<&Digest>) -> (u64, Option<Result<String, String>>) {
    let Some(digest) = digest else {
        return (0, Some(Ok("is not named by a digest (not a blob dist4d wrote)".into())));
    };
    let file = match std::fs::read(path) {
        Ok(f) => f,
        Err(e) => return (0, Some(Ok(format!("cannot be read: {e}")))),
    };
    let size = file.len() as u64;
    match blob::unpack(file, digest) {
        Ok(_) => (size, None),
        Err(why @ Unreadable::Newer { .. }) => (size, Some(Err(why.to_string()))),
        Err(why) => (size, Some(Ok(format!("{why} (a run that needs it removes it and makes it again)")))),
    }
}
