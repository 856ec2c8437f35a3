//! File formats dist4d writes, shared by the stages that export them and the synthetic world that
//! writes its ground truth: OpenEXR depth, 16-bit PNG depth, NPY arrays.

use crate::artifact::DepthMap;
pub use crate::npy::{npy_f32, npy_f64, npy_u8, npz, read_npy_f32, read_npy_u8};
use anyhow::{Context, Result};
pub use png;

/// OpenEXR, one float32 channel `Y`, ZIP-compressed (blocks of 16 scanlines). `Y`, not `Z`:
/// OpenCV (`cv2.imread(path, IMREAD_UNCHANGED)`, how most users open an EXR) reads a lone `Y`
/// channel as a grey float image and returns zeros for a lone `Z`; the OpenEXR bindings and readers
/// that take the first channel read either.
///
/// Written here rather than with the `exr` crate (which reads them): a one-channel scanline file
/// is a fixed header, an offset table and blocks, and its deflate level is ours to choose. The
/// blocks are compressed in parallel at deflate level 1 (~3x faster than the `exr` crate's
/// level 4, files ~15% larger); see [`exr_zip_block`].
pub fn depth_exr(d: &DepthMap) -> Result<Vec<u8>> {
    depth_exr_with(d, ExrCompression::Zip)
}

/// How [`depth_exr_with`] compresses the pixels.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ExrCompression {
    /// ZIP_COMPRESSION, blocks of 16 scanlines, deflate level 1 (0.75-0.9 of the raw size for a
    /// curated 1600x900 map with full float bits, ~20 ms).
    Zip,
    /// PXR24_COMPRESSION, blocks of 16 scanlines: each float rounded to 24 bits (16 significant),
    /// differences along the row split into byte planes, deflated by runs and literals
    /// ([`crate::deflate_rle`]). Exact for values that already have 16 significant bits
    /// ([`has_16_significant_bits`], what CompleteDepth makes): ~0.35 of the raw size for a
    /// curated map, ~10 ms. Other values lose their low 8 bits (except in a block that does not
    /// compress, which is stored as its floats).
    Pxr24,
    /// NO_COMPRESSION, one scanline per block: the floats as they are (~1 ms; 5.8 MB at 1600x900).
    None,
}

/// [`depth_exr`] with a choice of compression.
pub fn depth_exr_with(d: &DepthMap, compression: ExrCompression) -> Result<Vec<u8>> {
    use rayon::prelude::*;
    let (w, h) = (d.width as usize, d.height as usize);
    anyhow::ensure!(d.data.len() == w * h && w > 0 && h > 0, "depth map size {}x{} with {} values", w, h, d.data.len());
    let (lines, code) = match compression {
        ExrCompression::Zip => (16, 3u8),
        ExrCompression::Pxr24 => (16, 5u8),
        ExrCompression::None => (1, 0u8),
    };
    let blocks: Vec<Vec<u8>> = match compression {
        ExrCompression::Zip => d.data.par_chunks(w * lines).map(exr_zip_block).collect(),
        ExrCompression::Pxr24 => d.data.par_chunks(w * lines).map(|b| exr_pxr24_block(b, w)).collect(),
        ExrCompression::None => {
            d.data.chunks(w).map(|row| row.iter().flat_map(|v| v.to_le_bytes()).collect()).collect()
        }
    };
    let mut out = Vec::with_capacity(400 + 8 * blocks.len() + blocks.iter().map(|b| b.len() + 8).sum::<usize>());
    out.extend_from_slice(&[0x76, 0x2f, 0x31, 0x01, 2, 0, 0, 0]);
    let mut attr = |name: &str, ty: &str, value: &[u8]| {
        out.extend_from_slice(name.as_bytes());
        out.push(0);
        out.extend_from_slice(ty.as_bytes());
        out.push(0);
        out.extend_from_slice(&(value.len() as i32).to_le_bytes());
        out.extend_from_slice(value);
    };
    // Channel `Y`: FLOAT (2), not linear, sampling 1x1; the list ends with an empty name.
    let mut chlist = b"Y\0".to_vec();
    for x in [2i32, 0, 1, 1] {
        chlist.extend_from_slice(&x.to_le_bytes());
    }
    chlist.push(0);
    attr("channels", "chlist", &chlist);
    attr("compression", "compression", &[code]);
    let window: Vec<u8> = [0i32, 0, w as i32 - 1, h as i32 - 1].iter().flat_map(|x| x.to_le_bytes()).collect();
    attr("dataWindow", "box2i", &window);
    attr("displayWindow", "box2i", &window);
    attr("lineOrder", "lineOrder", &[0]); // INCREASING_Y
    attr("pixelAspectRatio", "float", &1f32.to_le_bytes());
    attr("screenWindowCenter", "v2f", &[0u8; 8]);
    attr("screenWindowWidth", "float", &1f32.to_le_bytes());
    out.push(0);
    let mut at = (out.len() + 8 * blocks.len()) as u64;
    for b in &blocks {
        out.extend_from_slice(&at.to_le_bytes());
        at += 8 + b.len() as u64;
    }
    for (i, b) in blocks.iter().enumerate() {
        out.extend_from_slice(&((i * lines) as i32).to_le_bytes());
        out.extend_from_slice(&(b.len() as i32).to_le_bytes());
        out.extend_from_slice(b);
    }
    Ok(out)
}

