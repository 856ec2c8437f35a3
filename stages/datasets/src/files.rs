//! Sensor file formats shared by the dataset readers: JPEG images and NumPy `.npy` / `.npz`,
//! and the one way they read a file of a dataset ([`read_input`]): regular files only, and never
//! more bytes than the format allows.

use crate::checks::{MAX_IMAGE_FILE_BYTES, MAX_NPZ_MEMBER_BYTES};
use anyhow::{bail, ensure, Context, Result};
use dist4d_types::artifact::Image;
use std::io::Read;
use std::path::Path;

/// Reads a file of a dataset whole: `what` says what it is (`a LiDAR sweep`) for the errors, and
/// `max_bytes` is the most such a file may hold (the bounds are in [`crate::checks`]).
///
/// Only a regular file is read ([`dist4d_runtime::regular_file`]: a FIFO or `/dev/zero` fails at
/// once), and at most `max_bytes` + 1 bytes, so a file that grows while it is read cannot exhaust
/// memory.
pub fn read_input(path: &Path, what: &str, max_bytes: u64) -> Result<Vec<u8>> {
    let file = open_regular(path, what, max_bytes)?;
    let len = file.metadata().map(|m| m.len()).unwrap_or(0);
    let mut bytes = Vec::with_capacity(len.min(max_bytes) as usize);
    file.take(max_bytes + 1).read_to_end(&mut bytes).with_context(|| format!("reading {what} {}", path.display()))?;
    ensure!(
        bytes.len() as u64 <= max_bytes,
        "{what} {} grew past the {max_bytes} bytes such a file may have while it was read",
        path.display()
    );
    Ok(bytes)
}

/// Opens a regular file of at most `max_bytes` without blocking (see [`read_input`]).
fn open_regular(path: &Path, what: &str, max_bytes: u64) -> Result<std::fs::File> {
    let (file, meta) =
        dist4d_runtime::regular_file::open(path).with_context(|| format!("reading {what} {}", path.display()))?;
    ensure!(
        meta.len() <= max_bytes,
        "{what} {} is {} bytes, more than the {max_bytes} bytes such a file may have",
        path.display(),
        meta.len()
    );
    Ok(file)
}

/// Decodes a JPEG (or any image the `image` crate reads) to RGB8.
///
/// A JPEG must end with its end-of-image marker: the decoder fills a truncated file's missing
/// rows with grey without an error, which would reach the pipeline as plausible-looking pixels.
pub fn read_jpeg(path: &Path) -> Result<Image> {
    let (bytes, w, h) = read_image_header(path)?;
    decode_image(path, &bytes, w, h)
}

/// A camera image whose size must be the one its metadata gives (`width` x `height`, skipped when
/// 0): `source` names that metadata, e.g. `sample_data <token>`. Checked here, where the file is
/// known, rather than in a stage that only sees two sizes disagree; and checked on the header,
/// before a single pixel is decoded, so a header that says 65535 x 65535 cannot make the decoder
/// allocate 12 GB.
pub fn read_camera_image(path: &Path, width: u32, height: u32, source: &str) -> Result<Image> {
    let (bytes, w, h) = read_image_header(path).with_context(|| source.to_string())?;
    if width > 0 && height > 0 && (w, h) != (width, height) {
        bail!("{} is {w}x{h} but {source} (fields width, height) says {width}x{height}", path.display());
    }
    decode_image(path, &bytes, w, h).with_context(|| source.to_string())
}

/// A camera image held in memory (`bytes`, e.g. a row of a log), checked and decoded as
/// [`read_camera_image`] does a file; `source` names where the bytes are (file and row).
pub fn decode_camera_image(bytes: &[u8], width: u32, height: u32, source: &str) -> Result<Image> {
    let place = Path::new(source);
    check_jpeg_end(bytes).with_context(|| format!("{source} is truncated"))?;
    let (w, h) = image::ImageReader::new(std::io::Cursor::new(bytes))
        .with_guessed_format()
        .map_err(anyhow::Error::from)
        .and_then(|r| Ok(r.into_dimensions()?))
        .with_context(|| format!("{source} is not a readable image (its header)"))?;
    crate::checks::image_size(source, "its header", w, h).map_err(anyhow::Error::msg)?;
    if width > 0 && height > 0 && (w, h) != (width, height) {
        bail!("{source} is {w}x{h} but its metadata says {width}x{height}");
    }
    decode_image(place, bytes, w, h)
}

