//! What a simulated run shows, and how it prints.

use std::fmt;
use std::time::Duration;

/// What happened in virtual time. A function of the configuration alone: two runs of
/// the same seed give equal outcomes.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Outcome {
    pub workers_initial: usize,
    /// Machines that joined during the run.
    pub workers_joined: usize,
    /// Rendering threads of the initial machines.
    pub threads_initial: u64,
    /// Machines running or stopped (not crashed) when the last job ended.
    pub workers_at_end: usize,
    pub crashes: u64,
    pub hangs: u64,
    /// Render hangs: a machine's render threads stopped while it kept heart-beating.
    pub render_hangs: u64,
    /// Times the scheduler marked a worker unresponsive (leases run out, no result),
    /// and times one came back with a result.
    pub unresponsive: u64,
    pub responsive_again: u64,
    /// Workers the coordinator dropped for silence (hangs longer than the timeout).
    pub drops: u64,
    /// Sessions a worker ended because the coordinator closed them, then reconnected.
    pub reconnects: u64,
    /// Crashed workers started again by their supervisor, under the same name.
    pub restarts: u64,
    /// Times the whole coordinator stopped for a while.
    pub coordinator_pauses: u64,
    /// Network cuts between a machine and the coordinator.
    pub network_cuts: u64,
    /// `Timeout`s: the daemon's timer firing at the earlier of the two machines' next
    /// deadlines.
    pub timeouts: u64,

    pub jobs: usize,
    /// Jobs the lifecycle shows `Done`: every tile in, the image stored and the end
    /// written.
    pub jobs_done: usize,
    /// Jobs the lifecycle shows `Failed` (the end written).
    pub jobs_failed: usize,
    /// Each failed job and the reason written with its end.
    pub job_failures: Vec<(u64, String)>,

    /// Submissions the lifecycle admitted (an id given, the row to be written):
    /// one per job, plus one per insert that failed.
    pub jobs_admitted: u64,
    /// Jobs acknowledged: the row written, the tiles handed to the tile scheduler.
    pub jobs_acknowledged: usize,
    /// Submissions the lifecycle refused (storage known to be unavailable, or a limit on
    /// active jobs reached); the client submitted them again.
    pub admissions_refused: u64,
    /// Submissions admitted whose row could not be written (the client is told at
    /// once, and submitted again).
    pub stores_refused: u64,
    /// The longest a job waited from its client's first submission to its
    /// acknowledgement, refusals included.
    pub longest_admission_ms: f64,
    /// The longest from a done job's last tile to its end written (the image encoded
    /// and stored, the end written, and the waits for the disk).
    pub longest_finish_ms: f64,
    /// Jobs deleted after the lifecycle's retention.
    pub jobs_deleted: u64,

    /// Outages of the disk (every write fails while one lasts).
    pub storage_outages: u64,
    /// Times a failed write made the daemon report storage unavailable to both machines
    /// (each followed by `StorageAvailable` once a write succeeds again, unless the run
    /// ended first).
    pub storage_unavailable: u64,
    /// Virtual time during which storage was reported unavailable.
    pub storage_unavailable_ms: f64,
    /// Writes carried out on the persistence thread (inserts, batches of tiles, starts,
    /// images, ends, deletions and probes of the disk).
    pub writes: u64,
    /// Attempts of a write that failed (each retried, but a job's insert, answered
    /// at once).
    pub write_failures: u64,
    /// Accepted tiles written.
    pub tiles_written: u64,
    /// Images stored.
    pub images_stored: u64,
    pub tiles: u64,
    /// `AcceptTile` actions: one per tile when nothing is lost or counted twice.
    pub tiles_accepted: u64,
    /// Tiles accepted more than once (must be 0).
    pub tiles_accepted_twice: u64,
    /// Passes that went on to another (jobs in passes only).
    pub passes_continued: u64,
    /// Tiles of jobs reported done that were never accepted (must be 0).
    pub tiles_missing: u64,

    /// `Assign` actions; beyond one per tile, the tile is rendered again because...
    pub assignments: u64,
    /// ...its holder was lost (crashed, dropped),
    pub reassigned_after_loss: u64,
    /// ...every lease on it ran out,
    pub reassigned_after_expiry: u64,
    /// ...or it was a straggler, copied to an idle worker.
    pub speculative_copies: u64,
    /// Leases that ran out while their tile was still out.
    pub leases_expired: u64,
    /// Second results for accepted tiles (straggler copies and late holders).
    pub duplicate_results: u64,
    /// Results the scheduler ignored (its job had ended, or the sender no longer held it).
    pub stray_results: u64,
    /// Results sent on a connection the coordinator had already dropped, never read.
    pub results_unread: u64,

    pub renders_started: u64,
    pub renders_completed: u64,
    /// Renders cut short by a crash.
    pub renders_interrupted: u64,
    /// Renders that finished after their session ended, so were never sent.
    pub renders_orphaned: u64,
    /// Tiles received but never started: their job was cancelled on the worker, or the
    /// session ended.
    pub tasks_skipped: u64,
    pub scenes_sent: u64,
    pub scenes_forgotten: u64,

    /// Work in the jobs, in milliseconds of a reference thread.
    pub work_ms: f64,
    /// Work the farm did, in the same unit: re-renders, copies and renders cut short
    /// included.
    pub work_spent_ms: f64,

    /// From the first submission to the last job's end written.
    pub makespan_ms: f64,
    /// A lower bound on the makespan: the larger of `ideal_work_ms` and `ideal_tile_ms`.
    pub ideal_ms: f64,
    /// The time at which the farm's capacity, integrated from the moment the first
    /// job's first tile could reach a worker (its submission and that tile crossing the
    /// network at base latency, its row written), reaches the jobs' total work, plus
    /// what must follow the last tile (its result crossing the network, the image
    /// encoded and written, the end written): capacity is the sum of threads × thread
    /// speed of the machines up at each instant (from boot, less crashed and stopped
    /// ones; joiners counted from the moment they start), as if every tile were
    /// infinitely divisible and no tile were ever rendered twice.
    pub ideal_work_ms: f64,
    /// No job ends before its submission, the same steps before its first tile and
    /// after its last, and its costliest tile rendered by the fastest thread that ever
    /// ran in the farm.
    pub ideal_tile_ms: f64,
    /// `ideal_ms / makespan_ms`: 1 would be a perfect schedule.
    pub efficiency: f64,
    /// The last tile accepted: what the end of the run waited for.
    pub last_tile: Option<LastTile>,

    /// Calls to the decision core (`Farm::handle` and `Farm::admit`).
    pub events: u64,
    /// Disagreements between the scheduler's actions and the simulation's account of
    /// leases and connections (must be 0).
    pub model_mismatches: u64,
    /// The run reached `max_virtual_ms` with jobs left, or nothing was left to happen
    /// (no worker, no event to come) with jobs left.
    pub timed_out: bool,
}

