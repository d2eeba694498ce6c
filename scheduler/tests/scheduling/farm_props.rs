//! The decision core (the tile scheduler and the lifecycle joined) against random
//! histories of the inputs a daemon feeds it, checked after every input.
//!
//! The histories mix submissions whose rows are written or not, workers joining and
//! leaving, results, reported failures, cancels, pauses and resumes, storage going down
//! and coming back, images stored or not, ends written, and time passing. After every
//! input, the two machines agree:
//!
//! - **Active means queued or running**: a job has tiles in the tile scheduler exactly
//!   when the lifecycle shows it queued or running; a job whose row is being written has
//!   none, nor has one that is finishing or has ended.
//! - **Handed out means running**: a job one of whose tiles went out in this input
//!   shows running (or has moved on since, within the same input).
//! - **Each tile once**: a tile is accepted at most once.
//! - **The image is due with the last tile**: `StoreImage` comes only once every tile
//!   of the job is accepted, and at most once per run of the job until it is stored.
//! - **Jobs in passes**: some jobs render in passes. A pass's last tile asks for the
//!   pass to be added up, and the job then has no tile out until the totals come
//!   (`Evaluated`, `Failed`, or a take-back that restarts the pass); each tile is
//!   accepted once per pass that sends it, and the image is due only once the totals
//!   meet the target with every tile in. Totals for a pass that is no longer awaited
//!   (restarted, or its job ended) change nothing.
//! - **A quarantine takes back what the machine rendered**: exactly the tiles accepted
//!   from its workers in the active jobs not in passes, each of which must then be
//!   accepted again.
//! - **Sequences**: some submissions are sequences, whose frames the core starts as
//!   frame jobs (admitted here as a daemon would), and which operators cancel, pause,
//!   resume, requeue frames of and delete. A frame starts only while its sequence is
//!   stored, not paused, not cancelled, and storage writes; at most
//!   `MAX_ACTIVE_FRAMES` of a sequence start or run at once; a frame ends only with its
//!   frame job's end written, in the same state; the sequence's end is told once
//!   every frame has ended, in the state its frames give, and told again only after
//!   it ran again (a requeued frame).
//!
//! Liveness: after any history, storage comes back, workers join, sequences are
//! resumed, and every tile out is returned: every job the core acknowledged ends within
//! a bounded number of inputs, and a job ends only once (one `RecordEnd`); every
//! sequence ends, its end told.

use std::collections::{BTreeMap, BTreeSet};

use proptest::prelude::*;
use protocol::{JobId, JobState, SceneHash, WorkerId};
use scheduler::farm::{
    Effect, Farm, Input, PassAction, PassInput, PassTile, SequenceAction, SequenceInput,
    SequenceRun, TilePlan,
};
use scheduler::lifecycle::{self, Lifecycle, Limits, Phase, Request};
use scheduler::passes::{Passes, RungCheck};
use scheduler::sequence::{FrameState, MAX_ACTIVE_FRAMES};
use scheduler::{Action, Event, Policy, Scheduler};

/// The ladder of the jobs in passes: short, so that histories reach its end.
const LAST_RUNG: u32 = 6;

#[derive(Clone, Debug)]
enum Op {
    Submit {
        tiles: u32,
        in_passes: bool,
    },
    /// The totals of a pass being added up come: meeting the target (at the pass's
    /// rung), not meeting it, or not computable; or for a pass not awaited.
    AddedUp {
        pick: usize,
        meets: bool,
        fails: bool,
        stale: bool,
    },
    /// Some tiles of a job in passes were built by a machine caught lying.
    TakeBack {
        pick: usize,
        tiles: u8,
    },
    /// The machine of a history's worker is caught returning wrong pixels.
    Quarantine {
        worker: u8,
    },
    Store {
        pick: usize,
        ok: bool,
    },
    Join {
        worker: u8,
        threads: u32,
    },
    Leave {
        worker: u8,
    },
    Result {
        pick: usize,
    },
    Fail {
        pick: usize,
    },
    Cancel {
        pick: usize,
    },
    Pause {
        pick: usize,
    },
    Resume {
        pick: usize,
    },
    ImageStored {
        pick: usize,
        ok: bool,
    },
    EndRecorded {
        pick: usize,
    },
    Storage {
        ok: bool,
    },
    Advance {
        ms: u64,
    },
    /// A sequence of `frames` frames of `tiles` tiles each, its row written at once.
    Sequence {
        frames: u32,
        tiles: u32,
    },
    /// An operator's control of a sequence, checked as the daemon checks it: 0 cancel,
    /// 1 pause, 2 resume, 3 requeue its failed and cancelled frames, 4 delete.
    Control {
        pick: usize,
        control: u8,
    },
}

