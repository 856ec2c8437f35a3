//! Stages that call an external model worker (docs/workers.md): the worker a pipeline names in a
//! stage's `worker` param, a pool of it per stage (started at the first call), and the files a
//! request exchanges (NPY, in a folder of the system's temporary directory, removed after the
//! call). The engine validates what comes back before anything enters the store.

use anyhow::{bail, ensure, Context, Result};
use dist4d_graph::ParamChecks;
use dist4d_runtime::worker::{FileRef, Request, WorkerCommand};
use dist4d_runtime::worker_pool::{PoolOptions, WorkerPool};
use dist4d_runtime::TaskContext;
use dist4d_types::formats::{npy_u8, read_npy_u8};
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, OnceLock, Weak};
use std::time::Duration;

/// A worker as a pipeline names it: `worker: Some((program: "python3", args: ["completer.py"]))`.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct WorkerSpec {
    pub program: String,
    pub args: Vec<String>,
    /// Worker processes at most (one per GPU, typically).
    pub max_workers: u32,
    /// Seconds to a request's reply; a worker that misses it is killed and the item tried again.
    pub deadline_s: f64,
    /// Tries of one item in all.
    pub tries: u32,
}

impl Default for WorkerSpec {
    fn default() -> Self {
        WorkerSpec { program: String::new(), args: Vec::new(), max_workers: 1, deadline_s: 600.0, tries: 3 }
    }
}

impl WorkerSpec {
    /// The problems of a stage's optional `worker` param (none when it is not set).
    pub fn problems_of(worker: Option<&WorkerSpec>) -> Vec<dist4d_graph::ParamProblem> {
        let mut c = ParamChecks::new();
        if let Some(w) = worker {
            w.check(&mut c);
        }
        c.done()
    }

    pub fn check(&self, c: &mut ParamChecks) {
        c.check(!self.program.is_empty(), "worker", || "names no `program`".into())
            .count("worker", self.max_workers as u64, 1, 64)
            .above("worker", self.deadline_s, 0.0, 86_400.0)
            .count("worker", self.tries as u64, 1, 10);
    }
}

/// A stage's worker pool, started at its first use.
#[derive(Default)]
pub struct ModelWorker {
    spec: Option<WorkerSpec>,
    pool: OnceLock<WorkerPool>,
    shared: Mutex<HashMap<String, Weak<SharedInput>>>,
}

/// An input file that several requests name at once (every camera of a step reads the same
/// reference frame): written once, under its digest, and removed when the last request that
/// holds it is done.
pub struct SharedInput {
    path: PathBuf,
}

impl Drop for ModelWorker {
    fn drop(&mut self) {
        // The shared inputs' folder, once its last file is gone (fails harmlessly otherwise).
        let _ = std::fs::remove_dir(std::env::temp_dir().join(format!("dist4d-worker-{}-shared", std::process::id())));
    }
}

impl Drop for SharedInput {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.path);
    }
}

impl ModelWorker {
    pub fn new(spec: Option<WorkerSpec>) -> ModelWorker {
        ModelWorker { spec, pool: OnceLock::new(), shared: Mutex::new(HashMap::new()) }
    }

    /// `bytes` as a file the worker reads as input `name`, shared with the requests in flight
    /// that put the same bytes (one write instead of one per request); keep the returned handle
    /// until the reply.
    pub fn put_shared(&self, name: &str, ext: &str, bytes: &[u8]) -> Result<(FileRef, Arc<SharedInput>)> {
        let digest = blake3::hash(bytes).to_hex().to_string();
        let mut shared = self.shared.lock().map_err(|_| anyhow::anyhow!("shared inputs poisoned"))?;
        shared.retain(|_, w| w.strong_count() > 0);
        let file = match shared.get(&digest).and_then(Weak::upgrade) {
            Some(f) => f,
            None => {
                let dir = std::env::temp_dir().join(format!("dist4d-worker-{}-shared", std::process::id()));
                std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
                let path = dir.join(format!("{digest}.{ext}"));
                std::fs::write(&path, bytes).with_context(|| format!("writing {}", path.display()))?;
                let f = Arc::new(SharedInput { path });
                shared.insert(digest.clone(), Arc::downgrade(&f));
                f
            }
        };
        Ok((FileRef { name: name.into(), path: file.path.display().to_string(), digest: Some(digest) }, file))
    }

    pub fn is_set(&self) -> bool {
        self.spec.is_some()
    }

    fn pool(&self) -> Result<&WorkerPool> {
        let spec = self.spec.as_ref().context("no worker")?;
        Ok(self.pool.get_or_init(|| {
            WorkerPool::new(
                WorkerCommand { program: spec.program.clone(), args: spec.args.clone() },
                PoolOptions {
                    max_workers: spec.max_workers as usize,
                    deadline: Duration::from_secs_f64(spec.deadline_s),
                    tries: spec.tries,
                    // A run stopping on SIGTERM does not wait out a deadline, nor try again.
                    stop: Some(dist4d_types::cancel::requested),
                    ..PoolOptions::default()
                },
            )
        }))
    }

    /// The worker's name, version and weights digest (for task keys); `None` without a worker.
    pub fn identity(&self) -> Result<Option<String>> {
        if !self.is_set() {
            return Ok(None);
        }
        let h = self.pool()?.hello()?;
        Ok(Some(format!("{} {} weights {}", h.name, h.version, h.weights_digest)))
    }

