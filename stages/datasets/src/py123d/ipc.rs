//! Arrow IPC files as py123d writes them, read with arrow-rs.
//!
//! Two things keep arrow-rs's `FileReader` from opening them as they are, and this module does
//! what it would otherwise do:
//!
//! - py123d puts each file's metadata in the schema's custom metadata as **msgpack bytes** (key
//!   `metadata`), which is not UTF-8; the flatbuffers verifier refuses such a footer. The footer is
//!   verified on a copy in which each such value is overwritten with ASCII (the verifier names the
//!   byte range of every string it refuses), and the original bytes are kept as the metadata.
//! - The file is memory-mapped, as pyarrow (and py123d) read it, and a row is read by decoding only
//!   the record batch that holds it (zero-copy, `FileDecoder`, which decompresses LZ4 and ZSTD
//!   bodies), with a projection when only some columns are wanted: the timestamps and poses of a
//!   camera file are read without touching the pages of its images. (A log truncated by another
//!   process while a run reads it would be a bus error: logs are written once, as py123d does.)
//! - A compressed batch (py123d's `ipc_compression`) holds up to 10 images or 1000 sweeps (128 MiB
//!   at most) and is decompressed whole, so the last few decoded batches are kept (process-wide,
//!   a handful): reading a log row by row decompresses each batch about once, not once per row.

use anyhow::{anyhow, bail, ensure, Context, Result};
use arrow_array::RecordBatch;
use arrow_buffer::Buffer;
use arrow_ipc::reader::FileDecoder;
use arrow_ipc::{Block, MetadataVersion};
use arrow_schema::{Schema, SchemaRef};
use std::path::{Path, PathBuf};
use std::ptr::NonNull;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

const MAGIC: &[u8; 6] = b"ARROW1";
/// Footers hold a schema and one block per batch: a few KB. A larger one is not a py123d log.
const MAX_FOOTER_BYTES: usize = 64 << 20;

/// One record batch of a file: where it is and which rows it holds.
#[derive(Clone, Copy, Debug)]
struct BatchBlock {
    block: Block,
    first_row: u64,
    rows: u64,
}

/// An open Arrow IPC file: its schema, its msgpack metadata and its batches.
pub struct IpcFile {
    pub path: PathBuf,
    map: Buffer,
    pub schema: SchemaRef,
    /// The schema's `metadata` value (py123d: msgpack), when it has one.
    pub metadata: Option<Vec<u8>>,
    version: MetadataVersion,
    batches: Vec<BatchBlock>,
    pub rows: u64,
    /// Tells this file's batches apart in [`RECENT`].
    id: u64,
}

/// A decoded batch: which file, which batch, which columns.
type BatchKey = (u64, usize, Option<Vec<usize>>);

/// The most recently decoded batches, newest last. A decoded uncompressed batch only points into
/// the map; a compressed one is its decompressed body, so the count is kept small (each is at most
/// py123d's 128 MiB batch limit).
static RECENT: Mutex<Vec<(BatchKey, RecordBatch)>> = Mutex::new(Vec::new());
const RECENT_BATCHES: usize = 8;
static NEXT_FILE_ID: AtomicU64 = AtomicU64::new(0);

impl std::fmt::Debug for IpcFile {
    fn fmt(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
        write!(f, "IpcFile({}, {} rows)", self.path.display(), self.rows)
    }
}