/// A whole image file and the size its header declares (within the bounds of
/// [`crate::checks::image_size`]).
fn read_image_header(path: &Path) -> Result<(Vec<u8>, u32, u32)> {
    let bytes = read_input(path, "the image", MAX_IMAGE_FILE_BYTES)?;
    check_jpeg_end(&bytes).with_context(|| format!("{} is truncated", path.display()))?;
    let (w, h) = image::ImageReader::new(std::io::Cursor::new(&bytes))
        .with_guessed_format()
        .map_err(anyhow::Error::from)
        .and_then(|r| Ok(r.into_dimensions()?))
        .with_context(|| format!("{} is not a readable image (its header)", path.display()))?;
    crate::checks::image_size(&path.display().to_string(), "its header", w, h).map_err(anyhow::Error::msg)?;
    Ok((bytes, w, h))
}

/// Decodes an image whose header said `w` x `h`. A decoder that cannot read the scan data (a
/// corrupt JPEG) is an error, never grey or partial pixels.
fn decode_image(path: &Path, bytes: &[u8], w: u32, h: u32) -> Result<Image> {
    let rgb = if bytes.starts_with(&[0xFF, 0xD8]) {
        decode_jpeg_strictly(bytes).with_context(|| format!("{} is not a readable JPEG", path.display()))?
    } else {
        let img =
            image::load_from_memory(bytes).with_context(|| format!("{} is not a readable image", path.display()))?;
        img.into_rgb8().into_raw()
    };
    ensure!(
        rgb.len() as u64 == w as u64 * h as u64 * 3,
        "{} decoded to {} bytes though its header says {w}x{h} RGB",
        path.display(),
        rgb.len()
    );
    Ok(Image { width: w, height: h, rgb })
}

/// A JPEG decoded to RGB8 in zune-jpeg's strict mode. The `image` crate decodes leniently: corrupt
/// scan data (a flipped bit in the entropy-coded segment, a bad Huffman code) becomes grey or
/// smeared blocks without an error, which would reach the pipeline as plausible pixels.
fn decode_jpeg_strictly(bytes: &[u8]) -> Result<Vec<u8>> {
    use zune_core::{bytestream::ZCursor, colorspace::ColorSpace, options::DecoderOptions};
    let options = DecoderOptions::default()
        .set_strict_mode(true)
        .jpeg_set_out_colorspace(ColorSpace::RGB)
        .set_max_width(crate::checks::MAX_IMAGE_SIDE as usize)
        .set_max_height(crate::checks::MAX_IMAGE_SIDE as usize);
    let mut decoder = zune_jpeg::JpegDecoder::new_with_options(ZCursor::new(bytes), options);
    decoder.decode().map_err(|e| anyhow::anyhow!("{e:?}"))
}

/// The width and height an image file's header declares, without decoding it: how a camera's
/// calibration learns that the metadata's size is the file's, for stages that never decode it.
pub fn image_dimensions(path: &Path) -> Result<(u32, u32)> {
    // Buffered, so the decoder reads the header's blocks and no more (a whole JPEG would double
    // the image reads of a run).
    let file = open_regular(path, "the image", MAX_IMAGE_FILE_BYTES)?;
    image::ImageReader::new(std::io::BufReader::with_capacity(16 << 10, file))
        .with_guessed_format()
        .map_err(anyhow::Error::from)
        .and_then(|r| Ok(r.into_dimensions()?))
        .with_context(|| format!("{} is not a readable image (its header)", path.display()))
}

/// A JPEG (it starts with the SOI marker FF D8) must end with the EOI marker FF D9. Zero bytes
/// after it are allowed: some writers pad files to a block size. Other formats pass unchecked.
fn check_jpeg_end(bytes: &[u8]) -> Result<()> {
    if !bytes.starts_with(&[0xFF, 0xD8]) {
        return Ok(());
    }
    // Cameras and tools may append bytes after the end marker (padding, a newline, metadata).
    // Inside the compressed data a 0xFF is always followed by 0x00 or a restart marker, so an
    // FF D9 near the end is the end-of-image marker of a whole file.
    let tail = &bytes[bytes.len().saturating_sub(JPEG_TRAILER_MAX)..];
    ensure!(
        tail.windows(2).any(|w| w == [0xFF, 0xD9]),
        "the JPEG has no end-of-image marker (FF D9) in the last {} of its {} bytes",
        tail.len(),
        bytes.len()
    );
    Ok(())
}

/// How many bytes after the end-of-image marker a JPEG may carry and still count as whole.
const JPEG_TRAILER_MAX: usize = 4096;

/// A numeric array from an `.npy` file: shape and values as f64.
#[derive(Debug, PartialEq)]
pub struct NpyArray {
    pub shape: Vec<usize>,
    pub data: Vec<f64>,
}

