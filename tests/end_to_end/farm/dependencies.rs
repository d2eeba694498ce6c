//! Jobs submitted after others (`tessera submit --after JOB`) on a real farm: a chain
//! of fifty jobs with the coordinator killed in the middle of it, and a dependency
//! cancelled, kept from deletion, retried, and the chain going on.

use std::path::Path;
use std::thread;
use std::time::{Duration, Instant};

use serde_json::Value;
use tempfile::TempDir;

use crate::support::{
    assert_job_image, client, exclusive, ok, restart_coordinator, scene_path, shared,
    start_coordinator_in, start_restartable_coordinator, start_worker, status_json, submit,
    wait_for_workers, REGISTER_TIMEOUT,
};

const SMALL: &[&str] = &["--width", "64", "--height", "48", "--aa", "1"];

/// `tessera submit SEED SMALL --after ...`: the job's id.
fn submit_after(dir: &Path, addr: &str, after: &[u64]) -> u64 {
    let seed = scene_path("seed.json");
    let after: Vec<String> = after.iter().map(|j| j.to_string()).collect();
    let mut args: Vec<&str> = vec![&seed];
    args.extend(SMALL);
    for a in &after {
        args.extend(["--after", a.as_str()]);
    }
    submit(dir, addr, &args)
}

/// `tessera events JOB --json`: (kind, unix_ms) of each event.
fn timed_events(dir: &Path, addr: &str, job: u64) -> Vec<(String, u64)> {
    let run = ok(
        client(dir, addr, &["events", &job.to_string(), "--json"]),
        "events --json",
    );
    let value: Value = serde_json::from_str(run.stdout.trim()).unwrap();
    value
        .as_array()
        .unwrap()
        .iter()
        .map(|e| {
            (
                e["event"].as_str().unwrap().to_owned(),
                e["unix_ms"].as_u64().unwrap(),
            )
        })
        .collect()
}

/// The status of `job`, or `None` while the coordinator does not answer.
fn try_status(dir: &Path, addr: &str, job: u64) -> Option<Value> {
    crate::support::try_status(dir, addr, job)
}

#[test]
fn a_chain_of_fifty_jobs_goes_in_order_through_a_coordinator_killed_midway() {
    let _turn = exclusive();
    let dir = TempDir::new().unwrap();
    let d = dir.path();
    let (mut coordinator, addr) = start_restartable_coordinator(d);
    let mut chain = vec![submit_after(d, &addr, &[])];
    for _ in 1..50 {
        let previous = *chain.last().unwrap();
        chain.push(submit_after(d, &addr, &[previous]));
    }
    let last = status_json(d, &addr, chain[49]);
    assert_eq!(last["state"], "waiting", "{last}");
    assert_eq!(
        last["waiting_for"],
        serde_json::json!([chain[48]]),
        "{last}"
    );
    let _worker = start_worker(d, &addr, "w1");

    // Killed once a third of the chain is done.
    let deadline = Instant::now() + Duration::from_secs(60);
    while try_status(d, &addr, chain[16]).is_none_or(|s| s["state"] != "done") {
        assert!(Instant::now() < deadline, "the chain does not progress");
        thread::sleep(Duration::from_millis(20));
    }
    coordinator.kill9();
    let _coordinator = restart_coordinator(d, &addr, &[]);
    // Killed in the middle of the chain, not after it.
    let after_restart = status_json(d, &addr, chain[49]);
    assert_ne!(after_restart["state"], "done", "{after_restart}");
    let deadline = Instant::now() + Duration::from_secs(120);
    loop {
        match try_status(d, &addr, chain[49]) {
            Some(s) if s["state"] == "done" => break,
            Some(s) => assert!(
                ["waiting", "queued", "running"].contains(&s["state"].as_str().unwrap()),
                "{s}"
            ),
            None => {}
        }
        assert!(
            Instant::now() < deadline,
            "the chain did not finish after the restart"
        );
        thread::sleep(Duration::from_millis(50));
    }
    // Every job done, each started only once the one before it had ended.
    let mut previous_end = 0;
    for (k, &job) in chain.iter().enumerate() {
        let status = status_json(d, &addr, job);
        assert_eq!(status["state"], "done", "{status}");
        let events = timed_events(d, &addr, job);
        let at = |kind: &str| events.iter().find(|(e, _)| e == kind).map(|(_, t)| *t);
        if k > 0 {
            assert!(
                events.iter().any(|(e, _)| e == "waiting"),
                "job {job}: {events:?}"
            );
            let first_tile = at("started").unwrap_or_else(|| panic!("job {job}: {events:?}"));
            assert!(
                first_tile >= previous_end,
                "job {job} started at {first_tile}, before job {} ended at {previous_end}",
                chain[k - 1]
            );
        }
        previous_end = at("done").unwrap_or_else(|| panic!("job {job}: {events:?}"));
    }
    assert_job_image(
        d,
        &addr,
        chain[49],
        &scene_path("seed.json"),
        SMALL,
        "the chain's last job",
    );
}