/// One block of EXR ZIP compression: the scanlines' bytes (little-endian floats) split into even
/// and odd bytes, delta-coded (OpenEXR's predictor), then zlib. A block that does not shrink is
/// stored as it is, which readers recognise by its size.
fn exr_zip_block(values: &[f32]) -> Vec<u8> {
    // Bytes 0 and 2 of each float are the even bytes of the block, 1 and 3 the odd ones.
    let n = values.len();
    let mut t = vec![0u8; 4 * n];
    let (even, odd) = t.split_at_mut(2 * n);
    for ((v, e), o) in values.iter().zip(even.chunks_exact_mut(2)).zip(odd.chunks_exact_mut(2)) {
        let b = v.to_le_bytes();
        e.copy_from_slice(&[b[0], b[2]]);
        o.copy_from_slice(&[b[1], b[3]]);
    }
    let mut prev = t[0];
    for x in &mut t[1..] {
        let cur = *x;
        *x = cur.wrapping_sub(prev).wrapping_add(128);
        prev = cur;
    }
    let z = zlib(&t, 1, miniz_oxide::deflate::core::CompressionStrategy::Default);
    if z.len() < 4 * n {
        z
    } else {
        values.iter().flat_map(|v| v.to_le_bytes()).collect()
    }
}

/// `v` rounded to the nearest float with 16 significant bits (the low 8 of its 24 zero), which
/// PXR24 stores exactly: at most 2^-16 = 1.5e-5 off, relative (1 mm at 80 m), finer than the
/// PNG16's 1/256 m below 128 m. CompleteDepth rounds every depth it outputs so: the bits below are
/// its solver's noise (its last conjugate-gradient step moves depths by far more), and they made a
/// curated map's EXR incompressible; without them EncodeDepth writes it as PXR24 in ~0.4 of the
/// bytes of a ZIP of the full floats, in half the time (docs/BENCHMARKS.md, "Store and encoders"), and
/// the store's copy shrinks too. Positive finite `v` only (a carry into the exponent is the correct
/// rounding).
pub fn to_16_significant_bits(v: f32) -> f32 {
    f32::from_bits((v.to_bits() + 0x80) & !0xFF)
}

/// Whether every value is a float with 16 significant bits (its low 8 bits zero), which PXR24
/// stores exactly.
pub fn has_16_significant_bits(values: &[f32]) -> bool {
    values.iter().fold(0u32, |acc, v| acc | v.to_bits()) & 0xFF == 0
}

/// OpenEXR's float-to-24-bit conversion for PXR24 (ImfPxr24Compressor, Loren Carpenter's): the
/// significand rounded to 15 bits, truncated instead where rounding would overflow the exponent;
/// a NaN keeps a significand bit so that it does not become an infinity.
fn float24(v: f32) -> u32 {
    let u = v.to_bits();
    let (s, e, m) = (u & 0x8000_0000, u & 0x7F80_0000, u & 0x007F_FFFF);
    let i = if e == 0x7F80_0000 {
        let m = m >> 8;
        (e >> 8) | m | u32::from(m == 0 && (u & 0x007F_FFFF) != 0)
    } else {
        let rounded = ((e | m) + (m & 0x80)) >> 8;
        if rounded >= 0x7F_8000 {
            (e | m) >> 8
        } else {
            rounded
        }
    };
    (s >> 8) | i
}

