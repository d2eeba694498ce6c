//! A job's life: acknowledged once stored, done once its end is written, failures and
//! cancels final, storage outages, retention, restarts, and the bound on active pixels.

use super::*;

fn request(client: u8) -> Request {
    Request {
        client: Some(IpAddr::from([127, 0, 0, client])),
        scene_bytes: 100,
        objects: 3,
        width: 64,
        height: 48,
        aa: 2,
    }
}

fn stored(l: &mut Lifecycle, now: Millis) -> JobId {
    let job = l.admit(now, &request(1)).unwrap();
    assert_eq!(
        l.handle(now, Event::Stored { job }),
        [Action::Acknowledge { job }]
    );
    job
}

#[test]
fn a_job_is_acknowledged_only_once_stored_and_done_only_once_its_end_is_written() {
    let mut l = Lifecycle::new(Limits::default(), 7);
    let job = l.admit(0, &request(1)).unwrap();
    assert_eq!(job, 7);
    assert_eq!(l.job(job).unwrap().phase.visible(), JobState::Queued);
    assert_eq!(
        l.handle(1, Event::Stored { job }),
        [Action::Acknowledge { job }]
    );
    l.handle(2, Event::TileAssigned { job });
    assert_eq!(l.job(job).unwrap().phase, Phase::Running);
    assert_eq!(
        l.handle(3, Event::TilesComplete { job }),
        [Action::StoreImage { job }]
    );
    let ended = l.handle(
        4,
        Event::ImageStored {
            job,
            result: Ok(()),
        },
    );
    assert_eq!(
        ended,
        [Action::RecordEnd {
            job,
            state: JobState::Done,
            error: None
        }]
    );
    assert_eq!(l.job(job).unwrap().phase.visible(), JobState::Running);
    l.handle(5, Event::EndRecorded { job });
    assert_eq!(l.job(job).unwrap().phase.visible(), JobState::Done);
    assert_eq!(l.job(job).unwrap().ended, Some(4));
}

#[test]
fn a_failed_store_releases_the_slot_and_never_reuses_the_id() {
    let mut l = Lifecycle::new(
        Limits {
            max_active_per_client: 1,
            ..Limits::default()
        },
        1,
    );
    let job = l.admit(0, &request(1)).unwrap();
    assert!(l
        .admit(0, &request(1))
        .unwrap_err()
        .message
        .contains("already has 1"));
    let refused = l.handle(
        1,
        Event::StoreFailed {
            job,
            message: "disk full".into(),
        },
    );
    assert_eq!(
        refused,
        [Action::RefuseStored {
            job,
            message: "disk full".into()
        }]
    );
    assert!(l.job(job).is_none());
    assert_eq!(l.admit(2, &request(1)), Ok(job + 1));
}

#[test]
fn storage_down_refuses_submissions_and_retries_images_until_it_is_back() {
    let mut l = Lifecycle::new(Limits::default(), 1);
    let job = stored(&mut l, 0);
    l.handle(1, Event::TilesComplete { job });
    l.handle(
        2,
        Event::StorageUnavailable {
            reason: "No space left on device".into(),
        },
    );
    let refused = l.admit(3, &request(2)).unwrap_err();
    assert!(
        refused.message.contains("cannot store new jobs"),
        "{refused}"
    );
    assert!(refused.message.contains("No space left"), "{refused}");
    // A failed store is not a failure of the job: it is retried.
    l.handle(
        4,
        Event::ImageStored {
            job,
            result: Err("No space left on device".into()),
        },
    );
    assert_eq!(l.job(job).unwrap().phase.visible(), JobState::Running);
    assert_eq!(l.next_deadline(), Some(504));
    assert!(l.handle(100, Event::Timeout).is_empty());
    assert_eq!(l.handle(504, Event::Timeout), [Action::StoreImage { job }]);
    l.handle(
        505,
        Event::ImageStored {
            job,
            result: Err("still full".into()),
        },
    );
    // Storage back: the image is stored at once, not at the next retry.
    assert_eq!(
        l.handle(600, Event::StorageAvailable),
        [Action::StoreImage { job }]
    );
    assert_eq!(l.admit(601, &request(2)), Ok(job + 1));
}

