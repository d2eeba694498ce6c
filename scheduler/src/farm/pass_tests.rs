//! Jobs rendered in passes, at the core's level: the end of a pass, the next pass's
//! tiles, a pause across passes, a pass restarted by a take-back, and the inputs that
//! come too late.

use super::tests::{assigned, done, farm, join, phase, plan, request};
use super::*;
use crate::lifecycle::Phase;
use crate::passes::RungCheck;

/// A job of `tiles` tiles aiming for 1 level, on a ladder of 40 rungs, stored and
/// running, with one worker of two threads.
fn job_in_passes(f: &mut Farm, tiles: u32, limit_ms: Option<u64>) -> JobId {
    join(f, 1, 2);
    let job = f.admit(0, &request(), plan(tiles)).unwrap();
    f.start_passes(job, Passes::new(1.0, 40).with_time_limit(limit_ms));
    f.handle(0, Input::Job(lifecycle::Event::Stored { job }));
    job
}

fn check(rung: u32, estimate: f64, target: f64) -> RungCheck {
    RungCheck {
        rung,
        estimate,
        meets: estimate <= target,
    }
}

/// Every tile at `rung` with work at `next_work`.
fn at(tiles: u32, rung: u32, next_work: Option<u32>) -> Vec<PassTile> {
    vec![
        PassTile {
            rung: Some(rung),
            next_work,
        };
        tiles as usize
    ]
}

fn evaluated(job: JobId, pass: u32, checks: Vec<RungCheck>, tiles: Vec<PassTile>) -> Input {
    Input::Pass(PassInput::Evaluated {
        job,
        pass,
        checks,
        tiles,
        elapsed_ms: 10,
        samples: 100,
    })
}

fn passes(effects: &[Effect]) -> Vec<&PassAction> {
    effects
        .iter()
        .filter_map(|e| match e {
            Effect::Pass(action) => Some(action),
            _ => None,
        })
        .collect()
}

/// Renders every tile the worker holds of the job; the effects of the last.
fn finish_pass(f: &mut Farm, job: JobId, tiles: &[u32]) -> Vec<Effect> {
    tiles
        .iter()
        .map(|&t| done(f, 1, job, t))
        .last()
        .unwrap_or_default()
}

/// The last tile of a pass is not the job's end: the pass is added up; a total short
/// of the target starts the next pass with the tiles that have work at its rung, and
/// one that meets it makes the image due.
#[test]
fn a_pass_is_added_up_then_the_next_goes_out_or_the_image_is_due() {
    let mut f = farm();
    let job = job_in_passes(&mut f, 2, None);
    let end = finish_pass(&mut f, job, &[0, 1]);
    assert!(end.contains(&Effect::Tiles(Action::JobDone { job })));
    assert!(
        !end.iter().any(|e| matches!(e, Effect::Job(_))),
        "the image is not due: {end:?}"
    );
    assert_eq!(
        passes(&end),
        vec![&PassAction::AddUp {
            job,
            pass: 0,
            rungs: 0..=0
        }]
    );
    assert!(f.pass_run(job).unwrap().evaluating());
    // Rung 0 is far from the target; tile 0 has no more work (its blocks are capped).
    let mut tiles = at(2, 0, Some(1));
    tiles[0].next_work = None;
    let next = f.handle(2, evaluated(job, 0, vec![check(0, 64.0, 1.0)], tiles));
    let rung = f.pass_run(job).unwrap().rung();
    assert!(rung > 0);
    assert_eq!(
        passes(&next),
        vec![
            &PassAction::Continued { job, pass: 1, rung },
            &PassAction::Start {
                job,
                pass: 1,
                rung,
                send: vec![1]
            }
        ]
    );
    assert_eq!(assigned(&next), vec![(1, job, 1)]);
    assert!(f.pass_run(job).unwrap().takes(1, rung));
    // The second pass meets the target at its rung.
    let end = finish_pass(&mut f, job, &[1]);
    let rungs = 1..=rung;
    assert_eq!(
        passes(&end),
        vec![&PassAction::AddUp {
            job,
            pass: 1,
            rungs: rungs.clone()
        }]
    );
    let checks = rungs.map(|r| check(r, if r == rung { 0.5 } else { 2.0 }, 1.0));
    let image = f.handle(3, evaluated(job, 1, checks.collect(), at(2, rung, None)));
    assert_eq!(
        image,
        vec![
            Effect::Pass(PassAction::Finished {
                job,
                pass: 1,
                rung,
                out_of_time: false
            }),
            Effect::Job(lifecycle::Action::StoreImage { job })
        ]
    );
}

/// A pass's totals for a pass that is not awaited (a restarted one, a repeated
/// answer) count for nothing; those of a job cancelled meanwhile neither, and no tile
/// of it goes out again.
#[test]
fn totals_for_a_pass_not_awaited_or_a_cancelled_job_count_for_nothing() {
    let mut f = farm();
    let job = job_in_passes(&mut f, 2, None);
    finish_pass(&mut f, job, &[0, 1]);
    let far = vec![check(0, 64.0, 1.0)];
    assert!(f
        .handle(2, evaluated(job, 7, far.clone(), at(2, 0, Some(1))))
        .is_empty());
    let next = f.handle(2, evaluated(job, 0, far.clone(), at(2, 0, Some(1))));
    assert_eq!(assigned(&next).len(), 2);
    assert!(f
        .handle(2, evaluated(job, 0, far, at(2, 0, Some(1))))
        .is_empty());
    let rung = f.pass_run(job).unwrap().rung();
    // The second pass completes, and the job is cancelled while it is added up.
    finish_pass(&mut f, job, &[0, 1]);
    f.handle(3, Input::Job(lifecycle::Event::Cancel { job }));
    assert!(matches!(phase(&f, job), Phase::Ended { .. }));
    let late = f.handle(
        4,
        evaluated(
            job,
            1,
            vec![check(1, 2.0, 1.0)],
            at(2, rung, Some(rung + 1)),
        ),
    );
    assert!(late.is_empty(), "{late:?}");
    assert!(!f.pass_run(job).unwrap().evaluating());
}

