//! Watching the daemons: health, readiness and metrics over HTTP, and JSON logs,
//! following a job and a worker killed mid-job. Real binaries on 127.0.0.1.

use std::path::Path;
use std::time::Duration;

use crate::support::{
    assert_same_png, fetch, free_port, header, http_get, http_get_text, http_request, metric_value,
    ok, poll, render_reference, scene_path, shared, start_coordinator_in,
    start_coordinator_with_http, start_worker, start_worker_with, submit, tessera, wait_done,
    wait_for_workers, worker_named, workers_json, Daemon,
};

/// A coordinator serving HTTP on its own free port, with JSON logs.
fn observed_coordinator(dir: &Path, extra: &[&str]) -> (Daemon, String, String) {
    let mut args = vec!["--log-format", "json"];
    args.extend(extra);
    start_coordinator_with_http(dir, &args)
}

#[test]
fn health_readiness_metrics_and_json_logs_follow_a_job() {
    let _turn = shared();
    let dir = tempfile::tempdir().unwrap();
    let (mut coordinator, addr, http) = observed_coordinator(dir.path(), &[]);
    assert_eq!(http_get_text(&http, "/healthz"), "ok\n");
    assert!(http_get_text(&http, "/readyz").starts_with("ready"));
    let worker_http = format!("127.0.0.1:{}", free_port());
    let _worker = start_worker_with(dir.path(), &addr, "w1", &["--http", &worker_http]);
    poll("the worker to be ready", Duration::from_secs(20), || {
        http_get(&worker_http, "/readyz").filter(|(s, _)| *s == 200)
    });
    assert_eq!(http_get_text(&worker_http, "/healthz"), "ok\n");

    let seed = scene_path("seed.json");
    let settings = [
        "--width", "160", "--height", "96", "--aa", "2", "--tile", "32",
    ];
    let mut args = vec![seed.as_str()];
    args.extend(settings);
    let job = submit(dir.path(), &addr, &args);
    let status = wait_done(dir.path(), &addr, job, Duration::from_secs(60));
    let tiles = status["tiles_total"].as_u64().unwrap();
    assert_eq!(tiles, 15);

    let text = http_get_text(&http, "/metrics");
    metrics_in_both_formats(&http, &text);
    assert_eq!(
        metric_value(&text, "tessera_jobs{state=\"done\"}"),
        Some(1.0),
        "{text}"
    );
    assert_eq!(
        metric_value(&text, "tessera_jobs{state=\"running\"}"),
        Some(0.0)
    );
    assert_eq!(metric_value(&text, "tessera_workers_connected"), Some(1.0));
    assert_eq!(
        metric_value(&text, "tessera_tiles_rendered_total"),
        Some(tiles as f64)
    );
    assert_eq!(
        metric_value(&text, "tessera_tile_latency_seconds_count"),
        Some(tiles as f64)
    );
    assert_eq!(
        metric_value(&text, "tessera_rays_total"),
        Some(status["rays"].as_u64().unwrap() as f64)
    );
    for name in [
        "tessera_leases_expired_total",
        "tessera_tiles_reassigned_total",
        "tessera_rays_per_second",
    ] {
        assert!(
            metric_value(&text, name).is_some(),
            "{name} missing:\n{text}"
        );
    }

    // The page's view and image agree with the client's.
    let farm: serde_json::Value =
        serde_json::from_str(&http_get_text(&http, "/api/status")).unwrap();
    assert_eq!(farm["jobs"][0]["state"], "done");
    assert_eq!(farm["workers"][0]["name"], "w1");
    let (status, png) = http_get(&http, &format!("/jobs/{job}/image.png")).unwrap();
    assert_eq!(status, 200);
    std::fs::write(dir.path().join("page.png"), png).unwrap();
    let fetched = fetch(dir.path(), &addr, job, "fetched.png");
    let reference = render_reference(dir.path(), &seed, "reference.png", &settings[..6]);
    assert_same_png(&fetched, &reference, "fetched");
    assert_same_png(&dir.path().join("page.png"), &reference, "served over HTTP");
    assert_eq!(http_get(&http, "/jobs/99/image.png").unwrap().0, 404);

    // JSON logs: one object a line, the ids as fields.
    coordinator.signal("TERM");
    coordinator
        .wait_exit(Duration::from_secs(20))
        .expect("the coordinator exits");
    let log = coordinator.log_text();
    let events: Vec<serde_json::Value> = log
        .lines()
        .map(|l| serde_json::from_str(l).unwrap_or_else(|e| panic!("not JSON ({e}): {l}")))
        .collect();
    let accepted = events
        .iter()
        .find(|e| e["message"] == "job accepted")
        .expect("a job accepted event");
    assert_eq!(accepted["job"], job);
    assert_eq!(accepted["level"], "INFO");
    assert!(events
        .iter()
        .any(|e| e["message"] == "job done" && e["job"] == job));
    // The worker notices and is no longer ready, but stays alive to reconnect.
    poll("the worker to be unready", Duration::from_secs(30), || {
        http_get(&worker_http, "/readyz").filter(|(s, _)| *s == 503)
    });
    assert_eq!(http_get_text(&worker_http, "/healthz"), "ok\n");
}

