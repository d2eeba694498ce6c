//! Operating the daemons: settings from a file, the environment and flags; health,
//! readiness and metrics over HTTP; JSON logs. Real binaries on 127.0.0.1.

mod common;

use std::path::Path;
use std::time::Duration;

use common::{
    assert_same_png, fetch, free_port, http_get, ok, poll, render_reference, scene_path,
    start_coordinator, start_worker_with, submit, tessera, wait_done, Daemon, BIN,
};

/// `tessera ARGS` with extra environment variables.
fn tessera_env(dir: &Path, args: &[&str], env: &[(&str, &str)]) -> std::process::Output {
    std::process::Command::new(BIN)
        .args(args)
        .envs(env.iter().copied())
        .current_dir(dir)
        .output()
        .expect("cannot run tessera")
}

/// The value and source `--print-config` shows for `key`.
fn setting(printed: &str, key: &str) -> (String, String) {
    let line = printed
        .lines()
        .find(|l| l.starts_with(&format!("{key} = ")))
        .unwrap_or_else(|| panic!("no {key} in\n{printed}"));
    let (value, source) = line[key.len() + 3..]
        .split_once("  # ")
        .unwrap_or_else(|| panic!("no source in {line:?}"));
    (value.to_owned(), source.to_owned())
}

#[test]
fn a_flag_beats_the_environment_which_beats_the_config_file() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(
        dir.path().join("tessera.toml"),
        "[coordinator]\nmax-aa = 8\nmax-objects = 10\nmax-pixels = 1000\ninsecure = true\n\
         [worker]\nthreads = 3\nname = \"render-7\"\n",
    )
    .unwrap();
    let out = tessera_env(
        dir.path(),
        &[
            "coordinator",
            "--config",
            "tessera.toml",
            "--max-aa",
            "4",
            "--print-config",
        ],
        &[("TESSERA_MAX_OBJECTS", "20"), ("TESSERA_MAX_PIXELS", "5")],
    );
    assert!(out.status.success(), "{out:?}");
    let printed = String::from_utf8(out.stdout).unwrap();
    assert_eq!(setting(&printed, "max-aa"), ("4".into(), "flag".into()));
    assert_eq!(
        setting(&printed, "max-objects"),
        ("20".into(), "environment".into())
    );
    assert_eq!(
        setting(&printed, "max-pixels"),
        ("5".into(), "environment".into())
    );
    assert_eq!(
        setting(&printed, "insecure"),
        ("true".into(), "config file".into())
    );
    assert_eq!(
        setting(&printed, "listen"),
        ("\"127.0.0.1:7878\"".into(), "default".into())
    );
    // The file is found through the environment too, and each daemon reads its table.
    let out = tessera_env(
        dir.path(),
        &["worker", "--print-config"],
        &[("TESSERA_CONFIG", "tessera.toml")],
    );
    let printed = String::from_utf8(out.stdout).unwrap();
    assert_eq!(
        setting(&printed, "threads"),
        ("3".into(), "config file".into())
    );
    assert_eq!(
        setting(&printed, "name"),
        ("\"render-7\"".into(), "config file".into())
    );
    // The printed settings are themselves a valid config file.
    let section = printed.split_once("[worker]\n").unwrap().1;
    std::fs::write(
        dir.path().join("again.toml"),
        format!("[worker]\n{section}"),
    )
    .unwrap();
    let again = tessera_env(
        dir.path(),
        &["worker", "--config", "again.toml", "--print-config"],
        &[],
    );
    assert!(again.status.success(), "{again:?}");
    assert_eq!(
        setting(&String::from_utf8(again.stdout).unwrap(), "threads").0,
        "3"
    );
}

#[test]
fn a_bad_config_file_is_one_line_that_says_where() {
    let dir = tempfile::tempdir().unwrap();
    for (text, expected) in [
        (
            "[coordinator]\nlisten = \"127.0.0.1:1\"\nmax-aaa = 3\n",
            "bad.toml: [coordinator] max-aaa: unknown setting",
        ),
        ("[coordinator\n", "bad.toml:1:13:"),
        ("[coordinatr]\n", "bad.toml: unknown section `coordinatr`"),
        (
            "[coordinator]\ninsecure = \"yes\"\n",
            "bad.toml: [coordinator] insecure: must be true or false",
        ),
        (
            "[coordinator]\nmax-aa = [1]\n",
            "bad.toml: [coordinator] max-aa: must be a string or a number",
        ),
    ] {
        std::fs::write(dir.path().join("bad.toml"), text).unwrap();
        let run = tessera(
            dir.path(),
            &["coordinator", "--config", "bad.toml"],
            Duration::from_secs(20),
        );
        assert!(!run.status.success(), "{text:?} was accepted");
        let stderr = run.stderr.trim();
        assert_eq!(stderr.lines().count(), 1, "{text:?}: {stderr}");
        assert!(
            stderr.starts_with(&format!("error: {expected}")),
            "{text:?}: {stderr}"
        );
    }
    let run = tessera(
        dir.path(),
        &["coordinator", "--config", "missing.toml"],
        Duration::from_secs(20),
    );
    assert!(
        run.stderr
            .starts_with("error: cannot read the config file missing.toml"),
        "{}",
        run.stderr
    );
}

