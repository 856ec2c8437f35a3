//! dist4d-runtime: item-level task planning, scheduling, content-addressed cache, resume,
//! explain and garbage collection. Knows nothing about driving: datasets and stage operators
//! come in through the [`Dataset`] and [`Operator`] traits.

pub mod blob;
pub mod digest;
pub mod direct_io;
pub mod exec;
pub mod explain;
pub mod export;
pub mod gc;
pub mod item;
pub mod keys;
pub mod lease;
pub mod nothing;
pub mod operator;
pub mod plan;
pub mod progress;
pub mod record;
pub mod regular_file;
pub mod runs;
pub mod segment;
pub mod store;
pub mod verify;
pub mod worker;
pub mod worker_pool;

pub use digest::{Digest, DigestBuilder};
pub use exec::{Engine, RunOptions, RunSummary};
pub use item::{ItemKey, ItemSpace};
pub use operator::{Artifact, Blob, Dataset, FileDigests, Made, Operator, Output, Resource, TaskContext, WithVariants};
pub use progress::ProgressMode;
pub use runs::{RunRecord, RunStatus};
pub use store::{Access, Store};
pub mod testkit;
