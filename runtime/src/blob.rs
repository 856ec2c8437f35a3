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
//! map: 0.25-0.40 of its size against 0.36-0.58 with zstd alone). 3 is 2 with each plane its own
//! zstd frame, what dist4d writes now: the same size, in ~0.6 of the time (zstd's fast match finder
//! runs through a nearly constant plane, and the noisy low bytes of a float, faster apart than
//! together):
//!
//! ```text
//! codec 3 payload: compressed length of the frame of plane k, for k = 0..4, u64 LE each |
//!                  the four zstd frames | the 0-3 filtered bytes past the last whole word
//! ```
//!
//! A store reads every codec it ever wrote (2 is no longer written). A packed blob of a codec it
//! does not know was written by a newer dist4d: [`unpack`] says so ([`Unreadable::Newer`]), and
//! the store leaves the file as it is rather than remove it as corrupt (see `store::read_blob`).
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
const ZSTD_PLANES_APART: u8 = 3;

/// zstd level: 1 compresses a 5.8 MB float depth map in ~10 ms; higher levels gain a few percent
/// for several times the time, and every task output passes through here.
const LEVEL: i32 = 1;
/// zstd level of each byte plane of codec 3. The two low planes of a float are mostly noise, which
/// level -1 gets through ~2.5x faster for ~4% more of their bytes (a curated depth map: plane 1
/// 1.6 -> 0.6 ms, 0.82 -> 0.85 of its size; `codec_figures`); the high planes (exponent, high
/// significand) are where the savings are, at level 1.
const PLANE_LEVELS: [i32; 4] = [-1, -1, LEVEL, LEVEL];

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
    let file = match codec {
        ZSTD_PLANES_APART => planes_apart(bytes),
        _ => compress(bytes).map(|p| packed(codec, bytes.len(), &p)),
    };
    match file {
        Some(f) if f.len() <= bytes.len() - bytes.len() / 8 => Kept::Packed(f),
        _ => raw(),
    }
}

/// The whole file of codec 3: header, frame lengths, one zstd frame per filtered plane, tail.
/// The frames are written in place behind the lengths, not compressed apart and copied together.
fn planes_apart(bytes: &[u8]) -> Option<Vec<u8>> {
    let filtered = to_planes_delta(bytes);
    let n = bytes.len() / 4;
    let bound = zstd::zstd_safe::compress_bound(n);
    let mut file = std::io::Cursor::new(Vec::with_capacity(HEADER + 32 + 4 * bound + 3));
    file.get_mut().extend_from_slice(&packed(ZSTD_PLANES_APART, bytes.len(), &[0u8; 32]));
    let mut lengths = [0usize; 4];
    for (k, length) in lengths.iter_mut().enumerate() {
        file.set_position(file.get_ref().len() as u64);
        *length = with_compressor(PLANE_LEVELS[k], |c| c.compress_to_buffer(&filtered[k * n..(k + 1) * n], &mut file))?;
    }
    let mut file = file.into_inner();
    file.extend_from_slice(&filtered[4 * n..]);
    for (k, length) in lengths.iter().enumerate() {
        file[HEADER + 8 * k..HEADER + 8 * (k + 1)].copy_from_slice(&(*length as u64).to_le_bytes());
    }
    Some(file)
}

/// The bytes of a codec 3 payload that unpacks to `len` bytes (`None` if it is damaged).
fn unpack_planes_apart(payload: &[u8], len: usize) -> Option<Vec<u8>> {
    let (n, tail) = (len / 4, len % 4);
    let mut lengths = [0usize; 4];
    for (k, length) in lengths.iter_mut().enumerate() {
        *length = usize::try_from(u64::from_le_bytes(payload.get(8 * k..8 * (k + 1))?.try_into().ok()?)).ok()?;
    }
    let frames = lengths.iter().try_fold(0usize, |a, &b| a.checked_add(b))?;
    if frames.checked_add(32 + tail)? != payload.len() {
        return None;
    }
    // A damaged length must not make us allocate without bound: reserve fallibly.
    let mut out = std::io::Cursor::new(Vec::new());
    out.get_mut().try_reserve_exact(len).ok()?;
    let mut decompressor = zstd::bulk::Decompressor::new().ok()?;
    let mut at = 32;
    for (k, &length) in lengths.iter().enumerate() {
        out.set_position((k * n) as u64);
        if decompressor.decompress_to_buffer(&payload[at..at + length], &mut out).ok()? != n {
            return None;
        }
        at += length;
    }
    let mut filtered = out.into_inner();
    filtered.extend_from_slice(&payload[at..]);
    Some(from_planes_delta(filtered))
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
    let (codec, best) = if planes < plain { (ZSTD_PLANES_APART, planes) } else { (ZSTD, plain) };
    (best <= sample.len() - sample.len() / 8).then_some(codec)
}