fn op() -> impl Strategy<Value = Op> {
    prop_oneof![
        3 => (1u32..6, prop::bool::weighted(0.4)).prop_map(|(tiles, in_passes)| Op::Submit { tiles, in_passes }),
        3 => (any::<usize>(), any::<bool>(), prop::bool::weighted(0.1), prop::bool::weighted(0.1))
            .prop_map(|(pick, meets, fails, stale)| Op::AddedUp { pick, meets, fails, stale }),
        1 => (any::<usize>(), 1u8..8).prop_map(|(pick, tiles)| Op::TakeBack { pick, tiles }),
        1 => (0u8..4).prop_map(|worker| Op::Quarantine { worker }),
        3 => (any::<usize>(), prop::bool::weighted(0.85)).prop_map(|(pick, ok)| Op::Store { pick, ok }),
        2 => (0u8..4, 1u32..3).prop_map(|(worker, threads)| Op::Join { worker, threads }),
        1 => (0u8..4).prop_map(|worker| Op::Leave { worker }),
        8 => any::<usize>().prop_map(|pick| Op::Result { pick }),
        1 => any::<usize>().prop_map(|pick| Op::Fail { pick }),
        1 => any::<usize>().prop_map(|pick| Op::Cancel { pick }),
        1 => any::<usize>().prop_map(|pick| Op::Pause { pick }),
        1 => any::<usize>().prop_map(|pick| Op::Resume { pick }),
        3 => (any::<usize>(), prop::bool::weighted(0.8)).prop_map(|(pick, ok)| Op::ImageStored { pick, ok }),
        3 => any::<usize>().prop_map(|pick| Op::EndRecorded { pick }),
        1 => prop::bool::weighted(0.6).prop_map(|ok| Op::Storage { ok }),
        2 => (1u64..3_000).prop_map(|ms| Op::Advance { ms }),
        1 => (1u32..7, 1u32..4).prop_map(|(frames, tiles)| Op::Sequence { frames, tiles }),
        1 => (any::<usize>(), 0u8..5).prop_map(|(pick, control)| Op::Control { pick, control }),
    ]
}

fn scene(job: u64) -> SceneHash {
    let mut hash = [0; 32];
    hash[..8].copy_from_slice(&job.to_le_bytes());
    hash
}

struct Run {
    farm: Farm,
    now: u64,
    /// Workers connected, by the small number the history names them with.
    connected: BTreeMap<u8, WorkerId>,
    next_worker: WorkerId,
    /// Jobs admitted, with their tile count.
    jobs: BTreeMap<JobId, u32>,
    /// Tiles out: (worker, job, tile) as assigned and not yet returned or withdrawn.
    out: BTreeSet<(WorkerId, JobId, u32)>,
    accepted: BTreeSet<(JobId, u32)>,
    /// Jobs whose image the core asked to store, not yet reported stored.
    storing: BTreeSet<JobId>,
    /// Jobs whose end the core asked to write, not yet reported written.
    ending: BTreeSet<JobId>,
    ends: BTreeMap<JobId, u32>,
    /// Jobs in passes: the rung each tile has reached.
    passes: BTreeMap<JobId, Vec<Option<u32>>>,
    /// Passes being added up: the job's pass and the rungs to look at.
    adding: BTreeMap<JobId, (u32, u32, u32)>,
    /// The rung of each job in passes' pass under way.
    rung: BTreeMap<JobId, u32>,
    /// Jobs in passes whose totals met the target (or the ladder's end).
    finished: BTreeSet<JobId>,
    /// The machine each accepted tile came from, and the worker whose result the
    /// input under way is.
    accepted_from: BTreeMap<(JobId, u32), String>,
    reporter: Option<WorkerId>,
    /// Each worker's machine name.
    machines: BTreeMap<WorkerId, String>,
    /// The sequences not deleted, with the tiles of their frames; and the final state
    /// the core said each has ended in (until it said it runs again).
    sequences: BTreeMap<JobId, u32>,
    sequence_ended: BTreeMap<JobId, JobState>,
    /// Frame jobs, with their sequence and frame.
    frames: BTreeMap<JobId, (JobId, u32)>,
}