#[test]
fn reassigned_tiles_are_counted_when_a_worker_is_killed() {
    let _turn = shared();
    let dir = tempfile::tempdir().unwrap();
    let (_coordinator, addr, http) = observed_coordinator(dir.path(), &[]);
    // A worker takes tiles and dies holding them; a fast one finishes the job. It is
    // frozen (SIGSTOP) once it has joined, so that it holds the tiles it is sent
    // however fast this machine renders them.
    let mut doomed = start_worker_with(dir.path(), &addr, "doomed", &[]);
    wait_for_workers(dir.path(), &addr, 1, Duration::from_secs(30));
    doomed.signal("STOP");
    let seed = scene_path("seed.json");
    let job = submit(
        dir.path(),
        &addr,
        &[&seed, "--width", "128", "--height", "64", "--tile", "32"],
    );
    poll(
        "the frozen worker to hold tiles",
        Duration::from_secs(20),
        || {
            let text = http_get_text(&http, "/metrics");
            (metric_value(&text, "tessera_tiles_in_flight")? > 0.0).then_some(())
        },
    );
    doomed.kill9();
    let _fast = start_worker_with(dir.path(), &addr, "fast", &[]);
    wait_done(dir.path(), &addr, job, Duration::from_secs(60));
    // The tiles rendered again give the same image.
    let fetched = fetch(dir.path(), &addr, job, "fetched.png");
    let reference = render_reference(
        dir.path(),
        &seed,
        "reference.png",
        &["--width", "128", "--height", "64"],
    );
    assert_same_png(&fetched, &reference, "after a worker was killed");
    let text = http_get_text(&http, "/metrics");
    assert!(
        metric_value(&text, "tessera_tiles_reassigned_total").unwrap() >= 1.0,
        "{text}"
    );
    ok(
        tessera(
            dir.path(),
            &["list", "--coordinator", &addr],
            Duration::from_secs(20),
        ),
        "list",
    );
}

