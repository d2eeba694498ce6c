//! `tessera`: the command line. This file only parses arguments and hands them to the
//! modules that run each subcommand.

mod client_commands;
mod config;
mod daemons;
mod output;
mod render_command;
mod render_state;
mod sequence_commands;
mod simulate_command;
mod studio_command;
mod up_command;

use std::net::SocketAddr;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

use anyhow::{anyhow, bail, Result};
use clap::{Args, CommandFactory, FromArgMatches, Parser, Subcommand, ValueEnum};
use protocol::{JobId, Overrides};
use render::limits::{MAX_AA, MAX_DEPTH, MAX_SIDE};
use render::Sampling;
use transport::{ClientTls, Endpoint, ServerTls};

/// The coordinator's default address.
const DEFAULT_COORDINATOR: &str = "127.0.0.1:7878";

/// Tessera renders ray-traced images of JSON scenes (spheres, planes, point lights,
/// mirrors and checkerboards), on this machine or on a farm of workers.
#[derive(Parser)]
#[command(
    name = "tessera",
    version,
    propagate_version = true,
    args_override_self = true
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Render a scene file to a PNG image on this machine.
    #[command(
        long_about = "Render a scene file to a PNG image on this machine, using all cores.\n\n\
            The scene is a JSON file (see docs/scene-format.md); its optional \"image\" \
            settings give the size and antialiasing, and the flags below override them. \
            The image is written only when the whole render succeeds.\n\n\
            An animated scene renders its frame 1, or frame K with --frame K; --frames \
            renders a sequence into a directory, one PNG per frame, each written whole.",
        after_help = "Examples:\n  \
            tessera render scenes/seed.json                 writes seed.png here\n  \
            tessera render scenes/seed.json -o big.png --width 1920 --height 1080 --aa 4\n  \
            tessera render scenes/seed-orbit.json --frame 17 -o orbit17.png\n  \
            tessera render scenes/seed-orbit.json --frames 1-120 -o orbit/"
    )]
    Render(RenderArgs),

    /// Go on from a saved adaptive render to a lower error or a larger cap.
    #[command(
        long_about = "Go on from a render saved with `tessera render --state FILE` to a lower \
            error target or a larger --aa, taking only the samples it lacks. The image is \
            byte for byte the one a direct render with the final settings gives. The state \
            file is updated in place, so refining can go on again. Given the id of a \
            finished adaptive job instead, a coordinator starts a new job from the tile \
            states it kept for that job, with the same bytes a direct job would give.",
        after_help = "Examples:\n  \
            tessera render scenes/seed.json --sampler adaptive --target-error 4 --state seed.state\n  \
            tessera refine seed.state --target-error 1 -o seed.png\n  \
            tessera refine 12 --target-error 0.5 --aa 16 --wait -o seed.png"
    )]
    Refine(RefineArgs),

    /// Render a scene on a farm started on this machine for the occasion.
    #[command(
        long_about = "Start a coordinator and worker processes on this machine (loopback \
            only), render the scene on them, write the image and stop them all again.",
        after_help = "Example:\n  tessera up scenes/seed.json --workers 3 -o seed.png"
    )]
    Up(UpArgs),
    /// Edit a scene and move its camera in the browser while a local farm renders it.
    #[command(
        long_about = "Start a coordinator and worker processes on this machine (loopback \
            only), serve the studio page and print its address: a scene editor whose \
            every change the farm renders progressively. Ctrl-C stops the farm and removes \
            its files.",
        after_help = "Example:\n  tessera studio scenes/seed.json\n  \
            (then open the printed http://127.0.0.1:PORT/studio)"
    )]
    Studio(StudioArgs),

    /// Run a coordinator: accept jobs, hand tiles to workers, store images.
    #[command(
        after_help = "Example:\n  tessera coordinator --listen 127.0.0.1:7878 --data /var/lib/tessera"
    )]
    Coordinator(CoordinatorArgs),

    /// Run a worker: render tiles for a coordinator.
    #[command(after_help = "Example:\n  tessera worker --coordinator 127.0.0.1:7878 --threads 8")]
    Worker(WorkerArgs),

    /// Submit a scene to a coordinator; print the job id, or with --wait, write the image.
    #[command(after_help = "Examples:\n  \
        tessera submit scenes/seed.json                  prints the job id\n  \
        tessera submit scenes/seed.json --wait -o seed.png --aa 4\n  \
        tessera submit scenes/seed-orbit.json --frame 17 --wait -o orbit17.png")]
    Submit(SubmitArgs),

    /// Show a job's state and progress.
    Status {
        /// The job's id (as `tessera submit` and `tessera list` show it).
        #[arg(value_parser = parse_job_id)]
        job: JobId,
        #[command(flatten)]
        common: ClientArgs,
    },

    /// List the coordinator's jobs.
    List {
        #[command(flatten)]
        common: ClientArgs,
    },

    /// Cancel a job: its tiles stop being rendered.
    Cancel {
        /// The job's id (as `tessera submit` and `tessera list` show it).
        #[arg(value_parser = parse_job_id)]
        job: JobId,
        #[command(flatten)]
        common: ClientArgs,
    },

    /// Pause a queued or running job: no new tiles of it go out until it is resumed.
    #[command(
        long_about = "Pause a queued or running job: no new tiles of it are handed out \
            (tiles already out may finish, and count) until `tessera resume`. The pause \
            survives a restart of the coordinator. Pausing a paused job changes nothing; \
            pausing a job that has ended is an error.",
        after_help = "Example:\n  tessera pause 7"
    )]
    Pause {
        /// The job's id (as `tessera submit` and `tessera list` show it).
        #[arg(value_parser = parse_job_id)]
        job: JobId,
        #[command(flatten)]
        common: ClientArgs,
    },

    /// Resume a paused job: its tiles are handed out again.
    #[command(after_help = "Example:\n  tessera resume 7")]
    Resume {
        /// The job's id (as `tessera submit` and `tessera list` show it).
        #[arg(value_parser = parse_job_id)]
        job: JobId,
        #[command(flatten)]
        common: ClientArgs,
    },

    /// Change a queued or running job's priority: higher runs first.
    #[command(
        long_about = "Change a queued or running job's priority (as `tessera submit \
            --priority` sets it): higher runs first, and the next tiles handed out follow \
            the new order. Tiles already out finish where they are. Kept across a restart \
            of the coordinator.",
        after_help = "Example:\n  tessera priority 7 10\n  tessera priority 7 -5"
    )]
    Priority {
        /// The job's id (as `tessera submit` and `tessera list` show it).
        #[arg(value_parser = parse_job_id)]
        job: JobId,
        /// The new priority: higher runs first.
        #[arg(allow_negative_numbers = true)]
        priority: i32,
        #[command(flatten)]
        common: ClientArgs,
    },

    /// Show a job's event log: what happened to it, one line per event.
    #[command(
        long_about = "Show a job's event log, one line per event (time in UTC, event, \
            details): its submission (name, submitter, address), its first tile out, \
            each tile handed out and done (by which worker, in how long), failed or \
            taken back, quarantines affecting it, operators' pauses, priorities, \
            cancels, retries and requeues (with their address), adaptive passes, and \
            its end. Kept on the coordinator's disk with the job (at most 10,000 \
            events, then one saying how many more were not kept, and the end).",
        after_help = "Example:\n  tessera events 7\n  tessera events 7 --json"
    )]
    Events {
        /// The job's id (as `tessera submit` and `tessera list` show it).
        #[arg(value_parser = parse_job_id)]
        job: JobId,
        #[command(flatten)]
        common: ClientArgs,
    },

    /// Put a failed or cancelled job back in the queue under the same id.
    #[command(
        long_about = "Put a failed or cancelled job back in the queue under the same id: \
            the tiles it has stored count, the others are rendered, and its image is the \
            same as if it had never stopped. A job that is done, queued or running \
            cannot be retried.",
        after_help = "Example:\n  tessera retry 7"
    )]
    Retry {
        /// The job's id (as `tessera submit` and `tessera list` show it).
        #[arg(value_parser = parse_job_id)]
        job: JobId,
        /// For a sequence: render frame K again, alone (done, failed or cancelled).
        /// Without it, a sequence's failed and cancelled frames are rendered again.
        #[arg(long, value_name = "K", value_parser = clap::value_parser!(u32).range(1..))]
        frame: Option<u32>,
        #[command(flatten)]
        common: ClientArgs,
    },

    /// Render tiles of a queued or running job again (a machine is suspected).
    #[command(
        long_about = "Render the named tiles of a queued or running job again, wherever \
            they are: waiting, out on a worker (its result no longer counts), or done \
            (its result is dropped). For a machine an operator suspects; the events of \
            the job (`tessera events`) say which worker rendered each tile. A job that \
            has ended cannot be requeued: its image is final (submit it again instead).",
        after_help = "Example:\n  tessera requeue 7 3 4 12"
    )]
    Requeue {
        /// The job's id (as `tessera submit` and `tessera list` show it).
        #[arg(value_parser = parse_job_id)]
        job: JobId,
        /// The tiles' numbers (from 0, as the job's events name them).
        #[arg(required = true, num_args = 1..)]
        tiles: Vec<u32>,
        #[command(flatten)]
        common: ClientArgs,
    },

    /// Delete an ended job (done, failed or cancelled) and its image from the coordinator.
    #[command(
        long_about = "Delete an ended job (done, failed or cancelled) from the coordinator: \
            its image, scene and records are removed from its disk and `tessera status` \
            no longer knows it. A queued or running job must be cancelled first. Its id \
            is never given to another job.",
        after_help = "Example:\n  tessera delete 7"
    )]
    Delete {
        /// The job's id (as `tessera submit` and `tessera list` show it).
        #[arg(value_parser = parse_job_id)]
        job: JobId,
        #[command(flatten)]
        common: ClientArgs,
    },

    /// Download a finished job's image.
    Fetch {
        /// The job's id (as `tessera submit` and `tessera list` show it).
        #[arg(value_parser = parse_job_id)]
        job: JobId,
        /// Where to write the PNG [default: job-JOB.png]; for a sequence, the directory
        /// its done frames go into, as frame_0001.png, ... [default: job-JOB/].
        #[arg(short, long, value_name = "OUT.png|DIR")]
        output: Option<PathBuf>,
        #[command(flatten)]
        common: ClientArgs,
    },

    /// List the workers connected to the coordinator, with their throughput; or drain,
    /// disable or enable one.
    #[command(
        args_conflicts_with_subcommands = true,
        after_help = "Examples:\n  \
            tessera workers                      lists them (id, name, state)\n  \
            tessera workers drain render-07      finishes its tiles, then it exits\n  \
            tessera workers disable render-07    no new tiles, even after a restart\n  \
            tessera workers enable render-07"
    )]
    Workers {
        #[command(subcommand)]
        action: Option<WorkerAction>,
        #[command(flatten)]
        common: ClientArgs,
    },

    /// Drive the scheduler with thousands of simulated workers in virtual time.
    #[command(
        long_about = "Run the coordinator's real scheduler against simulated workers of \
            mixed speeds that crash, hang and join, in virtual time, and report scheduling \
            throughput, memory and makespan against the ideal (see docs/simulation.md). \
            A seed names a run: the same options give the same report.",
        after_help = "Examples:\n  \
            tessera simulate --workers 2000 --jobs 10\n  \
            tessera simulate --table"
    )]
    Simulate(SimulateArgs),
}

