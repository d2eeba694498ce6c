use protocol::{JobState, RefusalKind};

use super::*;
use crate::lifecycle::{Limits, Phase, Reply};
use crate::Policy;

pub(super) const SCENE: SceneHash = [7; 32];

pub(super) fn farm() -> Farm {
    let policy = Policy {
        max_attempts: 2,
        speculate: false,
        ..Policy::default()
    };
    Farm::new(
        Scheduler::with_policy(policy),
        Lifecycle::new(Limits::default(), 1),
    )
}

pub(super) fn request() -> lifecycle::Request {
    lifecycle::Request {
        client: None,
        scene_bytes: 100,
        objects: 1,
        width: 8,
        height: 8,
        aa: 1,
    }
}

pub(super) fn plan(tiles: u32) -> TilePlan {
    TilePlan {
        priority: 0,
        scene: SCENE,
        tiles,
        interactive: false,
    }
}

pub(super) fn phase(f: &Farm, job: JobId) -> Phase {
    f.lifecycle().job(job).expect("a known job").phase.clone()
}

pub(super) fn join(f: &mut Farm, worker: u64, threads: u32) -> Vec<Effect> {
    f.handle(
        0,
        Input::Tiles(Event::WorkerJoined {
            worker,
            threads,
            machine: Some(format!("m{worker}")),
        }),
    )
}

pub(super) fn done(f: &mut Farm, worker: u64, job: JobId, tile: u32) -> Vec<Effect> {
    f.handle(1, Input::Tiles(Event::TileDone { worker, job, tile }))
}

/// A quarantine of `machine`, caught in no job in particular.
pub(super) fn quarantine(machine: &str) -> Input {
    Input::Quarantine {
        machine: machine.into(),
        caught_in: 0,
        reason: "caught".into(),
    }
}

pub(super) fn assigned(effects: &[Effect]) -> Vec<(u64, JobId, u32)> {
    effects
        .iter()
        .filter_map(|e| match *e {
            Effect::Tiles(Action::Assign { worker, job, tile }) => Some((worker, job, tile)),
            _ => None,
        })
        .collect()
}

/// Admitted, stored, running with its first tile out, its image due with its last
/// tile in, done once the image and the end are written: every step between the two
/// machines is the core's, and the executor only reports what its world did.
#[test]
fn a_job_goes_from_admission_to_done_through_both_machines() {
    let mut f = farm();
    join(&mut f, 1, 2);
    let job = f.admit(0, &request(), plan(3)).unwrap();
    assert_eq!(phase(&f, job), Phase::Storing);
    let stored = f.handle(0, Input::Job(lifecycle::Event::Stored { job }));
    assert_eq!(
        stored.first(),
        Some(&Effect::Job(lifecycle::Action::Acknowledge { job }))
    );
    assert_eq!(
        assigned(&stored),
        vec![(1, job, 0), (1, job, 1), (1, job, 2)]
    );
    // The scene goes first, then the tiles.
    assert_eq!(
        stored[1],
        Effect::Tiles(Action::SendScene { worker: 1, job })
    );
    assert_eq!(phase(&f, job), Phase::Running);
    done(&mut f, 1, job, 0);
    done(&mut f, 1, job, 1);
    let last = done(&mut f, 1, job, 2);
    let store = last
        .iter()
        .position(|e| *e == Effect::Job(lifecycle::Action::StoreImage { job }))
        .expect("the image is due");
    let tiles_done = last
        .iter()
        .position(|e| *e == Effect::Tiles(Action::JobDone { job }))
        .unwrap();
    assert!(
        tiles_done < store,
        "the cause comes before its follow-up: {last:?}"
    );
    let stored = f.handle(
        2,
        Input::Job(lifecycle::Event::ImageStored {
            job,
            result: Ok(()),
        }),
    );
    assert!(stored.contains(&Effect::Job(lifecycle::Action::RecordEnd {
        job,
        state: JobState::Done,
        error: None,
    })));
    f.handle(3, Input::Job(lifecycle::Event::EndRecorded { job }));
    assert_eq!(phase(&f, job).visible(), JobState::Done);
}

