//! `tessera bench`: its arguments, turned into the options of [`crate::bench`]. No
//! other command depends on this module or on the benchmarks.

use std::path::PathBuf;
use std::time::Duration;

use anyhow::Result;
use render::limits::MAX_AA;

use crate::bench;

/// Measure speed against error, and how time scales: tables (Markdown, CSV) and plots.
#[derive(clap::Args)]
#[command(
    long_about = "Measure the renderer and the farm on this machine and write the \
        results to a directory: speed against error for every sampling setting on four \
        scenes (bench.md, bench.csv, bench.png), and time against pixels and objects, \
        the farm's speed-up and the pull scheduler against a static split \
        (scaling.md, scaling.png). The renderer suite times whole `tessera render` \
        processes against external programs given by path (--anchor, --limit-bench, \
        --seed-cpp; a column without its program says \"not given\") and sweeps \
        pixels, objects, lights and mirror depth (renderer.md, renderer.csv, \
        renderer-scaling.md/.csv/.png). Build with --release.",
    after_help = "Examples:\n  \
        cargo run --release -- bench --out bench-results\n  \
        cargo run --release -- bench --suite error --quick --out /tmp/check\n  \
        tessera bench --suite renderer --anchor ./ew --limit-bench ./limit_bench \\\n      \
        --seed-cpp ./seed_structured --out docs/perf"
)]
pub struct Args {
    /// Which measurements to make.
    #[arg(long, value_enum, default_value = "all")]
    suite: bench::Suite,
    /// Directory for the tables and plots.
    #[arg(long, value_name = "DIR", default_value = "bench-results")]
    out: PathBuf,
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
}

pub fn run(args: Args) -> Result<()> {
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let options = bench::Options {
        suite: args.suite,
        out: args.out,
        width: args.width,
        height: args.height,
        threads: args.threads.map_or(cores, |n| n as usize),
        reference_aa: args.reference_aa,
        min_time: Duration::from_millis(args.min_time_ms),
        max_runs: args.max_runs,
        quick: args.quick,
        reference_check: args.reference_check,
        external: bench::External {
            anchor: args.anchor,
            limit_bench: args.limit_bench,
            seed_cpp: args.seed_cpp,
        },
        reps: args.reps.unwrap_or(if args.quick { 2 } else { 7 }),
    };
    super::block_on(bench::run(&options))
}
