//! A farm of thousands of workers, simulated in virtual time around the real core.
//!
//! One machine cannot host a farm of thousands of workers, but the coordinator's
//! decision core ([`Farm`]: the tile [`Scheduler`] and the job [`Lifecycle`] joined)
//! owns no socket, clock, file or thread, so it can be driven by a discrete-event
//! simulation instead: [`run`] feeds the very core the daemon (the coordinator) runs
//! the same inputs in the same order as the daemon would, from simulated clients,
//! workers with heterogeneous speeds that crash, hang, reconnect and join, over links
//! with latency, and a simulated disk that fails now and then; and it carries out the
//! core's effects the way the daemon does. How the two machines feed each other is
//! the core's, not the simulator's: nothing of it is written twice. Time
//! is virtual (a binary heap of timed events), so a run of hours of farm time takes
//! seconds, and a seed names one run exactly.
//!
//! What is modelled, mirroring the daemon, its persistence thread, the client and the
//! worker:
//! - **Coordinator**: every input handed to the core with the virtual clock in
//!   milliseconds, and a `Timeout` when [`Farm::next_deadline`] comes (the daemon's
//!   timer, re-armed after every call); `WorkerJoined` when a worker's hello arrives
//!   (under its machine's name), its `Accepted` sent first; `Heartbeat` and `TileDone`
//!   as they arrive; `WorkerLeft` when a connection closes, and right after a
//!   `DropWorker` (the daemon closes the connection, whose task then reports it).
//!   Messages on a connection the coordinator dropped are not read.
//! - **The core's effects carried out as the daemon does**: a submission is checked
//!   by [`Farm::admit`] and its row written (`Stored`) before its tiles go out; the
//!   first `Assign` of a job also writes the job's start; every accepted tile is
//!   written; `StoreImage` encodes the frame (off the writer) and writes it, then
//!   `ImageStored`; `RecordEnd` writes the end, then `EndRecorded`; `DeleteStored` is
//!   a write reported as `Deleted` (retention from [`SimConfig::limits`]). A job
//!   counts as done only once the lifecycle shows it `Done`: its image and its end
//!   written.
//! - **Persistence**: one writer carrying out the writes in order, each taking its
//!   latency (consecutive tiles in batches of up to 256, as the daemon's thread
//!   batches them). A write that fails reports storage unavailable (once) and is
//!   tried again every
//!   [`Limits::retry_ms`](crate::lifecycle::Limits::retry_ms) while the writes behind
//!   it wait; the first write that succeeds reports storage available again. A job's
//!   insert that
//!   fails is not retried: its client is answered at once (`StoreFailed`) and the
//!   writer probes the disk until it can write again.
//! - **Storage outages** (a Poisson process, off by default): for a random time every
//!   write fails at once, as on a full or read-only disk; a write under way when the
//!   outage begins fails too. The daemon learns of an outage only from a failed write.
//! - **Clients**: each job is submitted once, at its time, by the same client address;
//!   a submission refused (the lifecycle's limits on active jobs, or storage known to
//!   be unavailable) or whose insert failed is submitted again
//!   [`SimConfig::resubmit_ms`] after the answer arrives, until it is acknowledged.
//! - **Coordinator pauses** (a Poisson process, off by default): the whole daemon
//!   stops, as with `SIGSTOP` or a paused VM, for a random time. What arrives meanwhile
//!   waits in its sockets, and its persistence thread and encoder stop with it; when it
//!   runs again its timer fires first (the worst case: the tile scheduler sees the gap
//!   before any message), then it reads the backlog in order.
//! - **Links**: a one-way latency (base plus jitter) per message, in order per direction
//!   (TCP).
//! - **Network cuts** (a Poisson process per machine, off by default): for a random
//!   time nothing crosses between the machine and the coordinator in either direction;
//!   TCP delivers what was sent during the cut once it heals. A cut longer than the
//!   heartbeat timeout gets the worker dropped; it reads the close after the cut and
//!   reconnects under its name.
//! - **Workers**: `threads` rendering slots fed first-in first-out from the tiles
//!   received; a tile of a job cancelled before it starts is skipped; a heartbeat every
//!   second from the moment the handshake is accepted; when the coordinator closes the
//!   connection the worker drops its queue (the tiles being rendered finish, unsent) and
//!   reconnects after 100 ms × [0.5, 1) as a new worker under the same machine name.
//! - **Failures**: crashes (the process dies; its connection closes after a latency;
//!   with [`SimConfig::restart_after_ms`] its supervisor starts it again after that
//!   delay, under the same machine name, as systemd or Kubernetes would) and
//!   hangs (the whole process stops, as with `SIGSTOP`, for a random time: its renders
//!   pause, messages wait in its socket, no heartbeats; if the coordinator dropped it
//!   meanwhile it finds the connection closed when it wakes, and reconnects), each a
//!   Poisson process per machine; and render hangs (only the render threads stop, for
//!   a random time: renders pause and none starts, while heartbeats, messages and the
//!   queue go on, so that only the scheduler's progress check can tell), a Poisson
//!   process per machine too; new machines join as a Poisson process for the farm.
//! - **Work**: a tile's cost is its area times a per-frame cost map (smooth hot regions,
//!   like a glass object, up to `hotspot_factor` times the base cost, and a per-tile
//!   random factor); a worker renders it in cost / speed of one of its threads.
//!
//! What is not: bandwidth (scenes and results cross the network instantly whatever
//! their size), image assembly, the daemon's bookkeeping around the two machines, a
//! frozen disk (whose writes hang rather than fail, caught by the daemon's stall
//! check), restarts of the coordinator, failed tiles (`TileFailed`), draining,
//! cancellations and deletions asked by clients (deletions after the retention are
//! modelled), and priorities (every job has priority 0).