#[derive(Args)]
struct SimulateArgs {
    /// Simulated machines at the start.
    #[arg(long, default_value_t = 1000)]
    workers: usize,
    /// Jobs submitted at the start.
    #[arg(long, default_value_t = 20)]
    jobs: usize,
    /// Seed of the run.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Without crashes, hangs and new machines.
    #[arg(long)]
    no_failures: bool,
    /// Without copies of straggling tiles for idle workers.
    #[arg(long)]
    no_speculation: bool,
    /// Frame width of each job.
    #[arg(long, default_value_t = 3840)]
    width: u32,
    /// Frame height of each job.
    #[arg(long, default_value_t = 2160)]
    height: u32,
    /// Tile side in pixels.
    #[arg(long, default_value_t = 32)]
    tile: u32,
    /// Every run of docs/simulation.md's scaling table instead of one run (minutes).
    #[arg(long)]
    table: bool,
}

/// Image settings that override the scene's own.
#[derive(Args, Clone, Copy)]
struct ImageArgs {
    /// Image width in pixels [default: the scene's, else 600].
    #[arg(long, value_name = "W", value_parser = clap::value_parser!(u32).range(1..=i64::from(MAX_SIDE)))]
    width: Option<u32>,

    /// Image height in pixels [default: the scene's, else 400].
    #[arg(long, value_name = "H", value_parser = clap::value_parser!(u32).range(1..=i64::from(MAX_SIDE)))]
    height: Option<u32>,

