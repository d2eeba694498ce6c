//! `tessera-bench`: the measurements behind docs/performance.md, as one reproducible
//! command. Each suite writes Markdown, CSV where it helps, and PNG charts.
//!
//! A program of its own, not a subcommand of `tessera`, so that the shipped binary
//! carries neither the benchmarks nor what only they use (the charts' plotting and
//! font, the codecs of the compression study). What it measures of the farm it
//! measures on the real thing: the `tessera` executable beside this one (built by the
//! same `cargo build --release`), or the one given with `--tessera`.

mod api;
mod compression;
mod error_table;
mod farm;
mod farm_meshes;
mod latency;
mod liveness;
mod measure;
mod plot;
mod relay;
mod renderer;
mod scaling;
mod scenes;
mod sequence;
mod verification;

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Duration;

use anyhow::{bail, Context, Result};
use clap::Parser;
use render::limits::MAX_AA;

/// Measure speed against error, and how time scales: tables (Markdown, CSV) and plots.
#[derive(Parser)]
#[command(
    name = "tessera-bench",
    version,
    long_about = "Measure the renderer and the farm on this machine and write the \
        results to a directory: speed against error for every sampling setting on four \
        scenes (bench.md, bench.csv, bench.png), and time against pixels and objects, \
        the farm's speed-up and the pull scheduler against a static split \
        (scaling.md, scaling.png). The renderer suite times whole `tessera render` \
        processes against external programs given by path (--anchor, --limit-bench, \
        --seed-cpp; a column without its program says \"not given\") and sweeps \
        pixels, objects, lights and mirror depth (renderer.md, renderer.csv, \
        renderer-scaling.md/.csv/.png), and with --anchor-mesh and --mesh-scenes the mesh \
        scenes (in renderer.md and renderer.csv) and parse and build time against \
        triangles (renderer-mesh-build.md/.csv/.png). The farm runs on the tessera executable beside \
        this one (--tessera to give another). The static split (scaling, and so all) \
        slows one worker through a cgroup, which needs root; the liveness suite freezes \
        a worker's render threads with ptrace (liveness.md, liveness.csv), which needs \
        root too. Build with --release.",
    after_help = "Examples (`cargo build --release` builds the tessera executable it runs):\n  \
        cargo build --release && cargo run --release -p tessera-bench -- --out bench-results\n  \
        cargo run --release -p tessera-bench -- --suite error --quick --out /tmp/check\n  \
        target/release/tessera-bench --suite renderer --anchor ./ew --limit-bench ./limit_bench \\\n      \
        --seed-cpp ./seed_structured --out docs/perf\n  \
        target/release/tessera-bench --suite renderer --only meshes --anchor-mesh ./ewm \\\n      \
        --mesh-scenes ../shared/mesh-scenes --out /tmp/meshes\n  \
        target/release/tessera-bench --suite farm-meshes --mesh-scenes ../shared/mesh-scenes \
        --out /tmp/farm-meshes"
)]
struct Args {
    /// Which measurements to make.
    #[arg(long, value_enum, default_value = "all")]
    suite: Suite,
    /// Directory for the tables and plots.
    #[arg(long, value_name = "DIR", default_value = "bench-results")]
    out: PathBuf,
    /// The tessera executable the farm and the renderer suite run (every suite but
    /// error) [default: the one beside tessera-bench].
    #[arg(long, value_name = "PATH")]
    tessera: Option<PathBuf>,
    /// Frame width of the error suite.
    #[arg(long, default_value_t = 600, value_parser = clap::value_parser!(u32).range(8..=4096))]
    width: u32,
    /// Frame height of the error suite.
    #[arg(long, default_value_t = 400, value_parser = clap::value_parser!(u32).range(8..=4096))]
    height: u32,
    /// Rendering threads for single-machine timings [default: one per core].
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=1024))]
    threads: Option<u32>,
    /// Grid antialiasing of the converged reference the error is measured against.
    #[arg(long, default_value_t = 32, value_parser = clap::value_parser!(u32).range(2..=i64::from(MAX_AA * 4)))]
    reference_aa: u32,
    /// Each timing repeats until this many milliseconds have passed...
    #[arg(long, default_value_t = 1000)]
    min_time_ms: u64,
    /// ...or this many runs.
    #[arg(long, default_value_t = 5, value_parser = clap::value_parser!(u32).range(1..))]
    max_runs: u32,
    /// Small frames and few settings: checks that everything works, in seconds; the
    /// figures mean nothing.
    #[arg(long)]
    quick: bool,
    /// The error suite also renders each scene with a grid of twice the reference's aa
    /// and reports how far the reference is from converged (slow at aa 64).
    #[arg(long)]
    reference_check: bool,
    /// Renderer suite: the Embree-based anchor tracer to run side by side with
    /// `tessera render` (same scenes, same image expected).
    #[arg(long, value_name = "PATH")]
    anchor: Option<PathBuf>,
    /// Renderer suite: the SIMD floor program; the seed frame's tracing time is
    /// reported as a multiple of its floor.
    #[arg(long, value_name = "PATH")]
    limit_bench: Option<PathBuf>,
    /// Renderer suite: the seed's structure in C++ (built from
    /// render/benches/seed_structured.cpp), timed on the seed frame.
    #[arg(long, value_name = "PATH")]
    seed_cpp: Option<PathBuf>,
    /// Renderer suite: runs of each program on each case [default: 7, 2 with --quick].
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=100))]
    reps: Option<u32>,
    /// Renderer suite: the Embree-based mesh anchor (built from
    /// embree_whitted_mesh.cpp), run with `--spheres user --robust` on the mesh scenes
    /// and on the generated meshes of the parse and build sweep.
    #[arg(long, value_name = "PATH")]
    anchor_mesh: Option<PathBuf>,
    /// Renderer and farm-meshes suites: the directory of the mesh scenes (bunny, armadillo, elephant,
    /// dragon, bunny64: a JSON scene each, beside their PLY files) [default:
    /// ../shared/mesh-scenes beside the source tree, if it is there].
    #[arg(long, value_name = "DIR")]
    mesh_scenes: Option<PathBuf>,
    /// Renderer suite: the largest generated mesh of the parse and build sweep, in
    /// triangles (the sweep goes 1,000, 10,000, ... up to it) [default: 10,000,000,
    /// 100,000 with --quick].
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u64).range(1_000..=20_000_000))]
    mesh_max_triangles: Option<u64>,
    /// Renderer suite: run only one half, spheres (the sphere cases and the scaling
    /// sweeps) or meshes (the mesh scenes and the parse and build sweep) [default:
    /// both].
    #[arg(long, value_enum, value_name = "PART")]
    only: Option<renderer::Part>,
}

