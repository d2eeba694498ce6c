//! One module per subcommand: each holds its clap `Args` (the subcommand's description,
//! flags and help) and its `run`, which turns the arguments into library calls.

pub mod coordinator;
pub mod jobs;
pub mod refine;
pub mod render;
pub mod simulate;
pub mod studio;
pub mod submit;
pub mod up;
pub mod worker;
pub mod workers;

use std::future::Future;

use anyhow::Result;

/// Runs a command that talks over the network on a multi-threaded runtime made for it:
/// the commands that render on this machine alone start none.
fn block_on(command: impl Future<Output = Result<()>>) -> Result<()> {
    tokio::runtime::Runtime::new()?.block_on(command)
}
