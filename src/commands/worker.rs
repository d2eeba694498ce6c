//! `tessera worker`: the daemon that renders tiles for a coordinator, with an optional
//! HTTP port for health checks.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use anyhow::{Context, Result};
use tracing::{info, warn};

use crate::args::{DaemonArgs, PeerArgs};
use crate::signals::shutdown_signal;

/// Run a worker: render tiles for a coordinator.
#[derive(clap::Args)]
#[command(after_help = "Example:\n  tessera worker --coordinator 127.0.0.1:7878 --threads 8")]
pub struct Args {
    #[command(flatten)]
    daemon: DaemonArgs,
    #[command(flatten)]
    peer: PeerArgs,
    /// Rendering threads [default: one per core].
    #[arg(long, env = "TESSERA_THREADS", value_name = "N", value_parser = clap::value_parser!(u32).range(1..=1024))]
    threads: Option<u32>,
    /// Name shown by `tessera workers`, under which the coordinator counts this worker's
    /// failed tiles: keep it stable across restarts (the host name) [default: HOST-PID].
    #[arg(long, env = "TESSERA_NAME")]
    name: Option<String>,
    /// Keep the files scenes name (meshes and their buffers) in DIR once fetched, so
    /// that the next job naming one starts without a transfer [default: none, files are
    /// kept only while their scene is].
    #[arg(long, env = "TESSERA_CACHE_DIR", value_name = "DIR")]
    cache_dir: Option<std::path::PathBuf>,
    /// The most bytes of files kept in --cache-dir; the least recently used go first.
    #[arg(long, env = "TESSERA_CACHE_SIZE", value_name = "BYTES", default_value_t = 10 << 30)]
    cache_size: u64,
    /// A tag of this worker (repeat for more, or in TESSERA_TAG separate them with
    /// commas; in a config file an array): jobs submitted with `--require NAME` go only
    /// to workers with every tag they require. Names: lowercase letters, digits, '.',
    /// '_' and '-', starting with a letter or a digit, at most 64 characters; at most 32
    /// tags.
    #[arg(long = "tag", env = "TESSERA_TAG", value_name = "NAME", value_delimiter = ',',
          action = clap::ArgAction::Append, value_parser = crate::args::parse_tag)]
    tags: Vec<String>,
    /// Exit when standard input closes (used by `tessera up` for its children).
    #[arg(long, hide = true)]
    exit_on_stdin_eof: bool,
}

/// Starts the worker, or with `print_config` (the effective settings, as
/// `--print-config` shows them) makes the start's checks and prints them instead.
pub fn run(args: Args, print_config: Option<String>) -> Result<()> {
    args.daemon.init_logging();
    super::block_on(work(args, print_config))
}

/// Serves health on `--http` (ready while connected and taking tiles, for supervisors)
/// and renders until a signal, a drain, or with `--exit-on-stdin-eof` its parent gone.
async fn work(a: Args, print_config: Option<String>) -> Result<()> {
    let coordinator = a.peer.endpoint()?;
    if let Some(warning) = a.peer.token_file_warning() {
        warn!("{warning}");
    }
    // `--print-config` stops here, with the verdict of the start's checks.
    if let Some(settings) = print_config {
        print!("{settings}");
        return Ok(());
    }
    let threads = a.threads.map_or_else(
        || std::thread::available_parallelism().map_or(1, |n| n.get()),
        |n| n as usize,
    );
    let name = a.name.unwrap_or_else(default_worker_name);
    let tags = protocol::check_tags(&a.tags).map_err(|e| anyhow::anyhow!("--tag: {e}"))?;
    let ready = Arc::new(AtomicBool::new(false));
    let _health = match a.daemon.http {
        Some(addr) => {
            let listener = tokio::net::TcpListener::bind(addr)
                .await
                .with_context(|| format!("cannot listen for HTTP on {addr}"))?;
            info!(http = %listener.local_addr()?, "health on /healthz and /readyz");
            let flag = Arc::clone(&ready);
            let routes = httpd::worker_routes(Arc::new(move || flag.load(Ordering::Relaxed)));
            Some(httpd::spawn(listener, None, routes))
        }
        None => None,
    };
    worker::run(
        worker::Config {
            coordinator,
            threads,
            name,
            ready,
            cache_dir: a.cache_dir,
            cache_bytes: a.cache_size,
            tags,
        },
        shutdown_signal(a.exit_on_stdin_eof),
    )
    .await
    .context("worker stopped")
}

/// `host-pid`, unique enough to tell workers apart in listings.
fn default_worker_name() -> String {
    let host = std::fs::read_to_string("/etc/hostname")
        .ok()
        .map(|h| h.trim().to_string())
        .filter(|h| !h.is_empty())
        .unwrap_or_else(|| "worker".into());
    format!("{host}-{}", std::process::id())
}
