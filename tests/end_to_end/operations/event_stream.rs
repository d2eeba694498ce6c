//! The farm's event stream, `GET /api/v1/events` (docs/events.md), read as a client
//! reads it, over a raw socket:
//!
//! - a stream sees a worker join and a job's submission, start and end, in id order;
//! - a stream cut while its job waits, resumed with `Last-Event-ID`, gets exactly the
//!   events it missed: every one the database has after its last id, none twice;
//! - the same across a coordinator `kill -9` and restart, and ids go on increasing;
//! - an id older than the events kept (`--event-retention-count 3`) gets `gap` first;
//! - reading it takes the client token: none is 401, a wrong one or the worker token
//!   403.

use std::io::{BufRead, BufReader, Write};
use std::net::TcpStream;
use std::path::Path;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use serde_json::Value;
use tempfile::TempDir;

use crate::support::{
    client, free_port, ok, path_str, scene_path, shared, start_coordinator,
    start_coordinator_with_http, start_worker, submit_scene, wait_done, write_token_file,
};

/// A quick job: the seed scene at 64 × 48, one sample per pixel.
const SMALL: &[&str] = &["--width", "64", "--height", "48", "--aa", "1"];

/// How long a test waits for one event.
const EVENT_TIMEOUT: Duration = Duration::from_secs(20);

/// One server-sent event.
#[derive(Clone, Debug, PartialEq)]
struct Sse {
    id: u64,
    kind: String,
    data: Value,
}

/// An open event stream: the answer's head, then its events as they come.
struct Stream {
    status: u16,
    head: String,
    reader: BufReader<TcpStream>,
}

impl Stream {
    /// `GET PATH` on the HTTP listener at `http` with `headers`, over HTTP/1.0 (the
    /// body is then the stream itself, unchunked, until the server closes it).
    fn open(http: &str, path: &str, headers: &[(&str, &str)]) -> Stream {
        let socket = TcpStream::connect(http).expect("cannot connect to the HTTP side");
        socket.set_read_timeout(Some(EVENT_TIMEOUT)).unwrap();
        let mut request = format!("GET {path} HTTP/1.0\r\nHost: {http}\r\n");
        for (name, value) in headers {
            request.push_str(&format!("{name}: {value}\r\n"));
        }
        request.push_str("\r\n");
        (&socket).write_all(request.as_bytes()).unwrap();
        let mut reader = BufReader::new(socket);
        let mut head = String::new();
        loop {
            let mut line = String::new();
            reader.read_line(&mut line).expect("no answer's head");
            if line.trim().is_empty() {
                break;
            }
            head.push_str(&line.to_ascii_lowercase());
        }
        let status = head
            .split_whitespace()
            .nth(1)
            .and_then(|s| s.parse().ok())
            .unwrap_or_else(|| panic!("not an HTTP answer: {head:?}"));
        Stream {
            status,
            head,
            reader,
        }
    }

    /// The next event, heartbeats skipped; `None` once the stream ends (or is cut, or
    /// has no event for [`EVENT_TIMEOUT`], heartbeats or not).
    fn next(&mut self) -> Option<Sse> {
        let deadline = Instant::now() + EVENT_TIMEOUT;
        let (mut id, mut kind, mut data) = (None, None, None);
        loop {
            let mut line = String::new();
            if Instant::now() > deadline || self.reader.read_line(&mut line).unwrap_or(0) == 0 {
                return None;
            }
            let line = line.trim_end_matches(['\r', '\n']);
            if line.is_empty() {
                if let (Some(id), Some(kind), Some(data)) = (id.take(), kind.take(), data.take()) {
                    return Some(Sse { id, kind, data });
                }
                continue;
            }
            match line.split_once(':') {
                Some(("id", v)) => id = Some(v.trim().parse().expect("a numeric id")),
                Some(("event", v)) => kind = Some(v.trim().to_owned()),
                Some(("data", v)) => {
                    data = Some(serde_json::from_str(v.trim()).expect("one line of JSON"))
                }
                _ => {}
            }
        }
    }

    /// Events until one of `kind` about `job` (included).
    fn until(&mut self, kind: &str, job: u64) -> Vec<Sse> {
        let deadline = Instant::now() + EVENT_TIMEOUT;
        let mut seen = Vec::new();
        while Instant::now() < deadline {
            let event = self
                .next()
                .unwrap_or_else(|| panic!("the stream ended before {kind} of job {job}: {seen:?}"));
            let found = event.kind == kind && event.data["job"]["id"] == job;
            seen.push(event);
            if found {
                return seen;
            }
        }
        panic!("no {kind} of job {job} within {EVENT_TIMEOUT:?}: {seen:?}");
    }