fn main() -> ExitCode {
    let args = Args::parse();
    let result = options(args).and_then(|opts| {
        let runtime = tokio::runtime::Runtime::new()?;
        runtime.block_on(run(&opts))
    });
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

/// The options of a run, with the tessera executable found and, for every suite but
/// `error` (which renders in this process), checked: a missing one is said at once, not
/// after minutes of the suites that do not need it.
fn options(a: Args) -> Result<Options> {
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let tessera = match a.tessera {
        Some(path) => path,
        None => beside_this_executable()?,
    };
    if a.suite != Suite::Error && !tessera.is_file() {
        bail!(
            "no tessera executable at {}: build it with `cargo build --release` (or give \
             one with --tessera PATH)",
            tessera.display()
        );
    }
    Ok(Options {
        suite: a.suite,
        out: a.out,
        tessera,
        width: a.width,
        height: a.height,
        threads: a.threads.map_or(cores, |n| n as usize),
        reference_aa: a.reference_aa,
        min_time: Duration::from_millis(a.min_time_ms),
        max_runs: a.max_runs,
        quick: a.quick,
        reference_check: a.reference_check,
        external: External {
            anchor: a.anchor,
            limit_bench: a.limit_bench,
            seed_cpp: a.seed_cpp,
            anchor_mesh: a.anchor_mesh,
        },
        reps: a.reps.unwrap_or(if a.quick { 2 } else { 7 }),
        mesh_scenes: a.mesh_scenes.or_else(default_mesh_scenes),
        mesh_max_triangles: a
            .mesh_max_triangles
            .map_or(if a.quick { 100_000 } else { 10_000_000 }, |n| n as usize),
        renderer_only: a.only,
    })
}

/// `../shared/mesh-scenes` beside the source tree this was built from, where the
/// project keeps the mesh scenes it measures, if it is there.
fn default_mesh_scenes() -> Option<PathBuf> {
    let workspace = Path::new(env!("CARGO_MANIFEST_DIR")).parent()?;
    let dir = workspace.join("../shared/mesh-scenes");
    dir.is_dir().then(|| dir.canonicalize().unwrap_or(dir))
}

/// `tessera` in this executable's directory: where `cargo build` puts both.
fn beside_this_executable() -> Result<PathBuf> {
    let this = std::env::current_exe().context("cannot find the tessera-bench executable")?;
    let dir = this.parent().unwrap_or(Path::new("."));
    Ok(dir.join(format!("tessera{}", std::env::consts::EXE_SUFFIX)))
}

/// Which measurements to make.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Suite {
    /// Speed against error for every sampling setting on four scenes.
    Error,
    /// Time against pixels and objects, farm speed-up, pull against static split. The
    /// static split slows one worker to a third of a core through a cgroup: run as root.
    Scaling,
    /// The farm through 0 to 200 ms of round-trip time (workers behind a delaying
    /// relay), the bytes on the wire per job, and compressing tile results. About 12
    /// minutes, so not part of `all`.
    Latency,
    /// What verifying the workers' results costs: checks off, sampled and full
    /// verification on the 1920 × 1080 aa 2 seed job. About 2 minutes, so not part
    /// of `all`.
    Verification,
    /// The whole `tessera render` process against external programs given by path
    /// (an Embree-based anchor, the SIMD floor, the seed's structure in C++) on six
    /// sphere cases, and time against pixels, objects, lights and mirror depth with
    /// log-log slopes; then the five mesh scenes (--mesh-scenes) at 1 and 2 threads
    /// against the Embree mesh anchor (--anchor-mesh: times, speed-ups, peak memory,
    /// pixels that differ), and parse and build time of generated meshes of 1,000 to
    /// 10 million triangles, Tessera's and the anchor's, with log-log slopes. About 10
    /// minutes for the sphere half and 3 to 5 for the mesh half with the defaults
    /// (--only to run one), so not part of `all`.
    Renderer,
    /// Sequence jobs: a 120-frame orbit on a local farm of two one-thread workers
    /// against `tessera render --frames` with two threads (throughput, overhead per
    /// frame, byte-identical frames), and the coordinator's and workers' memory for a
    /// 10,000-frame sequence. About 5 to 10 minutes on a busy 2-core machine, so not
    /// part of `all`.
    Sequence,
    /// A worker whose render threads hang while its heartbeats go on: the 768-tile
    /// hall-of-mirrors job (2000 × 1500, aa 4) on two workers, then with `--verify
    /// full` on three, one worker's render threads frozen (ptrace, so as root) two
    /// seconds in; when it is found unresponsive, when its tiles are done elsewhere
    /// and when the job ends. About 2 minutes, so not part of `all`.
    Liveness,
    /// Scenes with mesh files on a local farm, the files' journey included: a 60-frame
    /// orbit of the bunny and a 1920 × 1080 aa 4 frame of a million-triangle mesh on
    /// two one-thread workers against `tessera render --threads 2`; the first tile of
    /// a job on a 100 MB mesh with four workers against one worker's parse and build,
    /// and a second job on it; the bytes on the wire per job for 1, 2 and 4 workers
    /// (from the coordinator's metrics). Needs the mesh scenes (--mesh-scenes). About
    /// 5 minutes, so not part of `all`.
    FarmMeshes,
    /// The HTTP API against the binary protocol on one coordinator: status and submit
    /// latency, then a job rendered while a hundred clients poll its status (the job's
    /// time and a binary status probe's latency, quiet against polled). About 2
    /// minutes, so not part of `all`.
    Api,
    /// Error and scaling (so as root, for the static split).
    All,
}

