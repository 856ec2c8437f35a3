//! Materialization: final outputs copied from the store into the user-facing dataset layout.
//!
//! ```text
//! <out>/
//!   .dist4d-manifest   which pipeline owns the folder, and what each exported path holds
//!   .dist4d-manifest.d/<time>-<writer>   what one sharded run changed, applied over the manifest
//!   .dist4d-tmp/       temp files, renamed into place when complete (the folder goes when a run leaves it empty)
//!   .dist4d-index.d/shard-<i>-of-<n>.json   the files one shard exported
//!   index.json         every file of the last run with its stage, item and digest
//! ```
//!
//! A run over the whole dataset rewrites the manifest (folding in the shards' deltas) and
//! `index.json` whole. The shards of a sharded run (`--shard I/N`, one Slurm array task each)
//! run at once into one folder, so none of them may rewrite what the others write: each leaves
//! a manifest delta and an index part, and readers merge them ([`read_index`]); each also
//! rewrites `index.json` from the parts, for tools that read only that file.
//!
//! Files are written whole (temp file, rename; fsynced together, once, before the manifest). A
//! file whose blob the store keeps raw is made by reflink where the filesystem allows (it then
//! shares the blob's disk blocks, no second copy), else written from memory or from the unpacked
//! blob. What is written where is confined:
//! every dimension label put into a path is checked to be one plain path component, and the
//! joined path must stay inside the output folder, so a dataset labelling an item `../../x` cannot
//! write outside it. An output folder belongs to one pipeline (by name): its manifest says which,
//! and another pipeline refuses to write there instead of overwriting its files.
//!
//! The manifest records each file's digest and its stat (device, inode, size, mtime, ctime) as
//! written. A rerun trusts a file whose stat is unchanged; one whose stat changed is hashed again
//! and rewritten if its bytes differ (an edit that keeps the size and mtime still changes ctime).
//! [`verify`] hashes every file on demand.
//!
//! Outputs that are exported and read by no stage are kept only here, not in the store (see
//! [`OutputFolder`] and docs/cache.md): the folder is then where their bytes live, and a task
//! record of theirs is a cache hit only while its files here hold the bytes it names.

use crate::blob;
use crate::digest::Digest;
use crate::item::ItemKey;
use crate::operator::{Blob, Dataset};
use crate::record::OutputRef;
use crate::store::{read_blob, sync_filesystem, write_atomic_via, write_whole_io, BlobError, Store, Unread};
use anyhow::{anyhow, bail, Context, Result};
use dist4d_graph::{Dim, Export, TemplatePart};
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, HashMap};
use std::os::unix::fs::MetadataExt;
use std::path::{Component, Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};

const MANIFEST: &str = ".dist4d-manifest";
const MANIFEST_DELTAS: &str = ".dist4d-manifest.d";
pub(crate) const TMP: &str = ".dist4d-tmp";
const INDEX: &str = "index.json";
const INDEX_PARTS: &str = ".dist4d-index.d";
/// First word of a version-2 manifest; version 1 had no header and no stats.
const MANIFEST_V2: &str = "dist4d-manifest 2";

/// What a file looked like when dist4d wrote or last confirmed it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct FileStat {
    dev: u64,
    ino: u64,
    size: u64,
    mtime_ns: i128,
    ctime_ns: i128,
}

impl FileStat {
    fn of(path: &Path) -> Option<FileStat> {
        let m = std::fs::metadata(path).ok()?;
        Some(FileStat {
            dev: m.dev(),
            ino: m.ino(),
            size: m.size(),
            mtime_ns: m.mtime() as i128 * 1_000_000_000 + m.mtime_nsec() as i128,
            ctime_ns: m.ctime() as i128 * 1_000_000_000 + m.ctime_nsec() as i128,
        })
    }

    fn encode(&self) -> String {
        format!("{}:{}:{}:{}:{}", self.dev, self.ino, self.size, self.mtime_ns, self.ctime_ns)
    }

    fn decode(s: &str) -> Option<FileStat> {
        let mut p = s.split(':');
        let stat = FileStat {
            dev: p.next()?.parse().ok()?,
            ino: p.next()?.parse().ok()?,
            size: p.next()?.parse().ok()?,
            mtime_ns: p.next()?.parse().ok()?,
            ctime_ns: p.next()?.parse().ok()?,
        };
        p.next().is_none().then_some(stat)
    }
}

/// What the manifest says one exported path holds.
#[derive(Clone, Debug, PartialEq)]
struct Held {
    digest: Digest,
    size: u64,
    /// None for entries of a version-1 manifest: the file is hashed once to confirm it.
    stat: Option<FileStat>,
}

/// The `.dist4d-manifest` of an output folder.
#[derive(Debug, Default, Clone)]
struct Manifest {
    /// The pipeline that owns the folder; None for a version-1 manifest, which named none.
    owner: Option<String>,
    files: BTreeMap<String, Held>,
    /// The deltas of sharded runs applied over the manifest file, in order.
    deltas: Vec<PathBuf>,
}

/// The first line of a manifest that is neither version 1 nor 2: written by a newer dist4d, or
/// edited; either way its owner cannot be told, so the folder is not written into.
fn unknown_header(first_line: &str) -> bool {
    first_line.starts_with("dist4d-manifest") && !first_line.starts_with(&format!("{MANIFEST_V2} "))
}

impl Manifest {
    /// Reads the manifest of `dir` with the deltas of sharded runs applied over it; `Ok(None)`
    /// when there is none.
    fn read(dir: &Path) -> Result<Option<Manifest>> {
        let mut m = Manifest::read_file(&dir.join(MANIFEST))?;
        let deltas = dir.join(MANIFEST_DELTAS);
        let mut names: Vec<PathBuf> = match std::fs::read_dir(&deltas) {
            Ok(rd) => rd.filter_map(|e| e.ok()).map(|e| e.path()).collect(),
            Err(_) => Vec::new(),
        };
        names.sort();
        for path in names {
            // A delta removed by a run folding it in since we listed it is in the manifest now.
            let Some(delta) = Manifest::read_file(&path)? else { continue };
            let m = m.get_or_insert_with(|| Manifest { owner: delta.owner.clone(), ..Default::default() });
            if m.owner.is_none() {
                m.owner = delta.owner.clone();
            }
            if delta.owner != m.owner {
                bail!(
                    "{} names pipeline {:?} and {} names {:?}: remove the folder, or export elsewhere",
                    path.display(),
                    delta.owner.as_deref().unwrap_or_default(),
                    dir.join(MANIFEST).display(),
                    m.owner.as_deref().unwrap_or_default()
                );
            }
            for (rel, held) in delta.files {
                if held.size == u64::MAX {
                    m.files.remove(&rel);
                } else {
                    m.files.insert(rel, held);
                }
            }
            m.deltas.push(path);
        }
        Ok(m)
    }