    /// Every event to the end of a stream that ends (`follow=false`).
    fn read_to_end(mut self) -> Vec<Sse> {
        std::iter::from_fn(|| self.next()).collect()
    }
}

/// Everything the database keeps after `after`: a replay that ends.
fn kept_after(http: &str, after: u64) -> Vec<Sse> {
    let stream = Stream::open(
        http,
        &format!("/api/v1/events?after={after}&follow=false"),
        &[],
    );
    assert_eq!(stream.status, 200, "{}", stream.head);
    stream.read_to_end()
}

fn ids(events: &[Sse]) -> Vec<u64> {
    events.iter().map(|e| e.id).collect()
}

fn assert_increasing(events: &[Sse], what: &str) {
    assert!(
        events.windows(2).all(|w| w[0].id < w[1].id),
        "{what}: ids must strictly increase: {:?}",
        ids(events)
    );
}

fn unix_ms() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .unwrap()
        .as_millis() as u64
}

fn submit_small(dir: &Path, addr: &str) -> u64 {
    submit_scene(dir, addr, &scene_path("seed.json"), SMALL)
}

/// A stream opened before anything happened sees the worker join and the job's
/// submission, start and end, in id order, each with its time and details, live
/// (only once recorded: the delay that adds is printed).
#[test]
fn a_stream_sees_a_worker_join_and_a_job_run_in_id_order() {
    let _turn = shared();
    let dir = TempDir::new().unwrap();
    let d = dir.path();
    let (_coordinator, addr, http) = start_coordinator_with_http(d, &[]);
    let mut stream = Stream::open(&http, "/api/v1/events", &[]);
    assert_eq!(stream.status, 200, "{}", stream.head);
    assert!(
        stream.head.contains("content-type: text/event-stream"),
        "{}",
        stream.head
    );

    let _worker = start_worker(d, &addr, "w1");
    let joined = stream.next().expect("an event");
    let received = unix_ms();
    assert_eq!(joined.kind, "joined", "{joined:?}");
    assert_eq!(joined.data["worker"]["name"], "w1", "{joined:?}");
    assert_eq!(joined.data["id"], joined.id);
    let delay = received.saturating_sub(joined.data["unix_ms"].as_u64().expect("unix_ms"));
    eprintln!("event stream: joined streamed {delay} ms after it happened (recorded first)");

    let job = submit_small(d, &addr);
    let seen = stream.until("done", job);
    let kinds: Vec<&str> = seen.iter().map(|e| e.kind.as_str()).collect();
    assert_eq!(kinds, ["submitted", "started", "done"], "{seen:?}");
    assert_increasing(&[vec![joined.clone()], seen.clone()].concat(), "live");
    for event in &seen {
        assert_eq!(event.data["kind"], event.kind.as_str());
        assert_eq!(event.data["job"]["id"], job);
        assert!(event.data["unix_ms"].as_u64().unwrap() > 1_600_000_000_000);
    }
    assert_eq!(
        seen[0].data["job"]["name"].as_str().map(|n| !n.is_empty()),
        Some(true)
    );
    // The same events, read back from the database.
    assert_eq!(kept_after(&http, 0), [vec![joined], seen].concat());
    // Filters: one kind, one job.
    let only = Stream::open(&http, "/api/v1/events?after=0&follow=false&kinds=done", &[]);
    assert_eq!(kinds_of(&only.read_to_end()), ["done"]);
    let other = Stream::open(
        &http,
        &format!("/api/v1/events?after=0&follow=false&job={}", job + 1),
        &[],
    );
    assert!(other.read_to_end().is_empty());
}

fn kinds_of(events: &[Sse]) -> Vec<&str> {
    events.iter().map(|e| e.kind.as_str()).collect()
}

