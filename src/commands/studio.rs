//! `tessera studio [SCENE]`: the studio on a farm of this machine. A [`LocalFarm`]
//! whose coordinator serves HTTP on loopback, the page's address printed, and
//! everything stopped and removed again on Ctrl-C, SIGTERM or SIGHUP (docs/studio.md).

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use anyhow::{anyhow, Context, Result};
use localfarm::{up_limits, LocalFarm, WorkerSpec};

use crate::args::threads_per_worker;
use crate::scene_file::read_studio_scene;
use crate::signals::{Interrupted, StopSignals};

/// Edit a scene and move its camera in the browser while a local farm renders it.
#[derive(clap::Args)]
#[command(
    long_about = "Start a coordinator and worker processes on this machine (loopback \
        only), serve the studio page and print its address: a scene editor whose \
        every change the farm renders progressively. Ctrl-C stops the farm and removes \
        its files.",
    after_help = "Example:\n  tessera studio scenes/seed.json\n  \
        (then open the printed http://127.0.0.1:PORT/studio)"
)]
pub struct Args {
    /// The scene to open: a scene file (its mesh files read beside it), or a .tar
    /// archive of a scene and its files [default: the seed scene at 960 x 540, aa 2].
    scene: Option<PathBuf>,
    /// Worker processes to start.
    #[arg(long, value_name = "N", default_value_t = 2, value_parser = clap::value_parser!(u32).range(1..=64))]
    workers: u32,
    /// Rendering threads of each worker [default: cores / workers, at least 1].
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u32).range(1..=1024))]
    threads_per_worker: Option<u32>,
    /// Where to serve the page: a loopback address; port 0 takes a free one.
    #[arg(long, value_name = "ADDR", default_value = "127.0.0.1:0")]
    http: SocketAddr,
}

pub fn run(args: Args) -> Result<()> {
    super::block_on(studio(args))
}

async fn studio(args: Args) -> Result<()> {
    let workers = args.workers as usize;
    let threads = threads_per_worker(workers, args.threads_per_worker);
    let mut stop = StopSignals::new()?;
    if !args.http.ip().is_loopback() {
        // The farm has no secret: its controls (and so the studio) trust this machine
        // only. A farm of many machines is a coordinator with --http and a secret.
        anyhow::bail!(
            "--http {}: the studio's local farm listens on loopback only (127.0.0.1 or ::1)",
            args.http
        );
    }
    if let Some(scene) = &args.scene {
        read_studio_scene(scene)?;
    }
    let specs = vec![
        WorkerSpec {
            threads,
            ..WorkerSpec::default()
        };
        workers
    ];
    let mut coordinator_args = up_limits();
    coordinator_args.extend(["--http".to_owned(), args.http.to_string()]);
    if let Some(scene) = &args.scene {
        let absolute = std::path::absolute(scene)
            .with_context(|| format!("cannot resolve {}", scene.display()))?;
        coordinator_args.extend(["--studio-scene".to_owned(), absolute.display().to_string()]);
    }
    let exe = std::env::current_exe().context("cannot find the tessera executable")?;
    let starting = tokio::task::spawn_blocking(move || {
        let args: Vec<&str> = coordinator_args.iter().map(String::as_str).collect();
        LocalFarm::start_with(&exe, &specs, &args)
    });
    let farm = tokio::select! {
        farm = starting => farm.context("starting the local farm")??,
        signal = stop.next() => return Err(signal.into()),
    };
    let ready: Result<()> = tokio::select! {
        r = farm.wait_for_workers(workers, Duration::from_secs(30)) => r.map_err(Into::into),
        e = farm.first_exit() => Err(e.into()),
        signal = stop.next() => Err(signal.into()),
    };
    ready?;
    let http = farm
        .http_address()
        .ok_or_else(|| anyhow!("the local coordinator did not say where it serves HTTP"))?;
    println!("studio on http://{http}/studio");
    println!(
        "farm: coordinator {} with {} workers; status page http://{http}/; Ctrl-C stops it",
        farm.address(),
        workers
    );
    let result: Result<()> = tokio::select! {
        e = farm.first_exit() => Err(e.into()),
        signal = stop.next() => Err(signal.into()),
    };
    drop(farm);
    match result {
        // Stopping the studio is how it ends: not an error, but the farm is gone.
        Err(e) if e.downcast_ref::<Interrupted>().is_some() => {
            eprintln!("studio stopped: the local farm is stopped and its files removed");
            Ok(())
        }
        other => other,
    }
}