    /// Reads one manifest file (tombstones of a delta, `- <path>`, come back with size
    /// `u64::MAX`); `Ok(None)` when there is none.
    fn read_file(path: &Path) -> Result<Option<Manifest>> {
        let text = match std::fs::read_to_string(path) {
            Ok(t) => t,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(e).with_context(|| format!("reading {}", path.display())),
        };
        if text.lines().next().is_some_and(unknown_header) {
            bail!(
                "{} starts with {:?}, a manifest this dist4d does not read (a newer version wrote it, or it \
                 was edited), so it cannot tell which pipeline owns the folder: export elsewhere",
                path.display(),
                text.lines().next().unwrap_or_default()
            );
        }
        let mut m = Manifest::default();
        let mut lines = text.lines().peekable();
        if let Some(owner) = lines.peek().and_then(|l| l.strip_prefix(MANIFEST_V2)) {
            m.owner = Some(owner.trim().to_string());
            lines.next();
        }
        for line in lines {
            if let Some(rel) = line.strip_prefix("- ") {
                m.files.insert(rel.to_string(), Held { digest: Digest::default(), size: u64::MAX, stat: None });
                continue;
            }
            // v2: `<digest> <size> <stat> <path>`; v1: `<digest> <size> <path>`.
            let parts: Vec<&str> = line.splitn(if m.owner.is_some() { 4 } else { 3 }, ' ').collect();
            let (d, n, stat, rel) = match parts[..] {
                [d, n, s, rel] => (d, n, FileStat::decode(s), rel),
                [d, n, rel] => (d, n, None, rel),
                _ => continue,
            };
            if let (Some(digest), Ok(size)) = (Digest::from_hex(d), n.parse()) {
                m.files.insert(rel.to_string(), Held { digest, size, stat });
            }
        }
        Ok(Some(m))
    }

    fn write(&self, dir: &Path, tmp: &Path) -> Result<()> {
        write_if_changed(tmp, &dir.join(MANIFEST), self.text(&[]).as_bytes())
    }

    /// The manifest's text, with tombstones for `removed` (in a delta).
    fn text(&self, removed: &[String]) -> String {
        let mut text = format!("{MANIFEST_V2} {}\n", self.owner.as_deref().unwrap_or_default());
        for (rel, h) in &self.files {
            let stat = h.stat.map(|s| s.encode()).unwrap_or_else(|| "-".into());
            text.push_str(&format!("{} {} {stat} {rel}\n", h.digest.hex(), h.size));
        }
        for rel in removed {
            text.push_str(&format!("- {rel}\n"));
        }
        text
    }
}

/// One file of `index.json`: where it is, which stage, port and item made it, and its bytes.
#[derive(Serialize, Deserialize, Clone, Debug)]
pub struct IndexEntry {
    /// Relative to the output folder.
    pub path: String,
    pub stage: String,
    pub port: String,
    /// The item's labels joined by `/`.
    pub item: String,
    pub digest: String,
    pub bytes: u64,
}

#[derive(Deserialize)]
struct Index {
    files: Vec<IndexEntry>,
    #[serde(default)]
    sources: BTreeMap<String, serde_json::Value>,
}

impl Index {
    fn read(path: &Path) -> Result<Index> {
        let bytes = std::fs::read(path).with_context(|| format!("reading {}", path.display()))?;
        serde_json::from_slice(&bytes).with_context(|| format!("{} is not a dist4d index", path.display()))
    }
}

/// The files the last run exported into `out_dir`: those of its `index.json`, or, when the last
/// run was sharded, the union of its shards' index parts (see the module doc).
pub fn read_index(out_dir: &Path) -> Result<Vec<IndexEntry>> {
    // Parts older than index.json are a whole run's leftovers (it removes them; a crash, or an
    // NFS silly-renamed file, can keep them): that run's index lists everything.
    let modified = |p: &Path| std::fs::metadata(p).and_then(|m| m.modified()).ok();
    let whole = modified(&out_dir.join(INDEX));
    match merged_parts(out_dir)? {
        Some((index, parts)) if parts.iter().any(|p| modified(p) > whole) => Ok(index.files),
        _ => Ok(Index::read(&out_dir.join(INDEX))?.files),
    }
}

/// The index parts of the newest sharded run merged, with the part files read; `None` when
/// there are none. Parts of an earlier split (another shard count) are left out.
fn merged_parts(out_dir: &Path) -> Result<Option<(Index, Vec<PathBuf>)>> {
    let dir = out_dir.join(INDEX_PARTS);
    let Ok(rd) = std::fs::read_dir(&dir) else { return Ok(None) };
    let mut parts: Vec<(PathBuf, u32, std::time::SystemTime)> = Vec::new();
    for e in rd.filter_map(|e| e.ok()) {
        let path = e.path();
        let name = e.file_name().to_string_lossy().into_owned();
        let Some(n) = name.strip_suffix(".json").and_then(|n| n.rsplit_once("-of-")).and_then(|(_, n)| n.parse().ok())
        else {
            continue;
        };
        let modified = e.metadata().and_then(|m| m.modified()).unwrap_or(std::time::UNIX_EPOCH);
        parts.push((path, n, modified));
    }
    let Some(&(_, newest, _)) = parts.iter().max_by_key(|p| p.2) else { return Ok(None) };
    parts.retain(|p| p.1 == newest);
    parts.sort();
    let mut files: BTreeMap<String, IndexEntry> = BTreeMap::new();
    let mut sources = BTreeMap::new();
    for (path, ..) in &parts {
        let part = match Index::read(path) {
            Ok(p) => p,
            // Folded away by a whole run since it was listed.
            Err(_) if !path.exists() => continue,
            Err(e) => return Err(e),
        };
        files.extend(part.files.into_iter().map(|f| (f.path.clone(), f)));
        sources.extend(part.sources);
    }
    let index = Index { files: files.into_values().collect(), sources };
    Ok(Some((index, parts.into_iter().map(|p| p.0).collect())))
}

/// The bytes of an `index.json` listing `files` (in path order) and their items' sources.
fn index_json<'a>(
    files: impl IntoIterator<Item = &'a IndexEntry>,
    sources: &BTreeMap<String, serde_json::Value>,
) -> Result<Vec<u8>> {
    let files: Vec<&IndexEntry> = files.into_iter().collect();
    let items: std::collections::BTreeSet<&str> = files.iter().map(|e| e.item.as_str()).collect();
    let sources: BTreeMap<&String, &serde_json::Value> =
        sources.iter().filter(|(item, _)| items.contains(item.as_str())).collect();
    // Through a JSON value, whose keys are sorted: the index's bytes do not depend on field order.
    Ok(serde_json::to_vec_pretty(&serde_json::json!({ "files": files, "sources": sources }))?)
}