    /// Antialiasing: N gives N x N samples per pixel [default: the scene's, else 1].
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u32).range(1..=i64::from(MAX_AA)))]
    aa: Option<u32>,

    /// Maximum reflection depth [default: the scene's, else 10].
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u32).range(0..=i64::from(MAX_DEPTH)))]
    max_depth: Option<u32>,

    /// Where the samples of a pixel go: grid (the regular N x N grid, the reference),
    /// jittered (one random point in each of the N x N cells) or adaptive (4 samples, then
    /// more only where they disagree, up to N x N) [default: grid].
    #[arg(long, value_name = "SAMPLER", value_enum)]
    sampler: Option<SamplerArg>,

    /// With --sampler adaptive: the error each pixel should reach, in 8-bit levels (for
    /// example 1); a pixel stops taking samples once its estimated error is below it.
    #[arg(long, value_name = "LEVELS", allow_negative_numbers = true)]
    target_error: Option<f64>,
}

/// The samplers as the command line names them.
#[derive(Clone, Copy, PartialEq, Eq, ValueEnum)]
enum SamplerArg {
    Grid,
    Jittered,
    Adaptive,
}

#[derive(Args)]
struct RenderArgs {
    /// The scene file (JSON).
    scene: PathBuf,
    /// Where to write the PNG [default: the scene's file name with .png, here].
    #[arg(short, long, value_name = "OUT.png")]
    output: Option<PathBuf>,
    #[command(flatten)]
    image: ImageArgs,
    /// Rendering threads [default: one per core].
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u32).range(1..=1024))]
    threads: Option<u32>,
    /// Adaptive sampling for about this long (500ms, 30s, 2m): the best image
    /// reachable, and the error it reached. Implies --sampler adaptive; with
    /// --target-error it stops at whichever comes first.
    #[arg(long, value_name = "TIME", value_parser = config::parse_duration)]
    time_limit: Option<Duration>,
    /// Save every sample taken (adaptive sampling) to FILE, so that `tessera refine
    /// FILE` can go on to a lower error or a larger --aa without taking them again.
    #[arg(long, value_name = "FILE")]
    state: Option<PathBuf>,
    /// Render frame K of an animated scene (frames are numbered from 1; a scene
    /// without animation has frame 1 only) [default: 1].
    #[arg(long, value_name = "K", value_parser = clap::value_parser!(u64).range(1..), conflicts_with = "frames")]
    frame: Option<u64>,
    /// Render frames A to B of an animated scene (A-B, K or all; alone: all) into the
    /// directory given by -o, as frame_0001.png, ... [default directory: the scene's
    /// file name without .json, here].
    #[arg(long, value_name = "A-B", num_args = 0..=1, default_missing_value = "all",
          value_parser = render_command::parse_frame_range)]
    frames: Option<render_command::FrameRange>,
}

#[derive(Args)]
struct RefineArgs {
    /// A render state saved by `tessera render --state FILE`, or the id of a finished
    /// adaptive job on a coordinator (a new job goes on from its stored samples).
    state: PathBuf,
    /// The new error target, in 8-bit levels [default: the saved one].
    #[arg(long, value_name = "LEVELS", allow_negative_numbers = true)]
    target_error: Option<f64>,
    /// A new cap: at most the largest power of two not above N x N samples per pixel
    /// [default: the saved one].
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u32).range(1..=i64::from(MAX_AA)))]
    aa: Option<u32>,
    /// Refine for about this long, at most.
    #[arg(long, value_name = "TIME", value_parser = config::parse_duration)]
    time_limit: Option<Duration>,
    /// Where to write the PNG [default: the state's file name with .png].
    #[arg(short, long, value_name = "OUT.png")]
    output: Option<PathBuf>,
    /// Rendering threads [default: one per core].
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u32).range(1..=1024))]
    threads: Option<u32>,
    /// For a job id: wait for the new job, showing progress, and write its image.
    #[arg(long)]
    wait: bool,
    #[command(flatten)]
    common: ClientArgs,
}

#[derive(Args)]
struct UpArgs {
    /// The scene file (JSON).
    scene: PathBuf,
    /// Worker processes to start.
    #[arg(long, value_name = "N", default_value_t = 2, value_parser = clap::value_parser!(u32).range(1..=64))]
    workers: u32,
    /// Rendering threads of each worker [default: cores / workers, at least 1].
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u32).range(1..=1024))]
    threads_per_worker: Option<u32>,
    /// Where to write the PNG [default: the scene's file name with .png, here]; with
    /// --frames, the directory of the frames [default: the scene's file name].
    #[arg(short, long, value_name = "OUT.png|DIR")]
    output: Option<PathBuf>,
    /// Render frames A to B of an animated scene (A-B, K or all) as one sequence job,
    /// written into the directory -o as they are done.
    #[arg(long, value_name = "RANGE", value_parser = render_command::parse_frame_range)]
    frames: Option<render_command::FrameRange>,
    #[command(flatten)]
    image: ImageArgs,
    /// Adaptive sampling for about this long (500ms, 30s, 2m): the job stops at the
    /// end of the pass that reaches it. Implies --sampler adaptive.
    #[arg(long, value_name = "TIME", value_parser = config::parse_duration)]
    time_limit: Option<Duration>,
    /// Tile side in pixels [default: chosen from the image size and aa].
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u32).range(8..=512))]
    tile: Option<u32>,
}

