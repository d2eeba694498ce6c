//! The HTTP API (`/api/v1`, docs/api.md) against a real coordinator: a scene with a
//! mesh submitted through it as a pipeline would (its files resolved, uploaded in
//! resumed chunks, the job waited for and its image fetched, the same as `tessera
//! render`'s), its listings and controls; and its OpenAPI document validated, then
//! the API fuzzed from it by schemathesis.

use std::path::Path;
use std::process::Command;
use std::time::{Duration, Instant};

use serde_json::{json, Value};
use sha2::{Digest, Sha256};
use tempfile::TempDir;

use crate::support::{
    assert_same_png, free_port, path_str, python_tools_or_skip, render_reference, repo, scene_path,
    shared, start_coordinator, start_worker, Answer, Site,
};

const TOKEN: &str = "9f3b2c7d1e0a4f6b8c5d2e9a7b1c3f0e";
const SMALL: &[&str] = &["--width", "96", "--height", "64", "--aa", "1"];

/// A coordinator serving HTTP with the client token `TOKEN` (and `extra` flags), and
/// its HTTP site: the daemon, its address, the site.
fn coordinator(dir: &Path, extra: &[&str]) -> (crate::support::Daemon, String, Site) {
    let token = dir.join("client.token");
    std::fs::write(&token, format!("{TOKEN}\n")).unwrap();
    let http = format!("127.0.0.1:{}", free_port());
    let mut args = vec!["--http", &http, "--client-token-file", path_str(&token)];
    args.extend(extra);
    let (daemon, addr) = start_coordinator(
        dir,
        &dir.join("data"),
        "127.0.0.1:0",
        &args,
        "coordinator.log",
    );
    (daemon, addr, Site::plain(&http))
}

/// `METHOD PATH` with the token, a JSON body (or raw bytes for a PUT).
fn call(site: &Site, method: &str, path: &str, body: &[u8]) -> Answer {
    site.api(TOKEN, method, path, body)
}

/// [`call`], which must answer `status` with JSON: the JSON.
fn json_call(site: &Site, method: &str, path: &str, body: Value, status: u16) -> Value {
    let body = if method == "GET" {
        Vec::new()
    } else {
        body.to_string().into_bytes()
    };
    let answer = call(site, method, path, &body);
    let text = String::from_utf8_lossy(&answer.body).into_owned();
    assert_eq!(answer.status, status, "{method} {path}: {text}");
    assert!(
        !text.trim_end().contains('\n'),
        "{method} {path}: one line: {text}"
    );
    serde_json::from_str(&text).unwrap_or_else(|e| panic!("{method} {path}: {e}: {text}"))
}