/// An output folder as a run (or explain) found it: its manifest as earlier runs left it, read
/// once, and the files found to hold given bytes by hashing since. It says whether an output kept
/// only in the folder (not in the store) is still in place, which decides whether its task is a
/// cache hit, and the exporter then trusts the same answer instead of hashing the file again.
pub struct OutputFolder {
    dir: PathBuf,
    /// Dimension names, for messages about labels that cannot be path components.
    dims: Vec<String>,
    manifest: Manifest,
    /// Files whose stat was not the manifest's and that were hashed: path -> (digest, stat then).
    confirmed: Mutex<HashMap<String, (Digest, FileStat)>>,
}

impl OutputFolder {
    /// The folder `dir` as its manifest describes it (as an empty folder when it has none),
    /// without writing anything: for explain, which must not claim a folder.
    pub fn read(dir: &Path, dims: &[Dim]) -> Result<OutputFolder> {
        Ok(OutputFolder::new(dir, dims, Manifest::read(dir)?.unwrap_or_default()))
    }

    fn new(dir: &Path, dims: &[Dim], manifest: Manifest) -> OutputFolder {
        OutputFolder {
            dir: dir.to_path_buf(),
            dims: dims.iter().map(|d| d.name.clone()).collect(),
            manifest,
            confirmed: Mutex::new(HashMap::new()),
        }
    }

    /// The pipeline the manifest names as the folder's owner, if any.
    pub fn owner(&self) -> Option<&str> {
        self.manifest.owner.as_deref()
    }

    /// Whether the file `export` makes for `item` holds the bytes of digest `digest` (`size`
    /// bytes): yes when its stat is the one the manifest (or an earlier hash in this process)
    /// recorded for those bytes; no when it is missing, has another size, or its path cannot be
    /// made; otherwise the file is hashed, or, when `hash` is false, `None` says that only
    /// hashing can tell. A stat can be trusted because every write replaces the file (a new
    /// inode) and an edit in place changes its ctime.
    pub fn holds(
        &self,
        export: &Export,
        item: &ItemKey,
        dataset: &dyn Dataset,
        digest: &Digest,
        size: u64,
        hash: bool,
    ) -> Option<bool> {
        let Ok(rel) = render(export, item, dataset, &self.dims) else { return Some(false) };
        let Ok(path) = confined(&self.dir, &rel) else { return Some(false) };
        let Some(now) = FileStat::of(&path) else { return Some(false) };
        if now.size != size {
            return Some(false);
        }
        if let Some(known) = self.known_digest(&rel, &now) {
            return Some(known == *digest);
        }
        if !hash {
            return None;
        }
        let Some(found) = file_digest(&path) else { return Some(false) };
        // A file changed while it was hashed has another stat by now: not remembered.
        if FileStat::of(&path) == Some(now) {
            self.confirmed.lock().unwrap().insert(rel, (found, now));
        }
        Some(found == *digest)
    }

    /// The digest of the bytes at `rel` when its stat is `now`, if the manifest or a hash made in
    /// this process says.
    fn known_digest(&self, rel: &str, now: &FileStat) -> Option<Digest> {
        self.listed_digest(rel, now).or_else(|| self.hashed_digest(rel, now))
    }

    /// The digest the manifest lists for `rel` with stat `now`.
    fn listed_digest(&self, rel: &str, now: &FileStat) -> Option<Digest> {
        self.manifest.files.get(rel).filter(|h| h.stat.as_ref() == Some(now)).map(|h| h.digest)
    }

    /// The digest a hash made in this process found at `rel` with stat `now`.
    fn hashed_digest(&self, rel: &str, now: &FileStat) -> Option<Digest> {
        let confirmed = self.confirmed.lock().unwrap();
        confirmed.get(rel).filter(|(_, stat)| stat == now).map(|(d, _)| *d)
    }
}

pub struct Exporter {
    /// The folder as earlier runs left it, owned by this pipeline.
    folder: Arc<OutputFolder>,
    writer: String,
    counter: u64,
    /// This run's files as planned, and those of them confirmed or written (with their stat).
    entries: BTreeMap<String, IndexEntry>,
    done: BTreeMap<String, FileStat>,
    /// What the dataset says each exported item was read from, by item path.
    sources: BTreeMap<String, serde_json::Value>,
    reflinks: Arc<AtomicBool>,
    /// Whether a job ran (wrote or confirmed a file) since the folder was last synced.
    jobs_done: bool,
    /// The shard this run is (`shard-<i>-of-<n>`), which leaves a delta and an index part
    /// instead of rewriting the manifest and index; None for a run over the whole dataset.
    part: Option<String>,
    /// Files removed as stale (their tasks now have nothing to make).
    removed: Vec<String>,
}

/// One file to write.
pub struct ExportJob {
    /// The path relative to the output folder.
    pub rel: String,
    dest: PathBuf,
    tmp: PathBuf,
    digest: Digest,
    size: u64,
    bytes: Source,
    /// Whether a file already there may hold these bytes and is worth hashing before writing:
    /// not when the manifest says it holds other bytes (a param changed), so that an
    /// incremental run reads each stale export no more than it writes it.
    confirm: bool,
    /// The blob file in the store, for outputs not kept inside their record.
    cas: Option<PathBuf>,
    /// Shared by the jobs of one exporter: false once a reflink failed because the filesystem
    /// (or the pair of filesystems) cannot do it, so that later jobs write without trying.
    reflinks: Arc<AtomicBool>,
}

enum Source {
    Mem(Blob),
    Inline(Arc<[u8]>),
    Blob,
}

/// Why an export job did not write its file.
#[derive(Debug)]
pub enum ExportError {
    /// The blob holding its bytes is missing or corrupt: the scheduler runs its task again, which
    /// exports it anew.
    LostBlob(BlobError),
    /// The temp file or its folder was not there when written or renamed (another run that
    /// exported into the folder removed its temp folder): worth another try.
    NotFound(anyhow::Error),
    Failed(anyhow::Error),
}

impl From<anyhow::Error> for ExportError {
    fn from(e: anyhow::Error) -> ExportError {
        ExportError::Failed(e)
    }
}

impl std::fmt::Display for ExportError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            ExportError::LostBlob(e) => e.fmt(f),
            ExportError::NotFound(e) | ExportError::Failed(e) => write!(f, "{e:#}"),
        }
    }
}

