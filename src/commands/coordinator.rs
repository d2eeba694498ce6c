//! `tessera coordinator`: the daemon that accepts jobs, hands tiles to workers and
//! stores images. Its settings become a [`coordinator::Config`], checked by the
//! library's rules ([`coordinator::Config::check_security`]) before it binds.

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use anyhow::{anyhow, bail, Result};
use render::limits::MAX_AA;
use tracing::{error, info, warn};
use transport::ServerTls;

use crate::args::DaemonArgs;
use crate::config;
use crate::scene_file::read_studio_scene;
use crate::signals::{shutdown_signal, Hangups};

/// Run a coordinator: accept jobs, hand tiles to workers, store images.
#[derive(clap::Args)]
#[command(
    after_help = "Example:\n  tessera coordinator --listen 127.0.0.1:7878 --data /var/lib/tessera"
)]
pub struct Args {
    #[command(flatten)]
    daemon: DaemonArgs,
    /// Address to listen on.
    #[arg(long, env = "TESSERA_LISTEN", value_name = "ADDR", default_value = transport::DEFAULT_ADDRESS)]
    listen: SocketAddr,
    /// Where jobs and images are stored.
    #[arg(
        long,
        env = "TESSERA_DATA",
        value_name = "DIR",
        default_value = "tessera-data"
    )]
    data: PathBuf,
    /// Largest protocol frame accepted from a peer, in bytes (it bounds the scene a job
    /// may carry).
    #[arg(long, env = "TESSERA_MAX_FRAME", value_name = "BYTES", default_value_t = protocol::DEFAULT_MAX_FRAME as u64,
          value_parser = clap::value_parser!(u64).range(2 * 1024 * 1024..=protocol::MAX_FRAME_LIMIT as u64))]
    max_frame: u64,
    /// Connections served at once; more are refused with a message.
    #[arg(long, env = "TESSERA_MAX_CONNECTIONS", value_name = "N", default_value_t = coordinator::server::DEFAULT_MAX_CONNECTIONS as u32,
          value_parser = clap::value_parser!(u32).range(1..=65_536))]
    max_connections: u32,
    /// Largest scene a job may carry, in bytes.
    #[arg(long, env = "TESSERA_MAX_SCENE_BYTES", value_name = "BYTES", default_value_t = 8 * 1024 * 1024)]
    max_scene_bytes: u64,
    /// Most objects a scene may have.
    #[arg(
        long,
        env = "TESSERA_MAX_OBJECTS",
        value_name = "N",
        default_value_t = 100_000
    )]
    max_objects: u64,
    /// Most pixels an image may have.
    #[arg(long, env = "TESSERA_MAX_PIXELS", value_name = "N", default_value_t = 8192 * 8192)]
    max_pixels: u64,
    /// Largest antialiasing a job may ask for.
    #[arg(long, env = "TESSERA_MAX_AA", value_name = "N", default_value_t = 16, value_parser = clap::value_parser!(u32).range(1..=i64::from(MAX_AA)))]
    max_aa: u32,
    /// Largest file a scene may name (a mesh, a glTF's buffer), in bytes: an upload of
    /// a larger one is refused at its first chunk.
    #[arg(long, env = "TESSERA_MAX_FILE_BYTES", value_name = "BYTES", default_value_t = render::limits::MAX_MESH_FILE_BYTES,
          value_parser = clap::value_parser!(u64).range(1..=render::limits::MAX_MESH_FILE_BYTES))]
    max_file_bytes: u64,
    /// Most bytes of the files scenes name kept under --data (complete files and uploads
    /// in progress): an upload that would go over is refused at its first chunk.
    #[arg(long, env = "TESSERA_MAX_STORE_BYTES", value_name = "BYTES", default_value_t = coordinator::server::default_file_limits().max_total_bytes,
          value_parser = clap::value_parser!(u64).range(1..))]
    max_store_bytes: u64,
    /// Most jobs queued or running per client address.
    #[arg(
        long,
        env = "TESSERA_MAX_JOBS_PER_CLIENT",
        value_name = "N",
        default_value_t = 64
    )]
    max_jobs_per_client: u64,
    #[command(flatten)]
    secrets: CoordinatorSecretArgs,
    /// After SIGHUP reloads the token files, how long a replaced token stays accepted
    /// beside the new one (then the peers still using it are disconnected and must
    /// reconnect with the new one): a whole number and a unit, ms, s, m, h or d.
    #[arg(long, env = "TESSERA_TOKEN_OVERLAP", value_name = "DURATION", default_value = "10m",
          value_parser = config::parse_duration)]
    token_overlap: Duration,
    /// Serve TLS with a self-signed certificate made on first start and kept under
    /// --data (tls/cert.pem, tls/key.pem, mode 0600); its SHA-256 fingerprint is printed
    /// at startup for peers to pin with --tls-fingerprint.
    #[arg(long, env = "TESSERA_TLS_AUTO", conflicts_with_all = ["tls_cert", "tls_key"])]
    tls_auto: bool,
    /// Print the SHA-256 fingerprint of the TLS certificate (with --tls-auto, making it
    /// if there is none yet) and exit.
    #[arg(long)]
    print_fingerprint: bool,
    /// PEM certificate chain: serve TLS with it (needs --tls-key).
    #[arg(
        long,
        env = "TESSERA_TLS_CERT",
        value_name = "FILE",
        requires = "tls_key"
    )]
    tls_cert: Option<PathBuf>,
    /// PEM private key of --tls-cert.
    #[arg(
        long,
        env = "TESSERA_TLS_KEY",
        value_name = "FILE",
        requires = "tls_cert"
    )]
    tls_key: Option<PathBuf>,
    /// Milliseconds without a heartbeat after which a worker counts as lost and its
    /// tiles go to others.
    #[arg(long, env = "TESSERA_HEARTBEAT_TIMEOUT_MS", value_name = "MS", default_value_t = scheduler::Policy::default().heartbeat_timeout,
          value_parser = clap::value_parser!(u64).range(500..=3_600_000))]
    heartbeat_timeout_ms: u64,
    /// Milliseconds a worker holding a tile whose lease ran out may go without
    /// returning any result before it is marked unresponsive (its heartbeats prove a
    /// connection, not progress): it then gets no tile and its tiles go to others until
    /// it returns one. A slow worker is given more: sixteen times its own slowest
    /// result, when that is longer (docs/reliability.md, "Liveness").
    #[arg(long, env = "TESSERA_PROGRESS_TIMEOUT_MS", value_name = "MS", default_value_t = scheduler::Policy::default().progress_timeout,
          value_parser = clap::value_parser!(u64).range(1_000..=86_400_000))]
    progress_timeout_ms: u64,
    /// Pixels of every tile result the coordinator renders again to check it, chosen at
    /// random once the result has arrived (at most one in 128 of the tile's pixels; 0
    /// turns spot checks off).
    #[arg(long, env = "TESSERA_SPOT_PIXELS", value_name = "N", default_value_t = coordinator::VerifyConfig::default().spot_pixels,
          value_parser = clap::value_parser!(u32).range(0..=1024))]
    spot_pixels: u32,
    /// Share of the tiles of jobs in sampled verification rendered again by another
    /// machine and compared byte for byte, from 0 (none) to 1 (all).
    #[arg(long, env = "TESSERA_AUDIT_SHARE", value_name = "SHARE", default_value_t = coordinator::VerifyConfig::default().audit_share,
          value_parser = config::parse_share)]
    audit_share: f64,
    /// Listen on a non-loopback address without both tokens: peers whose role has no
    /// token are accepted without proof.
    #[arg(long, env = "TESSERA_INSECURE")]
    insecure: bool,
    /// Serve --http on a non-loopback address without TLS: the client secret, scenes
    /// and images then cross the network in clear.
    #[arg(long, env = "TESSERA_HTTP_INSECURE")]
    http_insecure: bool,
    /// Milliseconds a peer has to complete its handshake.
    #[arg(long, env = "TESSERA_HANDSHAKE_TIMEOUT_MS", value_name = "MS", default_value_t = coordinator::server::DEFAULT_HANDSHAKE_TIMEOUT.as_millis() as u64,
          value_parser = clap::value_parser!(u64).range(100..=600_000))]
    handshake_timeout_ms: u64,
    /// Delete a finished job (done, failed or cancelled) this long after it ended: a
    /// whole number and a unit, s, m, h or d (90s, 30m, 12h, 7d) [default: keep jobs
    /// until `tessera delete`].
    #[arg(long, env = "TESSERA_RETENTION", value_name = "DURATION", value_parser = config::parse_duration)]
    retention: Option<Duration>,
    /// How long the farm's events are kept for event streams that resume (`GET
    /// /api/v1/events`, docs/events.md): a whole number and a unit, s, m, h or d. A
    /// stream asking for an older one is told of the gap.
    #[arg(long, env = "TESSERA_EVENT_RETENTION", value_name = "DURATION", default_value = "7d",
          value_parser = config::parse_duration)]
    event_retention: Duration,
    /// How many of the farm's events are kept at most (the newest), whatever their age.
    #[arg(long, env = "TESSERA_EVENT_RETENTION_COUNT", value_name = "N", default_value_t = coordinator::events::DEFAULT_RETENTION_COUNT,
          value_parser = clap::value_parser!(u64).range(1..))]
    event_retention_count: u64,
    /// If the job database is missing or unreadable although the data directory has
    /// held jobs, start a new empty one instead of refusing to start (unfinished jobs
    /// are lost; new ids continue after the highest ever issued). For this start only:
    /// no environment variable or config file key.
    #[arg(long)]
    reset_database: bool,
    /// The scene the studio page (`/studio`) opens with [default: the seed scene at
    /// 960 x 540, aa 2]: a scene file, its mesh files read beside it, or a .tar archive
    /// of a scene and its files (the studio's Save). Checked at start like any scene.
    #[arg(long, env = "TESSERA_STUDIO_SCENE", value_name = "FILE")]
    studio_scene: Option<PathBuf>,
    /// The webhooks: boxed, as the largest of the settings, so that the command line's
    /// parsed form stays small beside the other commands'.
    #[command(flatten)]
    webhooks: Box<WebhookArgs>,
    /// Exit when standard input closes (used by `tessera up` for its children).
    #[arg(long, hide = true)]
    exit_on_stdin_eof: bool,
}