mod agenda;
mod alloc;
mod config;
mod jobs;
mod leases;
mod measure;
mod metered;
mod passes;
mod report;
mod rng;
mod workers;
mod writer;

use std::collections::{BTreeMap, BTreeSet};
use std::time::Instant;

use protocol::{JobId, WorkerId};

use crate::farm::{Effect, Farm, Input};
use crate::lifecycle::{self, Lifecycle};
use crate::tiles::{Action, Event, Millis, Scheduler};

use agenda::{Agenda, Down, Ev, Scheduled, Up};
pub use alloc::{counting, live_bytes, CountingAlloc};
pub use config::{scaling_runs, MachineClass, SimConfig};
use jobs::{scene_of, tile_costs, SimJob};
use leases::{AssignKind, LeaseModel};
use metered::{Cost, Metered, EVENT_KINDS};
use passes::SimPasses;
pub use report::{EventCost, LastTile, Memory, Outcome, SimReport};
use rng::Rng;
use workers::{Life, Machine};
use writer::{Write, Writer};

/// Runs the simulation. Panics if the configuration does not [validate](SimConfig::validate).
///
/// The memory figures need [`CountingAlloc`] as the program's global allocator; without
/// it the report's `memory` is `None`.
pub fn run(config: &SimConfig) -> SimReport {
    if let Err(e) = config.validate() {
        panic!("invalid simulation: {e}");
    }
    let started = Instant::now();
    let mut sim = Sim::new(config);
    let memory = counting().then(|| sim.probe_memory());
    sim.run();
    sim.into_report(memory, started.elapsed())
}

// ---------------------------------------------------------------------------------------
// Virtual time and random streams.

/// Virtual microseconds since the start of the run.
type Micros = u64;

const MS: Micros = 1_000;

/// Random streams, one per purpose.
const STREAM_MACHINES: u64 = 1;
const STREAM_TILES: u64 = 2;
const STREAM_FAILURES: u64 = 3;
const STREAM_NETWORK: u64 = 4;
const STREAM_JOINS: u64 = 5;
const STREAM_PAUSES: u64 = 6;
const STREAM_CUTS: u64 = 7;
const STREAM_STORAGE: u64 = 8;

