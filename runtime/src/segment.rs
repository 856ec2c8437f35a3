//! Append-only segment files of checksummed entries.
//!
//! Small records (task records, file fingerprints) are packed into segments instead of one file
//! each: two million 4 KiB files would waste gigabytes. Each process appends to segments of its
//! own (named by a unique writer id), so concurrent processes on one store never write the same
//! file. An entry is `len: u32 | crc32(payload): u32 | payload`; a process killed mid-append
//! leaves a torn last entry, which fails its checksum and is ignored by readers.
//!
//! A segment begins with `D4SEG` and a two-digit format version (`D4SEG01\n`). A segment of a
//! later version was written by a newer dist4d: readers say so ([`Header::Newer`]) instead of
//! taking it for an empty or foreign file, so that a store is never silently recomputed, nor its
//! newer records deleted by gc. One flipped bit in `D4SEG` or the newline (not in the version) is
//! damage to one of ours: it is read as ours.
//!
//! An entry that fails its checksum in the middle of a segment (a flipped bit, a bad sector)
//! costs that entry only: a full read ([`Segment::entries`]) scans on from it for the next
//! offset where a whole entry checks out (a length no larger than [`MAX_ENTRY`] whose payload
//! matches its CRC32), so the records after it are recovered.

use anyhow::{Context, Result};
use memmap2::Mmap;
use std::fs::{File, OpenOptions};
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

const MAGIC: &[u8; 8] = b"D4SEG01\n";
/// The format version this dist4d writes and reads (the digits of [`MAGIC`]).
pub const VERSION: u32 = 1;
/// Entries larger than this are treated as corruption (a torn length field).
pub const MAX_ENTRY: u32 = 64 << 20;

/// What the first bytes of a segment file say about it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Header {
    /// Ours: its entries can be read.
    Current,
    /// Ours with one bit of `D4SEG` or of the newline flipped (the version digits exact): read as
    /// ours, reported as damage by [`Segment::check`].
    DamagedMagic,
    /// Empty, or cut inside the magic (a writer killed before its first entry): no entries, and
    /// nothing lost by removing it.
    Torn,
    /// `D4SEG` and a version greater than [`VERSION`]: a newer dist4d wrote it. Never read as
    /// empty nor removed.
    Newer(u32),
    /// Anything else (not a dist4d segment, or one whose header is damaged): not read, never
    /// removed.
    Unknown,
}

impl Header {
    pub fn of(bytes: &[u8]) -> Header {
        if bytes.starts_with(MAGIC) {
            return Header::Current;
        }
        if bytes.len() < MAGIC.len() && MAGIC.starts_with(bytes) {
            return Header::Torn;
        }
        if let Some(h) = bytes.get(..MAGIC.len()).filter(|h| h[5..7] == MAGIC[5..7]) {
            let flipped: u32 = h.iter().zip(MAGIC).map(|(a, b)| (a ^ b).count_ones()).sum();
            if flipped == 1 {
                return Header::DamagedMagic;
            }
        }
        let version = bytes
            .get(..MAGIC.len())
            .filter(|h| h.starts_with(b"D4SEG") && h[7] == b'\n' && h[5..7].iter().all(u8::is_ascii_digit))
            .map(|h| u32::from(h[5] - b'0') * 10 + u32::from(h[6] - b'0'));
        match version {
            Some(v) if v > VERSION => Header::Newer(v),
            _ => Header::Unknown,
        }
    }

    /// Why a store cannot use a segment with this header, if it cannot (for messages naming the file).
    pub fn problem(&self) -> Option<String> {
        match self {
            Header::Current | Header::DamagedMagic | Header::Torn => None,
            Header::Newer(v) => Some(format!(
                "was written by a newer dist4d (segment format {v:02}; this dist4d reads format {VERSION:02})"
            )),
            Header::Unknown => Some("does not begin with a dist4d segment header (D4SEGnn)".into()),
        }
    }
}

/// Appends entries to one segment file.
pub struct SegmentWriter {
    path: PathBuf,
    out: BufWriter<File>,
    unflushed: usize,
}

