//! The scheduler core against a model of the daemon that carries out its actions.
//!
//! [`Farm`] feeds events to the [`Scheduler`] and replays every returned action the way
//! the daemon would: it tracks which tiles each worker holds (from `Assign`,
//! `CancelOnWorker` and the worker's own results), which scenes each worker has (from
//! `SendScene` and `ForgetScene`), which tiles were accepted and how each job ended.
//! After every event it checks the invariants below, so the unit tests get them for free
//! and the property tests check them on random histories of joins, departures, drains,
//! submissions, results (real, duplicate, stolen, from departed workers, for unknown jobs
//! or tiles), failures and cancellations.
//!
//! Proven after every event (a violation panics with the event that caused it):
//! - **No double assignment**: a tile is held by at most one live worker, and never
//!   assigned again once accepted (invariant 2, idempotent results).
//! - **Credit** (invariant 5): a worker holds at most twice its threads; a draining worker
//!   is assigned nothing; the model's holdings agree with `Scheduler::held_by`.
//! - **Policy order**: every `Assign` goes to the job the module doc names: highest
//!   priority with waiting tiles, then fewest tiles in flight, then oldest.
//! - **Work conservation**: while a tile waits, every live, non-draining worker is at its
//!   credit (no idle slot next to queued work).
//! - **Scenes once**: an `Assign` follows a `SendScene` of its scene to that worker, a
//!   scene is sent only to a worker that does not have it, and a worker keeps only scenes
//!   of active jobs (`ForgetScene` when the last job using one ends).
//! - **First result wins**: `AcceptTile` exactly when the worker holding the tile returns
//!   it, at most once per tile; every other result is dropped.
//! - **Endings**: `JobDone` once, when all tiles are accepted, never for a failed or
//!   cancelled job; a cancelled or failed job is no longer assigned, and every live
//!   worker holding its tiles gets `CancelOnWorker`; `is_active`/`has_started` agree.
//!
//! Liveness: after each random history a worker that never leaves joins and every
//! worker returns every tile it holds, round after round; every job neither cancelled nor
//! failed must then end with `JobDone`, within `ceil(remaining tiles / 4) + 1` rounds
//! (the new worker alone renders 4 tiles a round whenever any tile waits).
//!
//! The focused tests show the policy's consequences: pull by credit, fast workers render
//! more, priority first, fair share between equal priorities, a departing worker's tiles
//! going to another, a worker joining mid-job, and scenes sent once and forgotten.

use std::cmp::Reverse;
use std::collections::{BTreeMap, BTreeSet, VecDeque};

use coordinator::scheduler::{Action, Event, Scheduler};
use proptest::prelude::*;
use proptest::sample::Index;
use protocol::{JobId, SceneHash, WorkerId};

const SCENE_A: SceneHash = [1; 32];
const SCENE_B: SceneHash = [2; 32];
const SCENE_C: SceneHash = [3; 32];
const SCENES: [SceneHash; 3] = [SCENE_A, SCENE_B, SCENE_C];

// ---------------------------------------------------------------------------------------
// The model.

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Fate {
    Active,
    Done,
    Failed,
    Cancelled,
}

struct ModelJob {
    priority: i32,
    scene: SceneHash,
    tiles: u32,
    accepted: BTreeSet<u32>,
    fate: Fate,
}

struct ModelWorker {
    credit: usize,
    draining: bool,
    holding: BTreeSet<(JobId, u32)>,
    scenes: BTreeSet<SceneHash>,
}

/// The scheduler, and the daemon's view of the farm rebuilt from its actions.
struct Farm {
    scheduler: Scheduler,
    workers: BTreeMap<WorkerId, ModelWorker>,
    /// Workers that left, with the tiles they held then (for stale results).
    departed: Vec<(WorkerId, Vec<(JobId, u32)>)>,
    jobs: BTreeMap<JobId, ModelJob>,
    next_worker: WorkerId,
    next_job: JobId,
    /// Tiles accepted per worker whose result was kept.
    rendered_by: BTreeMap<WorkerId, usize>,
}

impl Farm {
    fn new() -> Self {
        Farm {
            scheduler: Scheduler::new(),
            workers: BTreeMap::new(),
            departed: Vec::new(),
            jobs: BTreeMap::new(),
            next_worker: 1,
            next_job: 1,
            rendered_by: BTreeMap::new(),
        }
    }

    fn join(&mut self, threads: u32) -> (WorkerId, Vec<Action>) {
        let worker = self.next_worker;
        (worker, self.step(Event::WorkerJoined { worker, threads }))
    }