/// Where each job's end is posted (docs/operations.md, "Webhooks").
#[derive(clap::Args)]
struct WebhookArgs {
    /// Post each job's end (done, failed, cancelled) as signed JSON to this URL, http://
    /// or https:// (docs/operations.md, "Webhooks"); repeat it for several receivers (a
    /// config file takes a list; TESSERA_WEBHOOK holds one URL). Redirects are not
    /// followed.
    #[arg(long = "webhook", env = "TESSERA_WEBHOOK", value_name = "URL")]
    webhook: Vec<String>,
    /// File holding the key webhook posts are signed with (HMAC-SHA256 in the
    /// Tessera-Signature header) [or set TESSERA_WEBHOOK_SECRET to the key itself];
    /// without one, posts are not signed.
    #[arg(long, env = "TESSERA_WEBHOOK_SECRET_FILE", value_name = "FILE")]
    webhook_secret_file: Option<PathBuf>,
    /// PEM file of the CA certificates https:// webhooks are verified against, instead
    /// of the system's trust store.
    #[arg(long, env = "TESSERA_WEBHOOK_CA", value_name = "FILE")]
    webhook_ca: Option<PathBuf>,
    /// Job ends waiting per webhook behind the one being posted or retried; when one
    /// more comes, the oldest of them is dropped (counted in
    /// tessera_webhook_dropped_total).
    #[arg(long, env = "TESSERA_WEBHOOK_QUEUE", value_name = "N", default_value_t = coordinator::webhooks::DEFAULT_QUEUE as u32,
          value_parser = clap::value_parser!(u32).range(1..=1_000_000))]
    webhook_queue: u32,
    /// Failed attempts after which a job's end is given up (logged, counted).
    #[arg(long, env = "TESSERA_WEBHOOK_ATTEMPTS", value_name = "N", default_value_t = coordinator::webhooks::DEFAULT_ATTEMPTS,
          value_parser = clap::value_parser!(u32).range(1..=1000))]
    webhook_attempts: u32,
    /// The delay before a webhook's first retry, doubled at each next one up to 5
    /// minutes: a whole number and a unit, ms, s, m, h or d.
    #[arg(long, env = "TESSERA_WEBHOOK_BACKOFF", value_name = "DURATION", default_value = "1s",
          value_parser = config::parse_duration)]
    webhook_backoff: Duration,
    /// A job's end older than this is given up at its next failed attempt, whatever
    /// its attempts.
    #[arg(long, env = "TESSERA_WEBHOOK_MAX_AGE", value_name = "DURATION", default_value = "1h",
          value_parser = config::parse_duration)]
    webhook_max_age: Duration,
    /// How long a webhook post may take, connecting and answering, before it counts as
    /// failed.
    #[arg(long, env = "TESSERA_WEBHOOK_TIMEOUT", value_name = "DURATION", default_value = "10s",
          value_parser = config::parse_duration)]
    webhook_timeout: Duration,
}

