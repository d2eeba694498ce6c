//! The workers' side of the farm: the simulated machines, their sessions as seen from
//! the worker, the rendering slots fed from the tiles received, and what goes wrong on
//! a machine (crashes, hangs of the whole process or of its render threads, network
//! cuts). Everything here stands for the worker binary and its host, never for the
//! coordinator, whose side is the engine's.

use std::collections::VecDeque;

use protocol::JobId;

use super::{Conn, Down, Ev, Micros, Sim, Up, MS};

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Life {
    /// Not started yet.
    Off,
    Running,
    Frozen,
    Dead,
}

struct Task {
    conn: usize,
    job: JobId,
    tile: u32,
    sent: Micros,
}

struct Render {
    id: u64,
    conn: usize,
    job: JobId,
    tile: u32,
    /// Reference-thread microseconds of the tile.
    cost: Micros,
    sent: Micros,
    started: Micros,
    end: Micros,
    /// While frozen: what was left to render.
    remaining: Micros,
}

pub(super) struct Machine {
    pub(super) threads: u32,
    pub(super) speed: f64,
    pub(super) life: Life,
    /// Bumped on every freeze, thaw and crash: events of an older epoch are void.
    pub(super) epoch: u32,
    pub(super) conn: Option<usize>,
    queue: VecDeque<Task>,
    running: Vec<Render>,
    /// Messages that arrived while the process was stopped.
    pub(super) inbox: Vec<(usize, Down)>,
    /// Its render threads are stopped (a render hang): renders neither progress nor
    /// start, while heartbeats and messages go on.
    renders_hung: bool,
    pub(super) reconnect_on_thaw: bool,
    /// Nothing crosses the network to or from it before this time.
    pub(super) cut_until: Micros,
}

impl Machine {
    pub(super) fn capacity(&self) -> f64 {
        f64::from(self.threads) * self.speed
    }
}