    fn submit(&mut self, priority: i32, scene: SceneHash, tiles: u32) -> (JobId, Vec<Action>) {
        let job = self.next_job;
        let actions = self.step(Event::JobSubmitted {
            job,
            priority,
            scene,
            tiles,
        });
        (job, actions)
    }

    fn done(&mut self, worker: WorkerId, job: JobId, tile: u32) -> Vec<Action> {
        self.step(Event::TileDone { worker, job, tile })
    }

    /// The tiles the worker holds, oldest job first.
    fn held(&self, worker: WorkerId) -> Vec<(JobId, u32)> {
        self.workers
            .get(&worker)
            .map_or_else(Vec::new, |w| w.holding.iter().copied().collect())
    }

    fn active(&self, job: JobId) -> bool {
        self.jobs.get(&job).is_some_and(|j| j.fate == Fate::Active)
    }

    /// Live workers holding tiles of the job.
    fn holders(&self, job: JobId) -> BTreeSet<WorkerId> {
        self.workers
            .iter()
            .filter(|(_, w)| w.holding.iter().any(|&(j, _)| j == job))
            .map(|(&id, _)| id)
            .collect()
    }

    fn in_flight(&self, job: JobId) -> usize {
        self.workers
            .values()
            .map(|w| w.holding.iter().filter(|&&(j, _)| j == job).count())
            .sum()
    }

    /// Tiles of the job neither accepted nor held by a live worker.
    fn waiting(&self, job: JobId) -> usize {
        let j = &self.jobs[&job];
        j.tiles as usize - j.accepted.len() - self.in_flight(job)
    }

    /// The job the policy says the next free slot goes to.
    fn next_by_policy(&self) -> Option<JobId> {
        self.jobs
            .iter()
            .filter(|&(&id, j)| j.fate == Fate::Active && self.waiting(id) > 0)
            .min_by_key(|&(&id, j)| (Reverse(j.priority), self.in_flight(id), id))
            .map(|(&id, _)| id)
    }