/// A coordinator serving HTTP on its own free port, with JSON logs.
fn observed_coordinator(dir: &Path, extra: &[&str]) -> (Daemon, String, String) {
    let http = format!("127.0.0.1:{}", free_port());
    let mut args = vec!["--http", &http, "--log-format", "json"];
    args.extend(extra);
    let data = dir.join("data");
    let (daemon, addr) = start_coordinator(dir, &data, "127.0.0.1:0", &args, "coordinator.log");
    (daemon, addr, http)
}

fn get_ok(http: &str, path: &str) -> String {
    let (status, body) = http_get(http, path).unwrap_or_else(|| panic!("no answer on {path}"));
    assert_eq!(status, 200, "{path}: {}", String::from_utf8_lossy(&body));
    String::from_utf8(body).expect("a text answer")
}

/// The value of the metric line `name` (with its labels), if present.
fn metric(text: &str, name: &str) -> Option<f64> {
    text.lines()
        .find_map(|l| l.strip_prefix(name)?.strip_prefix(' '))
        .map(|v| v.trim().parse().expect("a number"))
}

#[test]
fn health_readiness_metrics_and_json_logs_follow_a_job() {
    let dir = tempfile::tempdir().unwrap();
    let (mut coordinator, addr, http) = observed_coordinator(dir.path(), &[]);
    assert_eq!(get_ok(&http, "/healthz"), "ok\n");
    assert!(get_ok(&http, "/readyz").starts_with("ready"));
    let worker_http = format!("127.0.0.1:{}", free_port());
    let _worker = start_worker_with(dir.path(), &addr, "w1", &["--http", &worker_http]);
    poll("the worker to be ready", Duration::from_secs(20), || {
        http_get(&worker_http, "/readyz").filter(|(s, _)| *s == 200)
    });
    assert_eq!(get_ok(&worker_http, "/healthz"), "ok\n");

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

    let text = get_ok(&http, "/metrics");
    assert_eq!(
        metric(&text, "tessera_jobs{state=\"done\"}"),
        Some(1.0),
        "{text}"
    );
    assert_eq!(metric(&text, "tessera_jobs{state=\"running\"}"), Some(0.0));
    assert_eq!(metric(&text, "tessera_workers_connected"), Some(1.0));
    assert_eq!(
        metric(&text, "tessera_tiles_rendered_total"),
        Some(tiles as f64)
    );
    assert_eq!(
        metric(&text, "tessera_tile_latency_seconds_count"),
        Some(tiles as f64)
    );
    assert_eq!(
        metric(&text, "tessera_rays_total"),
        Some(status["rays"].as_u64().unwrap() as f64)
    );
    for name in [
        "tessera_leases_expired_total",
        "tessera_tiles_reassigned_total",
        "tessera_rays_per_second",
    ] {
        assert!(metric(&text, name).is_some(), "{name} missing:\n{text}");
    }

    // The page's view and image agree with the client's.
    let farm: serde_json::Value = serde_json::from_str(&get_ok(&http, "/api/status")).unwrap();
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
    assert_eq!(get_ok(&worker_http, "/healthz"), "ok\n");
}

#[test]
fn reassigned_tiles_are_counted_when_a_worker_is_killed() {
    let dir = tempfile::tempdir().unwrap();
    let (_coordinator, addr, http) = observed_coordinator(dir.path(), &[]);
    // A slow worker takes tiles and dies holding them; a fast one finishes the job.
    let mut slow = start_worker_with(dir.path(), &addr, "slow", &["--throttle", "400"]);
    let seed = scene_path("seed.json");
    let job = submit(
        dir.path(),
        &addr,
        &[&seed, "--width", "128", "--height", "64", "--tile", "32"],
    );
    poll(
        "the slow worker to hold tiles",
        Duration::from_secs(20),
        || {
            let text = get_ok(&http, "/metrics");
            (metric(&text, "tessera_tiles_in_flight")? > 0.0).then_some(())
        },
    );
    slow.kill9();
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
    let text = get_ok(&http, "/metrics");
    assert!(
        metric(&text, "tessera_tiles_reassigned_total").unwrap() >= 1.0,
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