fn compress(bytes: &[u8]) -> Option<Vec<u8>> {
    with_compressor(LEVEL, |c| c.compress(bytes))
}

/// `f` with a zstd context at `level`. Contexts are kept from one compression to the next (a new
/// one allocates its tables, through the C allocator, fresh pages each time for sizes this large,
/// and a blob takes three to six compressions); a few are kept, not one per thread: a run may have
/// hundreds of threads waiting on model workers.
fn with_compressor<T>(
    level: i32,
    f: impl FnOnce(&mut zstd::bulk::Compressor<'static>) -> std::io::Result<T>,
) -> Option<T> {
    static KEPT: std::sync::Mutex<Vec<zstd::bulk::Compressor<'static>>> = std::sync::Mutex::new(Vec::new());
    let kept = KEPT.lock().ok().and_then(|mut kept| kept.pop());
    let mut c = match kept {
        Some(c) => c,
        None => zstd::bulk::Compressor::new(level).ok()?,
    };
    let result = c.set_compression_level(level).and_then(|()| f(&mut c)).ok();
    if let Ok(mut kept) = KEPT.lock() {
        if kept.len() < 4 {
            kept.push(c);
        }
    }
    result
}

fn packed(codec: u8, len: usize, payload: &[u8]) -> Vec<u8> {
    let mut out = Vec::with_capacity(HEADER + payload.len());
    out.extend_from_slice(&MAGIC);
    out.extend_from_slice(&[codec, 0, 0, 0]);
    out.extend_from_slice(&(len as u64).to_le_bytes());
    out.extend_from_slice(payload);
    out
}

/// `out` (the length of `bytes`) cut into its four planes of `n` bytes and the 0-3 byte tail.
fn planes_mut(out: &mut [u8], n: usize) -> ([&mut [u8]; 4], &mut [u8]) {
    let (planes, tail) = out.split_at_mut(4 * n);
    let (p0, rest) = planes.split_at_mut(n);
    let (p1, rest) = rest.split_at_mut(n);
    let (p2, p3) = rest.split_at_mut(n);
    ([p0, p1, p2, p3], tail)
}

/// [`to_planes`], then every byte minus the one before it (wrapping), in one pass: byte k of a
/// word follows byte k of the word before it in plane k, so its delta is taken there (the first
/// byte of a plane follows the last of the plane before; the tail follows the last plane).
fn to_planes_delta(bytes: &[u8]) -> Vec<u8> {
    let n = bytes.len() / 4;
    let mut out = vec![0u8; bytes.len()];
    let ([p0, p1, p2, p3], tail) = planes_mut(&mut out, n);
    let words = &bytes[..4 * n];
    let mut prev = match words.last_chunk::<4>() {
        Some(last) => [0, last[0], last[1], last[2]],
        None => [0; 4],
    };
    for (i, w) in words.chunks_exact(4).enumerate() {
        p0[i] = w[0].wrapping_sub(prev[0]);
        p1[i] = w[1].wrapping_sub(prev[1]);
        p2[i] = w[2].wrapping_sub(prev[2]);
        p3[i] = w[3].wrapping_sub(prev[3]);
        prev = [w[0], w[1], w[2], w[3]];
    }
    let mut prev = words.last().copied().unwrap_or(0);
    for (t, &b) in tail.iter_mut().zip(&bytes[4 * n..]) {
        *t = b.wrapping_sub(prev);
        prev = b;
    }
    out
}

/// The inverse of [`to_planes_delta`], in one pass after a sum per plane: plane k starts from the
/// last byte of plane k - 1, which is the wrapping sum of every delta before it.
fn from_planes_delta(p: Vec<u8>) -> Vec<u8> {
    let n = p.len() / 4;
    let sum = |s: &[u8]| s.iter().fold(0u8, |a, &b| a.wrapping_add(b));
    let (d0, d1, d2, d3) = (&p[..n], &p[n..2 * n], &p[2 * n..3 * n], &p[3 * n..4 * n]);
    let mut acc = [0u8; 4];
    for k in 1..4 {
        acc[k] = acc[k - 1].wrapping_add(sum(&p[(k - 1) * n..k * n]));
    }
    let mut out = vec![0u8; p.len()];
    for (i, w) in out[..4 * n].chunks_exact_mut(4).enumerate() {
        acc = [
            acc[0].wrapping_add(d0[i]),
            acc[1].wrapping_add(d1[i]),
            acc[2].wrapping_add(d2[i]),
            acc[3].wrapping_add(d3[i]),
        ];
        w.copy_from_slice(&acc);
    }
    let mut prev = acc[3];
    for (o, &d) in out[4 * n..].iter_mut().zip(&p[4 * n..]) {
        prev = prev.wrapping_add(d);
        *o = prev;
    }
    out
}

/// Byte k of every 4-byte word, for k = 0..4, then the 0-3 bytes past the last whole word (the
/// layout [`to_planes_delta`] fills; its tests compare with it).
#[cfg(test)]
fn to_planes(bytes: &[u8]) -> Vec<u8> {
    let n = bytes.len() / 4;
    let mut out = vec![0u8; bytes.len()];
    let ([p0, p1, p2, p3], tail) = planes_mut(&mut out, n);
    for (i, w) in bytes[..4 * n].chunks_exact(4).enumerate() {
        p0[i] = w[0];
        p1[i] = w[1];
        p2[i] = w[2];
        p3[i] = w[3];
    }
    tail.copy_from_slice(&bytes[4 * n..]);
    out
}

#[cfg(test)]
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

/// Why a blob file cannot give the bytes of its name.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Unreadable {
    /// Damaged: it holds other bytes, or does not unpack.
    Corrupt(&'static str),
    /// Packed with a codec this dist4d does not know: a newer dist4d wrote it (or its header's
    /// codec byte is damaged; either way it is not this dist4d's to remove).
    Newer { codec: u8 },
}

impl std::fmt::Display for Unreadable {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Unreadable::Corrupt(why) => f.write_str(why),
            Unreadable::Newer { codec } => write!(
                f,
                "was written by a newer dist4d (blob codec {codec}; this dist4d reads codecs 0 to {ZSTD_PLANES_APART})"
            ),
        }
    }
}

