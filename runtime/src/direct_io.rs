//! Writing large files around the page cache (`O_DIRECT`).
//!
//! A run writes gigabytes it does not read back: the exported files, and the blobs later runs
//! may read. A buffered write copies every byte into the page cache first, and on the machines
//! measured that copy into fresh pages cost more than a fifth of a curation run's CPU (the
//! 240-image chain of docs/BENCHMARKS.md: 7 of 31 CPU seconds in the kernel's
//! `copy_folio_from_iter_atomic`). A direct write hands this process's buffer to the device
//! instead (bytes that do not start on a page boundary are first copied into a page-aligned
//! staging buffer, a copy into warm memory that costs a fraction of the kernel's), and leaves the
//! page cache to the data that is read.
//!
//! Only on local block filesystems (ext4, XFS, btrfs), where direct I/O is the plain path the
//! databases take; on network filesystems it turns each write into synchronous round trips, and
//! tmpfs has no device to skip to. Everywhere else, for files under [`DIRECT_MIN`], and whenever
//! the kernel refuses the flag or an aligned write, the bytes are written as usual: the caller
//! gets the same file either way.

use std::fs::File;
use std::io;
use std::os::fd::AsRawFd;
use std::os::unix::fs::FileExt;

/// Alignment of a direct write's buffer, offset and length: the page size, a multiple of every
/// logical block size in use.
const ALIGN: usize = 4096;
/// Smaller files are written buffered: the saving is in the bulk, and each direct write waits
/// for the device.
pub const DIRECT_MIN: usize = 1 << 20;
/// Bytes per direct write (and the size of each thread's aligned staging buffer).
const CHUNK: usize = 4 << 20;

/// Writes `bytes` at the start of the empty file `f`, directly to the device where the file's
/// filesystem allows it (see the module doc). Returns whether it did: a caller that starts the
/// kernel's writeback early need not for a file written directly.
pub fn write_new(f: &File, bytes: &[u8]) -> io::Result<bool> {
    if bytes.len() < DIRECT_MIN || !local_block_filesystem(f) || !set_direct(f, true) {
        f.write_all_at(bytes, 0)?;
        return Ok(false);
    }
    // The aligned head goes directly; the tail (under one page) buffered.
    let head = bytes.len() / ALIGN * ALIGN;
    let (mut at, mut direct) = (0, true);
    let mut staging: Option<Staging> = None;
    while at < head {
        let n = (head - at).min(CHUNK);
        let src = &bytes[at..at + n];
        let aligned: &[u8] = if (src.as_ptr() as usize) & (ALIGN - 1) == 0 {
            src
        } else {
            let buf = staging.get_or_insert_with(Staging::take).bytes();
            buf[..n].copy_from_slice(src);
            &buf[..n]
        };
        match f.write_all_at(aligned, at as u64) {
            Ok(()) => at += n,
            // A filesystem that took the flag but not this write (alignment rules of its own):
            // the rest goes buffered.
            Err(e) if e.raw_os_error() == Some(libc::EINVAL) => {
                direct = false;
                break;
            }
            Err(e) => return Err(e),
        }
    }
    set_direct(f, false);
    f.write_all_at(&bytes[at..], at as u64)?;
    Ok(direct)
}

/// Turns `O_DIRECT` on or off for an open file; false when the kernel refuses.
fn set_direct(f: &File, on: bool) -> bool {
    let fd = f.as_raw_fd();
    // SAFETY: fcntl on a descriptor that `f` keeps open; no pointers are passed.
    unsafe {
        let flags = libc::fcntl(fd, libc::F_GETFL);
        if flags < 0 {
            return false;
        }
        let flags = if on { flags | libc::O_DIRECT } else { flags & !libc::O_DIRECT };
        libc::fcntl(fd, libc::F_SETFL, flags) == 0
    }
}