    /// Applies one event to the scheduler, replays its actions and checks every
    /// invariant. Returns the actions.
    fn step(&mut self, event: Event) -> Vec<Action> {
        // What the event must cause, judged on the state before it; and the parts of the
        // daemon's view that change with the event itself rather than with an action.
        let mut must_accept = None;
        let mut must_end = None;
        match event {
            Event::WorkerJoined { worker, threads } => {
                assert!(!self.workers.contains_key(&worker), "worker ids are fresh");
                self.next_worker = self.next_worker.max(worker + 1);
                self.workers.insert(
                    worker,
                    ModelWorker {
                        credit: 2 * threads as usize,
                        draining: false,
                        holding: BTreeSet::new(),
                        scenes: BTreeSet::new(),
                    },
                );
            }
            Event::WorkerLeft { worker } => {
                if let Some(w) = self.workers.remove(&worker) {
                    self.departed
                        .push((worker, w.holding.into_iter().collect()));
                }
            }
            Event::WorkerDraining { worker } => {
                if let Some(w) = self.workers.get_mut(&worker) {
                    w.draining = true;
                }
            }
            Event::JobSubmitted {
                job,
                priority,
                scene,
                tiles,
            } => {
                assert!(!self.jobs.contains_key(&job), "job ids are fresh");
                self.next_job = self.next_job.max(job + 1);
                self.jobs.insert(
                    job,
                    ModelJob {
                        priority,
                        scene,
                        tiles,
                        accepted: BTreeSet::new(),
                        fate: Fate::Active,
                    },
                );
            }
            Event::TileDone { worker, job, tile } => {
                // The worker is done with the tile, whatever becomes of its result.
                if let Some(w) = self.workers.get_mut(&worker) {
                    if w.holding.remove(&(job, tile)) {
                        must_accept = Some((job, tile));
                    }
                }
            }
            Event::TileFailed {
                worker, job, tile, ..
            } => {
                if let Some(w) = self.workers.get_mut(&worker) {
                    if w.holding.remove(&(job, tile)) {
                        must_end = Some((job, self.holders(job)));
                    }
                }
            }
            Event::CancelJob { job } => {
                if self.active(job) {
                    must_end = Some((job, self.holders(job)));
                    // Cancelled from now on: no action may give it out again.
                    self.jobs.get_mut(&job).expect("active").fate = Fate::Cancelled;
                }
            }
        }

        let actions = self.scheduler.handle(event.clone());
        let context = || format!("after {event:?}\nactions: {actions:?}");

        let mut accepts = 0;
        let mut cancelled_on = BTreeSet::new();
        let mut forgotten = Vec::new();
        for (i, action) in actions.iter().enumerate() {
            match *action {
                Action::SendScene { worker, job } => {
                    let scene = self.jobs[&job].scene;
                    assert!(self.active(job), "scene of an ended job {}", context());
                    let w = self
                        .workers
                        .get_mut(&worker)
                        .expect("SendScene to a live worker");
                    assert!(w.scenes.insert(scene), "scene re-sent {}", context());
                    let next = actions.get(i + 1);
                    assert!(
                        matches!(next, Some(&Action::Assign { worker: to, job: of, .. })
                            if to == worker && of == job),
                        "a scene is sent for the tile that follows {}",
                        context()
                    );
                }
                Action::Assign { worker, job, tile } => {
                    assert!(self.active(job), "tile of an ended job {}", context());
                    let j = &self.jobs[&job];
                    assert!(tile < j.tiles, "no such tile {}", context());
                    assert!(
                        !j.accepted.contains(&tile),
                        "accepted tile again {}",
                        context()
                    );
                    assert!(
                        self.workers
                            .values()
                            .all(|w| !w.holding.contains(&(job, tile))),
                        "double assignment {}",
                        context()
                    );
                    assert_eq!(
                        self.next_by_policy(),
                        Some(job),
                        "priority, fair share, age {}",
                        context()
                    );
                    let scene = j.scene;
                    let w = self
                        .workers
                        .get_mut(&worker)
                        .expect("Assign to a live worker");
                    assert!(!w.draining, "draining worker assigned {}", context());
                    assert!(w.scenes.contains(&scene), "tile before scene {}", context());
                    w.holding.insert((job, tile));
                    assert!(w.holding.len() <= w.credit, "over credit {}", context());
                }
                Action::AcceptTile { job, tile } => {
                    accepts += 1;
                    assert_eq!(must_accept, Some((job, tile)), "{}", context());
                    let j = self.jobs.get_mut(&job).expect("a known job");
                    assert!(j.accepted.insert(tile), "accepted twice {}", context());
                    if let Event::TileDone { worker, .. } = event {
                        *self.rendered_by.entry(worker).or_default() += 1;
                    }
                }
                Action::CancelOnWorker { worker, job } => {
                    assert!(
                        must_end.as_ref().is_some_and(|(j, _)| *j == job),
                        "cancel of a job not ending {}",
                        context()
                    );
                    let w = self.workers.get_mut(&worker).expect("live worker");
                    w.holding.retain(|&(j, _)| j != job);
                    cancelled_on.insert(worker);
                }
                Action::ForgetScene { worker, scene } => {
                    let w = self.workers.get_mut(&worker).expect("live worker");
                    assert!(
                        w.scenes.remove(&scene),
                        "forgot an unknown scene {}",
                        context()
                    );
                    forgotten.push(scene);
                }
                Action::JobDone { job } => {
                    let j = self.jobs.get_mut(&job).expect("a known job");
                    assert_eq!(j.fate, Fate::Active, "ended twice {}", context());
                    assert_eq!(j.accepted.len(), j.tiles as usize, "early {}", context());
                    j.fate = Fate::Done;
                }
                Action::JobFailed { job, ref message } => {
                    assert!(
                        matches!(event, Event::TileFailed { job: j, message: ref m, .. }
                            if j == job && m == message),
                        "failure not from a TileFailed {}",
                        context()
                    );
                    assert!(
                        must_end.as_ref().is_some_and(|(j, _)| *j == job),
                        "failed from a tile the worker does not hold {}",
                        context()
                    );
                    let j = self.jobs.get_mut(&job).expect("a known job");
                    assert_eq!(j.fate, Fate::Active, "ended twice {}", context());
                    j.fate = Fate::Failed;
                }
            }
        }

        // Results: the holder's is accepted, every other one dropped.
        assert_eq!(accepts, usize::from(must_accept.is_some()), "{}", context());

        // Endings by failure or cancellation.
        if let Some((job, holders)) = must_end {
            let j = self.jobs.get_mut(&job).expect("a known job");
            let fate = match event {
                Event::CancelJob { .. } => Fate::Cancelled,
                _ => Fate::Failed,
            };
            assert_eq!(j.fate, fate, "{}", context());
            for worker in holders {
                assert!(
                    cancelled_on.contains(&worker),
                    "holder not told {}",
                    context()
                );
            }
        }

        self.check_state(&forgotten, &context);
        actions
    }

