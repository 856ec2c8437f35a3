//! How one blob is kept in `cas/`: its bytes as they are, or compressed behind a small header.
//!
//! ```text
//! raw:     the bytes themselves (what every store before this format held; also what dist4d
//!          keeps for bytes that do not compress, such as PNG, JPEG or ZIP-compressed EXR, so that
//!          an export can share their disk blocks by reflink)
//! packed:  magic "\xd4BLB" | codec u8 | 3 zero bytes | length of the bytes u64 LE | payload
//! ```
//!
//! Codecs: 0 stored (bytes that happen to begin with the magic, kept whole behind the header so
//! they cannot be mistaken for a packed blob), 1 zstd, 2 zstd of the bytes split into four byte
//! planes (byte k of every 4-byte word together), each byte then replaced by its difference to the
//! one before. Float and u32 arrays, which most artifacts are, compress much better so: the
//! sign/exponent plane is nearly constant and neighbouring depths are alike (a dense 1600x900 depth
//! map: 0.25 of its size against 0.36 with zstd alone, for ~5 ms more).
//!
//! A blob is named by the digest of its bytes, not of its file, so task keys do not depend on
//! how blobs are kept, and the digest is checked after unpacking on every read. A file that does
//! not begin with the magic is raw; one that does but fails to unpack, or unpacks to other bytes,
//! is still accepted if the file itself hashes to the digest (raw bytes that begin with the magic,
//! written by a store of the older format): an old store reads without a rebuild.

use crate::digest::Digest;
use std::path::Path;

pub const MAGIC: [u8; 4] = *b"\xd4BLB";
const HEADER: usize = 16;

const STORED: u8 = 0;
const ZSTD: u8 = 1;
const ZSTD_PLANES_DELTA: u8 = 2;

/// zstd level: 1 compresses a 5.8 MB float depth map in ~10 ms; higher levels gain a few percent
/// for several times the time, and every task output passes through here.
const LEVEL: i32 = 1;

/// Bytes shorter than this are kept raw: a header and a zstd frame would not pay.
const MIN_PACK: usize = 256;

/// How a blob's bytes go to disk.
pub enum Kept<'a> {
    /// As they are: the file is the bytes (reflinkable into an export).
    Raw(&'a [u8]),
    /// Header and payload.
    Packed(Vec<u8>),
}

impl Kept<'_> {
    pub fn file_bytes(&self) -> &[u8] {
        match self {
            Kept::Raw(b) => b,
            Kept::Packed(v) => v,
        }
    }
}

/// Chooses how to keep `bytes`: compressed when that saves at least an eighth, else raw.
/// Whether (and with which filter) they compress is judged on a sample first, so bytes that are
/// already compressed (images, EXR) cost a few small trial compressions, not a full one.
pub fn pack(bytes: &[u8]) -> Kept<'_> {
    let raw =
        || if bytes.starts_with(&MAGIC) { Kept::Packed(packed(STORED, bytes.len(), bytes)) } else { Kept::Raw(bytes) };
    if bytes.len() < MIN_PACK {
        return raw();
    }
    let Some(codec) = choose_codec(bytes) else { return raw() };
    let payload = match codec {
        ZSTD_PLANES_DELTA => compress(&to_planes_delta(bytes)),
        _ => compress(bytes),
    };
    match payload {
        Some(p) if p.len() + HEADER <= bytes.len() - bytes.len() / 8 => Kept::Packed(packed(codec, bytes.len(), &p)),
        _ => raw(),
    }
}

/// Up to three 32 KiB windows (start, middle, end) compressed both ways: the better codec, or
/// None when neither saves an eighth.
fn choose_codec(bytes: &[u8]) -> Option<u8> {
    const W: usize = 32 << 10;
    let sample: Vec<u8> = if bytes.len() <= 3 * W {
        bytes.to_vec()
    } else {
        let mid = (bytes.len() / 2 - W / 2) & !3;
        let end = (bytes.len() - W) & !3;
        [&bytes[..W], &bytes[mid..mid + W], &bytes[end..end + W]].concat()
    };
    let plain = compress(&sample)?.len();
    let planes = compress(&to_planes_delta(&sample))?.len();
    let (codec, best) = if planes < plain { (ZSTD_PLANES_DELTA, planes) } else { (ZSTD, plain) };
    (best <= sample.len() - sample.len() / 8).then_some(codec)
}