impl Run {
    fn new() -> Run {
        let policy = Policy {
            max_attempts: 3,
            ..Policy::default()
        };
        Run {
            farm: Farm::new(
                Scheduler::with_policy(policy),
                Lifecycle::new(Limits::default(), 1),
            ),
            now: 0,
            connected: BTreeMap::new(),
            next_worker: 1,
            jobs: BTreeMap::new(),
            out: BTreeSet::new(),
            accepted: BTreeSet::new(),
            storing: BTreeSet::new(),
            ending: BTreeSet::new(),
            ends: BTreeMap::new(),
            passes: BTreeMap::new(),
            adding: BTreeMap::new(),
            rung: BTreeMap::new(),
            finished: BTreeSet::new(),
            accepted_from: BTreeMap::new(),
            reporter: None,
            machines: BTreeMap::new(),
            sequences: BTreeMap::new(),
            sequence_ended: BTreeMap::new(),
            frames: BTreeMap::new(),
        }
    }

    fn request() -> Request {
        Request {
            client: None,
            scene_bytes: 10,
            objects: 1,
            width: 8,
            height: 8,
            aa: 1,
        }
    }

    /// The frames the core starts, admitted as frame jobs as the daemon does.
    fn start_frames(&mut self, sequence: JobId, frames: &[u32]) {
        let run = self
            .farm
            .sequence(sequence)
            .expect("frames of a known sequence");
        assert!(
            run.stored() && !run.deleting(),
            "frames of sequence {sequence} started before its row was written or while deleted"
        );
        assert!(
            !run.frames().paused(),
            "frames of paused sequence {sequence} started"
        );
        assert!(
            self.farm.lifecycle().storage_down().is_none(),
            "frames started while storage cannot write"
        );
        let tiles = self.sequences[&sequence];
        for &frame in frames {
            assert_eq!(
                self.farm
                    .sequence(sequence)
                    .and_then(|r| r.frames().frame(frame)),
                Some(FrameState::Starting),
                "frame {frame} of sequence {sequence} started while not starting"
            );
            let plan = TilePlan {
                priority: 0,
                scene: scene(sequence),
                tiles,
                interactive: false,
            };
            let admitted = self
                .farm
                .admit_frame(self.now, sequence, frame, &Self::request(), plan);
            if let Ok(job) = admitted {
                self.farm.keep(job);
                self.jobs.insert(job, tiles);
                self.frames.insert(job, (sequence, frame));
            }
        }
    }

    /// A job deleted (a requeued frame's old job, or a deleted sequence's): its rows
    /// and files are gone at once.
    fn deleted(&mut self, job: JobId) {
        self.jobs.remove(&job);
        self.storing.remove(&job);
        self.ending.remove(&job);
        self.input(Input::Job(lifecycle::Event::Deleted { job }));
    }

    /// A job in passes' tiles as the executor holds them: the rung each has reached
    /// and its next work (one rung up, none at the last).
    fn pass_tiles(&self, job: JobId) -> Vec<PassTile> {
        self.passes[&job]
            .iter()
            .map(|&rung| PassTile {
                rung,
                next_work: match rung {
                    None => Some(0),
                    Some(r) if r >= LAST_RUNG => None,
                    Some(r) => Some(r + 1),
                },
            })
            .collect()
    }

    fn pick_job(&self, pick: usize) -> Option<JobId> {
        let ids: Vec<JobId> = self.jobs.keys().copied().collect();
        (!ids.is_empty()).then(|| ids[pick % ids.len()])
    }