/// The coordinator's two secrets: one that workers prove, one that clients prove.
#[derive(clap::Args)]
struct CoordinatorSecretArgs {
    /// File holding the token workers must prove (and that the coordinator proves to
    /// them) [or set TESSERA_WORKER_TOKEN to the token itself].
    #[arg(long, env = "TESSERA_WORKER_TOKEN_FILE", value_name = "FILE")]
    worker_token_file: Option<PathBuf>,
    /// File holding the token clients must prove (and that the coordinator proves to
    /// them); it must differ from the worker token [or set TESSERA_CLIENT_TOKEN to the
    /// token itself].
    #[arg(long, env = "TESSERA_CLIENT_TOKEN_FILE", value_name = "FILE")]
    client_token_file: Option<PathBuf>,
    /// File holding the token Prometheus scrapes /metrics with (`Authorization: Bearer
    /// TOKEN`), a secret of its own that shows the counters and nothing else; without
    /// it /metrics takes the client token [or set TESSERA_METRICS_TOKEN to the token
    /// itself].
    #[arg(long, env = "TESSERA_METRICS_TOKEN_FILE", value_name = "FILE")]
    metrics_token_file: Option<PathBuf>,
    /// No longer a coordinator setting: refused with an explanation.
    #[arg(long, hide = true, value_name = "FILE")]
    token_file: Option<PathBuf>,
}

