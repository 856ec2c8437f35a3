//! NumPy's `.npy` arrays and `.npz` archives, written and read with no dependency on the artifact
//! types (which encode a dense depth map as an NPY), so that `artifact` and `formats` can both use
//! them without importing each other.

use anyhow::{Context, Result};

/// The NPY v1.0 magic and header of an array of `descr` (`<f4`, `|u1`) and `shape`, C order,
/// padded so that the data starts at a multiple of 64 bytes.
fn npy_header(descr: &str, shape: &[usize], data_len: usize) -> Vec<u8> {
    let dims = shape.iter().map(|d| d.to_string()).collect::<Vec<_>>().join(", ");
    let shape = if shape.len() == 1 { format!("({dims},)") } else { format!("({dims})") };
    let mut header = format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape}, }}");
    // Magic (6) + version (2) + length (2) + header + '\n' is a multiple of 64.
    while (10 + header.len() + 1) % 64 != 0 {
        header.push(' ');
    }
    header.push('\n');
    let mut out = Vec::with_capacity(10 + header.len() + data_len);
    out.extend_from_slice(b"\x93NUMPY\x01\x00");
    out.extend_from_slice(&(header.len() as u16).to_le_bytes());
    out.extend_from_slice(header.as_bytes());
    out
}

/// NPY v1.0 of a little-endian float32 array.
pub fn npy_f32(shape: &[usize], data: &[f32]) -> Vec<u8> {
    let mut out = npy_header("<f4", shape, 4 * data.len());
    let at = out.len();
    out.resize(at + 4 * data.len(), 0);
    for (x, le) in data.iter().zip(out[at..].chunks_exact_mut(4)) {
        le.copy_from_slice(&x.to_le_bytes());
    }
    out
}

/// NPY v1.0 of a little-endian float64 array (a 4 x 4 pose).
pub fn npy_f64(shape: &[usize], data: &[f64]) -> Vec<u8> {
    let mut out = npy_header("<f8", shape, 8 * data.len());
    for x in data {
        out.extend_from_slice(&x.to_le_bytes());
    }
    out
}

/// NPY v1.0 of a uint8 array (an RGB image H x W x 3, a mask H x W).
pub fn npy_u8(shape: &[usize], data: &[u8]) -> Vec<u8> {
    let mut out = npy_header("|u1", shape, data.len());
    out.extend_from_slice(data);
    out
}

/// The shape and the data bytes of an NPY v1.0 array of `descr` in C order, as numpy writes it,
/// checked to hold `item_size` bytes per element.
fn read_npy<'a>(bytes: &'a [u8], descr: &str, item_size: usize) -> Result<(Vec<usize>, &'a [u8])> {
    anyhow::ensure!(bytes.len() >= 10 && bytes.starts_with(b"\x93NUMPY\x01\x00"), "not an NPY v1.0 file");
    let hlen = u16::from_le_bytes([bytes[8], bytes[9]]) as usize;
    let header = bytes.get(10..10 + hlen).context("NPY header is truncated")?;
    let header = std::str::from_utf8(header).context("NPY header is not text")?;
    anyhow::ensure!(
        header.contains(&format!("'descr': '{descr}'")) && header.contains("'fortran_order': False"),
        "NPY array is not {descr} in C order: {}",
        header.trim()
    );
    let shape = header
        .split_once("'shape': (")
        .and_then(|(_, rest)| rest.split_once(')'))
        .context("NPY header has no shape")?
        .0
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(|s| s.parse::<usize>().with_context(|| format!("NPY shape entry {s:?}")))
        .collect::<Result<Vec<_>>>()?;
    let n = shape.iter().try_fold(1usize, |a, &b| a.checked_mul(b)).context("NPY shape overflows")?;
    let data = &bytes[10 + hlen..];
    anyhow::ensure!(
        data.len() == n.checked_mul(item_size).context("NPY shape overflows")?,
        "NPY holds {} bytes for shape {shape:?}",
        data.len()
    );
    Ok((shape, data))
}