    /// Invariants of the state between events.
    fn check_state(&self, forgotten: &[SceneHash], context: &dyn Fn() -> String) {
        let in_use: BTreeSet<SceneHash> = self
            .jobs
            .values()
            .filter(|j| j.fate == Fate::Active)
            .map(|j| j.scene)
            .collect();
        for scene in forgotten {
            assert!(
                !in_use.contains(scene),
                "forgot a scene in use {}",
                context()
            );
        }

        let mut held = BTreeSet::new();
        for (&id, w) in &self.workers {
            assert_eq!(self.scheduler.held_by(id), w.holding.len(), "{}", context());
            assert!(w.holding.len() <= w.credit, "over credit {}", context());
            for &(job, tile) in &w.holding {
                assert!(
                    self.active(job),
                    "holds a tile of an ended job {}",
                    context()
                );
                assert!(held.insert((job, tile)), "double assignment {}", context());
            }
            assert!(
                w.scenes.is_subset(&in_use),
                "worker {id} keeps a scene no active job uses {}",
                context()
            );
        }

        let mut anything_waits = false;
        for (&id, j) in &self.jobs {
            let active = j.fate == Fate::Active;
            assert_eq!(
                self.scheduler.is_active(id),
                active,
                "job {id} {}",
                context()
            );
            if active {
                assert!(
                    j.accepted.len() < j.tiles as usize,
                    "job {id} complete without JobDone {}",
                    context()
                );
                let waiting = self.waiting(id);
                anything_waits |= waiting > 0;
                assert_eq!(
                    self.scheduler.has_started(id),
                    waiting < j.tiles as usize,
                    "job {id} {}",
                    context()
                );
            }
        }
        if anything_waits {
            for (id, w) in &self.workers {
                assert!(
                    w.draining || w.holding.len() == w.credit,
                    "worker {id} idles while tiles wait {}",
                    context()
                );
            }
        }
    }

    /// Lets every worker return every tile it holds, round after round, with one more
    /// worker that never leaves. Returns the number of rounds.
    fn run_to_completion(&mut self) -> usize {
        let (finisher, _) = self.join(2);
        let credit = self.workers[&finisher].credit;
        let remaining: usize = self
            .jobs
            .values()
            .filter(|j| j.fate == Fate::Active)
            .map(|j| j.tiles as usize - j.accepted.len())
            .sum();
        let bound = remaining.div_ceil(credit) + 1;
        let mut rounds = 0;
        loop {
            let held: Vec<(WorkerId, JobId, u32)> = self
                .workers
                .iter()
                .flat_map(|(&w, mw)| mw.holding.iter().map(move |&(j, t)| (w, j, t)))
                .collect();
            if held.is_empty() {
                break;
            }
            rounds += 1;
            assert!(rounds <= bound, "{rounds} rounds for {remaining} tiles");
            for (worker, job, tile) in held {
                if self.workers[&worker].holding.contains(&(job, tile)) {
                    self.done(worker, job, tile);
                }
            }
        }
        for (id, j) in &self.jobs {
            assert_ne!(j.fate, Fate::Active, "job {id} never finished");
        }
        rounds
    }
}

fn assigns(actions: &[Action]) -> Vec<(WorkerId, JobId, u32)> {
    actions
        .iter()
        .filter_map(|a| match *a {
            Action::Assign { worker, job, tile } => Some((worker, job, tile)),
            _ => None,
        })
        .collect()
}

fn job_done(actions: &[Action], job: JobId) -> bool {
    actions.contains(&Action::JobDone { job })
}

// ---------------------------------------------------------------------------------------
// Random histories.

/// A result that is not the holder's own.
#[derive(Clone, Debug)]
enum Stray {
    /// Any (job, tile), also an unknown job or a tile past the end.
    Random { job: Index, tile: u32 },
    /// A tile already accepted, sent again.
    Duplicate(Index),
    /// A tile another worker holds.
    Stolen(Index),
    /// A tile a departed worker held, from that worker.
    Departed(Index),
}

#[derive(Clone, Debug)]
enum Op {
    Join {
        threads: u32,
    },
    Leave(Index),
    Drain(Index),
    Submit {
        priority: i32,
        scene: usize,
        tiles: u32,
    },
    /// A worker returns a tile it holds.
    Return {
        worker: Index,
        tile: Index,
    },
    Stray {
        worker: Index,
        kind: Stray,
    },
    /// A worker fails a tile it holds.
    Fail {
        worker: Index,
        tile: Index,
    },
    Cancel(Index),
}

