//! `tessera up`: a whole farm on this machine for one scene. A coordinator with a
//! temporary data directory and N worker processes on loopback, the scene submitted,
//! progress shown, the image written, and everything shut down again.
//!
//! The children are the real `tessera coordinator` and `tessera worker` processes of a
//! [`LocalFarm`], stopped when `up` ends for any reason.

use std::path::PathBuf;

use anyhow::{anyhow, Context, Result};
use protocol::Overrides;
use transport::Endpoint;

use crate::client_commands::{submit, summary, wait, Session};
use crate::local_farm::{LocalFarm, WorkerSpec};
use crate::output::{default_output, ImageOutput};

pub struct Options {
    pub scene: PathBuf,
    pub workers: usize,
    pub threads_per_worker: usize,
    pub output: Option<PathBuf>,
    /// The image settings and the time limit (ms), if any.
    pub job: (Overrides, Option<u64>),
}

pub async fn run(opts: Options) -> Result<()> {
    // Fail on an unreadable scene or an image that cannot be written before starting
    // anything.
    crate::client_commands::read_scene(&opts.scene)?;
    let output = ImageOutput::create(
        &opts
            .output
            .clone()
            .unwrap_or_else(|| default_output(&opts.scene)),
    )?;
    let specs = vec![
        WorkerSpec {
            threads: opts.threads_per_worker,
            throttle: None,
        };
        opts.workers
    ];
    let farm = tokio::task::spawn_blocking(move || LocalFarm::start(&specs))
        .await
        .context("starting the local farm")??;
    let result = tokio::select! {
        r = render_on(farm.address(), &opts, output) => r,
        e = farm.first_exit() => Err(e),
        _ = tokio::signal::ctrl_c() => Err(anyhow!("interrupted")),
    };
    drop(farm);
    result
}

async fn render_on(address: &str, opts: &Options, output: ImageOutput) -> Result<()> {
    let mut session = Session::connect(&Endpoint::plain(address)).await?;
    let job = submit(
        session.client(),
        &opts.scene,
        opts.job.0,
        0,
        protocol::Verification::default(),
        opts.job.1,
    )
    .await?;
    let status = wait(&mut session, job).await?;
    let path = output.path().to_path_buf();
    // The farm and its copy of the image go with this command: no `tessera fetch`.
    let png = session.fetch(job).await?;
    output.write(&png)?;
    eprintln!("{} ({} workers)", summary(&path, &status), opts.workers);
    Ok(())
}