/// The shape and values of an NPY v1.0 little-endian float32 array in C order (what [`npy_f32`]
/// writes).
pub fn read_npy_f32(bytes: &[u8]) -> Result<(Vec<usize>, Vec<f32>)> {
    let (shape, data) = read_npy(bytes, "<f4", 4)?;
    Ok((shape, data.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect()))
}

/// The shape and values of an NPY v1.0 uint8 array in C order (what [`npy_u8`] and numpy write).
pub fn read_npy_u8(bytes: &[u8]) -> Result<(Vec<usize>, Vec<u8>)> {
    let (shape, data) = read_npy(bytes, "|u1", 1)?;
    Ok((shape, data.to_vec()))
}

/// A NumPy `.npz` archive as `np.savez_compressed` writes it: a ZIP of `<name>.npy` members,
/// each deflated; deterministic (no timestamps: 1980-01-01).
pub fn npz(members: &[(&str, Vec<u8>)]) -> Vec<u8> {
    let mut out = Vec::new();
    let mut central = Vec::new();
    let (time, date) = (0u16, (1 << 5) | 1); // 1980-01-01 00:00
    for (name, data) in members {
        let file = format!("{name}.npy");
        let packed = miniz_oxide::deflate::compress_to_vec(data, 6);
        let crc = crc32fast::hash(data);
        let offset = out.len() as u32;
        // Local file header.
        out.extend_from_slice(&0x0403_4b50u32.to_le_bytes());
        for v in [20u16, 0, 8, time, date] {
            out.extend_from_slice(&v.to_le_bytes());
        }
        for v in [crc, packed.len() as u32, data.len() as u32] {
            out.extend_from_slice(&v.to_le_bytes());
        }
        out.extend_from_slice(&(file.len() as u16).to_le_bytes());
        out.extend_from_slice(&0u16.to_le_bytes());
        out.extend_from_slice(file.as_bytes());
        out.extend_from_slice(&packed);
        // Its central directory entry.
        central.extend_from_slice(&0x0201_4b50u32.to_le_bytes());
        for v in [20u16, 20, 0, 8, time, date] {
            central.extend_from_slice(&v.to_le_bytes());
        }
        for v in [crc, packed.len() as u32, data.len() as u32] {
            central.extend_from_slice(&v.to_le_bytes());
        }
        for v in [file.len() as u16, 0, 0, 0, 0] {
            central.extend_from_slice(&v.to_le_bytes());
        }
        central.extend_from_slice(&0u32.to_le_bytes()); // external attributes
        central.extend_from_slice(&offset.to_le_bytes());
        central.extend_from_slice(file.as_bytes());
    }
    let (cd_offset, cd_size) = (out.len() as u32, central.len() as u32);
    out.extend_from_slice(&central);
    out.extend_from_slice(&0x0605_4b50u32.to_le_bytes());
    for v in [0u16, 0, members.len() as u16, members.len() as u16] {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out.extend_from_slice(&cd_size.to_le_bytes());
    out.extend_from_slice(&cd_offset.to_le_bytes());
    out.extend_from_slice(&0u16.to_le_bytes());
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn arrays_read_back_and_malformed_ones_are_errors() {
        let data = [1.5f32, -2.0, 0.0, 7.25, 3.0, 9.0];
        let (shape, back) = read_npy_f32(&npy_f32(&[2, 3], &data)).unwrap();
        assert_eq!((shape, back), (vec![2, 3], data.to_vec()));
        let (shape, bytes) = read_npy_u8(&npy_u8(&[4], &[1, 2, 3, 4])).unwrap();
        assert_eq!((shape, bytes), (vec![4], vec![1, 2, 3, 4]));
        let whole = npy_f32(&[2, 3], &data);
        assert!(read_npy_f32(&whole[..whole.len() - 1]).is_err(), "truncated data");
        assert!(read_npy_f32(&whole[..8]).is_err(), "truncated header");
        assert!(read_npy_u8(&whole).is_err(), "another dtype");
        // An archive holds its members deflated under `<name>.npy`.
        let archive = npz(&[("depth", whole.clone())]);
        assert_eq!(&archive[..4], b"PK\x03\x04");
        assert!(archive.windows(9).any(|w| w == b"depth.npy"));
    }
}