/// The threads of each local worker: as asked, or the cores shared among them.
fn threads_per_worker(workers: usize, asked: Option<u32>) -> usize {
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    asked.map_or((cores / workers).max(1), |n| n as usize)
}

#[derive(Args)]
struct StudioArgs {
    /// The scene to open [default: the seed scene at 960 x 540, aa 2].
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

/// What both daemons take: where their settings come from, HTTP and logs.
#[derive(Args)]
struct DaemonArgs {
    /// A TOML file of settings: a [coordinator] and a [worker] table whose keys are the
    /// flags' names. Flags beat environment variables, which beat the file.
    #[arg(long, value_name = "FILE", env = "TESSERA_CONFIG")]
    config: Option<PathBuf>,
    /// Print the effective settings, and where each comes from, then exit.
    #[arg(long)]
    print_config: bool,
    /// Serve HTTP on this address: /healthz and /readyz, and on a coordinator also
    /// /metrics (Prometheus) and the status page at /.
    #[arg(long, value_name = "ADDR", env = "TESSERA_HTTP")]
    http: Option<SocketAddr>,
    /// How logs on stderr look: text (coloured on a terminal) or json (one object a line).
    #[arg(
        long,
        value_name = "FORMAT",
        value_enum,
        default_value = "text",
        env = "TESSERA_LOG_FORMAT"
    )]
    log_format: LogFormat,
}

#[derive(Clone, Copy, PartialEq, Eq, ValueEnum)]
enum LogFormat {
    Text,
    Json,
}

#[derive(Args)]
struct CoordinatorArgs {
    #[command(flatten)]
    daemon: DaemonArgs,
    /// Address to listen on.
    #[arg(long, env = "TESSERA_LISTEN", value_name = "ADDR", default_value = DEFAULT_COORDINATOR)]
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
    /// Milliseconds a peer has to complete its handshake.
    #[arg(long, env = "TESSERA_HANDSHAKE_TIMEOUT_MS", value_name = "MS", default_value_t = coordinator::server::DEFAULT_HANDSHAKE_TIMEOUT.as_millis() as u64,
          value_parser = clap::value_parser!(u64).range(100..=600_000))]
    handshake_timeout_ms: u64,
    /// Delete a finished job (done, failed or cancelled) this long after it ended: a
    /// whole number and a unit, s, m, h or d (90s, 30m, 12h, 7d) [default: keep jobs
    /// until `tessera delete`].
    #[arg(long, env = "TESSERA_RETENTION", value_name = "DURATION", value_parser = config::parse_duration)]
    retention: Option<Duration>,
    /// If the job database is missing or unreadable although the data directory has
    /// held jobs, start a new empty one instead of refusing to start (unfinished jobs
    /// are lost; new ids continue after the highest ever issued). For this start only:
    /// no environment variable or config file key.
    #[arg(long)]
    reset_database: bool,
    /// The scene the studio page (`/studio`) opens with [default: the seed scene at
    /// 960 x 540, aa 2]. Checked at start like any scene.
    #[arg(long, env = "TESSERA_STUDIO_SCENE", value_name = "FILE")]
    studio_scene: Option<PathBuf>,
    /// Exit when standard input closes (used by `tessera up` for its children).
    #[arg(long, hide = true)]
    exit_on_stdin_eof: bool,
}

#[derive(Args)]
struct WorkerArgs {
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
    /// Take FACTOR times as long per tile, to stand for a slower machine (tests).
    #[arg(long, hide = true, value_name = "FACTOR")]
    throttle: Option<f64>,
    /// Exit when standard input closes (used by `tessera up` for its children).
    #[arg(long, hide = true)]
    exit_on_stdin_eof: bool,
}

#[derive(Args)]
struct SubmitArgs {
    /// The scene file (JSON).
    scene: PathBuf,
    /// Render frame K of an animated scene only (frames are numbered from 1; a scene
    /// without animation has frame 1 only): the image is `tessera render --frame K`'s.
    #[arg(long, value_name = "K", value_parser = clap::value_parser!(u32).range(1..),
          conflicts_with = "frames")]
    frame: Option<u32>,
    /// Render frames A to B of an animated scene as one sequence job (A-B, K or all)
    /// [default: every frame of an animated scene]. With --wait, the frames are
    /// written into the directory -o as they are done, as `tessera render --frames`
    /// writes them.
    #[arg(long, value_name = "RANGE", value_parser = render_command::parse_frame_range)]
    frames: Option<render_command::FrameRange>,
    #[command(flatten)]
    image: ImageArgs,
    /// Adaptive sampling for about this long (500ms, 30s, 2m) of the farm's rendering:
    /// the job stops at the end of the pass that reaches it, with the error it reached.
    /// Implies --sampler adaptive; with --target-error, whichever comes first.
    #[arg(long, value_name = "TIME", value_parser = config::parse_duration)]
    time_limit: Option<Duration>,
    /// Tile side in pixels [default: chosen from the image size and aa].
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u32).range(8..=512))]
    tile: Option<u32>,
    /// Priority: higher runs first; equal priorities share the farm.
    #[arg(long, default_value_t = 0, allow_negative_numbers = true)]
    priority: i32,
    /// How results are checked: `sampled` (spot checks and a random share of tiles
    /// rendered twice) or `full` (every tile rendered by two different machines, which
    /// must agree byte for byte; needs two workers).
    #[arg(long, value_enum, default_value_t = VerifyArg::Sampled, value_name = "MODE")]
    verify: VerifyArg,
    /// Wait for the job, showing progress, and write its image.
    #[arg(long)]
    wait: bool,
    /// With --wait: where to write the PNG [default: the scene's file name with .png],
    /// or for a sequence the directory of its frames [default: the scene's file name].
    #[arg(short, long, value_name = "OUT.png|DIR", requires = "wait")]
    output: Option<PathBuf>,
    /// What listings call the job [default: the scene file's name without .json].
    #[arg(long, value_name = "NAME")]
    name: Option<String>,
    /// Who submitted the job, shown in listings [default: $USER@hostname]. The
    /// client's claim, not checked: the coordinator records the address the
    /// submission came from beside it.
    #[arg(long, value_name = "WHO")]
    submitter: Option<String>,
    #[command(flatten)]
    common: ClientArgs,
}

