//! Task records: what a finished task produced, keyed by its task key (the `ac/` of the store).

use crate::digest::Digest;
use crate::item::ItemKey;
use crate::segment::enc::{self, Reader};
use anyhow::{bail, Result};
use std::sync::Arc;

/// Outputs this small are kept inside the record instead of as a blob file of their own.
pub const INLINE_MAX: usize = 1024;

/// One output artifact of a task.
#[derive(Clone, Debug, PartialEq)]
pub struct OutputRef {
    pub digest: Digest,
    pub size: u64,
    /// The bytes, for outputs of at most [`INLINE_MAX`] bytes.
    pub inline: Option<Arc<[u8]>>,
}

impl OutputRef {
    /// An output the task did not make (nothing of its run read it): the all-zero digest, which
    /// no blake3 hash of any bytes is, with no size and no bytes.
    pub fn unmade() -> OutputRef {
        OutputRef { digest: Digest::default(), size: 0, inline: None }
    }

    pub fn is_unmade(&self) -> bool {
        self.inline.is_none() && self.size == 0 && self.digest == Digest::default()
    }
}

/// The digests an input port received, in selector order.
#[derive(Clone, Debug, PartialEq)]
pub struct RecordInput {
    pub port: String,
    pub digests: Vec<Digest>,
}

/// A finished task. Besides the outputs it keeps what went into the key (kind, version, params,
/// input digests), so that `explain` can say what changed when a key is not found.
#[derive(Clone, Debug, PartialEq)]
pub struct TaskRecord {
    pub key: Digest,
    /// Name of the stage in its pipeline.
    pub stage: String,
    pub item: ItemKey,
    pub kind: String,
    pub version: u32,
    /// Digest of the canonical params text, which is stored as a blob.
    pub params: Digest,
    pub inputs: Vec<RecordInput>,
    pub outputs: Vec<OutputRef>,
    /// Unix time in milliseconds when the task finished.
    pub finished_ms: u64,
    pub micros: u64,
}

const FORMAT: u8 = 1;

impl TaskRecord {
    pub fn encode(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(256);
        out.push(FORMAT);
        out.extend_from_slice(&self.key.0);
        enc::bytes(&mut out, self.stage.as_bytes());
        out.extend_from_slice(&self.item.to_bytes());
        enc::bytes(&mut out, self.kind.as_bytes());
        enc::u32(&mut out, self.version);
        out.extend_from_slice(&self.params.0);
        enc::u32(&mut out, self.inputs.len() as u32);
        for i in &self.inputs {
            enc::bytes(&mut out, i.port.as_bytes());
            enc::u32(&mut out, i.digests.len() as u32);
            for d in &i.digests {
                out.extend_from_slice(&d.0);
            }
        }
        enc::u32(&mut out, self.outputs.len() as u32);
        for o in &self.outputs {
            out.extend_from_slice(&o.digest.0);
            enc::u64(&mut out, o.size);
            match &o.inline {
                Some(b) => {
                    out.push(1);
                    enc::bytes(&mut out, b);
                }
                None => out.push(0),
            }
        }
        enc::u64(&mut out, self.finished_ms);
        enc::u64(&mut out, self.micros);
        out
    }

    /// The task key of an encoded record, without decoding the rest.
    pub fn key_of(payload: &[u8]) -> Option<Digest> {
        (payload.first() == Some(&FORMAT) && payload.len() >= 33).then(|| Digest(payload[1..33].try_into().unwrap()))
    }

    /// When the task of an encoded record finished (Unix milliseconds), without decoding the rest.
    pub fn finished_ms_of(payload: &[u8]) -> Option<u64> {
        // The record ends with its finish time and its duration, 8 bytes each.
        let at = payload.len().checked_sub(16)?;
        Some(u64::from_le_bytes(payload[at..at + 8].try_into().ok()?))
    }

    /// Whether encoded record `a` is to be used rather than `b`, of the same key: the one whose
    /// task finished later. Records of one key normally name the same outputs; when a task that
    /// ran again gave other bytes (a stage that is not deterministic), the last run's record is
    /// the one that matches what it left in the output folder. Segments are read in the order of
    /// their writers' names, which is not the order they were written in.
    pub fn supersedes(a: &[u8], b: &[u8]) -> bool {
        TaskRecord::finished_ms_of(a) >= TaskRecord::finished_ms_of(b)
    }

    /// The stage name and item of an encoded record, without decoding the rest.
    pub fn stage_item_of(payload: &[u8]) -> Result<(&str, ItemKey)> {
        let mut r = Reader { buf: payload.get(33..).unwrap_or(&[]) };
        let stage = r.str()?;
        let item = ItemKey::from_bytes(r.take(17)?).ok_or_else(|| anyhow::anyhow!("bad item key"))?;
        Ok((stage, item))
    }

    pub fn decode(payload: &[u8]) -> Result<TaskRecord> {
        let mut r = Reader { buf: payload };
        if r.u8()? != FORMAT {
            bail!("unknown task record format");
        }
        let key = Digest(r.take(32)?.try_into()?);
        let stage = r.str()?.to_string();
        let item = ItemKey::from_bytes(r.take(17)?).ok_or_else(|| anyhow::anyhow!("bad item key"))?;
        let kind = r.str()?.to_string();
        let version = r.u32()?;
        let params = Digest(r.take(32)?.try_into()?);
        let n = r.u32()? as usize;
        let mut inputs = Vec::with_capacity(n.min(64));
        for _ in 0..n {
            let port = r.str()?.to_string();
            let m = r.u32()? as usize;
            let mut digests = Vec::with_capacity(m.min(1024));
            for _ in 0..m {
                digests.push(Digest(r.take(32)?.try_into()?));
            }
            inputs.push(RecordInput { port, digests });
        }
        let n = r.u32()? as usize;
        let mut outputs = Vec::with_capacity(n.min(64));
        for _ in 0..n {
            let digest = Digest(r.take(32)?.try_into()?);
            let size = r.u64()?;
            let inline = match r.u8()? {
                0 => None,
                _ => Some(Arc::from(r.bytes()?)),
            };
            outputs.push(OutputRef { digest, size, inline });
        }
        let finished_ms = r.u64()?;
        let micros = r.u64()?;
        Ok(TaskRecord { key, stage, item, kind, version, params, inputs, outputs, finished_ms, micros })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn records_round_trip() {
        let rec = TaskRecord {
            key: Digest::of(b"k"),
            stage: "project".into(),
            item: ItemKey::new(&[0, 3, 5]),
            kind: "Project".into(),
            version: 2,
            params: Digest::of(b"p"),
            inputs: vec![RecordInput { port: "points".into(), digests: vec![Digest::of(b"a"), Digest::of(b"b")] }],
            outputs: vec![
                OutputRef { digest: Digest::of(b"o"), size: 5_000_000, inline: None },
                OutputRef { digest: Digest::of(b"s"), size: 3, inline: Some(Arc::from(&b"abc"[..])) },
            ],
            finished_ms: 1_700_000_000_000,
            micros: 1234,
        };
        let bytes = rec.encode();
        assert_eq!(TaskRecord::decode(&bytes).unwrap(), rec);
        assert_eq!(TaskRecord::key_of(&bytes), Some(rec.key));
        assert_eq!(TaskRecord::stage_item_of(&bytes).unwrap(), ("project", rec.item));
        assert_eq!(TaskRecord::finished_ms_of(&bytes), Some(rec.finished_ms));
        assert!(TaskRecord::decode(&bytes[..bytes.len() - 3]).is_err());
    }
}
