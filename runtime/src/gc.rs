//! `gc`: drop task records and blobs that no recent run used.
//!
//! Reachable = the task keys listed by the newest `keep_runs` runs (all pipelines sharing the
//! store; the shards and merge of one cluster submission count as one run); with a size
//! budget, older runs among those are dropped until the blobs they reach fit. Records are
//! compacted into one new segment (written and fsynced before the old ones are removed, so a
//! crash leaves duplicates at worst), and so is the file-fingerprint memo (one segment per
//! process that hashed files: a cluster leaves thousands); then unreachable blobs are deleted.
//! Needs the store alone: it gives way while another process's lease is live (see
//! [`crate::lease`]).
//!
//! gc deletes only what it can read and found unreachable: a segment of a newer dist4d makes it
//! refuse the store (as a run does), a segment of unknown format and a blob of an unknown codec
//! (a newer dist4d's) are left in place. `dry_run` reports what it would remove and writes
//! nothing, so it works on a store it cannot write (no lease either: a run may hold the store).

use crate::digest::{Digest, DigestMap};
use crate::record::TaskRecord;
use crate::runs::{keys_path, list_runs};
use crate::segment::SegmentWriter;
use crate::store::{removable_segments, Access, Store};
use anyhow::{Context, Result};
use std::collections::HashSet;
use std::path::Path;

#[derive(Debug, Default, PartialEq)]
pub struct GcReport {
    pub runs_kept: usize,
    pub runs_dropped: usize,
    pub records_kept: usize,
    pub records_dropped: usize,
    pub blobs_kept: usize,
    pub blobs_dropped: usize,
    pub bytes_freed: u64,
    pub bytes_kept: u64,
}

pub fn gc(root: &Path, keep_runs: usize, max_bytes: Option<u64>, dry_run: bool) -> Result<GcReport> {
    let store = Store::open(root, if dry_run { Access::ReadOnly } else { Access::Exclusive })?;
    // Runs recorded as running are dead (gc holds the store alone): they recorded no keys.
    let (all, dead): (Vec<_>, Vec<_>) =
        list_runs(&store.runs_dir())?.into_iter().partition(|r| r.status != crate::runs::RunStatus::Running);
    for run in dead.iter().filter(|_| !dry_run) {
        let _ = std::fs::remove_file(store.runs_dir().join(format!("{}.json", run.id)));
    }
    let mut report = GcReport::default();
    let records = latest_records(&store);
    let kept = reachable(&store, &all, &records, keep_runs, max_bytes)?;
    report.runs_kept = kept.runs.len();
    for run in all.iter().filter(|r| !kept.runs.contains(&r.id)) {
        if !dry_run {
            let _ = std::fs::remove_file(store.runs_dir().join(format!("{}.json", run.id)));
            let _ = std::fs::remove_file(keys_path(&store, &run.id));
        }
        report.runs_dropped += 1;
    }
    compact_records(&store, root, &records, &kept.keys, dry_run, &mut report)?;
    drop_blobs(root, &kept.blobs, dry_run, &mut report)?;
    Ok(report)
}

/// The latest record per key (the one a run uses).
fn latest_records(store: &Store) -> DigestMap<Vec<u8>> {
    let mut records: DigestMap<Vec<u8>> = DigestMap::default();
    for (_, payload) in store.all_records() {
        let Some(k) = TaskRecord::key_of(payload) else { continue };
        if records.get(&k).is_none_or(|kept| TaskRecord::supersedes(payload, kept)) {
            records.insert(k, payload.to_vec());
        }
    }
    records
}

/// What the kept runs reach: their ids, task keys and blobs.
struct Reachable {
    runs: Vec<String>,
    keys: HashSet<Digest>,
    blobs: HashSet<Digest>,
}

/// The runs to keep, newest first, within the count and (if any) the size budget of the blobs
/// they reach; a group (the shards and merge of one cluster submission) counts as one run.
fn reachable(
    store: &Store,
    all: &[crate::runs::RunRecord],
    records: &DigestMap<Vec<u8>>,
    keep_runs: usize,
    max_bytes: Option<u64>,
) -> Result<Reachable> {
    let mut groups: Vec<Vec<&crate::runs::RunRecord>> = crate::runs::grouped(all);
    groups.reverse(); // newest first
    let blob_size = |d: &Digest| std::fs::metadata(store.blob_path(d)).map(|m| m.len()).unwrap_or(0);
    let mut kept = Reachable { runs: Vec::new(), keys: HashSet::new(), blobs: HashSet::new() };
    let mut bytes = 0u64;
    for (i, group) in groups.iter().enumerate().take(keep_runs) {
        let mut run_keys = Vec::new();
        for run in group {
            run_keys.extend(read_keys(&keys_path(store, &run.id))?);
        }
        let mut new_blobs = Vec::new();
        let mut new_bytes = 0;
        for payload in run_keys.iter().filter_map(|k| records.get(k)) {
            for b in blobs_of(payload) {
                if !kept.blobs.contains(&b) && !new_blobs.contains(&b) {
                    new_bytes += blob_size(&b);
                    new_blobs.push(b);
                }
            }
        }
        if i > 0 && max_bytes.is_some_and(|m| bytes + new_bytes > m) {
            break;
        }
        bytes += new_bytes;
        kept.blobs.extend(new_blobs);
        kept.keys.extend(run_keys);
        kept.runs.extend(group.iter().map(|r| r.id.clone()));
    }
    Ok(kept)
}