/// `--verify`.
#[derive(Clone, Copy, Debug, clap::ValueEnum)]
enum VerifyArg {
    Sampled,
    Full,
}

impl From<VerifyArg> for protocol::Verification {
    fn from(v: VerifyArg) -> Self {
        match v {
            VerifyArg::Sampled => protocol::Verification::Sampled,
            VerifyArg::Full => protocol::Verification::Full,
        }
    }
}

/// `tessera workers drain|disable|enable WORKER`.
#[derive(Subcommand)]
enum WorkerAction {
    /// The worker finishes the tiles it holds, then exits (status 0) without
    /// reconnecting, as on SIGTERM on its machine.
    Drain {
        /// A worker's id or name, as `tessera workers` shows them (a name drains every
        /// worker connected under it).
        worker: String,
        #[command(flatten)]
        common: ClientArgs,
    },
    /// The worker's machine gets no new tiles (those it holds finish); it stays
    /// connected. Kept by machine name and stored: it holds across reconnects and
    /// coordinator restarts until `tessera workers enable`.
    Disable {
        /// A worker's id or name, as `tessera workers` shows them.
        worker: String,
        #[command(flatten)]
        common: ClientArgs,
    },
    /// The disabled machine takes tiles again.
    Enable {
        /// A connected worker's id or name, or the name of a disabled machine.
        worker: String,
        #[command(flatten)]
        common: ClientArgs,
    },
}

/// What every client command takes.
#[derive(Args)]
struct ClientArgs {
    #[command(flatten)]
    peer: PeerArgs,
    /// Machine-readable JSON output.
    #[arg(long)]
    json: bool,
}

/// How clients and workers reach a coordinator.
#[derive(Args)]
struct PeerArgs {
    /// The coordinator's address, HOST:PORT (the port it listens on for workers and
    /// clients, not its HTTP port).
    #[arg(long, env = "TESSERA_COORDINATOR", value_name = "ADDR", default_value = DEFAULT_COORDINATOR,
          value_parser = parse_coordinator_address)]
    coordinator: String,
    #[command(flatten)]
    secret: SecretArgs,
    /// Speak TLS, trusting the certificates in this PEM file (the coordinator's own
    /// certificate or the CA that signed it).
    #[arg(long, env = "TESSERA_TLS_CA", value_name = "FILE")]
    tls_ca: Option<PathBuf>,
    /// Speak TLS, trusting exactly the coordinator certificate with this SHA-256
    /// fingerprint (64 hex digits, as the coordinator prints at startup; an empty
    /// value counts as none, for container environments).
    #[arg(
        long,
        env = "TESSERA_TLS_FINGERPRINT",
        value_name = "SHA256HEX",
        conflicts_with = "tls_ca",
        value_parser = parse_pin
    )]
    tls_fingerprint: Option<Pin>,
    /// The name the coordinator's certificate must carry [default: the host of
    /// --coordinator].
    #[arg(
        long,
        env = "TESSERA_TLS_SERVER_NAME",
        value_name = "NAME",
        requires = "tls_ca"
    )]
    tls_server_name: Option<String>,
}

impl PeerArgs {
    fn endpoint(&self) -> Result<Endpoint> {
        let tls = match (&self.tls_ca, self.tls_fingerprint) {
            (Some(ca), _) => Some(ClientTls::from_ca_file(
                ca,
                self.tls_server_name.as_deref(),
            )?),
            (None, Some(Pin(Some(pin)))) => Some(ClientTls::pinned(pin)?),
            (None, _) => None,
        };
        Ok(Endpoint {
            address: self.coordinator.clone(),
            tls,
            secret: self.secret.load()?,
        })
    }
}

/// A job id as the commands that take one read it.
fn parse_job_id(text: &str) -> Result<JobId, String> {
    text.trim().parse().map_err(|_| {
        "a job id is a whole number, as `tessera submit` and `tessera list` print it".to_owned()
    })
}

/// `--coordinator`: a host and a port, which a bare host or address lacks.
fn parse_coordinator_address(text: &str) -> Result<String, String> {
    let text = text.trim();
    let port = DEFAULT_COORDINATOR
        .rsplit_once(':')
        .map_or("7878", |(_, port)| port);
    let (host, given) = if let Some(rest) = text.strip_prefix('[') {
        match rest.split_once(']') {
            Some((host, tail)) => (format!("[{host}]"), tail.strip_prefix(':')),
            None => return Err("an IPv6 address needs its closing `]`".to_owned()),
        }
    } else {
        match text.matches(':').count() {
            0 => (text.to_owned(), None),
            1 => {
                let (host, port) = text.split_once(':').expect("one colon");
                (host.to_owned(), Some(port))
            }
            _ => {
                return Err(format!(
                    "an IPv6 address goes in brackets with its port: [{text}]:{port}"
                ))
            }
        }
    };
    if host.is_empty() {
        return Err(format!(
            "no host: give HOST:PORT, for example 127.0.0.1:{port}"
        ));
    }
    match given {
        None => Err(format!(
            "no port: give HOST:PORT, for example {host}:{port} ({port} is the coordinator's \
             default port)"
        )),
        Some(p) if p.parse::<u16>().is_ok_and(|p| p > 0) => Ok(text.to_owned()),
        Some(p) => Err(format!(
            "{p:?} is not a port number: give HOST:PORT, for example {host}:{port}"
        )),
    }
}

/// A `--tls-fingerprint`: none when given empty.
#[derive(Clone, Copy)]
struct Pin(Option<[u8; 32]>);