impl Sim<'_> {
    pub(super) fn new_machine(&mut self) -> usize {
        let total: f64 = self.cfg.classes.iter().map(|c| c.share).sum();
        let mut pick = self.machines_rng.unit() * total;
        let class = self
            .cfg
            .classes
            .iter()
            .find(|c| {
                pick -= c.share;
                pick < 0.0
            })
            .unwrap_or(&self.cfg.classes[self.cfg.classes.len() - 1]);
        let spread = self.cfg.speed_spread;
        let speed = class.speed * self.machines_rng.range(1.0 - spread, 1.0 + spread);
        self.machines.push(Machine {
            threads: class.threads,
            speed,
            life: Life::Off,
            epoch: 0,
            conn: None,
            queue: VecDeque::new(),
            running: Vec::new(),
            inbox: Vec::new(),
            renders_hung: false,
            reconnect_on_thaw: false,
            cut_until: 0,
        });
        self.machines.len() - 1
    }

    pub(super) fn connect(&mut self, machine: usize) {
        self.conns.push(Conn {
            machine,
            ..Conn::default()
        });
        let conn = self.conns.len() - 1;
        self.machines[machine].conn = Some(conn);
        self.send_up(conn, Up::Hello);
    }

    pub(super) fn at_worker(&mut self, conn: usize, msg: Down) {
        if self.conns[conn].worker_closed {
            return;
        }
        let machine = self.conns[conn].machine;
        match msg {
            Down::Welcome => {
                self.conns[conn].welcomed = true;
                let epoch = self.machines[machine].epoch;
                // The worker's interval fires at once, then every period.
                self.agenda.push(
                    self.now,
                    Ev::HeartbeatTimer {
                        machine,
                        epoch,
                        conn,
                    },
                );
            }
            Down::Render { job, tile, sent } => {
                self.machines[machine].queue.push_back(Task {
                    conn,
                    job,
                    tile,
                    sent,
                });
                self.start_renders(machine);
            }
            Down::Cancel { job } => {
                self.conns[conn].cancelled.insert(job);
            }
            Down::Close => {
                // The session ends: queued tiles are never rendered, the ones being
                // rendered finish unsent; the worker reconnects after its backoff.
                self.conns[conn].worker_closed = true;
                let m = &mut self.machines[machine];
                if m.conn == Some(conn) {
                    m.conn = None;
                }
                let before = m.queue.len();
                m.queue.retain(|t| t.conn != conn);
                self.out.tasks_skipped += (before - m.queue.len()) as u64;
                let delay =
                    self.cfg.reconnect_ms as f64 * MS as f64 * self.network_rng.range(0.5, 1.0);
                self.out.reconnects += 1;
                self.agenda.push(
                    self.now + delay.round() as Micros,
                    Ev::Reconnect { machine },
                );
            }
        }
    }

    fn start_renders(&mut self, machine: usize) {
        let m = &mut self.machines[machine];
        while !m.renders_hung && m.running.len() < m.threads as usize {
            let Some(task) = m.queue.pop_front() else {
                break;
            };
            let conn = &self.conns[task.conn];
            if conn.worker_closed || conn.cancelled.contains(&task.job) {
                self.out.tasks_skipped += 1;
                continue;
            }
            let cost = self.jobs[self.by_id[task.job as usize]].cost(task.tile);
            let took = ((cost as f64 / m.speed).round() as Micros).max(1);
            let id = self.next_render;
            self.next_render += 1;
            m.running.push(Render {
                id,
                conn: task.conn,
                job: task.job,
                tile: task.tile,
                cost,
                sent: task.sent,
                started: self.now,
                end: self.now + took,
                remaining: 0,
            });
            self.out.renders_started += 1;
            self.agenda.push(
                self.now + took,
                Ev::RenderDone {
                    machine,
                    epoch: m.epoch,
                    render: id,
                },
            );
        }
    }

    pub(super) fn render_done(&mut self, machine: usize, epoch: u32, render: u64) {
        let m = &mut self.machines[machine];
        if m.epoch != epoch || m.life != Life::Running {
            return;
        }
        if m.renders_hung {
            return;
        }
        // A render moved by a render hang has a later end: its first event is stale.
        let Some(pos) = m
            .running
            .iter()
            .position(|r| r.id == render && r.end == self.now)
        else {
            return;
        };
        let r = m.running.swap_remove(pos);
        self.out.renders_completed += 1;
        self.out.work_spent_ms += r.cost as f64 / MS as f64;
        if m.conn == Some(r.conn) && !self.conns[r.conn].worker_closed {
            self.send_up(
                r.conn,
                Up::TileDone {
                    job: r.job,
                    tile: r.tile,
                    sent: r.sent,
                    started: r.started,
                },
            );
        } else {
            self.out.renders_orphaned += 1;
        }
        self.start_renders(machine);
    }

    pub(super) fn arm_failures(&mut self, machine: usize) {
        let epoch = self.machines[machine].epoch;
        let hour = 3_600_000.0 * MS as f64;
        if self.cfg.crashes_per_worker_hour > 0.0 {
            let after = self
                .failures_rng
                .exponential(hour / self.cfg.crashes_per_worker_hour);
            self.agenda.push(
                self.now + after.round() as Micros,
                Ev::Crash { machine, epoch },
            );
        }
        if self.cfg.hangs_per_worker_hour > 0.0 {
            let after = self
                .failures_rng
                .exponential(hour / self.cfg.hangs_per_worker_hour);
            self.agenda.push(
                self.now + after.round() as Micros,
                Ev::Hang { machine, epoch },
            );
        }
        if !self.machines[machine].renders_hung {
            // (A machine whose renders hang arms its next render hang when they run.)
            self.arm_render_hang(machine);
        }
    }

    /// The machine's next render hang (Poisson).
    fn arm_render_hang(&mut self, machine: usize) {
        if self.cfg.render_hangs_per_worker_hour > 0.0 {
            let hour = 3_600_000.0 * MS as f64;
            let epoch = self.machines[machine].epoch;
            let after = self
                .failures_rng
                .exponential(hour / self.cfg.render_hangs_per_worker_hour);
            self.agenda.push(
                self.now + after.round() as Micros,
                Ev::RenderHang { machine, epoch },
            );
        }
    }

    pub(super) fn crash(&mut self, machine: usize, epoch: u32) {
        let now = self.now;
        let m = &mut self.machines[machine];
        if m.epoch != epoch || m.life != Life::Running {
            return;
        }
        m.life = Life::Dead;
        m.epoch += 1;
        self.out.crashes += 1;
        if !std::mem::replace(&mut m.renders_hung, false) {
            // (A render hang already took its capacity.)
            self.capacity.push((now, -m.capacity()));
        }
        for r in m.running.drain(..) {
            self.out.renders_interrupted += 1;
            self.out.work_spent_ms += (now - r.started) as f64 * m.speed / MS as f64;
        }
        m.queue.clear();
        if let Some(conn) = m.conn.take() {
            self.send_up(conn, Up::Closed);
        }
        if let Some(after) = self.cfg.restart_after_ms {
            self.agenda.push(now + after * MS, Ev::Restart { machine });
        }
    }

    /// The machine's next network cut, after `from` (Poisson).
    pub(super) fn arm_cut(&mut self, machine: usize, from: Micros) {
        if self.cfg.cuts_per_worker_hour > 0.0 {
            let hour = 3_600_000.0 * MS as f64;
            let after = self
                .cuts_rng
                .exponential(hour / self.cfg.cuts_per_worker_hour);
            self.agenda
                .push(from + after.round() as Micros, Ev::Cut { machine });
        }
    }

    pub(super) fn hang(&mut self, machine: usize, epoch: u32) {
        let now = self.now;
        let m = &mut self.machines[machine];
        if m.epoch != epoch || m.life != Life::Running {
            return;
        }
        m.life = Life::Frozen;
        m.epoch += 1;
        self.out.hangs += 1;
        if !m.renders_hung {
            // (A render hang already took its capacity and froze its renders.)
            self.pause_renders(machine);
        }
        let at = now + self.failure_span(self.cfg.hang_min_ms, self.cfg.hang_max_ms);
        self.agenda.push(at, Ev::Thaw { machine });
    }

    /// A duration uniform in [min, max) ms, in µs, from the failures' generator.
    fn failure_span(&mut self, min_ms: u64, max_ms: u64) -> Micros {
        let span = self.failures_rng.range(min_ms as f64, max_ms as f64);
        (span * MS as f64).round() as Micros
    }

    /// The machine's renders stop where they are (a hang of the process or of its render
    /// threads), and its capacity leaves the farm's.
    fn pause_renders(&mut self, machine: usize) {
        let now = self.now;
        let m = &mut self.machines[machine];
        self.capacity.push((now, -m.capacity()));
        for r in &mut m.running {
            r.remaining = r.end - now;
        }
    }

    /// The machine's paused renders go on from where they stopped, and its capacity
    /// comes back.
    fn resume_renders(&mut self, machine: usize) {
        let now = self.now;
        let m = &mut self.machines[machine];
        let epoch = m.epoch;
        self.capacity.push((now, m.capacity()));
        for r in &mut m.running {
            // The pause shifts the render; its start moves with it, so that work done
            // counts only time running.
            r.started += now - (r.end - r.remaining);
            r.end = now + r.remaining;
            self.agenda.push(
                r.end,
                Ev::RenderDone {
                    machine,
                    epoch,
                    render: r.id,
                },
            );
        }
    }

    pub(super) fn thaw(&mut self, machine: usize) {
        let now = self.now;
        let m = &mut self.machines[machine];
        if m.life != Life::Frozen {
            return;
        }
        m.life = Life::Running;
        m.epoch += 1;
        let epoch = m.epoch;
        if !m.renders_hung {
            self.resume_renders(machine);
        }
        let m = &mut self.machines[machine];
        let inbox = std::mem::take(&mut m.inbox);
        let reconnect = std::mem::replace(&mut m.reconnect_on_thaw, false);
        // The heartbeat resumes at once on a session already accepted; one accepted
        // while stopped starts its own when its `Welcome` is read below.
        if let Some(conn) = m.conn.filter(|&c| self.conns[c].welcomed) {
            self.agenda.push(
                now,
                Ev::HeartbeatTimer {
                    machine,
                    epoch,
                    conn,
                },
            );
        }
        for (conn, msg) in inbox {
            self.at_worker(conn, msg);
        }
        if reconnect && self.machines[machine].conn.is_none() {
            self.connect(machine);
        }
        self.arm_failures(machine);
        self.start_renders(machine);
    }

    /// The machine's render threads stop: what they render stays where it is, nothing
    /// new starts; heartbeats, messages and the queue go on.
    pub(super) fn render_hang(&mut self, machine: usize, epoch: u32) {
        let now = self.now;
        let m = &mut self.machines[machine];
        if m.epoch != epoch || m.life != Life::Running || m.renders_hung {
            return;
        }
        m.renders_hung = true;
        self.out.render_hangs += 1;
        self.pause_renders(machine);
        let at = now + self.failure_span(self.cfg.render_hang_min_ms, self.cfg.render_hang_max_ms);
        self.agenda.push(at, Ev::RenderThaw { machine });
    }

    /// The render threads run again (if the process is running; a stopped one resumes
    /// them when it is thawed).
    pub(super) fn render_thaw(&mut self, machine: usize) {
        let m = &mut self.machines[machine];
        if !m.renders_hung || m.life == Life::Dead {
            return;
        }
        m.renders_hung = false;
        if m.life != Life::Running {
            // Stopped meanwhile: its thaw restarts the renders (and the capacity).
            return;
        }
        self.resume_renders(machine);
        self.arm_render_hang(machine);
        self.start_renders(machine);
    }
}
