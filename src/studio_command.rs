//! `tessera studio [SCENE]`: the studio on a farm of this machine. A [`LocalFarm`]
//! whose coordinator serves HTTP on loopback, the page's address printed, and
//! everything stopped and removed again on Ctrl-C, SIGTERM or SIGHUP (docs/studio.md).

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{anyhow, Context, Result};

use localfarm::{up_limits, LocalFarm, WorkerSpec};

use crate::up_command::StopSignals;

pub struct Options {
    /// The scene the page opens with; the page's own default (the seed scene) without.
    pub scene: Option<PathBuf>,
    pub workers: usize,
    pub threads_per_worker: usize,
    /// Where the page is served (loopback; port 0 takes a free one).
    pub http: SocketAddr,
}

/// Reads a scene file and checks it with the renderer's loader: its text, or the
/// loader's one-line error prefixed with the file.
pub fn read_checked_scene(path: &Path) -> Result<String> {
    let text = crate::client_commands::read_scene(path)?;
    render::parse_scene(&text).map_err(|e| anyhow!("{}: {e}", path.display()))?;
    Ok(text)
}

pub async fn run(opts: Options) -> Result<()> {
    let mut stop = StopSignals::new()?;
    if !opts.http.ip().is_loopback() {
        // The farm has no secret: its controls (and so the studio) trust this machine
        // only. A farm of many machines is a coordinator with --http and a secret.
        anyhow::bail!(
            "--http {}: the studio's local farm listens on loopback only (127.0.0.1 or ::1)",
            opts.http
        );
    }
    if let Some(scene) = &opts.scene {
        read_checked_scene(scene)?;
    }
    let specs = vec![
        WorkerSpec {
            threads: opts.threads_per_worker,
        };
        opts.workers
    ];
    let mut args = up_limits();
    args.extend(["--http".to_owned(), opts.http.to_string()]);
    if let Some(scene) = &opts.scene {
        let absolute = std::path::absolute(scene)
            .with_context(|| format!("cannot resolve {}", scene.display()))?;
        args.extend(["--studio-scene".to_owned(), absolute.display().to_string()]);
    }
    let exe = std::env::current_exe().context("cannot find the tessera executable")?;
    let starting = tokio::task::spawn_blocking(move || {
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        LocalFarm::start_with(&exe, &specs, &args)
    });
    let farm = tokio::select! {
        farm = starting => farm.context("starting the local farm")??,
        signal = stop.next() => return Err(signal.into()),
    };
    let ready: Result<()> = tokio::select! {
        r = farm.wait_for_workers(opts.workers, Duration::from_secs(30)) => r.map_err(Into::into),
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
        opts.workers
    );
    let result: Result<()> = tokio::select! {
        e = farm.first_exit() => Err(e.into()),
        signal = stop.next() => Err(signal.into()),
    };
    drop(farm);
    match result {
        // Stopping the studio is how it ends: not an error, but the farm is gone.
        Err(e) if e.downcast_ref::<crate::up_command::Interrupted>().is_some() => {
            eprintln!("studio stopped: the local farm is stopped and its files removed");
            Ok(())
        }
        other => other,
    }
}