impl IpcFile {
    pub fn open(path: &Path) -> Result<IpcFile> {
        let file = std::fs::File::open(path).with_context(|| format!("opening {}", path.display()))?;
        let what = || format!("{} is not an Arrow IPC file", path.display());
        let len = file.metadata().with_context(|| format!("reading {}", path.display()))?.len();
        ensure!(len >= 18, "{} ({len} bytes: truncated?)", what());
        // SAFETY: the map is only read; see the module's note on files changed under a run.
        let mmap = unsafe { memmap2::Mmap::map(&file) }.with_context(|| format!("mapping {}", path.display()))?;
        let map = {
            let ptr = NonNull::new(mmap.as_ptr() as *mut u8).expect("a mapped file is not at address 0");
            // SAFETY: the buffer owns the map, which stays valid for `mmap.len()` bytes while it lives.
            unsafe { Buffer::from_custom_allocation(ptr, mmap.len(), Arc::new(mmap)) }
        };
        let bytes = map.as_slice();
        let len = bytes.len();
        // The file may have shrunk between its metadata and the map.
        ensure!(len >= 18, "{} ({len} bytes: truncated?)", what());
        ensure!(&bytes[..6] == MAGIC, "{} (no ARROW1 magic at its start)", what());
        ensure!(
            &bytes[len - 6..] == MAGIC,
            "{} (no ARROW1 magic at its end: truncated or still being written?)",
            what()
        );
        let footer_len = i32::from_le_bytes(bytes[len - 10..len - 6].try_into().unwrap());
        ensure!(
            footer_len > 0 && (footer_len as usize) <= MAX_FOOTER_BYTES && footer_len as usize + 10 + 8 <= len,
            "{}: its footer length {footer_len} does not fit the file of {len} bytes",
            path.display()
        );
        let footer = bytes[len - 10 - footer_len as usize..len - 10].to_vec();
        let (verified, metadata) =
            verified_footer(footer).with_context(|| format!("the footer of {}", path.display()))?;
        let fb = arrow_ipc::root_as_footer(&verified).expect("verified above");
        let ipc_schema = fb.schema().ok_or_else(|| anyhow!("{}: its footer has no schema", path.display()))?;
        // The fields only: the schema's own custom metadata is what `verified_footer` took out.
        let fields: Vec<arrow_schema::Field> = ipc_schema
            .fields()
            .map(|fields| fields.iter().map(arrow_schema::Field::from).collect())
            .unwrap_or_default();
        let schema = Arc::new(Schema::new(fields));
        let version = fb.version();
        let mut batches = Vec::new();
        let mut rows = 0u64;
        for block in fb.recordBatches().map(|b| b.iter().copied().collect::<Vec<_>>()).unwrap_or_default() {
            let (offset, meta, body) = (block.offset(), block.metaDataLength(), block.bodyLength());
            ensure!(
                offset >= 8 && meta > 0 && body >= 0 && offset as u64 + meta as u64 + body as u64 <= len as u64,
                "{}: a record batch block (offset {offset}, {meta} + {body} bytes) lies outside the file of {len} bytes",
                path.display()
            );
            let header = &bytes[offset as usize..offset as usize + meta as usize];
            let length = batch_length(header).with_context(|| {
                format!("{}: the record batch at byte {offset} has no readable header", path.display())
            })?;
            batches.push(BatchBlock { block, first_row: rows, rows: length });
            rows += length;
        }
        let id = NEXT_FILE_ID.fetch_add(1, Ordering::Relaxed);
        Ok(IpcFile { path: path.to_path_buf(), map, schema, metadata, version, batches, rows, id })
    }

    /// The index of the column named `name`.
    pub fn column(&self, name: &str) -> Result<usize> {
        self.schema.index_of(name).map_err(|_| {
            anyhow!(
                "{} has no column `{name}` (it has: {})",
                self.path.display(),
                self.schema.fields().iter().map(|f| f.name().as_str()).collect::<Vec<_>>().join(", ")
            )
        })
    }

