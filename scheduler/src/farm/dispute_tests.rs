//! Straggler copies that differ, settled by the core: the executor compares the
//! pixels and renders where they differ; the core quarantines whichever machine is
//! shown wrong and takes back what it rendered of the active jobs.

use super::tests::{assigned, done, farm, join, stored_job};
use super::*;

fn duplicate(job: JobId, tile: u32, verdict: CopyVerdict) -> Input {
    Input::Duplicate(Duplicate {
        job,
        tile,
        accepted_by: Some("m1".into()),
        copy_by: "m2".into(),
        verdict,
    })
}

/// The tiles taken back from each job.
type Taken = Vec<(JobId, Vec<u32>)>;

fn quarantined(effects: &[Effect]) -> Vec<(String, Taken)> {
    effects
        .iter()
        .filter_map(|e| match e {
            Effect::Quarantined { machine, taken, .. } => Some((machine.clone(), taken.clone())),
            _ => None,
        })
        .collect()
}

/// What a copy of tile 0 by m2 that settles nothing gives.
fn settled(job: JobId, same: bool) -> Vec<Effect> {
    vec![Effect::DuplicateSettled {
        job,
        tile: 0,
        machine: "m2".into(),
        same,
    }]
}

/// Two machines, the first holding a job of 3 tiles whose tile 0 it rendered; the
/// job is still active.
fn farm_with_an_accepted_tile() -> (Farm, JobId) {
    let mut f = farm();
    join(&mut f, 1, 1);
    let job = stored_job(&mut f, 3);
    assert!(done(&mut f, 1, job, 0).contains(&Effect::Tiles(Action::AcceptTile { job, tile: 0 })));
    join(&mut f, 2, 4);
    (f, job)
}

/// A copy equal to the accepted one changes nothing, and says so.
#[test]
fn an_equal_copy_settles_nothing() {
    let (mut f, job) = farm_with_an_accepted_tile();
    let effects = f.handle(3, duplicate(job, 0, CopyVerdict::Same));
    assert_eq!(effects, settled(job, true));
}

/// The accepted copy shown wrong: its machine is quarantined, the tile is taken back
/// from the active job and goes out again, to the other machine.
#[test]
fn an_accepted_copy_shown_wrong_is_taken_back_and_rendered_again() {
    let (mut f, job) = farm_with_an_accepted_tile();
    let verdict = CopyVerdict::Differs {
        accepted_wrong: Some("pixel (0, 0) is (255, 0, 0), not (10, 10, 10)".into()),
        copy_wrong: None,
    };
    let effects = f.handle(3, duplicate(job, 0, verdict));
    assert_eq!(
        quarantined(&effects),
        vec![("m1".to_string(), vec![(job, vec![0])])]
    );
    let Effect::Quarantined {
        caught_in, reason, ..
    } = &effects[0]
    else {
        panic!("the executor hears first: {effects:?}");
    };
    assert_eq!(*caught_in, job);
    assert!(
        reason.contains("comparing its result with m2's copy"),
        "{reason}"
    );
    assert_eq!(
        effects[1],
        Effect::TakenBack {
            job,
            tiles: vec![0]
        }
    );
    assert!(
        assigned(&effects)
            .iter()
            .any(|&(w, j, t)| (w, j, t) == (2, job, 0)),
        "the tile goes out again to the honest machine: {effects:?}"
    );
    // Nothing more goes to the quarantined machine.
    let later = done(&mut f, 2, job, 1);
    assert!(
        assigned(&later).iter().all(|&(w, _, _)| w != 1),
        "{later:?}"
    );
}

/// The copy shown wrong: its machine is quarantined; the accepted tile stays.
#[test]
fn a_copy_shown_wrong_quarantines_its_machine_alone() {
    let (mut f, job) = farm_with_an_accepted_tile();
    let verdict = CopyVerdict::Differs {
        accepted_wrong: None,
        copy_wrong: Some("pixel (1, 0) differs".into()),
    };
    let effects = f.handle(3, duplicate(job, 0, verdict));
    assert_eq!(quarantined(&effects), vec![("m2".to_string(), vec![])]);
    assert!(!effects
        .iter()
        .any(|e| matches!(e, Effect::TakenBack { .. })));
}

/// Both shown wrong: both machines are quarantined, the accepted copy's first.
#[test]
fn both_copies_shown_wrong_quarantine_both_machines() {
    let (mut f, job) = farm_with_an_accepted_tile();
    let verdict = CopyVerdict::Differs {
        accepted_wrong: Some("a".into()),
        copy_wrong: Some("b".into()),
    };
    let effects = f.handle(3, duplicate(job, 0, verdict));
    let machines: Vec<String> = quarantined(&effects).into_iter().map(|(m, _)| m).collect();
    assert_eq!(machines, vec!["m1", "m2"]);
}

/// Copies that differ with neither shown wrong (nothing to render them with) keep
/// the accepted one and quarantine nobody; the executor logs it.
#[test]
fn copies_that_differ_with_neither_shown_wrong_quarantine_nobody() {
    let (mut f, job) = farm_with_an_accepted_tile();
    let verdict = CopyVerdict::Differs {
        accepted_wrong: None,
        copy_wrong: None,
    };
    let effects = f.handle(3, duplicate(job, 0, verdict));
    assert_eq!(effects, settled(job, false));
}

/// The accepted copy shown wrong once its job has finished: its machine is
/// quarantined, but nothing is taken back (the image is stored or being stored).
#[test]
fn a_wrong_copy_of_a_finished_job_is_too_late_to_take_back() {
    let mut f = farm();
    join(&mut f, 1, 1);
    let job = stored_job(&mut f, 1);
    done(&mut f, 1, job, 0);
    let verdict = CopyVerdict::Differs {
        accepted_wrong: Some("a".into()),
        copy_wrong: None,
    };
    let effects = f.handle(3, duplicate(job, 0, verdict));
    assert_eq!(quarantined(&effects), vec![("m1".to_string(), vec![])]);
}
