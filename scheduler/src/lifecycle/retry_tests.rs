//! Which ended jobs may be retried, and a retried job's retention stopping.

use super::*;

#[test]
fn only_a_failed_or_cancelled_job_is_retried_and_its_retention_stops() {
    let mut l = Lifecycle::new(
        Limits {
            retention: Some(1_000),
            ..Limits::default()
        },
        1,
    );
    for (job, state) in [
        (1, JobState::Cancelled),
        (2, JobState::Done),
        (3, JobState::Queued),
    ] {
        l.handle(
            0,
            Event::Restored {
                job,
                state,
                error: None,
                started: false,
                pixels: 64,
                ended_ago: 0,
            },
        );
    }
    let reply = |actions: Vec<Action>| match actions.as_slice() {
        [Action::Reply { result, .. }] => result.clone(),
        other => panic!("{other:?}"),
    };
    assert_eq!(
        reply(l.handle(
            1,
            Event::Retry {
                job: 1,
                started: true,
                pixels: 64,
            }
        )),
        Ok(Reply::Retried)
    );
    assert_eq!(l.job(1).unwrap().phase, Phase::Running);
    assert!(reply(l.handle(
        1,
        Event::Retry {
            job: 2,
            started: true,
            pixels: 64,
        }
    ))
    .unwrap_err()
    .message
    .contains("it is done"));
    assert!(reply(l.handle(
        1,
        Event::Retry {
            job: 3,
            started: false,
            pixels: 64,
        }
    ))
    .unwrap_err()
    .message
    .contains("it is queued"));
    assert!(reply(l.handle(
        1,
        Event::Retry {
            job: 9,
            started: false,
            pixels: 64,
        }
    ))
    .unwrap_err()
    .message
    .contains("no job 9"));
    // Only the done job is deleted when its retention runs out.
    let expired = l.handle(5_000, Event::Timeout);
    assert!(
        expired.contains(&Action::DeleteStored { job: 2 }),
        "{expired:?}"
    );
    assert!(
        !expired.contains(&Action::DeleteStored { job: 1 }),
        "{expired:?}"
    );
}