/// How to run the benchmarks.
pub struct Options {
    pub suite: Suite,
    pub out: PathBuf,
    /// The `tessera` executable: the farm's processes and the renderer suite's runs.
    pub tessera: PathBuf,
    pub width: u32,
    pub height: u32,
    pub threads: usize,
    pub reference_aa: u32,
    /// Each timing repeats until this much time has passed...
    pub min_time: Duration,
    /// ...or this many runs.
    pub max_runs: u32,
    /// Small images and few settings: a check that everything works, not a measurement.
    pub quick: bool,
    /// The error suite also renders a grid of twice `reference_aa` per scene and
    /// measures how far the reference is from it (slow: 4× the reference's samples).
    pub reference_check: bool,
    /// The renderer suite's external programs, each optional.
    pub external: renderer::External,
    /// Runs of each program on each case in the renderer suite.
    pub reps: u32,
    /// The renderer suite's mesh scenes, `None` when not given and not found.
    pub mesh_scenes: Option<PathBuf>,
    /// The largest generated mesh of the renderer suite's parse and build sweep.
    pub mesh_max_triangles: usize,
    /// The renderer suite's one half to run, `None` for both.
    pub renderer_only: Option<renderer::Part>,
}

pub use renderer::External;

/// Runs the chosen suites.
pub async fn run(opts: &Options) -> Result<()> {
    if matches!(opts.suite, Suite::Scaling | Suite::All) {
        // The static split comes last: lacking root is said before the minutes before it.
        localfarm::CpuLimit::probe()
            .context("the scaling suite slows one worker of its farm with a CPU limit")?;
    }
    std::fs::create_dir_all(&opts.out)
        .with_context(|| format!("cannot create {}", opts.out.display()))?;
    if matches!(opts.suite, Suite::Error | Suite::All) {
        error_table::run(opts, &opts.out)?;
    }
    if matches!(opts.suite, Suite::Scaling | Suite::All) {
        run_scaling(opts).await?;
    }
    if opts.suite == Suite::Verification {
        verification::run(opts, &opts.out).await?;
    }
    if opts.suite == Suite::Renderer {
        renderer::run(opts, &opts.out)?;
    }
    if opts.suite == Suite::Sequence {
        sequence::run(opts, &opts.out).await?;
    }
    if opts.suite == Suite::FarmMeshes {
        farm_meshes::run(opts, &opts.out).await?;
    }
    if opts.suite == Suite::Latency {
        latency::run(opts, &opts.out).await?;
    }
    if opts.suite == Suite::Api {
        api::run(opts, &opts.out).await?;
    }
    if opts.suite == Suite::Liveness {
        liveness::run(opts, &opts.out).await?;
    }
    eprintln!("results in {}", opts.out.display());
    Ok(())
}

/// Writes `scaling.md` and `scaling.png`.
async fn run_scaling(opts: &Options) -> Result<()> {
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let pixels = scaling::time_against_pixels(opts)?;
    let counts: &[usize] = if opts.quick {
        &[10, 100, 1000]
    } else {
        &[10, 30, 100, 300, 1000, 3000, 10_000]
    };
    let objects = scaling::time_against_objects(opts, counts)?;
    let max_workers = if opts.quick { 2 } else { (2 * cores).max(4) };
    let speedup = farm::speedup(opts, max_workers).await?;
    let split = farm::split(opts, 3.0).await?;
    let mut md = scaling::curves_markdown(&pixels, &objects);
    md.push('\n');
    md.push_str(&farm::speedup_markdown(&speedup, cores, opts));
    md.push('\n');
    md.push_str(&farm::split_markdown(&split));
    std::fs::write(opts.out.join("scaling.md"), md)?;
    let mut panels = scaling::curves_panels(&pixels, &objects);
    panels.push(farm::speedup_panel(&speedup));
    crate::plot::write_png(&opts.out.join("scaling.png"), &panels, 3, (560, 440))?;
    Ok(())
}