/// Why a coordinator does not take one shared token any more.
const ONE_TOKEN_RETIRED: &str = "a coordinator takes two tokens, one for workers and one for \
    clients, so that a client's credential cannot join as a worker: give \
    --worker-token-file FILE and --client-token-file FILE (TESSERA_WORKER_TOKEN_FILE, \
    TESSERA_CLIENT_TOKEN_FILE), two different secrets, e.g. each from `openssl rand -hex 32`";

/// The workers' secret and the clients' secret, each if set.
type RoleSecrets = (Option<Vec<u8>>, Option<Vec<u8>>);

impl CoordinatorSecretArgs {
    /// The worker secret and the client secret. One shared token (`--token-file`,
    /// `TESSERA_TOKEN_FILE`, `TESSERA_TOKEN`) is refused rather than silently applied to
    /// both roles or ignored; two equal secrets are refused by
    /// [`coordinator::Config::check_security`].
    fn load(&self) -> Result<RoleSecrets> {
        if self.token_file.is_some() {
            bail!("--token-file: {ONE_TOKEN_RETIRED}");
        }
        for variable in ["TESSERA_TOKEN_FILE", "TESSERA_TOKEN"] {
            if std::env::var_os(variable).is_some() {
                bail!("{variable} is set (unset it for the coordinator): {ONE_TOKEN_RETIRED}");
            }
        }
        let worker =
            transport::load_secret(self.worker_token_file.as_deref(), "TESSERA_WORKER_TOKEN")?;
        let client =
            transport::load_secret(self.client_token_file.as_deref(), "TESSERA_CLIENT_TOKEN")?;
        Ok((worker, client))
    }

    /// The scrape token of `/metrics`, if set.
    fn load_scrape(&self) -> Result<Option<Vec<u8>>> {
        Ok(transport::load_secret(
            self.metrics_token_file.as_deref(),
            "TESSERA_METRICS_TOKEN",
        )?)
    }
}

/// Starts the coordinator, or with `print_config` (the effective settings, as
/// `--print-config` shows them) makes the start's checks and prints them instead.
pub fn run(args: Args, print_config: Option<String>) -> Result<()> {
    args.daemon.init_logging();
    super::block_on(coordinator(args, print_config))
}

