//! The store and the cache on real files in temporary directories: uploads chunk by
//! chunk and across restarts, what each refuses, damage on disk, collection, eviction,
//! and disks that are full or cannot be written.

mod cache;
mod common;
mod store_upkeep;
mod store_upload;