fn op() -> impl Strategy<Value = Op> {
    let stray = prop_oneof![
        (any::<Index>(), 0u32..40).prop_map(|(job, tile)| Stray::Random { job, tile }),
        any::<Index>().prop_map(Stray::Duplicate),
        any::<Index>().prop_map(Stray::Stolen),
        any::<Index>().prop_map(Stray::Departed),
    ];
    prop_oneof![
        3 => (1u32..=4).prop_map(|threads| Op::Join { threads }),
        1 => any::<Index>().prop_map(Op::Leave),
        1 => any::<Index>().prop_map(Op::Drain),
        3 => (-1i32..=2, 0..SCENES.len(), 0u32..=30)
            .prop_map(|(priority, scene, tiles)| Op::Submit { priority, scene, tiles }),
        12 => (any::<Index>(), any::<Index>())
            .prop_map(|(worker, tile)| Op::Return { worker, tile }),
        3 => (any::<Index>(), stray).prop_map(|(worker, kind)| Op::Stray { worker, kind }),
        1 => (any::<Index>(), any::<Index>()).prop_map(|(worker, tile)| Op::Fail { worker, tile }),
        1 => any::<Index>().prop_map(Op::Cancel),
    ]
}

fn pick<T: Copy>(items: &[T], index: &Index) -> Option<T> {
    (!items.is_empty()).then(|| items[index.index(items.len())])
}

impl Farm {
    /// The event an operation stands for in the current state, if it has one.
    fn event(&self, op: &Op) -> Option<Event> {
        let live: Vec<WorkerId> = self.workers.keys().copied().collect();
        let busy: Vec<WorkerId> = self
            .workers
            .iter()
            .filter(|(_, w)| !w.holding.is_empty())
            .map(|(&id, _)| id)
            .collect();
        Some(match op {
            &Op::Join { threads } => Event::WorkerJoined {
                worker: self.next_worker,
                threads,
            },
            Op::Leave(i) => Event::WorkerLeft {
                worker: pick(&live, i)?,
            },
            Op::Drain(i) => Event::WorkerDraining {
                worker: pick(&live, i)?,
            },
            &Op::Submit {
                priority,
                scene,
                tiles,
            } => Event::JobSubmitted {
                job: self.next_job,
                priority,
                scene: SCENES[scene],
                tiles,
            },
            Op::Return { worker, tile } => {
                let worker = pick(&busy, worker)?;
                let (job, tile) = pick(&self.held(worker), tile)?;
                Event::TileDone { worker, job, tile }
            }
            Op::Fail { worker, tile } => {
                let worker = pick(&busy, worker)?;
                let (job, tile) = pick(&self.held(worker), tile)?;
                Event::TileFailed {
                    worker,
                    job,
                    tile,
                    message: format!("tile {tile} of job {job} failed"),
                }
            }
            Op::Stray { worker, kind } => {
                let (worker, job, tile) = match kind {
                    Stray::Random { job, tile } => {
                        // Known jobs and one that never existed.
                        let ids: Vec<JobId> = (1..=self.next_job).collect();
                        (pick(&live, worker)?, pick(&ids, job)?, *tile)
                    }
                    Stray::Duplicate(i) => {
                        let accepted: Vec<(JobId, u32)> = self
                            .jobs
                            .iter()
                            .flat_map(|(&j, mj)| mj.accepted.iter().map(move |&t| (j, t)))
                            .collect();
                        let (job, tile) = pick(&accepted, i)?;
                        (pick(&live, worker)?, job, tile)
                    }
                    Stray::Stolen(i) => {
                        let worker = pick(&live, worker)?;
                        let others: Vec<(JobId, u32)> = self
                            .workers
                            .iter()
                            .filter(|&(&id, _)| id != worker)
                            .flat_map(|(_, w)| w.holding.iter().copied())
                            .collect();
                        let (job, tile) = pick(&others, i)?;
                        (worker, job, tile)
                    }
                    Stray::Departed(i) => {
                        let gone: Vec<(WorkerId, JobId, u32)> = self
                            .departed
                            .iter()
                            .flat_map(|(w, tiles)| tiles.iter().map(move |&(j, t)| (*w, j, t)))
                            .collect();
                        pick(&gone, i)?
                    }
                };
                Event::TileDone { worker, job, tile }
            }
            Op::Cancel(i) => {
                let ids: Vec<JobId> = (1..=self.next_job).collect();
                Event::CancelJob {
                    job: pick(&ids, i)?,
                }
            }
        })
    }
}