#[test]
fn a_pipeline_submits_a_scene_with_its_files_waits_and_fetches_its_image_over_http() {
    let _turn = shared();
    let dir = TempDir::new().unwrap();
    let d = dir.path();
    let (_coordinator, addr, site) = coordinator(d, &[]);
    let scene: Value =
        serde_json::from_str(&std::fs::read_to_string(scene_path("instances.json")).unwrap())
            .unwrap();

    // Which files the scene reads, by the renderer's rules: its mesh, not yet given.
    let resolved = json_call(
        &site,
        "POST",
        "/api/v1/resolve",
        json!({ "scene": scene }),
        200,
    );
    assert_eq!(
        resolved["missing"],
        json!(["models/knot.obj"]),
        "{resolved}"
    );
    assert_eq!(resolved["complete"], false);
    let knot = std::fs::read(repo().join("scenes/models/knot.obj")).unwrap();
    let sha: String = Sha256::digest(&knot)
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect();
    let asset = json!({ "name": "models/knot.obj", "sha256": sha, "size": knot.len() });
    let resolved = json_call(
        &site,
        "POST",
        "/api/v1/resolve",
        json!({ "scene": scene, "assets": [asset] }),
        200,
    );
    assert_eq!(resolved["missing"], json!([]), "{resolved}");
    assert_eq!(resolved["lacking"][0]["received"], 0, "{resolved}");

    // Submitted before its file is uploaded: 409, with what is lacking.
    let job = json!({
        "scene": scene, "width": 96, "height": 64, "aa": 1, "name": "knots",
        "submitter": "pipeline", "assets": [asset],
    });
    let refused = json_call(&site, "POST", "/api/v1/jobs", job.clone(), 409);
    assert_eq!(refused["kind"], "lacking");
    assert_eq!(
        refused["lacking"],
        json!([{ "sha256": sha, "size": knot.len() }])
    );

    // Uploaded in two requests, the second resuming where the store says it stands.
    let half = knot.len() / 2;
    let file = format!("/api/v1/files/{sha}-{}", knot.len());
    let first = call(&site, "PUT", &format!("{file}?offset=0"), &knot[..half]);
    assert_eq!(
        first.status,
        200,
        "{}",
        String::from_utf8_lossy(&first.body)
    );
    let lacking = json_call(
        &site,
        "POST",
        "/api/v1/files/lacking",
        json!({ "files": [{ "sha256": sha, "size": knot.len() }] }),
        200,
    );
    let received = lacking["lacking"][0]["received"].as_u64().unwrap() as usize;
    assert_eq!(received, half, "{lacking}");
    let rest = call(
        &site,
        "PUT",
        &format!("{file}?offset={received}"),
        &knot[received..],
    );
    let rest: Value = serde_json::from_slice(&rest.body).unwrap();
    assert_eq!(rest["complete"], true, "{rest}");
    // A chunk that does not match the file is refused in one line of JSON.
    let wrong = call(&site, "PUT", &format!("{file}?offset=0"), b"not the file");
    assert!((400..500).contains(&wrong.status), "{}", wrong.status);
    let resolved = json_call(
        &site,
        "POST",
        "/api/v1/resolve",
        json!({ "scene": scene, "assets": [asset] }),
        200,
    );
    assert_eq!(resolved["complete"], true, "{resolved}");

    let submitted = json_call(&site, "POST", "/api/v1/jobs", job, 201);
    let id = submitted["id"].as_u64().unwrap();
    // Controls while it waits for a worker: the status as `tessera status --json`.
    let status = json_call(
        &site,
        "POST",
        &format!("/api/v1/jobs/{id}/priority"),
        json!({ "priority": 5 }),
        200,
    );
    assert_eq!(
        (status["priority"].clone(), status["state"].clone()),
        (json!(5), json!("queued"))
    );
    let paused = json_call(
        &site,
        "POST",
        &format!("/api/v1/jobs/{id}/pause"),
        json!({}),
        200,
    );
    assert_eq!(paused["state"], "paused");
    let listed = json_call(
        &site,
        "GET",
        "/api/v1/jobs?state=paused&submitter=pipe",
        json!(null),
        200,
    );
    assert_eq!(listed["jobs"][0]["id"], id, "{listed}");
    json_call(
        &site,
        "POST",
        &format!("/api/v1/jobs/{id}/resume"),
        json!({}),
        200,
    );
    let image = call(&site, "GET", &format!("/api/v1/jobs/{id}/image.png"), b"");
    assert_eq!(image.status, 409, "no image before it is done");

    let _worker = start_worker(d, &addr, "w1");
    let started = Instant::now();
    let done = loop {
        let status = json_call(
            &site,
            "GET",
            &format!("/api/v1/jobs/{id}/wait?timeout=5"),
            json!(null),
            200,
        );
        if status["state"] != "queued" && status["state"] != "running" {
            break status;
        }
        assert!(started.elapsed() < Duration::from_secs(120), "{status}");
    };
    assert_eq!(done["state"], "done", "{done}");
    assert_eq!(done["assets"]["files"], 1);
    let image = call(&site, "GET", &format!("/api/v1/jobs/{id}/image.png"), b"");
    assert_eq!(image.status, 200);
    let fetched = d.join("fetched.png");
    std::fs::write(&fetched, &image.body).unwrap();
    let reference = render_reference(d, &scene_path("instances.json"), "reference.png", SMALL);
    assert_same_png(&fetched, &reference, "the API's image");

    // Its events, the workers, and what a finished job refuses.
    let events = json_call(
        &site,
        "GET",
        &format!("/api/v1/jobs/{id}/events"),
        json!(null),
        200,
    );
    let kinds: Vec<&str> = events
        .as_array()
        .unwrap()
        .iter()
        .filter_map(|e| e["event"].as_str())
        .collect();
    assert!(
        kinds.contains(&"paused") && kinds.contains(&"priority"),
        "{kinds:?}"
    );
    let workers = json_call(&site, "GET", "/api/v1/workers", json!(null), 200);
    assert_eq!(workers[0]["name"], "w1", "{workers}");
    let refused = json_call(
        &site,
        "POST",
        &format!("/api/v1/jobs/{id}/pause"),
        json!({}),
        409,
    );
    assert_eq!(refused["kind"], "state", "{refused}");
    let missing = json_call(&site, "GET", "/api/v1/jobs/999", json!(null), 404);
    assert_eq!(missing["kind"], "not_found");
    let bad = json_call(&site, "GET", "/api/v1/jobs?limit=0", json!(null), 400);
    assert_eq!(bad["kind"], "invalid");
    let deleted = json_call(
        &site,
        "POST",
        &format!("/api/v1/jobs/{id}/delete"),
        json!({}),
        200,
    );
    assert_eq!(deleted["state"], "deleted");
}