/// The blobs a record names: its outputs not inlined, and its params.
fn blobs_of(payload: &[u8]) -> Vec<Digest> {
    TaskRecord::decode(payload)
        .map(|r| {
            r.outputs
                .iter()
                .filter(|o| o.inline.is_none() && !o.is_unmade())
                .map(|o| o.digest)
                .chain([r.params])
                .collect()
        })
        .unwrap_or_default()
}

/// Compacts records: the kept ones go to a fresh segment, then the old segments go (those it
/// read: one it cannot read stays); the fingerprint memo is compacted too.
fn compact_records(
    store: &Store,
    root: &Path,
    records: &DigestMap<Vec<u8>>,
    keys: &HashSet<Digest>,
    dry_run: bool,
    report: &mut GcReport,
) -> Result<()> {
    let old_segments = if dry_run { Vec::new() } else { removable_segments(&root.join("ac"))? };
    let mut writer = match dry_run {
        true => None,
        false => Some(SegmentWriter::create(&root.join("ac"), &format!("gc-{}", store.writer_id()))?),
    };
    for (k, payload) in records {
        if keys.contains(k) {
            if let Some(w) = writer.as_mut() {
                w.append(payload)?;
            }
            report.records_kept += 1;
        } else {
            report.records_dropped += 1;
        }
    }
    if let Some(mut w) = writer {
        w.sync()?;
        for seg in old_segments {
            std::fs::remove_file(&seg).with_context(|| format!("removing {}", seg.display()))?;
        }
        store.compact_fingerprints()?;
    }
    Ok(())
}

/// Deletes the blobs no kept record names (a newer dist4d's stay).
fn drop_blobs(root: &Path, blobs: &HashSet<Digest>, dry_run: bool, report: &mut GcReport) -> Result<()> {
    let cas = root.join("cas");
    for dir in std::fs::read_dir(&cas).with_context(|| format!("listing {}", cas.display()))? {
        let dir = dir?.path();
        let Some(prefix) = dir.file_name().and_then(|n| n.to_str()).map(String::from) else { continue };
        for f in std::fs::read_dir(&dir)? {
            let f = f?.path();
            let name = f.file_name().and_then(|n| n.to_str()).unwrap_or("");
            let digest = Digest::from_hex(&format!("{prefix}{name}"));
            let len = std::fs::metadata(&f).map(|m| m.len()).unwrap_or(0);
            if digest.is_some_and(|d| blobs.contains(&d)) {
                report.blobs_kept += 1;
                report.bytes_kept += len;
            } else if let Some(codec) = newer_codec(&f) {
                // No record names it, but a newer dist4d's may (in a store two versions share).
                eprintln!(
                    "warning: leaving {} as it is: it was written by a newer dist4d (blob codec {codec})",
                    f.display()
                );
                report.blobs_kept += 1;
                report.bytes_kept += len;
            } else {
                if !dry_run {
                    std::fs::remove_file(&f).with_context(|| format!("removing {}", f.display()))?;
                }
                report.blobs_dropped += 1;
                report.bytes_freed += len;
            }
        }
    }
    Ok(())
}

/// The unknown codec of the blob file at `path`, if a newer dist4d packed it.
fn newer_codec(path: &Path) -> Option<u8> {
    let mut head = Vec::with_capacity(16);
    let f = std::fs::File::open(path).ok()?;
    std::io::Read::read_to_end(&mut std::io::Read::take(f, 16), &mut head).ok()?;
    crate::blob::newer_codec(&head)
}

/// The task keys a run used (cached or run), as its keys file lists them; none when it has none.
pub(crate) fn read_keys(path: &Path) -> Result<Vec<Digest>> {
    match std::fs::read(path) {
        Ok(b) => Ok(b.chunks_exact(32).map(|c| Digest(c.try_into().unwrap())).collect()),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(Vec::new()),
        Err(e) => Err(e).with_context(|| format!("reading {}", path.display())),
    }
}
