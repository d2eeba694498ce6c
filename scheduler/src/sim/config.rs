//! What names a run: the farm's machines, its jobs, its failures, and the policy and
//! limits the core runs with ([`SimConfig`]), checked before a run starts; and the
//! runs of the scaling table. A run is its configuration and nothing else, so the
//! settings read apart from the engine that plays them.

use std::net::IpAddr;

use crate::lifecycle::{self, Lifecycle, Limits};
use crate::tiles::Policy;

/// A kind of machine in the farm: real farms mix laptops, desktops and servers, and the
/// spread of their speeds is what makes stragglers.
#[derive(Clone, Debug, PartialEq)]
pub struct MachineClass {
    /// Relative share of the farm's machines in this class (shares need not sum to 1).
    pub share: f64,
    /// Rendering threads; the scheduler gives the worker twice as many tiles.
    pub threads: u32,
    /// Speed of one thread, relative to the reference thread that renders a full tile in
    /// [`SimConfig::tile_ms`].
    pub speed: f64,
}

/// Everything that defines a simulated run. Two runs of the same configuration give the
/// same [`Outcome`] and [`Memory`].
///
/// [`Outcome`]: super::Outcome
/// [`Memory`]: super::Memory
#[derive(Clone, Debug, PartialEq)]
pub struct SimConfig {
    /// Names the run: every random draw derives from it.
    pub seed: u64,
    /// Machines present from the start.
    pub workers: usize,
    /// The mix of machines, for the initial ones and those that join.
    pub classes: Vec<MachineClass>,
    /// Each machine's thread speed is its class's times a factor uniform in
    /// [1 - spread, 1 + spread): no two machines are quite alike.
    pub speed_spread: f64,
    /// Jobs (frames) submitted.
    pub jobs: usize,
    /// The first this many of them render in passes (adaptive sampling): each pass
    /// takes every tile with work further up the threshold ladder, and the core adds
    /// it up before the next (see [`super::passes`]).
    pub jobs_in_passes: usize,
    /// Time between two submissions (0: all at once).
    pub job_interval_ms: u64,
    /// Frame size and tile side, as a client would ask; they give the tiles per job.
    pub width: u32,
    pub height: u32,
    pub tile_size: u32,
    /// Time of one full tile of average cost on a reference thread (speed 1).
    pub tile_ms: f64,
    /// Costly regions per frame, at random places, each a smooth bump of radius 5–20 %
    /// of the frame's smaller side.
    pub hotspots: usize,
    /// A tile at the centre of a hot region costs this many times the base.
    pub hotspot_factor: f64,
    /// Each tile's cost is also scaled by a factor uniform in [1 - noise, 1 + noise).
    pub tile_noise: f64,
    /// Crashes per machine per hour of farm time (Poisson).
    pub crashes_per_worker_hour: f64,
    /// Hangs per machine per hour of farm time (Poisson).
    pub hangs_per_worker_hour: f64,
    /// A hang lasts a time uniform in [min, max): around the heartbeat timeout, some
    /// workers come back in time and some are dropped.
    pub hang_min_ms: u64,
    pub hang_max_ms: u64,
    /// Render hangs per machine per hour of farm time (Poisson): the worker's render
    /// threads stop (a deadlock, a driver hang) while its runtime keeps heart-beating
    /// and reading, for a time uniform in [min, max). Only the scheduler's progress
    /// check ([`Policy::progress_timeout`]) tells such a worker from a working one.
    pub render_hangs_per_worker_hour: f64,
    pub render_hang_min_ms: u64,
    pub render_hang_max_ms: u64,
    /// New machines per minute (Poisson), while jobs remain.
    pub joins_per_minute: f64,
    /// One-way network latency: base plus a jitter uniform in [0, jitter).
    pub latency_ms: f64,
    pub latency_jitter_ms: f64,
    /// The worker's heartbeat period (its own constant: 1 s).
    pub heartbeat_ms: u64,
    /// A crashed machine's supervisor restarts its worker after this long, under the
    /// same name (`None`: a crashed machine stays down).
    pub restart_after_ms: Option<u64>,
    /// Pauses of the whole coordinator per hour of farm time (Poisson), each lasting a
    /// time uniform in [min, max).
    pub coordinator_pauses_per_hour: f64,
    pub coordinator_pause_min_ms: u64,
    pub coordinator_pause_max_ms: u64,
    /// Network cuts per machine per hour of farm time (Poisson), each lasting a time
    /// uniform in [min, max).
    pub cuts_per_worker_hour: f64,
    pub cut_min_ms: u64,
    pub cut_max_ms: u64,
    /// The worker's first reconnection delay (its own constant: 100 ms), scaled by a
    /// random factor in [0.5, 1).
    pub reconnect_ms: u64,
    /// The tile scheduler's policy, as the daemon would set it.
    pub policy: Policy,
    /// The lifecycle's limits, as the daemon would set them. Its `retry_ms` is also the
    /// persistence thread's pause between two attempts of a failed write (the daemon
    /// sets both to 500 ms).
    pub limits: Limits,
    /// One write of rows on the persistence thread, synced to the disk: a job's
    /// insert, a batch of tiles, a job's start, its end, a deletion.
    pub storage_write_ms: f64,
    /// Encoding a finished job's image, on the blocking pool (off the writer).
    pub image_encode_ms: f64,
    /// Writing a finished job's image files, on the persistence thread.
    pub image_write_ms: f64,
    /// Outages of the disk per hour of farm time (Poisson), each lasting a time uniform
    /// in [min, max): every write fails meanwhile.
    pub storage_outages_per_hour: f64,
    pub storage_outage_min_ms: u64,
    pub storage_outage_max_ms: u64,
    /// A client whose submission is refused submits it again this long after the
    /// answer arrives.
    pub resubmit_ms: u64,
    /// The run stops here even if jobs remain (reported as timed out).
    pub max_virtual_ms: u64,
}