async fn coordinator(a: Args, print_config: Option<String>) -> Result<()> {
    let pem = a.tls_cert.clone().zip(a.tls_key.clone());
    let pem = pem
        .as_ref()
        .map(|(cert, key)| (cert.as_path(), key.as_path()));
    if a.print_fingerprint {
        let tls = ServerTls::from_settings(pem, a.tls_auto, &a.data)?;
        let tls = tls.ok_or_else(|| {
            anyhow!(
                "--print-fingerprint: this coordinator has no certificate: give \
                 --tls-auto (or --tls-cert and --tls-key)"
            )
        })?;
        println!("{}", transport::fingerprint_hex(&tls.fingerprint()));
        return Ok(());
    }
    let (worker_secret, client_secret) = a.secrets.load()?;
    for file in [&a.secrets.worker_token_file, &a.secrets.client_token_file] {
        if let Some(warning) = file.as_deref().and_then(transport::exposed_token_file) {
            warn!("{warning}");
        }
    }
    let mut config = coordinator::Config {
        listen: a.listen,
        data: a.data,
        max_frame: a.max_frame as usize,
        max_connections: a.max_connections as usize,
        handshake_timeout: Duration::from_millis(a.handshake_timeout_ms),
        worker_secret,
        client_secret,
        metrics_secret: a.secrets.load_scrape()?,
        token_overlap: a.token_overlap,
        // Set once the settings pass the checks: `--tls-auto` creates a certificate.
        tls: None,
        policy: scheduler::Policy {
            heartbeat_timeout: a.heartbeat_timeout_ms,
            progress_timeout: a.progress_timeout_ms,
            ..Default::default()
        },
        verify: coordinator::VerifyConfig {
            spot_pixels: a.spot_pixels,
            audit_share: a.audit_share,
        },
        limits: scheduler::lifecycle::Limits {
            max_scene_bytes: a.max_scene_bytes as usize,
            max_objects: a.max_objects as usize,
            max_pixels: a.max_pixels,
            max_aa: a.max_aa,
            max_active_per_client: a.max_jobs_per_client as usize,
            retention: a.retention.map(|d| d.as_millis() as scheduler::Millis),
            ..Default::default()
        },
        files: coordinator::server::StoreLimits {
            max_file_bytes: a.max_file_bytes,
            max_total_bytes: a.max_store_bytes,
        },
        http: a.daemon.http,
        events: coordinator::events::Retention {
            max_age: a.event_retention,
            max_count: a.event_retention_count,
        },
        reset_database: a.reset_database,
        // Read once the settings pass the security check, whose refusal comes first.
        studio_scene: None,
        webhooks: coordinator::server::WebhookConfig {
            urls: a.webhooks.webhook.clone(),
            secret: transport::load_secret(
                a.webhooks.webhook_secret_file.as_deref(),
                "TESSERA_WEBHOOK_SECRET",
            )
            .map_err(|e| anyhow!("--webhook-secret-file: {e}"))?,
            ca: a.webhooks.webhook_ca.clone(),
            policy: coordinator::webhooks::Policy {
                queue: a.webhooks.webhook_queue as usize,
                attempts: a.webhooks.webhook_attempts,
                backoff: a.webhooks.webhook_backoff,
                max_age: a.webhooks.webhook_max_age,
            },
            timeout: a.webhooks.webhook_timeout,
        },
    };
    for url in &a.webhooks.webhook {
        coordinator::webhooks::parse_url(url).map_err(|why| anyhow!("--webhook {url:?}: {why}"))?;
    }
    if let Some(warning) = a
        .webhooks
        .webhook_secret_file
        .as_deref()
        .and_then(transport::exposed_token_file)
    {
        warn!("{warning}");
    }
    config.check_security(a.insecure, a.http_insecure, a.tls_auto || pem.is_some())?;
    config.studio_scene = a
        .studio_scene
        .as_deref()
        .map(read_studio_scene)
        .transpose()?;
    // `--print-config` stops here, with the verdict of the start's checks: what
    // follows creates files or binds.
    if let Some(settings) = print_config {
        print!("{settings}");
        return Ok(());
    }
    config.tls = ServerTls::from_settings(pem, a.tls_auto, &config.data)?;
    serve(config, a.exit_on_stdin_eof, a.secrets).await
}