fn config(cases: u32) -> ProptestConfig {
    ProptestConfig {
        cases,
        // Keep the tree clean: a failure prints its minimal history, which is enough.
        failure_persistence: None,
        ..ProptestConfig::default()
    }
}

proptest! {
    #![proptest_config(config(1000))]

    /// Every invariant after every event of a random history, then every surviving job
    /// finishes once one steady worker joins and everyone returns their tiles.
    #[test]
    fn random_histories_keep_the_invariants_and_finish_every_job(
        ops in prop::collection::vec(op(), 0..150),
    ) {
        let mut farm = Farm::new();
        for op in &ops {
            if let Some(event) = farm.event(op) {
                farm.step(event);
            }
        }
        farm.run_to_completion();
        for (_, j) in farm.jobs.iter().filter(|(_, j)| j.fate == Fate::Done) {
            prop_assert_eq!(j.accepted.len(), j.tiles as usize);
        }
    }

    /// Without failures, cancellations or departures, every job ends with `JobDone`
    /// even when all workers but the finisher drain.
    #[test]
    fn every_job_finishes_without_mishaps(
        jobs in prop::collection::vec((-1i32..=2, 0..SCENES.len(), 0u32..=30), 1..8),
        threads in prop::collection::vec(1u32..=4, 0..4),
        drain in any::<bool>(),
    ) {
        let mut farm = Farm::new();
        let workers: Vec<WorkerId> = threads.iter().map(|&t| farm.join(t).0).collect();
        for &(priority, scene, tiles) in &jobs {
            farm.submit(priority, SCENES[scene], tiles);
        }
        if drain {
            for worker in workers {
                farm.step(Event::WorkerDraining { worker });
            }
        }
        farm.run_to_completion();
        for (id, j) in &farm.jobs {
            prop_assert_eq!(j.fate, Fate::Done, "job {}", id);
        }
    }
}

// ---------------------------------------------------------------------------------------
// Focused tests.

#[test]
fn a_worker_pulls_by_credit() {
    let mut farm = Farm::new();
    let (job, _) = farm.submit(0, SCENE_A, 10);
    let (worker, joined) = farm.join(1);
    assert_eq!(
        joined,
        vec![
            Action::SendScene { worker, job },
            Action::Assign {
                worker,
                job,
                tile: 0
            },
            Action::Assign {
                worker,
                job,
                tile: 1
            },
        ]
    );
    // At its credit, a new job gives it nothing.
    let (other, submitted) = farm.submit(0, SCENE_B, 3);
    assert!(assigns(&submitted).is_empty());
    // One back, exactly one more: the other job, which has none in flight.
    let returned = farm.done(worker, job, 0);
    assert_eq!(assigns(&returned), vec![(worker, other, 0)]);
    assert_eq!(farm.scheduler.held_by(worker), 2);
}

#[test]
fn a_faster_worker_renders_more_tiles() {
    let mut farm = Farm::new();
    let (fast, _) = farm.join(1);
    let (slow, _) = farm.join(1);
    let (job, _) = farm.submit(0, SCENE_A, 300);
    // The fast worker returns a tile every tick, the slow one every fourth.
    let mut tick = 0;
    while farm.active(job) {
        tick += 1;
        for (worker, every) in [(fast, 1), (slow, 4)] {
            if tick % every == 0 {
                if let Some(&(job, tile)) = farm.held(worker).first() {
                    farm.done(worker, job, tile);
                }
            }
        }
    }
    let (f, s) = (farm.rendered_by[&fast], farm.rendered_by[&slow]);
    assert_eq!(f + s, 300);
    assert!(f >= 3 * s, "fast {f} tiles, slow {s}");
}

#[test]
fn higher_priority_tiles_go_first() {
    let mut farm = Farm::new();
    let (low, _) = farm.submit(0, SCENE_A, 6);
    let (high, _) = farm.submit(2, SCENE_B, 6);
    let (mid, _) = farm.submit(1, SCENE_A, 6);
    let (worker, joined) = farm.join(1);
    let mut order: Vec<JobId> = assigns(&joined).iter().map(|a| a.1).collect();
    while let Some(&(job, tile)) = farm.held(worker).first() {
        order.extend(assigns(&farm.done(worker, job, tile)).iter().map(|a| a.1));
    }
    let expected: Vec<JobId> = [[high; 6], [mid; 6], [low; 6]].concat();
    assert_eq!(order, expected);

    // A running low-priority job yields the next free slot to a new urgent one.
    let (background, _) = farm.submit(0, SCENE_A, 50);
    let (urgent, _) = farm.submit(1, SCENE_C, 1);
    let &(job, tile) = farm.held(worker).first().unwrap();
    assert_eq!(
        job, background,
        "the urgent job came while the worker was full"
    );
    assert_eq!(
        assigns(&farm.done(worker, job, tile)),
        vec![(worker, urgent, 0)]
    );
}

