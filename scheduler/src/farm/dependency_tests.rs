//! Jobs submitted after others: examples, then properties over random farms of
//! dependent jobs ended, retried, deleted and restarted at random.

use std::collections::{BTreeMap, BTreeSet};

use proptest::prelude::*;
use protocol::{JobState, RefusalKind};

use super::tests::{farm, plan, request};
use super::*;
use crate::lifecycle::Reply;

/// Feeds `input`, then everything the executor would report back at once (images and
/// ends written, rows deleted), until nothing is left: the effects, in order.
fn run(f: &mut Farm, input: Input) -> Vec<Effect> {
    let mut all = Vec::new();
    let mut queue = vec![input];
    while let Some(input) = queue.pop() {
        let effects = f.handle(0, input);
        for effect in &effects {
            match effect {
                Effect::Job(lifecycle::Action::StoreImage { job }) => {
                    queue.push(Input::Job(lifecycle::Event::ImageStored {
                        job: *job,
                        result: Ok(()),
                    }))
                }
                Effect::Job(lifecycle::Action::RecordEnd { job, .. }) => {
                    queue.push(Input::Job(lifecycle::Event::EndRecorded { job: *job }))
                }
                Effect::Job(lifecycle::Action::DeleteStored { job }) => {
                    queue.push(Input::Job(lifecycle::Event::Deleted { job: *job }))
                }
                _ => {}
            }
        }
        all.extend(effects);
    }
    all
}

/// A one-tile job submitted after `after`, stored.
fn submit(f: &mut Farm, after: &[JobId]) -> (JobId, Vec<Effect>) {
    let job = f.admit_after(0, &request(), plan(1), after).unwrap();
    (job, run(f, Input::Job(lifecycle::Event::Stored { job })))
}

/// The job's one tile, done by worker 1.
fn finish(f: &mut Farm, job: JobId) -> Vec<Effect> {
    run(
        f,
        Input::Tiles(Event::TileDone {
            worker: 1,
            job,
            tile: 0,
        }),
    )
}

fn ended(f: &Farm, job: JobId) -> Option<(JobState, Option<String>)> {
    match &f.lifecycle().job(job)?.phase {
        Phase::Ended { state, error, .. } => Some((*state, error.clone())),
        _ => None,
    }
}

fn replies(effects: &[Effect]) -> Vec<Result<Reply, Refusal>> {
    effects
        .iter()
        .filter_map(|e| match e {
            Effect::Job(lifecycle::Action::Reply { result, .. }) => Some(result.clone()),
            _ => None,
        })
        .collect()
}

fn farm_with_worker() -> Farm {
    let mut f = farm();
    run(
        &mut f,
        Input::Tiles(Event::WorkerJoined {
            worker: 1,
            threads: 64,
            machine: Some("m1".into()),
        }),
    );
    f
}

#[test]
fn a_job_waits_for_its_dependency_and_goes_once_its_end_is_written() {
    let mut f = farm_with_worker();
    let (a, _) = submit(&mut f, &[]);
    let (b, stored) = submit(&mut f, &[a]);
    assert!(stored.contains(&Effect::Waiting {
        job: b,
        on: vec![a]
    }));
    assert!(!f.tiles().is_active(b), "no tile of a waiting job goes out");
    assert_eq!(f.dependencies().waiting_for(b), Some(&BTreeSet::from([a])));
    // Done, but not yet written: still waiting (a restart could lose it).
    let effects = f.handle(
        0,
        Input::Tiles(Event::TileDone {
            worker: 1,
            job: a,
            tile: 0,
        }),
    );
    assert!(!effects.contains(&Effect::Released { job: b }));
    run(
        &mut f,
        Input::Job(lifecycle::Event::ImageStored {
            job: a,
            result: Ok(()),
        }),
    );
    assert!(f.tiles().is_active(b), "released once a's end is written");
    assert_eq!(f.dependencies().waiting_for(b), None);
    finish(&mut f, b);
    assert_eq!(ended(&f, b).map(|e| e.0), Some(JobState::Done));
}

