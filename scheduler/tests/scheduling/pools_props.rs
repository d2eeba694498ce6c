//! Pools against random histories: workers with random tags (restarted under their
//! machine name with other tags while holding tiles), jobs with random requirements,
//! some in full verification, results coming back in random order.
//!
//! Checked:
//! - **Eligibility**: no tile (a confirmation included) ever goes to a worker lacking
//!   a tag its job requires, whatever the worker had before a restart.
//! - **Confirmation by a qualifying machine**: a full-verification tile's confirming
//!   copy goes to another machine than the one whose result is held, itself
//!   qualifying (by the rule above).
//! - **Progress**: once the workers settle, every job whose requirements some
//!   connected worker meets (two machines for full verification) is done, and no job
//!   fails: one that no connected worker qualifies for waits.

use std::collections::{BTreeMap, BTreeSet};

use proptest::prelude::*;
use protocol::{JobId, WorkerId};
use scheduler::{Action, Event, Millis, Policy, Scheduler};

const TAGS: [&str; 2] = ["gpu", "ssd"];

/// A tag set from its bits over [`TAGS`].
fn tags(bits: u8) -> Vec<String> {
    TAGS.iter()
        .enumerate()
        .filter(|(i, _)| bits & (1 << i) != 0)
        .map(|(_, t)| (*t).to_string())
        .collect()
}

#[derive(Clone, Debug)]
struct JobPlan {
    require: u8,
    tiles: u32,
    full: bool,
}

#[derive(Clone, Debug)]
enum Op {
    /// A worker (by index among the connected) returns the tile it holds (by index).
    Return(usize, usize),
    /// Machine `m` restarts with tag bits `t` (its connection goes, a new one joins).
    Restart(usize, u8),
    /// Time passes and the timer fires.
    Tick,
}

fn op() -> impl Strategy<Value = Op> {
    prop_oneof![
        6 => (any::<usize>(), any::<usize>()).prop_map(|(w, t)| Op::Return(w, t)),
        1 => (0..4usize, 0..4u8).prop_map(|(m, t)| Op::Restart(m, t)),
        1 => Just(Op::Tick),
    ]
}

/// The daemon, as far as pools are concerned: who holds what, whose result is held,
/// and each worker's tags.
struct Model {
    s: Scheduler,
    now: Millis,
    next_id: WorkerId,
    /// Connected workers: id → (machine, tag bits).
    workers: BTreeMap<WorkerId, (usize, u8)>,
    holding: BTreeMap<WorkerId, BTreeSet<(JobId, u32)>>,
    /// Held results (full verification): (job, tile) → machine.
    held: BTreeMap<(JobId, u32), usize>,
    jobs: BTreeMap<JobId, JobPlan>,
    done: BTreeSet<JobId>,
}

impl Model {
    fn apply(&mut self, event: Event) {
        self.now += 50;
        let actions = self.s.handle(self.now, event);
        for action in actions {
            match action {
                Action::Assign { worker, job, tile } => {
                    let (machine, bits) = self.workers[&worker];
                    let require = self.jobs[&job].require;
                    assert_eq!(
                        bits & require,
                        require,
                        "tile {tile} of job {job} (requires {:?}) went to worker {worker} \
                         with {:?}",
                        tags(require),
                        tags(bits)
                    );
                    if let Some(&from) = self.held.get(&(job, tile)) {
                        assert_ne!(from, machine, "a held tile went to its own machine");
                    }
                    self.holding.entry(worker).or_default().insert((job, tile));
                }
                Action::CancelOnWorker { worker, job } => {
                    if let Some(h) = self.holding.get_mut(&worker) {
                        h.retain(|(j, _)| *j != job);
                    }
                }
                Action::JobDone { job } => {
                    assert!(self.done.insert(job), "job {job} done twice");
                }
                Action::JobFailed { job, message } => {
                    panic!("job {job} failed: {message}");
                }
                Action::AcceptTile { job, tile } | Action::AcceptHeld { job, tile } => {
                    self.held.remove(&(job, tile));
                }
                Action::DropWorker { worker } => self.leave(worker),
                _ => {}
            }
        }
    }

    fn join(&mut self, machine: usize, bits: u8) {
        let worker = self.next_id;
        self.next_id += 1;
        self.workers.insert(worker, (machine, bits));
        self.apply(Event::WorkerTags {
            worker,
            tags: tags(bits),
        });
        self.apply(Event::WorkerJoined {
            worker,
            threads: 1,
            machine: Some(format!("m{machine}")),
        });
    }

    fn leave(&mut self, worker: WorkerId) {
        if self.workers.remove(&worker).is_some() {
            self.holding.remove(&worker);
            self.apply(Event::WorkerLeft { worker });
        }
    }

