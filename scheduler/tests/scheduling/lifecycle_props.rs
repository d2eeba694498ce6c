//! The job lifecycle against random histories of events, checked after every event.
//!
//! The histories mix submissions from a few clients, stores that succeed or fail,
//! storage going down and coming back, tiles handed out, completed or failed,
//! images stored or not, ends written, cancellations, deletions, retention timeouts
//! and stray events for unknown jobs. After every event:
//!
//! - **Ids**: every admitted job gets a new id, above every id seen before (also
//!   restored ones): ids are never reused.
//! - **Durable before acknowledged**: `Acknowledge` only for a job in `Storing` that was
//!   just stored, exactly once; `RefuseStored` only after a failed store.
//! - **Admission**: nothing is admitted while storage is down; a client never has more
//!   than its limit of jobs not ended.
//! - **Final means written**: a job shows done, failed or cancelled... done and failed
//!   only after `EndRecorded`; once a job shows a final state it never shows another;
//!   `RecordEnd` is asked once per job.
//! - **A failed store is not a failed job**: `ImageStored` with an error never ends a
//!   job; the store is asked again (at the retry deadline, or at once when storage
//!   comes back).
//! - **Deletion**: only of jobs whose end is written; a deleted job is gone.
//!
//! Liveness: after any history, storage comes back and every job's pending steps are
//! carried out (stored, tiles completed, images stored, ends written): every job then
//! shows a final state within a bounded number of events.

use std::collections::{BTreeMap, BTreeSet};
use std::net::IpAddr;

use proptest::prelude::*;
use protocol::{JobId, JobState};
use scheduler::lifecycle::{Action, Event, Lifecycle, Limits, Phase, Request};

const LIMIT: usize = 3;

#[derive(Clone, Debug)]
enum Op {
    Submit { client: u8 },
    Stored { pick: usize, ok: bool },
    Assign { pick: usize },
    Complete { pick: usize },
    Fail { pick: usize },
    ImageStored { pick: usize, ok: bool },
    EndRecorded { pick: usize },
    Cancel { pick: usize },
    Delete { pick: usize },
    Deleted { pick: usize },
    StorageDown,
    StorageUp,
    Advance { ms: u64 },
    Stray,
}

fn op() -> impl Strategy<Value = Op> {
    prop_oneof![
        4 => (0u8..3).prop_map(|client| Op::Submit { client }),
        4 => (any::<usize>(), prop::bool::weighted(0.8)).prop_map(|(pick, ok)| Op::Stored { pick, ok }),
        3 => any::<usize>().prop_map(|pick| Op::Assign { pick }),
        3 => any::<usize>().prop_map(|pick| Op::Complete { pick }),
        1 => any::<usize>().prop_map(|pick| Op::Fail { pick }),
        3 => (any::<usize>(), prop::bool::weighted(0.7)).prop_map(|(pick, ok)| Op::ImageStored { pick, ok }),
        3 => any::<usize>().prop_map(|pick| Op::EndRecorded { pick }),
        1 => any::<usize>().prop_map(|pick| Op::Cancel { pick }),
        1 => any::<usize>().prop_map(|pick| Op::Delete { pick }),
        2 => any::<usize>().prop_map(|pick| Op::Deleted { pick }),
        1 => Just(Op::StorageDown),
        1 => Just(Op::StorageUp),
        2 => (0u64..2_000).prop_map(|ms| Op::Advance { ms }),
        1 => Just(Op::Stray),
    ]
}

/// The model's view of the machine, built from the actions it returned.
#[derive(Default)]
struct Model {
    now: u64,
    highest: JobId,
    /// Jobs admitted and not deleted, with their client.
    jobs: BTreeMap<JobId, u8>,
    /// Jobs whose `RecordEnd` was asked, and the state.
    ended: BTreeMap<JobId, JobState>,
    /// Jobs whose final state was seen by clients.
    shown_final: BTreeMap<JobId, JobState>,
    /// Jobs with a `StoreImage` outstanding.
    storing_image: BTreeSet<JobId>,
    deleting: BTreeSet<JobId>,
    down: bool,
}

struct Run {
    l: Lifecycle,
    m: Model,
}

fn client_ip(client: u8) -> IpAddr {
    IpAddr::from([10, 0, 0, client])
}

impl Run {
    fn new() -> Run {
        Run {
            l: Lifecycle::new(
                Limits {
                    max_active_per_client: LIMIT,
                    retention: Some(5_000),
                    ..Limits::default()
                },
                1,
            ),
            m: Model::default(),
        }
    }

