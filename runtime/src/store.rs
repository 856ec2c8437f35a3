//! The store: content-addressed blobs, task records, file fingerprints and run records.
//!
//! ```text
//! <store>/
//!   leases/<writer>.lease   one per process using the store, kept fresh by a heartbeat
//!   leases/gc.lease     held by gc, which needs the store alone (see [`crate::lease`])
//!   leases/claims/      the outer items runs are working on, so that they share the work
//!   cas/ab/cdef...      blobs named by the blake3 digest of their bytes; compressed when that
//!                       pays, behind a header (see [`crate::blob`])
//!   ac/<writer>.seg     task records, packed in per-process append-only segments
//!   fp/<writer>.seg     memo of raw-file digests: (path, size, mtime, inode) -> digest
//!   runs/<id>.json      one record per run; <id>.keys lists the task keys it used
//!   tmp/                temp files, renamed into place when complete
//! ```
//!
//! Every file appears whole or not at all: blobs and JSON are written to `tmp/` and renamed (JSON
//! fsynced first; blobs together at the end of a run, see [`Store::sync`]); segment entries carry
//! checksums. So a killed process leaves nothing half-written, and
//! several processes (or cluster nodes on a shared filesystem) can use one store at once: they
//! write different segments, and renaming a blob over an identical one is harmless. Who is using
//! the store is told by lease files, not by `flock` (which does not work across nodes on Lustre
//! or NFS): see [`crate::lease`].

use crate::blob;
use crate::digest::{Digest, DigestMap};
use crate::lease::{self, Holder, Lease, Liveness};
use crate::record::TaskRecord;
use crate::segment::{enc, segment_paths, Segment, SegmentWriter};
use anyhow::{bail, Context, Result};
use std::collections::HashMap;
use std::fs::{self, File};
use std::os::unix::fs::MetadataExt;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Mutex, RwLock};

/// A blob that a task record names is missing or corrupt: the task that made it must run again.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct BlobError {
    pub digest: Digest,
    /// "is corrupt and was removed (path)", "cannot be read (path): ...".
    pub problem: String,
}

impl std::fmt::Display for BlobError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "cache blob {} {}", self.digest.short(), self.problem)
    }
}

impl std::error::Error for BlobError {}

/// A blob that a newer dist4d wrote (a codec this one does not know): left in place, and the task
/// that needs it fails with this, rather than remove and remake what a newer version stored.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct NewerBlob {
    pub digest: Digest,
    pub path: PathBuf,
    pub why: blob::Unreadable,
}

impl std::fmt::Display for NewerBlob {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "cache blob {} ({}) {}: it is left as it is; use that newer dist4d with this store, or give this one \
             another --cache",
            self.digest.short(),
            self.path.display(),
            self.why
        )
    }
}

impl std::error::Error for NewerBlob {}

/// Why a blob could not be read, as a value the scheduler acts on: a lost blob is remade by
/// running its task again, a newer dist4d's is left alone and its reader fails.
#[derive(Debug)]
pub enum Unread {
    Lost(BlobError),
    Newer(NewerBlob),
}

impl std::fmt::Display for Unread {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Unread::Lost(e) => e.fmt(f),
            Unread::Newer(e) => e.fmt(f),
        }
    }
}

impl std::error::Error for Unread {}

impl Unread {
    /// As an error carrying the [`BlobError`] or [`NewerBlob`] itself.
    pub fn into_error(self) -> anyhow::Error {
        match self {
            Unread::Lost(e) => anyhow::Error::new(e),
            Unread::Newer(e) => anyhow::Error::new(e),
        }
    }
}

/// How a process uses the store.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub enum Access {
    /// Runs and explains: many at once.
    Shared,
    /// Garbage collection: alone.
    Exclusive,
    /// Commands that only read (explain, `gc --dry-run`): no lease, no directory created, no temp
    /// file removed, no fingerprint memoised on disk, so that they work on a store they cannot
    /// write (a read-only mount, another user's store). Writes fail.
    ReadOnly,
}

/// Records found after open, and how far each segment file has been read.
#[derive(Default)]
struct Later {
    segments: Vec<Segment>,
    index: DigestMap<(u32, u64)>,
    read_to: HashMap<PathBuf, usize>,
    /// The place in `segments` of each file mapped since open: a file that grew again is mapped
    /// anew in the same place (its offsets stay valid), so maps do not pile up.
    slot: HashMap<PathBuf, u32>,
}

/// What a raw file looked like when it was hashed. The device number is kept but not compared
/// (it is always 0 here): an NFS or Lustre mount has a different one on each node, while path,
/// inode, size and mtime are the same, so the memo a shard on one node wrote holds on the others.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
struct FileStamp {
    dev: u64,
    ino: u64,
    size: u64,
    mtime_ns: i64,
}

pub struct Store {
    pub root: PathBuf,
    writer_id: String,
    /// Our lease; gc's too when gc holds the store (dropped first: gc lets go before it leaves).
    gc_lease: Option<Lease>,
    /// Writers found dead at open (their leases then removed): their temp files elsewhere (in
    /// output folders) are abandoned too.
    dead_writers: std::collections::HashSet<String>,
    /// None for [`Access::ReadOnly`].
    writer_lease: Option<Lease>,
    read_only: bool,
    records: Mutex<Option<SegmentWriter>>,
    fp_writer: Mutex<Option<SegmentWriter>>,
    /// The records found at open: read without a lock (lookups are on the hot path).
    segments: Vec<Segment>,
    index: DigestMap<(u32, u64)>,
    /// Records other processes appended since, found by [`Store::refresh`].
    later: RwLock<Later>,
    fingerprints: RwLock<HashMap<PathBuf, (FileStamp, Digest)>>,
    tmp_counter: AtomicU64,
    /// Whether this process wrote a blob since its last `sync` (which then flushes them).
    unsynced_blobs: AtomicBool,
}

