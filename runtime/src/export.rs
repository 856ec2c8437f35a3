//! Materialization: final outputs copied from the store into the user-facing dataset layout.
//!
//! Files are written whole (temp file in `<out>/.dist4d-tmp/`, fsync, rename). A manifest of what
//! each path holds lets a rerun skip files already in place, and `index.json` lists every file
//! of the run with its stage, item and digest.

use crate::digest::Digest;
use crate::item::ItemKey;
use crate::operator::{Blob, Dataset};
use crate::record::OutputRef;
use crate::store::{write_atomic_via, Store};
use anyhow::{bail, Context, Result};
use dist4d_graph::{Export, TemplatePart};
use serde::Serialize;
use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::sync::Arc;

const MANIFEST: &str = ".dist4d-manifest";
const TMP: &str = ".dist4d-tmp";

#[derive(Serialize, Clone)]
struct IndexEntry {
    path: String,
    stage: String,
    port: String,
    item: String,
    digest: String,
    bytes: u64,
}

pub struct Exporter {
    dir: PathBuf,
    writer: String,
    counter: u64,
    /// What each path held after earlier runs.
    old: HashMap<String, (Digest, u64)>,
    entries: BTreeMap<String, IndexEntry>,
}

/// One file to write.
pub struct ExportJob {
    dest: PathBuf,
    tmp: PathBuf,
    digest: Digest,
    bytes: Source,
}

enum Source {
    Mem(Blob),
    Inline(Arc<[u8]>),
    Blob(PathBuf),
}

impl ExportJob {
    pub fn write(self) -> Result<()> {
        let owned;
        let bytes: &[u8] = match &self.bytes {
            Source::Mem(b) => b,
            Source::Inline(b) => b,
            Source::Blob(p) => {
                owned = std::fs::read(p).with_context(|| format!("reading cache blob {}", p.display()))?;
                if Digest::of(&owned) != self.digest {
                    let _ = std::fs::remove_file(p);
                    bail!("cache blob {} is corrupt and was removed; rerun to recompute it", p.display());
                }
                &owned
            }
        };
        write_atomic_via(&self.tmp, &self.dest, bytes).with_context(|| format!("exporting {}", self.dest.display()))
    }
}

impl Exporter {
    pub fn open(dir: &Path, store: &Store) -> Result<Exporter> {
        let tmp = dir.join(TMP);
        std::fs::create_dir_all(&tmp).with_context(|| format!("creating output directory {}", dir.display()))?;
        // Temp files of writers that are gone (killed runs) are removed.
        for e in std::fs::read_dir(&tmp)? {
            let p = e?.path();
            let writer =
                p.file_name().and_then(|n| n.to_str()).and_then(|n| n.rsplit_once('-')).map(|(w, _)| w.to_string());
            if writer.is_none_or(|w| !store.writer_alive(&w)) {
                let _ = std::fs::remove_file(&p);
            }
        }
        let mut old = HashMap::new();
        if let Ok(text) = std::fs::read_to_string(dir.join(MANIFEST)) {
            for line in text.lines() {
                let mut parts = line.splitn(3, ' ');
                if let (Some(d), Some(n), Some(path)) = (parts.next(), parts.next(), parts.next()) {
                    if let (Some(d), Ok(n)) = (Digest::from_hex(d), n.parse()) {
                        old.insert(path.to_string(), (d, n));
                    }
                }
            }
        }
        Ok(Exporter {
            dir: dir.to_path_buf(),
            writer: store.writer_id().to_string(),
            counter: 0,
            old,
            entries: BTreeMap::new(),
        })
    }

    /// Records the file an output maps to; returns a job when the file is not already in place.
    #[allow(clippy::too_many_arguments)]
    pub fn plan(
        &mut self,
        export: &Export,
        names: (&str, &str),
        item: &ItemKey,
        dataset: &dyn Dataset,
        out: &OutputRef,
        mem: Option<Blob>,
        store: &Store,
    ) -> Option<ExportJob> {
        let rel = render(export, item, dataset);
        let (stage, port) = names;
        self.entries.insert(
            rel.clone(),
            IndexEntry {
                path: rel.clone(),
                stage: stage.into(),
                port: port.into(),
                item: dataset.path(item),
                digest: out.digest.hex(),
                bytes: out.size,
            },
        );
        let dest = self.dir.join(&rel);
        let in_place = self.old.get(&rel) == Some(&(out.digest, out.size))
            && std::fs::metadata(&dest).is_ok_and(|m| m.len() == out.size);
        if in_place {
            return None;
        }
        self.counter += 1;
        let tmp = self.dir.join(TMP).join(format!("{}-{}", self.writer, self.counter));
        let bytes = match (mem, &out.inline) {
            (Some(m), _) => Source::Mem(m),
            (None, Some(b)) => Source::Inline(b.clone()),
            (None, None) => Source::Blob(store.blob_path(&out.digest)),
        };
        Some(ExportJob { dest, tmp, digest: out.digest, bytes })
    }

    /// Writes the manifest and `index.json`; returns how many files the run exported or confirmed.
    pub fn finish(self) -> Result<u64> {
        let mut manifest: BTreeMap<String, (Digest, u64)> = self.old.into_iter().collect();
        for (path, e) in &self.entries {
            manifest.insert(path.clone(), (Digest::from_hex(&e.digest).unwrap_or_default(), e.bytes));
        }
        let mut text = String::new();
        for (path, (d, n)) in &manifest {
            text.push_str(&format!("{} {} {}\n", d.hex(), n, path));
        }
        let tmp = self.dir.join(TMP);
        write_atomic_via(&tmp.join(format!("{}-manifest", self.writer)), &self.dir.join(MANIFEST), text.as_bytes())?;
        let files: Vec<&IndexEntry> = self.entries.values().collect();
        let json = serde_json::to_vec_pretty(&serde_json::json!({ "files": files }))?;
        write_atomic_via(&tmp.join(format!("{}-index", self.writer)), &self.dir.join("index.json"), &json)?;
        Ok(self.entries.len() as u64)
    }
}

/// The relative path of an export for an item: the template with dimension labels filled in.
pub fn render(export: &Export, item: &ItemKey, dataset: &dyn Dataset) -> String {
    let mut out = String::new();
    for part in &export.parts {
        match part {
            TemplatePart::Text(t) => out.push_str(t),
            TemplatePart::Dim(d) => out.push_str(&dataset.label(&item.prefix(d + 1))),
        }
    }
    out
}
