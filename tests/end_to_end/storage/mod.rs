//! What the coordinator keeps on disk: its data directory failing under a running job
//! (full, read-only, frozen), and what it finds there at startup damaged (the job
//! database lost, tile rows and blobs altered, a stored image altered).

mod damage;
mod outages;