/// A client's cancel ends the job and withdraws its tiles from the workers holding
/// them, in one input.
#[test]
fn a_cancel_withdraws_the_tiles_from_their_holders() {
    let mut f = farm();
    join(&mut f, 1, 4);
    let job = f.admit(0, &request(), plan(8)).unwrap();
    f.handle(0, Input::Job(lifecycle::Event::Stored { job }));
    let cancelled = f.handle(1, Input::Job(lifecycle::Event::Cancel { job }));
    assert!(cancelled.contains(&Effect::Job(lifecycle::Action::Reply {
        job,
        result: Ok(Reply::Cancelled),
    })));
    assert!(cancelled.contains(&Effect::Tiles(Action::CancelOnWorker { worker: 1, job })));
    assert_eq!(f.tiles().tiles_in_flight(), 0);
    // A second cancel is refused for the job's state, and changes nothing.
    let again = f.handle(2, Input::Job(lifecycle::Event::Cancel { job }));
    match &again[..] {
        [Effect::Job(lifecycle::Action::Reply {
            result: Err(refusal),
            ..
        })] => assert_eq!(refusal.kind, RefusalKind::State),
        other => panic!("{other:?}"),
    }
}

/// A tile that fails on every machine it may go to fails the job: the scheduler's
/// verdict reaches the lifecycle, which records the end with the reason.
#[test]
fn a_job_the_scheduler_gives_up_fails_with_its_reason() {
    let mut f = farm();
    join(&mut f, 1, 1);
    join(&mut f, 2, 1);
    let job = f.admit(0, &request(), plan(1)).unwrap();
    f.handle(0, Input::Job(lifecycle::Event::Stored { job }));
    let mut effects = Vec::new();
    for worker in [1, 2] {
        if f.tiles().held_by(worker) > 0 {
            effects = f.handle(
                1,
                Input::Tiles(Event::TileFailed {
                    worker,
                    job,
                    tile: 0,
                    message: "out of memory".into(),
                }),
            );
        }
    }
    let recorded = effects.iter().find_map(|e| match e {
        Effect::Job(lifecycle::Action::RecordEnd { state, error, .. }) => {
            Some((*state, error.clone()))
        }
        _ => None,
    });
    let (state, error) = recorded.expect("the end is recorded");
    assert_eq!(state, JobState::Failed);
    assert!(error.unwrap().contains("out of memory"));
}

/// A job whose row could not be written is refused to its client and leaves nothing:
/// its tiles never go out, and its plan is forgotten.
#[test]
fn a_job_whose_row_fails_is_refused_and_never_handed_out() {
    let mut f = farm();
    join(&mut f, 1, 2);
    let job = f.admit(0, &request(), plan(4)).unwrap();
    let failed = f.handle(
        0,
        Input::Job(lifecycle::Event::StoreFailed {
            job,
            message: "disk full".into(),
        }),
    );
    assert!(assigned(&failed).is_empty());
    assert!(failed
        .iter()
        .any(|e| matches!(e, Effect::Job(lifecycle::Action::RefuseStored { .. }))));
    assert!(f.plans.is_empty());
    assert_eq!(f.tiles().tiles_in_flight(), 0);
}

/// The time reaches both machines: a worker silent past the heartbeat timeout is
/// dropped, and the core's deadline is the earlier of the two machines'.
#[test]
fn the_time_reaches_both_machines_and_the_deadline_is_the_earliest() {
    let mut f = farm();
    join(&mut f, 1, 1);
    let mut dropped = false;
    while !dropped {
        let deadline = f.next_deadline().expect("a worker's heartbeat is awaited");
        assert_eq!(
            Some(deadline),
            [f.tiles().next_deadline(), f.lifecycle().next_deadline()]
                .into_iter()
                .flatten()
                .min()
        );
        assert!(deadline <= Policy::default().heartbeat_timeout + 1_000);
        let effects = f.handle(deadline, Input::Timeout);
        dropped = effects.contains(&Effect::Tiles(Action::DropWorker { worker: 1 }));
    }
}

/// A studio view's pass goes ahead of a batch job stored before it.
#[test]
fn an_interactive_job_goes_ahead_of_a_batch_job() {
    let mut f = farm();
    let batch = f.admit(0, &request(), plan(4)).unwrap();
    f.handle(0, Input::Job(lifecycle::Event::Stored { job: batch }));
    let view = TilePlan {
        interactive: true,
        ..plan(4)
    };
    let pass = f.admit(0, &request(), view).unwrap();
    let stored = f.handle(0, Input::Job(lifecycle::Event::Stored { job: pass }));
    assert!(assigned(&stored).is_empty(), "no worker yet: {stored:?}");
    let joined = join(&mut f, 1, 1);
    let first: Vec<JobId> = assigned(&joined).iter().map(|a| a.1).collect();
    assert_eq!(first.first(), Some(&pass), "{joined:?}");
}

