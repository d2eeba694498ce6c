//! Sequences in the core: frames started as the workers' credit allows, frame jobs
//! stored, refused and ended, operators' controls racing with them, and a restart.
//! A small executor here admits the frames the core starts and writes every row at
//! once, as the daemon does over time.

use protocol::JobState;

use super::tests::{assigned, done, farm, join, phase, plan, request};
use super::*;
use crate::lifecycle::{Limits, Phase};
use crate::sequence::FrameState;
use crate::Policy;

const SEQ: JobId = 1_000;
/// Tiles of a frame: more than a worker of one thread may hold.
const TILES: u32 = 8;

/// Carries out the sequence's effects as the daemon would with storage that writes
/// at once: each frame started is admitted and its row written. Returns every effect,
/// those of the follow-ups included, and the frame jobs admitted.
fn run(f: &mut Farm, now: Millis, first: Vec<Effect>) -> (Vec<Effect>, Vec<JobId>) {
    let mut all = Vec::new();
    let mut jobs = Vec::new();
    let mut queue = std::collections::VecDeque::from(first);
    while let Some(effect) = queue.pop_front() {
        if let Effect::Sequence(SequenceAction::StartFrames { sequence, frames }) = &effect {
            for &frame in frames {
                if let Ok(job) = f.admit_frame(now, *sequence, frame, &request(), plan(TILES)) {
                    jobs.push(job);
                    queue.extend(f.handle(now, Input::Job(lifecycle::Event::Stored { job })));
                }
            }
        }
        all.push(effect);
    }
    (all, jobs)
}

fn sequence_actions(effects: &[Effect]) -> Vec<SequenceAction> {
    effects
        .iter()
        .filter_map(|e| match e {
            Effect::Sequence(a) => Some(a.clone()),
            _ => None,
        })
        .collect()
}

/// Renders a frame job to its end: its tiles (by worker 1), its image stored, its
/// end written.
fn finish(f: &mut Farm, job: JobId) -> Vec<Effect> {
    let mut effects = Vec::new();
    for tile in 0..TILES {
        effects.extend(done(f, 1, job, tile));
    }
    effects.extend(f.handle(
        5,
        Input::Job(lifecycle::Event::ImageStored {
            job,
            result: Ok(()),
        }),
    ));
    effects.extend(f.handle(6, Input::Job(lifecycle::Event::EndRecorded { job })));
    effects
}

fn stored_sequence(f: &mut Farm, first: u32, last: u32) -> (Vec<Effect>, Vec<JobId>) {
    f.enter_sequence(SEQ, SequenceRun::new(first, last, TILES));
    let stored = f.handle(0, Input::Sequence(SequenceInput::Stored { sequence: SEQ }));
    run(f, 0, stored)
}

/// Nothing starts before the sequence's row is written; then its first frame, and
/// the next only once the tiles waiting would leave the workers' credit idle; each
/// frame's end starts the next, and the last one ends the sequence, written once.
#[test]
fn frames_start_as_the_credit_allows_and_the_last_one_ends_the_sequence() {
    let mut f = farm();
    join(&mut f, 1, 1);
    f.enter_sequence(SEQ, SequenceRun::new(1, 3, TILES));
    let nothing = f.handle(0, Input::Timeout);
    assert!(sequence_actions(&nothing).is_empty(), "{nothing:?}");
    let stored = f.handle(0, Input::Sequence(SequenceInput::Stored { sequence: SEQ }));
    let (effects, jobs) = run(&mut f, 0, stored);
    // One frame runs; its tiles fill the single worker: the next frame waits.
    assert_eq!(jobs.len(), 1, "{effects:?}");
    let first = jobs[0];
    assert!(
        sequence_actions(&effects).contains(&SequenceAction::FrameOut {
            sequence: SEQ,
            frame: 1,
            job: first,
        })
    );
    // The worker's credit (two tiles) is full.
    assert_eq!(assigned(&effects).len(), 2);
    let mut ended = Vec::new();
    let mut next = vec![first];
    while let Some(job) = next.pop() {
        let effects = finish(&mut f, job);
        let (effects, jobs) = run(&mut f, 6, effects);
        ended.extend(sequence_actions(&effects).into_iter().filter(|a| {
            matches!(
                a,
                SequenceAction::FrameEnded { .. } | SequenceAction::Ended { .. }
            )
        }));
        next.extend(jobs);
    }
    let frames: Vec<u32> = ended
        .iter()
        .filter_map(|a| match a {
            SequenceAction::FrameEnded { frame, state, .. } => {
                assert_eq!(*state, JobState::Done);
                Some(*frame)
            }
            _ => None,
        })
        .collect();
    assert_eq!(frames, vec![1, 2, 3], "frames end in order");
    assert_eq!(
        ended.last(),
        Some(&SequenceAction::Ended {
            sequence: SEQ,
            state: JobState::Done
        })
    );
    let again = f.handle(7, Input::Timeout);
    assert!(sequence_actions(&again).is_empty(), "the end is told once");
}