impl Store {
    /// Opens (creating if needed) the store at `root` and loads its record index and fingerprint memo.
    ///
    /// Refuses a store holding a segment that a newer dist4d wrote: reading it as empty would run
    /// again every task it records (and gc would delete it). Segments that are not dist4d's are
    /// left alone, with a warning.
    pub fn open(root: &Path, access: Access) -> Result<Store> {
        refuse_newer(root)?;
        if access == Access::ReadOnly {
            return Store::load(root, unique_writer_id(), None, None, Default::default());
        }
        for d in ["cas", "ac", "fp", "runs", "tmp", "leases"] {
            fs::create_dir_all(root.join(d))
                .with_context(|| format!("creating store directory {}", root.join(d).display()))?;
        }
        let writer_id = unique_writer_id();
        let leases = root.join("leases");
        let me = Holder::me(&writer_id);
        let writer_lease = Lease::create(&leases.join(format!("{writer_id}.lease")), &me)?
            .with_context(|| format!("writer id {writer_id} is taken in {}", leases.display()))?;
        let now = || lease::fs_now(writer_lease.path());
        let gc_path = leases.join("gc.lease");
        let gc_lease = match access {
            Access::Exclusive => {
                let gc = match lease::acquire(&gc_path, &me, now)? {
                    Ok(l) => l,
                    Err(h) => bail!("another gc ({}) is working on the store {}", h.describe(), root.display()),
                };
                let mut users = live_writers(&leases, &writer_id, now());
                // On a shared filesystem a run starting on another node now may not see gc's
                // lease yet, nor gc its lease (directory caches): gc waits them out and looks
                // again before it deletes anything.
                if users.is_empty() && lease::network_filesystem(root) {
                    eprintln!(
                        "gc: the store is on a network filesystem; waiting {:.0} s (the lease timeout) for every node's \
                         view of it to catch up",
                        lease::timeout().as_secs_f64()
                    );
                    std::thread::sleep(lease::timeout());
                    users = live_writers(&leases, &writer_id, now());
                }
                if !users.is_empty() {
                    bail!(
                        "{} other dist4d process{} using the store {} ({}); gc needs it alone: run it when they end",
                        users.len(),
                        if users.len() == 1 { " is" } else { "es are" },
                        root.display(),
                        users.iter().take(4).map(|h| h.describe()).collect::<Vec<_>>().join(", ")
                    );
                }
                Some(gc)
            }
            Access::Shared | Access::ReadOnly => {
                // Our lease is out first, so a gc starting now sees us and gives way; one that
                // already checked is waited for.
                let mut said = false;
                while let Liveness::Live(h) = lease::judge(&gc_path, now()) {
                    if !said {
                        eprintln!("waiting: gc ({}) is working on the store {}", h.describe(), root.display());
                        said = true;
                    }
                    std::thread::sleep(std::time::Duration::from_millis(250));
                }
                None
            }
        };
        let dead_writers = remove_abandoned(root, &writer_id, now());
        Store::load(root, writer_id, Some(writer_lease), gc_lease, dead_writers)
    }

    /// Reads the record index and the fingerprint memo.
    fn load(
        root: &Path,
        writer_id: String,
        writer_lease: Option<Lease>,
        gc_lease: Option<Lease>,
        dead_writers: std::collections::HashSet<String>,
    ) -> Result<Store> {
        let read_only = writer_lease.is_none();
        let mut segments: Vec<Segment> = Vec::new();
        let mut index = DigestMap::default();
        let mut later = Later::default();
        for path in segment_paths(&root.join("ac"))? {
            let seg = match Segment::open(&path) {
                Ok(seg) => seg,
                // Compacted away by a gc meanwhile (a reader holds no lease that would stop it).
                Err(_) if read_only && !path.exists() => continue,
                Err(e) => return Err(e),
            };
            if let Some(problem) = seg.header().problem() {
                eprintln!("warning: ignoring {}: it {problem}", path.display());
            }
            let si = segments.len() as u32;
            for (off, payload) in seg.entries() {
                let Some(key) = TaskRecord::key_of(payload) else { continue };
                // A key recorded twice (a task run again) is rare: only then is a record compared.
                let earlier = match index.get(&key) {
                    Some(&(s, o)) if s != si => segments[s as usize].payload_at(o as usize),
                    _ => None,
                };
                if earlier.is_none_or(|e| TaskRecord::supersedes(payload, e)) {
                    index.insert(key, (si, off as u64));
                }
            }
            // Later reads go on from the end of what reads in order (past a damaged entry, bytes
            // may be ones not seen yet): see `Segment::entries_from`.
            later.read_to.insert(path, seg.sound_prefix());
            segments.push(seg);
        }
        let fingerprints = load_fingerprints(&root.join("fp"))?;
        Ok(Store {
            root: root.to_path_buf(),
            writer_id,
            gc_lease,
            dead_writers,
            writer_lease,
            read_only,
            records: Mutex::new(None),
            fp_writer: Mutex::new(None),
            segments,
            index,
            later: RwLock::new(later),
            fingerprints: RwLock::new(fingerprints),
            tmp_counter: AtomicU64::new(0),
            unsynced_blobs: AtomicBool::new(false),
        })
    }

    /// Number of task records loaded at open.
    pub fn record_count(&self) -> usize {
        self.index.len()
    }

    /// The record of a task key, if a finished task with that key is in the store (found at
    /// open, or by a [`Store::refresh`] since).
    pub fn lookup(&self, key: &Digest) -> Option<TaskRecord> {
        if let Some(&(seg, off)) = self.index.get(key) {
            let payload = self.segments[seg as usize].payload_at(off as usize)?;
            return TaskRecord::decode(payload).ok();
        }
        let later = self.later.read().unwrap();
        let &(seg, off) = later.index.get(key)?;
        TaskRecord::decode(later.segments[seg as usize].payload_at(off as usize)?).ok()
    }

    /// Reads the records other processes appended since the store was opened (or last
    /// refreshed): a run that waited for another process to finish an item then finds that
    /// item's tasks cached. Returns how many records it found.
    pub fn refresh(&self) -> Result<usize> {
        let own = self.records.lock().unwrap().as_ref().map(|w| w.path().to_path_buf());
        let mut later = self.later.write().unwrap();
        let mut found = 0;
        for path in segment_paths(&self.root.join("ac"))? {
            if own.as_ref() == Some(&path) {
                continue;
            }
            let from = later.read_to.get(&path).copied().unwrap_or(0);
            // Opened anew, its length taken from the open file: on NFS, opening is what
            // revalidates a file another node appended to.
            let seg = match Segment::open_if_longer(&path, from) {
                Ok(Some(s)) => s,
                Ok(None) => continue,
                Err(_) if !path.exists() => continue, // compacted away by gc meanwhile
                Err(e) => return Err(e),
            };
            let mut end = from;
            let mut entries = Vec::new();
            for (off, payload) in seg.entries_from(from) {
                end = Segment::end_of(off, payload.len());
                if let Some(key) = TaskRecord::key_of(payload) {
                    entries.push((key, off as u64));
                }
            }
            if end == from {
                continue; // nothing new whole yet (a torn or unseen tail): no new map kept
            }
            let si = match later.slot.get(&path) {
                Some(&si) => {
                    later.segments[si as usize] = seg;
                    si
                }
                None => {
                    let si = later.segments.len() as u32;
                    later.segments.push(seg);
                    later.slot.insert(path.clone(), si);
                    si
                }
            };
            found += entries.len();
            for (key, off) in entries {
                later.index.insert(key, (si, off));
            }
            later.read_to.insert(path, end);
        }
        Ok(found)
    }

    /// Makes the task records this process appended durable and visible to other nodes (on
    /// NFS, another client sees appended bytes once they reach the server).
    pub fn sync_records(&self) -> Result<()> {
        match self.records.lock().unwrap().as_mut() {
            Some(w) => w.sync(),
            None => Ok(()),
        }
    }

    /// Claims `name` (an item of work) for this process until the claim is dropped;
    /// `Ok(Err(holder))` when a live process holds it (see [`lease::Claim`]).
    pub fn claim(&self, name: &str) -> Result<std::result::Result<lease::Claim, Holder>> {
        let leases = self.root.join("leases");
        lease::Claim::take(&leases.join("claims").join(format!("{name}.claim")), &leases, &self.holder(), self.fs_now())
    }