/// Totals that cannot be added up fail the job with the reason.
#[test]
fn totals_that_cannot_be_added_up_fail_the_job() {
    let mut f = farm();
    let job = job_in_passes(&mut f, 1, None);
    finish_pass(&mut f, job, &[0]);
    let failed = f.handle(
        2,
        Input::Pass(PassInput::Failed {
            job,
            pass: 0,
            message: "no tracer".into(),
        }),
    );
    assert!(
        failed.iter().any(|e| matches!(
            e,
            Effect::Job(lifecycle::Action::RecordEnd { error: Some(m), .. })
                if m.contains("cannot add up the pass's tiles: no tracer")
        )),
        "{failed:?}"
    );
}

/// A job paused during a pass starts its next pass paused (the tile scheduler forgets
/// a pause when a run ends), and its tiles go out once it is resumed.
#[test]
fn a_pause_outlives_the_pass_it_came_in() {
    let mut f = farm();
    let job = job_in_passes(&mut f, 2, None);
    f.handle(1, Input::Tiles(Event::PauseJob { job }));
    finish_pass(&mut f, job, &[0, 1]);
    let next = f.handle(
        2,
        evaluated(job, 0, vec![check(0, 64.0, 1.0)], at(2, 0, Some(1))),
    );
    assert!(matches!(passes(&next)[1], PassAction::Start { .. }));
    assert!(assigned(&next).is_empty(), "{next:?}");
    assert!(f.tiles().is_paused(job));
    let resumed = f.handle(3, Input::Tiles(Event::ResumeJob { job }));
    assert_eq!(assigned(&resumed).len(), 2);
}

/// Results taken back from a quarantined machine restart the pass under a new
/// number: the tiles out are withdrawn, and the taken tiles go out again from nothing
/// with those that still had work; once the job is past its passes it is too late.
#[test]
fn a_take_back_restarts_the_pass_and_comes_too_late_once_it_is_over() {
    let mut f = farm();
    let job = job_in_passes(&mut f, 3, None);
    join(&mut f, 2, 1);
    // Tile 0 is in; tiles 1 and 2 are out.
    done(&mut f, 1, job, 0);
    let mut tiles = vec![
        PassTile {
            rung: None,
            next_work: Some(0),
        };
        3
    ];
    tiles[0] = PassTile {
        rung: Some(0),
        next_work: Some(1),
    };
    let taken = f.handle(
        2,
        Input::Pass(PassInput::TakeBack {
            job,
            taken: vec![0],
            tiles: tiles.clone(),
        }),
    );
    assert_eq!(
        passes(&taken),
        vec![
            &PassAction::TakenBack {
                job,
                pass: 1,
                taken: vec![0]
            },
            &PassAction::Start {
                job,
                pass: 1,
                rung: 0,
                send: vec![0, 1, 2]
            }
        ]
    );
    assert!(taken
        .iter()
        .any(|e| matches!(e, Effect::Tiles(Action::CancelOnWorker { job: j, .. }) if *j == job)));
    assert!(f.pass_run(job).unwrap().takes(1, 0));
    assert!(!f.pass_run(job).unwrap().takes(0, 0));
    // Nothing taken: nothing happens.
    let none = f.handle(
        2,
        Input::Pass(PassInput::TakeBack {
            job,
            taken: vec![],
            tiles: tiles.clone(),
        }),
    );
    assert!(none.is_empty());
    // The job meets the target and is done: too late.
    for t in 0..3 {
        for w in [1, 2] {
            if f.tiles().held_by(w) > 0 {
                done(&mut f, w, job, t);
            }
        }
    }
    assert!(f.pass_run(job).unwrap().evaluating());
    f.handle(
        3,
        evaluated(job, 1, vec![check(0, 0.5, 1.0)], at(3, 0, None)),
    );
    f.handle(
        4,
        Input::Job(lifecycle::Event::ImageStored {
            job,
            result: Ok(()),
        }),
    );
    let late = f.handle(
        5,
        Input::Pass(PassInput::TakeBack {
            job,
            taken: vec![2],
            tiles,
        }),
    );
    assert_eq!(
        late,
        vec![Effect::Pass(PassAction::TooLate {
            job,
            taken: vec![2]
        })]
    );
}

/// A pass that ends past the job's time limit ends the job at its own rung.
#[test]
fn a_pass_past_the_time_limit_ends_the_job_at_its_rung() {
    let mut f = farm();
    let job = job_in_passes(&mut f, 1, Some(5));
    finish_pass(&mut f, job, &[0]);
    let end = f.handle(
        2,
        evaluated(job, 0, vec![check(0, 64.0, 1.0)], at(1, 0, Some(1))),
    );
    assert_eq!(
        passes(&end),
        vec![&PassAction::Finished {
            job,
            pass: 0,
            rung: 0,
            out_of_time: true
        }]
    );
    assert!(end.contains(&Effect::Job(lifecycle::Action::StoreImage { job })));
}