impl SegmentWriter {
    /// Creates `dir/<name>.seg`; the name must be unique to this writer.
    pub fn create(dir: &Path, name: &str) -> Result<SegmentWriter> {
        std::fs::create_dir_all(dir).with_context(|| format!("creating {}", dir.display()))?;
        let path = dir.join(format!("{name}.seg"));
        let file = OpenOptions::new()
            .create_new(true)
            .append(true)
            .open(&path)
            .with_context(|| format!("creating segment {}", path.display()))?;
        let mut out = BufWriter::with_capacity(64 << 10, file);
        out.write_all(MAGIC)?;
        Ok(SegmentWriter { path, out, unflushed: 0 })
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    pub fn append(&mut self, payload: &[u8]) -> Result<()> {
        let mut head = [0u8; 8];
        head[..4].copy_from_slice(&(payload.len() as u32).to_le_bytes());
        head[4..].copy_from_slice(&crc32fast::hash(payload).to_le_bytes());
        // A full buffer is written out here: an error then (a full disk) names the file.
        self.out
            .write_all(&head)
            .and_then(|_| self.out.write_all(payload))
            .with_context(|| format!("writing {}", self.path.display()))?;
        self.unflushed += 1;
        Ok(())
    }

    /// Hands buffered entries to the OS, so that they survive the process being killed.
    pub fn flush(&mut self) -> Result<()> {
        if self.unflushed > 0 {
            self.out.flush().with_context(|| format!("writing {}", self.path.display()))?;
            self.unflushed = 0;
        }
        Ok(())
    }

    /// Flushes and fsyncs, so that entries survive a power loss too.
    pub fn sync(&mut self) -> Result<()> {
        self.flush()?;
        self.out.get_ref().sync_data().with_context(|| format!("syncing {}", self.path.display()))
    }
}

/// A mapped segment file, read entry by entry.
pub struct Segment {
    pub path: PathBuf,
    map: Option<Mmap>,
}

impl Segment {
    pub fn open(path: &Path) -> Result<Segment> {
        Ok(Segment::open_if_longer(path, 0)?.unwrap_or(Segment { path: path.to_path_buf(), map: None }))
    }

    /// The segment at `path` if its file is longer than `than` bytes (`None` otherwise, without
    /// mapping it).
    pub fn open_if_longer(path: &Path, than: usize) -> Result<Option<Segment>> {
        let file = File::open(path).with_context(|| format!("opening segment {}", path.display()))?;
        // The length of the opened file (on NFS, opening revalidates it; a path stat may not).
        let len = file.metadata()?.len();
        if than > 0 && len as usize <= than {
            return Ok(None);
        }
        // An empty file cannot be mapped; it has no entries anyway.
        let map = if len == 0 {
            None
        } else {
            Some(unsafe { Mmap::map(&file) }.with_context(|| format!("mapping {}", path.display()))?)
        };
        Ok(Some(Segment { path: path.to_path_buf(), map }))
    }

    fn bytes(&self) -> &[u8] {
        self.map.as_deref().unwrap_or(&[])
    }

    /// What the segment's header says about it.
    pub fn header(&self) -> Header {
        Header::of(self.bytes())
    }

    /// Every valid entry as (offset of payload, payload). A damaged entry is skipped: the scan
    /// goes on at the next offset where a whole entry checks out (see the module doc).
    pub fn entries(&self) -> Entries<'_> {
        Entries::new(self.bytes(), 0, true)
    }

    /// Valid entries from byte offset `from`, which is 0 (the first entry) or the end of an
    /// entry ([`Segment::end_of`]): what a writer appended since the segment was last read.
    /// Stops at the first entry that does not check out: past the end of what was read, that is
    /// most often bytes not yet seen (zeros on NFS, a torn tail), which a later read will find
    /// whole; skipping ahead would lose them.
    pub fn entries_from(&self, from: usize) -> Entries<'_> {
        Entries::new(self.bytes(), from, false)
    }

    /// What a full read finds: for `verify --store`.
    pub fn check(&self) -> Check {
        let mut it = self.entries();
        let (mut entries, mut end) = (0, MAGIC.len().min(self.bytes().len()));
        for (off, payload) in it.by_ref() {
            entries += 1;
            end = Self::end_of(off, payload.len());
        }
        let mut damaged = it.skipped;
        if self.header() == Header::DamagedMagic {
            damaged.insert(0, (0, MAGIC.len()));
        }
        Check { header: self.header(), entries, damaged, tail: self.bytes().len().saturating_sub(end) }
    }

    /// The end of the entries read in order from the start before the first damaged one: how far
    /// a reader that does not skip ([`Segment::entries_from`]) has read the segment.
    pub fn sound_prefix(&self) -> usize {
        let mut end = MAGIC.len();
        for (off, payload) in self.entries_from(0) {
            end = Self::end_of(off, payload.len());
        }
        end
    }

    /// The byte offset just past the entry whose payload starts at `offset` and is `len` long.
    pub fn end_of(offset: usize, len: usize) -> usize {
        offset + len
    }

    /// The payload at an offset returned by [`Segment::entries`].
    pub fn payload_at(&self, offset: usize) -> Option<&[u8]> {
        let bytes = self.bytes();
        let len = u32::from_le_bytes(bytes.get(offset - 8..offset - 4)?.try_into().ok()?) as usize;
        bytes.get(offset..offset + len)
    }
}