    /// The resource its tasks wait on: the worker command, with two batches per process waiting
    /// at once (one in the worker, the next ready to send when it replies, so that the worker
    /// never idles between batches); `None` without a worker.
    pub fn resource(&self) -> Option<dist4d_runtime::Resource> {
        let spec = self.spec.as_ref()?;
        let batch = self.pool.get().and_then(|p| p.known_hello()).map_or(1, |h| h.max_batch.max(1) as usize);
        Some(dist4d_runtime::Resource {
            name: format!(
                "worker `{}`",
                std::iter::once(&spec.program).chain(&spec.args).cloned().collect::<Vec<_>>().join(" ")
            ),
            slots: spec.max_workers as usize * batch * 2,
        })
    }

    /// Runs `op` on the named input files (written by the caller into `exchange.dir`), returning
    /// the paths of the outputs the worker names.
    pub fn call(
        &self,
        ctx: &TaskContext,
        exchange: &Exchange,
        op: &str,
        inputs: Vec<FileRef>,
        params: serde_json::Value,
    ) -> Result<Vec<FileRef>> {
        let pool = self.pool()?;
        ensure!(pool.hello()?.ops.iter().any(|o| o == op), "the worker does not serve `{op}`");
        let reply = pool.call(&Request {
            op: op.into(),
            item: ctx.label.to_string(),
            inputs,
            params,
            out_dir: exchange.dir.display().to_string(),
        })?;
        Ok(reply.outputs)
    }
}

/// The depth map a worker returned as output `name` (NPY float32, H x W), checked: its shape,
/// and every depth finite and not negative (before anything of it enters the store).
pub fn worker_depth(exchange: &Exchange, outputs: &[FileRef], name: &str, width: u32, height: u32) -> Result<Vec<f32>> {
    let (shape, data) = dist4d_types::formats::read_npy_f32(&exchange.get(outputs, name)?)
        .with_context(|| format!("the worker's `{name}` (float32 NPY)"))?;
    ensure!(
        shape == [height as usize, width as usize],
        "the worker's `{name}` has shape {shape:?}, not [{height}, {width}]"
    );
    if let Some(bad) = data.iter().position(|z| !z.is_finite() || *z < 0.0) {
        bail!("the worker's `{name}` holds {} at pixel {bad}: depths are finite and not negative", data[bad]);
    }
    Ok(data)
}

/// A folder for one request's files, removed when dropped.
pub struct Exchange {
    pub dir: PathBuf,
}

impl Exchange {
    pub fn new() -> Result<Exchange> {
        static NEXT: AtomicU64 = AtomicU64::new(0);
        let dir = std::env::temp_dir().join(format!(
            "dist4d-worker-{}-{}",
            std::process::id(),
            NEXT.fetch_add(1, Ordering::Relaxed)
        ));
        std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
        Ok(Exchange { dir })
    }

    /// Writes `bytes` as `name` in the folder and names it for a request.
    pub fn put(&self, name: &str, file: &str, bytes: &[u8]) -> Result<FileRef> {
        let path = self.dir.join(file);
        std::fs::write(&path, bytes).with_context(|| format!("writing {}", path.display()))?;
        Ok(FileRef {
            name: name.into(),
            path: path.display().to_string(),
            digest: Some(blake3::hash(bytes).to_hex().to_string()),
        })
    }

    /// Reads the output `name` a reply names: it must be inside the folder.
    pub fn get(&self, outputs: &[FileRef], name: &str) -> Result<Vec<u8>> {
        let out =
            outputs.iter().find(|o| o.name == name).with_context(|| format!("the worker returned no `{name}`"))?;
        let path = Path::new(&out.path);
        let inside = path.canonicalize().ok().zip(self.dir.canonicalize().ok()).is_some_and(|(p, d)| p.starts_with(d));
        if !inside {
            bail!("the worker's `{name}` ({}) is not in the request's folder {}", out.path, self.dir.display());
        }
        std::fs::read(path).with_context(|| format!("reading the worker's `{name}` at {}", path.display()))
    }
}

impl Drop for Exchange {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

/// An RGB8 image as NPY (uint8, H x W x 3).
pub fn npy_rgb8(width: u32, height: u32, rgb: &[u8]) -> Vec<u8> {
    npy_u8(&[height as usize, width as usize, 3], rgb)
}

/// A one-byte-per-pixel map (a mask) as NPY (uint8, H x W).
pub fn npy_gray8(width: u32, height: u32, data: &[u8]) -> Vec<u8> {
    npy_u8(&[height as usize, width as usize], data)
}

/// An RGB8 image from an NPY file (uint8, H x W x 3), checked against the size.
pub fn read_npy_rgb8(bytes: &[u8], width: u32, height: u32) -> Result<Vec<u8>> {
    read_shaped(bytes, &[height as usize, width as usize, 3])
}

/// A one-byte-per-pixel map from an NPY file (uint8, H x W), checked against the size.
pub fn read_npy_gray8(bytes: &[u8], width: u32, height: u32) -> Result<Vec<u8>> {
    read_shaped(bytes, &[height as usize, width as usize])
}

fn read_shaped(bytes: &[u8], want: &[usize]) -> Result<Vec<u8>> {
    let (shape, data) = read_npy_u8(bytes)?;
    ensure!(shape == want, "an array of shape {shape:?}, not {want:?}");
    Ok(data)
}