fn compress(bytes: &[u8]) -> Option<Vec<u8>> {
    zstd::bulk::compress(bytes, LEVEL).ok()
}

fn packed(codec: u8, len: usize, payload: &[u8]) -> Vec<u8> {
    let mut out = Vec::with_capacity(HEADER + payload.len());
    out.extend_from_slice(&MAGIC);
    out.extend_from_slice(&[codec, 0, 0, 0]);
    out.extend_from_slice(&(len as u64).to_le_bytes());
    out.extend_from_slice(payload);
    out
}

/// [`to_planes`], then every byte minus the one before it (wrapping).
fn to_planes_delta(bytes: &[u8]) -> Vec<u8> {
    let mut p = to_planes(bytes);
    let mut prev = 0u8;
    for x in &mut p {
        let cur = *x;
        *x = cur.wrapping_sub(prev);
        prev = cur;
    }
    p
}

fn from_planes_delta(mut p: Vec<u8>) -> Vec<u8> {
    let mut prev = 0u8;
    for x in &mut p {
        prev = prev.wrapping_add(*x);
        *x = prev;
    }
    from_planes(&p)
}

/// Byte k of every 4-byte word, for k = 0..4, then the 0-3 bytes past the last whole word.
fn to_planes(bytes: &[u8]) -> Vec<u8> {
    let n = bytes.len() / 4;
    let mut out = vec![0u8; bytes.len()];
    let (planes, tail) = out.split_at_mut(4 * n);
    let (p0, rest) = planes.split_at_mut(n);
    let (p1, rest) = rest.split_at_mut(n);
    let (p2, p3) = rest.split_at_mut(n);
    for (i, w) in bytes[..4 * n].chunks_exact(4).enumerate() {
        p0[i] = w[0];
        p1[i] = w[1];
        p2[i] = w[2];
        p3[i] = w[3];
    }
    tail.copy_from_slice(&bytes[4 * n..]);
    out
}

fn from_planes(planes: &[u8]) -> Vec<u8> {
    let n = planes.len() / 4;
    let mut out = vec![0u8; planes.len()];
    let (p0, p1, p2, p3) = (&planes[..n], &planes[n..2 * n], &planes[2 * n..3 * n], &planes[3 * n..4 * n]);
    for (i, w) in out[..4 * n].chunks_exact_mut(4).enumerate() {
        w.copy_from_slice(&[p0[i], p1[i], p2[i], p3[i]]);
    }
    out[4 * n..].copy_from_slice(&planes[4 * n..]);
    out
}

/// The bytes of a blob file named `digest`, checked. `Err` says what is wrong with the file.
pub fn unpack(file: Vec<u8>, digest: &Digest) -> Result<Vec<u8>, &'static str> {
    if !file.starts_with(&MAGIC) {
        return if Digest::of(&file) == *digest { Ok(file) } else { Err("is corrupt") };
    }
    match unpack_packed(&file) {
        Some(bytes) if Digest::of(&bytes) == *digest => Ok(bytes),
        // Raw bytes that begin with the magic, as a store of the older format kept them.
        _ if Digest::of(&file) == *digest => Ok(file),
        _ => Err("is corrupt (its packed bytes do not unpack to its digest)"),
    }
}

fn unpack_packed(file: &[u8]) -> Option<Vec<u8>> {
    let header = file.get(..HEADER)?;
    let (codec, len) = (header[4], u64::from_le_bytes(header[8..16].try_into().ok()?));
    let payload = &file[HEADER..];
    if header[5..8] != [0, 0, 0] {
        return None;
    }
    let len = usize::try_from(len).ok()?;
    let unzstd = || -> Option<Vec<u8>> {
        // A damaged length must not make us allocate without bound: reserve fallibly.
        let mut out = Vec::new();
        out.try_reserve_exact(len).ok()?;
        let n = zstd::bulk::Decompressor::new().ok()?.decompress_to_buffer(payload, &mut out).ok()?;
        (n == len).then_some(out)
    };
    match codec {
        STORED => (payload.len() == len).then(|| payload.to_vec()),
        ZSTD => unzstd(),
        ZSTD_PLANES_DELTA => unzstd().map(from_planes_delta),
        _ => None,
    }
}