/// What [`Segment::check`] found.
#[derive(Debug, PartialEq, Eq)]
pub struct Check {
    pub header: Header,
    /// Valid entries.
    pub entries: usize,
    /// Damaged stretches (start, end) that valid entries follow: what is lost is in them.
    pub damaged: Vec<(usize, usize)>,
    /// Bytes past the last valid entry: a torn last entry (a killed writer), or damage there.
    pub tail: usize,
}

/// The valid entries of a segment, in order: see [`Segment::entries`] and [`Segment::entries_from`].
pub struct Entries<'a> {
    bytes: &'a [u8],
    pos: usize,
    /// Whether to scan past a damaged entry for the next valid one.
    resync: bool,
    /// Damaged stretches skipped so far (start, end).
    skipped: Vec<(usize, usize)>,
}

impl<'a> Entries<'a> {
    fn new(bytes: &'a [u8], from: usize, resync: bool) -> Entries<'a> {
        // A segment that is not ours (a newer or foreign header) has no entries we can read.
        let ours = matches!(Header::of(bytes), Header::Current | Header::DamagedMagic);
        let pos = if ours { from.max(MAGIC.len()) } else { bytes.len() };
        Entries { bytes, pos, resync, skipped: Vec::new() }
    }

    /// The entry at `pos` as (payload start, payload) if it checks out.
    fn at(&self, pos: usize) -> Option<(usize, &'a [u8])> {
        let bytes = self.bytes;
        let head = bytes.get(pos..pos + 8)?;
        let len = u32::from_le_bytes([head[0], head[1], head[2], head[3]]);
        let crc = u32::from_le_bytes([head[4], head[5], head[6], head[7]]);
        let start = pos + 8;
        // No writer appends an empty entry: zeros are a gap (bytes another node wrote not
        // yet seen, on NFS), not an entry, whose checksum would pass (crc32 of nothing is 0).
        if len == 0 || len > MAX_ENTRY || start + len as usize > bytes.len() {
            return None;
        }
        let payload = &bytes[start..start + len as usize];
        (crc32fast::hash(payload) == crc).then_some((start, payload))
    }
}

impl<'a> Iterator for Entries<'a> {
    type Item = (usize, &'a [u8]);

    fn next(&mut self) -> Option<Self::Item> {
        if self.pos + 8 > self.bytes.len() {
            return None;
        }
        let found = match self.at(self.pos) {
            Some(e) => Some(e),
            None if self.resync => {
                // A damaged entry: the next offset whose length and checksum check out. A false
                // match needs a CRC32 to agree by chance (1 in 2^32 per candidate offset).
                let damaged = self.pos;
                let next = (damaged + 1..=self.bytes.len() - 8).find_map(|p| self.at(p));
                if let Some((start, _)) = next {
                    self.skipped.push((damaged, start - 8));
                }
                next
            }
            None => None,
        };
        match found {
            Some((start, payload)) => {
                self.pos = start + payload.len();
                Some((start, payload))
            }
            None => {
                self.pos = self.bytes.len();
                None
            }
        }
    }
}

/// Every `*.seg` file in a directory, in name order.
pub fn segment_paths(dir: &Path) -> Result<Vec<PathBuf>> {
    let mut out = Vec::new();
    match std::fs::read_dir(dir) {
        Ok(rd) => {
            for e in rd {
                let p = e?.path();
                if p.extension().is_some_and(|x| x == "seg") {
                    out.push(p);
                }
            }
        }
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
        Err(e) => return Err(e).with_context(|| format!("listing {}", dir.display())),
    }
    out.sort();
    Ok(out)
}

/// Little-endian field encoding for segment payloads.
pub mod enc {
    use anyhow::{bail, Result};