#[test]
fn a_cancelled_dependency_fails_its_dependent_stays_while_needed_and_retries_go_on() {
    let _turn = shared();
    let dir = TempDir::new().unwrap();
    let d = dir.path();
    let (_coordinator, addr) = start_coordinator_in(d);
    let first = submit_after(d, &addr, &[]);
    let second = submit_after(d, &addr, &[first]);
    let line = ok(client(d, &addr, &["status", &second.to_string()]), "status");
    assert!(
        line.stdout.contains(": waiting, ")
            && line
                .stdout
                .contains(&format!("(waiting for job {first} to be done)")),
        "{}",
        line.stdout
    );

    // No such job to wait for: one line, and nothing submitted.
    let seed = scene_path("seed.json");
    let refused = client(d, &addr, &["submit", &seed, "--after", "4000"]);
    assert!(!refused.status.success());
    assert!(
        refused.stderr.trim().starts_with("error: ")
            && refused
                .stderr
                .trim()
                .ends_with(": after: there is no job 4000 to wait for")
            && refused.stderr.trim().lines().count() == 1,
        "{}",
        refused.stderr
    );
    let refused = client(d, &addr, &["submit", &seed, "--after", "x"]);
    assert!(!refused.status.success());
    assert!(
        refused.stderr.contains("'--after <JOB>'"),
        "{}",
        refused.stderr
    );

    ok(client(d, &addr, &["cancel", &first.to_string()]), "cancel");
    let failed = crate::support::poll("the dependent to fail", Duration::from_secs(10), || {
        let s = status_json(d, &addr, second);
        (s["state"] == "failed").then_some(s)
    });
    assert_eq!(
        failed["error"],
        format!("job {first}, which this job waits for, is cancelled")
    );
    // Kept while its dependent may still need it.
    let refused = client(d, &addr, &["delete", &first.to_string()]);
    assert!(!refused.status.success());
    assert!(
        refused.stderr.contains(&format!(
            "job {first} cannot be deleted: job {second} depends on it"
        )),
        "{}",
        refused.stderr
    );
    // The dependent cannot go first.
    let refused = client(d, &addr, &["retry", &second.to_string()]);
    assert!(!refused.status.success());
    assert!(
        refused.stderr.contains(&format!("retry job {first} first")),
        "{}",
        refused.stderr
    );
    ok(
        client(d, &addr, &["retry", &first.to_string()]),
        "retry first",
    );
    ok(
        client(d, &addr, &["retry", &second.to_string()]),
        "retry second",
    );
    assert_eq!(status_json(d, &addr, second)["state"], "waiting");

    let _worker = start_worker(d, &addr, "w1");
    wait_for_workers(d, &addr, 1, REGISTER_TIMEOUT);
    crate::support::wait_done(d, &addr, second, Duration::from_secs(60));
    assert_job_image(d, &addr, second, &seed, SMALL, "the retried dependent");
    // Done: its dependency may go now.
    ok(
        client(d, &addr, &["delete", &first.to_string()]),
        "delete first",
    );
}