    /// The worker returns one tile it holds: a first result of a full-verification
    /// tile is to be confirmed, any other counts.
    fn give_back(&mut self, worker: WorkerId, job: JobId, tile: u32) {
        self.holding.get_mut(&worker).unwrap().remove(&(job, tile));
        let (machine, _) = self.workers[&worker];
        let full = self.jobs[&job].full;
        if full && !self.done.contains(&job) && !self.held.contains_key(&(job, tile)) {
            self.held.insert((job, tile), machine);
            self.apply(Event::TileToConfirm {
                worker,
                job,
                tile,
                required: true,
            });
        } else {
            self.apply(Event::TileDone { worker, job, tile });
        }
    }

    fn step(&mut self, op: &Op) {
        match *op {
            Op::Return(w, t) => {
                let ids: Vec<WorkerId> = self.workers.keys().copied().collect();
                if ids.is_empty() {
                    return;
                }
                let worker = ids[w % ids.len()];
                let held: Vec<(JobId, u32)> = self
                    .holding
                    .get(&worker)
                    .into_iter()
                    .flatten()
                    .copied()
                    .collect();
                if let Some(&(job, tile)) = held.get(t % held.len().max(1)) {
                    self.give_back(worker, job, tile);
                }
            }
            Op::Restart(m, bits) => {
                let old: Vec<WorkerId> = self
                    .workers
                    .iter()
                    .filter(|(_, (machine, _))| *machine == m)
                    .map(|(&id, _)| id)
                    .collect();
                for id in old {
                    self.leave(id);
                }
                self.join(m, bits);
            }
            Op::Tick => self.apply(Event::Timeout),
        }
    }
}

fn run(machines: Vec<u8>, plans: Vec<JobPlan>, ops: Vec<Op>) {
    let policy = Policy {
        // Restarts lose tiles with their workers; histories are not about that limit.
        max_losses: u32::MAX,
        ..Policy::default()
    };
    let mut m = Model {
        s: Scheduler::with_policy(policy),
        now: 0,
        next_id: 1,
        workers: BTreeMap::new(),
        holding: BTreeMap::new(),
        held: BTreeMap::new(),
        jobs: BTreeMap::new(),
        done: BTreeSet::new(),
    };
    for (i, &bits) in machines.iter().enumerate() {
        m.join(i, bits);
    }
    for (i, plan) in plans.into_iter().enumerate() {
        let job = i as JobId + 1;
        m.jobs.insert(job, plan.clone());
        m.apply(Event::RequireTags {
            job,
            tags: tags(plan.require),
        });
        m.apply(Event::JobSubmitted {
            job,
            priority: 0,
            scene: [i as u8; 32],
            tiles: plan.tiles,
        });
    }
    for op in &ops {
        m.step(op);
    }
    // The workers settle: every result comes back, in worker order, until none is out
    // even after a timeout (which fills the workers a finished job's end freed).
    for _ in 0..10_000 {
        let next = m
            .holding
            .iter()
            .find_map(|(&w, h)| h.first().map(|&(j, t)| (w, j, t)));
        match next {
            Some((worker, job, tile)) => m.give_back(worker, job, tile),
            None => {
                m.apply(Event::Timeout);
                if m.holding.values().all(BTreeSet::is_empty) {
                    break;
                }
            }
        }
    }
    let machine_tags: BTreeMap<usize, u8> = m.workers.values().copied().collect();
    for (&job, plan) in &m.jobs {
        let qualifying = machine_tags
            .values()
            .filter(|&&bits| bits & plan.require == plan.require)
            .count();
        let needed = if plan.full { 2 } else { 1 };
        if qualifying >= needed {
            assert!(
                m.done.contains(&job),
                "job {job} {plan:?} not done with {machine_tags:?}"
            );
        } else if qualifying == 0 && !m.done.contains(&job) {
            // (Workers that qualified before a restart may have finished it.)
            assert!(
                m.s.is_active(job),
                "job {job} waits for a qualifying worker"
            );
        }
    }
}

fn job_plan() -> impl Strategy<Value = JobPlan> {
    (0..4u8, 1..6u32, any::<bool>()).prop_map(|(require, tiles, full)| JobPlan {
        require,
        tiles,
        full,
    })
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 256, ..ProptestConfig::default() })]

    #[test]
    fn tiles_go_only_to_qualifying_workers_and_every_servable_job_ends(
        machines in prop::collection::vec(0..4u8, 1..5),
        plans in prop::collection::vec(job_plan(), 1..5),
        ops in prop::collection::vec(op(), 0..120),
    ) {
        run(machines, plans, ops);
    }
}