/// The codec of a packed blob file's header (its first [`HEADER`] bytes or more) when this
/// dist4d does not know it: a newer dist4d wrote the file.
pub fn newer_codec(head: &[u8]) -> Option<u8> {
    let header = head.get(..HEADER)?;
    (header.starts_with(&MAGIC) && header[4] > ZSTD_PLANES_APART).then_some(header[4])
}

/// The bytes of a blob file named `digest`, checked. `Err` says what is wrong with the file.
pub fn unpack(file: Vec<u8>, digest: &Digest) -> Result<Vec<u8>, Unreadable> {
    if !file.starts_with(&MAGIC) {
        return if Digest::of(&file) == *digest { Ok(file) } else { Err(Unreadable::Corrupt("is corrupt")) };
    }
    match unpack_packed(&file) {
        Some(bytes) if Digest::of(&bytes) == *digest => Ok(bytes),
        // Raw bytes that begin with the magic, as a store of the older format kept them.
        _ if Digest::of(&file) == *digest => Ok(file),
        _ => match newer_codec(&file) {
            Some(codec) => Err(Unreadable::Newer { codec }),
            None => Err(Unreadable::Corrupt("is corrupt (its packed bytes do not unpack to its digest)")),
        },
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
        ZSTD_PLANES_APART => unpack_planes_apart(payload, len),
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
        assert_eq!(file[4], ZSTD_PLANES_APART, "floats compress best by byte planes");
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
    fn blobs_of_every_codec_written_so_far_still_read() {
        for n in [256, 1001, 100_003] {
            let bytes: Vec<u8> = floats(n / 4 + 1)[..n].to_vec();
            let d = Digest::of(&bytes);
            // Codec 2, one frame of the filtered planes (what stores wrote before codec 3).
            let two = packed(ZSTD_PLANES_DELTA, bytes.len(), &compress(&to_planes_delta(&bytes)).unwrap());
            assert_eq!(unpack(two, &d).unwrap(), bytes);
            let one = packed(ZSTD, bytes.len(), &compress(&bytes).unwrap());
            assert_eq!(unpack(one, &d).unwrap(), bytes);
            let three = planes_apart(&bytes).unwrap();
            assert_eq!(three[4], ZSTD_PLANES_APART);
            assert_eq!(unpack(three, &d).unwrap(), bytes, "{n} bytes");
        }
    }

    #[test]
    fn damaged_frame_lengths_are_refused_without_panicking() {
        let bytes = floats(50_001);
        let d = Digest::of(&bytes);
        let file = planes_apart(&bytes).unwrap();
        for (at, value) in [(0, 0u64), (0, 1), (8, u64::MAX), (16, u64::MAX / 2), (24, 7)] {
            let mut bad = file.clone();
            bad[HEADER + at..HEADER + at + 8].copy_from_slice(&value.to_le_bytes());
            assert!(unpack(bad, &d).is_err(), "length {value} at {at}");
        }
        // Lengths that add up but split the frames wrongly.
        let mut bad = file.clone();
        let l0 = u64::from_le_bytes(bad[HEADER..HEADER + 8].try_into().unwrap());
        let l1 = u64::from_le_bytes(bad[HEADER + 8..HEADER + 16].try_into().unwrap());
        bad[HEADER..HEADER + 8].copy_from_slice(&(l0 + 1).to_le_bytes());
        bad[HEADER + 8..HEADER + 16].copy_from_slice(&(l1 - 1).to_le_bytes());
        assert!(unpack(bad, &d).is_err());
        assert!(unpack(file[..HEADER + 20].to_vec(), &d).is_err(), "lengths cut short");
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
        assert_eq!(unpack(codec, &d), Err(Unreadable::Newer { codec: 99 }), "unknown codec: a newer dist4d's");
        assert!(unpack(file[..10].to_vec(), &d).is_err(), "header only");
        assert!(unpack(vec![0x5a; 1000], &d).is_err(), "raw and wrong");
    }

    #[test]
    fn planes_round_trip_with_a_tail() {
        for n in [0, 1, 3, 4, 5, 6, 7, 8, 1001, 1003] {
            let b: Vec<u8> = (0..n as u32).map(|i| (i * 7 + 3 + i * i / 5) as u8).collect();
            assert_eq!(from_planes(&to_planes(&b)), b);
            // The one-pass filter writes what the planes, then a running delta, gave (the bytes
            // of every store packed so far).
            let mut two_pass = to_planes(&b);
            for i in (1..two_pass.len()).rev() {
                two_pass[i] = two_pass[i].wrapping_sub(two_pass[i - 1]);
            }
            assert_eq!(to_planes_delta(&b), two_pass, "{n} bytes");
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
            // Process CPU time over repeats of at least a second (/proc/self/stat counts in 10 ms
            // ticks): on the shared machine, wall time counted other processes' load.
            let cpu = || {
                let stat = std::fs::read_to_string("/proc/self/stat").unwrap();
                let f: Vec<&str> = stat.rsplit_once(')').unwrap().1.split_whitespace().collect();
                (f[11].parse::<u64>().unwrap() + f[12].parse::<u64>().unwrap()) as f64 / 100.0
            };
            let time = |name: &str, f: &dyn Fn() -> usize| {
                let (t, mut reps, mut n) = (cpu(), 0, 0);
                while reps < 3 || cpu() - t < 1.0 {
                    n = f();
                    reps += 1;
                }
                println!(
                    "  {name:28} {:7.1} ms CPU {:6.3} of raw",
                    (cpu() - t) * 1e3 / reps as f64,
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
            time("to_planes_delta (one pass)", &|| to_planes_delta(&bytes).len());
            time("to_planes, then delta", &|| {
                let mut p = to_planes(&bytes);
                for i in (1..p.len()).rev() {
                    p[i] = p[i].wrapping_sub(p[i - 1]);
                }
                p.len()
            });
            let filtered = to_planes_delta(&bytes);
            time("from_planes_delta", &|| from_planes_delta(filtered.clone()).len());
            let n = bytes.len() / 4;
            for level in [1, -1, -2] {
                for k in 0..4 {
                    let plane = &filtered[k * n..(k + 1) * n];
                    time(&format!("plane {k}, zstd {level}"), &|| {
                        4 * zstd::bulk::compress(plane, level).unwrap().len()
                    });
                }
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