/// Storage that cannot write stops both machines: no tile goes out and no job is
/// admitted, until it writes again.
#[test]
fn storage_that_cannot_write_stops_both_machines_until_it_can() {
    let mut f = farm();
    let job = f.admit(0, &request(), plan(2)).unwrap();
    f.handle(0, Input::Job(lifecycle::Event::Stored { job }));
    f.handle(0, Input::Storage(Err("disk full".into())));
    assert!(assigned(&join(&mut f, 1, 2)).is_empty());
    let refused = f.admit(0, &request(), plan(2)).unwrap_err();
    assert_eq!(refused.kind, RefusalKind::Unavailable);
    let back = f.handle(1, Input::Storage(Ok(())));
    assert_eq!(assigned(&back), vec![(1, job, 0), (1, job, 1)]);
    assert!(f.admit(1, &request(), plan(2)).is_ok());
}

/// A new priority given while the job's row is being written holds once its tiles go
/// out.
#[test]
fn a_priority_set_before_the_job_is_stored_holds_when_it_goes_out() {
    let mut f = farm();
    let first = f.admit(0, &request(), plan(4)).unwrap();
    let urgent = f.admit(0, &request(), plan(4)).unwrap();
    f.handle(
        0,
        Input::Tiles(Event::SetPriority {
            job: urgent,
            priority: 5,
        }),
    );
    f.handle(0, Input::Job(lifecycle::Event::Stored { job: first }));
    f.handle(0, Input::Job(lifecycle::Event::Stored { job: urgent }));
    let joined = join(&mut f, 1, 1);
    assert_eq!(
        assigned(&joined).first().map(|a| a.1),
        Some(urgent),
        "{joined:?}"
    );
}

pub(super) fn stored_job(f: &mut Farm, tiles: u32) -> JobId {
    let job = f.admit(0, &request(), plan(tiles)).unwrap();
    f.handle(0, Input::Job(lifecycle::Event::Stored { job }));
    job
}

fn image_due(effects: &[Effect], job: JobId) -> bool {
    effects.contains(&Effect::Job(lifecycle::Action::StoreImage { job }))
}

/// A result that arrives after its job was cancelled counts for nothing: no tile is
/// accepted, and the image never becomes due.
#[test]
fn a_result_racing_a_cancel_counts_for_nothing() {
    let mut f = farm();
    join(&mut f, 1, 1);
    let job = stored_job(&mut f, 1);
    f.handle(1, Input::Job(lifecycle::Event::Cancel { job }));
    let late = done(&mut f, 1, job, 0);
    assert!(
        !late
            .iter()
            .any(|e| matches!(e, Effect::Tiles(Action::AcceptTile { .. }))),
        "{late:?}"
    );
    assert!(!image_due(&late, job));
    assert_eq!(phase(&f, job).visible(), JobState::Cancelled);
}

/// A delete asked while the job runs is refused for its state, and the job goes on;
/// once it has ended and its end is written, the delete goes through.
#[test]
fn a_delete_racing_a_running_job_is_refused_until_it_has_ended() {
    let mut f = farm();
    join(&mut f, 1, 1);
    let job = stored_job(&mut f, 1);
    let refused = f.handle(1, Input::Job(lifecycle::Event::Delete { job }));
    match &refused[..] {
        [Effect::Job(lifecycle::Action::Reply {
            result: Err(refusal),
            ..
        })] => assert_eq!(refusal.kind, RefusalKind::State),
        other => panic!("{other:?}"),
    }
    assert!(image_due(&done(&mut f, 1, job, 0), job));
    f.handle(
        2,
        Input::Job(lifecycle::Event::ImageStored {
            job,
            result: Ok(()),
        }),
    );
    f.handle(3, Input::Job(lifecycle::Event::EndRecorded { job }));
    let deleting = f.handle(4, Input::Job(lifecycle::Event::Delete { job }));
    assert!(deleting.contains(&Effect::Job(lifecycle::Action::DeleteStored { job })));
    f.handle(5, Input::Job(lifecycle::Event::Deleted { job }));
    assert!(f.lifecycle().job(job).is_none());
    assert!(f.plans.is_empty(), "a deleted job's plan is forgotten");
}