/// Whether a blob file holds its bytes raw (no header): only such a file can be reflinked
/// into an export.
pub fn is_raw_file(path: &Path) -> bool {
    let mut head = [0u8; 4];
    std::fs::File::open(path)
        .and_then(|mut f| std::io::Read::read_exact(&mut f, &mut head))
        .map(|_| head != MAGIC)
        .unwrap_or(false)
}

/// Makes `dest` (a new file) share the disk blocks of `src` (ioctl FICLONE: btrfs, XFS with
/// reflink, bcachefs, ...). Fails on filesystems without reflink (ext4, tmpfs) and across
/// filesystems; the caller then writes the bytes.
pub fn reflink(src: &Path, dest: &Path) -> std::io::Result<()> {
    use std::os::fd::AsRawFd;
    let from = std::fs::File::open(src)?;
    let to = std::fs::File::create(dest)?;
    // SAFETY: both descriptors are open for the duration of the call; FICLONE reads no memory.
    let r = unsafe { libc::ioctl(to.as_raw_fd(), FICLONE, from.as_raw_fd()) };
    if r == 0 {
        Ok(())
    } else {
        let e = std::io::Error::last_os_error();
        drop(to);
        let _ = std::fs::remove_file(dest);
        Err(e)
    }
}

/// `_IOW(0x94, 9, int)`, the same on every Linux architecture dist4d builds for.
const FICLONE: libc::c_ulong = 0x4004_9409;