impl ExportJob {
    /// Writes the file unless it already holds the right bytes; returns its stat afterwards.
    pub fn write(self) -> std::result::Result<FileStat, ExportError> {
        // Another run exporting into the folder finished and removed the temp folder, empty then
        // ([`Exporter::finish`]): made again, once the temp file is in it, it stays. Several
        // times: a run that finishes makes the folder for its own lists and removes it again, so
        // it can vanish between our making it and our temp file landing in it (seen with two
        // shards exporting into one folder on a loaded 2-core machine).
        let mut attempts = 0;
        loop {
            match self.write_once() {
                // Not found: by the time we look, the other run may have made the folder again for
                // its own lists, so the error is the test, not whether the folder is there now.
                Err(ExportError::NotFound(_)) if attempts < 20 => {
                    attempts += 1;
                    if let Some(d) = self.tmp.parent() {
                        std::fs::create_dir_all(d).with_context(|| format!("creating {}", d.display()))?;
                    }
                }
                r => return r,
            }
        }
    }

    fn write_once(&self) -> std::result::Result<FileStat, ExportError> {
        if let Some(stat) = FileStat::of(&self.dest).filter(|s| self.confirm && s.size == self.size) {
            // Same size: maybe the same bytes (a copied folder, a touched file, a v1 manifest).
            if file_digest(&self.dest) == Some(self.digest) {
                return Ok(stat);
            }
        }
        if !self.try_reflink()? {
            let owned;
            let bytes: &[u8] = match (&self.bytes, &self.cas) {
                (Source::Mem(b), _) => b,
                (Source::Inline(b), _) => b,
                (Source::Blob, cas) => {
                    let path = cas.as_ref().ok_or_else(|| anyhow!("no bytes to export {}", self.dest.display()))?;
                    owned = read_blob(path, &self.digest).map_err(|e| match e {
                        Unread::Lost(lost) => ExportError::LostBlob(lost),
                        newer @ Unread::Newer(_) => ExportError::Failed(newer.into_error()),
                    })?;
                    &owned
                }
            };
            if let Some(dir) = self.dest.parent() {
                std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
            }
            // Made durable together before the manifest is written (`Exporter::finish`).
            if let Err(io) = write_whole_io(&self.tmp, &self.dest, bytes, false) {
                let gone = io.kind() == std::io::ErrorKind::NotFound;
                let e = anyhow::Error::new(io)
                    .context(format!("writing {}", self.dest.display()))
                    .context(format!("exporting {}", self.dest.display()));
                return Err(if gone { ExportError::NotFound(e) } else { ExportError::Failed(e) });
            }
        }
        Ok(FileStat::of(&self.dest)
            .ok_or_else(|| anyhow!("{} vanished right after it was written", self.dest.display()))?)
    }

    /// Materializes the file by reflink from its blob when the blob holds its bytes raw and the
    /// filesystem shares blocks between files (btrfs, XFS): no second copy on disk. The clone is
    /// hashed before it is renamed into place, as a read of the blob would be. Ok(false) when
    /// no reflink was made (the caller writes the bytes).
    fn try_reflink(&self) -> std::result::Result<bool, ExportError> {
        let Some(cas) = self.cas.as_ref().filter(|_| self.reflinks.load(Ordering::Relaxed)) else { return Ok(false) };
        if !blob::is_raw_file(cas) {
            return Ok(false);
        }
        if let Some(dir) = self.dest.parent() {
            std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        }
        if let Err(e) = blob::reflink(cas, &self.tmp) {
            // Not supported here (ext4, tmpfs, or the store on another filesystem): stop trying.
            if matches!(
                e.raw_os_error(),
                Some(libc::EOPNOTSUPP | libc::EXDEV | libc::EINVAL | libc::ENOTTY | libc::ENOSYS)
            ) {
                self.reflinks.store(false, Ordering::Relaxed);
            }
            return Ok(false);
        }
        if file_digest(&self.tmp) != Some(self.digest) {
            // A corrupt blob: removed either way; written from memory if the bytes are there.
            let _ = std::fs::remove_file(&self.tmp);
            let _ = std::fs::remove_file(cas);
            if matches!(self.bytes, Source::Blob) {
                return Err(ExportError::LostBlob(BlobError {
                    digest: self.digest,
                    problem: format!("is corrupt and was removed ({})", cas.display()),
                }));
            }
            return Ok(false);
        }
        std::fs::rename(&self.tmp, &self.dest).with_context(|| format!("exporting {}", self.dest.display()))?;
        Ok(true)
    }
}

/// The error of a run of `pipeline` into a folder that pipeline `owner` owns.
fn owned_by_another(dir: &Path, owner: &str, pipeline: &str) -> anyhow::Error {
    anyhow::anyhow!(
        "{} holds the exports of pipeline `{owner}` (see {}); pipeline `{pipeline}` will not overwrite them: give it \
         its own --out (by default each pipeline exports to out/<its name>/ beside its file), or remove that folder",
        dir.display(),
        dir.join(MANIFEST).display()
    )
}

/// Writes `manifest` as the first manifest of the new folder `dir`, unless another process wrote
/// one first: then that one is returned. Written whole to `tmp`, then hard-linked to its name
/// (link(2) never replaces a file, on NFS too), so exactly one of several racing runs claims it.
fn claim_new(manifest: &Manifest, dir: &Path, tmp: &Path) -> Result<Option<Manifest>> {
    let whole = std::fs::File::create(tmp).and_then(|mut f| {
        use std::io::Write;
        f.write_all(manifest.text(&[]).as_bytes())?;
        f.sync_all()
    });
    whole.with_context(|| format!("writing {}", tmp.display()))?;
    let linked = std::fs::hard_link(tmp, dir.join(MANIFEST));
    let _ = std::fs::remove_file(tmp);
    match linked {
        Ok(()) => {
            std::fs::File::open(dir).and_then(|d| d.sync_all()).ok();
            Ok(None)
        }
        Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {
            let theirs = Manifest::read(dir)?.with_context(|| format!("{} vanished", dir.join(MANIFEST).display()))?;
            Ok(Some(theirs))
        }
        // A filesystem without hard links (FUSE object stores, SMB, exFAT): create_new is
        // exclusive too; the manifest is then written in place, so a kill in that instant can leave
        // it short (the next run then refuses the folder, naming the manifest to remove).
        Err(e) if matches!(e.raw_os_error(), Some(libc::EPERM) | Some(libc::EOPNOTSUPP) | Some(libc::ENOSYS)) => {
            let created = std::fs::OpenOptions::new().write(true).create_new(true).open(dir.join(MANIFEST));
            match created {
                Ok(mut f) => {
                    use std::io::Write;
                    f.write_all(manifest.text(&[]).as_bytes())
                        .and_then(|_| f.sync_all())
                        .with_context(|| format!("writing {}", dir.join(MANIFEST).display()))?;
                    Ok(None)
                }
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {
                    let theirs =
                        Manifest::read(dir)?.with_context(|| format!("{} vanished", dir.join(MANIFEST).display()))?;
                    Ok(Some(theirs))
                }
                Err(e) => Err(e).with_context(|| format!("claiming {}", dir.display())),
            }
        }
        Err(e) => Err(e).with_context(|| format!("claiming {} with {}", dir.display(), dir.join(MANIFEST).display())),
    }
}