    fn pick_out(&self, pick: usize) -> Option<(WorkerId, JobId, u32)> {
        let out: Vec<_> = self.out.iter().copied().collect();
        (!out.is_empty()).then(|| out[pick % out.len()])
    }

    fn phase(&self, job: JobId) -> Option<Phase> {
        self.farm.lifecycle().job(job).map(|j| j.phase.clone())
    }

    fn input(&mut self, input: Input) {
        let effects = self.farm.handle(self.now, input);
        self.absorb(&effects);
    }

    /// Follows the effects as an executor would, and checks what they promise.
    fn absorb(&mut self, effects: &[Effect]) {
        let mut assigned = BTreeSet::new();
        for effect in effects {
            match effect {
                Effect::Tiles(Action::Assign { worker, job, tile }) => {
                    self.out.insert((*worker, *job, *tile));
                    assigned.insert(*job);
                }
                Effect::Tiles(Action::AcceptTile { job, tile }) => {
                    assert!(
                        self.accepted.insert((*job, *tile)),
                        "tile {tile} of job {job} accepted twice"
                    );
                    if let (Some(reached), Some(&rung)) =
                        (self.passes.get_mut(job), self.rung.get(job))
                    {
                        reached[*tile as usize] = Some(rung);
                    }
                    if let Some(machine) = self.reporter.and_then(|w| self.machines.get(&w)) {
                        self.accepted_from.insert((*job, *tile), machine.clone());
                    }
                }
                Effect::Pass(PassAction::AddUp { job, pass, rungs }) => {
                    let unfinished = (0..self.jobs[job])
                        .filter(|t| !self.accepted.contains(&(*job, *t)))
                        .count();
                    assert_eq!(unfinished, 0, "job {job}'s pass {pass} added up unfinished");
                    self.adding
                        .insert(*job, (*pass, *rungs.start(), *rungs.end()));
                }
                Effect::Pass(PassAction::Start {
                    job, rung, send, ..
                }) => {
                    self.adding.remove(job);
                    self.rung.insert(*job, *rung);
                    let reached = self.passes.get_mut(job).expect("a job in passes");
                    for (t, reached) in reached.iter_mut().enumerate() {
                        if send.contains(&(t as u32)) {
                            // Accepted again in this pass.
                            self.accepted.remove(&(*job, t as u32));
                        } else {
                            *reached = Some(*rung);
                        }
                    }
                }
                Effect::Pass(PassAction::TakenBack { job, taken, .. }) => {
                    self.adding.remove(job);
                    let reached = self.passes.get_mut(job).expect("a job in passes");
                    for &t in taken {
                        reached[t as usize] = None;
                        self.accepted.remove(&(*job, t));
                    }
                }
                Effect::TakenBack { job, tiles } => {
                    for &tile in tiles {
                        assert!(
                            self.accepted.remove(&(*job, tile)),
                            "tile {tile} of job {job} taken back, never accepted"
                        );
                        self.accepted_from.remove(&(*job, tile));
                    }
                }
                Effect::Pass(PassAction::Finished { job, .. }) => {
                    self.adding.remove(job);
                    self.finished.insert(*job);
                }
                Effect::Tiles(Action::CancelOnWorker { worker, job }) => {
                    self.out.retain(|&(w, j, _)| !(w == *worker && j == *job));
                }
                Effect::Tiles(Action::DropWorker { worker }) => {
                    self.connected.retain(|_, w| w != worker);
                    self.out.retain(|&(w, _, _)| w != *worker);
                    self.input(Input::Tiles(Event::WorkerLeft { worker: *worker }));
                }
                Effect::Job(lifecycle::Action::StoreImage { job }) => {
                    let tiles = self.jobs[job];
                    let accepted = (0..tiles)
                        .filter(|t| self.accepted.contains(&(*job, *t)))
                        .count();
                    assert_eq!(
                        accepted, tiles as usize,
                        "job {job}'s image asked for with {accepted} of {tiles} tiles"
                    );
                    assert!(
                        !self.passes.contains_key(job) || self.finished.contains(job),
                        "job {job}'s image asked for before its passes met the target"
                    );
                    self.storing.insert(*job);
                }
                Effect::Job(lifecycle::Action::RecordEnd { job, .. }) => {
                    *self.ends.entry(*job).or_default() += 1;
                    self.ending.insert(*job);
                }
                Effect::Job(lifecycle::Action::DeleteStored { job }) => self.deleted(*job),
                Effect::Sequence(action) => self.sequence_action(action),
                _ => {}
            }
        }
        for job in assigned {
            let phase = self.phase(job);
            assert!(
                !matches!(phase, Some(Phase::Storing | Phase::Queued) | None),
                "job {job} handed out while {phase:?}"
            );
        }
    }

