//! The end-to-end tests: the real `tessera` binary run as a user or an operator runs it
//! (`render`, `up`, `studio`, coordinators, workers, clients), on 127.0.0.1 only, with
//! time limits on every run and wait, and guards that kill and reap every process a test
//! starts, also when it fails.
//!
//! One test binary, by area:
//!
//! - [`cli`]: `tessera render` on one machine, animated scenes, golden images, refining
//!   a saved render.
//! - [`sampling`]: the samplers, locally and on farms.
//! - [`farm`]: jobs on a farm, `tessera up`, refining farm jobs, frames and sequences.
//! - [`operations`]: client commands, job and machine controls, what jobs report,
//!   configuration, monitoring, the status page, the studio, previews.
//! - [`faults`]: workers, the coordinator and the network failing under a job.
//! - [`storage`]: the data directory failing, and damaged data found at startup.
//! - [`security`]: authentication, TLS, hostile peers.
//! - [`verification`]: wrong results caught and their machines quarantined.
//!
//! The tests run in parallel; each first takes its turn on the machine, shared or
//! exclusive ([`support::shared`], [`support::exclusive`]), as `support/turns.rs`
//! explains. `cargo test --release --test end_to_end -- farm::` runs one area.

mod cli;
mod farm;
mod faults;
mod operations;
mod sampling;
mod security;
mod storage;
mod support;
mod verification;