fn parse_pin(text: &str) -> Result<Pin, String> {
    if text.trim().is_empty() {
        return Ok(Pin(None));
    }
    transport::parse_fingerprint(text).map(|pin| Pin(Some(pin)))
}

/// The secret of a worker or a client: the worker token or the client token of its
/// farm, whichever its role needs.
#[derive(Args)]
struct SecretArgs {
    /// File holding this peer's token: the farm's worker token for a worker, its client
    /// token for a client [or set TESSERA_TOKEN to the token itself].
    #[arg(long, env = "TESSERA_TOKEN_FILE", value_name = "FILE")]
    token_file: Option<PathBuf>,
}

impl SecretArgs {
    /// The secret from --token-file, else from TESSERA_TOKEN, else none.
    fn load(&self) -> Result<Option<Vec<u8>>> {
        load_secret(self.token_file.as_deref(), "TESSERA_TOKEN")
    }
}

/// The coordinator's two secrets: one that workers prove, one that clients prove.
#[derive(Args)]
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
    /// both roles or ignored, and so are two equal secrets.
    fn load(&self) -> Result<RoleSecrets> {
        if self.token_file.is_some() {
            bail!("--token-file: {ONE_TOKEN_RETIRED}");
        }
        for variable in ["TESSERA_TOKEN_FILE", "TESSERA_TOKEN"] {
            if std::env::var_os(variable).is_some() {
                bail!("{variable} is set (unset it for the coordinator): {ONE_TOKEN_RETIRED}");
            }
        }
        let worker = load_secret(self.worker_token_file.as_deref(), "TESSERA_WORKER_TOKEN")?;
        let client = load_secret(self.client_token_file.as_deref(), "TESSERA_CLIENT_TOKEN")?;
        if worker.is_some() && worker == client {
            bail!(
                "the worker token and the client token are the same secret, so any client could \
                 join as a worker: give two different secrets (e.g. each from `openssl rand \
                 -hex 32`)"
            );
        }
        Ok((worker, client))
    }
}

/// A token from `file`, else from the environment variable `variable` holding the token
/// itself, else none: whitespace trimmed at both ends, used as bytes.
fn load_secret(file: Option<&std::path::Path>, variable: &str) -> Result<Option<Vec<u8>>> {
    let (secret, source) = match file {
        Some(path) => (
            std::fs::read_to_string(path).map_err(|e| {
                anyhow::anyhow!("cannot read the token file {}: {e}", path.display())
            })?,
            format!("the token file {}", path.display()),
        ),
        None => match std::env::var(variable) {
            Ok(token) => (token, variable.to_string()),
            Err(_) => return Ok(None),
        },
    };
    let secret = secret.trim();
    anyhow::ensure!(!secret.is_empty(), "the token is empty ({source})");
    Ok(Some(secret.as_bytes().to_vec()))
}

impl ClientArgs {
    fn target(&self) -> Result<Endpoint> {
        self.peer.endpoint()
    }
}

impl ImageArgs {
    /// The sampling asked for (`None`: the default grid), checked: adaptive sampling needs
    /// a target and the other samplers take none.
    fn sampling(self) -> Result<Option<Sampling>> {
        match (self.sampler, self.target_error) {
            (Some(SamplerArg::Adaptive), Some(levels)) => Sampling::adaptive(levels)
                .map(Some)
                .map_err(|e| anyhow!("--target-error: {e}")),
            (Some(SamplerArg::Adaptive), None) => bail!(
                "--sampler adaptive needs --target-error LEVELS (the error each pixel should \
                 reach, in 8-bit levels, for example 1)"
            ),
            (_, Some(_)) => bail!("--target-error applies only to --sampler adaptive"),
            (Some(SamplerArg::Grid), None) => Ok(Some(Sampling::Grid)),
            (Some(SamplerArg::Jittered), None) => Ok(Some(Sampling::Jittered)),
            (None, None) => Ok(None),
        }
    }

    /// The sampling with a time limit: a limit alone asks for adaptive sampling to the
    /// smallest target there is (the time decides), as `tessera render` does.
    fn sampling_within(self, time_limit: Option<Duration>) -> Result<Option<Sampling>> {
        Ok(match (time_limit, self.sampler, self.target_error) {
            (Some(_), None | Some(SamplerArg::Adaptive), None) => Some(Sampling::adaptive(
                f64::from(render::MIN_TARGET_MILLI) / 1000.0,
            )?),
            (Some(_), None, Some(_)) => ImageArgs {
                sampler: Some(SamplerArg::Adaptive),
                ..self
            }
            .sampling()?,
            (Some(_), Some(_), _) => bail!("--time-limit applies only to --sampler adaptive"),
            (None, ..) => self.sampling()?,
        })
    }

    /// The overrides of a farm job with an optional time limit, and the limit in ms.
    fn farm_job(
        self,
        tile_size: Option<u32>,
        time_limit: Option<Duration>,
    ) -> Result<(Overrides, Option<u64>)> {
        let sampling = self.sampling_within(time_limit)?;
        let overrides = Overrides {
            sampling: sampling.map(protocol_sampling),
            ..ImageArgs {
                sampler: None,
                target_error: None,
                ..self
            }
            .overrides(tile_size)?
        };
        let ms = time_limit.map(|t| (t.as_millis() as u64).max(1));
        Ok((overrides, ms))
    }

    fn overrides(self, tile_size: Option<u32>) -> Result<Overrides> {
        Ok(Overrides {
            width: self.width,
            height: self.height,
            aa: self.aa,
            max_depth: self.max_depth,
            tile_size,
            sampling: self.sampling()?.map(|s| match s {
                Sampling::Grid => protocol::Sampling::Grid,
                Sampling::Jittered => protocol::Sampling::Jittered,
                Sampling::Adaptive { target_milli } => {
                    protocol::Sampling::Adaptive { target_milli }
                }
            }),
        })
    }
}

fn protocol_sampling(s: Sampling) -> protocol::Sampling {
    match s {
        Sampling::Grid => protocol::Sampling::Grid,
        Sampling::Jittered => protocol::Sampling::Jittered,
        Sampling::Adaptive { target_milli } => protocol::Sampling::Adaptive { target_milli },
    }
}