    pub fn u32(out: &mut Vec<u8>, x: u32) {
        out.extend_from_slice(&x.to_le_bytes());
    }
    pub fn u64(out: &mut Vec<u8>, x: u64) {
        out.extend_from_slice(&x.to_le_bytes());
    }
    pub fn bytes(out: &mut Vec<u8>, b: &[u8]) {
        u32(out, b.len() as u32);
        out.extend_from_slice(b);
    }

    /// Reads fields back, failing (never panicking) on short input.
    pub struct Reader<'a> {
        pub buf: &'a [u8],
    }

    impl<'a> Reader<'a> {
        pub fn take(&mut self, n: usize) -> Result<&'a [u8]> {
            if self.buf.len() < n {
                bail!("record is truncated");
            }
            let (a, b) = self.buf.split_at(n);
            self.buf = b;
            Ok(a)
        }
        pub fn u8(&mut self) -> Result<u8> {
            Ok(self.take(1)?[0])
        }
        pub fn u32(&mut self) -> Result<u32> {
            Ok(u32::from_le_bytes(self.take(4)?.try_into()?))
        }
        pub fn u64(&mut self) -> Result<u64> {
            Ok(u64::from_le_bytes(self.take(8)?.try_into()?))
        }
        pub fn bytes(&mut self) -> Result<&'a [u8]> {
            let n = self.u32()? as usize;
            self.take(n)
        }
        pub fn str(&mut self) -> Result<&'a str> {
            Ok(std::str::from_utf8(self.bytes()?)?)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn torn_tail_is_ignored() {
        let dir = tempfile::tempdir().unwrap();
        let mut w = SegmentWriter::create(dir.path(), "a").unwrap();
        w.append(b"first").unwrap();
        w.append(b"second").unwrap();
        w.sync().unwrap();
        let path = w.path().to_path_buf();
        drop(w);
        // Simulate a kill mid-append: a length and half a payload.
        let mut f = OpenOptions::new().append(true).open(&path).unwrap();
        f.write_all(&[20, 0, 0, 0, 1, 2, 3, 4, b'x']).unwrap();
        let seg = Segment::open(&path).unwrap();
        let got: Vec<&[u8]> = seg.entries().map(|(_, p)| p).collect();
        assert_eq!(got, vec![&b"first"[..], &b"second"[..]]);
        let (off, _) = seg.entries().nth(1).unwrap();
        assert_eq!(seg.payload_at(off), Some(&b"second"[..]));
        // A writer that goes on after the torn tail was read: its next entries are found from
        // where the last valid one ended (a real writer never leaves a torn entry mid-file).
        let (off, first) = seg.entries().next().unwrap();
        let rest: Vec<&[u8]> = seg.entries_from(Segment::end_of(off, first.len())).map(|(_, p)| p).collect();
        assert_eq!(rest, vec![&b"second"[..]]);
    }

    #[test]
    fn zeros_are_a_gap_not_entries() {
        // On NFS a reader may see the end of a segment before bytes another node wrote in
        // between: zeros, which would read as empty entries with a valid checksum (crc32 of
        // nothing is 0), and the scan would go on past real entries it then never reads.
        let dir = tempfile::tempdir().unwrap();
        let mut w = SegmentWriter::create(dir.path(), "a").unwrap();
        w.append(b"first").unwrap();
        w.sync().unwrap();
        let path = w.path().to_path_buf();
        let mut f = OpenOptions::new().append(true).open(&path).unwrap();
        f.write_all(&[0u8; 16]).unwrap();
        let seg = Segment::open(&path).unwrap();
        assert_eq!(seg.entries().map(|(_, p)| p).collect::<Vec<_>>(), vec![&b"first"[..]]);
    }

    /// Entries `0..n` of `size` bytes each, then the segment's bytes.
    fn segment_of(dir: &Path, n: usize, size: usize) -> (PathBuf, Vec<Vec<u8>>) {
        let mut w = SegmentWriter::create(dir, "a").unwrap();
        let payloads: Vec<Vec<u8>> = (0..n).map(|i| format!("{i:0size$}").into_bytes()).collect();
        for p in &payloads {
            w.append(p).unwrap();
        }
        w.sync().unwrap();
        (w.path().to_path_buf(), payloads)
    }