/// ext4 (also ext2/3), XFS or btrfs.
fn local_block_filesystem(f: &File) -> bool {
    // SAFETY: a zeroed statfs the call fills, for a descriptor `f` keeps open.
    let mut st: libc::statfs = unsafe { std::mem::zeroed() };
    if unsafe { libc::fstatfs(f.as_raw_fd(), &mut st) } != 0 {
        return false;
    }
    const LOCAL: [u32; 3] = [
        0xEF53,      // ext2/3/4
        0x5846_5342, // XFS
        0x9123_683E, // btrfs
    ];
    // The magic is 32 bits wide; `f_type` is signed and as wide as a C long.
    LOCAL.contains(&(st.f_type as u32))
}

/// A page-aligned buffer of [`CHUNK`] bytes: the bytes to write rarely start on a page boundary,
/// and direct I/O needs them to. A few are kept for reuse across writes and threads ([`SPARE`]),
/// not one per thread: a run may have hundreds of threads waiting on model workers.
struct Staging(Vec<Page>);

/// Staging buffers kept between writes; more writers at once allocate their own and drop them.
static SPARE: std::sync::Mutex<Vec<Vec<Page>>> = std::sync::Mutex::new(Vec::new());
const KEPT: usize = 4;

#[repr(C, align(4096))]
#[derive(Clone, Copy)]
struct Page([u8; ALIGN]);

impl Staging {
    /// A kept buffer, or a new one; it goes back to [`SPARE`] when dropped.
    fn take() -> Staging {
        let kept = SPARE.lock().ok().and_then(|mut spare| spare.pop());
        Staging(kept.unwrap_or_else(|| vec![Page([0; ALIGN]); CHUNK / ALIGN]))
    }

    fn bytes(&mut self) -> &mut [u8] {
        // SAFETY: the pages are contiguous, plain bytes, and borrowed mutably for the slice's life.
        unsafe { std::slice::from_raw_parts_mut(self.0.as_mut_ptr().cast::<u8>(), self.0.len() * ALIGN) }
    }
}

impl Drop for Staging {
    fn drop(&mut self) {
        if let Ok(mut spare) = SPARE.lock() {
            if spare.len() < KEPT {
                spare.push(std::mem::take(&mut self.0));
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Bytes of `n` that are not all alike, so that a chunk written at the wrong offset shows.
    fn pattern(n: usize) -> Vec<u8> {
        (0..n).map(|i| (i * 7 + i / 4096) as u8).collect()
    }

    #[test]
    fn a_file_reads_back_as_written_whatever_its_size_and_alignment() {
        let dir = tempfile::tempdir().unwrap();
        // Under the threshold, a page multiple, a tail, several chunks, and a slice that starts
        // off a page boundary (copied through the staging buffer) or on one (written as it is).
        let big = pattern(2 * CHUNK + 3 * ALIGN + 123);
        let cases: Vec<&[u8]> =
            vec![&big[..1000], &big[..DIRECT_MIN], &big[..DIRECT_MIN + 1], &big[1..CHUNK + 77], &big[..], &big[5..]];
        let on_ext4 = {
            let f = File::create(dir.path().join("probe")).unwrap();
            local_block_filesystem(&f)
        };
        for (i, bytes) in cases.into_iter().enumerate() {
            let path = dir.path().join(format!("f{i}"));
            let f = File::create(&path).unwrap();
            let direct = write_new(&f, bytes).unwrap();
            drop(f);
            assert_eq!(std::fs::read(&path).unwrap(), bytes, "case {i} ({} bytes)", bytes.len());
            // Where direct I/O is used, it must be taken (ext4 takes it), or this tests nothing.
            assert_eq!(direct, on_ext4 && bytes.len() >= DIRECT_MIN, "case {i}: written directly");
        }
    }

    #[test]
    fn a_file_left_open_after_a_direct_write_takes_buffered_writes_again() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("f");
        let f = File::create(&path).unwrap();
        let bytes = pattern(DIRECT_MIN + 10);
        write_new(&f, &bytes).unwrap();
        // An unaligned write would fail with EINVAL if the flag were still on.
        f.write_all_at(b"xyz", 3).unwrap();
        drop(f);
        let mut want = bytes.clone();
        want[3..6].copy_from_slice(b"xyz");
        assert_eq!(std::fs::read(&path).unwrap(), want);
    }
}