    /// Every record in the store, as loaded at open (for explain and gc).
    pub fn all_records(&self) -> impl Iterator<Item = (usize, &[u8])> + '_ {
        self.segments.iter().enumerate().flat_map(|(i, s)| s.entries().map(move |(_, p)| (i, p)))
    }

    pub fn append_record(&self, rec: &TaskRecord) -> Result<()> {
        self.writable()?;
        let mut w = self.records.lock().unwrap();
        if w.is_none() {
            *w = Some(SegmentWriter::create(&self.root.join("ac"), &self.writer_id)?);
        }
        let w = w.as_mut().unwrap();
        w.append(&rec.encode())?;
        // Hand the entry to the OS at once: a SIGKILL then loses nothing; an fsync per record
        // would cost more than most tasks, so durability against power loss is per `sync`.
        w.flush()
    }

    /// Makes this process's writes durable: the blobs (flushed with the whole filesystem, one
    /// syncfs), then this process's segments. Blobs are not fsynced one by one as they are
    /// written: on a busy disk an fsync per multi-megabyte blob kept workers waiting longer than
    /// the task took. They are still renamed into place whole, so a killed process leaves no
    /// half-written blob; after a power loss, a blob that did not reach the disk is missing or
    /// fails its digest check when read, and its task runs again like that of any lost blob.
    pub fn sync(&self) -> Result<()> {
        if self.unsynced_blobs.swap(false, Ordering::Relaxed) {
            sync_filesystem(&self.root.join("cas"))?;
        }
        for w in [&self.records, &self.fp_writer] {
            if let Some(w) = w.lock().unwrap().as_mut() {
                w.sync()?;
            }
        }
        Ok(())
    }

    pub fn blob_path(&self, d: &Digest) -> PathBuf {
        let hex = d.hex();
        self.root.join("cas").join(&hex[..2]).join(&hex[2..])
    }

    /// Whether the blob is there as a file (its bytes are checked when they are read).
    pub fn has_blob(&self, d: &Digest) -> bool {
        fs::metadata(self.blob_path(d)).is_ok_and(|m| m.is_file())
    }

    /// Stores bytes under their digest (once: an existing blob file is not rewritten), compressed
    /// when that pays (see [`crate::blob`]). Anything else in its place (a folder, say) is
    /// removed first, so that a store damaged that way heals.
    pub fn put_blob(&self, digest: &Digest, bytes: &[u8]) -> Result<()> {
        self.writable()?;
        let path = self.blob_path(digest);
        match fs::symlink_metadata(&path) {
            Ok(m) if m.is_file() => return Ok(()),
            Ok(m) if m.is_dir() => fs::remove_dir_all(&path),
            Ok(_) => fs::remove_file(&path),
            Err(_) => Ok(()),
        }
        .with_context(|| format!("removing {}, which is not a blob file", path.display()))?;
        // Not fsynced here: see `sync`.
        self.unsynced_blobs.store(true, Ordering::Relaxed);
        write_whole_via(&self.temp_path(), &path, blob::pack(bytes).file_bytes(), false)
    }

    /// Reads a blob and checks its digest: a corrupt blob is removed so that it is made again.
    /// A store opened [`Access::ReadOnly`] leaves a corrupt blob in place (it writes nothing).
    pub fn get_blob(&self, digest: &Digest) -> Result<Vec<u8>> {
        self.read_blob(digest).map_err(Unread::into_error)
    }

    /// [`Store::get_blob`], saying why a blob could not be read as a value: [`Unread::Lost`] (the
    /// scheduler runs the task that made it again) or [`Unread::Newer`] (a newer dist4d wrote it).
    pub fn read_blob(&self, digest: &Digest) -> std::result::Result<Vec<u8>, Unread> {
        read_checked(&self.blob_path(digest), digest, !self.read_only)
    }

    /// Fails for a store opened [`Access::ReadOnly`].
    fn writable(&self) -> Result<()> {
        if self.read_only {
            bail!("the store {} was opened read-only (by a command that only reads it)", self.root.display());
        }
        Ok(())
    }

    /// Whether the store was opened [`Access::ReadOnly`].
    pub fn read_only(&self) -> bool {
        self.read_only
    }

    /// Removes the temp files this process left in the store's `tmp/` and in `more` (an output
    /// folder's temp folder): a run that stops on an error (a full disk) must not leave its
    /// half-written files taking space until the lease timeout. Best effort.
    pub fn remove_own_temp_files(&self, more: &[PathBuf]) {
        let prefix = format!("{}-", self.writer_id);
        for dir in std::iter::once(self.root.join("tmp")).chain(more.iter().cloned()) {
            let Ok(rd) = fs::read_dir(&dir) else { continue };
            for e in rd.filter_map(|e| e.ok()) {
                if e.file_name().to_str().is_some_and(|n| n.starts_with(&prefix)) {
                    let _ = fs::remove_file(e.path());
                }
            }
        }
    }

    /// A path in `tmp/` unique to this process.
    pub fn temp_path(&self) -> PathBuf {
        let n = self.tmp_counter.fetch_add(1, Ordering::Relaxed);
        self.root.join("tmp").join(format!("{}-{n}.tmp", self.writer_id))
    }

    /// Writes a file whole or not at all: temp file in `tmp/`, fsync, rename.
    pub fn write_atomic(&self, dest: &Path, bytes: &[u8]) -> Result<()> {
        write_atomic_via(&self.temp_path(), dest, bytes)
    }

    /// The content digest of a raw input file, hashing it only when its (path, size, mtime, inode)
    /// is not in the memo. With `allow_hash` false, returns `None` instead of hashing.
    pub fn file_digest(&self, path: &Path, allow_hash: bool) -> Result<Option<Digest>> {
        // Regular files only: a FIFO or /dev/zero among a dataset's files must not hang the run.
        // (The errors leave the path to the callers, which name the file.)
        let (file, meta) = crate::regular_file::open(path)?;
        let stamp = FileStamp {
            dev: 0,
            ino: meta.ino(),
            size: meta.size(),
            mtime_ns: meta.mtime() * 1_000_000_000 + meta.mtime_nsec(),
        };
        if let Some((s, d)) = self.fingerprints.read().unwrap().get(path) {
            if *s == stamp {
                return Ok(Some(*d));
            }
        }
        if !allow_hash {
            return Ok(None);
        }
        let mut hasher = blake3::Hasher::new();
        // The file opened above, mapped (an empty file cannot be): no second open by path.
        if meta.len() > 0 {
            // SAFETY: the map is read while this function runs; a file changed meanwhile gives a
            // mixed digest, which the stamp check below keeps out of the memo.
            let map = unsafe { memmap2::Mmap::map(&file) }.with_context(|| format!("reading {}", path.display()))?;
            hasher.update(&map);
        }
        let digest = Digest(*hasher.finalize().as_bytes());
        // A file modified while it was hashed gets a new stamp; do not memoise a mixed read.
        let after = fs::metadata(path)?;
        let unchanged =
            after.mtime() * 1_000_000_000 + after.mtime_nsec() == stamp.mtime_ns && after.size() == stamp.size;
        if unchanged && self.read_only {
            // Kept in memory only: a reader writes nothing.
            self.fingerprints.write().unwrap().insert(path.to_path_buf(), (stamp, digest));
        } else if unchanged {
            let mut payload = Vec::new();
            enc::bytes(&mut payload, path.as_os_str().as_encoded_bytes());
            for x in [stamp.dev, stamp.ino, stamp.size, stamp.mtime_ns as u64] {
                enc::u64(&mut payload, x);
            }
            payload.extend_from_slice(&digest.0);
            let mut w = self.fp_writer.lock().unwrap();
            if w.is_none() {
                *w = Some(SegmentWriter::create(&self.root.join("fp"), &self.writer_id)?);
            }
            let w = w.as_mut().unwrap();
            w.append(&payload)?;
            w.flush()?;
            self.fingerprints.write().unwrap().insert(path.to_path_buf(), (stamp, digest));
        }
        Ok(Some(digest))
    }

    pub fn runs_dir(&self) -> PathBuf {
        self.root.join("runs")
    }

    /// Whether a temp file that writer `writer` left (in the store or an output folder) may be
    /// removed: its writer is dead on this host, or not live and the file is older than the
    /// lease timeout (a temp file younger than that may belong to a writer whose lease we cannot
    /// see yet, on another node).
    pub fn temp_abandoned(&self, writer: &str, path: &Path) -> bool {
        if self.dead_writers.contains(writer) {
            return true;
        }
        let now = self.fs_now();
        abandoned(&self.root.join("leases"), writer, path, now)
    }

    /// The time now on the store's filesystem clock (see [`lease::fs_now`]).
    pub fn fs_now(&self) -> std::time::SystemTime {
        match &self.writer_lease {
            Some(l) => lease::fs_now(l.path()),
            None => std::time::SystemTime::now(),
        }
    }

    /// Packs the file-fingerprint memo into one segment (one entry per path: the last one read),
    /// removing the segments it read. Every process that hashed a raw file left a segment of its
    /// own, and every process opening the store reads them all. For `gc`, which holds the store
    /// alone. Returns the number of entries kept.
    pub fn compact_fingerprints(&self) -> Result<usize> {
        let dir = self.root.join("fp");
        // Only segments it can read: one it cannot is left as it is.
        let old = removable_segments(&dir)?;
        if old.len() <= 1 {
            return Ok(0);
        }
        let mut latest: HashMap<Vec<u8>, Vec<u8>> = HashMap::new();
        for path in &old {
            let seg = Segment::open(path)?;
            for (_, payload) in seg.entries() {
                let Ok(file) = (enc::Reader { buf: payload }).bytes() else { continue };
                latest.insert(file.to_vec(), payload.to_vec());
            }
        }
        let mut w = SegmentWriter::create(&dir, &format!("gc-{}", self.writer_id))?;
        for payload in latest.values() {
            w.append(payload)?;
        }
        w.sync()?;
        for path in old {
            fs::remove_file(&path).with_context(|| format!("removing {}", path.display()))?;
        }
        Ok(latest.len())
    }

    /// Whether this process's lease was lost: another process judged it dead (it was stopped or
    /// its filesystem stalled for longer than the lease timeout) and may have taken over its
    /// work and removed its temp files. A run that sees this stops (see [`Lease::lost`]).
    pub fn lease_lost(&self) -> bool {
        self.writer_lease.as_ref().is_some_and(|l| l.lost())
    }

    /// This process, as its lease names it.
    pub fn holder(&self) -> Holder {
        Holder::me(&self.writer_id)
    }

    /// This process's unique writer id (names its segments and temp files).
    pub fn writer_id(&self) -> &str {
        &self.writer_id
    }
}