    /// Follows a sequence's effect as the daemon would, and checks what it promises.
    fn sequence_action(&mut self, action: &SequenceAction) {
        match action {
            SequenceAction::StartFrames { sequence, frames } => {
                self.start_frames(*sequence, frames);
            }
            SequenceAction::FrameEnded {
                sequence,
                frame,
                job,
                state,
            } => {
                assert_eq!(self.frames.get(job), Some(&(*sequence, *frame)));
                let phase = self.phase(*job);
                assert!(
                    matches!(phase, Some(Phase::Ended { state: s, recorded: true, .. }) if s == *state),
                    "frame {frame} of sequence {sequence} ended {state:?}, its job {phase:?}"
                );
            }
            SequenceAction::Ended { sequence, state } => {
                let run = self.farm.sequence(*sequence).expect("a known sequence");
                assert!(state.is_final(), "sequence {sequence} ended {state:?}");
                assert_eq!(run.frames().state(), *state, "sequence {sequence}'s end");
                assert!(
                    self.sequence_ended.insert(*sequence, *state).is_none(),
                    "sequence {sequence}'s end told twice"
                );
            }
            SequenceAction::Running { sequence } => {
                assert!(
                    self.sequence_ended.remove(sequence).is_some(),
                    "sequence {sequence} runs again without having ended"
                );
            }
            SequenceAction::Paused { paused, jobs, .. } => {
                for &job in jobs {
                    let event = if *paused {
                        Event::PauseJob { job }
                    } else {
                        Event::ResumeJob { job }
                    };
                    self.input(Input::Tiles(event));
                }
            }
            SequenceAction::DeleteStored { sequence } => {
                self.sequences.remove(sequence);
                self.sequence_ended.remove(sequence);
                self.input(Input::Sequence(SequenceInput::Deleted {
                    sequence: *sequence,
                }));
            }
            SequenceAction::FrameOut { .. } | SequenceAction::Requeued { .. } => {}
        }
    }

    fn check(&self) {
        for &sequence in self.sequences.keys() {
            let run = self
                .farm
                .sequence(sequence)
                .expect("a sequence not deleted");
            let c = run.frames().counts();
            assert_eq!(
                c.pending + c.active + c.done + c.failed + c.cancelled,
                run.frames().len()
            );
            assert!(
                c.active as usize <= MAX_ACTIVE_FRAMES,
                "sequence {sequence} runs {} frames",
                c.active
            );
        }
        for &job in self.jobs.keys() {
            let phase = self.phase(job);
            let adding = self.farm.pass_run(job).is_some_and(|r| r.evaluating());
            let runs = matches!(phase, Some(Phase::Queued | Phase::Running)) && !adding;
            assert_eq!(
                self.farm.tiles().is_active(job),
                runs,
                "job {job}: active in the tile scheduler, but {phase:?}"
            );
        }
        for (&job, &count) in &self.ends {
            assert_eq!(count, 1, "job {job} ended {count} times");
        }
    }