#[test]
fn a_small_job_is_not_starved_behind_a_big_one_of_equal_priority() {
    let mut farm = Farm::new();
    let (worker, _) = farm.join(2); // credit 4
    let (big, _) = farm.submit(0, SCENE_A, 100);
    let (small, _) = farm.submit(0, SCENE_A, 4);
    // The worker renders its tiles in the order it got them.
    let mut queue: VecDeque<(JobId, u32)> = farm.held(worker).into_iter().collect();
    let (mut small_done, mut big_done) = (None, None);
    let mut step = 0;
    while let Some((job, tile)) = queue.pop_front() {
        step += 1;
        let actions = farm.done(worker, job, tile);
        queue.extend(assigns(&actions).iter().map(|&(_, j, t)| (j, t)));
        if job_done(&actions, small) {
            small_done = Some(step);
        }
        if job_done(&actions, big) {
            big_done = Some(step);
        }
    }
    let (small_done, big_done) = (small_done.unwrap(), big_done.unwrap());
    // Alone it would take 4 returns; sharing evenly, about 8. Behind the big job, 104.
    assert!(small_done <= 12, "small job done after {small_done} tiles");
    assert_eq!(big_done, 104);
}

#[test]
fn equal_priorities_alternate_from_the_start() {
    let mut farm = Farm::new();
    let (big, _) = farm.submit(0, SCENE_A, 100);
    let (small, _) = farm.submit(0, SCENE_A, 4);
    let (worker, joined) = farm.join(2);
    assert_eq!(
        assigns(&joined),
        vec![
            (worker, big, 0),
            (worker, small, 0),
            (worker, big, 1),
            (worker, small, 1)
        ]
    );
}

#[test]
fn a_leaving_worker_s_tiles_go_to_another() {
    let mut farm = Farm::new();
    let (job, _) = farm.submit(0, SCENE_A, 4);
    let (first, _) = farm.join(1);
    let (second, _) = farm.join(2);
    assert_eq!(farm.held(first), vec![(job, 0), (job, 1)]);
    assert_eq!(farm.held(second), vec![(job, 2), (job, 3)]);
    let left = farm.step(Event::WorkerLeft { worker: first });
    // The second worker has the scene already and two free slots: no SendScene.
    assert_eq!(left.len(), 2, "{left:?}");
    let mut moved = assigns(&left);
    moved.sort_unstable();
    assert_eq!(moved, vec![(second, job, 0), (second, job, 1)]);
    // A late result from the departed worker is dropped.
    assert!(farm.done(first, job, 0).is_empty());
    let mut ended = false;
    for tile in 0..4 {
        ended |= job_done(&farm.done(second, job, tile), job);
    }
    assert!(ended);
    assert_eq!(farm.rendered_by.get(&first), None);
}

#[test]
fn a_worker_joining_mid_job_gets_tiles() {
    let mut farm = Farm::new();
    let (job, _) = farm.submit(0, SCENE_A, 10);
    let (first, _) = farm.join(1);
    farm.done(first, job, 0);
    assert!(farm.scheduler.has_started(job));
    let (second, joined) = farm.join(1);
    assert_eq!(
        joined,
        vec![
            Action::SendScene {
                worker: second,
                job
            },
            Action::Assign {
                worker: second,
                job,
                tile: 3
            },
            Action::Assign {
                worker: second,
                job,
                tile: 4
            },
        ]
    );
}