#[test]
fn failure_and_cancel_are_final_and_written_and_only_ended_jobs_are_deleted() {
    let mut l = Lifecycle::new(Limits::default(), 1);
    let a = stored(&mut l, 0);
    let b = stored(&mut l, 0);
    let failed = l.handle(
        1,
        Event::TilesFailed {
            job: a,
            message: "tile 3 failed 5 times".into(),
        },
    );
    assert!(matches!(
        &failed[..],
        [Action::RecordEnd {
            state: JobState::Failed,
            ..
        }]
    ));
    // A late completion changes nothing.
    assert!(l.handle(2, Event::TilesComplete { job: a }).is_empty());
    let delete_running = l.handle(3, Event::Delete { job: b });
    assert_eq!(
        delete_running,
        [Action::Reply {
            job: b,
            result: Err(Refusal::state(format!(
                "job {b} is queued: cancel it first"
            )))
        }]
    );
    let cancelled = l.handle(4, Event::Cancel { job: b });
    assert_eq!(cancelled[0], Action::CancelTiles { job: b });
    assert_eq!(
        cancelled.last(),
        Some(&Action::Reply {
            job: b,
            result: Ok(Reply::Cancelled)
        })
    );
    assert_eq!(l.job(b).unwrap().phase.visible(), JobState::Cancelled);
    let again = l.handle(5, Event::Cancel { job: b });
    assert_eq!(
        again,
        [Action::Reply {
            job: b,
            result: Err(Refusal::state(format!("job {b} is already cancelled")))
        }]
    );
    // Deleted before its end is written: the deletion waits for the write.
    assert_eq!(
        l.handle(6, Event::Delete { job: b }),
        [Action::Reply {
            job: b,
            result: Ok(Reply::Deleting)
        }]
    );
    assert_eq!(
        l.handle(6, Event::EndRecorded { job: b }),
        [Action::DeleteStored { job: b }]
    );
    assert!(
        l.handle(7, Event::Delete { job: b })
            .iter()
            .all(|a| !matches!(a, Action::DeleteStored { .. })),
        "one deletion at a time"
    );
    l.handle(8, Event::Deleted { job: b });
    assert!(l.job(b).is_none());
    assert_eq!(
        l.handle(9, Event::Cancel { job: 99 }),
        [Action::Reply {
            job: 99,
            result: Err(Refusal::not_found("no job 99 on this coordinator"))
        }]
    );
}

#[test]
fn ended_jobs_are_deleted_after_the_retention() {
    let mut l = Lifecycle::new(
        Limits {
            retention: Some(1_000),
            ..Limits::default()
        },
        1,
    );
    let job = stored(&mut l, 0);
    l.handle(10, Event::Cancel { job });
    l.handle(11, Event::EndRecorded { job });
    assert_eq!(l.next_deadline(), Some(1_010));
    assert!(l.handle(1_009, Event::Timeout).is_empty());
    assert_eq!(
        l.handle(1_010, Event::Timeout),
        [Action::DeleteStored { job }]
    );
    l.handle(1_011, Event::Deleted { job });
    assert_eq!(l.next_deadline(), None);
}

#[test]
fn restored_jobs_keep_their_state_and_ids_continue_above_them() {
    let mut l = Lifecycle::new(Limits::default(), 1);
    l.handle(
        0,
        Event::Restored {
            job: 4,
            state: JobState::Queued,
            error: None,
            started: true,
            pixels: 64,
            ended_ago: 0,
        },
    );
    l.handle(
        0,
        Event::Restored {
            job: 9,
            state: JobState::Done,
            error: None,
            started: true,
            pixels: 64,
            ended_ago: 0,
        },
    );
    assert_eq!(l.job(4).unwrap().phase.visible(), JobState::Running);
    assert_eq!(l.job(9).unwrap().phase.visible(), JobState::Done);
    assert_eq!(l.admit(1, &request(1)), Ok(10));
}

#[test]
fn a_job_that_ended_before_a_restart_expires_from_its_end() {
    let mut l = Lifecycle::new(
        Limits {
            retention: Some(10_000),
            ..Limits::default()
        },
        1,
    );
    l.handle(
        0,
        Event::Restored {
            job: 2,
            state: JobState::Done,
            error: None,
            started: true,
            pixels: 64,
            ended_ago: 9_000,
        },
    );
    assert_eq!(l.next_deadline(), Some(1_000));
    assert_eq!(
        l.handle(1_000, Event::Timeout),
        [Action::DeleteStored { job: 2 }]
    );
}

#[test]
fn the_pixels_of_active_jobs_are_bounded() {
    let mut l = Lifecycle::new(
        Limits {
            max_active_pixels: 64 * 48 * 2,
            ..Limits::default()
        },
        1,
    );
    let a = stored(&mut l, 0);
    stored(&mut l, 0);
    let refused = l.admit(1, &request(2)).unwrap_err();
    assert!(
        refused.message.contains("would pass its limit of 6144"),
        "{refused}"
    );
    l.handle(2, Event::Cancel { job: a });
    assert!(l.admit(3, &request(2)).is_ok());
}