/// A paused job hands out nothing, but a result of a tile already out still counts;
/// resumed, the rest goes out and the job ends.
#[test]
fn a_pause_keeps_results_that_race_it_and_the_job_ends_once_resumed() {
    let mut f = farm();
    join(&mut f, 1, 1);
    let job = stored_job(&mut f, 3);
    let out = f.tiles().held_by(1);
    assert!(out > 0);
    f.handle(1, Input::Tiles(Event::PauseJob { job }));
    let first = done(&mut f, 1, job, 0);
    assert!(first.contains(&Effect::Tiles(Action::AcceptTile { job, tile: 0 })));
    assert!(assigned(&first).is_empty(), "paused: {first:?}");
    let resumed = f.handle(2, Input::Tiles(Event::ResumeJob { job }));
    let mut effects = resumed;
    let mut rounds = 0;
    while !image_due(&effects, job) {
        rounds += 1;
        assert!(rounds < 10, "the job never ends");
        let tiles: Vec<u32> = (0..3)
            .filter(|&t| {
                effects.contains(&Effect::Tiles(Action::Assign {
                    worker: 1,
                    job,
                    tile: t,
                }))
            })
            .collect();
        let mut next = Vec::new();
        for t in tiles.into_iter().chain(1..3) {
            next.extend(done(&mut f, 1, job, t));
        }
        effects = next;
    }
}

/// A failed job retried takes back what persistence holds: only the tiles not stored
/// go out again, and the image is due once they are in.
#[test]
fn a_retried_job_renders_only_the_tiles_not_stored() {
    let mut f = farm();
    let job = f.admit(0, &request(), plan(3)).unwrap();
    f.handle(0, Input::Job(lifecycle::Event::Stored { job }));
    f.handle(0, Input::Job(lifecycle::Event::Cancel { job }));
    f.handle(1, Input::Job(lifecycle::Event::EndRecorded { job }));
    let retried = f.handle(
        2,
        Input::Job(lifecycle::Event::Retry {
            job,
            started: true,
            pixels: 64,
        }),
    );
    assert!(retried.contains(&Effect::Job(lifecycle::Action::Reply {
        job,
        result: Ok(Reply::Retried),
    })));
    join(&mut f, 1, 4);
    let resumed = f.resume_job(3, job, plan(3), &[0, 2]);
    assert_eq!(assigned(&resumed), vec![(1, job, 1)]);
    assert!(image_due(&done(&mut f, 1, job, 1), job));
}

/// After a restart, a job whose every tile is stored needs no worker: its image is
/// due at once.
#[test]
fn a_job_restored_with_every_tile_stored_is_due_at_once() {
    let mut f = farm();
    f.handle(
        0,
        Input::Job(lifecycle::Event::Restored {
            job: 4,
            state: JobState::Running,
            error: None,
            started: true,
            pixels: 64,
            ended_ago: 0,
        }),
    );
    let effects = f.resume_job(0, 4, plan(2), &[0, 1]);
    assert!(image_due(&effects, 4), "{effects:?}");
}

/// Two machines' copies of a straggler: the first result is accepted, the second is a
/// duplicate the executor compares with it (a copy that differs is a quarantine, which
/// the executor reports back as an input); the job ends once, with its last tile.
#[test]
fn a_stragglers_second_copy_is_a_duplicate_not_a_second_tile() {
    let mut f = Farm::new(Scheduler::new(), Lifecycle::new(Limits::default(), 1));
    join(&mut f, 1, 1);
    let job = stored_job(&mut f, 2);
    // A second machine joins once every tile is out: it gets copies.
    let copy = assigned(&join(&mut f, 2, 1));
    assert!(!copy.is_empty(), "{copy:?}");
    let tile = copy[0].2;
    let first = done(&mut f, 1, job, tile);
    assert!(first.contains(&Effect::Tiles(Action::AcceptTile { job, tile })));
    assert!(!image_due(&first, job));
    let second = done(&mut f, 2, job, tile);
    assert!(
        second.contains(&Effect::Tiles(Action::DuplicateResult { job, tile })),
        "{second:?}"
    );
    assert!(!image_due(&second, job));
    let last = done(&mut f, 1, job, 1 - tile);
    assert!(image_due(&last, job), "{last:?}");
}