impl Default for SimConfig {
    /// A thousand mixed machines rendering twenty 4K frames, with a few crashes, hangs
    /// and arrivals: a busy farm on an ordinary day.
    fn default() -> Self {
        SimConfig {
            seed: 1,
            workers: 1000,
            classes: vec![
                MachineClass {
                    share: 0.25,
                    threads: 4,
                    speed: 0.7,
                },
                MachineClass {
                    share: 0.5,
                    threads: 8,
                    speed: 1.0,
                },
                MachineClass {
                    share: 0.2,
                    threads: 16,
                    speed: 1.2,
                },
                MachineClass {
                    share: 0.05,
                    threads: 32,
                    speed: 1.5,
                },
            ],
            speed_spread: 0.2,
            jobs: 20,
            jobs_in_passes: 0,
            job_interval_ms: 0,
            width: 3840,
            height: 2160,
            tile_size: 32,
            tile_ms: 2_000.0,
            hotspots: 3,
            hotspot_factor: 8.0,
            tile_noise: 0.3,
            crashes_per_worker_hour: 1.0,
            hangs_per_worker_hour: 1.0,
            hang_min_ms: 1_000,
            hang_max_ms: 20_000,
            render_hangs_per_worker_hour: 0.5,
            render_hang_min_ms: 10_000,
            render_hang_max_ms: 600_000,
            joins_per_minute: 10.0,
            latency_ms: 0.5,
            latency_jitter_ms: 0.5,
            heartbeat_ms: 1_000,
            restart_after_ms: None,
            coordinator_pauses_per_hour: 0.0,
            coordinator_pause_min_ms: 3_000,
            coordinator_pause_max_ms: 10_000,
            cuts_per_worker_hour: 0.0,
            cut_min_ms: 1_000,
            cut_max_ms: 10_000,
            reconnect_ms: 100,
            policy: Policy::default(),
            limits: Limits::default(),
            storage_write_ms: 5.0,
            image_encode_ms: 300.0,
            image_write_ms: 50.0,
            storage_outages_per_hour: 0.0,
            storage_outage_min_ms: 1_000,
            storage_outage_max_ms: 30_000,
            resubmit_ms: 1_000,
            max_virtual_ms: 24 * 3_600_000,
        }
    }
}

impl SimConfig {
    /// A farm of identical single-threaded machines that never fail: the setting in
    /// which the makespan should come close to the ideal.
    pub fn uniform(workers: usize) -> Self {
        SimConfig {
            workers,
            classes: vec![MachineClass {
                share: 1.0,
                threads: 1,
                speed: 1.0,
            }],
            speed_spread: 0.0,
            hotspots: 0,
            tile_noise: 0.0,
            ..SimConfig::default()
        }
        .without_failures()
    }

    /// The same farm where nothing fails and nobody joins.
    pub fn without_failures(self) -> Self {
        SimConfig {
            crashes_per_worker_hour: 0.0,
            hangs_per_worker_hour: 0.0,
            render_hangs_per_worker_hour: 0.0,
            joins_per_minute: 0.0,
            coordinator_pauses_per_hour: 0.0,
            cuts_per_worker_hour: 0.0,
            storage_outages_per_hour: 0.0,
            ..self
        }
    }

    /// What every job asks of the lifecycle: the frame, a small scene, from one client
    /// address (a pipeline submitting the frames of an animation).
    pub fn request(&self) -> lifecycle::Request {
        lifecycle::Request {
            client: Some(IpAddr::from([10, 0, 0, 1])),
            scene_bytes: 4_096,
            objects: 16,
            width: self.width,
            height: self.height,
            aa: 1,
        }
    }

    pub fn tiles_per_job(&self) -> u32 {
        self.width.div_ceil(self.tile_size.max(1)) * self.height.div_ceil(self.tile_size.max(1))
    }