impl Exporter {
    /// Opens `dir` for the exports of pipeline `pipeline`. Refuses a folder that another pipeline
    /// owns, or one that holds files but no manifest (it was not made by dist4d), before anything
    /// is written; claims a new or empty folder by writing its manifest at once, so that a run
    /// killed before its end still leaves the folder marked as this pipeline's.
    ///
    /// `shard` = (i, n) for shard i of n of a sharded run (see the module doc).
    pub fn open(
        dir: &Path,
        store: &Store,
        pipeline: &str,
        stages: &[&str],
        dims: &[Dim],
        shard: Option<(u32, u32)>,
    ) -> Result<Exporter> {
        let found = Manifest::read(dir)?;
        let new_folder = found.is_none();
        let mut manifest = match found {
            Some(m) => match &m.owner {
                None => {
                    adopt_legacy(dir, pipeline, stages)?;
                    m
                }
                Some(owner) if owner != pipeline => return Err(owned_by_another(dir, owner, pipeline)),
                _ => m,
            },
            None => {
                let foreign = not_bookkeeping(dir, 3);
                if !foreign.is_empty() {
                    bail!(
                        "{} is not empty (it holds {}) and has no {MANIFEST}, so dist4d did not make it; \
                         export into a new or empty folder (--out) instead of writing among files that are not \
                         its own",
                        dir.display(),
                        foreign.join(", ")
                    );
                }
                Manifest::default()
            }
        };
        let tmp = dir.join(TMP);
        // The temp folder is made for the run's writes. A folder that cannot take it (a finished,
        // read-only --out) is still opened: a run with nothing to write there goes on, and one
        // that must write fails then, naming the file.
        if let Err(e) = std::fs::create_dir_all(&tmp) {
            if !dir.is_dir() {
                return Err(e).with_context(|| format!("creating output directory {}", dir.display()));
            }
        }
        // Temp files of writers that are gone (killed runs) are removed.
        for e in std::fs::read_dir(&tmp).into_iter().flatten() {
            let p = e?.path();
            let writer =
                p.file_name().and_then(|n| n.to_str()).and_then(|n| n.rsplit_once('-')).map(|(w, _)| w.to_string());
            if writer.is_none_or(|w| store.temp_abandoned(&w, &p)) {
                let _ = std::fs::remove_file(&p);
            }
        }
        let writer = store.writer_id().to_string();
        let mut counter = 0;
        if manifest.owner.as_deref() != Some(pipeline) {
            manifest.owner = Some(pipeline.to_string());
            counter += 1;
            let tmp = dir.join(TMP).join(format!("{writer}-manifest{counter}"));
            if new_folder {
                // Two runs that both found no manifest must not both take the folder: the claim
                // is a hard link, which fails when the manifest exists, where a rename replaces
                // it. The loser reads the winner's manifest: a run of the same pipeline (a shard)
                // goes on, another pipeline is refused before it exports anything.
                match claim_new(&manifest, dir, &tmp)? {
                    None => {}
                    Some(theirs) => match theirs.owner {
                        Some(owner) if owner != pipeline => return Err(owned_by_another(dir, &owner, pipeline)),
                        _ => manifest = Manifest { owner: Some(pipeline.to_string()), ..theirs },
                    },
                }
            } else {
                manifest.write(dir, &tmp)?;
            }
        }
        Ok(Exporter {
            folder: Arc::new(OutputFolder::new(dir, dims, manifest)),
            writer,
            counter,
            entries: BTreeMap::new(),
            done: BTreeMap::new(),
            sources: BTreeMap::new(),
            reflinks: Arc::new(AtomicBool::new(true)),
            jobs_done: false,
            part: shard.map(|(i, n)| format!("shard-{i}-of-{n}")),
            removed: Vec::new(),
        })
    }

    /// For a task that now has nothing to make: removes the file an earlier run of this pipeline
    /// exported for it (only a file the manifest lists, so never one dist4d did not write); the
    /// manifest drops it at the end of the run. Without this a rerun would leave it beside the
    /// new files, listed nowhere but in the manifest.
    pub fn remove_stale(&mut self, export: &Export, item: &ItemKey, dataset: &dyn Dataset) {
        let Ok(rel) = render(export, item, dataset, &self.folder.dims) else { return };
        if self.folder.manifest.files.contains_key(&rel) {
            if let Ok(dest) = confined(&self.folder.dir, &rel) {
                let _ = std::fs::remove_file(dest);
                self.removed.push(rel);
            }
        }
    }

    /// The folder as this run found it, for the cache decision of outputs kept only there.
    pub fn folder(&self) -> Arc<OutputFolder> {
        self.folder.clone()
    }

    fn tmp_path(&mut self, what: &str) -> PathBuf {
        self.counter += 1;
        self.folder.dir.join(TMP).join(format!("{}-{what}{}", self.writer, self.counter))
    }

