//! `tessera coordinator` and `tessera worker`: the two long-running processes.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use anyhow::{Context, Result};
use tracing::info;
use transport::Endpoint;

/// Completes on Ctrl-C, on SIGTERM, or (for processes started by `tessera up`) when
/// standard input reaches its end because the parent is gone.
pub async fn shutdown_signal(exit_on_stdin_eof: bool) {
    let stdin_closed = async {
        if exit_on_stdin_eof {
            let _ = tokio::task::spawn_blocking(|| {
                let mut sink = Vec::new();
                let _ = std::io::Read::read_to_end(&mut std::io::stdin(), &mut sink);
            })
            .await;
        } else {
            std::future::pending::<()>().await;
        }
    };
    #[cfg(unix)]
    let terminate = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(_) => std::future::pending().await,
        }
    };
    #[cfg(not(unix))]
    let terminate = std::future::pending::<()>();
    tokio::select! {
        _ = tokio::signal::ctrl_c() => info!("interrupted"),
        () = terminate => info!("terminated"),
        () = stdin_closed => info!("parent gone"),
    }
}

pub async fn coordinator(config: coordinator::Config, exit_on_stdin_eof: bool) -> Result<()> {
    return_large_blocks_to_the_system();
    let fingerprint = config
        .tls
        .as_ref()
        .map(|tls| transport::fingerprint_hex(&tls.fingerprint()));
    let (workers_prove, clients_prove) = (
        config.worker_secret.is_some(),
        config.client_secret.is_some(),
    );
    let server = coordinator::server::Server::bind(config).await?;
    let addr = server.local_addr()?;
    // The first line on stdout is the address, for scripts and `tessera up`.
    println!("listening on {addr}");
    info!(%addr, workers_prove, clients_prove, "coordinator listening");
    if let Some(http) = server.http_addr()? {
        println!("http on {http}");
        info!(%http, "status page, metrics and health on http://{http}/");
    }
    if let Some(fingerprint) = fingerprint {
        // Peers pin this (`--tls-fingerprint`) instead of needing a copy of the
        // certificate.
        println!("tls fingerprint {fingerprint}");
        info!(%fingerprint, "TLS certificate's SHA-256 fingerprint: pin it with --tls-fingerprint");
    }
    server.run(shutdown_signal(exit_on_stdin_eof)).await
}

pub async fn worker(
    coordinator: Endpoint,
    threads: Option<usize>,
    name: Option<String>,
    throttle: Option<f64>,
    http: Option<std::net::SocketAddr>,
    exit_on_stdin_eof: bool,
) -> Result<()> {
    let threads =
        threads.unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()));
    let name = name.unwrap_or_else(default_worker_name);
    let ready = Arc::new(AtomicBool::new(false));
    let _health = match http {
        Some(addr) => {
            let listener = tokio::net::TcpListener::bind(addr)
                .await
                .with_context(|| format!("cannot listen for HTTP on {addr}"))?;
            info!(http = %listener.local_addr()?, "health on /healthz and /readyz");
            let flag = Arc::clone(&ready);
            let routes =
                coordinator::http::worker_routes(Arc::new(move || flag.load(Ordering::Relaxed)));
            Some(coordinator::http::spawn(listener, routes))
        }
        None => None,
    };
    worker::run(
        worker::Config {
            coordinator,
            threads,
            name,
            throttle,
            ready,
        },
        shutdown_signal(exit_on_stdin_eof),
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

/// Has the C allocator give every large block (a frame being assembled, an encoded
/// image) straight back to the system when it is freed.
///
/// glibc otherwise raises its threshold for such blocks each time one is freed, and
/// then serves the next ones from its heap, which keeps the memory of past frames:
/// a coordinator's resident memory would follow the largest frames it ever finished,
/// not the frames it is assembling now. A fixed threshold keeps it to the active jobs
/// (measured in `tests/coordinator_faults.rs`, and in docs/reliability.md).
fn return_large_blocks_to_the_system() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        /// `M_MMAP_THRESHOLD` of glibc's `<malloc.h>`.
        const M_MMAP_THRESHOLD: std::os::raw::c_int = -3;
        extern "C" {
            fn mallopt(
                param: std::os::raw::c_int,
                value: std::os::raw::c_int,
            ) -> std::os::raw::c_int;
        }
        // SAFETY: mallopt only sets a tuning parameter of the allocator; it is called
        // at startup, before the daemon allocates frames, and its failure (return 0)
        // leaves the default behaviour.
        unsafe {
            mallopt(M_MMAP_THRESHOLD, 256 * 1024);
        }
    }
}