/// A stream cut while its job waits for a worker, then resumed with `Last-Event-ID`
/// once the job has been paused, resumed, reprioritised and rendered: it gets exactly
/// what the database has after its last id, none lost, none twice, and goes on live.
#[test]
fn a_stream_cut_and_resumed_gets_exactly_the_events_it_missed() {
    let _turn = shared();
    let dir = TempDir::new().unwrap();
    let d = dir.path();
    let (_coordinator, addr, http) = start_coordinator_with_http(d, &[]);
    let mut stream = Stream::open(&http, "/api/v1/events?after=0", &[]);
    let job = submit_small(d, &addr);
    let before = stream.until("submitted", job);
    let last = before.last().unwrap().id;
    drop(stream);

    let id = job.to_string();
    ok(client(d, &addr, &["pause", &id]), "pause");
    ok(client(d, &addr, &["resume", &id]), "resume");
    ok(client(d, &addr, &["priority", &id, "3"]), "priority");
    let _worker = start_worker(d, &addr, "w1");
    wait_done(d, &addr, job, Duration::from_secs(30));
    let missed = kept_after(&http, last);

    let mut resumed = Stream::open(
        &http,
        "/api/v1/events",
        &[("Last-Event-ID", &last.to_string())],
    );
    let got = resumed.until("done", job);
    assert_eq!(got, missed, "exactly what the database has after {last}");
    assert_increasing(&got, "resumed");
    let kinds = kinds_of(&got);
    for kind in ["paused", "resumed", "priority", "joined", "started", "done"] {
        assert!(kinds.contains(&kind), "{kind} missing from {kinds:?}");
    }
    // And it goes on live: a second job's events follow with larger ids.
    let second = submit_small(d, &addr);
    let live = resumed.until("done", second);
    assert!(live[0].id > got.last().unwrap().id, "{live:?}");
    assert_eq!(kinds_of(&live), ["submitted", "started", "done"]);
}

/// The coordinator killed (`kill -9`) under a stream and restarted on the same
/// address and data: the stream resumed with `Last-Event-ID` gets every event the
/// database has after its last id, the ones recorded just before the kill included,
/// and the events after the restart have larger ids than any before.
#[test]
fn a_stream_resumes_across_a_coordinator_killed_and_restarted() {
    let _turn = shared();
    let dir = TempDir::new().unwrap();
    let d = dir.path();
    let listen = format!("127.0.0.1:{}", free_port());
    let http = format!("127.0.0.1:{}", free_port());
    let args = ["--http", http.as_str()];
    let data = d.join("data");
    let (mut coordinator, addr) = start_coordinator(d, &data, &listen, &args, "coordinator-1.log");
    let mut stream = Stream::open(&http, "/api/v1/events?after=0", &[]);
    let job = submit_small(d, &addr);
    let seen = stream.until("submitted", job);
    let last = seen.last().unwrap().id;
    // Events the stream has not read yet, some perhaps not recorded, when it dies.
    let id = job.to_string();
    ok(client(d, &addr, &["pause", &id]), "pause");
    ok(client(d, &addr, &["priority", &id, "2"]), "priority");
    coordinator.kill9();
    // What it had sent before it died, then the end.
    while stream.next().is_some() {}

    let (_coordinator, again) = start_coordinator(d, &data, &listen, &args, "coordinator-2.log");
    assert_eq!(again, addr);
    let before_restart = kept_after(&http, 0);
    let max_before = before_restart.last().map_or(0, |e| e.id);
    assert!(
        kinds_of(&before_restart).starts_with(&["submitted", "paused", "priority"]),
        "the controls answered before the kill are recorded: {before_restart:?}"
    );
    let mut resumed = Stream::open(
        &http,
        "/api/v1/events",
        &[("Last-Event-ID", &last.to_string())],
    );
    ok(client(d, &addr, &["resume", &id]), "resume");
    let _worker = start_worker(d, &addr, "w1");
    let got = resumed.until("done", job);
    assert_increasing(&got, "resumed across the restart");
    let missed: Vec<&Sse> = before_restart.iter().filter(|e| e.id > last).collect();
    assert!(!missed.is_empty(), "{before_restart:?}");
    for event in &missed {
        assert!(
            got.contains(event),
            "{event:?} recorded before the kill is lost: {got:?}"
        );
    }
    let after: Vec<&Sse> = got.iter().filter(|e| e.id > max_before).collect();
    assert!(
        kinds_of(&after.iter().map(|e| (*e).clone()).collect::<Vec<_>>()).starts_with(&["resumed"]),
        "ids go on above {max_before} after the restart: {got:?}"
    );
    assert_eq!(
        got,
        kept_after(&http, last)[..got.len()],
        "the stream is the database's"
    );
}

