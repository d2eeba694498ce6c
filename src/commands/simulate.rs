//! `tessera simulate`: the coordinator's core (the tile scheduler and the job lifecycle)
//! driven by thousands of simulated workers, clients and a simulated disk in virtual
//! time (see docs/simulation.md). Reproducible: a seed names a run.

use anyhow::{bail, Result};
use scheduler::sim::{self, SimConfig};

/// Drive the scheduler with thousands of simulated workers in virtual time.
#[derive(clap::Args)]
#[command(
    long_about = "Run the coordinator's real scheduler against simulated workers of \
        mixed speeds that crash, hang and join, in virtual time, and report scheduling \
        throughput, memory and makespan against the ideal (see docs/simulation.md). \
        A seed names a run: the same options give the same report.",
    after_help = "Examples:\n  \
        tessera simulate --workers 2000 --jobs 10\n  \
        tessera simulate --table"
)]
pub struct Args {
    /// Simulated machines at the start.
    #[arg(long, default_value_t = 1000)]
    workers: usize,
    /// Jobs submitted at the start.
    #[arg(long, default_value_t = 20)]
    jobs: usize,
    /// How many of the jobs render in passes (adaptive sampling), the first ones.
    #[arg(long, default_value_t = 0)]
    jobs_in_passes: usize,
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

pub fn run(args: Args) -> Result<()> {
    if args.table {
        println!("{}", sim::SimReport::table_header());
        for (label, config) in sim::scaling_runs() {
            eprintln!("simulating: {label}");
            let report = sim::run(&config);
            println!("{}", report.table_row(&label));
        }
        return Ok(());
    }
    let mut config = SimConfig {
        seed: args.seed,
        workers: args.workers,
        jobs: args.jobs,
        jobs_in_passes: args.jobs_in_passes,
        width: args.width,
        height: args.height,
        tile_size: args.tile,
        ..SimConfig::default()
    };
    config.policy.speculate = !args.no_speculation;
    if args.no_failures {
        config = config.without_failures();
    }
    if let Err(reason) = config.validate() {
        bail!("cannot simulate this farm: {reason}");
    }
    print!("{}", sim::run(&config));
    Ok(())
}