#[test]
fn a_failed_dependency_fails_the_chain_naming_it_and_retries_let_it_go_on() {
    let mut f = farm_with_worker();
    let (a, _) = submit(&mut f, &[]);
    let (b, _) = submit(&mut f, &[a]);
    let (c, _) = submit(&mut f, &[b]);
    run(&mut f, Input::Job(lifecycle::Event::Cancel { job: a }));
    let (state, error) = ended(&f, b).unwrap();
    assert_eq!(state, JobState::Failed);
    assert_eq!(
        error.as_deref(),
        Some(format!("job {a}, which this job waits for, is cancelled").as_str())
    );
    let (state, error) = ended(&f, c).unwrap();
    assert_eq!(state, JobState::Failed);
    assert!(error.unwrap().starts_with(&format!("job {b}, which")));
    // The dependent first: refused, naming what to retry.
    let refusal = f.check_retry(c, 64).unwrap_err();
    assert_eq!(refusal.kind, RefusalKind::State);
    assert!(
        refusal.message.contains(&format!("retry job {b} first")),
        "{refusal}"
    );
    let refused = run(
        &mut f,
        Input::Job(lifecycle::Event::Retry {
            job: c,
            started: false,
            pixels: 64,
        }),
    );
    assert!(matches!(replies(&refused)[..], [Err(_)]), "{refused:?}");
    // Then in order: each waits for the one before.
    for job in [a, b, c] {
        f.check_retry(job, 64).unwrap();
        let retried = run(
            &mut f,
            Input::Job(lifecycle::Event::Retry {
                job,
                started: false,
                pixels: 64,
            }),
        );
        assert_eq!(replies(&retried), vec![Ok(Reply::Retried)]);
        run_resume(&mut f, job);
    }
    assert_eq!(f.dependencies().waiting_for(c), Some(&BTreeSet::from([b])));
    finish(&mut f, a);
    finish(&mut f, b);
    finish(&mut f, c);
    assert_eq!(ended(&f, c).map(|e| e.0), Some(JobState::Done));
}

/// What the daemon does after a retry: the job's tiles go back to the core.
fn run_resume(f: &mut Farm, job: JobId) -> Vec<Effect> {
    let effects = f.resume_job(0, job, plan(1), &[]);
    let mut all = effects.clone();
    for effect in effects {
        if let Effect::Job(lifecycle::Action::RecordEnd { job, .. }) = effect {
            all.extend(run(f, Input::Job(lifecycle::Event::EndRecorded { job })));
        }
    }
    all
}

#[test]
fn a_dependency_cannot_be_deleted_while_a_job_that_needs_it_is_not_done() {
    let mut f = farm_with_worker();
    let (a, _) = submit(&mut f, &[]);
    let (b, _) = submit(&mut f, &[a]);
    run(&mut f, Input::Job(lifecycle::Event::Cancel { job: a }));
    let refused = run(&mut f, Input::Job(lifecycle::Event::Delete { job: a }));
    match &replies(&refused)[..] {
        [Err(refusal)] => assert!(
            refusal.message.contains(&format!("job {b} depends on it")),
            "{refusal}"
        ),
        other => panic!("{other:?}"),
    }
    // Once the dependent is gone, so may the dependency be.
    run(&mut f, Input::Job(lifecycle::Event::Delete { job: b }));
    let deleted = run(&mut f, Input::Job(lifecycle::Event::Delete { job: a }));
    assert_eq!(replies(&deleted), vec![Ok(Reply::Deleting)]);
    assert!(f.lifecycle().job(a).is_none());
}

#[test]
fn a_job_may_only_wait_for_jobs_that_exist() {
    let mut f = farm_with_worker();
    let refusal = f.admit_after(0, &request(), plan(1), &[41]).unwrap_err();
    assert_eq!(refusal.kind, RefusalKind::NotFound);
    assert_eq!(refusal.message, "after: there is no job 41 to wait for");
    let too_many: Vec<JobId> = (0..=protocol::MAX_AFTER as JobId).collect();
    let refusal = f
        .admit_after(0, &request(), plan(1), &too_many)
        .unwrap_err();
    assert_eq!(refusal.kind, RefusalKind::Invalid);
}

/// One step of a random history.
#[derive(Clone, Debug)]
enum Step {
    /// Submit a job after some of the jobs so far (indices into them, taken modulo).
    Submit(Vec<usize>),
    /// The k-th job's tile is done (if it is out).
    Finish(usize),
    /// The k-th job's tiles fail.
    Fail(usize),
    Cancel(usize),
    Retry(usize),
    Delete(usize),
    /// The coordinator restarts: a new core from what is stored.
    Restart,
}