/// A machine caught returning wrong pixels gets no tile again, and the tiles it
/// rendered in an active job are taken back (the core knows which they are): they go
/// to another machine, and the job's image is due only once they are in again. A
/// finished job's tiles are too late to take back.
#[test]
fn a_quarantine_takes_back_the_machines_tiles_and_the_job_waits_for_them() {
    let mut f = farm();
    join(&mut f, 1, 1);
    let finished = stored_job(&mut f, 1);
    assert!(image_due(&done(&mut f, 1, finished, 0), finished));
    let job = stored_job(&mut f, 3);
    assert!(done(&mut f, 1, job, 0).contains(&Effect::Tiles(Action::AcceptTile { job, tile: 0 })));
    join(&mut f, 2, 4);
    let caught = f.handle(2, quarantine("m1"));
    assert_eq!(
        caught[1],
        Effect::TakenBack {
            job,
            tiles: vec![0]
        },
        "only the active job's tile, before anything goes out: {caught:?}"
    );
    assert_eq!(
        caught
            .iter()
            .filter(|e| matches!(e, Effect::TakenBack { .. }))
            .count(),
        1
    );
    let again = assigned(&caught);
    assert!(
        again.iter().all(|a| a.0 == 2),
        "only the other machine: {caught:?}"
    );
    assert!(
        again.contains(&(2, job, 0)),
        "the taken-back tile goes out: {caught:?}"
    );
    // The quarantined machine's late results count for nothing.
    let late = done(&mut f, 1, job, 1);
    assert!(!late
        .iter()
        .any(|e| matches!(e, Effect::Tiles(Action::AcceptTile { .. }))));
    // Worker 2 holds every tile left: tile 0 again, and the two worker 1 held.
    let mut effects = Vec::new();
    for tile in 0..3 {
        assert!(
            !image_due(&effects, job),
            "due before tile {tile}: {effects:?}"
        );
        effects = done(&mut f, 2, job, tile);
    }
    assert!(image_due(&effects, job), "{effects:?}");
}

/// A worker whose render threads hang keeps talking but returns nothing: once its
/// leases run out and its allowance is past, it is marked unresponsive, its tiles go
/// to a worker that renders, and the job's image is due all the same.
#[test]
fn a_hung_worker_is_worked_around_and_the_job_ends() {
    let mut f = farm();
    join(&mut f, 1, 1);
    let job = stored_job(&mut f, 2);
    assert_eq!(f.tiles().held_by(1), 2);
    join(&mut f, 2, 1);
    let mut now = 0;
    let mut marked = false;
    let mut taken = Vec::new();
    while now < 5 * 60_000 && !marked {
        now += 1_000;
        for worker in [1, 2] {
            f.handle(now, Input::Tiles(Event::Heartbeat { worker }));
        }
        let effects = f.handle(now, Input::Timeout);
        marked |= effects.iter().any(|e| {
            matches!(
                e,
                Effect::Tiles(Action::WorkerUnresponsive { worker: 1, .. })
            )
        });
        taken.extend(assigned(&effects).into_iter().filter(|a| a.0 == 2));
    }
    assert!(marked, "worker 1 never marked unresponsive");
    let mut effects = Vec::new();
    for _ in 0..4 {
        for (_, _, tile) in std::mem::take(&mut taken) {
            effects = f.handle(
                now,
                Input::Tiles(Event::TileDone {
                    worker: 2,
                    job,
                    tile,
                }),
            );
            taken.extend(assigned(&effects).into_iter().filter(|a| a.0 == 2));
        }
        if image_due(&effects, job) {
            break;
        }
        now += 1_000;
        let timeout = f.handle(now, Input::Timeout);
        taken.extend(assigned(&timeout).into_iter().filter(|a| a.0 == 2));
    }
    assert!(image_due(&effects, job), "{effects:?}");
}

/// What a quarantine takes back is what the machine rendered as the core saw it: tiles
/// stored before a restart (told with `restored_tiles`), not a tile an operator put
/// back in the queue since, and only in jobs still active.
#[test]
fn a_quarantine_takes_back_restored_tiles_but_not_requeued_ones() {
    let mut f = farm();
    join(&mut f, 1, 1);
    // A job taken back after a restart: tiles 0 and 1 stored, by m7 and m1.
    let job = f.admit(0, &request(), plan(4)).unwrap();
    f.handle(0, Input::Job(lifecycle::Event::Stored { job }));
    f.handle(0, Input::Tiles(Event::CancelJob { job }));
    let resumed = f.resume_job(1, job, plan(4), &[0, 1]);
    f.restored_tiles(job, &[(0, "m7"), (1, "m1")]);
    // m1 renders a tile now; an operator puts tile 1 back in the queue.
    let out: Vec<u32> = assigned(&resumed).iter().map(|a| a.2).collect();
    assert!(!out.is_empty(), "{resumed:?}");
    done(&mut f, 1, job, out[0]);
    f.handle(
        2,
        Input::Tiles(Event::RequeueTiles {
            job,
            tiles: vec![1],
        }),
    );
    let caught = f.handle(3, quarantine("m1"));
    assert_eq!(
        caught[1],
        Effect::TakenBack {
            job,
            tiles: vec![out[0]]
        },
        "{caught:?}"
    );
    let seven = f.handle(4, quarantine("m7"));
    assert_eq!(
        seven[1],
        Effect::TakenBack {
            job,
            tiles: vec![0]
        },
        "{seven:?}"
    );
}