/// With only the 3 newest events kept, a client resuming after an id trimmed gets a
/// `gap` event saying from which id the stream goes on, then the events kept.
#[test]
fn an_id_older_than_the_events_kept_gets_a_gap_event() {
    let _turn = shared();
    let dir = TempDir::new().unwrap();
    let d = dir.path();
    let (_coordinator, addr, http) =
        start_coordinator_with_http(d, &["--event-retention-count", "3"]);
    // Five submissions: ids 1 to 5, of which 3 to 5 are kept.
    let jobs: Vec<u64> = (0..5).map(|_| submit_small(d, &addr)).collect();
    let mut kept = kept_after(&http, 0);
    // The first event a stream from the start gets is the gap.
    let gap = kept.remove(0);
    assert_eq!(gap.kind, "gap", "{gap:?}");
    assert_eq!(gap.data["after"], 0);
    assert_eq!(gap.data["oldest_kept"], 3);
    assert_eq!(
        gap.id, 2,
        "a reconnect after the gap is not told of it again"
    );
    assert_eq!(ids(&kept), [3, 4, 5]);
    assert_eq!(kept[0].data["job"]["id"], jobs[2]);

    let resumed = Stream::open(
        &http,
        "/api/v1/events?follow=false",
        &[("Last-Event-ID", "1")],
    );
    let got = resumed.read_to_end();
    assert_eq!(
        kinds_of(&got),
        ["gap", "submitted", "submitted", "submitted"]
    );
    assert_eq!(got[0].data["after"], 1);
    // No gap for a client that missed nothing trimmed.
    assert_eq!(ids(&kept_after(&http, 2)), [3, 4, 5]);
}

/// The stream is the farm's: it takes the client token (401 without, 403 with a wrong
/// one or the worker's), and with it streams.
#[test]
fn the_event_stream_takes_the_client_token() {
    let _turn = shared();
    let dir = TempDir::new().unwrap();
    let d = dir.path();
    let worker_token = d.join("worker.token");
    let client_token = d.join("client.token");
    let worker_secret = "51a7c0de9b2f4e8d6c3a1b0f9e8d7c6b5a4f3e2d1c0b9a8f";
    let client_secret = "c0ffee1234567890abcdef1234567890abcdef1234567890";
    write_token_file(&worker_token, &format!("{worker_secret}\n"));
    write_token_file(&client_token, &format!("{client_secret}\n"));
    let (_coordinator, _addr, http) = start_coordinator_with_http(
        d,
        &[
            "--worker-token-file",
            path_str(&worker_token),
            "--client-token-file",
            path_str(&client_token),
        ],
    );
    let path = "/api/v1/events?after=0&follow=false";
    let status = |auth: Option<String>| {
        let headers: Vec<(&str, &str)> = auth
            .as_deref()
            .map(|a| vec![("Authorization", a)])
            .unwrap_or_default();
        Stream::open(&http, path, &headers).status
    };
    assert_eq!(status(None), 401);
    assert_eq!(status(Some("Bearer not-the-secret".into())), 403);
    assert_eq!(status(Some(format!("Bearer {worker_secret}"))), 403);
    let right = Stream::open(
        &http,
        path,
        &[("Authorization", &format!("Bearer {client_secret}"))],
    );
    assert_eq!(right.status, 200, "{}", right.head);
    assert!(right.head.contains("text/event-stream"), "{}", right.head);
    // A resumption point that is not an id is refused, not taken as the start.
    let wrong = Stream::open(
        &http,
        "/api/v1/events",
        &[
            ("Authorization", &format!("Bearer {client_secret}")),
            ("Last-Event-ID", "forty-one"),
        ],
    );
    assert_eq!(wrong.status, 400, "{}", wrong.head);
}

/// A stream from now begins with the latest event's id and no data, so that a client
/// cut off before the first event comes resumes after it, missing nothing.
#[test]
fn a_stream_from_now_starts_with_the_id_to_resume_after() {
    let _turn = shared();
    let dir = TempDir::new().unwrap();
    let d = dir.path();
    let (_coordinator, addr, http) = start_coordinator_with_http(d, &[]);
    submit_small(d, &addr);
    let latest = kept_after(&http, 0)
        .last()
        .expect("the submission's event")
        .id;
    let mut stream = Stream::open(&http, "/api/v1/events", &[]);
    let mut first = Vec::new();
    loop {
        let mut line = String::new();
        stream
            .reader
            .read_line(&mut line)
            .expect("the stream's first lines");
        let line = line.trim_end_matches(['\r', '\n']).to_owned();
        if line.is_empty() {
            break;
        }
        first.push(line);
    }
    let id: Vec<&str> = first
        .iter()
        .filter_map(|l| l.strip_prefix("id:"))
        .map(str::trim)
        .collect();
    assert_eq!(id, [latest.to_string()], "{first:?}");
    assert!(first.iter().all(|l| !l.starts_with("data:")), "{first:?}");
    // Cut before any event; one happens meanwhile; resumed after that id, it comes.
    drop(stream);
    let job = submit_small(d, &addr);
    let resumed = Stream::open(
        &http,
        "/api/v1/events?follow=false",
        &[("Last-Event-ID", &latest.to_string())],
    )
    .read_to_end();
    assert_eq!(kinds_of(&resumed), ["submitted"], "{resumed:?}");
    assert_eq!(resumed[0].data["job"]["id"], job);
}
