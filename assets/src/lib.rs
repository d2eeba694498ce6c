//! Scene files by content: the meshes and buffers a job's scene names (OBJ, PLY, STL,
//! glTF and its buffer files), each known by its [`AssetId`], the SHA-256 and length of
//! its bytes.
//!
//! The coordinator keeps every uploaded file once in a [`Store`], however many jobs
//! name it, and hands it to workers in chunks; each worker keeps the files it fetched
//! in a bounded [`Cache`]. Naming files by content makes both safe to trust: a file
//! either hashes to its name or is thrown away and fetched again.
//!
//! Nothing here knows a network protocol: the HTTP API and the binary protocol both
//! move files through these calls, in pieces of at most [`CHUNK`] bytes. Everything is
//! synchronous file I/O, which callers run on a blocking pool.

mod cache;
mod error;
mod id;
mod layout;
mod store;
mod upload;

pub use cache::{Cache, CacheStats, Lookup};
pub use error::AssetError;
pub use id::AssetId;
pub use store::{Collected, Store, StoreLimits, StoreStats, Upload};

/// The largest piece of a file moved at once: small enough that a chunk in flight costs
/// little memory and a lost connection little work, large enough that the per-chunk
/// overhead (a message, a write) is negligible.
pub const CHUNK: usize = 1 << 20;