    /// Whether the run can make sense, with the reason if not.
    pub fn validate(&self) -> Result<(), String> {
        let rate = |r: f64| r.is_finite() && r >= 0.0;
        if self.jobs == 0 {
            return Err("jobs: at least one".into());
        }
        if self.jobs_in_passes > self.jobs {
            return Err(format!(
                "jobs_in_passes: at most the {} jobs, not {}",
                self.jobs, self.jobs_in_passes
            ));
        }
        if self.width == 0 || self.height == 0 || self.tile_size == 0 {
            return Err("width, height and tile_size must be positive".into());
        }
        if self.workers == 0 && self.joins_per_minute <= 0.0 {
            return Err("no worker: give workers or a join rate".into());
        }
        if self.classes.is_empty()
            || self.classes.iter().any(|c| {
                c.threads == 0 || !(c.speed.is_finite() && c.speed > 0.0) || !rate(c.share)
            })
            || self.classes.iter().map(|c| c.share).sum::<f64>() <= 0.0
        {
            return Err(
                "classes: at least one, each with threads, a positive speed and a share".into(),
            );
        }
        if !(0.0..1.0).contains(&self.speed_spread) || !(0.0..1.0).contains(&self.tile_noise) {
            return Err("speed_spread and tile_noise must be in [0, 1)".into());
        }
        let tile_ok = self.tile_ms.is_finite() && self.tile_ms > 0.0;
        let hotspot_ok = self.hotspot_factor.is_finite() && self.hotspot_factor >= 1.0;
        if !(tile_ok && hotspot_ok) {
            return Err("tile_ms must be positive and hotspot_factor at least 1".into());
        }
        if ![
            self.crashes_per_worker_hour,
            self.hangs_per_worker_hour,
            self.render_hangs_per_worker_hour,
            self.joins_per_minute,
            self.coordinator_pauses_per_hour,
            self.cuts_per_worker_hour,
            self.latency_ms,
            self.latency_jitter_ms,
            self.storage_outages_per_hour,
            self.storage_write_ms,
            self.image_encode_ms,
            self.image_write_ms,
        ]
        .into_iter()
        .all(rate)
        {
            return Err("rates, latencies and write times must be finite and not negative".into());
        }
        if self.hang_min_ms > self.hang_max_ms
            || self.render_hang_min_ms > self.render_hang_max_ms
            || self.coordinator_pause_min_ms > self.coordinator_pause_max_ms
            || self.cut_min_ms > self.cut_max_ms
            || self.storage_outage_min_ms > self.storage_outage_max_ms
        {
            return Err("each minimum duration must not exceed its maximum".into());
        }
        if self.heartbeat_ms == 0 || self.reconnect_ms == 0 || self.restart_after_ms == Some(0) {
            return Err("heartbeat_ms, reconnect_ms and restart_after_ms must be positive".into());
        }
        if self.resubmit_ms == 0 || self.limits.retry_ms == 0 {
            return Err("resubmit_ms and limits.retry_ms must be positive".into());
        }
        // A job the lifecycle refuses on its own would be submitted again forever.
        if let Err(reason) = Lifecycle::new(self.limits, 1).admit(0, &self.request()) {
            return Err(format!("the lifecycle refuses every job: {reason}"));
        }
        Ok(())
    }
}

/// The runs of the scaling table in `docs/simulation.md`: 100, 1,000 and 5,000 mixed
/// machines on one and on twenty 4K frames, without and with failures (the defaults:
/// a crash and a hang per machine-hour, ten arrivals a minute); then the largest farm
/// without speculation, and one 8192 × 8192 frame cut into 32- and 16-pixel tiles on
/// 1,000 identical single-threaded machines.
pub fn scaling_runs() -> Vec<(String, SimConfig)> {
    let mut runs = Vec::new();
    for workers in [100, 1_000, 5_000] {
        for jobs in [1, 20] {
            for failures in [false, true] {
                let config = SimConfig {
                    workers,
                    jobs,
                    ..SimConfig::default()
                };
                let (config, trouble) = if failures {
                    (config, ", failures")
                } else {
                    (config.without_failures(), "")
                };
                runs.push((format!("{workers} w, {jobs} × 4K{trouble}"), config));
            }
        }
    }
    let mut config = SimConfig {
        workers: 5_000,
        jobs: 20,
        ..SimConfig::default()
    };
    config.policy.speculate = false;
    runs.push(("5000 w, 20 × 4K, failures, no speculation".into(), config));
    // The same frame and the same work cut finer, on identical machines: what changes
    // is only the number of tiles the scheduler tracks.
    for tile_size in [32, 16] {
        let config = SimConfig {
            jobs: 1,
            width: 8192,
            height: 8192,
            tile_size,
            tile_ms: 2_000.0 * f64::from(tile_size * tile_size) / (32.0 * 32.0),
            ..SimConfig::uniform(1_000)
        };
        runs.push((
            format!("1000 × 1 thread, 1 × 8192², {tile_size}-px tiles"),
            config,
        ));
    }
    runs
}
