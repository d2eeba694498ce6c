//! What a retry needs to be let in: room among the active pixels, and storage.

use super::*;

#[test]
fn a_retry_must_fit_in_the_active_pixels_and_needs_storage() {
    let mut l = Lifecycle::new(
        Limits {
            max_active_pixels: 100,
            ..Limits::default()
        },
        1,
    );
    for (job, state) in [(1, JobState::Failed), (2, JobState::Running)] {
        l.handle(
            0,
            Event::Restored {
                job,
                state,
                error: None,
                started: true,
                pixels: 64,
                ended_ago: 0,
            },
        );
    }
    let refused = l.check_retry(1, 64).unwrap_err();
    assert_eq!(refused.kind, protocol::RefusalKind::Limit);
    assert!(
        refused.message.contains("would pass its limit of 100"),
        "{refused}"
    );
    assert_eq!(l.check_retry(1, 36), Ok(()));
    l.handle(
        0,
        Event::StorageUnavailable {
            reason: "disk full".into(),
        },
    );
    let refused = l.check_retry(1, 36).unwrap_err();
    assert!(
        refused.message.contains("storage unavailable: disk full"),
        "{refused}"
    );
}