/// Parses NPY v1/v2/v3 bytes of little-endian `<f4` or `<f8`, C order.
pub fn parse_npy(bytes: &[u8]) -> Result<NpyArray> {
    ensure!(bytes.len() >= 10 && &bytes[..6] == b"\x93NUMPY", "not an NPY array");
    let (hlen, start) = match bytes[6] {
        1 => (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10),
        2 | 3 => {
            ensure!(bytes.len() >= 12, "NPY header is truncated");
            (u32::from_le_bytes(bytes[8..12].try_into()?) as usize, 12)
        }
        v => bail!("NPY version {v} is not supported"),
    };
    let header = std::str::from_utf8(bytes.get(start..start + hlen).context("NPY header is truncated")?)?;
    let field = |name: &str| -> Result<&str> {
        let i = header.find(&format!("'{name}'")).with_context(|| format!("NPY header lacks '{name}'"))?;
        Ok(header[i + name.len() + 2..].trim_start().trim_start_matches(':').trim_start())
    };
    let descr = field("descr")?;
    let width = if descr.starts_with("'<f8'") {
        8
    } else if descr.starts_with("'<f4'") {
        4
    } else {
        bail!("NPY dtype {} is not supported (need <f4 or <f8)", descr.split(',').next().unwrap_or(""))
    };
    ensure!(field("fortran_order")?.starts_with("False"), "Fortran-ordered NPY arrays are not supported");
    let shape_text = field("shape")?;
    let shape_text = &shape_text[1..shape_text.find(')').context("NPY shape is malformed")?];
    let shape: Vec<usize> = shape_text
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(|s| s.parse::<usize>().with_context(|| format!("NPY shape entry `{s}`")))
        .collect::<Result<_>>()?;
    // Checked products: a header may claim any shape, and the body is what bounds it.
    let n = shape.iter().try_fold(1usize, |n, d| n.checked_mul(*d)).context("NPY shape overflows")?;
    let body = &bytes[start + hlen..];
    let need = n.checked_mul(width).context("NPY shape overflows")?;
    ensure!(body.len() >= need, "NPY data is truncated: {} bytes for {n} values", body.len());
    let data = if width == 8 {
        body.chunks_exact(8).take(n).map(|c| f64::from_le_bytes(c.try_into().unwrap())).collect()
    } else {
        body.chunks_exact(4).take(n).map(|c| f32::from_le_bytes(c.try_into().unwrap()) as f64).collect()
    };
    Ok(NpyArray { shape, data })
}

/// Reads array `key` (e.g. `data`) from an `.npz` (a zip of `.npy` files, stored or deflated).
pub fn read_npz(path: &Path, key: &str) -> Result<NpyArray> {
    let bytes = read_input(path, "the .npz", crate::checks::MAX_SENSOR_FILE_BYTES)?;
    let member = zip_member(&bytes, &format!("{key}.npy"))
        .with_context(|| format!("{} is not a readable .npz", path.display()))?;
    parse_npy(&member).with_context(|| format!("{}: array `{key}`", path.display()))
}

/// The `.npy` bytes of array `key` in `.npz` bytes, for readers of other dtypes than
/// [`parse_npy`]'s (e.g. `dist4d_types::formats::read_npy_u8`).
pub fn npz_member(npz: &[u8], key: &str) -> Result<Vec<u8>> {
    zip_member(npz, &format!("{key}.npy")).with_context(|| format!("array `{key}` of the .npz"))
}