    /// The record batch that holds `row` (only the `columns` given, by index, when some are),
    /// with the row's index inside it.
    pub fn batch_of(&self, row: u64, columns: Option<&[usize]>) -> Result<(RecordBatch, usize)> {
        let index = self
            .batches
            .iter()
            .position(|b| row >= b.first_row && row < b.first_row + b.rows)
            .ok_or_else(|| anyhow!("{} has {} rows, no row {row}", self.path.display(), self.rows))?;
        let b = &self.batches[index];
        let key: BatchKey = (self.id, index, columns.map(<[usize]>::to_vec));
        let recent = |r: &mut Vec<(BatchKey, RecordBatch)>| {
            let at = r.iter().position(|(k, _)| *k == key)?;
            let hit = r.remove(at);
            r.push(hit.clone());
            Some(hit.1)
        };
        if let Some(batch) = recent(&mut RECENT.lock().unwrap_or_else(|p| p.into_inner())) {
            return Ok((batch, (row - b.first_row) as usize));
        }
        // Decoded outside the lock: two threads may decode one batch at once, which costs time, not
        // correctness.
        let batch = self.read_batch(b, columns)?;
        let mut r = RECENT.lock().unwrap_or_else(|p| p.into_inner());
        if recent(&mut r).is_none() {
            if r.len() >= RECENT_BATCHES {
                r.remove(0);
            }
            r.push((key, batch.clone()));
        }
        Ok((batch, (row - b.first_row) as usize))
    }

    /// Every record batch in order, with only `columns` (by index) when given.
    pub fn batches<'a>(&'a self, columns: Option<&'a [usize]>) -> impl Iterator<Item = Result<RecordBatch>> + 'a {
        self.batches.iter().map(move |b| self.read_batch(b, columns))
    }

    fn read_batch(&self, b: &BatchBlock, columns: Option<&[usize]>) -> Result<RecordBatch> {
        let len = b.block.metaDataLength() as usize + b.block.bodyLength() as usize;
        let data = self.map.slice_with_length(b.block.offset() as usize, len);
        let mut decoder = FileDecoder::new(self.schema.clone(), self.version);
        if let Some(columns) = columns {
            decoder = decoder.with_projection(columns.to_vec());
        }
        let batch = decoder
            .read_record_batch(&b.block, &data)
            .with_context(|| {
                format!("decoding rows {}..{} of {}", b.first_row, b.first_row + b.rows, self.path.display())
            })?
            .ok_or_else(|| {
                anyhow!("{}: an empty message where rows {}.. should be", self.path.display(), b.first_row)
            })?;
        ensure!(
            batch.num_rows() as u64 == b.rows,
            "{}: the batch at rows {}.. has {} rows, its header says {}",
            self.path.display(),
            b.first_row,
            batch.num_rows(),
            b.rows
        );
        Ok(batch)
    }
}

/// The footer, verified, with the values the verifier refuses as UTF-8 (py123d's msgpack
/// metadata) overwritten by ASCII in the copy, and the original bytes of the schema's `metadata`
/// value.
fn verified_footer(mut footer: Vec<u8>) -> Result<(Vec<u8>, Option<Vec<u8>>)> {
    let original = footer.clone();
    let mut replaced = Vec::new();
    loop {
        match arrow_ipc::root_as_footer(&footer) {
            Ok(_) => break,
            Err(flatbuffers::InvalidFlatbuffer::Utf8Error { range, .. })
                if range.end <= footer.len() && !replaced.contains(&range.start) && replaced.len() < 64 =>
            {
                footer[range.clone()].fill(b'0');
                replaced.push(range.start);
            }
            Err(e) => bail!("not a valid Arrow footer: {e}"),
        }
    }
    let fb = arrow_ipc::root_as_footer(&footer).expect("verified");
    let mut metadata = None;
    if let Some(kvs) = fb.schema().and_then(|s| s.custom_metadata()) {
        for kv in kvs.iter() {
            if kv.key() != Some("metadata") {
                continue;
            }
            // The value's bytes, read as a byte vector at the string's field (no UTF-8 involved).
            // SAFETY: the footer was verified, and a flatbuffers string is laid out as a vector
            // of bytes (length, bytes, NUL), so this field is a valid `[u8]` vector.
            let bytes = unsafe {
                kv._tab
                    .get::<flatbuffers::ForwardsUOffset<flatbuffers::Vector<u8>>>(arrow_ipc::KeyValue::VT_VALUE, None)
            };
            if let Some(v) = bytes {
                let start = v.bytes().as_ptr() as usize - footer.as_ptr() as usize;
                metadata = Some(original[start..start + v.len()].to_vec());
            }
        }
    }
    Ok((footer, metadata))
}