impl Drop for Store {
    fn drop(&mut self) {
        let _ = self.sync();
        // The gc lease first: our writer lease dropping after it means gc holds the store to the end.
        drop(self.gc_lease.take());
    }
}

/// Reads the blob file at `path`, unpacks it and checks its digest; a corrupt one is removed
/// ([`BlobError`]), one that a newer dist4d wrote is not ([`NewerBlob`]).
pub fn read_blob(path: &Path, digest: &Digest) -> std::result::Result<Vec<u8>, Unread> {
    read_checked(path, digest, true)
}

/// [`read_blob`], removing a corrupt blob only with `remove_corrupt`.
fn read_checked(path: &Path, digest: &Digest, remove_corrupt: bool) -> std::result::Result<Vec<u8>, Unread> {
    let lost = |problem: String| Unread::Lost(BlobError { digest: *digest, problem });
    let file = read_retrying(path).map_err(|e| lost(format!("cannot be read ({}): {e}", path.display())))?;
    match blob::unpack(file, digest) {
        Ok(bytes) => Ok(bytes),
        Err(why @ blob::Unreadable::Newer { .. }) => {
            Err(Unread::Newer(NewerBlob { digest: *digest, path: path.to_path_buf(), why }))
        }
        Err(why) if remove_corrupt => {
            let _ = fs::remove_file(path);
            Err(lost(format!("{why} and was removed ({})", path.display())))
        }
        Err(why) => Err(lost(format!("{why} ({})", path.display()))),
    }
}

/// Fails when a segment of the store at `root` (records or fingerprint memo) was written by a
/// newer dist4d, naming it.
fn refuse_newer(root: &Path) -> Result<()> {
    for dir in ["ac", "fp"] {
        for path in segment_paths(&root.join(dir))? {
            let mut head = [0u8; 8];
            let n = match File::open(&path).and_then(|mut f| std::io::Read::read(&mut f, &mut head)) {
                Ok(n) => n,
                // Compacted away by a gc since the listing: nothing of it to refuse.
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => continue,
                Err(e) => return Err(e).with_context(|| format!("reading {}", path.display())),
            };
            if let h @ crate::segment::Header::Newer(_) = crate::segment::Header::of(&head[..n]) {
                bail!(
                    "the store {} holds {}, which {}: this dist4d will not use the store (it would run again \
                     every task recorded there); use the newer dist4d, or give this one another --cache",
                    root.display(),
                    path.display(),
                    h.problem().unwrap_or_default()
                );
            }
        }
    }
    Ok(())
}

/// The segments in `dir` that compaction may remove once it has copied their entries: ours, or
/// torn before their first entry. A segment of a newer dist4d or of unknown format is left in
/// place (with a warning): what cannot be read is never deleted.
pub fn removable_segments(dir: &Path) -> Result<Vec<PathBuf>> {
    let mut out = Vec::new();
    for path in segment_paths(dir)? {
        let mut head = Vec::with_capacity(8);
        match File::open(&path).and_then(|f| std::io::Read::read_to_end(&mut std::io::Read::take(f, 8), &mut head)) {
            Ok(_) => {}
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => continue,
            Err(e) => return Err(e).with_context(|| format!("reading {}", path.display())),
        }
        match crate::segment::Header::of(&head) {
            crate::segment::Header::Current | crate::segment::Header::DamagedMagic | crate::segment::Header::Torn => {
                out.push(path)
            }
            h => eprintln!("warning: leaving {} as it is: it {}", path.display(), h.problem().unwrap_or_default()),
        }
    }
    Ok(out)
}