/// One block of EXR PXR24 compression of a lone FLOAT channel, rows of `w` values: per row, the
/// differences of each 24-bit value from its left neighbour (from 0 at the row's start), their
/// high, middle and low bytes as three planes of `w` bytes; the rows one after the other, then
/// zlib ([`crate::deflate_rle`]: as small as miniz_oxide's level 1 on these planes, in ~0.65 of
/// its time). A block that does not shrink below its floats is stored as the floats.
fn exr_pxr24_block(values: &[f32], w: usize) -> Vec<u8> {
    let z = crate::deflate_rle::zlib_rle(&pxr24_planes(values, w));
    if z.len() < 4 * values.len() {
        z
    } else {
        values.iter().flat_map(|v| v.to_le_bytes()).collect()
    }
}

/// The byte planes of a PXR24 block before its deflate (see [`exr_pxr24_block`]).
fn pxr24_planes(values: &[f32], w: usize) -> Vec<u8> {
    // Values with 16 significant bits convert by a shift (no rounding, no overflow, and an
    // infinity or a NaN keeps its bits), which vectorises; others take OpenEXR's conversion.
    if has_16_significant_bits(values) {
        planes_of(values, w, |v| v.to_bits() >> 8)
    } else {
        planes_of(values, w, float24)
    }
}

fn planes_of(values: &[f32], w: usize, to24: impl Fn(f32) -> u32) -> Vec<u8> {
    let mut t = vec![0u8; 3 * values.len()];
    for (row, planes) in values.chunks(w).zip(t.chunks_mut(3 * w)) {
        let (hi, rest) = planes.split_at_mut(w);
        let (mid, lo) = rest.split_at_mut(w);
        let mut prev = 0u32;
        for (((&v, h), m), l) in row.iter().zip(hi).zip(mid).zip(lo) {
            let p = to24(v);
            let d = p.wrapping_sub(prev);
            prev = p;
            (*h, *m, *l) = ((d >> 16) as u8, (d >> 8) as u8, d as u8);
        }
    }
    t
}

/// zlib stream of `input` (miniz_oxide) with a given level and match strategy.
fn zlib(mut input: &[u8], level: u8, strategy: miniz_oxide::deflate::core::CompressionStrategy) -> Vec<u8> {
    use miniz_oxide::deflate::core::{
        compress, create_comp_flags_from_zip_params, CompressorOxide, TDEFLFlush, TDEFLStatus,
    };
    let mut c = CompressorOxide::new(create_comp_flags_from_zip_params(level.into(), 1, strategy as i32));
    let mut out = vec![0u8; input.len() / 2 + 64];
    let mut at = 0;
    loop {
        let (status, read, wrote) = compress(&mut c, input, &mut out[at..], TDEFLFlush::Finish);
        at += wrote;
        input = &input[read..];
        match status {
            TDEFLStatus::Done => break,
            TDEFLStatus::Okay => {
                if out.len() - at < 64 {
                    out.resize(out.len() * 2, 0);
                }
            }
            _ => unreachable!("compressing into a growing vector cannot fail"),
        }
    }
    out.truncate(at);
    out
}

/// 16-bit grey PNG of depth x 256 (see [`png_bytes`]).
pub fn depth_png16(d: &DepthMap) -> Result<Vec<u8>> {
    let mut px = vec![0u8; 2 * d.data.len()];
    for (&z, be) in d.data.iter().zip(px.chunks_exact_mut(2)) {
        // Clamped first, then rounded half up by truncation: in [1, 65535] adding 0.5 is exact, so
        // this is `round().clamp()`, and it vectorises (a float-to-int cast per lane; `round` then a
        // cast to u16 went lane by lane, 2% of the chain's CPU).
        let v = if z > 0.0 && z.is_finite() { ((z * 256.0).clamp(1.0, 65535.0) + 0.5) as i32 } else { 0 };
        be.copy_from_slice(&(v as u16).to_be_bytes());
    }
    png_bytes(d.width, d.height, &px, png::ColorType::Grayscale, png::BitDepth::Sixteen)
}

