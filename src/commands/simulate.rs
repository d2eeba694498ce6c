//! `tessera simulate`: the coordinator's core (the tile scheduler and the job lifecycle)
//! driven by thousands of simulated workers, clients and a simulated disk in virtual
//! time (see docs/simulation.md). Reproducible: a seed names a run.

use anyhow::{bail, Result};
use scheduler::sim::{self, SimConfig};

/// What to simulate.
pub struct Options {
    pub workers: usize,
    pub jobs: usize,
    pub seed: u64,
    pub failures: bool,
    pub speculate: bool,
    pub width: u32,
    pub height: u32,
    pub tile: u32,
    /// Every run of the scaling table instead of one run.
    pub table: bool,
}

pub fn run(opts: &Options) -> Result<()> {
    if opts.table {
        println!("{}", sim::SimReport::table_header());
        for (label, config) in sim::scaling_runs() {
            eprintln!("simulating: {label}");
            let report = sim::run(&config);
            println!("{}", report.table_row(&label));
        }
        return Ok(());
    }
    let mut config = SimConfig {
        seed: opts.seed,
        workers: opts.workers,
        jobs: opts.jobs,
        width: opts.width,
        height: opts.height,
        tile_size: opts.tile,
        ..SimConfig::default()
    };
    config.policy.speculate = opts.speculate;
    if !opts.failures {
        config = config.without_failures();
    }
    if let Err(reason) = config.validate() {
        bail!("cannot simulate this farm: {reason}");
    }
    print!("{}", sim::run(&config));
    Ok(())
}
