//! How `tests/measure_commands.rs` runs the binary: the end-to-end tests' own runner
//! (`tests/end_to_end/support/run.rs`), until those tests join `tests/end_to_end`.

#[path = "../end_to_end/support/run.rs"]
mod run;

pub use run::{ok, tessera};