/// The tile whose result ended the run, to see what the tail waited for. Times are
/// virtual milliseconds since the start of the run.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct LastTile {
    pub job: u64,
    pub tile: u32,
    /// Its cost on a reference thread.
    pub cost_ms: f64,
    /// How often it was sent out (copies and reassignments included), and when last.
    pub assignments: u32,
    pub last_assigned_ms: f64,
    /// The speed of the thread that rendered the accepted copy.
    pub thread_speed: f64,
    /// When the coordinator sent the accepted copy, when its render began (after the
    /// tiles queued before it on that worker), and when its result was accepted.
    pub assigned_ms: f64,
    pub started_ms: f64,
    pub accepted_ms: f64,
}

/// The heap the scheduler holds, in bytes the program asked the allocator for (the
/// allocator's own overhead comes on top). Measured with [`super::CountingAlloc`].
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Memory {
    /// A job submitted to a farm without workers: its queue and bookkeeping.
    pub per_job_queued: f64,
    pub per_tile_queued: f64,
    /// A worker joining a scheduler without jobs.
    pub per_worker_idle: f64,
    /// A worker joining while jobs wait: its own record plus the leases of the tiles it
    /// takes (its credit).
    pub per_worker_busy: f64,
    /// What a tile costs while in flight, over what it costs queued.
    pub per_tile_in_flight: f64,
    /// Tiles in flight in that measurement.
    pub tiles_in_flight_probed: u64,
    /// The largest heap the scheduler held during the run.
    pub peak_bytes: i64,
    /// What it still held when the last job ended.
    pub end_bytes: i64,
}