fn step() -> impl Strategy<Value = Step> {
    prop_oneof![
        3 => prop::collection::vec(0usize..64, 0..4).prop_map(Step::Submit),
        3 => (0usize..64).prop_map(Step::Finish),
        1 => (0usize..64).prop_map(Step::Fail),
        1 => (0usize..64).prop_map(Step::Cancel),
        2 => (0usize..64).prop_map(Step::Retry),
        1 => (0usize..64).prop_map(Step::Delete),
        1 => Just(Step::Restart),
    ]
}

/// What the daemon stores of a job: its dependencies and its state (queued while it
/// is active, the end once written).
fn stored(f: &Farm, jobs: &[(JobId, Vec<JobId>)]) -> Vec<(JobId, Vec<JobId>, Phase)> {
    jobs.iter()
        .filter_map(|(job, after)| {
            let phase = f.lifecycle().job(*job)?.phase.clone();
            Some((*job, after.clone(), phase))
        })
        .collect()
}

/// A restarted core: every stored job taken back in the order of their ids, as the
/// daemon does, and the worker joined again.
fn restart(f: &Farm, jobs: &[(JobId, Vec<JobId>)]) -> Farm {
    // Ids are never given twice: the daemon keeps the highest issued beside the jobs.
    let policy = crate::Policy {
        max_attempts: 2,
        speculate: false,
        ..crate::Policy::default()
    };
    let mut g = Farm::new(
        Scheduler::with_policy(policy),
        Lifecycle::new(lifecycle::Limits::default(), f.lifecycle().next_id()),
    );
    for (job, after, phase) in stored(f, jobs) {
        let (state, error) = match phase {
            Phase::Ended { state, error, .. } => (state, error),
            _ => (JobState::Queued, None),
        };
        run(
            &mut g,
            Input::Job(lifecycle::Event::Restored {
                job,
                state,
                error,
                started: false,
                pixels: 64,
                ended_ago: 0,
            }),
        );
        g.declare_after(job, &after);
        if !state.is_final() {
            let effects = g.resume_job(0, job, plan(1), &[]);
            for effect in effects {
                if let Effect::Job(lifecycle::Action::RecordEnd { job, .. }) = effect {
                    run(&mut g, Input::Job(lifecycle::Event::EndRecorded { job }));
                }
            }
        }
    }
    run(
        &mut g,
        Input::Tiles(Event::WorkerJoined {
            worker: 1,
            threads: 64,
            machine: Some("m1".into()),
        }),
    );
    g
}