    fn pick(&self, pick: usize) -> Option<JobId> {
        let ids: Vec<JobId> = self.l.jobs().map(|(id, _)| id).collect();
        (!ids.is_empty()).then(|| ids[pick % ids.len()])
    }

    fn event(&mut self, event: Event) -> Vec<Action> {
        let before: BTreeMap<JobId, Phase> =
            self.l.jobs().map(|(id, j)| (id, j.phase.clone())).collect();
        let actions = self.l.handle(self.m.now, event.clone());
        for action in &actions {
            match action {
                Action::Acknowledge { job } => {
                    assert_eq!(
                        event,
                        Event::Stored { job: *job },
                        "acknowledged without a store"
                    );
                    assert_eq!(before.get(job), Some(&Phase::Storing));
                }
                Action::RefuseStored { job, .. } => {
                    assert!(matches!(event, Event::StoreFailed { job: j, .. } if j == *job));
                    self.m.jobs.remove(job);
                }
                Action::StoreImage { job } => {
                    self.m.storing_image.insert(*job);
                }
                Action::RecordEnd { job, state, .. } => {
                    assert!(
                        self.m.ended.insert(*job, *state).is_none(),
                        "job {job} ended twice"
                    );
                    assert!(state.is_final());
                }
                Action::DeleteStored { job } => {
                    // Its end written before, or by this very event (a delete asked
                    // while the end was being written).
                    assert!(
                        matches!(before.get(job), Some(Phase::Ended { recorded: true, .. }))
                            || (event == Event::EndRecorded { job: *job }
                                && matches!(before.get(job), Some(Phase::Ended { .. }))),
                        "deleting job {job} whose end is not written: {:?}",
                        before.get(job)
                    );
                    assert!(self.m.deleting.insert(*job), "job {job} deleted twice");
                }
                Action::CancelTiles { .. } | Action::Reply { .. } => {}
            }
        }
        if let Event::ImageStored {
            result: Err(_),
            job,
        } = &event
        {
            assert!(
                !self.m.ended.contains_key(job) || before.get(job).is_some_and(Phase::has_ended)
            );
        }
        self.check();
        actions
    }

    fn check(&mut self) {
        let mut active: BTreeMap<u8, usize> = BTreeMap::new();
        for (id, job) in self.l.jobs() {
            let visible = job.phase.visible();
            if let Some(before) = self.m.shown_final.get(&id) {
                assert_eq!(*before, visible, "job {id} changed its final state");
            }
            if matches!(visible, JobState::Done | JobState::Failed) {
                assert!(
                    matches!(job.phase, Phase::Ended { recorded: true, .. }),
                    "job {id} shows {visible:?} before its end is written"
                );
            }
            if visible.is_final() {
                self.m.shown_final.insert(id, visible);
            }
            if !job.phase.has_ended() {
                if let Some(&client) = self.m.jobs.get(&id) {
                    *active.entry(client).or_default() += 1;
                }
            }
        }
        for (client, n) in active {
            assert!(n <= LIMIT, "client {client} has {n} active jobs");
        }
    }