/// Writes `bytes` to `path` (for tests that forge old-format or damaged blobs).
#[cfg(test)]
fn write(path: &Path, bytes: &[u8]) {
    std::fs::write(path, bytes).unwrap();
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    fn floats(n: usize) -> Vec<u8> {
        (0..n).flat_map(|i| (10.0 + (i as f32 * 0.01).sin() * 5.0).to_le_bytes()).collect()
    }

    #[test]
    fn compressible_bytes_are_packed_and_unpack_to_themselves() {
        let bytes = floats(100_000);
        let kept = pack(&bytes);
        let Kept::Packed(file) = kept else { panic!("a smooth float array compresses") };
        assert!(file.len() < bytes.len() / 2, "{} of {}", file.len(), bytes.len());
        assert_eq!(file[4], ZSTD_PLANES_DELTA, "floats compress best by byte planes");
        assert_eq!(unpack(file, &Digest::of(&bytes)).unwrap(), bytes);
        let text = "a line of text that repeats\n".repeat(1000).into_bytes();
        let Kept::Packed(file) = pack(&text) else { panic!("text compresses") };
        assert_eq!(unpack(file, &Digest::of(&text)).unwrap(), text);
    }

    /// `len` bytes zstd cannot shrink (xorshift64).
    pub(crate) fn noise(len: usize) -> Vec<u8> {
        let mut x = 0x9e3779b97f4a7c15u64;
        (0..len)
            .map(|_| {
                x ^= x << 13;
                x ^= x >> 7;
                x ^= x << 17;
                x as u8
            })
            .collect()
    }

    #[test]
    fn incompressible_and_small_bytes_stay_raw() {
        let noise = noise(200_000);
        assert!(matches!(pack(&noise), Kept::Raw(_)));
        assert!(matches!(pack(b"short"), Kept::Raw(_)));
        assert_eq!(unpack(noise.clone(), &Digest::of(&noise)).unwrap(), noise);
        // Raw bytes that begin with the magic are kept behind a header, not taken for packed ones.
        let tricky = [&MAGIC[..], &noise[..1000]].concat();
        let Kept::Packed(file) = pack(&tricky) else { panic!("kept behind a header") };
        assert_eq!(file[4], STORED);
        assert_eq!(unpack(file, &Digest::of(&tricky)).unwrap(), tricky);
    }

    #[test]
    fn old_raw_blobs_read_even_when_they_begin_with_the_magic() {
        let old = [&MAGIC[..], &[7u8; 40][..]].concat();
        assert_eq!(unpack(old.clone(), &Digest::of(&old)).unwrap(), old);
    }

    #[test]
    fn damaged_packed_blobs_are_refused_without_panicking() {
        let bytes = floats(50_000);
        let d = Digest::of(&bytes);
        let Kept::Packed(file) = pack(&bytes) else { panic!() };
        let mut flipped = file.clone();
        let at = flipped.len() / 2;
        flipped[at] ^= 0x40;
        assert!(unpack(flipped, &d).is_err());
        assert!(unpack(file[..file.len() - 10].to_vec(), &d).is_err(), "truncated");
        let mut huge = file.clone();
        huge[8..16].copy_from_slice(&u64::MAX.to_le_bytes());
        assert!(unpack(huge, &d).is_err(), "a damaged length allocates nothing");
        let mut codec = file.clone();
        codec[4] = 99;
        assert!(unpack(codec, &d).is_err(), "unknown codec");
        assert!(unpack(file[..10].to_vec(), &d).is_err(), "header only");
        assert!(unpack(vec![0x5a; 1000], &d).is_err(), "raw and wrong");
    }

    #[test]
    fn planes_round_trip_with_a_tail() {
        for n in [0, 1, 3, 4, 5, 1001] {
            let b: Vec<u8> = (0..n as u32).map(|i| (i * 7 + 3) as u8).collect();
            assert_eq!(from_planes(&to_planes(&b)), b);
            assert_eq!(from_planes_delta(to_planes_delta(&b)), b);
        }
    }

    /// Sizes and times of the codecs on real blobs: `DIST4D_BLOBS="file ..." cargo test --release
    /// -p dist4d-runtime codec_figures -- --ignored --nocapture`.
    #[test]
    #[ignore]
    fn codec_figures() {
        for path in std::env::var("DIST4D_BLOBS").expect("DIST4D_BLOBS").split_whitespace() {
            let bytes = std::fs::read(path).unwrap();
            println!("{path}: {} bytes", bytes.len());
            let time = |name: &str, f: &dyn Fn() -> usize| {
                let t = std::time::Instant::now();
                let n = f();
                println!(
                    "  {name:28} {:7.1} ms {:6.3} of raw",
                    t.elapsed().as_secs_f64() * 1e3,
                    n as f64 / bytes.len() as f64
                );
            };
            for level in [-1, 1, 3] {
                time(&format!("zstd {level}"), &|| zstd::bulk::compress(&bytes, level).unwrap().len());
                time(&format!("zstd {level} planes"), &|| {
                    zstd::bulk::compress(&to_planes(&bytes), level).unwrap().len()
                });
                time(&format!("zstd {level} planes + delta"), &|| {
                    let mut p = to_planes(&bytes);
                    for i in (1..p.len()).rev() {
                        p[i] = p[i].wrapping_sub(p[i - 1]);
                    }
                    zstd::bulk::compress(&p, level).unwrap().len()
                });
            }
            time("pack (chosen)", &|| pack(&bytes).file_bytes().len());
            let file = pack(&bytes).file_bytes().to_vec();
            let d = Digest::of(&bytes);
            time("unpack + digest", &|| unpack(file.clone(), &d).unwrap().len());
        }
    }

    #[test]
    fn reflink_fails_cleanly_or_clones() {
        let dir = tempfile::tempdir().unwrap();
        let (a, b) = (dir.path().join("a"), dir.path().join("b"));
        write(&a, b"some bytes");
        match reflink(&a, &b) {
            Ok(()) => assert_eq!(std::fs::read(&b).unwrap(), b"some bytes"),
            Err(_) => assert!(!b.exists(), "a failed clone leaves no file"),
        }
    }
}