/// Real time spent in `Scheduler::handle` (or the lifecycle) for one kind of event.
#[derive(Clone, Debug, PartialEq)]
pub struct EventCost {
    pub kind: String,
    pub count: u64,
    pub total: Duration,
    /// The longest single call: the daemon holds its state lock that long.
    pub max: Duration,
}

/// The result of [`super::run`]: the outcome in virtual time, the memory held by the
/// decision core, and the real time it took to decide.
#[derive(Clone, Debug)]
pub struct SimReport {
    pub outcome: Outcome,
    /// `None` unless [`super::CountingAlloc`] is the global allocator.
    pub memory: Option<Memory>,
    /// Real time inside the decision core (each call timed on its own, so a timer
    /// read of some tens of nanoseconds is included per call), the follow-ups it feeds
    /// itself included.
    pub handle_time: Duration,
    /// By kind of input: those about tiles and workers (the time counted as
    /// `Timeout`), then `admit`, then those about jobs, in the order first seen.
    pub by_event: Vec<EventCost>,
    /// Real time of the whole run, the simulation's own work included.
    pub wall: Duration,
}

impl SimReport {
    /// Tiles accepted per second of the core's time: the rate at which one core could
    /// drive this farm, leaving out the network, the database and image assembly.
    pub fn tiles_per_second(&self) -> f64 {
        self.outcome.tiles_accepted as f64 / self.handle_time.as_secs_f64().max(1e-12)
    }

    pub fn events_per_second(&self) -> f64 {
        self.outcome.events as f64 / self.handle_time.as_secs_f64().max(1e-12)
    }

    /// The core's time per second of farm time: the share of one core it would take
    /// in the daemon (under its single lock) to run this farm.
    pub fn cpu_load(&self) -> f64 {
        self.handle_time.as_secs_f64() / (self.outcome.makespan_ms / 1e3).max(1e-12)
    }

    /// The columns of [`SimReport::table_row`], as a Markdown table header.
    pub fn table_header() -> String {
        "| run | workers (threads) | jobs × tiles | makespan | ideal | efficiency | \
         re-rendered | core time | tiles/s | CPU load | longest call | bytes/job | \
         bytes/worker |\n\
         | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: \
         | ---: |"
            .to_string()
    }

    /// One line of a Markdown table comparing runs.
    pub fn table_row(&self, label: &str) -> String {
        let o = &self.outcome;
        let rerendered = o.reassigned_after_loss + o.reassigned_after_expiry + o.speculative_copies;
        let longest = self
            .by_event
            .iter()
            .map(|c| c.max)
            .max()
            .unwrap_or_default();
        let (per_job, per_worker) = match &self.memory {
            Some(m) => (bytes(m.per_job_queued), bytes(m.per_worker_busy)),
            None => ("–".into(), "–".into()),
        };
        format!(
            "| {label} | {} ({}) | {} × {} | {} | {} | {:.2} | {} ({:.1} %) | {} | {} | {:.3} | {} | {per_job} | {per_worker} |",
            o.workers_initial,
            o.threads_initial,
            o.jobs,
            o.tiles / o.jobs.max(1) as u64,
            seconds(o.makespan_ms),
            seconds(o.ideal_ms),
            o.efficiency,
            rerendered,
            100.0 * rerendered as f64 / o.tiles.max(1) as f64,
            duration(self.handle_time),
            count(self.tiles_per_second()),
            self.cpu_load(),
            duration(longest),
        )
    }
}

fn seconds(ms: f64) -> String {
    if ms.is_finite() {
        format!("{:.1} s", ms / 1e3)
    } else {
        "∞".into()
    }
}

/// A virtual time, in milliseconds below a second.
fn span(ms: f64) -> String {
    if ms < 1e3 {
        format!("{ms:.0} ms")
    } else {
        seconds(ms)
    }
}

fn duration(d: Duration) -> String {
    let s = d.as_secs_f64();
    if s >= 1.0 {
        format!("{s:.2} s")
    } else if s >= 1e-3 {
        format!("{:.1} ms", s * 1e3)
    } else {
        format!("{:.1} µs", s * 1e6)
    }
}