/// How long a read waits for a file that a record names but that is not there: on NFS, a
/// client's cached view of a directory may not yet show a file another node just renamed into
/// it. `DIST4D_READ_RETRY_MS`, else 1 s on a local filesystem and half the lease timeout on a
/// network one (NFS keeps directory attributes up to 30-60 s by default).
fn read_retry(path: &Path) -> std::time::Duration {
    static T: std::sync::OnceLock<Option<u64>> = std::sync::OnceLock::new();
    let set = *T.get_or_init(|| std::env::var("DIST4D_READ_RETRY_MS").ok().and_then(|s| s.trim().parse().ok()));
    match set {
        Some(ms) => std::time::Duration::from_millis(ms),
        None if path.parent().is_some_and(lease::network_filesystem) => lease::timeout() / 2,
        None => std::time::Duration::from_secs(1),
    }
}

/// Reads a file, retrying "not found" with backoff for [`read_retry`]: a blob that is still
/// missing then is missing (and its task runs again).
pub fn read_retrying(path: &Path) -> std::io::Result<Vec<u8>> {
    let started = std::time::Instant::now();
    let mut wait = std::time::Duration::from_millis(5);
    let mut bound = None;
    loop {
        match fs::read(path) {
            Err(e)
                if e.kind() == std::io::ErrorKind::NotFound
                    && started.elapsed() + wait <= *bound.get_or_insert_with(|| read_retry(path)) =>
            {
                std::thread::sleep(wait);
                wait = (wait * 2).min(std::time::Duration::from_secs(2));
            }
            other => return other,
        }
    }
}

/// Writes `bytes` to `tmp`, fsyncs, and renames it to `dest` (creating `dest`'s directory).
pub fn write_atomic_via(tmp: &Path, dest: &Path, bytes: &[u8]) -> Result<()> {
    write_whole_via(tmp, dest, bytes, true)
}

/// Flushes every dirty page of the filesystem that holds `path` (syncfs(2)).
pub fn sync_filesystem(path: &Path) -> Result<()> {
    use std::os::fd::AsRawFd;
    let dir = File::open(path).with_context(|| format!("opening {}", path.display()))?;
    // SAFETY: the descriptor is open for the duration of the call.
    if unsafe { libc::syncfs(dir.as_raw_fd()) } != 0 {
        return Err(std::io::Error::last_os_error())
            .with_context(|| format!("syncing the filesystem of {}", path.display()));
    }
    Ok(())
}

/// Asks the kernel to start writing a file's pages to disk now, without waiting for them
/// (sync_file_range WRITE): the data then goes out while the run computes, and the sync at its
/// end finds little left to wait for (a 240-image run waited 4.7 s in its final syncfs without
/// this). Best effort: an error (a filesystem without it) changes nothing.
fn start_writeback(f: &File) {
    use std::os::fd::AsRawFd;
    // SAFETY: the descriptor is open for the duration of the call.
    let _ = unsafe { libc::sync_file_range(f.as_raw_fd(), 0, 0, libc::SYNC_FILE_RANGE_WRITE) };
}

/// Writes `bytes` to `tmp` and renames it to `dest` (creating `dest`'s directory): the file
/// appears whole or not at all to other processes, and survives this one being killed. With
/// `durable`, also fsynced before the rename (survives a power loss); without, the caller
/// makes it durable later (see [`sync_filesystem`]).
pub fn write_whole_via(tmp: &Path, dest: &Path, bytes: &[u8], durable: bool) -> Result<()> {
    if let Some(dir) = dest.parent() {
        fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
    }
    write_whole_io(tmp, dest, bytes, durable).with_context(|| format!("writing {}", dest.display()))
}

/// [`write_whole_via`] into folders that exist, with the io error as it is: a caller may act on
/// its kind.
pub fn write_whole_io(tmp: &Path, dest: &Path, bytes: &[u8], durable: bool) -> std::io::Result<()> {
    let result = (|| -> std::io::Result<()> {
        let f = File::create(tmp)?;
        let direct = crate::direct_io::write_new(&f, bytes)?;
        if durable {
            f.sync_all()?;
        } else if !direct {
            start_writeback(&f);
        }
        // Closed before the rename: on NFS, closing is what sends the bytes to the server, so
        // another node that opens the new name reads them all.
        drop(f);
        fs::rename(tmp, dest)?;
        if durable {
            // The rename itself survives a power loss once its directory is synced.
            if let Some(dir) = dest.parent() {
                File::open(dir)?.sync_all()?;
            }
        }
        Ok(())
    })();
    if result.is_err() {
        let _ = fs::remove_file(tmp);
    }
    result
}

fn unique_writer_id() -> String {
    // Stores opened by threads of one process in the same clock tick (a coarse clock on CI
    // machines) got one id, and the second failed with "writer id is taken": the per-process
    // count makes them differ whatever the clock.
    static OPENED: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
    let nth = OPENED.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let nanos = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_nanos()).unwrap_or(0);
    let host = fs::read_to_string("/proc/sys/kernel/hostname").unwrap_or_default();
    let d = crate::digest::DigestBuilder::new("writer")
        .str(host.trim())
        .u64(std::process::id() as u64)
        .u64(nanos as u64)
        .u64(nth)
        .finish();
    format!("{}-{}", std::process::id(), &d.hex()[..10])
}

/// The writers other than `me` whose leases are live.
fn live_writers(leases: &Path, me: &str, now: std::time::SystemTime) -> Vec<Holder> {
    let Ok(rd) = fs::read_dir(leases) else { return Vec::new() };
    rd.filter_map(|e| e.ok())
        .filter_map(|e| {
            let name = e.file_name().to_str()?.to_string();
            let writer = name.strip_suffix(".lease")?;
            if writer == me || writer == "gc" {
                return None;
            }
            match lease::judge(&e.path(), now) {
                Liveness::Live(h) => Some(h),
                _ => None,
            }
        })
        .collect()
}

/// Whether writer `writer`'s temp file at `path` may go (see [`Store::temp_abandoned`]).
fn abandoned(leases: &Path, writer: &str, path: &Path, now: std::time::SystemTime) -> bool {
    match lease::judge(&leases.join(format!("{writer}.lease")), now) {
        Liveness::Live(_) => false,
        Liveness::Dead(Some(h)) if h.on_this_host() => true,
        _ => {
            let modified = fs::symlink_metadata(path).and_then(|m| m.modified()).unwrap_or(now);
            now.duration_since(modified).is_ok_and(|age| age > lease::timeout())
        }
    }
}

