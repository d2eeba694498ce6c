//! Pools seen from the daemon: the warning a job gets while the workers it requires
//! are missing, and the work waiting in each pool for autoscalers (`/metrics`).
//!
//! A pool is a set of required tags, named by [`protocol::pool_name`] (sorted, joined
//! with `,`; the empty name for jobs any worker may take).

use std::collections::BTreeMap;

use protocol::{JobId, Verification};

use super::Core;
use crate::metrics::PoolFigures;

/// Camera samples per second one thread is taken to render before anything was
/// measured on this farm: a guess (a simple scene at depth 10 on a current core), only
/// until the first result, after which measured figures replace it.
pub const GUESSED_SAMPLES_PER_SECOND: f64 = 250_000.0;

/// Rendering time measured from accepted results: their time on one thread and their
/// camera samples, over how many tiles.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Measured {
    pub render_us: u64,
    pub samples: u64,
    pub tiles: u64,
}

impl Measured {
    pub fn add(&mut self, render_us: u64, samples: u64) {
        self.render_us = self.render_us.saturating_add(render_us);
        self.samples = self.samples.saturating_add(samples);
        self.tiles += 1;
    }
}

/// The estimated CPU-seconds (on one thread) of `left` tiles of a job: at the job's own
/// measured seconds per tile once it has a result; before that, at the farm's measured
/// seconds per camera sample times the samples a tile of the job takes at most
/// (`samples_per_tile`); before any result at all, at
/// [`GUESSED_SAMPLES_PER_SECOND`].
pub fn cpu_seconds(left: u32, job: Measured, farm: Measured, samples_per_tile: f64) -> f64 {
    let per_tile = if job.tiles > 0 {
        job.render_us as f64 / 1e6 / job.tiles as f64
    } else if farm.samples > 0 {
        farm.render_us as f64 / 1e6 / farm.samples as f64 * samples_per_tile
    } else {
        samples_per_tile / GUESSED_SAMPLES_PER_SECOND
    };
    f64::from(left) * per_tile
}

impl Core {
    /// Why a job requiring `require` cannot go on now, in one line: no connected worker
    /// ready for work has its tags (it waits until one connects), or for `--verify
    /// full` only one machine has (its tiles cannot be confirmed). `None` otherwise,
    /// and for a job that requires nothing (the farm's own warning covers it).
    pub(super) fn pool_warning(
        &self,
        require: &[String],
        verification: Verification,
    ) -> Option<String> {
        if require.is_empty() {
            return None;
        }
        let tags = require.join(", ");
        let machines = self.farm.tiles().qualifying_machines(require);
        match machines.as_slice() {
            [] => Some(format!(
                "no connected worker has every tag this job requires ({tags}): it waits \
                 until one connects"
            )),
            [only] if verification == Verification::Full => Some(format!(
                "only one connected machine ({}) has every tag this job requires \
                 ({tags}): --verify full needs a second to confirm its tiles",
                only.replace(char::is_control, "?")
            )),
            _ => None,
        }
    }

    /// The work waiting in each pool, and the workers that may take it, for
    /// `/metrics`: every pool of an active job, each tag of a connected worker (so that
    /// a pool an autoscaler watches shows its workers while idle), and the default
    /// pool, by name.
    pub fn pool_figures(&self) -> Vec<PoolFigures> {
        let tiles = self.farm.tiles();
        let mut pools: BTreeMap<String, (Vec<String>, u64, f64)> = BTreeMap::new();
        pools.insert(String::new(), (Vec::new(), 0, 0.0));
        for w in self.workers.values() {
            for tag in &w.tags {
                pools.insert(tag.clone(), (vec![tag.clone()], 0, 0.0));
            }
        }
        for (job, left) in tiles.work_left() {
            let require = tiles.requirements(job);
            let seconds = self.cpu_seconds_left(job, left);
            let entry = pools
                .entry(protocol::pool_name(&require))
                .or_insert_with(|| (require, 0, 0.0));
            entry.1 += u64::from(left);
            entry.2 += seconds;
        }
        pools
            .into_iter()
            .map(
                |(pool, (require, waiting_tiles, waiting_cpu_seconds))| PoolFigures {
                    workers: u64::from(tiles.qualifying_workers(&require)),
                    pool,
                    waiting_tiles,
                    waiting_cpu_seconds,
                },
            )
            .collect()
    }

    /// [`cpu_seconds`] for `left` tiles of the job.
    fn cpu_seconds_left(&self, job: JobId, left: u32) -> f64 {
        let Some(record) = self.jobs.get(&job) else {
            return 0.0;
        };
        let tiles = record.tiles_total.max(1);
        let pixels = u64::from(record.settings.width) * u64::from(record.settings.height);
        let aa = u64::from(record.settings.aa);
        let samples_per_tile = (pixels * aa * aa) as f64 / f64::from(tiles);
        cpu_seconds(left, record.measured, self.measured, samples_per_tile)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cpu_seconds_follow_the_job_then_the_farm_then_the_guess() {
        let none = Measured::default();
        // Nothing measured: 4 tiles of 500,000 samples at the guessed pace.
        assert_eq!(cpu_seconds(4, none, none, 500_000.0), 8.0);
        // The farm's pace: 2 s for 1,000,000 samples is 2 µs a sample.
        let farm = Measured {
            render_us: 2_000_000,
            samples: 1_000_000,
            tiles: 10,
        };
        assert_eq!(cpu_seconds(4, none, farm, 500_000.0), 4.0);
        // The job's own: 3 tiles in 1.5 s of rendering is 0.5 s a tile.
        let mut job = Measured::default();
        for _ in 0..3 {
            job.add(500_000, 7);
        }
        assert_eq!(job.tiles, 3);
        assert_eq!(cpu_seconds(4, job, farm, 500_000.0), 2.0);
        assert_eq!(cpu_seconds(0, job, farm, 500_000.0), 0.0);
    }
}