fn count(x: f64) -> String {
    if x >= 1e6 {
        format!("{:.2} M", x / 1e6)
    } else if x >= 1e3 {
        format!("{:.0} k", x / 1e3)
    } else {
        format!("{x:.0}")
    }
}

fn bytes(b: f64) -> String {
    if b >= 1024.0 * 1024.0 {
        format!("{:.1} MiB", b / (1024.0 * 1024.0))
    } else if b >= 1024.0 {
        format!("{:.1} KiB", b / 1024.0)
    } else {
        format!("{b:.0} B")
    }
}

/// The real time of each kind of event, as a Markdown table.
fn cost_table(f: &mut fmt::Formatter<'_>, costs: &[EventCost]) -> fmt::Result {
    writeln!(f, "| event | calls | total | mean | longest |")?;
    writeln!(f, "| --- | ---: | ---: | ---: | ---: |")?;
    for c in costs {
        writeln!(
            f,
            "| {} | {} | {} | {} | {} |",
            c.kind,
            c.count,
            duration(c.total),
            duration(c.total / u32::try_from(c.count).unwrap_or(u32::MAX).max(1)),
            duration(c.max)
        )?;
    }
    Ok(())
}

impl fmt::Display for SimReport {
    /// A Markdown summary, for the command line and for pasting into a report.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let o = &self.outcome;
        writeln!(f, "## Farm")?;
        writeln!(f)?;
        writeln!(
            f,
            "- {} machines ({} threads) at the start, {} joined, {} up at the end",
            o.workers_initial, o.threads_initial, o.workers_joined, o.workers_at_end
        )?;
        writeln!(
            f,
            "- {} crashes ({} restarted under their name), {} hangs, {} render hangs ({} \
             workers marked unresponsive, {} responsive again), {} network cuts, {} \
             workers dropped for silence, {} reconnections; {} coordinator pauses",
            o.crashes,
            o.restarts,
            o.hangs,
            o.render_hangs,
            o.unresponsive,
            o.responsive_again,
            o.network_cuts,
            o.drops,
            o.reconnects,
            o.coordinator_pauses
        )?;
        writeln!(
            f,
            "- {} jobs: {} done (image and end written), {} failed{}",
            o.jobs,
            o.jobs_done,
            o.jobs_failed,
            if o.timed_out {
                ", the rest unfinished (timed out)"
            } else {
                ""
            }
        )?;
        for (job, message) in &o.job_failures {
            writeln!(f, "  - job {job} failed: {message}")?;
        }
        writeln!(
            f,
            "- {} tiles: {} accepted, {} twice, {} missing",
            o.tiles, o.tiles_accepted, o.tiles_accepted_twice, o.tiles_missing
        )?;
        if o.passes_continued > 0 {
            writeln!(
                f,
                "- {} passes of jobs in passes went on to another (each pass accepts its tiles once)",
                o.passes_continued
            )?;
        }
        writeln!(f)?;
        writeln!(f, "## Admission and storage")?;
        writeln!(f)?;
        writeln!(
            f,
            "- {} submissions admitted, {} acknowledged once stored; {} refused by the \
             lifecycle and {} whose insert failed (each submitted again); the longest wait \
             for an acknowledgement {}",
            o.jobs_admitted,
            o.jobs_acknowledged,
            o.admissions_refused,
            o.stores_refused,
            span(o.longest_admission_ms)
        )?;
        writeln!(
            f,
            "- {} disk outages; storage reported unavailable {} times, for {} in all",
            o.storage_outages,
            o.storage_unavailable,
            span(o.storage_unavailable_ms)
        )?;
        writeln!(
            f,
            "- {} writes ({} tiles, {} images), {} failed attempts; the longest from a \
             job's last tile to its end written {}; {} jobs deleted after their retention",
            o.writes,
            o.tiles_written,
            o.images_stored,
            o.write_failures,
            span(o.longest_finish_ms),
            o.jobs_deleted
        )?;
        writeln!(f)?;
        writeln!(f, "## Makespan")?;
        writeln!(f)?;
        writeln!(f, "| | virtual time |")?;
        writeln!(f, "| --- | ---: |")?;
        writeln!(f, "| makespan | {} |", seconds(o.makespan_ms))?;
        writeln!(f, "| ideal (lower bound) | {} |", seconds(o.ideal_ms))?;
        writeln!(f, "| – capacity bound | {} |", seconds(o.ideal_work_ms))?;
        writeln!(f, "| – longest-tile bound | {} |", seconds(o.ideal_tile_ms))?;
        writeln!(f, "| efficiency (ideal / makespan) | {:.3} |", o.efficiency)?;
        writeln!(f)?;
        if let Some(t) = &o.last_tile {
            writeln!(
                f,
                "The last tile accepted (job {}, tile {}) costs {} on a reference thread. It \
                 was sent out {} times, last at {}; the accepted copy was sent at {}, began \
                 at {} on a thread of speed {:.2} and was accepted at {}.",
                t.job,
                t.tile,
                seconds(t.cost_ms),
                t.assignments,
                seconds(t.last_assigned_ms),
                seconds(t.assigned_ms),
                seconds(t.started_ms),
                t.thread_speed,
                seconds(t.accepted_ms)
            )?;
            writeln!(f)?;
        }
        writeln!(f, "## Work")?;
        writeln!(f)?;
        writeln!(
            f,
            "- {} assignments for {} tiles: {} after a lost holder, {} after leases ran out, \
             {} straggler copies",
            o.assignments,
            o.tiles,
            o.reassigned_after_loss,
            o.reassigned_after_expiry,
            o.speculative_copies
        )?;
        writeln!(
            f,
            "- {} leases ran out; {} duplicate results, {} ignored, {} unread on dropped \
             connections",
            o.leases_expired, o.duplicate_results, o.stray_results, o.results_unread
        )?;
        writeln!(
            f,
            "- {} renders started, {} completed, {} cut short by a crash, {} finished after \
             their session, {} received but skipped",
            o.renders_started,
            o.renders_completed,
            o.renders_interrupted,
            o.renders_orphaned,
            o.tasks_skipped
        )?;
        writeln!(
            f,
            "- work: {:.0} reference-thread seconds needed, {:.0} spent ({:.1} % more)",
            o.work_ms / 1e3,
            o.work_spent_ms / 1e3,
            100.0 * (o.work_spent_ms / o.work_ms.max(1e-9) - 1.0)
        )?;
        writeln!(
            f,
            "- {} scenes sent, {} forgotten; simulation checks: {} mismatches",
            o.scenes_sent, o.scenes_forgotten, o.model_mismatches
        )?;
        writeln!(f)?;
        writeln!(f, "## Decision core time (real)")?;
        writeln!(f)?;
        writeln!(
            f,
            "{} events in {}: {} events/s, {} tiles/s; {:.3} of a core at this farm's pace \
             (whole simulation: {})",
            o.events,
            duration(self.handle_time),
            count(self.events_per_second()),
            count(self.tiles_per_second()),
            self.cpu_load(),
            duration(self.wall)
        )?;
        writeln!(f)?;
        cost_table(f, &self.by_event)?;
        writeln!(f)?;
        writeln!(f, "## Decision core memory")?;
        writeln!(f)?;
        match &self.memory {
            None => writeln!(
                f,
                "Not measured: install `scheduler::sim::CountingAlloc` as the global \
                 allocator."
            )?,
            Some(m) => {
                writeln!(f, "| | bytes |")?;
                writeln!(f, "| --- | ---: |")?;
                writeln!(f, "| per job, queued | {} |", bytes(m.per_job_queued))?;
                writeln!(f, "| per tile, queued | {:.1} |", m.per_tile_queued)?;
                writeln!(f, "| per worker, idle | {} |", bytes(m.per_worker_idle))?;
                writeln!(
                    f,
                    "| per worker, holding its credit | {} |",
                    bytes(m.per_worker_busy)
                )?;
                writeln!(
                    f,
                    "| per tile in flight, over queued ({} tiles) | {:.1} |",
                    m.tiles_in_flight_probed, m.per_tile_in_flight
                )?;
                writeln!(
                    f,
                    "| peak during the run | {} |",
                    bytes(m.peak_bytes as f64)
                )?;
                writeln!(f, "| at the end | {} |", bytes(m.end_bytes as f64))?;
            }
        }
        Ok(())
    }
}