/// Binds, prints where it listens (and its certificate's fingerprint) and serves until
/// a signal, or with `exit_on_stdin_eof` until its parent is gone. SIGHUP reloads the
/// token files from `secrets`.
async fn serve(
    config: coordinator::Config,
    exit_on_stdin_eof: bool,
    secrets: CoordinatorSecretArgs,
) -> Result<()> {
    return_large_blocks_to_the_system();
    // Caught before anything is bound, so that a SIGHUP sent as soon as the address is
    // printed never ends the daemon.
    let hangups = Hangups::new()?;
    let fingerprint = config
        .tls
        .as_ref()
        .map(|tls| transport::fingerprint_hex(&tls.fingerprint()));
    let (workers_prove, clients_prove) = (
        config.worker_secret.is_some(),
        config.client_secret.is_some(),
    );
    let worker_key = config.worker_secret.as_deref().map(protocol::KeyId::of);
    let client_key = config.client_secret.as_deref().map(protocol::KeyId::of);
    let server = coordinator::server::Server::bind(config).await?;
    let _reloads = AbortOnDrop(tokio::spawn(reload_on_hangup(
        hangups,
        secrets,
        server.token_reloader(),
    )));
    let addr = server.local_addr()?;
    // The first line on stdout is the address, for scripts and `tessera up`.
    println!("listening on {addr}");
    info!(%addr, workers_prove, clients_prove, "coordinator listening");
    if worker_key.is_some() || client_key.is_some() {
        let key =
            |k: Option<protocol::KeyId>| k.map_or_else(|| "none".to_owned(), |k| k.to_string());
        info!(
            worker_key = %key(worker_key),
            client_key = %key(client_key),
            "tokens loaded (SIGHUP reloads them)"
        );
    }
    if let Some(http) = server.http_addr()? {
        println!("http on {http}");
        let scheme = if fingerprint.is_some() {
            "https"
        } else {
            "http"
        };
        info!(%http, "status page, metrics and health on {scheme}://{http}/");
    }
    if let Some(fingerprint) = fingerprint {
        // Peers pin this (`--tls-fingerprint`) instead of needing a copy of the
        // certificate.
        println!("tls fingerprint {fingerprint}");
        info!(%fingerprint, "TLS certificate's SHA-256 fingerprint: pin it with --tls-fingerprint");
    }
    coordinator::daemon::run(server, shutdown_signal(exit_on_stdin_eof)).await
}

/// Reloads the token files at every SIGHUP. A reload that fails (a file unreadable or
/// empty, the two tokens equal) changes nothing: one error line, and the daemon goes on
/// with the tokens it had.
async fn reload_on_hangup(
    mut hangups: Hangups,
    secrets: CoordinatorSecretArgs,
    reloader: coordinator::server::TokenReloader,
) {
    while hangups.next().await {
        let reloaded = secrets
            .load()
            .and_then(|(worker, client)| Ok(reloader.reload(worker, client)?));
        let reloaded = reloaded.and_then(|()| {
            reloader.reload_scrape(secrets.load_scrape()?);
            Ok(())
        });
        if let Err(e) = reloaded {
            error!(
                error = %format!("{e:#}"),
                "SIGHUP: cannot reload the token files: the tokens in use stay in use"
            );
        }
    }
}

/// Aborts a task when dropped: the reload task ends with the daemon.
struct AbortOnDrop(tokio::task::JoinHandle<()>);

impl Drop for AbortOnDrop {
    fn drop(&mut self) {
        self.0.abort();
    }
}

/// Has the C allocator give every large block (a frame being assembled, an encoded
/// image) straight back to the system when it is freed.
///
/// glibc otherwise raises its threshold for such blocks each time one is freed, and
/// then serves the next ones from its heap, which keeps the memory of past frames:
/// a coordinator's resident memory would follow the largest frames it ever finished,
/// not the frames it is assembling now. A fixed threshold keeps it to the active jobs
/// (measured in `tests/end_to_end/faults/coordinator.rs`, and in docs/reliability.md).
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