/// One connection (one worker session), seen from both ends.
#[derive(Default)]
struct Conn {
    machine: usize,
    /// The scheduler's id, once the coordinator has the hello.
    worker: Option<WorkerId>,
    /// The coordinator no longer reads it.
    coordinator_closed: bool,
    left_reported: bool,
    /// The worker side ended this session.
    worker_closed: bool,
    welcomed: bool,
    cancelled: BTreeSet<JobId>,
    /// Arrival time of the last message each way, to keep them in order.
    up_last: Micros,
    down_last: Micros,
}

// ---------------------------------------------------------------------------------------
// The engine.

struct Sim<'a> {
    cfg: &'a SimConfig,
    now: Micros,
    agenda: Agenda,
    machines: Vec<Machine>,
    conns: Vec<Conn>,
    jobs: Vec<SimJob>,
    /// The index in `jobs` of each job id the lifecycle gave (`usize::MAX`: none).
    by_id: Vec<usize>,
    core: Metered,
    writer: Writer,
    /// The disk fails every write, and how many outages began.
    disk_down: bool,
    disk_epoch: u64,
    /// Write times, in virtual microseconds.
    row_write: Micros,
    image_encode: Micros,
    image_write: Micros,
    /// The daemon's table of connected workers.
    worker_conn: BTreeMap<WorkerId, usize>,
    next_worker: WorkerId,
    model: LeaseModel,
    machines_rng: Rng,
    failures_rng: Rng,
    network_rng: Rng,
    joins_rng: Rng,
    pauses_rng: Rng,
    cuts_rng: Rng,
    storage_rng: Rng,
    /// When the daemon's timer is armed for (the earliest wake pending), if it is.
    wake_at: Option<Micros>,
    /// A `Continue` is on the agenda for the core's hand-out cut short.
    continuing: bool,
    /// The coordinator is stopped: what it should handle waits here, in order.
    paused: bool,
    backlog: Vec<Ev>,
    /// (time, change) of the farm's rendering capacity, in reference threads.
    capacity: Vec<(Micros, f64)>,
    next_render: u64,
    jobs_open: usize,
    out: Outcome,
}