    #[test]
    fn a_flipped_bit_costs_its_entry_only() {
        let dir = tempfile::tempdir().unwrap();
        let (path, payloads) = segment_of(dir.path(), 50, 40);
        let clean = std::fs::read(&path).unwrap();
        // Every bit of entry 10 (its length, its checksum, its payload) in turn.
        let entry = 8 + 10 * 48;
        for bit in 0..48 * 8 {
            let mut bytes = clean.clone();
            bytes[entry + bit / 8] ^= 1 << (bit % 8);
            std::fs::write(&path, &bytes).unwrap();
            let seg = Segment::open(&path).unwrap();
            let got: Vec<&[u8]> = seg.entries().map(|(_, p)| p).collect();
            let want: Vec<&[u8]> =
                payloads.iter().enumerate().filter(|&(i, _)| i != 10).map(|(_, p)| p.as_slice()).collect();
            assert_eq!(got, want, "bit {bit} of entry 10");
            let check = seg.check();
            assert_eq!((check.entries, check.tail), (49, 0));
            assert_eq!(check.damaged, vec![(entry, entry + 48)], "bit {bit}");
            // A reader that only follows what was appended stops there (it may be bytes not seen yet).
            assert_eq!(seg.entries_from(0).count(), 10);
            assert_eq!(seg.sound_prefix(), entry);
        }
    }

    #[test]
    fn a_flipped_bit_in_the_magic_loses_nothing() {
        let dir = tempfile::tempdir().unwrap();
        let (path, payloads) = segment_of(dir.path(), 5, 10);
        let clean = std::fs::read(&path).unwrap();
        for bit in (0..40).chain(56..64) {
            let mut bytes = clean.clone();
            bytes[bit / 8] ^= 1 << (bit % 8);
            std::fs::write(&path, &bytes).unwrap();
            let seg = Segment::open(&path).unwrap();
            assert_eq!(seg.entries().count(), payloads.len(), "bit {bit}");
            assert_eq!(seg.check().damaged, vec![(0, 8)], "bit {bit}");
        }
    }

    #[test]
    fn headers_say_who_wrote_a_segment() {
        assert_eq!(Header::of(b"D4SEG01\n\x05"), Header::Current);
        assert_eq!(Header::of(b""), Header::Torn);
        assert_eq!(Header::of(b"D4SE"), Header::Torn);
        assert_eq!(Header::of(b"D4SEG02\nmore"), Header::Newer(2));
        assert_eq!(Header::of(b"D4SEG17\n"), Header::Newer(17));
        assert_eq!(Header::of(b"D4SEG00\n"), Header::Unknown);
        assert_eq!(Header::of(b"hello world"), Header::Unknown);
        // One flipped bit of the magic is damage to our own segment; one in the version digits
        // is not taken for it ('1' ^ 2 = '3': format 03 may be a newer dist4d's).
        assert_eq!(Header::of(b"D4SGG01\n"), Header::DamagedMagic);
        assert_eq!(Header::of(b"D4SEG01\x0b"), Header::DamagedMagic);
        assert_eq!(Header::of(b"D4SEG03\n"), Header::Newer(3));
        assert!(Header::Newer(2)
            .problem()
            .unwrap()
            .contains("newer dist4d (segment format 02; this dist4d reads format 01)"));
        // A newer segment has no entries this dist4d reads, even if its entries look like ours.
        let dir = tempfile::tempdir().unwrap();
        let (path, _) = segment_of(dir.path(), 3, 10);
        let mut bytes = std::fs::read(&path).unwrap();
        bytes[6] = b'2';
        std::fs::write(&path, &bytes).unwrap();
        let seg = Segment::open(&path).unwrap();
        assert_eq!((seg.header(), seg.entries().count()), (Header::Newer(2), 0));
    }

    #[test]
    fn corrupt_entries_stop_the_scan() {
        let dir = tempfile::tempdir().unwrap();
        let mut w = SegmentWriter::create(dir.path(), "a").unwrap();
        w.append(b"good").unwrap();
        w.append(b"flipped").unwrap();
        w.sync().unwrap();
        let path = w.path().to_path_buf();
        let mut bytes = std::fs::read(&path).unwrap();
        let n = bytes.len();
        bytes[n - 1] ^= 0xff;
        std::fs::write(&path, bytes).unwrap();
        let seg = Segment::open(&path).unwrap();
        assert_eq!(seg.entries().count(), 1);
    }
}