/// A PNG of `px` (rows of samples; 16-bit ones big-endian, as PNG stores them) with the fast
/// deflate of the `png` crate (fdeflate) and the Paeth filter: on a 1600x900 depth map as small as
/// zlib's default level with adaptive filtering (the `image` crate's default), in less time; Up or
/// Sub alone leave it 1.5-3x larger.
pub fn png_bytes(width: u32, height: u32, px: &[u8], color: png::ColorType, depth: png::BitDepth) -> Result<Vec<u8>> {
    let mut out = Vec::new();
    let mut enc = png::Encoder::new(&mut out, width, height);
    enc.set_color(color);
    enc.set_depth(depth);
    enc.set_compression(png::Compression::Fast);
    enc.set_filter(png::Filter::Paeth);
    let mut w = enc.write_header().context("encoding PNG")?;
    w.write_image_data(px).context("encoding PNG")?;
    w.finish().context("encoding PNG")?;
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An EXR file as the exr crate reads it (every channel of its first layer).
    fn read_exr(
        bytes: Vec<u8>,
    ) -> exr::image::Image<exr::image::Layer<exr::image::AnyChannels<exr::image::FlatSamples>>> {
        use exr::prelude::*;
        read()
            .no_deep_data()
            .largest_resolution_level()
            .all_channels()
            .first_valid_layer()
            .all_attributes()
            .from_buffered(std::io::Cursor::new(bytes))
            .unwrap()
    }

    #[test]
    fn exrs_of_many_blocks_with_a_partial_last_one_read_back_exactly() {
        use exr::prelude::*;
        let (w, h) = (173usize, 37usize);
        let data: Vec<f32> = (0..w * h)
            .map(|i| match i % 97 {
                0 => f32::INFINITY,
                1 => 0.0,
                _ => 1.0 + (i as f32 * 0.37).sin().abs() * 80.0,
            })
            .collect();
        let d = DepthMap { width: w as u32, height: h as u32, data };
        let img = read_exr(depth_exr(&d).unwrap());
        assert_eq!(img.layer_data.size, Vec2(w, h));
        let FlatSamples::F32(v) = &img.layer_data.channel_data.list[0].sample_data else { panic!("float32") };
        assert!(v.iter().zip(&d.data).all(|(a, b)| a.to_bits() == b.to_bits()));
        let none = depth_exr_with(&d, ExrCompression::None).unwrap();
        assert!(none.len() > 4 * w * h);
        let img = read_exr(none);
        assert_eq!(img.layer_data.encoding.compression, Compression::Uncompressed);
        let FlatSamples::F32(v) = &img.layer_data.channel_data.list[0].sample_data else { panic!("float32") };
        assert!(v.iter().zip(&d.data).all(|(a, b)| a.to_bits() == b.to_bits()));
        // A constant map compresses; noise is stored in blocks as it is: both read back.
        for data in [
            vec![7.5f32; w * h],
            (0..w * h).map(|i| f32::from_bits(0x3f80_0000 ^ (i as u32).wrapping_mul(2654435761) >> 9)).collect(),
        ] {
            let d = DepthMap { width: w as u32, height: h as u32, data };
            let img = read_exr(depth_exr(&d).unwrap());
            let FlatSamples::F32(v) = &img.layer_data.channel_data.list[0].sample_data else { panic!("float32") };
            assert!(v.iter().zip(&d.data).all(|(a, b)| a.to_bits() == b.to_bits()));
        }
        assert!(depth_exr(&DepthMap { width: 3, height: 2, data: vec![1.0; 5] }).is_err(), "size mismatch");
    }

    #[test]
    fn pxr24_exrs_read_back_exactly_when_values_have_16_significant_bits() {
        use exr::prelude::*;
        let (w, h) = (173usize, 37usize);
        let smooth: Vec<f32> = (0..w * h)
            .map(|i| match i % 97 {
                0 => f32::INFINITY,
                1 => 0.0,
                _ => to_16_significant_bits(1.0 + (i as f32 * 0.37).sin().abs() * 80.0),
            })
            .collect();
        let noise: Vec<f32> = (0..w * h)
            .map(|i| f32::from_bits(0x3f80_0000 ^ (i as u32).wrapping_mul(2654435761) >> 9 & !0xFF))
            .collect();
        for (what, data) in [("smooth", smooth), ("constant", vec![7.5f32; w * h]), ("noise (stored)", noise)] {
            assert!(has_16_significant_bits(&data), "{what}");
            let d = DepthMap { width: w as u32, height: h as u32, data };
            let bytes = depth_exr_with(&d, ExrCompression::Pxr24).unwrap();
            let img = read_exr(bytes);
            assert_eq!(img.layer_data.encoding.compression, Compression::PXR24, "{what}");
            let FlatSamples::F32(v) = &img.layer_data.channel_data.list[0].sample_data else { panic!("float32") };
            assert!(v.iter().zip(&d.data).all(|(a, b)| a.to_bits() == b.to_bits()), "{what}");
        }
        // Full float bits lose their low 8, rounded as OpenEXR rounds them.
        let full: Vec<f32> = (0..w * h).map(|i| 0.5 + i as f32 * 0.0137).collect();
        assert!(!has_16_significant_bits(&full));
        let d = DepthMap { width: w as u32, height: h as u32, data: full };
        let img = read_exr(depth_exr_with(&d, ExrCompression::Pxr24).unwrap());
        let FlatSamples::F32(v) = &img.layer_data.channel_data.list[0].sample_data else { panic!("float32") };
        assert!(v.iter().zip(&d.data).all(|(a, b)| a.to_bits() == float24(*b) << 8));
        assert!(v.iter().zip(&d.data).all(|(a, b)| ((a - b) / b).abs() <= 1.0 / 65536.0));
        // The conversion's edge cases: infinity stays, a NaN stays a NaN, the largest float does
        // not round up into infinity.
        assert_eq!(f32::from_bits(float24(f32::INFINITY) << 8), f32::INFINITY);
        assert!(f32::from_bits(float24(f32::from_bits(0x7F80_0001)) << 8).is_nan());
        assert_eq!(f32::from_bits(float24(f32::MAX) << 8), f32::from_bits(0x7F7F_FF00));
    }

    #[test]
    fn png16_depths_are_rounded_half_away_from_zero_and_clamped() {
        let mut rng = crate::rng::Rng::new(9);
        let mut data: Vec<f32> = (0..5000).map(|_| rng.range(0.0, 300.0) as f32).collect();
        // Exact halves (x.5 / 256 m), the clamp's ends, and what has no depth.
        data.extend([1.001_953_1, 2.5 / 256.0, 0.001, 255.99, 256.0, 1e9, 0.0, -3.0, f32::INFINITY, f32::NAN]);
        data.extend((0..1000).map(|i| (i as f32 + 0.5) / 256.0 + 1.0));
        let (w, h) = (data.len() as u32, 1);
        let bytes = depth_png16(&DepthMap { width: w, height: h, data: data.clone() }).unwrap();
        let decoder = png::Decoder::new(std::io::Cursor::new(bytes));
        let mut reader = decoder.read_info().unwrap();
        let mut px = vec![0u8; reader.output_buffer_size().unwrap()];
        reader.next_frame(&mut px).unwrap();
        for (i, &z) in data.iter().enumerate() {
            let want = if z > 0.0 && z.is_finite() { (z * 256.0).round().clamp(1.0, 65535.0) as u16 } else { 0 };
            assert_eq!(u16::from_be_bytes([px[2 * i], px[2 * i + 1]]), want, "{z}");
        }
    }

    /// Encoder sizes and times on a real depth map: `DIST4D_DEPTH=path cargo test --release -p
    /// dist4d-types encoder_speed -- --ignored --nocapture` (sky, +inf, set to 100 m as curated).
    #[test]
    #[ignore]
    fn encoder_speed() {
        use exr::prelude::*;
        let path = std::env::var("DIST4D_DEPTH").expect("DIST4D_DEPTH: an .exr or .npy depth map");
        let (w, h, v) = if path.ends_with(".npy") {
            let (shape, v) = read_npy_f32(&std::fs::read(&path).unwrap()).unwrap();
            (shape[1], shape[0], v)
        } else {
            let img = read_first_flat_layer_from_file(&path).unwrap();
            let (w, h) = img.layer_data.size.into();
            let FlatSamples::F32(v) = &img.layer_data.channel_data.list[0].sample_data else { panic!() };
            (w, h, v.clone())
        };
        let d = DepthMap {
            width: w as u32,
            height: h as u32,
            data: v.iter().map(|&z| if z.is_finite() { z } else { 100.0 }).collect(),
        };
        // CPU time of the whole process (all threads), not wall: the machine is shared, and other
        // processes' load would count otherwise. /proc/self/stat counts in ticks (10 ms), so each
        // encoder repeats until a second of CPU has passed.
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
            println!("{name:40} {:8.1} ms CPU {:9} bytes", (cpu() - t) * 1e3 / reps as f64, n);
        };
        time("exr crate ZIP16 (before)", &|| {
            let channel = AnyChannel::new("Y", FlatSamples::F32(d.data.clone()));
            let layer = Layer::new(
                (w, h),
                LayerAttributes::named("depth"),
                Encoding::SMALL_LOSSLESS,
                AnyChannels::sort(smallvec::smallvec![channel]),
            );
            let mut out = std::io::Cursor::new(Vec::new());
            Image::from_layer(layer).write().non_parallel().to_buffered(&mut out).unwrap();
            out.into_inner().len()
        });
        time("depth_exr (parallel)", &|| depth_exr(&d).unwrap().len());
        let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap();
        time("depth_exr (1 thread)", &|| pool.install(|| depth_exr(&d).unwrap().len()));
        // The deflate alone, on the blocks as EXR's predictor leaves them.
        let predicted: Vec<Vec<u8>> = d
            .data
            .chunks(w * 16)
            .map(|c| {
                let raw: Vec<u8> = c.iter().flat_map(|v| v.to_le_bytes()).collect();
                let half = raw.len().div_ceil(2);
                let mut t = vec![0u8; raw.len()];
                for (i, b) in raw.iter().enumerate() {
                    t[if i % 2 == 0 { i / 2 } else { half + i / 2 }] = *b;
                }
                for i in (1..t.len()).rev() {
                    t[i] = t[i].wrapping_sub(t[i - 1]).wrapping_add(128);
                }
                t
            })
            .collect();
        use miniz_oxide::deflate::core::CompressionStrategy as S;
        // RLE and Huffman-only strategies leave the blocks at ~0.95 of their size: matches pay.
        for (level, strategy) in [(1u8, S::Default), (4, S::Default)] {
            time(&format!("exr blocks, miniz {level} {strategy:?}"), &|| {
                predicted.iter().map(|t| zlib(t, level, strategy).len()).sum()
            });
        }
        let rounded = DepthMap {
            width: d.width,
            height: d.height,
            data: d.data.iter().map(|&v| to_16_significant_bits(v)).collect(),
        };
        time("depth_exr PXR24, 16-bit values (1 thread)", &|| {
            pool.install(|| depth_exr_with(&rounded, ExrCompression::Pxr24).unwrap().len())
        });
        let planes: Vec<Vec<u8>> = rounded.data.chunks(w * 16).map(|c| pxr24_planes(c, w)).collect();
        time("pxr24 planes, miniz 1", &|| planes.iter().map(|t| zlib(t, 1, S::Default).len()).sum());
        time("pxr24 planes, zlib_rle", &|| planes.iter().map(|t| crate::deflate_rle::zlib_rle(t).len()).sum());
        time("png16 image crate default (before)", &|| {
            let px: Vec<u16> = d.data.iter().map(|&z| (z * 256.0).round().clamp(1.0, 65535.0) as u16).collect();
            let img = image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::from_raw(d.width, d.height, px).unwrap();
            let mut out = std::io::Cursor::new(Vec::new());
            img.write_to(&mut out, image::ImageFormat::Png).unwrap();
            out.into_inner().len()
        });
        time("depth_png16 (fast, Paeth)", &|| depth_png16(&d).unwrap().len());
        for (name, filter) in
            [("Sub", png::Filter::Sub), ("Paeth", png::Filter::Paeth), ("Adaptive", png::Filter::Adaptive)]
        {
            time(&format!("png16 fast {name}"), &|| {
                let px: Vec<u8> = d
                    .data
                    .iter()
                    .flat_map(|&z| ((z * 256.0).round().clamp(1.0, 65535.0) as u16).to_be_bytes())
                    .collect();
                let mut out = Vec::new();
                let mut enc = png::Encoder::new(&mut out, d.width, d.height);
                enc.set_color(png::ColorType::Grayscale);
                enc.set_depth(png::BitDepth::Sixteen);
                enc.set_compression(png::Compression::Fast);
                enc.set_filter(filter);
                let mut wr = enc.write_header().unwrap();
                wr.write_image_data(&px).unwrap();
                wr.finish().unwrap();
                out.len()
            });
        }
        time("npy", &|| npy_f32(&[h, w], &d.data).len());
    }
}