/// The invariants of a farm of dependent jobs, after every step.
fn check(f: &Farm, jobs: &[(JobId, Vec<JobId>)]) -> Result<(), TestCaseError> {
    let done = |d: JobId| {
        f.lifecycle().job(d).is_none_or(|j| {
            matches!(
                j.phase,
                Phase::Ended {
                    state: JobState::Done,
                    recorded: true,
                    ..
                }
            )
        })
    };
    for (job, after) in jobs {
        // No cycle: a job waits only for older ones.
        prop_assert!(after.iter().all(|d| d < job));
        let Some(j) = f.lifecycle().job(*job) else {
            continue;
        };
        // No tile goes out before every dependency is done and written.
        if f.tiles().is_active(*job) {
            prop_assert!(
                after.iter().all(|&d| done(d)),
                "job {job} runs before {after:?} are done"
            );
        }
        match f.dependencies().waiting_for(*job) {
            Some(on) => {
                // Waiting only while queued, for dependencies that have not ended: no
                // job waits for one that has, so none waits forever.
                prop_assert_eq!(&j.phase, &Phase::Queued);
                prop_assert!(!on.is_empty());
                for &d in on {
                    prop_assert!(after.contains(&d));
                    prop_assert!(
                        f.lifecycle().job(d).is_some_and(|j| !j.phase.has_ended()),
                        "job {job} waits for {d}, which has ended"
                    );
                }
                let pending: BTreeSet<JobId> =
                    after.iter().copied().filter(|&d| !done(d)).collect();
                prop_assert_eq!(on, &pending);
            }
            None if j.phase == Phase::Queued => {
                // Queued and not waiting: its tiles are out to be taken.
                prop_assert!(f.tiles().is_active(*job), "job {job} is stuck in the queue");
            }
            None => {}
        }
        // A job failed by a dependency names one of its dependencies.
        if let Phase::Ended {
            error: Some(error), ..
        } = &j.phase
        {
            if let Some(rest) = error.strip_prefix("job ") {
                if let Some((d, _)) = rest.split_once(", which this job waits for") {
                    let d: JobId = d.parse().unwrap();
                    // (Since retried, maybe: what it names ended badly when it failed.)
                    prop_assert!(after.contains(&d));
                }
            }
        }
    }
    Ok(())
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(300))]

    /// Whatever is submitted, ended, retried, deleted or restarted: no job runs before
    /// its dependencies are done, none waits for a job that has ended, a job failed by
    /// a dependency names it, and a restarted core waits for exactly what the one
    /// before it waited for.
    #[test]
    fn dependent_jobs_never_run_early_never_wait_forever_and_survive_restarts(
        steps in prop::collection::vec(step(), 1..60),
    ) {
        let mut f = farm_with_worker();
        let mut jobs: Vec<(JobId, Vec<JobId>)> = Vec::new();
        for step in steps {
            let pick = |k: usize| jobs.get(k % jobs.len().max(1)).map(|(j, _)| *j);
            match step {
                Step::Submit(picks) => {
                    let after: Vec<JobId> = picks.iter().filter_map(|&k| pick(k)).collect();
                    match f.admit_after(0, &request(), plan(1), &after) {
                        Ok(job) => {
                            run(&mut f, Input::Job(lifecycle::Event::Stored { job }));
                            let mut after = after;
                            after.sort_unstable();
                            after.dedup();
                            jobs.push((job, after));
                        }
                        // Only a deleted dependency may be refused.
                        Err(refusal) => prop_assert_eq!(refusal.kind, RefusalKind::NotFound),
                    }
                }
                Step::Finish(k) => {
                    if let Some(job) = pick(k) {
                        if f.tiles().is_active(job) {
                            finish(&mut f, job);
                        }
                    }
                }
                Step::Fail(k) => {
                    if let Some(job) = pick(k) {
                        let message = "its tiles failed".to_string();
                        run(&mut f, Input::Job(lifecycle::Event::TilesFailed { job, message }));
                    }
                }
                Step::Cancel(k) => {
                    if let Some(job) = pick(k) {
                        run(&mut f, Input::Job(lifecycle::Event::Cancel { job }));
                    }
                }
                Step::Retry(k) => {
                    if let Some(job) = pick(k) {
                        if f.check_retry(job, 64).is_ok() {
                            let retried = run(&mut f, Input::Job(lifecycle::Event::Retry {
                                job,
                                started: false,
                                pixels: 64,
                            }));
                            prop_assert_eq!(replies(&retried), vec![Ok(Reply::Retried)]);
                            run_resume(&mut f, job);
                        }
                    }
                }
                Step::Delete(k) => {
                    if let Some(job) = pick(k) {
                        run(&mut f, Input::Job(lifecycle::Event::Delete { job }));
                    }
                }
                Step::Restart => {
                    let before: BTreeMap<JobId, BTreeSet<JobId>> = f
                        .dependencies()
                        .waiting()
                        .map(|(j, on)| (j, on.clone()))
                        .collect();
                    f = restart(&f, &jobs);
                    let after: BTreeMap<JobId, BTreeSet<JobId>> = f
                        .dependencies()
                        .waiting()
                        .map(|(j, on)| (j, on.clone()))
                        .collect();
                    prop_assert_eq!(before, after, "a restart changes what waits");
                }
            }
            check(&f, &jobs)?;
        }
        // Finishing everything that can run ends every job that is not blocked by a
        // dependency that failed: no job is left waiting.
        for _ in 0..jobs.len() + 1 {
            for (job, _) in &jobs {
                if f.tiles().is_active(*job) {
                    finish(&mut f, *job);
                }
            }
        }
        prop_assert_eq!(f.dependencies().waiting().count(), 0);
        check(&f, &jobs)?;
    }
}