/// `/metrics` in the format a scrape asks for: the Prometheus text format without an
/// `Accept` header (`text`, as fetched) and for `text/plain`, which `promtool check
/// metrics` finds clean; OpenMetrics for the `Accept` header Prometheus sends, with the
/// same samples. promtool must be installed where `TESSERA_REQUIRE_PROMTOOL=1` (CI);
/// elsewhere its check is skipped with a line saying so.
fn metrics_in_both_formats(http: &str, text: &str) {
    let get = |accept: &str| {
        let answer = http_request(http, "/metrics", accept, Duration::from_secs(10))
            .expect("no answer from /metrics");
        assert_eq!(answer.status, 200, "{}", answer.head);
        let body = String::from_utf8(answer.body).expect("metrics are text");
        (
            header(&answer.head, "content-type").map(str::to_owned),
            body,
        )
    };
    let plain = "text/plain; version=0.0.4; charset=utf-8";
    let (kind, asked_text) = get("Accept: text/plain;version=0.0.4\r\n");
    assert_eq!(kind.as_deref(), Some(plain));
    assert_eq!(
        get("").0.as_deref(),
        Some(plain),
        "without an Accept header"
    );
    assert!(!text.contains("# EOF"), "{text}");
    assert!(
        text.contains("# TYPE tessera_rays_total counter\n"),
        "{text}"
    );
    let (kind, openmetrics) = get(
        "Accept: application/openmetrics-text;version=1.0.0,application/openmetrics-text;\
         version=0.0.1;q=0.75,text/plain;version=0.0.4;q=0.5,*/*;q=0.1\r\n",
    );
    assert_eq!(
        kind.as_deref(),
        Some("application/openmetrics-text; version=1.0.0; charset=utf-8")
    );
    assert!(openmetrics.ends_with("# EOF\n"), "{openmetrics}");
    assert!(openmetrics.contains("# TYPE tessera_rays counter\n"));
    let samples = |t: &str| -> Vec<String> {
        t.lines()
            .filter(|l| !l.starts_with('#') && !l.starts_with("tessera_rays_per_second"))
            .map(str::to_owned)
            .collect()
    };
    assert_eq!(samples(&asked_text), samples(&openmetrics));

    let promtool = std::process::Command::new("promtool")
        .args(["check", "metrics"])
        .stdin(std::process::Stdio::piped())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn();
    let mut promtool = match promtool {
        Ok(child) => child,
        Err(e) => {
            assert!(
                std::env::var("TESSERA_REQUIRE_PROMTOOL").as_deref() != Ok("1"),
                "TESSERA_REQUIRE_PROMTOOL=1 but promtool cannot run: {e}"
            );
            eprintln!("skipped: promtool check metrics: promtool cannot run: {e}");
            return;
        }
    };
    use std::io::Write as _;
    promtool
        .stdin
        .take()
        .expect("promtool's stdin")
        .write_all(text.as_bytes())
        .expect("writing to promtool");
    let checked = promtool.wait_with_output().expect("promtool ran");
    let said = format!(
        "{}{}",
        String::from_utf8_lossy(&checked.stdout),
        String::from_utf8_lossy(&checked.stderr)
    );
    assert!(
        checked.status.success() && said.trim().is_empty(),
        "promtool check metrics: {}: {said}\n{text}",
        checked.status
    );
}

#[test]
fn a_workers_rate_is_its_rate_while_rendering_and_idle_time_does_not_dilute_it() {
    let _turn = shared();
    let dir = tempfile::tempdir().unwrap();
    let (_coordinator, addr) = start_coordinator_in(dir.path());
    let _worker = start_worker(dir.path(), &addr, "w1");
    wait_for_workers(dir.path(), &addr, 1, Duration::from_secs(30));
    let seed = scene_path("seed.json");
    let job = submit(
        dir.path(),
        &addr,
        &[
            &seed, "--width", "640", "--height", "480", "--aa", "8", "--tile", "32",
        ],
    );
    let status = wait_done(dir.path(), &addr, job, Duration::from_secs(120));
    let rate = |what: &str| -> f64 {
        let workers = workers_json(dir.path(), &addr, &[]);
        worker_named(&workers, "w1")
            .and_then(|w| w["rays_per_second"].as_f64())
            .unwrap_or_else(|| panic!("{what}: no rate for w1 in {workers:?}"))
    };
    let after_job = rate("right after the job");
    // The job's own rate: its rays over the time from its first tile out to its end,
    // which its worker spent rendering (and waiting on the round trips).
    let rays = status["rays"].as_f64().unwrap();
    let rendering_ms =
        status["elapsed_ms"].as_u64().unwrap() - status["queued_ms"].as_u64().unwrap();
    let job_rate = rays / (rendering_ms.max(1) as f64 / 1000.0);
    assert!(
        after_job >= 0.9 * job_rate,
        "w1 at {after_job:.0} rays/s, its job at {job_rate:.0}: {status}"
    );
    // Idle for a while: its rate is still what it rendered at.
    std::thread::sleep(Duration::from_secs(2));
    let idle = rate("idle");
    assert_eq!(idle, after_job, "idle time does not dilute the rate");
    let listed = ok(
        tessera(
            dir.path(),
            &["workers", "--coordinator", &addr],
            Duration::from_secs(30),
        ),
        "workers",
    );
    assert!(
        listed
            .stdout
            .contains(&format!("{:.1} M rays/s", idle / 1e6)),
        "{}",
        listed.stdout
    );
}