/// Removes what dead writers left: their temp files and their leases (older dist4d versions'
/// `tmp/*.lock` files too). Best effort: a file another process removes first is no matter.
/// Returns the writers whose leases it found dead.
fn remove_abandoned(root: &Path, me: &str, now: std::time::SystemTime) -> std::collections::HashSet<String> {
    let leases = root.join("leases");
    let mut dead = std::collections::HashSet::new();
    if let Ok(rd) = fs::read_dir(root.join("tmp")) {
        for e in rd.filter_map(|e| e.ok()) {
            let p = e.path();
            let Some(name) = p.file_name().and_then(|n| n.to_str()) else { continue };
            let stem = name.strip_suffix(".tmp").or_else(|| name.strip_suffix(".lock")).unwrap_or(name);
            let writer = if name.ends_with(".lock") { stem } else { stem.rsplit_once('-').map_or(stem, |(w, _)| w) };
            if writer != me && abandoned(&leases, writer, &p, now) {
                let _ = fs::remove_file(&p);
            }
        }
    }
    if let Ok(rd) = fs::read_dir(&leases) {
        for e in rd.filter_map(|e| e.ok()) {
            let p = e.path();
            if p.extension().is_some_and(|x| x == "lease") && matches!(lease::judge(&p, now), Liveness::Dead(_)) {
                let _ = fs::remove_file(&p);
                if let Some(writer) = p.file_stem().and_then(|s| s.to_str()) {
                    dead.insert(writer.to_string());
                }
            }
        }
    }
    dead
}

