//! `tessera bench`: the measurements behind docs/performance.md, as one reproducible
//! command. Each suite writes Markdown, CSV where it helps, and PNG charts.

mod compression;
mod error_table;
mod farm;
mod latency;
mod measure;
mod relay;
mod renderer;
mod scaling;
mod scenes;
mod sequence;
mod verification;

use std::path::PathBuf;
use std::time::Duration;

use anyhow::{Context, Result};

/// Which measurements to make.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Suite {
    /// Speed against error for every sampling setting on four scenes.
    Error,
    /// Time against pixels and objects, farm speed-up, pull against static split.
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
    /// cases, and time against pixels, objects, lights and mirror depth with log-log
    /// slopes. About 10 minutes with the defaults, so not part of `all`.
    Renderer,
    /// Sequence jobs: a 120-frame orbit on a local farm of two one-thread workers
    /// against `tessera render --frames` with two threads (throughput, overhead per
    /// frame, byte-identical frames), and the coordinator's and workers' memory for a
    /// 10,000-frame sequence. About 5 to 10 minutes on a busy 2-core machine, so not
    /// part of `all`.
    Sequence,
    /// Error and scaling.
    All,
}

/// How to run the benchmarks.
pub struct Options {
    pub suite: Suite,
    pub out: PathBuf,
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
}

pub use renderer::External;

/// Runs the chosen suites.
pub async fn run(opts: &Options) -> Result<()> {
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
    if opts.suite == Suite::Latency {
        latency::run(opts, &opts.out).await?;
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