/// A sequence cancelled while a frame job is being stored: the other frames never
/// start, the frame job is cancelled as soon as its row is written (its tiles, out
/// already, are withdrawn), and its end ends the sequence as cancelled.
#[test]
fn a_frame_stored_after_its_sequence_was_cancelled_is_cancelled_at_once() {
    let mut f = farm();
    join(&mut f, 1, 1);
    f.enter_sequence(SEQ, SequenceRun::new(1, 3, TILES));
    let started = f.handle(0, Input::Sequence(SequenceInput::Stored { sequence: SEQ }));
    assert_eq!(
        sequence_actions(&started),
        vec![SequenceAction::StartFrames {
            sequence: SEQ,
            frames: vec![1]
        }]
    );
    let job = f.admit_frame(0, SEQ, 1, &request(), plan(TILES)).unwrap();
    let cancel = f.handle(1, Input::Sequence(SequenceInput::Cancel { sequence: SEQ }));
    assert!(sequence_actions(&cancel).is_empty(), "{cancel:?}");
    let frames = f.sequence(SEQ).unwrap().frames();
    assert_eq!(frames.frame(2), Some(FrameState::Cancelled));
    assert_eq!(frames.frame(1), Some(FrameState::Starting));
    let stored = f.handle(2, Input::Job(lifecycle::Event::Stored { job }));
    let out = stored
        .iter()
        .position(|e| matches!(e, Effect::Sequence(SequenceAction::FrameOut { .. })))
        .expect("the frame is out");
    let withdrawn = stored
        .iter()
        .position(|e| *e == Effect::Tiles(Action::CancelOnWorker { worker: 1, job }))
        .expect("its tile is withdrawn");
    assert!(out < withdrawn);
    assert!(matches!(phase(&f, job), Phase::Ended { .. }));
    let ended = f.handle(3, Input::Job(lifecycle::Event::EndRecorded { job }));
    assert_eq!(
        sequence_actions(&ended),
        vec![
            SequenceAction::FrameEnded {
                sequence: SEQ,
                frame: 1,
                job,
                state: JobState::Cancelled
            },
            SequenceAction::Ended {
                sequence: SEQ,
                state: JobState::Cancelled
            }
        ]
    );
}

/// A frame refused admission waits, and the sequence tries it again a second later,
/// not before; a frame job whose row cannot be written waits the same way.
#[test]
fn a_refused_frame_is_tried_again_after_a_second() {
    let policy = Policy {
        max_attempts: 2,
        speculate: false,
        ..Policy::default()
    };
    let limits = Limits {
        max_active_per_client: 1,
        ..Limits::default()
    };
    let mut f = Farm::new(Scheduler::with_policy(policy), Lifecycle::new(limits, 1));
    join(&mut f, 1, 8);
    let client = Some("10.0.0.1".parse().unwrap());
    let request = lifecycle::Request {
        client,
        ..request()
    };
    f.enter_sequence(SEQ, SequenceRun::new(1, 2, TILES));
    let started = f.handle(0, Input::Sequence(SequenceInput::Stored { sequence: SEQ }));
    assert_eq!(
        sequence_actions(&started),
        vec![SequenceAction::StartFrames {
            sequence: SEQ,
            frames: vec![1, 2]
        }]
    );
    let first = f.admit_frame(0, SEQ, 1, &request, plan(TILES)).unwrap();
    assert!(f.admit_frame(0, SEQ, 2, &request, plan(TILES)).is_err());
    let frames = f.sequence(SEQ).unwrap().frames();
    assert_eq!(frames.frame(2), Some(FrameState::Pending));
    assert_eq!(f.next_deadline(), Some(FRAME_RETRY_MS));
    // The first frame's row is written, its tile goes out: the refused frame is not
    // tried before its second is up.
    let stored = f.handle(10, Input::Job(lifecycle::Event::Stored { job: first }));
    assert!(!sequence_actions(&stored)
        .iter()
        .any(|a| matches!(a, SequenceAction::StartFrames { .. })));
    let retried = f.handle(FRAME_RETRY_MS, Input::Timeout);
    assert_eq!(
        sequence_actions(&retried),
        vec![SequenceAction::StartFrames {
            sequence: SEQ,
            frames: vec![2]
        }]
    );
    // Admitted this time (another client), but its row cannot be written.
    let second = f
        .admit_frame(
            FRAME_RETRY_MS,
            SEQ,
            2,
            &super::tests::request(),
            plan(TILES),
        )
        .unwrap();
    let failed = f.handle(
        FRAME_RETRY_MS,
        Input::Job(lifecycle::Event::StoreFailed {
            job: second,
            message: "disk full".into(),
        }),
    );
    assert!(sequence_actions(&failed).is_empty());
    assert_eq!(
        f.sequence(SEQ).unwrap().frames().frame(2),
        Some(FrameState::Pending)
    );
    assert_eq!(f.next_deadline(), Some(2 * FRAME_RETRY_MS));
}