fn load_fingerprints(dir: &Path) -> Result<HashMap<PathBuf, (FileStamp, Digest)>> {
    let mut out = HashMap::new();
    for path in segment_paths(dir)? {
        let seg = match Segment::open(&path) {
            Ok(seg) => seg,
            Err(_) if !path.exists() => continue, // compacted away by a gc meanwhile
            Err(e) => return Err(e),
        };
        for (_, payload) in seg.entries() {
            let mut r = enc::Reader { buf: payload };
            let parsed = (|| -> Result<(PathBuf, FileStamp, Digest)> {
                use std::os::unix::ffi::OsStrExt;
                let p = PathBuf::from(std::ffi::OsStr::from_bytes(r.bytes()?));
                let _dev = r.u64()?;
                let stamp = FileStamp { dev: 0, ino: r.u64()?, size: r.u64()?, mtime_ns: r.u64()? as i64 };
                Ok((p, stamp, Digest(r.take(32)?.try_into()?)))
            })();
            if let Ok((p, s, d)) = parsed {
                out.insert(p, (s, d));
            }
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::item::ItemKey;
    use crate::record::OutputRef;

    #[test]
    fn stores_opened_at_once_by_threads_of_one_process_get_distinct_writer_ids() {
        // CI hung when two threads opened a store in one clock tick: the same id, "writer id is
        // taken", and a test barrier waiting for the thread that had panicked.
        let ids: std::collections::HashSet<String> = std::thread::scope(|scope| {
            let handles: Vec<_> =
                (0..16).map(|_| scope.spawn(|| (0..64).map(|_| unique_writer_id()).collect::<Vec<_>>())).collect();
            handles.into_iter().flat_map(|h| h.join().unwrap()).collect()
        });
        assert_eq!(ids.len(), 16 * 64);
        let dir = tempfile::tempdir().unwrap();
        let stores: Vec<Store> = std::thread::scope(|scope| {
            let handles: Vec<_> =
                (0..8).map(|_| scope.spawn(|| Store::open(dir.path(), Access::Shared).unwrap())).collect();
            handles.into_iter().map(|h| h.join().unwrap()).collect()
        });
        let writers: std::collections::HashSet<&str> = stores.iter().map(|s| s.writer_id()).collect();
        assert_eq!(writers.len(), 8);
    }

    fn record(key: &[u8]) -> TaskRecord {
        TaskRecord {
            key: Digest::of(key),
            stage: "s".into(),
            item: ItemKey::new(&[0]),
            kind: "K".into(),
            version: 1,
            params: Digest::of(b"()"),
            inputs: vec![],
            outputs: vec![OutputRef {
                digest: Digest::of(b"x"),
                size: 1,
                inline: Some(std::sync::Arc::from(&b"x"[..])),
            }],
            finished_ms: 0,
            micros: 0,
        }
    }

    #[test]
    fn records_written_by_one_process_are_found_by_the_next() {
        let dir = tempfile::tempdir().unwrap();
        {
            let s = Store::open(dir.path(), Access::Shared).unwrap();
            s.append_record(&record(b"a")).unwrap();
            s.append_record(&record(b"b")).unwrap();
        }
        let s = Store::open(dir.path(), Access::Shared).unwrap();
        assert_eq!(s.record_count(), 2);
        assert_eq!(s.lookup(&Digest::of(b"a")).unwrap(), record(b"a"));
        assert!(s.lookup(&Digest::of(b"c")).is_none());
    }

    #[test]
    fn of_two_records_of_one_key_the_later_is_used_whatever_the_segment_order() {
        let dir = tempfile::tempdir().unwrap();
        let with = |key: &[u8], finished_ms: u64, out: &[u8]| TaskRecord {
            finished_ms,
            outputs: vec![OutputRef { digest: Digest::of(out), size: 1, inline: Some(std::sync::Arc::from(out)) }],
            ..record(key)
        };
        // Two writers (two segments, named in no particular order); for key a the newer record is
        // written first, for key b last.
        for (a, b) in [(2000, 1000), (1000, 2000)] {
            let s = Store::open(dir.path(), Access::Shared).unwrap();
            s.append_record(&with(b"a", a, if a > b { b"new" } else { b"old" })).unwrap();
            s.append_record(&with(b"b", b, if b > a { b"new" } else { b"old" })).unwrap();
        }
        let s = Store::open(dir.path(), Access::Shared).unwrap();
        for key in [b"a", b"b"] {
            let found = s.lookup(&Digest::of(key)).unwrap();
            assert_eq!((found.finished_ms, found.outputs[0].digest), (2000, Digest::of(b"new")));
        }
    }

    #[test]
    fn a_file_that_appears_late_is_read_and_a_missing_one_fails_in_bounded_time() {
        let dir = tempfile::tempdir().unwrap();
        let late = dir.path().join("late");
        let writer = {
            let late = late.clone();
            std::thread::spawn(move || {
                std::thread::sleep(std::time::Duration::from_millis(100));
                fs::write(late, b"here").unwrap();
            })
        };
        assert_eq!(read_retrying(&late).unwrap(), b"here");
        writer.join().unwrap();
        let started = std::time::Instant::now();
        let e = read_retrying(&dir.path().join("never")).unwrap_err();
        assert_eq!(e.kind(), std::io::ErrorKind::NotFound);
        assert!(started.elapsed() <= read_retry(&dir.path().join("never")) + std::time::Duration::from_millis(500));
    }

    #[test]
    fn blobs_are_checked_on_read() {
        let dir = tempfile::tempdir().unwrap();
        let s = Store::open(dir.path(), Access::Shared).unwrap();
        let d = Digest::of(b"hello");
        s.put_blob(&d, b"hello").unwrap();
        assert_eq!(s.get_blob(&d).unwrap(), b"hello");
        fs::write(s.blob_path(&d), b"jello").unwrap();
        let e = s.get_blob(&d).unwrap_err().to_string();
        assert!(e.contains("corrupt"), "{e}");
        assert!(!s.has_blob(&d));
    }

    #[test]
    fn blobs_are_kept_compressed_or_raw_and_read_back_the_same() {
        let dir = tempfile::tempdir().unwrap();
        let s = Store::open(dir.path(), Access::Shared).unwrap();
        let floats: Vec<u8> = (0..50_000).flat_map(|i| (1.0 + i as f32 * 1e-3).to_le_bytes()).collect();
        let d = Digest::of(&floats);
        s.put_blob(&d, &floats).unwrap();
        let on_disk = fs::read(s.blob_path(&d)).unwrap();
        assert!(on_disk.starts_with(&blob::MAGIC) && on_disk.len() < floats.len() / 2, "{}", on_disk.len());
        assert!(s.get_blob(&d).unwrap() == floats);
        // Bytes that do not compress are kept as they are (an export can reflink them).
        let noise = blob::tests::noise(20_000);
        let n = Digest::of(&noise);
        s.put_blob(&n, &noise).unwrap();
        assert!(fs::read(s.blob_path(&n)).unwrap() == noise);
        assert!(blob::is_raw_file(&s.blob_path(&n)));
        assert!(s.get_blob(&n).unwrap() == noise);
    }

    #[test]
    fn blobs_of_a_store_from_before_compression_still_read() {
        let dir = tempfile::tempdir().unwrap();
        let s = Store::open(dir.path(), Access::Shared).unwrap();
        // An older dist4d wrote every blob raw, compressible or not.
        let old = "(min_depth:1.0,max_depth:80.0)".repeat(100).into_bytes();
        let d = Digest::of(&old);
        let path = s.blob_path(&d);
        fs::create_dir_all(path.parent().unwrap()).unwrap();
        fs::write(&path, &old).unwrap();
        assert_eq!(s.get_blob(&d).unwrap(), old);
        s.put_blob(&d, &old).unwrap();
        assert_eq!(fs::read(&path).unwrap(), old, "an existing blob is not rewritten");
    }

    #[test]
    fn a_corrupt_compressed_blob_is_found_and_removed() {
        let dir = tempfile::tempdir().unwrap();
        let s = Store::open(dir.path(), Access::Shared).unwrap();
        let text = "the same line, again and again\n".repeat(500).into_bytes();
        let d = Digest::of(&text);
        s.put_blob(&d, &text).unwrap();
        let path = s.blob_path(&d);
        let mut file = fs::read(&path).unwrap();
        assert!(file.starts_with(&blob::MAGIC));
        let at = file.len() - 5;
        file[at] ^= 0xff;
        fs::write(&path, &file).unwrap();
        let e = s.read_blob(&d).unwrap_err();
        assert!(matches!(e, Unread::Lost(_)), "{e:#}");
        assert!(e.to_string().contains("corrupt"), "{e}");
        assert!(!s.has_blob(&d), "removed, so that its task runs again");
    }

    #[test]
    fn a_blob_a_newer_dist4d_wrote_is_left_in_place() {
        let dir = tempfile::tempdir().unwrap();
        let s = Store::open(dir.path(), Access::Shared).unwrap();
        let text = "a line a newer dist4d packs its own way\n".repeat(500).into_bytes();
        let d = Digest::of(&text);
        s.put_blob(&d, &text).unwrap();
        let path = s.blob_path(&d);
        let mut file = fs::read(&path).unwrap();
        file[4] = 9;
        fs::write(&path, &file).unwrap();
        let Unread::Newer(newer) = s.read_blob(&d).unwrap_err() else { panic!("not a blob to remake") };
        let e = s.get_blob(&d).unwrap_err();
        assert_eq!(newer.why, blob::Unreadable::Newer { codec: 9 });
        assert!(e.to_string().contains("was written by a newer dist4d (blob codec 9"), "{e}");
        assert_eq!(fs::read(&path).unwrap(), file, "neither removed nor rewritten");
        s.put_blob(&d, &text).unwrap();
        assert_eq!(fs::read(&path).unwrap(), file);
    }

    #[test]
    fn a_segment_a_newer_dist4d_wrote_refuses_the_store_and_a_foreign_one_is_left_alone() {
        let dir = tempfile::tempdir().unwrap();
        {
            let s = Store::open(dir.path(), Access::Shared).unwrap();
            s.append_record(&record(b"a")).unwrap();
        }
        fs::write(dir.path().join("ac/foreign.seg"), b"not a segment at all").unwrap();
        let s = Store::open(dir.path(), Access::Shared).unwrap();
        assert_eq!(s.record_count(), 1, "a foreign file is ignored (with a warning)");
        drop(s);
        assert_eq!(removable_segments(&dir.path().join("ac")).unwrap().len(), 1, "and never removed");
        fs::write(dir.path().join("fp/later.seg"), b"D4SEG03\n\x05\x00\x00\x00").unwrap();
        for access in [Access::Shared, Access::Exclusive, Access::ReadOnly] {
            let e = Store::open(dir.path(), access).err().expect("refused").to_string();
            assert!(e.contains("later.seg, which was written by a newer dist4d (segment format 03"), "{e}");
        }
    }

    #[test]
    fn a_read_only_open_writes_nothing() {
        let dir = tempfile::tempdir().unwrap();
        let raw = dir.path().join("raw.bin");
        fs::write(&raw, b"raw").unwrap();
        let root = dir.path().join("store");
        {
            let s = Store::open(&root, Access::Shared).unwrap();
            s.append_record(&record(b"a")).unwrap();
            s.put_blob(&Digest::of(b"hello"), b"hello").unwrap();
        }
        let listing = |p: &Path| -> Vec<PathBuf> {
            let mut out = Vec::new();
            let mut stack = vec![p.to_path_buf()];
            while let Some(d) = stack.pop() {
                for e in fs::read_dir(&d).unwrap() {
                    let p = e.unwrap().path();
                    if p.is_dir() {
                        stack.push(p.clone());
                    }
                    out.push(p);
                }
            }
            out.sort();
            out
        };
        let before = listing(&root);
        let s = Store::open(&root, Access::ReadOnly).unwrap();
        assert!(s.read_only());
        assert_eq!(s.lookup(&Digest::of(b"a")).unwrap(), record(b"a"));
        assert_eq!(s.get_blob(&Digest::of(b"hello")).unwrap(), b"hello");
        let blob = s.blob_path(&Digest::of(b"hello"));
        fs::write(&blob, b"jello").unwrap();
        assert!(s.get_blob(&Digest::of(b"hello")).unwrap_err().to_string().contains("is corrupt"));
        assert!(blob.exists(), "a reader removes nothing, not even a corrupt blob");
        assert_eq!(s.file_digest(&raw, true).unwrap(), Some(Digest::of(b"raw")));
        assert_eq!(s.file_digest(&raw, false).unwrap(), Some(Digest::of(b"raw")), "memoised in memory");
        assert!(s.put_blob(&Digest::of(b"x"), b"x").is_err());
        assert!(s.append_record(&record(b"b")).is_err());
        assert!(!s.lease_lost());
        drop(s);
        assert_eq!(listing(&root), before, "no lease, no memo segment, no directory");
        // A store that is not there reads as empty, and is not created.
        let none = Store::open(&dir.path().join("none"), Access::ReadOnly).unwrap();
        assert_eq!(none.record_count(), 0);
        assert!(!dir.path().join("none").exists());
    }

    #[test]
    fn file_digests_are_memoised_and_follow_content() {
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("raw.bin");
        fs::write(&f, b"one").unwrap();
        let s = Store::open(&dir.path().join("store"), Access::Shared).unwrap();
        assert_eq!(s.file_digest(&f, false).unwrap(), None);
        let d1 = s.file_digest(&f, true).unwrap().unwrap();
        assert_eq!(d1, Digest::of(b"one"));
        drop(s);
        let s = Store::open(&dir.path().join("store"), Access::Shared).unwrap();
        assert_eq!(s.file_digest(&f, false).unwrap(), Some(d1), "memo survives reopening");
        std::thread::sleep(std::time::Duration::from_millis(10));
        fs::write(&f, b"two").unwrap();
        assert_eq!(s.file_digest(&f, false).unwrap(), None, "a changed file is hashed again");
        assert_eq!(s.file_digest(&f, true).unwrap(), Some(Digest::of(b"two")));
    }

    #[test]
    fn the_fingerprint_memo_of_many_processes_packs_into_one_segment() {
        let dir = tempfile::tempdir().unwrap();
        let files: Vec<PathBuf> = (0..3).map(|i| dir.path().join(format!("raw{i}.bin"))).collect();
        for (i, f) in files.iter().enumerate() {
            fs::write(f, format!("raw {i}")).unwrap();
            // Each file hashed by a process of its own: three memo segments.
            let s = Store::open(&dir.path().join("store"), Access::Shared).unwrap();
            s.file_digest(f, true).unwrap();
        }
        assert_eq!(segment_paths(&dir.path().join("store/fp")).unwrap().len(), 3);
        let s = Store::open(&dir.path().join("store"), Access::Exclusive).unwrap();
        assert_eq!(s.compact_fingerprints().unwrap(), 3);
        drop(s);
        assert_eq!(segment_paths(&dir.path().join("store/fp")).unwrap().len(), 1);
        let s = Store::open(&dir.path().join("store"), Access::Shared).unwrap();
        for (i, f) in files.iter().enumerate() {
            let known = s.file_digest(f, false).unwrap();
            assert_eq!(known, Some(Digest::of(format!("raw {i}").as_bytes())), "memo kept for {}", f.display());
        }
    }

    #[test]
    fn temp_files_of_dead_writers_are_removed() {
        let dir = tempfile::tempdir().unwrap();
        let (tmp, leases) = (dir.path().join("tmp"), dir.path().join("leases"));
        fs::create_dir_all(&tmp).unwrap();
        fs::create_dir_all(&leases).unwrap();
        // A writer killed on this host: its lease names a process that is gone.
        let mut child = std::process::Command::new("true").spawn().unwrap();
        let dead_pid = child.id();
        child.wait().unwrap();
        let dead = Holder { pid: dead_pid, ..Holder::me("dead-1") }.encode();
        fs::write(leases.join("dead-1.lease"), dead).unwrap();
        fs::write(tmp.join("dead-1-3.tmp"), b"half").unwrap();
        // A temp file whose writer has no lease: young, it stays (its writer may be on another
        // node whose lease we do not see yet); older than the lease timeout, it goes.
        fs::write(tmp.join("unknown-7-1.tmp"), b"young").unwrap();
        fs::write(tmp.join("unknown-8-1.tmp"), b"old").unwrap();
        let old = std::time::SystemTime::now() - lease::timeout() * 2;
        File::options().write(true).open(tmp.join("unknown-8-1.tmp")).unwrap().set_modified(old).unwrap();
        let live = Store::open(dir.path(), Access::Shared).unwrap();
        let live_tmp = live.temp_path();
        fs::write(&live_tmp, b"mine").unwrap();
        assert!(!tmp.join("dead-1-3.tmp").exists());
        assert!(!leases.join("dead-1.lease").exists(), "a dead writer's lease goes too");
        assert!(
            live.temp_abandoned("dead-1", &dir.path().join("out/.dist4d-tmp/dead-1-manifest1")),
            "and its temp files in output folders are known abandoned once its lease is gone"
        );
        assert!(tmp.join("unknown-7-1.tmp").exists());
        assert!(!tmp.join("unknown-8-1.tmp").exists());
        let _other = Store::open(dir.path(), Access::Shared).unwrap();
        assert!(live_tmp.exists(), "a live writer's temp files stay");
        let e = Store::open(dir.path(), Access::Exclusive).err().expect("gc waits for runs to end").to_string();
        assert!(e.contains("2 other dist4d processes are using the store") && e.contains("gc needs it alone"), "{e}");
        assert!(!leases.join("gc.lease").exists(), "a gc that gave way leaves no lease");
    }

    #[test]
    fn a_run_waits_for_a_gc_and_a_gc_refuses_a_second_gc() {
        let dir = tempfile::tempdir().unwrap();
        let gc = Store::open(dir.path(), Access::Exclusive).unwrap();
        let e = Store::open(dir.path(), Access::Exclusive).err().unwrap().to_string();
        assert!(e.contains("another gc (pid"), "{e}");
        let (tx, rx) = std::sync::mpsc::channel();
        let root = dir.path().to_path_buf();
        let t = std::thread::spawn(move || {
            let s = Store::open(&root, Access::Shared).unwrap();
            tx.send(()).unwrap();
            drop(s);
        });
        assert!(rx.recv_timeout(std::time::Duration::from_millis(600)).is_err(), "the run waits for gc");
        drop(gc);
        rx.recv_timeout(std::time::Duration::from_secs(5)).expect("and goes on once gc is done");
        t.join().unwrap();
    }

    #[test]
    fn stores_opened_at_once_each_keep_their_lease() {
        // A store opening judges writers dead and removes their leases; one that had just
        // created its lease must never be among them (with flock it once was), or its temp
        // files (in the store and in output folders) would be removed under it.
        let dir = tempfile::tempdir().unwrap();
        std::thread::scope(|scope| {
            for _ in 0..4 {
                scope.spawn(|| {
                    for _ in 0..100 {
                        let s = Store::open(dir.path(), Access::Shared).unwrap();
                        let lease = dir.path().join("leases").join(format!("{}.lease", s.writer_id()));
                        assert!(lease.exists(), "{} lost its lease", s.writer_id());
                        let other = Store::open(dir.path(), Access::Shared).unwrap();
                        let judged = lease::judge(&lease, other.fs_now());
                        assert!(matches!(judged, Liveness::Live(_)), "{} judged dead while open", s.writer_id());
                    }
                });
            }
        });
    }
}