#[test]
fn a_scene_is_sent_once_per_worker_and_forgotten_with_its_last_job() {
    let mut farm = Farm::new();
    let mut history = Vec::new();
    let (w1, joined) = farm.join(1);
    history.push(joined);
    let (w2, joined) = farm.join(1);
    history.push(joined);
    let (short, submitted) = farm.submit(0, SCENE_A, 3);
    history.push(submitted);
    let (long, submitted) = farm.submit(0, SCENE_A, 9);
    history.push(submitted);
    while farm.active(short) || farm.active(long) {
        for worker in [w1, w2] {
            if let Some(&(job, tile)) = farm.held(worker).first() {
                history.push(farm.done(worker, job, tile));
            }
        }
    }
    for worker in [w1, w2] {
        // Both workers rendered tiles of both jobs, and got the scene once.
        assert!(farm.rendered_by[&worker] > 0);
        let sends = history
            .iter()
            .flatten()
            .filter(|a| matches!(a, Action::SendScene { worker: w, .. } if *w == worker))
            .count();
        assert_eq!(sends, 1, "worker {worker}");
        let forget = Action::ForgetScene {
            worker,
            scene: SCENE_A,
        };
        let forgets: Vec<usize> = history
            .iter()
            .enumerate()
            .filter(|(_, actions)| actions.contains(&forget))
            .map(|(i, _)| i)
            .collect();
        // Once, in the event that ended the last job using the scene, after its JobDone.
        assert_eq!(forgets.len(), 1, "worker {worker}");
        let actions = &history[forgets[0]];
        let done_at = actions
            .iter()
            .position(|a| *a == Action::JobDone { job: long });
        let forget_at = actions.iter().position(|a| *a == forget);
        assert!(done_at.is_some() && done_at < forget_at, "{actions:?}");
    }
    let short_done = history.iter().position(|a| job_done(a, short)).unwrap();
    assert!(!history[short_done]
        .iter()
        .any(|a| matches!(a, Action::ForgetScene { .. })));

    // A later job with the same scene sends it again, once per worker.
    let (again, submitted) = farm.submit(0, SCENE_A, 4);
    let sends: Vec<&Action> = submitted
        .iter()
        .filter(|a| matches!(a, Action::SendScene { .. }))
        .collect();
    assert_eq!(
        sends,
        vec![
            &Action::SendScene {
                worker: w1,
                job: again
            },
            &Action::SendScene {
                worker: w2,
                job: again
            },
        ]
    );
}

#[test]
fn cancelling_stops_assignments_and_tells_every_holder() {
    let mut farm = Farm::new();
    let (w1, _) = farm.join(1);
    let (w2, _) = farm.join(2);
    let (job, _) = farm.submit(0, SCENE_A, 20);
    let (other, _) = farm.submit(0, SCENE_B, 20);
    let cancelled = farm.step(Event::CancelJob { job });
    for worker in [w1, w2] {
        assert!(cancelled.contains(&Action::CancelOnWorker { worker, job }));
        assert!(cancelled.contains(&Action::ForgetScene {
            worker,
            scene: SCENE_A
        }));
    }
    // The freed slots go to the other job; results for the cancelled one are dropped.
    assert!(assigns(&cancelled).iter().all(|&(_, j, _)| j == other));
    assert!(farm
        .done(w1, job, 0)
        .iter()
        .all(|a| !matches!(a, Action::AcceptTile { .. })));
    farm.run_to_completion();
    assert_eq!(farm.jobs[&job].fate, Fate::Cancelled);
    assert_eq!(farm.jobs[&other].fate, Fate::Done);
}

#[test]
fn an_empty_job_is_done_at_once() {
    let mut farm = Farm::new();
    let (job, actions) = farm.submit(0, SCENE_A, 0);
    assert_eq!(actions, vec![Action::JobDone { job }]);
}

/// The module doc's "first result wins" drops a result from a worker that no longer
/// holds the tile; a failure report is a result too, and counts only from the holder.
/// Sequence: job 1 (4 tiles); worker 1 (1 thread) holds tiles 0 and 1, worker 2
/// (1 thread) tiles 2 and 3; worker 2 reports tile 0 as failed: nothing happens.
#[test]
fn a_failure_from_a_worker_not_holding_the_tile_is_dropped() {
    let mut scheduler = Scheduler::new();
    scheduler.handle(Event::JobSubmitted {
        job: 1,
        priority: 0,
        scene: SCENE_A,
        tiles: 4,
    });
    scheduler.handle(Event::WorkerJoined {
        worker: 1,
        threads: 1,
    });
    scheduler.handle(Event::WorkerJoined {
        worker: 2,
        threads: 1,
    });
    let actions = scheduler.handle(Event::TileFailed {
        worker: 2,
        job: 1,
        tile: 0,
        message: "stale".into(),
    });
    assert!(
        !actions
            .iter()
            .any(|a| matches!(a, Action::JobFailed { .. })),
        "{actions:?}"
    );
    assert!(scheduler.is_active(1));
}