/// A cancelled frame requeued after the sequence ended: its old job is deleted, the
/// sequence runs again (written once), the frame starts alone, and its end ends the
/// sequence again.
#[test]
fn a_requeued_frame_runs_an_ended_sequence_again() {
    let mut f = farm();
    join(&mut f, 1, 4);
    let (_, jobs) = stored_sequence(&mut f, 1, 1);
    let old = jobs[0];
    // An operator cancels the frame job itself.
    f.handle(1, Input::Job(lifecycle::Event::Cancel { job: old }));
    let ended = f.handle(2, Input::Job(lifecycle::Event::EndRecorded { job: old }));
    assert!(sequence_actions(&ended).contains(&SequenceAction::Ended {
        sequence: SEQ,
        state: JobState::Cancelled
    }));
    assert_eq!(
        f.sequence(SEQ).unwrap().recorded(),
        Some(JobState::Cancelled)
    );
    let requeue = Input::Sequence(SequenceInput::Requeue {
        sequence: SEQ,
        frames: vec![1],
    });
    let requeued = f.handle(3, requeue);
    let (effects, jobs) = run(&mut f, 3, requeued);
    let actions = sequence_actions(&effects);
    assert_eq!(
        actions[0],
        SequenceAction::Requeued {
            sequence: SEQ,
            frames: vec![1],
            old: vec![old]
        }
    );
    assert!(effects.contains(&Effect::Job(lifecycle::Action::DeleteStored { job: old })));
    assert!(actions.contains(&SequenceAction::Running { sequence: SEQ }));
    assert_eq!(jobs.len(), 1);
    assert_eq!(f.sequence(SEQ).unwrap().recorded(), None);
    // The old job's end, written late, changes nothing.
    let late = f.handle(4, Input::Job(lifecycle::Event::EndRecorded { job: old }));
    assert!(sequence_actions(&late).is_empty());
    let (effects, _) = {
        let finished = finish(&mut f, jobs[0]);
        run(&mut f, 6, finished)
    };
    assert!(sequence_actions(&effects).contains(&SequenceAction::Ended {
        sequence: SEQ,
        state: JobState::Done
    }));
}

/// Paused, a sequence starts no frame (its frame jobs are paused by the executor);
/// resumed, it starts the frames the credit allows.
#[test]
fn a_paused_sequence_starts_no_frame_until_resumed() {
    let mut f = farm();
    join(&mut f, 1, 1);
    let (_, jobs) = stored_sequence(&mut f, 1, 2);
    let pause = f.handle(
        1,
        Input::Sequence(SequenceInput::Pause {
            sequence: SEQ,
            paused: true,
        }),
    );
    assert_eq!(
        sequence_actions(&pause),
        vec![SequenceAction::Paused {
            sequence: SEQ,
            paused: true,
            jobs: jobs.clone()
        }]
    );
    let (effects, started) = {
        let finished = finish(&mut f, jobs[0]);
        run(&mut f, 6, finished)
    };
    assert!(started.is_empty(), "{effects:?}");
    let resume = Input::Sequence(SequenceInput::Pause {
        sequence: SEQ,
        paused: false,
    });
    let resumed = f.handle(7, resume);
    let (_, started) = run(&mut f, 7, resumed);
    assert_eq!(started.len(), 1);
    assert_eq!(f.sequence(SEQ).unwrap().frames().job(2), Some(started[0]));
}