    /// Records the file an output maps to; returns a job unless the file is known to be in place.
    /// Fails when the item's labels cannot make a path inside the output folder.
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
    ) -> Result<Option<ExportJob>> {
        let rel = render(export, item, dataset, &self.folder.dims)?;
        let dest = confined(&self.folder.dir, &rel)?;
        let (stage, port) = names;
        let item_path = dataset.path(item);
        if !self.sources.contains_key(&item_path) {
            if let Some(record) = dataset.source_record(item) {
                self.sources.insert(item_path.clone(), record);
            }
        }
        self.entries.insert(
            rel.clone(),
            IndexEntry {
                path: rel.clone(),
                stage: stage.into(),
                port: port.into(),
                item: item_path,
                digest: out.digest.hex(),
                bytes: out.size,
            },
        );
        // In place: the manifest says the path holds these bytes, and the file is untouched since;
        // or a hash made by this run found them there (a file the manifest does not list yet, as
        // a killed run leaves them: it may not be on disk yet, so the folder is synced before the
        // manifest lists it, as for a file written).
        let held = self.folder.manifest.files.get(&rel);
        let same_bytes = held.is_some_and(|h| h.digest == out.digest && h.size == out.size);
        if let Some(now) = FileStat::of(&dest).filter(|s| s.size == out.size) {
            let listed = self.folder.listed_digest(&rel, &now) == Some(out.digest);
            if listed || self.folder.hashed_digest(&rel, &now) == Some(out.digest) {
                self.jobs_done |= !listed;
                self.done.insert(rel, now);
                return Ok(None);
            }
        }
        let confirm = held.is_none() || same_bytes;
        let tmp = self.tmp_path("");
        let bytes = match (mem, &out.inline) {
            (Some(m), _) => Source::Mem(m),
            (None, Some(b)) => Source::Inline(b.clone()),
            (None, None) => Source::Blob,
        };
        let cas = out.inline.is_none().then(|| store.blob_path(&out.digest));
        let reflinks = self.reflinks.clone();
        Ok(Some(ExportJob { rel, dest, tmp, digest: out.digest, size: out.size, bytes, confirm, cas, reflinks }))
    }

    /// A job ended: its file is in place with `stat`, or (None) it failed.
    pub fn job_done(&mut self, rel: &str, stat: Option<FileStat>) {
        self.jobs_done = true;
        match stat {
            Some(stat) => self.done.insert(rel.to_string(), stat),
            None => self.done.remove(rel),
        };
    }

    /// Writes the manifest and `index.json`; returns how many files the run exported or confirmed.
    ///
    /// Both list only files that exist: a path whose export failed keeps its manifest entry only
    /// while the file earlier runs wrote is still there, untouched, and is left out of the index.
    pub fn finish(self) -> Result<u64> {
        let tmp = self.folder.dir.join(TMP);
        let count = self.write_lists();
        // The temp folder goes when empty: a finished folder holds the exports and their lists
        // only. (Not while another run still writes there: it is not empty then; and a run that
        // finds it gone makes it again, see `ExportJob::write`.)
        let _ = std::fs::remove_dir(&tmp);
        count
    }

    fn write_lists(mut self) -> Result<u64> {
        // Best effort, as in `open`: lists that have not changed are not written (a read-only
        // folder then needs no temp folder), and a write that needs it names the file it failed.
        let _ = std::fs::create_dir_all(self.folder.dir.join(TMP));
        let tmps: Vec<PathBuf> = ["manifest", "index", "part"].iter().map(|w| self.tmp_path(w)).collect();
        let Exporter { folder, entries, done, sources, jobs_done, part, removed, writer, .. } = self;
        let dir = folder.dir.clone();
        // Shared with the key layer during the run; by its end, normally ours alone.
        let mut manifest = Arc::try_unwrap(folder).map(|f| f.manifest).unwrap_or_else(|f| f.manifest.clone());
        let mut mine = Manifest { owner: manifest.owner.clone(), ..Default::default() };
        for (rel, entry) in &entries {
            if let Some(stat) = done.get(rel) {
                let digest = Digest::from_hex(&entry.digest).unwrap_or_default();
                mine.files.insert(rel.clone(), Held { digest, size: entry.bytes, stat: Some(*stat) });
            }
        }
        let files: Vec<&IndexEntry> =
            entries.iter().filter(|(rel, _)| done.contains_key(*rel)).map(|(_, e)| e).collect();
        let count = files.len() as u64;
        // The files written without an fsync each reach the disk before the manifest that lists
        // them as written: after a power loss, a file the manifest trusts holds its bytes.
        if jobs_done {
            sync_filesystem(&dir)?;
        }
        let json = index_json(files, &sources)?;
        match part {
            Some(part) => {
                let removed: Vec<String> = removed.into_iter().filter(|r| !mine.files.contains_key(r)).collect();
                let millis = std::time::SystemTime::now()
                    .duration_since(std::time::UNIX_EPOCH)
                    .map(|d| d.as_millis())
                    .unwrap_or(0);
                let delta = dir.join(MANIFEST_DELTAS).join(format!("{millis:013}-{writer}"));
                write_atomic_via(&tmps[0], &delta, mine.text(&removed).as_bytes())?;
                write_atomic_via(&tmps[2], &dir.join(INDEX_PARTS).join(format!("{part}.json")), &json)?;
                write_merged_index(&dir, &tmps[1])?;
            }
            None => {
                manifest.files.extend(mine.files);
                manifest.files.retain(|rel, held| match FileStat::of(&dir.join(rel)) {
                    None => false,
                    Some(now) => held.stat.is_none_or(|s| s == now) || done.contains_key(rel),
                });
                manifest.write(&dir, &tmps[0])?;
                // Folded in: the shards' index parts (this index lists the whole dataset), before
                // it is written, so that no part is left newer than it; then the deltas this
                // run read, which its manifest now holds.
                let _ = std::fs::remove_dir_all(dir.join(INDEX_PARTS));
                write_if_changed(&tmps[1], &dir.join(INDEX), &json)?;
                for delta in &manifest.deltas {
                    let _ = std::fs::remove_file(delta);
                }
            }
        }
        Ok(count)
    }
}

/// Writes `dest` whole (see [`write_atomic_via`]) unless it already holds `bytes`: a run with
/// nothing new to export writes nothing in the output folder, so it succeeds on a folder it
/// cannot write (a read-only mount of a finished dataset).
fn write_if_changed(tmp: &Path, dest: &Path, bytes: &[u8]) -> Result<()> {
    if std::fs::read(dest).is_ok_and(|held| held == bytes) {
        return Ok(());
    }
    write_atomic_via(tmp, dest, bytes)
}

/// Rewrites `index.json` from the index parts, again while parts changed as it merged them: of
/// shards finishing at once, the last to write its part also writes the index that lists it.
fn write_merged_index(dir: &Path, tmp: &Path) -> Result<()> {
    let stamp = |paths: &[PathBuf]| -> Vec<Option<std::time::SystemTime>> {
        paths.iter().map(|p| std::fs::metadata(p).and_then(|m| m.modified()).ok()).collect()
    };
    for _ in 0..16 {
        let Some((index, read)) = merged_parts(dir)? else { return Ok(()) };
        let before = stamp(&read);
        write_atomic_via(tmp, &dir.join(INDEX), &index_json(&index.files, &index.sources)?)?;
        match merged_parts(dir)? {
            Some((_, now)) if now == read && stamp(&now) == before => return Ok(()),
            _ => continue,
        }
    }
    Ok(())
}