/// The row count of an IPC record batch message.
fn batch_length(header: &[u8]) -> Result<u64> {
    // An encapsulated message: 0xFFFFFFFF continuation, i32 length, then the flatbuffer.
    let body = match header {
        [0xFF, 0xFF, 0xFF, 0xFF, a, b, c, d, rest @ ..] => {
            let n = i32::from_le_bytes([*a, *b, *c, *d]);
            ensure!(n >= 0 && n as usize <= rest.len(), "message length {n} over {} bytes", rest.len());
            &rest[..n as usize]
        }
        [a, b, c, d, rest @ ..] => {
            let n = i32::from_le_bytes([*a, *b, *c, *d]);
            ensure!(n >= 0 && n as usize <= rest.len(), "message length {n} over {} bytes", rest.len());
            &rest[..n as usize]
        }
        _ => bail!("a message header of {} bytes", header.len()),
    };
    let message = arrow_ipc::root_as_message(body).map_err(|e| anyhow!("{e}"))?;
    let batch = message.header_as_record_batch().ok_or_else(|| anyhow!("not a record batch"))?;
    ensure!(batch.length() >= 0, "a negative row count");
    Ok(batch.length() as u64)
}

/// The msgpack metadata as JSON.
pub fn metadata_json(file: &IpcFile) -> Result<serde_json::Value> {
    let bytes = file.metadata.as_ref().ok_or_else(|| anyhow!("{} has no py123d metadata", file.path.display()))?;
    rmp_serde::from_slice(bytes).with_context(|| format!("{}: its metadata is not msgpack", file.path.display()))
}

/// Every batch of an Arrow IPC **stream** held in memory (py123d's in-log LiDAR blobs).
pub fn read_stream(bytes: &[u8]) -> Result<Vec<RecordBatch>> {
    let reader = arrow_ipc::reader::StreamReader::try_new(std::io::Cursor::new(bytes), None)?;
    reader.collect::<Result<Vec<_>, _>>().map_err(Into::into)
}

#[cfg(test)]
mod tests {
    use super::*;
    use arrow_array::{BinaryArray, Int64Array};
    use arrow_schema::{DataType, Field};

    /// An IPC file with a `metadata` value of `len` ASCII bytes, the batches `rows`, compressed
    /// with `compression`.
    fn write(path: &Path, len: usize, rows: &[&[i64]], compression: Option<arrow_ipc::CompressionType>) {
        let schema = Arc::new(
            Schema::new(vec![Field::new("t", DataType::Int64, true), Field::new("data", DataType::Binary, true)])
                .with_metadata(std::collections::HashMap::from([("metadata".to_string(), "M".repeat(len))])),
        );
        let options = arrow_ipc::writer::IpcWriteOptions::default().try_with_compression(compression).unwrap();
        let mut w =
            arrow_ipc::writer::FileWriter::try_new_with_options(std::fs::File::create(path).unwrap(), &schema, options)
                .unwrap();
        for batch in rows {
            let data: Vec<Vec<u8>> = batch.iter().map(|v| vec![*v as u8; 100]).collect();
            let b = RecordBatch::try_new(
                schema.clone(),
                vec![
                    Arc::new(Int64Array::from(batch.to_vec())),
                    Arc::new(BinaryArray::from_iter_values(data.iter().map(|d| d.as_slice()))),
                ],
            )
            .unwrap();
            w.write(&b).unwrap();
        }
        w.finish().unwrap();
    }