/// What `tessera refine X` refines: the job X on a coordinator if X is all digits and
/// names no file, else a saved render state (whose reading reports a missing file).
fn refines_a_job(state: &std::path::Path) -> Result<Option<protocol::JobId>> {
    let text = state.to_string_lossy();
    if state.exists() || text.is_empty() || !text.bytes().all(|b| b.is_ascii_digit()) {
        return Ok(None);
    }
    let job = text
        .parse()
        .map_err(|_| anyhow!("refine: job id {text} is too large"))?;
    Ok(Some(job))
}

fn main() -> ExitCode {
    let cli = Cli::command();
    let args: Vec<std::ffi::OsString> = std::env::args_os().collect();
    let json = wants_json(&args);
    let expanded = match config::expand(args, &cli) {
        Ok(expanded) => expanded,
        Err(e) => {
            report_error(json, &format!("{e:#}"));
            return ExitCode::FAILURE;
        }
    };
    let matches = match cli.clone().try_get_matches_from(expanded.args) {
        Ok(matches) => matches,
        // A bad value is one line that names the option and says what is wrong.
        Err(e)
            if e.kind() == clap::error::ErrorKind::ValueValidation || (json && e.use_stderr()) =>
        {
            let text = e.render().to_string();
            let line = text.lines().next().unwrap_or_default();
            report_error(json, line.strip_prefix("error: ").unwrap_or(line));
            return ExitCode::from(2);
        }
        Err(e) => e.exit(),
    };
    let parsed = Cli::from_arg_matches(&matches).unwrap_or_else(|e| e.exit());
    if let Some((name, sub)) = matches.subcommand() {
        if config::SECTIONS.contains(&name) && sub.get_flag("print_config") {
            let command = cli.find_subcommand(name).expect("parsed subcommands exist");
            print!(
                "{}",
                config::describe(name, command, sub, &expanded.from_file)
            );
            return ExitCode::SUCCESS;
        }
    }
    match run(parsed.command) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            report_error(json, &format!("{e:#}"));
            match e.downcast_ref::<up_command::Interrupted>() {
                Some(signal) => ExitCode::from(signal.exit_code),
                None => ExitCode::FAILURE,
            }
        }
    }
}

/// Whether the command line asks for JSON (`--json`, before any `--`).
fn wants_json(args: &[std::ffi::OsString]) -> bool {
    args.iter()
        .skip(1)
        .take_while(|a| *a != "--")
        .any(|a| a == "--json")
}

/// A command's error: one line `error: MESSAGE` on stderr, or with `--json`, the object
/// `{"error": "MESSAGE"}` on stdout, where the command's result would have been.
fn report_error(json: bool, message: &str) {
    if json {
        println!("{}", serde_json::json!({ "error": message }));
    } else {
        eprintln!("error: {message}");
    }
}