/// A folder with a version-1 manifest (which named no owner, like an empty one) is taken over
/// only when its `index.json` shows that this pipeline's stages made its files: the stages of
/// another pipeline, or files without an index, are not overwritten.
fn adopt_legacy(dir: &Path, pipeline: &str, stages: &[&str]) -> Result<()> {
    let index = match read_index(dir) {
        Ok(files) => files,
        Err(_) if not_bookkeeping(dir, 1).is_empty() => return Ok(()),
        Err(e) => {
            return Err(e.context(format!(
                "{} has a manifest without an owner and no readable index, so dist4d cannot tell which pipeline \
                 wrote it; pipeline `{pipeline}` will not write there: export elsewhere, or remove that folder",
                dir.display()
            )))
        }
    };
    let mut foreign: Vec<&str> =
        index.iter().map(|e| e.stage.as_str()).filter(|s| !stages.contains(s)).collect::<Vec<_>>();
    foreign.sort();
    foreign.dedup();
    if !foreign.is_empty() {
        bail!(
            "{} holds exports of stages {} (listed in its index.json), which pipeline `{pipeline}` does not have: \
             another pipeline wrote them, and they are not overwritten; export elsewhere, or remove that folder",
            dir.display(),
            foreign.iter().map(|s| format!("`{s}`")).collect::<Vec<_>>().join(", ")
        );
    }
    Ok(())
}

/// Up to `most` names in `dir` other than dist4d's own bookkeeping (manifest, temp folder);
/// none for a folder that does not exist.
fn not_bookkeeping(dir: &Path, most: usize) -> Vec<String> {
    let Ok(entries) = std::fs::read_dir(dir) else { return Vec::new() };
    entries
        .filter_map(|e| e.ok())
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| ![MANIFEST, MANIFEST_DELTAS, TMP, INDEX_PARTS].contains(&n.as_str()))
        .take(most)
        .collect()
}

/// Why `label` cannot be one path component, if it cannot.
pub fn unsafe_component(label: &str) -> Option<&'static str> {
    if label.is_empty() {
        Some("is empty")
    } else if label == "." || label == ".." {
        Some("is `.` or `..`")
    } else if label.contains(['/', '\\']) {
        Some("contains a path separator")
    } else if label.contains('\0') {
        Some("contains a NUL byte")
    } else if label.chars().any(char::is_control) {
        Some("contains a control character")
    } else if label.len() > 255 {
        Some("is longer than 255 bytes")
    } else {
        None
    }
}

/// The relative path of an export for an item: the template with dimension labels filled in.
/// Every label must be one plain path component.
pub fn render(export: &Export, item: &ItemKey, dataset: &dyn Dataset, dims: &[String]) -> Result<String> {
    let mut out = String::new();
    for part in &export.parts {
        match part {
            TemplatePart::Text(t) => out.push_str(t),
            TemplatePart::Token(d) => {
                let at = item.prefix(d + 1);
                let dim = dims.get(*d).map(String::as_str).unwrap_or("item");
                let Some(token) = dataset.token(&at) else {
                    bail!(
                        "cannot export `{}`: the dataset has no token for the {dim} {:?}",
                        export.template,
                        dataset.label(&at)
                    );
                };
                if let Some(why) = unsafe_component(&token) {
                    bail!("cannot export `{}`: the {dim} token {token:?} {why}", export.template);
                }
                out.push_str(&token);
            }
            TemplatePart::Padded(d, width) => {
                let label = dataset.label(&item.prefix(d + 1));
                let Ok(n) = label.parse::<u64>() else {
                    bail!(
                        "cannot export `{}`: the {} name {label:?} is not a number to zero-pad",
                        export.template,
                        dims.get(*d).map(String::as_str).unwrap_or("item")
                    );
                };
                out.push_str(&format!("{n:0width$}"));
            }
            TemplatePart::Dim(d) => {
                let label = dataset.label(&item.prefix(d + 1));
                if let Some(why) = unsafe_component(&label) {
                    bail!(
                        "cannot export `{}`: the {} name {label:?} {why}, and names are put into export paths \
                         as single folder or file names",
                        export.template,
                        dims.get(*d).map(String::as_str).unwrap_or("item")
                    );
                }
                out.push_str(&label);
            }
        }
    }
    Ok(out)
}

/// `dir/rel`, provided `rel` is relative, every component a plain name, and its first component
/// none of the names dist4d keeps for itself in the folder.
fn confined(dir: &Path, rel: &str) -> Result<PathBuf> {
    let path = Path::new(rel);
    if rel.is_empty() || !path.components().all(|c| matches!(c, Component::Normal(_))) {
        bail!("the export path {rel:?} would leave the output folder {}", dir.display());
    }
    let first = rel.split('/').next().unwrap_or_default();
    if [MANIFEST, TMP, INDEX].contains(&first) {
        bail!("the export path {rel:?} would write into `{first}`, which dist4d keeps for itself in {}", dir.display());
    }
    Ok(dir.join(path))
}

/// The digest of a file's bytes, or None when it cannot be read.
fn file_digest(path: &Path) -> Option<Digest> {
    let mut hasher = blake3::Hasher::new();
    hasher.update_mmap(path).ok()?;
    Some(Digest(*hasher.finalize().as_bytes()))
}

/// What [`verify`] found.
#[derive(Debug, Default, Serialize)]
pub struct VerifyReport {
    pub ok: u64,
    /// Paths whose bytes differ from what dist4d wrote.
    pub modified: Vec<String>,
    pub missing: Vec<String>,
    /// The pipeline that owns the folder.
    pub owner: Option<String>,
}