    fn apply(&mut self, op: &Op) {
        match *op {
            Op::Submit { client } => {
                let request = Request {
                    client: Some(client_ip(client)),
                    scene_bytes: 10,
                    objects: 1,
                    width: 8,
                    height: 8,
                    aa: 1,
                };
                match self.l.admit(self.m.now, &request) {
                    Ok(id) => {
                        assert!(!self.m.down, "admitted while storage is down");
                        assert!(
                            id > self.m.highest,
                            "id {id} reused (highest {})",
                            self.m.highest
                        );
                        self.m.highest = id;
                        self.m.jobs.insert(id, client);
                    }
                    Err(message) => assert!(
                        self.m.down || message.kind == protocol::RefusalKind::Limit,
                        "refused for no reason: {message}"
                    ),
                }
                self.check();
            }
            Op::Stored { pick, ok } => {
                if let Some(job) = self.pick(pick) {
                    let event = if ok {
                        Event::Stored { job }
                    } else {
                        Event::StoreFailed {
                            job,
                            message: "disk full".into(),
                        }
                    };
                    self.event(event);
                }
            }
            Op::Assign { pick } => {
                if let Some(job) = self.pick(pick) {
                    self.event(Event::TileAssigned { job });
                }
            }
            Op::Complete { pick } => {
                if let Some(job) = self.pick(pick) {
                    self.event(Event::TilesComplete { job });
                }
            }
            Op::Fail { pick } => {
                if let Some(job) = self.pick(pick) {
                    self.event(Event::TilesFailed {
                        job,
                        message: "tile 1 failed 5 times".into(),
                    });
                }
            }
            Op::ImageStored { pick, ok } => {
                if let Some(job) = self.pick(pick) {
                    if self.m.storing_image.remove(&job) {
                        let result = if ok { Ok(()) } else { Err("read-only".into()) };
                        self.event(Event::ImageStored { job, result });
                    }
                }
            }
            Op::EndRecorded { pick } => {
                if let Some(job) = self.pick(pick) {
                    if self.m.ended.contains_key(&job) {
                        self.event(Event::EndRecorded { job });
                    }
                }
            }
            Op::Cancel { pick } => {
                if let Some(job) = self.pick(pick) {
                    self.event(Event::Cancel { job });
                }
            }
            Op::Delete { pick } => {
                if let Some(job) = self.pick(pick) {
                    self.event(Event::Delete { job });
                }
            }
            Op::Deleted { pick } => {
                if let Some(job) = self.pick(pick) {
                    if self.m.deleting.remove(&job) {
                        self.event(Event::Deleted { job });
                        assert!(self.l.job(job).is_none());
                        self.m.jobs.remove(&job);
                    }
                }
            }
            Op::StorageDown => {
                self.m.down = true;
                self.event(Event::StorageUnavailable {
                    reason: "No space left on device".into(),
                });
            }
            Op::StorageUp => {
                self.m.down = false;
                self.event(Event::StorageAvailable);
            }
            Op::Advance { ms } => {
                self.m.now += ms;
                self.event(Event::Timeout);
            }
            Op::Stray => {
                let job = self.m.highest + 100;
                for event in [
                    Event::Stored { job },
                    Event::TilesComplete { job },
                    Event::EndRecorded { job },
                    Event::Deleted { job },
                ] {
                    assert!(self.event(event).is_empty());
                }
                let replies = self.event(Event::Cancel { job });
                assert!(matches!(
                    &replies[..],
                    [Action::Reply { result: Err(_), .. }]
                ));
            }
        }
    }

    /// Storage comes back and every pending step succeeds: every job must end.
    fn settle(&mut self) {
        self.m.down = false;
        self.event(Event::StorageAvailable);
        for _ in 0..20 {
            let ids: Vec<(JobId, Phase)> =
                self.l.jobs().map(|(id, j)| (id, j.phase.clone())).collect();
            for (job, phase) in ids {
                match phase {
                    Phase::Storing => {
                        self.event(Event::Stored { job });
                    }
                    Phase::Queued | Phase::Running => {
                        self.event(Event::TilesComplete { job });
                    }
                    Phase::Finishing { .. } => {
                        self.m.now += Limits::default().retry_ms;
                        self.event(Event::Timeout);
                        if self.m.storing_image.remove(&job) {
                            self.event(Event::ImageStored {
                                job,
                                result: Ok(()),
                            });
                        }
                    }
                    Phase::Ended {
                        recorded: false, ..
                    } => {
                        self.event(Event::EndRecorded { job });
                    }
                    Phase::Ended { recorded: true, .. } => {}
                }
            }
        }
        for (id, job) in self.l.jobs() {
            assert!(
                job.phase.visible().is_final(),
                "job {id} is stuck in {:?}",
                job.phase
            );
        }
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 400, ..ProptestConfig::default() })]

    #[test]
    fn the_lifecycle_keeps_its_promises(ops in prop::collection::vec(op(), 1..120)) {
        let mut run = Run::new();
        for op in &ops {
            run.apply(op);
        }
        run.settle();
    }
}

#[test]
fn restored_ids_keep_new_ids_above_them() {
    let mut l = Lifecycle::new(Limits::default(), 1);
    for (job, state) in [
        (3, JobState::Done),
        (12, JobState::Running),
        (7, JobState::Cancelled),
    ] {
        l.handle(
            0,
            Event::Restored {
                job,
                state,
                error: None,
                started: true,
                pixels: 1,
                ended_ago: 0,
            },
        );
    }
    let request = Request {
        client: None,
        scene_bytes: 1,
        objects: 1,
        width: 1,
        height: 1,
        aa: 1,
    };
    assert_eq!(l.admit(1, &request), Ok(13));
}