/// The most lines of the fuzzer's output a failure shows, each cut to this length: a
/// failing request's body may be megabytes.
const SHOWN_LINES: usize = 80;
const SHOWN_WIDTH: usize = 400;

#[test]
fn the_openapi_document_is_valid_and_the_fuzzer_driven_by_it_finds_no_fault() {
    let Some(python) = python_tools_or_skip() else {
        return;
    };
    let _turn = shared();
    let dir = TempDir::new().unwrap();
    let d = dir.path();
    // Small limits, so that the random valid scenes stay cheap.
    let (_coordinator, _addr, site) = coordinator(
        d,
        &[
            "--max-pixels",
            "4096",
            "--max-objects",
            "16",
            "--max-file-bytes",
            "65536",
        ],
    );
    let document = call(&site, "GET", "/api/v1/openapi.json", b"");
    assert_eq!(document.status, 200);
    let path = d.join("openapi.json");
    std::fs::write(&path, &document.body).unwrap();
    let validated = Command::new(&python)
        .args(["-m", "openapi_spec_validator", path_str(&path)])
        .output()
        .unwrap();
    assert!(
        validated.status.success(),
        "openapi-spec-validator: {}{}",
        String::from_utf8_lossy(&validated.stdout),
        String::from_utf8_lossy(&validated.stderr)
    );

    // Valid by the document is not always valid by the scene format (a JSON object is
    // not a scene): a positive case may be refused as the scene's or the farm's
    // checks refuse it (422, 413), never with a server error. And a case invalid by
    // the document may be refused for its size before it is read (413: a list over
    // its `maxItems` can be a body over the request's bound).
    let config = d.join("schemathesis.toml");
    std::fs::write(
        &config,
        "[checks.positive_data_acceptance]\n\
         expected-statuses = [\"2xx\", \"400\", \"401\", \"403\", \"404\", \"409\", \"413\", \"422\", \"429\"]\n\
         [checks.negative_data_rejection]\n\
         expected-statuses = [\"400\", \"401\", \"403\", \"404\", \"405\", \"406\", \"409\", \"413\", \"415\", \"422\", \"428\", \"429\"]\n",
    )
    .unwrap();
    let base = format!("http://{}", site.addr);
    let report = d.join("report");
    let started = Instant::now();
    let fuzzed = Command::new(&python)
        .args([
            "-m",
            "schemathesis.cli",
            "--config-file",
            path_str(&config),
            "run",
        ])
        .arg(format!("{base}/api/v1/openapi.json"))
        .args([
            "--url",
            &base,
            "--checks",
            "all",
            // Every phase once (the examples, the coverage cases, then fuzzing and
            // stateful runs of this many cases an operation): a time budget would
            // repeat fuzzing and stateful runs until it is spent.
            "--max-examples",
            "20",
        ])
        // The event stream stays open by design (docs/events.md): its own tests
        // (operations::event_stream) cover it, not requests that wait for an end.
        .args(["--exclude-path", "/api/v1/events"])
        .args([
            "--request-timeout",
            "15",
            "--report",
            "ndjson",
            "--report-dir",
            path_str(&report),
        ])
        .args(["--header", &format!("Authorization: Bearer {TOKEN}")])
        .env("NO_COLOR", "1")
        .current_dir(d)
        .output()
        .unwrap();
    let out = String::from_utf8_lossy(&fuzzed.stdout);
    let shown: Vec<String> = out
        .lines()
        .filter(|l| !l.trim().is_empty())
        .map(|l| l.chars().take(SHOWN_WIDTH).collect())
        .collect();
    let tail = shown[shown.len().saturating_sub(SHOWN_LINES)..].join("\n");
    // The figures, for the log: how many requests, and in how long.
    let cases = out
        .lines()
        .map(str::trim)
        .find(|l| l.starts_with(|c: char| c.is_ascii_digit()) && l.contains(" generated"))
        .unwrap_or("?");
    eprintln!("schemathesis: {cases} in {:.0?}", started.elapsed());
    assert!(
        fuzzed.status.success(),
        "schemathesis found faults:\n{tail}\n{}",
        String::from_utf8_lossy(&fuzzed.stderr)
    );
}