    fn apply(&mut self, op: &Op) {
        match *op {
            Op::Submit { tiles, in_passes } => {
                let request = Self::request();
                let next = self.jobs.keys().last().map_or(1, |j| j + 1);
                let plan = TilePlan {
                    priority: 0,
                    scene: scene(next),
                    tiles,
                    interactive: false,
                };
                if let Ok(job) = self.farm.admit(self.now, &request, plan) {
                    self.jobs.insert(job, tiles);
                    if in_passes {
                        self.farm.start_passes(job, Passes::new(1.0, LAST_RUNG));
                        self.passes.insert(job, vec![None; tiles as usize]);
                        self.rung.insert(job, 0);
                    }
                }
            }
            Op::AddedUp {
                pick,
                meets,
                fails,
                stale,
            } => {
                let adding: Vec<JobId> = self.adding.keys().copied().collect();
                if adding.is_empty() {
                    return;
                }
                let job = adding[pick % adding.len()];
                let (pass, first, last) = self.adding[&job];
                let pass = if stale { pass + 7 } else { pass };
                let input = if fails {
                    PassInput::Failed {
                        job,
                        pass,
                        message: "no tracer".into(),
                    }
                } else {
                    let checks = (first..=last)
                        .map(|rung| RungCheck {
                            rung,
                            estimate: 2.0 / f64::from(rung + 1),
                            meets: (meets && rung == last) || rung >= LAST_RUNG,
                        })
                        .collect();
                    PassInput::Evaluated {
                        job,
                        pass,
                        checks,
                        tiles: self.pass_tiles(job),
                        elapsed_ms: 10,
                        samples: 100,
                    }
                };
                if !stale {
                    self.adding.remove(&job);
                    self.input(Input::Pass(input));
                    return self.check();
                }
                let effects = self.farm.handle(self.now, Input::Pass(input));
                assert!(
                    effects.is_empty(),
                    "totals of a pass not awaited: {effects:?}"
                );
            }
            Op::TakeBack { pick, tiles } => {
                let jobs: Vec<JobId> = self.passes.keys().copied().collect();
                if jobs.is_empty() {
                    return;
                }
                let job = jobs[pick % jobs.len()];
                let count = self.jobs.get(&job).copied().unwrap_or(0);
                let taken: Vec<u32> = (0..count).filter(|t| tiles & (1 << t) != 0).collect();
                let input = PassInput::TakeBack {
                    job,
                    taken,
                    tiles: self.pass_tiles(job),
                };
                let effects = self.farm.handle(self.now, Input::Pass(input));
                let before: Vec<_> = self.out.iter().filter(|o| o.1 == job).copied().collect();
                self.absorb(&effects);
                // A pass restarted: every holder of a tile of the pass it replaces is
                // told to drop it.
                if effects
                    .iter()
                    .any(|e| matches!(e, Effect::Pass(PassAction::TakenBack { .. })))
                {
                    for (worker, job, tile) in before {
                        let withdrawn = Effect::Tiles(Action::CancelOnWorker { worker, job });
                        assert!(
                            effects.contains(&withdrawn),
                            "tile {tile} of job {job} left with worker {worker} by a restart"
                        );
                    }
                }
            }
            Op::Store { pick, ok } => {
                let Some(job) = self.pick_job(pick) else {
                    return;
                };
                if self.phase(job) != Some(Phase::Storing) {
                    return;
                }
                let event = if ok {
                    lifecycle::Event::Stored { job }
                } else {
                    lifecycle::Event::StoreFailed {
                        job,
                        message: "disk full".into(),
                    }
                };
                self.input(Input::Job(event));
                if !ok {
                    self.jobs.remove(&job);
                }
            }
            Op::Join { worker, threads } => {
                if self.connected.contains_key(&worker) {
                    return;
                }
                let id = self.next_worker;
                self.next_worker += 1;
                self.connected.insert(worker, id);
                self.machines.insert(id, format!("m{worker}"));
                self.input(Input::Tiles(Event::WorkerJoined {
                    worker: id,
                    threads,
                    machine: Some(format!("m{worker}")),
                }));
            }
            Op::Leave { worker } => {
                if let Some(id) = self.connected.remove(&worker) {
                    self.out.retain(|&(w, _, _)| w != id);
                    self.input(Input::Tiles(Event::WorkerLeft { worker: id }));
                }
            }
            Op::Result { pick } => {
                if let Some((worker, job, tile)) = self.pick_out(pick) {
                    self.out.remove(&(worker, job, tile));
                    self.reporter = Some(worker);
                    self.input(Input::Tiles(Event::TileDone { worker, job, tile }));
                    self.reporter = None;
                }
            }
            Op::Quarantine { worker } => {
                let machine = format!("m{worker}");
                // What the core must take back: that machine's accepted tiles in the
                // active jobs not in passes.
                let expect: BTreeSet<(JobId, u32)> = self
                    .accepted_from
                    .iter()
                    .filter(|(&(job, _), m)| {
                        **m == machine
                            && self.farm.tiles().is_active(job)
                            && !self.passes.contains_key(&job)
                    })
                    .map(|(&k, _)| k)
                    .collect();
                let input = Input::Quarantine {
                    machine: machine.clone(),
                    caught_in: 0,
                    reason: "caught".into(),
                };
                let effects = self.farm.handle(self.now, input);
                // The executor hears first, with what is taken back.
                match effects.first() {
                    Some(Effect::Quarantined {
                        machine: m, taken, ..
                    }) => {
                        assert_eq!(*m, machine);
                        let told: BTreeSet<(JobId, u32)> = taken
                            .iter()
                            .flat_map(|(job, tiles)| tiles.iter().map(|&t| (*job, t)))
                            .collect();
                        assert_eq!(told, expect, "what the quarantine says it took back");
                    }
                    other => panic!("a quarantine first tells the executor: {other:?}"),
                }
                let taken: BTreeSet<(JobId, u32)> = effects
                    .iter()
                    .flat_map(|e| match e {
                        Effect::TakenBack { job, tiles } => {
                            tiles.iter().map(|&t| (*job, t)).collect::<Vec<_>>()
                        }
                        _ => Vec::new(),
                    })
                    .collect();
                assert_eq!(taken, expect, "what the quarantine took back");
                // Its workers hold nothing any more: what they send counts for nothing.
                let machine = format!("m{worker}");
                let machines = &self.machines;
                self.out
                    .retain(|(w, _, _)| machines.get(w).is_none_or(|m| *m != machine));
                self.absorb(&effects);
            }
            Op::Fail { pick } => {
                if let Some((worker, job, tile)) = self.pick_out(pick) {
                    self.out.remove(&(worker, job, tile));
                    self.input(Input::Tiles(Event::TileFailed {
                        worker,
                        job,
                        tile,
                        message: "out of memory".into(),
                    }));
                }
            }
            Op::Cancel { pick } => {
                if let Some(job) = self.pick_job(pick) {
                    self.input(Input::Job(lifecycle::Event::Cancel { job }));
                }
            }
            Op::Pause { pick } => {
                if let Some(job) = self.pick_job(pick) {
                    self.input(Input::Tiles(Event::PauseJob { job }));
                }
            }
            Op::Resume { pick } => {
                if let Some(job) = self.pick_job(pick) {
                    self.input(Input::Tiles(Event::ResumeJob { job }));
                }
            }
            Op::ImageStored { pick, ok } => {
                let stored: Vec<JobId> = self.storing.iter().copied().collect();
                if stored.is_empty() {
                    return;
                }
                let job = stored[pick % stored.len()];
                self.storing.remove(&job);
                let result = if ok { Ok(()) } else { Err("disk full".into()) };
                self.input(Input::Job(lifecycle::Event::ImageStored { job, result }));
            }
            Op::EndRecorded { pick } => {
                let ending: Vec<JobId> = self.ending.iter().copied().collect();
                if ending.is_empty() {
                    return;
                }
                let job = ending[pick % ending.len()];
                self.ending.remove(&job);
                self.input(Input::Job(lifecycle::Event::EndRecorded { job }));
            }
            Op::Storage { ok } => {
                let status = if ok { Ok(()) } else { Err("disk full".into()) };
                self.input(Input::Storage(status));
            }
            Op::Sequence { frames, tiles } => {
                let sequence = self.farm.issue_id();
                self.sequences.insert(sequence, tiles);
                self.farm
                    .enter_sequence(sequence, SequenceRun::new(1, frames, tiles));
                self.input(Input::Sequence(SequenceInput::Stored { sequence }));
            }
            Op::Control { pick, control } => {
                let ids: Vec<JobId> = self.sequences.keys().copied().collect();
                let Some(&sequence) = ids.get(pick % ids.len().max(1)) else {
                    return;
                };
                let run = self.farm.sequence(sequence).expect("a known sequence");
                let state = run.frames().state();
                let input = match control {
                    0 if !state.is_final() => SequenceInput::Cancel { sequence },
                    1 | 2 if !state.is_final() => SequenceInput::Pause {
                        sequence,
                        paused: control == 1,
                    },
                    3 => {
                        let frames: Vec<u32> = run
                            .frames()
                            .failed()
                            .chain(run.frames().frames_in(FrameState::Cancelled))
                            .map(|(f, _)| f)
                            .collect();
                        if frames.is_empty() {
                            return;
                        }
                        SequenceInput::Requeue { sequence, frames }
                    }
                    4 if state.is_final() && run.recorded() == Some(state) => {
                        SequenceInput::Delete { sequence }
                    }
                    _ => return,
                };
                self.input(Input::Sequence(input));
            }
            Op::Advance { ms } => {
                self.now += ms;
                // Connected workers talk at least once a second.
                let workers: Vec<WorkerId> = self.connected.values().copied().collect();
                for worker in workers {
                    self.input(Input::Tiles(Event::Heartbeat { worker }));
                }
                self.input(Input::Timeout);
            }
        }
        self.check();
    }