/// A job only one connected machine qualifies for, in full verification: its tiles
/// are rendered once and held, and the stall that follows fails it after the stall
/// timeout, naming the tags it requires, while a job nobody qualifies for waits.
#[test]
fn a_full_verification_job_with_one_qualifying_machine_stalls_naming_its_tags() {
    let mut s = Scheduler::new();
    let mut now = 0;
    s.handle(
        now,
        Event::WorkerTags {
            worker: 1,
            tags: tags(1),
        },
    );
    s.handle(
        now,
        Event::WorkerJoined {
            worker: 1,
            threads: 1,
            machine: Some("g".into()),
        },
    );
    s.handle(
        now,
        Event::WorkerJoined {
            worker: 2,
            threads: 1,
            machine: Some("p".into()),
        },
    );
    s.handle(
        now,
        Event::RequireTags {
            job: 1,
            tags: tags(1),
        },
    );
    s.handle(
        now,
        Event::RequireTags {
            job: 2,
            tags: tags(2),
        },
    );
    s.handle(
        now,
        Event::JobSubmitted {
            job: 2,
            priority: 0,
            scene: [2; 32],
            tiles: 1,
        },
    );
    let actions = s.handle(
        now,
        Event::JobSubmitted {
            job: 1,
            priority: 0,
            scene: [1; 32],
            tiles: 1,
        },
    );
    assert!(
        actions.contains(&Action::Assign {
            worker: 1,
            job: 1,
            tile: 0
        }),
        "{actions:?}"
    );
    assert_eq!(s.qualifying_machines(&tags(1)), vec!["g".to_string()]);
    assert_eq!(s.qualifying_machines(&tags(2)), Vec::<String>::new());
    assert_eq!(
        s.qualifying_machines(&[]),
        vec!["g".to_string(), "p".to_string()]
    );
    s.handle(
        now,
        Event::TileToConfirm {
            worker: 1,
            job: 1,
            tile: 0,
            required: true,
        },
    );
    let mut failed = None;
    while now < 40_000 && failed.is_none() {
        now += 1_000;
        s.handle(now, Event::Heartbeat { worker: 1 });
        s.handle(now, Event::Heartbeat { worker: 2 });
        for a in s.handle(now, Event::Timeout) {
            match a {
                Action::JobFailed { job, message } => failed = Some((job, message)),
                Action::Assign { .. } => panic!("nobody else may take the tile: {a:?}"),
                _ => {}
            }
        }
    }
    let (job, message) = failed.expect("the job fails after the stall timeout");
    assert_eq!(job, 1);
    assert!(
        message.contains("awaits confirmation by another machine")
            && message
                .ends_with("(counting only the machines with every tag the job requires: gpu)"),
        "{message}"
    );
    assert!(s.is_active(2), "the job nobody qualifies for waits");
    // A machine with the tag joins: the waiting job's tile goes to it.
    s.handle(
        now,
        Event::WorkerTags {
            worker: 3,
            tags: tags(2),
        },
    );
    let actions = s.handle(
        now,
        Event::WorkerJoined {
            worker: 3,
            threads: 1,
            machine: Some("s".into()),
        },
    );
    assert!(
        actions.contains(&Action::Assign {
            worker: 3,
            job: 2,
            tile: 0
        }),
        "{actions:?}"
    );
}

/// A connected worker told new tags gives back the tiles it no longer qualifies for:
/// they go to a qualifying worker, and its late result would still count.
#[test]
fn a_worker_that_loses_a_tag_gives_back_the_tiles_that_required_it() {
    // No copies of stragglers: the second worker gets the tile only once it is given
    // back.
    let mut s = Scheduler::with_policy(Policy {
        speculate: false,
        ..Policy::default()
    });
    s.handle(
        0,
        Event::WorkerTags {
            worker: 1,
            tags: tags(1),
        },
    );
    s.handle(
        0,
        Event::WorkerJoined {
            worker: 1,
            threads: 1,
            machine: Some("a".into()),
        },
    );
    s.handle(
        0,
        Event::RequireTags {
            job: 1,
            tags: tags(1),
        },
    );
    s.handle(
        0,
        Event::JobSubmitted {
            job: 1,
            priority: 0,
            scene: [1; 32],
            tiles: 1,
        },
    );
    assert_eq!(s.held_by(1), 1);
    s.handle(
        10,
        Event::WorkerTags {
            worker: 2,
            tags: tags(1),
        },
    );
    let joined = s.handle(
        10,
        Event::WorkerJoined {
            worker: 2,
            threads: 1,
            machine: Some("b".into()),
        },
    );
    assert!(
        joined.iter().all(|a| !matches!(a, Action::Assign { .. })),
        "{joined:?}"
    );
    let actions = s.handle(
        20,
        Event::WorkerTags {
            worker: 1,
            tags: Vec::new(),
        },
    );
    assert_eq!(
        actions
            .iter()
            .filter(|a| matches!(
                a,
                Action::Assign {
                    worker: 2,
                    job: 1,
                    tile: 0
                }
            ))
            .count(),
        1,
        "{actions:?}"
    );
    let done = s.handle(
        30,
        Event::TileDone {
            worker: 1,
            job: 1,
            tile: 0,
        },
    );
    assert!(done.contains(&Action::JobDone { job: 1 }), "{done:?}");
}