/// One member of a zip archive, found through the central directory.
fn zip_member(zip: &[u8], name: &str) -> Result<Vec<u8>> {
    let u16at = |i: usize| -> Result<usize> {
        Ok(u16::from_le_bytes(zip.get(i..i + 2).context("zip is truncated")?.try_into()?) as usize)
    };
    let u32at = |i: usize| -> Result<usize> {
        Ok(u32::from_le_bytes(zip.get(i..i + 4).context("zip is truncated")?.try_into()?) as usize)
    };
    // End of central directory: the last "PK\x05\x06" (a comment of up to 64 KiB may follow).
    let eocd = (0..zip.len().saturating_sub(21))
        .rev()
        .take(65_558)
        .find(|&i| zip[i..i + 4] == *b"PK\x05\x06")
        .context("no zip end record")?;
    let (entries, mut at) = (u16at(eocd + 10)?, u32at(eocd + 16)?);
    for _ in 0..entries {
        ensure!(zip.get(at..at + 4) == Some(b"PK\x01\x02"), "zip central directory is malformed");
        let (method, csize, size) = (u16at(at + 10)?, u32at(at + 20)?, u32at(at + 24)?);
        let (nlen, xlen, clen, local) = (u16at(at + 28)?, u16at(at + 30)?, u16at(at + 32)?, u32at(at + 42)?);
        let entry = zip.get(at + 46..at + 46 + nlen).context("zip is truncated")?;
        if entry == name.as_bytes() {
            ensure!(zip.get(local..local + 4) == Some(b"PK\x03\x04"), "zip local header is malformed");
            let data_at = local + 30 + u16at(local + 26)? + u16at(local + 28)?;
            let raw = zip.get(data_at..data_at + csize).context("zip member is truncated")?;
            return match method {
                0 => Ok(raw.to_vec()),
                8 => {
                    ensure!(
                        size as u64 <= MAX_NPZ_MEMBER_BYTES,
                        "{name} inflates to {size} bytes, more than the {MAX_NPZ_MEMBER_BYTES} an array may have"
                    );
                    let out = miniz_oxide::inflate::decompress_to_vec_with_limit(raw, size.max(1))
                        .map_err(|e| anyhow::anyhow!("inflating {name}: {e:?}"))?;
                    ensure!(out.len() == size, "{name}: inflated {} bytes, expected {size}", out.len());
                    Ok(out)
                }
                m => bail!("{name}: zip compression method {m} is not supported"),
            };
        }
        at += 46 + nlen + xlen + clen;
    }
    bail!("no member {name}")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn npy_headers_are_parsed_and_bad_ones_rejected() {
        let mut b = b"\x93NUMPY\x01\x00".to_vec();
        let header = "{'descr': '<f4', 'fortran_order': False, 'shape': (2, 2), }";
        b.extend_from_slice(&(header.len() as u16).to_le_bytes());
        b.extend_from_slice(header.as_bytes());
        for x in [1.0f32, 2.0, 3.0, 4.5] {
            b.extend_from_slice(&x.to_le_bytes());
        }
        assert_eq!(parse_npy(&b).unwrap(), NpyArray { shape: vec![2, 2], data: vec![1.0, 2.0, 3.0, 4.5] });
        assert!(parse_npy(&b[..b.len() - 2]).unwrap_err().to_string().contains("truncated"));
        assert!(parse_npy(&b"\x93NUMPY\x01\x00\x05\x00{'a'}"[..]).is_err());
    }

    fn tiny_jpeg() -> Vec<u8> {
        let rgb: Vec<u8> = (0..64 * 48 * 3).map(|i| (i * 7 % 251) as u8).collect();
        let mut jpeg = Vec::new();
        image::codecs::jpeg::JpegEncoder::new_with_quality(&mut jpeg, 90)
            .encode(&rgb, 64, 48, image::ExtendedColorType::Rgb8)
            .unwrap();
        jpeg
    }

    #[test]
    fn a_truncated_jpeg_is_an_error_naming_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("cam.jpg");
        let jpeg = tiny_jpeg();
        std::fs::write(&f, &jpeg).unwrap();
        assert_eq!(read_jpeg(&f).unwrap().width, 64);
        // Zero padding after the end-of-image marker is fine.
        std::fs::write(&f, [jpeg.as_slice(), &[0u8; 16]].concat()).unwrap();
        assert!(read_jpeg(&f).is_ok());
        // So are a newline or a few bytes of metadata after it.
        std::fs::write(&f, [jpeg.as_slice(), b"\nexif trailer"].concat()).unwrap();
        assert!(read_jpeg(&f).is_ok());
        std::fs::write(&f, &jpeg[..jpeg.len() / 2]).unwrap();
        let err = format!("{:#}", read_jpeg(&f).unwrap_err());
        assert!(err.contains(&format!("{} is truncated", f.display())), "{err}");
        assert!(err.contains("no end-of-image marker (FF D9)"), "{err}");
    }

    #[test]
    fn a_camera_image_of_the_wrong_size_names_the_file_and_both_sizes() {
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("cam.jpg");
        std::fs::write(&f, tiny_jpeg()).unwrap();
        assert!(read_camera_image(&f, 64, 48, "sample_data abc").is_ok());
        assert!(read_camera_image(&f, 0, 0, "sample_data abc").is_ok(), "size unknown: not checked");
        let err = read_camera_image(&f, 1600, 900, "sample_data abc").unwrap_err().to_string();
        assert_eq!(err, format!("{} is 64x48 but sample_data abc (fields width, height) says 1600x900", f.display()));
    }

    #[test]
    fn reads_the_shared_dgp_npz() {
        let dir =
            Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/data/dgp-scene02/scene_02/point_cloud/LIDAR");
        let Ok(entries) = std::fs::read_dir(&dir) else {
            eprintln!("SKIPPED: shared DGP data not found at {}", dir.display());
            return;
        };
        let mut files: Vec<_> = entries.map(|e| e.unwrap().path()).collect();
        files.sort();
        let a = read_npz(&files[0], "data").unwrap();
        assert_eq!(a.shape.len(), 2);
        assert_eq!(a.shape[1], 4);
        assert!((40_000..48_000).contains(&a.shape[0]), "{:?}", a.shape);
        assert!(read_npz(&files[0], "nope").is_err());
    }
}