    /// Storage comes back, the rows are written, a worker joins, and every tile out
    /// comes back, every image and end is written: every job ends.
    fn settle(&mut self) {
        self.apply(&Op::Storage { ok: true });
        self.apply(&Op::Join {
            worker: 9,
            threads: 2,
        });
        for _ in 0..2_000 {
            let storing: Vec<JobId> = self
                .jobs
                .keys()
                .copied()
                .filter(|&j| self.phase(j) == Some(Phase::Storing))
                .collect();
            for job in storing {
                self.input(Input::Job(lifecycle::Event::Stored { job }));
            }
            let jobs: Vec<JobId> = self.jobs.keys().copied().collect();
            for job in jobs {
                self.input(Input::Tiles(Event::ResumeJob { job }));
            }
            let paused: Vec<JobId> = self
                .sequences
                .keys()
                .copied()
                .filter(|&s| self.farm.sequence(s).is_some_and(|r| r.frames().paused()))
                .collect();
            for sequence in paused {
                self.input(Input::Sequence(SequenceInput::Pause {
                    sequence,
                    paused: false,
                }));
            }
            if !self.out.is_empty() {
                self.apply(&Op::Result { pick: 0 });
            } else if !self.adding.is_empty() {
                self.apply(&Op::AddedUp {
                    pick: 0,
                    meets: true,
                    fails: false,
                    stale: false,
                });
            } else if !self.storing.is_empty() {
                self.apply(&Op::ImageStored { pick: 0, ok: true });
            } else if !self.ending.is_empty() {
                self.apply(&Op::EndRecorded { pick: 0 });
            } else if self
                .jobs
                .keys()
                .all(|&j| self.phase(j).is_some_and(|p| p.has_ended()))
                && self
                    .sequences
                    .keys()
                    .all(|s| self.sequence_ended.contains_key(s))
            {
                break;
            } else {
                self.apply(&Op::Advance { ms: 1_000 });
            }
        }
        for &job in self.jobs.keys() {
            let phase = self.phase(job);
            assert!(
                matches!(
                    phase,
                    Some(Phase::Ended {
                        recorded: true,
                        state: JobState::Done | JobState::Failed | JobState::Cancelled,
                        ..
                    })
                ),
                "job {job} never ended: {phase:?}"
            );
        }
        for &sequence in self.sequences.keys() {
            let run = self.farm.sequence(sequence).expect("a known sequence");
            assert_eq!(
                self.sequence_ended.get(&sequence),
                Some(&run.frames().state()),
                "sequence {sequence} never ended: {:?}",
                run.frames().counts()
            );
        }
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 300, ..ProptestConfig::default() })]

    #[test]
    fn the_two_machines_agree_after_every_input(ops in prop::collection::vec(op(), 1..150)) {
        let mut run = Run::new();
        for op in &ops {
            run.apply(op);
        }
        run.settle();
    }
}