/// A deleted sequence deletes its frame jobs first, then its row; once that is gone
/// the core forgets it.
#[test]
fn a_deleted_sequence_goes_after_its_frame_jobs() {
    let mut f = farm();
    join(&mut f, 1, 4);
    let (_, jobs) = stored_sequence(&mut f, 1, 1);
    {
        let finished = finish(&mut f, jobs[0]);
        run(&mut f, 6, finished)
    };
    let delete = f.handle(7, Input::Sequence(SequenceInput::Delete { sequence: SEQ }));
    let frame_deleted = delete
        .iter()
        .position(|e| *e == Effect::Job(lifecycle::Action::DeleteStored { job: jobs[0] }))
        .expect("its frame job is deleted");
    let row = delete
        .iter()
        .position(|e| *e == Effect::Sequence(SequenceAction::DeleteStored { sequence: SEQ }))
        .expect("then its row");
    assert!(frame_deleted < row);
    assert!(f.sequence(SEQ).unwrap().deleting());
    f.handle(8, Input::Sequence(SequenceInput::Deleted { sequence: SEQ }));
    assert!(f.sequence(SEQ).is_none());
}

/// After a restart: a sequence that was cancelled starts none of its pending frames;
/// another resumes its active frame job where it was and starts its next frame as the
/// credit allows, and its end is written only when every frame has ended.
#[test]
fn a_restart_takes_sequences_back_as_they_stood() {
    let mut f = farm();
    join(&mut f, 1, 1);
    const OTHER: JobId = 2_000;
    f.enter_sequence(
        OTHER,
        SequenceRun::restored(1, 3, TILES, false, Some(JobState::Cancelled)),
    );
    f.restore_frame(OTHER, 1, 2_001, JobState::Done);
    f.enter_sequence(SEQ, SequenceRun::restored(1, 3, TILES, false, None));
    f.restore_frame(SEQ, 1, 1_001, JobState::Done);
    // Frame 2's job was running: the daemon takes it back as any job.
    let running = f.issue_id();
    f.restore_frame(SEQ, 2, running, JobState::Running);
    let restored = f.handle(0, Input::Sequence(SequenceInput::Restored));
    let actions = sequence_actions(&restored);
    assert!(
        !actions.iter().any(|a| matches!(
            a,
            SequenceAction::StartFrames {
                sequence: OTHER,
                ..
            } | SequenceAction::Ended { .. }
                | SequenceAction::Running { .. }
        )),
        "{actions:?}"
    );
    assert_eq!(
        f.sequence(OTHER).unwrap().frames().frame(2),
        Some(FrameState::Cancelled)
    );
    // Frame 2's job is not in the scheduler (nothing waits): frame 3 starts.
    assert_eq!(
        actions,
        vec![SequenceAction::StartFrames {
            sequence: SEQ,
            frames: vec![3]
        }]
    );
    assert_eq!(f.sequence(SEQ).unwrap().frames().state(), JobState::Running);
}

/// A sequence cancelled while its only frame's row was being written, and that row
/// then cannot be written: the frame is cancelled, and the sequence ends cancelled.
#[test]
fn a_cancelled_sequence_whose_last_frame_cannot_be_stored_ends() {
    let mut f = farm();
    join(&mut f, 1, 1);
    f.enter_sequence(SEQ, SequenceRun::new(1, 1, TILES));
    f.handle(0, Input::Sequence(SequenceInput::Stored { sequence: SEQ }));
    let job = f.admit_frame(0, SEQ, 1, &request(), plan(TILES)).unwrap();
    let cancel = f.handle(1, Input::Sequence(SequenceInput::Cancel { sequence: SEQ }));
    assert!(sequence_actions(&cancel).is_empty());
    let failed = f.handle(
        2,
        Input::Job(lifecycle::Event::StoreFailed {
            job,
            message: "disk full".into(),
        }),
    );
    assert_eq!(
        sequence_actions(&failed),
        vec![SequenceAction::Ended {
            sequence: SEQ,
            state: JobState::Cancelled
        }]
    );
}