    /// Overwrites the first run of `len` 'M's with `bytes` (what py123d's msgpack looks like).
    fn patch(path: &Path, len: usize, bytes: &[u8]) {
        let mut data = std::fs::read(path).unwrap();
        let run = vec![b'M'; len];
        let mut at = 0;
        while let Some(i) = data[at..].windows(len).position(|w| w == run.as_slice()) {
            data[at + i..at + i + len].copy_from_slice(bytes);
            at += i + len;
        }
        std::fs::write(path, data).unwrap();
    }

    #[test]
    fn a_footer_with_msgpack_metadata_opens_and_rows_come_from_their_batch() {
        let tmp = tempfile::tempdir().unwrap();
        for compression in [None, Some(arrow_ipc::CompressionType::LZ4_FRAME), Some(arrow_ipc::CompressionType::ZSTD)] {
            let path = tmp.path().join("f.arrow");
            let msgpack =
                rmp_serde::to_vec_named(&serde_json::json!({"camera_name": "CAM_FRONT", "width": 1600})).unwrap();
            write(&path, msgpack.len(), &[&[10, 11, 12], &[13, 14]], compression);
            patch(&path, msgpack.len(), &msgpack);
            // arrow-rs's own reader refuses it: what this module is for.
            assert!(arrow_ipc::reader::FileReader::try_new(std::fs::File::open(&path).unwrap(), None).is_err());
            let f = IpcFile::open(&path).unwrap();
            assert_eq!(f.rows, 5);
            assert_eq!(f.metadata.as_deref(), Some(msgpack.as_slice()));
            assert_eq!(metadata_json(&f).unwrap()["width"], 1600);
            let (batch, i) = f.batch_of(3, None).unwrap();
            assert_eq!(i, 0);
            let t = batch.column(f.column("t").unwrap()).as_any().downcast_ref::<Int64Array>().unwrap();
            assert_eq!(t.value(i), 13);
            let data = batch.column(1).as_any().downcast_ref::<BinaryArray>().unwrap();
            assert_eq!(data.value(i), &[13u8; 100][..]);
            // The next row of the batch comes from the batch decoded for row 3 (for a compressed
            // one, not decompressed again): the same bytes in memory.
            let (next, _) = f.batch_of(4, None).unwrap();
            let values = |b: &RecordBatch| b.column(1).to_data().buffers()[1].as_ptr();
            assert_eq!(values(&next), values(&batch), "{compression:?}");
            let (only_t, _) = f.batch_of(3, Some(&[0])).unwrap();
            assert_eq!(only_t.num_columns(), 1);
            assert!(f.batch_of(5, None).unwrap_err().to_string().contains("has 5 rows, no row 5"));
            assert!(f.column("nope").unwrap_err().to_string().contains("no column `nope` (it has: t, data)"));
        }
    }

    #[test]
    fn truncated_and_foreign_files_are_errors_naming_the_file() {
        let tmp = tempfile::tempdir().unwrap();
        let path = tmp.path().join("f.arrow");
        write(&path, 8, &[&[1, 2, 3]], None);
        let whole = std::fs::read(&path).unwrap();
        for cut in [0, 5, whole.len() / 2, whole.len() - 1] {
            std::fs::write(&path, &whole[..cut]).unwrap();
            let e = format!("{:#}", IpcFile::open(&path).unwrap_err());
            assert!(e.contains("f.arrow"), "{cut}: {e}");
        }
        // The footer intact but a batch body overwritten: opening works, reading the row fails.
        let mut broken = whole.clone();
        let body = whole.windows(4).position(|w| w == [0xFF, 0xFF, 0xFF, 0xFF]).unwrap();
        let second = body + 4 + whole[body + 4..].windows(4).position(|w| w == [0xFF, 0xFF, 0xFF, 0xFF]).unwrap();
        broken[second + 8..second + 40].fill(0xAB);
        std::fs::write(&path, &broken).unwrap();
        if let Ok(f) = IpcFile::open(&path) {
            assert!(f.batch_of(0, None).is_err());
        }
    }
}