impl<'a> Sim<'a> {
    fn new(cfg: &'a SimConfig) -> Sim<'a> {
        let mut tiles_rng = Rng::new(cfg.seed, STREAM_TILES);
        let jobs = (0..cfg.jobs)
            .map(|j| {
                let costs = tile_costs(cfg, &mut tiles_rng);
                SimJob {
                    accepted: vec![0; costs.len()],
                    assigned: vec![0; costs.len()],
                    last_sent: vec![0; costs.len()],
                    passes: (j < cfg.jobs_in_passes).then(|| SimPasses::new(costs.len())),
                    costs,
                    sent: j as Micros * cfg.job_interval_ms * MS,
                    id: None,
                    started: false,
                    tiles_ended: None,
                    ended: None,
                }
            })
            .collect();
        let mut sim = Sim {
            cfg,
            now: 0,
            agenda: Agenda::default(),
            machines: Vec::new(),
            conns: Vec::new(),
            jobs,
            by_id: Vec::new(),
            core: Metered {
                core: Farm::new(
                    Scheduler::with_policy(cfg.policy),
                    Lifecycle::new(cfg.limits, 1),
                ),
                bytes: 0,
                peak: 0,
                costs: [Cost::default(); EVENT_KINDS.len()],
                admit: Cost::default(),
                job_costs: Vec::new(),
            },
            writer: Writer::default(),
            disk_down: false,
            disk_epoch: 0,
            row_write: micros(cfg.storage_write_ms),
            image_encode: micros(cfg.image_encode_ms),
            image_write: micros(cfg.image_write_ms),
            worker_conn: BTreeMap::new(),
            next_worker: 1,
            model: LeaseModel {
                policy: cfg.policy,
                ..LeaseModel::default()
            },
            machines_rng: Rng::new(cfg.seed, STREAM_MACHINES),
            failures_rng: Rng::new(cfg.seed, STREAM_FAILURES),
            network_rng: Rng::new(cfg.seed, STREAM_NETWORK),
            joins_rng: Rng::new(cfg.seed, STREAM_JOINS),
            pauses_rng: Rng::new(cfg.seed, STREAM_PAUSES),
            cuts_rng: Rng::new(cfg.seed, STREAM_CUTS),
            storage_rng: Rng::new(cfg.seed, STREAM_STORAGE),
            wake_at: None,
            continuing: false,
            paused: false,
            backlog: Vec::new(),
            capacity: Vec::new(),
            next_render: 0,
            jobs_open: cfg.jobs,
            out: Outcome {
                workers_initial: cfg.workers,
                jobs: cfg.jobs,
                ..Outcome::default()
            },
        };
        for _ in 0..cfg.workers {
            let m = sim.new_machine();
            sim.agenda.push(0, Ev::Boot { machine: m });
        }
        for job in 0..cfg.jobs {
            let at = sim.jobs[job].sent + sim.latency();
            sim.agenda.push(at, Ev::Submit { job });
        }
        if cfg.joins_per_minute > 0.0 {
            let gap = sim.join_gap();
            sim.agenda.push(gap, Ev::NextJoin);
        }
        sim.arm_coordinator_pause();
        sim.arm_storage_outage();
        sim
    }

    fn latency(&mut self) -> Micros {
        let ms = self.cfg.latency_ms + self.cfg.latency_jitter_ms * self.network_rng.unit();
        (ms * MS as f64).round() as Micros
    }

    fn join_gap(&mut self) -> Micros {
        let mean = 60_000.0 * MS as f64 / self.cfg.joins_per_minute;
        (self.joins_rng.exponential(mean).round() as Micros).max(1)
    }

    /// When a message sent now over the connection arrives: after the latency, after
    /// the messages sent before it, and not before a cut of its machine heals.
    fn arrival(&mut self, conn: usize, last: Micros) -> Micros {
        let latency = self.latency();
        let cut = self.machines[self.conns[conn].machine].cut_until;
        (self.now.max(cut) + latency).max(last)
    }

    fn send_up(&mut self, conn: usize, msg: Up) {
        let at = self.arrival(conn, self.conns[conn].up_last);
        self.conns[conn].up_last = at;
        self.agenda.push(at, Ev::Arrival { conn, msg });
    }

    fn send_down(&mut self, conn: usize, msg: Down) {
        let at = self.arrival(conn, self.conns[conn].down_last);
        self.conns[conn].down_last = at;
        self.agenda.push(at, Ev::Delivery { conn, msg });
    }

    fn run(&mut self) {
        let limit = self.cfg.max_virtual_ms * MS;
        loop {
            let Some(Scheduled { at, ev, .. }) = self.agenda.heap.pop() else {
                // Nothing can happen any more, and jobs are left.
                self.out.timed_out = true;
                break;
            };
            if at > limit {
                self.out.timed_out = true;
                self.now = limit;
                break;
            }
            self.now = at;
            if self.paused && ev.at_coordinator() {
                self.backlog.push(ev);
            } else {
                self.dispatch(ev);
            }
            if self.jobs_open == 0 {
                break;
            }
        }
    }

    /// Hands one input to the decision core at the current virtual time, brings the
    /// lease account to the scheduler's clock, and re-arms the daemon's timer for the
    /// core's next deadline, as the daemon does after every call.
    fn handle(&mut self, input: Input) -> Vec<Effect> {
        let effects = self.core.handle(self.now / MS, input);
        self.model.now = self.model.now.max(self.core.core.tiles().clock());
        self.arm_wake(self.core.core.next_deadline());
        if self.core.core.has_more() && !std::mem::replace(&mut self.continuing, true) {
            self.agenda.push(self.now, Ev::Continue);
        }
        effects
    }

    /// Hands one input to the decision core and carries out its effects.
    fn feed(&mut self, input: Input) {
        let effects = self.handle(input);
        self.apply(effects, None);
    }

    /// [`Sim::feed`] for an input about jobs.
    fn life(&mut self, event: lifecycle::Event) {
        self.feed(Input::Job(event));
    }

    /// The daemon's timer fires at the earliest deadline either machine gave.
    fn arm_wake(&mut self, deadline: Option<Millis>) {
        if let Some(deadline) = deadline {
            // With the daemon's timer slack.
            let at = (crate::wake_time(deadline) * MS).max(self.now);
            if self.wake_at.is_none_or(|armed| at < armed) {
                self.wake_at = Some(at);
                self.agenda.push(at, Ev::Wake);
            }
        }
    }

    /// The daemon's timer fires: a `Timeout` for the core (the tile scheduler, then
    /// the lifecycle). (Only the earliest armed wake counts; one superseded by an
    /// earlier deadline is void, and a later deadline is re-armed by the calls.)
    fn timeout(&mut self) {
        self.wake_at = None;
        self.out.timeouts += 1;
        // The scheduler drops silent workers before it looks at leases; the model
        // expires leases once those drops are applied (see `apply`).
        let effects = self.handle(Input::Timeout);
        let clock = self.core.core.tiles().clock();
        self.apply(effects, Some(clock));
    }

    fn dispatch(&mut self, ev: Ev) {
        match ev {
            Ev::Wake => {
                if self.wake_at == Some(self.now) {
                    self.timeout();
                }
            }
            Ev::Continue => {
                self.continuing = false;
                // It goes on with the checks a call left at its bound, leases that
                // ran out meanwhile included: as for a timeout, the account expires
                // them before the first assignment.
                let effects = self.handle(Input::Tiles(Event::Continue));
                let clock = self.core.core.tiles().clock();
                self.apply(effects, Some(clock));
            }
            Ev::CoordinatorPause => {
                self.paused = true;
                self.out.coordinator_pauses += 1;
                let span = self.pauses_rng.range(
                    self.cfg.coordinator_pause_min_ms as f64,
                    self.cfg.coordinator_pause_max_ms as f64,
                );
                self.agenda.push(
                    self.now + (span * MS as f64).round() as Micros,
                    Ev::CoordinatorResume,
                );
            }
            Ev::CoordinatorResume => {
                self.paused = false;
                // Its timer is long overdue and fires first; then it reads what waited.
                self.timeout();
                for ev in std::mem::take(&mut self.backlog) {
                    if !matches!(ev, Ev::Wake) {
                        self.dispatch(ev);
                    }
                }
                self.arm_coordinator_pause();
            }
            Ev::Restart { machine } => {
                let m = &mut self.machines[machine];
                if m.life == Life::Dead {
                    m.life = Life::Running;
                    m.epoch += 1;
                    self.out.restarts += 1;
                    let capacity = m.capacity();
                    self.capacity.push((self.now, capacity));
                    self.arm_failures(machine);
                    self.connect(machine);
                }
            }
            Ev::Cut { machine } => {
                if self.machines[machine].life == Life::Dead && self.cfg.restart_after_ms.is_none()
                {
                    // The machine is gone for good: its chain of cuts ends.
                    return;
                }
                let span = self
                    .cuts_rng
                    .range(self.cfg.cut_min_ms as f64, self.cfg.cut_max_ms as f64);
                let until = self.now + (span * MS as f64).round() as Micros;
                self.machines[machine].cut_until = until;
                self.out.network_cuts += 1;
                self.arm_cut(machine, until);
            }
            Ev::Submit { job } => self.submit(job),
            Ev::WriteDone => self.write_done(),
            Ev::WriteRetry => self.attempt_write(),
            Ev::ImageEncoded { job } => self.persist(Write::Image(job)),
            Ev::PassAddedUp { job, pass, rungs } => self.pass_added_up(job, pass, rungs),
            Ev::StorageOutage => {
                self.disk_down = true;
                self.disk_epoch += 1;
                self.out.storage_outages += 1;
                let span = self.storage_rng.range(
                    self.cfg.storage_outage_min_ms as f64,
                    self.cfg.storage_outage_max_ms as f64,
                );
                self.agenda
                    .push(self.now + micros(span), Ev::StorageRecovered);
            }
            Ev::StorageRecovered => {
                self.disk_down = false;
                self.arm_storage_outage();
            }
            Ev::Boot { machine } => {
                let m = &mut self.machines[machine];
                m.life = Life::Running;
                let capacity = m.capacity();
                self.capacity.push((self.now, capacity));
                self.arm_failures(machine);
                self.arm_cut(machine, self.now);
                self.connect(machine);
            }
            Ev::Reconnect { machine } => match self.machines[machine].life {
                Life::Running => self.connect(machine),
                Life::Frozen => self.machines[machine].reconnect_on_thaw = true,
                Life::Off | Life::Dead => {}
            },
            Ev::NextJoin => {
                let machine = self.new_machine();
                self.out.workers_joined += 1;
                self.agenda.push(self.now, Ev::Boot { machine });
                let gap = self.join_gap();
                self.agenda.push(self.now + gap, Ev::NextJoin);
            }
            Ev::Arrival { conn, msg } => self.at_coordinator(conn, msg),
            Ev::Delivery { conn, msg } => {
                let machine = self.conns[conn].machine;
                match self.machines[machine].life {
                    Life::Running => self.at_worker(conn, msg),
                    Life::Frozen => self.machines[machine].inbox.push((conn, msg)),
                    Life::Off | Life::Dead => {}
                }
            }
            Ev::ConnectionTaskLeft { conn } => self.worker_left(conn),
            Ev::RenderDone {
                machine,
                epoch,
                render,
            } => self.render_done(machine, epoch, render),
            Ev::HeartbeatTimer {
                machine,
                epoch,
                conn,
            } => {
                let m = &self.machines[machine];
                if m.life == Life::Running
                    && m.epoch == epoch
                    && m.conn == Some(conn)
                    && !self.conns[conn].worker_closed
                {
                    self.send_up(conn, Up::Heartbeat);
                    self.agenda.push(
                        self.now + self.cfg.heartbeat_ms * MS,
                        Ev::HeartbeatTimer {
                            machine,
                            epoch,
                            conn,
                        },
                    );
                }
            }
            Ev::Crash { machine, epoch } => self.crash(machine, epoch),
            Ev::Hang { machine, epoch } => self.hang(machine, epoch),
            Ev::Thaw { machine } => self.thaw(machine),
            Ev::RenderHang { machine, epoch } => self.render_hang(machine, epoch),
            Ev::RenderThaw { machine } => self.render_thaw(machine),
        }
    }

    // --- the coordinator's side ------------------------------------------------------

    fn at_coordinator(&mut self, conn: usize, msg: Up) {
        if self.conns[conn].coordinator_closed {
            if let Up::TileDone { .. } = msg {
                self.out.results_unread += 1;
            }
            return;
        }
        match msg {
            Up::Hello => {
                let worker = self.next_worker;
                self.next_worker += 1;
                self.conns[conn].worker = Some(worker);
                self.worker_conn.insert(worker, conn);
                // `Accepted` goes out before anything the scheduler sends.
                self.send_down(conn, Down::Welcome);
                let machine = self.conns[conn].machine;
                let threads = self.machines[machine].threads;
                self.feed(Input::Tiles(Event::WorkerJoined {
                    worker,
                    threads,
                    machine: Some(format!("machine-{machine}")),
                }));
            }
            Up::Heartbeat => {
                let worker = self.conns[conn].worker.expect("hello first");
                self.feed(Input::Tiles(Event::Heartbeat { worker }));
            }
            Up::TileDone {
                job,
                tile,
                sent,
                started,
            } => {
                let worker = self.conns[conn].worker.expect("hello first");
                let held = self.model.holds(worker, job, tile);
                let effects = self.handle(Input::Tiles(Event::TileDone { worker, job, tile }));
                let accepted = effects.contains(&Effect::Tiles(Action::AcceptTile { job, tile }));
                let duplicate =
                    effects.contains(&Effect::Tiles(Action::DuplicateResult { job, tile }));
                if held != accepted {
                    self.out.model_mismatches += 1;
                }
                if accepted {
                    self.model.accepted(worker, job, tile);
                    let j = &self.jobs[self.slot(job)];
                    self.out.last_tile = Some(LastTile {
                        job,
                        tile,
                        cost_ms: j.costs[tile as usize] as f64 / MS as f64,
                        assignments: u32::from(j.assigned[tile as usize]),
                        last_assigned_ms: j.last_sent[tile as usize] as f64 / MS as f64,
                        thread_speed: self.machines[self.conns[conn].machine].speed,
                        assigned_ms: sent as f64 / MS as f64,
                        started_ms: started as f64 / MS as f64,
                        accepted_ms: self.now as f64 / MS as f64,
                    });
                } else if !duplicate {
                    self.out.stray_results += 1;
                }
                self.apply(effects, None);
            }
            Up::Closed => {
                self.conns[conn].coordinator_closed = true;
                self.worker_left(conn);
            }
        }
    }

    /// The daemon's end of a connection: `WorkerLeft`, once.
    fn worker_left(&mut self, conn: usize) {
        if std::mem::replace(&mut self.conns[conn].left_reported, true) {
            return;
        }
        let Some(worker) = self.conns[conn].worker else {
            return;
        };
        self.worker_conn.remove(&worker);
        self.model.remove_worker(worker);
        self.feed(Input::Tiles(Event::WorkerLeft { worker }));
    }

    /// Carries out the core's effects as the daemon does. `timeout`: the scheduler's
    /// clock at a `Timeout` whose lease expiries the model still has to apply (before
    /// its first assignment, after its drops).
    fn apply(&mut self, effects: Vec<Effect>, mut timeout: Option<Millis>) {
        for effect in effects {
            let action = match effect {
                Effect::Tiles(action) => action,
                Effect::Job(action) => {
                    self.apply_life(action);
                    continue;
                }
                Effect::Pass(action) => {
                    self.apply_pass(action);
                    continue;
                }
                // The simulated workers are honest: nothing is taken back; and the
                // simulated farm renders no sequence and submits no job after another.
                Effect::TakenBack { .. }
                | Effect::Waiting { .. }
                | Effect::Released { .. }
                | Effect::Quarantined { .. }
                | Effect::DuplicateSettled { .. }
                | Effect::Sequence(_) => {
                    self.out.model_mismatches += 1;
                    continue;
                }
            };
            match action {
                Action::SendScene { .. } => self.out.scenes_sent += 1,
                Action::Assign { worker, job, tile } => {
                    if let Some(now) = timeout.take() {
                        self.out.leases_expired += self.model.expire(now);
                    }
                    self.out.assignments += 1;
                    let slot = self.slot(job);
                    let j = &mut self.jobs[slot];
                    let first = !std::mem::replace(&mut j.started, true);
                    let before = j.assigned[tile as usize] > 0;
                    j.assigned[tile as usize] = j.assigned[tile as usize].saturating_add(1);
                    j.last_sent[tile as usize] = self.now;
                    match self.model.assign(worker, job, tile, before) {
                        AssignKind::First => {}
                        AssignKind::AfterLoss => self.out.reassigned_after_loss += 1,
                        AssignKind::AfterExpiry => self.out.reassigned_after_expiry += 1,
                        AssignKind::Speculative => self.out.speculative_copies += 1,
                        AssignKind::Unexplained => self.out.model_mismatches += 1,
                    }
                    if first {
                        self.persist(Write::Started(job));
                    }
                    match self.worker_conn.get(&worker) {
                        Some(&conn) => {
                            let sent = self.now;
                            self.send_down(conn, Down::Render { job, tile, sent });
                        }
                        None => self.out.model_mismatches += 1,
                    }
                }
                Action::AcceptTile { job, tile } => {
                    let slot = self.slot(job);
                    if let Some(p) = self.jobs[slot].passes.as_mut() {
                        p.reached[tile as usize] = Some(p.rung);
                    }
                    let count = &mut self.jobs[slot].accepted[tile as usize];
                    *count = count.saturating_add(1);
                    if *count > 1 {
                        self.out.tiles_accepted_twice += 1;
                    }
                    self.out.tiles_accepted += 1;
                    self.persist(Write::Tiles(1));
                }
                Action::DuplicateResult { .. } => self.out.duplicate_results += 1,
                // The simulated workers are honest: no result is held for confirmation.
                Action::HoldResult { .. } | Action::AcceptHeld { .. } => {
                    self.out.model_mismatches += 1
                }
                Action::CancelOnWorker { worker, job } => {
                    if let Some(&conn) = self.worker_conn.get(&worker) {
                        self.send_down(conn, Down::Cancel { job });
                    }
                }
                Action::ForgetScene { .. } => self.out.scenes_forgotten += 1,
                Action::WorkerUnresponsive { worker, .. } => {
                    // The timeout's expiries first, as the scheduler made them.
                    if let Some(now) = timeout.take() {
                        self.out.leases_expired += self.model.expire(now);
                    }
                    self.out.unresponsive += 1;
                    self.out.leases_expired += self.model.expire_worker(worker);
                }
                Action::WorkerResponsive { .. } => self.out.responsive_again += 1,
                Action::DropWorker { worker } => {
                    self.out.drops += 1;
                    self.model.remove_worker(worker);
                    if let Some(conn) = self.worker_conn.remove(&worker) {
                        self.conns[conn].coordinator_closed = true;
                        self.agenda.push(self.now, Ev::ConnectionTaskLeft { conn });
                        self.send_down(conn, Down::Close);
                    }
                }
                // The core has told the lifecycle: what it makes of it follows.
                // A job in passes: the pass is added up next.
                Action::JobDone { job } if self.jobs[self.slot(job)].passes.is_some() => {
                    self.model.end_job(job);
                }
                Action::JobDone { job } => self.tiles_ended(job, true),
                Action::JobFailed { job, .. } => self.tiles_ended(job, false),
            }
        }
        if let Some(now) = timeout {
            self.out.leases_expired += self.model.expire(now);
        }
    }

    /// The tile scheduler is done with the job (every tile in, or failed).
    pub(super) fn tiles_ended(&mut self, job: JobId, done: bool) {
        let slot = self.slot(job);
        let j = &mut self.jobs[slot];
        if j.tiles_ended.is_some() {
            self.out.model_mismatches += 1;
            return;
        }
        j.tiles_ended = Some(self.now);
        if done {
            self.out.tiles_missing += j.accepted.iter().filter(|&&c| c == 0).count() as u64;
        }
        self.model.end_job(job);
    }

    /// The index in `jobs` of a job id the lifecycle gave.
    fn slot(&self, job: JobId) -> usize {
        self.by_id[job as usize]
    }

    /// The coordinator's next pause (Poisson), while it runs.
    fn arm_coordinator_pause(&mut self) {
        if self.cfg.coordinator_pauses_per_hour > 0.0 {
            let hour = 3_600_000.0 * MS as f64;
            let after = self
                .pauses_rng
                .exponential(hour / self.cfg.coordinator_pauses_per_hour);
            self.agenda
                .push(self.now + after.round() as Micros, Ev::CoordinatorPause);
        }
    }
}

/// Virtual microseconds of a time in milliseconds.
fn micros(ms: f64) -> Micros {
    (ms * MS as f64).round() as Micros
}
