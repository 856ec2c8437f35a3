//! Append-only segment files of checksummed entries.
//!
//! Small records (task records, file fingerprints) are packed into segments instead of one file
//! each: two million 4 KiB files would waste gigabytes. Each process appends to segments of its
//! own (named by a unique writer id), so concurrent processes on one store never write the same
//! file. An entry is `len: u32 | crc32(payload): u32 | payload`; a process killed mid-append
//! leaves a torn last entry, which fails its checksum and is ignored by readers.

use anyhow::{Context, Result};
use memmap2::Mmap;
use std::fs::{File, OpenOptions};
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

const MAGIC: &[u8; 8] = b"D4SEG01\n";
/// Entries larger than this are treated as corruption (a torn length field).
const MAX_ENTRY: u32 = 64 << 20;

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
        self.out.write_all(&head)?;
        self.out.write_all(payload)?;
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

    /// Valid entries as (offset of payload, payload). Stops at the first torn or corrupt entry.
    pub fn entries(&self) -> impl Iterator<Item = (usize, &[u8])> {
        self.entries_from(0)
    }

    /// Valid entries from byte offset `from`, which is 0 (the first entry) or the end of an
    /// entry ([`Segment::end_of`]): what a writer appended since the segment was last read.
    pub fn entries_from(&self, from: usize) -> impl Iterator<Item = (usize, &[u8])> {
        let bytes = self.bytes();
        let mut pos = if !bytes.starts_with(MAGIC) { bytes.len() } else { from.max(MAGIC.len()) };
        std::iter::from_fn(move || {
            if pos + 8 > bytes.len() {
                return None;
            }
            let len = u32::from_le_bytes(bytes[pos..pos + 4].try_into().unwrap());
            let crc = u32::from_le_bytes(bytes[pos + 4..pos + 8].try_into().unwrap());
            let start = pos + 8;
            // No writer appends an empty entry: zeros are a gap (bytes another node wrote not
            // yet seen, on NFS), not an entry, whose checksum would pass (crc32 of nothing is 0).
            if len == 0 || len > MAX_ENTRY || start + len as usize > bytes.len() {
                return None;
            }
            let payload = &bytes[start..start + len as usize];
            if crc32fast::hash(payload) != crc {
                return None;
            }
            pos = start + len as usize;
            Some((start, payload))
        })
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