/// Hashes every file the manifest of `dir` lists and compares it with what was written.
pub fn verify(dir: &Path) -> Result<VerifyReport> {
    let manifest = Manifest::read(dir)?
        .ok_or_else(|| anyhow!("{} has no {MANIFEST}: it is not an output folder of dist4d", dir.display()))?;
    let mut report = VerifyReport { owner: manifest.owner.clone(), ..Default::default() };
    for (rel, held) in &manifest.files {
        let path = match confined(dir, rel) {
            Ok(p) => p,
            Err(_) => {
                report.modified.push(rel.clone());
                continue;
            }
        };
        match std::fs::metadata(&path) {
            Err(_) => report.missing.push(rel.clone()),
            Ok(m) if m.len() != held.size => report.modified.push(rel.clone()),
            Ok(_) if file_digest(&path).as_ref() == Some(&held.digest) => report.ok += 1,
            Ok(_) => report.modified.push(rel.clone()),
        }
    }
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn of_runs_racing_for_a_new_folder_exactly_one_pipeline_claims_it() {
        // Two pipelines started together on a new --out used to both go on in 11 of 20 tries (the
        // later manifest rename won; both exported). Racing 8 at once, 20 times: one pipeline wins
        // each time; runs of the winning pipeline (shards) may all go on.
        for round in 0..20 {
            let dir = tempfile::tempdir().unwrap();
            let (out, store) = (dir.path().join("out"), dir.path().join("store"));
            let barrier = std::sync::Barrier::new(8);
            let results: Vec<(String, Result<Exporter>)> = std::thread::scope(|scope| {
                let handles: Vec<_> = (0..8)
                    .map(|i| {
                        let (out, store, barrier) = (&out, &store, &barrier);
                        scope.spawn(move || {
                            // Every thread reaches the barrier, even one whose store failed to
                            // open: a panic before it left the other seven waiting for ever.
                            let s = Store::open(store, crate::Access::Shared);
                            // Runs 0-3 are four pipelines, 4-7 shards of pipeline p0.
                            let name = format!("p{}", if i < 4 { i } else { 0 });
                            barrier.wait();
                            let s = s.expect("opening the store");
                            let opened = Exporter::open(out, &s, &name, &[], &[], None);
                            (name, opened)
                        })
                    })
                    .collect();
                handles.into_iter().map(|h| h.join().unwrap()).collect()
            });
            let won: std::collections::BTreeSet<&str> =
                results.iter().filter(|(_, r)| r.is_ok()).map(|(n, _)| n.as_str()).collect();
            assert_eq!(won.len(), 1, "round {round}: {won:?}");
            let owner = Manifest::read(&out).unwrap().unwrap().owner.unwrap();
            assert_eq!(won.iter().next().unwrap(), &owner.as_str(), "round {round}");
            for (name, r) in &results {
                match r {
                    Ok(_) => assert_eq!(name, &owner),
                    Err(e) => {
                        let e = format!("{e:#}");
                        assert!(e.contains(&format!("holds the exports of pipeline `{owner}`")), "round {round}: {e}");
                    }
                }
            }
            // Every run of the owner went on, shards included.
            let owners = results.iter().filter(|(n, _)| n == &owner).count();
            assert_eq!(results.iter().filter(|(_, r)| r.is_ok()).count(), owners, "round {round}");
        }
    }

    #[test]
    fn only_plain_names_are_path_components() {
        for bad in ["", ".", "..", "../x", "a/b", "/etc", "a\\b", "a\0b", "a\nb"] {
            assert!(unsafe_component(bad).is_some(), "{bad:?}");
        }
        assert!(unsafe_component(&"x".repeat(256)).is_some());
        for good in ["scene-0061", "CAM_FRONT", "000", "scène 1", "..x", "a.b"] {
            assert_eq!(unsafe_component(good), None, "{good:?}");
        }
    }

    #[test]
    fn paths_that_leave_the_folder_are_refused() {
        let dir = Path::new("/tmp/out");
        assert_eq!(confined(dir, "a/b.png").unwrap(), dir.join("a/b.png"));
        for bad in
            ["", "../x", "a/../../x", "/etc/passwd", "./a", "index.json/x.png", ".dist4d-tmp/a", ".dist4d-manifest"]
        {
            assert!(confined(dir, bad).is_err(), "{bad:?}");
        }
    }

    #[test]
    fn a_folder_holds_a_file_by_its_listed_stat_or_by_a_hash_when_one_is_allowed() {
        let p = crate::testkit::load(
            r#"Pipeline(
                dataset: Grid(scenes: 1, frames: 2, cameras: 1),
                stages: {"file": ToFile(inputs: {"x": "dataset.frame_value"}, grain: frame)},
                export: {"file.file": "{scene}/{frame}.bin"},
            )"#,
            &[],
        );
        let grid = crate::testkit::grid_of(&p);
        let dir = tempfile::tempdir().unwrap();
        std::fs::create_dir_all(dir.path().join("s0")).unwrap();
        let (first, second) = (dir.path().join("s0/000.bin"), dir.path().join("s0/001.bin"));
        std::fs::write(&first, b"first").unwrap();
        std::fs::write(&second, b"second").unwrap();
        let mut m = Manifest { owner: Some("test".into()), ..Default::default() };
        for (rel, bytes) in [("s0/000.bin", &b"first"[..]), ("s0/001.bin", b"second")] {
            let stat = FileStat::of(&dir.path().join(rel));
            m.files.insert(rel.into(), Held { digest: Digest::of(bytes), size: bytes.len() as u64, stat });
        }
        m.write(dir.path(), &dir.path().join("tmp")).unwrap();
        let (item0, item1) = (ItemKey::new(&[0, 0]), ItemKey::new(&[0, 1]));

        let folder = OutputFolder::read(dir.path(), &p.dims).unwrap();
        let holds = |item: &ItemKey, bytes: &[u8], hash: bool| {
            folder.holds(&p.exports[0], item, &grid, &Digest::of(bytes), bytes.len() as u64, hash)
        };
        // Listed with this stat: no read needed either way.
        assert_eq!(holds(&item0, b"first", false), Some(true));
        assert_eq!(holds(&item0, b"fir5t", false), Some(false));
        assert_eq!(holds(&item0, b"other bytes", false), Some(false), "another size");
        // Another stat (touched): only a hash can tell, and is then remembered.
        let later = std::fs::metadata(&second).unwrap().modified().unwrap() + std::time::Duration::from_secs(5);
        std::fs::File::options().write(true).open(&second).unwrap().set_modified(later).unwrap();
        assert_eq!(holds(&item1, b"second", false), None);
        assert_eq!(holds(&item1, b"second", true), Some(true));
        assert_eq!(holds(&item1, b"second", false), Some(true));
        assert_eq!(holds(&item1, b"secont", true), Some(false));
        // Gone: no.
        std::fs::remove_file(&first).unwrap();
        assert_eq!(holds(&item0, b"first", true), Some(false));
    }

    #[test]
    fn manifests_keep_owner_digests_and_stats() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("a b.bin"), b"xyz").unwrap();
        let mut m = Manifest { owner: Some("curation".into()), ..Default::default() };
        let stat = FileStat::of(&dir.path().join("a b.bin"));
        m.files.insert("a b.bin".into(), Held { digest: Digest::of(b"xyz"), size: 3, stat });
        m.write(dir.path(), &dir.path().join("tmp")).unwrap();
        let back = Manifest::read(dir.path()).unwrap().unwrap();
        assert_eq!(back.owner.as_deref(), Some("curation"));
        assert_eq!(back.files, m.files);
        // A version-1 manifest (no header, no stats) is read without an owner.
        std::fs::write(dir.path().join(MANIFEST), format!("{} 3 x/y.bin\n", Digest::of(b"xyz").hex())).unwrap();
        let v1 = Manifest::read(dir.path()).unwrap().unwrap();
        assert_eq!(v1.owner, None);
        assert_eq!(v1.files["x/y.bin"].stat, None);
    }
}