fn run(command: Command) -> Result<()> {
    if let Command::Simulate(a) = command {
        return simulate_command::run(&simulate_command::Options {
            workers: a.workers,
            jobs: a.jobs,
            seed: a.seed,
            failures: !a.no_failures,
            speculate: !a.no_speculation,
            width: a.width,
            height: a.height,
            tile: a.tile,
            table: a.table,
        });
    }
    if let Command::Render(a) = command {
        let sampling = match (a.time_limit, a.image.sampler, a.image.target_error) {
            // A time limit alone: as far as the time allows.
            (Some(_), None | Some(SamplerArg::Adaptive), None) => Some(Sampling::adaptive(
                f64::from(render::MIN_TARGET_MILLI) / 1000.0,
            )?),
            (Some(_), None, Some(_)) => ImageArgs {
                sampler: Some(SamplerArg::Adaptive),
                ..a.image
            }
            .sampling()?,
            (Some(_), Some(_), _) => bail!("--time-limit applies only to --sampler adaptive"),
            (None, ..) => a.image.sampling()?,
        };
        return render_command::run(render_command::Options {
            scene: a.scene,
            output: a.output,
            width: a.image.width,
            height: a.image.height,
            aa: a.image.aa,
            max_depth: a.image.max_depth,
            sampling,
            threads: a.threads,
            time_limit: a.time_limit,
            state: a.state,
            frame: a.frame,
            frames: a.frames,
        });
    }
    let command = match command {
        Command::Refine(a) if refines_a_job(&a.state)?.is_none() => {
            return render_command::refine(render_command::RefineOptions {
                state: a.state,
                output: a.output,
                aa: a.aa,
                target_error: a.target_error,
                time_limit: a.time_limit,
                threads: a.threads,
            });
        }
        other => other,
    };
    match &command {
        Command::Coordinator(a) => init_logging(a.daemon.log_format),
        Command::Worker(a) => init_logging(a.daemon.log_format),
        _ => {}
    }
    let runtime = tokio::runtime::Runtime::new()?;
    runtime.block_on(async move {
        match command {
            Command::Render(_) | Command::Simulate(_) => {
                unreachable!("handled above")
            }
            Command::Refine(a) => {
                let job = refines_a_job(&a.state)?.expect("a state file was refined above");
                let target_milli = match a.target_error.map(Sampling::adaptive).transpose()? {
                    Some(Sampling::Adaptive { target_milli }) => Some(target_milli),
                    _ => None,
                };
                client_commands::run_refine(
                    &a.common.target()?,
                    job,
                    client_commands::Refinement {
                        target_milli,
                        aa: a.aa,
                        time_limit_ms: a.time_limit.map(|t| (t.as_millis() as u64).max(1)),
                    },
                    a.wait,
                    a.output,
                    a.common.json,
                )
                .await
            }
            Command::Up(a) => {
                let workers = a.workers as usize;
                up_command::run(up_command::Options {
                    scene: a.scene,
                    workers,
                    threads_per_worker: threads_per_worker(workers, a.threads_per_worker),
                    output: a.output,
                    frames: a.frames,
                    job: a.image.farm_job(a.tile, a.time_limit)?,
                })
                .await
            }
            Command::Studio(a) => {
                let workers = a.workers as usize;
                studio_command::run(studio_command::Options {
                    scene: a.scene,
                    workers,
                    threads_per_worker: threads_per_worker(workers, a.threads_per_worker),
                    http: a.http,
                })
                .await
            }
            Command::Coordinator(a) => {
                let tls = match (&a.tls_cert, &a.tls_key) {
                    (Some(cert), Some(key)) => Some(ServerTls::from_pem_files(cert, key)?),
                    _ if a.tls_auto => {
                        Some(ServerTls::auto(&a.data.join(transport::AUTO_TLS_DIR))?)
                    }
                    _ => None,
                };
                if a.print_fingerprint {
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
                if !a.listen.ip().is_loopback()
                    && (worker_secret.is_none() || client_secret.is_none())
                    && !a.insecure
                {
                    let missing = match (&worker_secret, &client_secret) {
                        (None, None) => "a token for workers and one for clients",
                        (None, Some(_)) => "a token for workers",
                        _ => "a token for clients",
                    };
                    anyhow::bail!(
                        "refusing to listen on {} without {missing}: anyone who can reach it \
                         could submit jobs or pose as a worker. Give --worker-token-file FILE \
                         and --client-token-file FILE (or pass --insecure to accept peers \
                         without proof)",
                        a.listen
                    );
                }
                let config = coordinator::Config {
                    listen: a.listen,
                    data: a.data,
                    max_frame: a.max_frame as usize,
                    max_connections: a.max_connections as usize,
                    handshake_timeout: Duration::from_millis(a.handshake_timeout_ms),
                    worker_secret,
                    client_secret,
                    tls,
                    policy: scheduler::Policy {
                        heartbeat_timeout: a.heartbeat_timeout_ms,
                        ..Default::default()
                    },
                    verify: coordinator::VerifyConfig {
                        spot_pixels: a.spot_pixels,
                        audit_share: a.audit_share,
                    },
                    limits: coordinator::server::JobLimits {
                        max_scene_bytes: a.max_scene_bytes as usize,
                        max_objects: a.max_objects as usize,
                        max_pixels: a.max_pixels,
                        max_aa: a.max_aa,
                        max_active_per_client: a.max_jobs_per_client as usize,
                    },
                    http: a.daemon.http,
                    retention: a.retention,
                    reset_database: a.reset_database,
                    studio_scene: a
                        .studio_scene
                        .as_deref()
                        .map(studio_command::read_checked_scene)
                        .transpose()?,
                };
                daemons::coordinator(config, a.exit_on_stdin_eof).await
            }
            Command::Worker(a) => {
                daemons::worker(
                    a.peer.endpoint()?,
                    a.threads.map(|n| n as usize),
                    a.name,
                    a.throttle,
                    a.daemon.http,
                    a.exit_on_stdin_eof,
                )
                .await
            }
            Command::Submit(a) => {
                let text = client_commands::read_scene(&a.scene)?;
                let frames = sequence_commands::choose_frames(&text, a.frame, a.frames)?;
                client_commands::run_submit(
                    &a.common.target()?,
                    &a.scene,
                    {
                        let (overrides, time_limit_ms) = a.image.farm_job(a.tile, a.time_limit)?;
                        client_commands::JobChoices {
                            overrides,
                            priority: a.priority,
                            verification: a.verify.into(),
                            time_limit_ms,
                            label: client_commands::Label {
                                name: a.name,
                                submitter: a.submitter,
                            },
                            frames,
                        }
                    },
                    a.wait,
                    a.output,
                    a.common.json,
                )
                .await
            }
            Command::Status { job, common } => {
                client_commands::run_status(&common.target()?, job, common.json).await
            }
            Command::List { common } => {
                client_commands::run_list(&common.target()?, common.json).await
            }
            Command::Cancel { job, common } => {
                client_commands::run_cancel(&common.target()?, job, common.json).await
            }
            Command::Pause { job, common } => {
                client_commands::run_pause(&common.target()?, job, true, common.json).await
            }
            Command::Resume { job, common } => {
                client_commands::run_pause(&common.target()?, job, false, common.json).await
            }
            Command::Priority {
                job,
                priority,
                common,
            } => client_commands::run_priority(&common.target()?, job, priority, common.json).await,
            Command::Events { job, common } => {
                client_commands::run_events(&common.target()?, job, common.json).await
            }
            Command::Retry { job, frame, common } => {
                client_commands::run_retry(&common.target()?, job, frame, common.json).await
            }
            Command::Requeue { job, tiles, common } => {
                client_commands::run_requeue(&common.target()?, job, tiles, common.json).await
            }
            Command::Delete { job, common } => {
                client_commands::run_delete(&common.target()?, job, common.json).await
            }
            Command::Fetch {
                job,
                output,
                common,
            } => client_commands::run_fetch(&common.target()?, job, output, common.json).await,
            Command::Workers {
                action: None,
                common,
            } => client_commands::run_workers(&common.target()?, common.json).await,
            Command::Workers {
                action: Some(action),
                ..
            } => {
                let (control, worker, common) = match action {
                    WorkerAction::Drain { worker, common } => {
                        (client_commands::WorkerControl::Drain, worker, common)
                    }
                    WorkerAction::Disable { worker, common } => {
                        (client_commands::WorkerControl::Disable, worker, common)
                    }
                    WorkerAction::Enable { worker, common } => {
                        (client_commands::WorkerControl::Enable, worker, common)
                    }
                };
                client_commands::run_worker_control(
                    &common.target()?,
                    control,
                    &worker,
                    common.json,
                )
                .await
            }
        }
    })
}

/// Logs of the daemons go to stderr, filtered by `RUST_LOG` (default `info`): readable
/// text, or one JSON object a line whose fields (`job`, `tile`, `worker`, ...) are
/// top-level keys, for log collectors.
fn init_logging(format: LogFormat) {
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info"));
    let logs = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr);
    match format {
        LogFormat::Text => logs
            .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
            .init(),
        LogFormat::Json => logs.json().flatten_event(true).init(),
    }
}
