//! Webhooks (docs/operations.md, "Webhooks"): each job's end posted to receivers run
//! here, small HTTP servers on 127.0.0.1 that record what they get and answer as told
//! (200, an error status, never, or not there at all):
//!
//! - a cancelled, a failed and a done job are each posted once, signed (the HMAC is
//!   checked here), with the farm event's id, in id order;
//! - a receiver answering 500 is retried with backoff and delivered to; one that never
//!   answers and one that is down are given up after their attempts with the reason
//!   logged, while a healthy one beside them gets every end at once;
//! - a coordinator killed (`kill -9`) while its receiver is down, restarted once it is
//!   up, delivers every end at least once (the figures are printed), and one killed
//!   with a post unanswered posts that end again (the duplicate a receiver drops by id);
//! - HTTPS is verified against `--webhook-ca`, and a wrong CA is refused with the
//!   reason logged;
//! - a full queue drops its oldest waiting ends and counts them.

use std::collections::VecDeque;
use std::io::{BufRead, BufReader, Read, Write};
use std::net::{TcpListener, TcpStream};
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::thread;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use serde_json::Value;
use sha2::{Digest, Sha256};
use tempfile::TempDir;

use crate::support::fake_worker::{FakeWorker, Lie};
use crate::support::{
    client, free_port, http_get_text, ok, path_str, poll, scene_path, shared, start_coordinator,
    start_worker, submit_scene, wait_done, wait_for_workers, REGISTER_TIMEOUT,
};

/// A quick job: the seed scene at 64 × 48, one sample per pixel.
const SMALL: &[&str] = &["--width", "64", "--height", "48", "--aa", "1"];

/// The key the posts are signed with.
const SECRET: &str = "9f1c2b7e4d5a6c3b8e0f1a2d3c4b5a69";

/// How long a test waits for what it expects.
const WAIT: Duration = Duration::from_secs(20);

/// How a receiver answers a post.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Answer {
    Status(u16),
    /// Reads the request and never answers (the connection stays open).
    Silent,
}

/// A post as a receiver got it.
#[derive(Clone, Debug)]
struct Post {
    target: String,
    headers: Vec<(String, String)>,
    raw: String,
    body: Value,
    at: Instant,
    /// When it came, in ms since the Unix epoch.
    unix_ms: u64,
}

impl Post {
    fn header(&self, name: &str) -> Option<&str> {
        self.headers
            .iter()
            .find(|(n, _)| n.eq_ignore_ascii_case(name))
            .map(|(_, v)| v.as_str())
    }

    fn id(&self) -> u64 {
        self.body["id"].as_u64().expect("an event id")
    }
}

/// What a receiver shares with its threads.
#[derive(Default)]
struct Shared {
    posts: Mutex<Vec<Post>>,
    /// The answers to the next posts, in order; then `then`.
    script: Mutex<VecDeque<Answer>>,
    then: Mutex<Option<Answer>>,
    stop: AtomicBool,
}

/// A webhook receiver on 127.0.0.1, plain or TLS, stopped when dropped.
struct Receiver {
    port: u16,
    shared: Arc<Shared>,
}

impl Receiver {
    /// Listens on `port` (0: any), answering `script` in order, then `then`.
    fn start(
        port: u16,
        tls: Option<Arc<rustls::ServerConfig>>,
        script: &[Answer],
        then: Answer,
    ) -> Receiver {
        let listener = TcpListener::bind(("127.0.0.1", port)).expect("bind the receiver");
        let port = listener.local_addr().unwrap().port();
        let shared = Arc::new(Shared::default());
        *shared.script.lock().unwrap() = script.iter().copied().collect();
        *shared.then.lock().unwrap() = Some(then);
        let s = Arc::clone(&shared);
        thread::spawn(move || {
            for stream in listener.incoming() {
                if s.stop.load(Ordering::SeqCst) {
                    return;
                }
                let Ok(stream) = stream else { continue };
                let s = Arc::clone(&s);
                let tls = tls.clone();
                thread::spawn(move || {
                    let _ = stream.set_read_timeout(Some(Duration::from_secs(5)));
                    match tls {
                        Some(config) => {
                            let Ok(conn) = rustls::ServerConnection::new(config) else {
                                return;
                            };
                            serve(&s, rustls::StreamOwned::new(conn, stream));
                        }
                        None => serve(&s, stream),
                    }
                });
            }
        });
        Receiver { port, shared }
    }

    /// A plain receiver answering 200.
    fn healthy() -> Receiver {
        Receiver::start(0, None, &[], Answer::Status(200))
    }

    fn url(&self, scheme: &str) -> String {
        format!("{scheme}://127.0.0.1:{}/hook?token=abc", self.port)
    }

    fn posts(&self) -> Vec<Post> {
        self.shared.posts.lock().unwrap().clone()
    }

    /// The posts, once there are at least `n`.
    fn wait_posts(&self, n: usize, timeout: Duration) -> Vec<Post> {
        poll(&format!("{n} posts to the receiver"), timeout, || {
            let posts = self.posts();
            (posts.len() >= n).then_some(posts)
        })
    }
}

impl Drop for Receiver {
    fn drop(&mut self) {
        self.shared.stop.store(true, Ordering::SeqCst);
        let _ = TcpStream::connect(("127.0.0.1", self.port));
    }
}

/// Reads one request from `stream`, records it, and answers it as scripted.
fn serve(shared: &Shared, stream: impl Read + Write) {
    let mut reader = BufReader::new(stream);
    let mut request_line = String::new();
    if reader.read_line(&mut request_line).unwrap_or(0) == 0 {
        return;
    }
    let target = request_line
        .split_whitespace()
        .nth(1)
        .unwrap_or("")
        .to_owned();
    let mut headers = Vec::new();
    loop {
        let mut line = String::new();
        if reader.read_line(&mut line).unwrap_or(0) == 0 {
            return;
        }
        let line = line.trim_end();
        if line.is_empty() {
            break;
        }
        if let Some((name, value)) = line.split_once(':') {
            headers.push((name.trim().to_owned(), value.trim().to_owned()));
        }
    }
    let length: usize = headers
        .iter()
        .find(|(n, _)| n.eq_ignore_ascii_case("content-length"))
        .and_then(|(_, v)| v.parse().ok())
        .unwrap_or(0);
    let mut body = vec![0; length];
    if reader.read_exact(&mut body).is_err() {
        return;
    }
    let raw = String::from_utf8(body).expect("a UTF-8 body");
    let body = serde_json::from_str(&raw).expect("a JSON body");
    shared.posts.lock().unwrap().push(Post {
        target,
        headers,
        raw,
        body,
        at: Instant::now(),
        unix_ms: unix_ms(),
    });
    let answer = shared
        .script
        .lock()
        .unwrap()
        .pop_front()
        .unwrap_or_else(|| shared.then.lock().unwrap().expect("an answer"));
    match answer {
        Answer::Status(status) => {
            let mut stream = reader.into_inner();
            let _ = write!(
                stream,
                "HTTP/1.1 {status} Whatever\r\nContent-Length: 2\r\nConnection: close\r\n\r\nok"
            );
            let _ = stream.flush();
        }
        Answer::Silent => {
            while !shared.stop.load(Ordering::SeqCst) {
                thread::sleep(Duration::from_millis(50));
            }
        }
    }
}

fn unix_ms() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .unwrap()
        .as_millis() as u64
}

/// HMAC-SHA256 (RFC 2104), as a receiver computes it.
fn hmac_sha256(key: &[u8], message: &[u8]) -> String {
    let mut block = [0u8; 64];
    if key.len() > 64 {
        block[..32].copy_from_slice(&Sha256::digest(key));
    } else {
        block[..key.len()].copy_from_slice(key);
    }
    let pad = |byte: u8| block.iter().map(|b| b ^ byte).collect::<Vec<u8>>();
    let inner = Sha256::new()
        .chain_update(pad(0x36))
        .chain_update(message)
        .finalize();
    let outer = Sha256::new()
        .chain_update(pad(0x5c))
        .chain_update(inner)
        .finalize();
    outer.iter().map(|b| format!("{b:02x}")).collect()
}

/// Checks a post's signature and headers as a receiver would.
fn assert_signed(post: &Post) {
    let timestamp = post.header("Tessera-Timestamp").expect("a timestamp");
    let id = post.header("Tessera-Event-Id").expect("an event id");
    assert_eq!(id, post.id().to_string(), "the header's id is the body's");
    let now = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .unwrap()
        .as_secs();
    let sent: u64 = timestamp.parse().expect("seconds");
    assert!(
        now.abs_diff(sent) < 60,
        "a current timestamp: {sent} at {now}"
    );
    let expected = hmac_sha256(
        SECRET.as_bytes(),
        format!("{timestamp}.{id}.{}", post.raw).as_bytes(),
    );
    assert_eq!(
        post.header("Tessera-Signature"),
        Some(format!("sha256={expected}").as_str()),
        "{post:?}"
    );
    assert_eq!(post.header("Content-Type"), Some("application/json"));
    // Tampered with, it does not verify.
    let forged = hmac_sha256(
        SECRET.as_bytes(),
        format!("{timestamp}.{id}.{}", post.raw.replace("64", "65")).as_bytes(),
    );
    assert_ne!(
        Some(format!("sha256={forged}").as_str()),
        post.header("Tessera-Signature")
    );
}

fn secret_file(dir: &Path) -> String {
    let path = dir.join("webhook.secret");
    std::fs::write(&path, format!("{SECRET}\n")).unwrap();
    path_str(&path).to_owned()
}

fn submit_small(dir: &Path, addr: &str) -> u64 {
    submit_scene(dir, addr, &scene_path("seed.json"), SMALL)
}

/// The value of the metric `name` for `webhook`, as `/metrics` shows it.
fn metric(http: &str, name: &str, webhook: &str) -> Option<f64> {
    let text = http_get_text(http, "/metrics");
    let prefix = format!("{name}{{webhook=\"{webhook}\"}} ");
    text.lines()
        .find_map(|l| l.strip_prefix(&prefix))
        .and_then(|v| v.trim().parse().ok())
}

/// A label as the coordinator gives it: the URL without its query.
fn label(url: &str) -> &str {
    url.split('?').next().unwrap()
}

/// A cancelled job, a failed one and a done one: each end posted once, signed, in id
/// order, with the job's status.
#[test]
fn every_job_end_is_posted_once_signed_and_in_order() {
    let _turn = shared();
    let dir = TempDir::new().unwrap();
    let d = dir.path();
    let receiver = Receiver::healthy();
    let url = receiver.url("http");
    let secret = secret_file(d);
    let (_coordinator, addr) = start_coordinator(
        d,
        &d.join("data"),
        "127.0.0.1:0",
        &["--webhook", &url, "--webhook-secret-file", &secret],
        "coordinator.log",
    );
    // Cancelled before any worker came.
    let cancelled = submit_small(d, &addr);
    ok(
        client(d, &addr, &["cancel", &cancelled.to_string()]),
        "cancel",
    );
    // Failed: every worker reports its first tile failed, as many as its attempts.
    let build = render::build_identity();
    let fakes: Vec<FakeWorker> = (0..5)
        .map(|i| FakeWorker::start(&addr, &format!("f{i}"), &build, Lie::FailFrame(1)))
        .collect();
    wait_for_workers(d, &addr, 5, REGISTER_TIMEOUT);
    let failed = submit_small(d, &addr);
    poll("the job to fail", WAIT, || {
        let posts = receiver.posts();
        posts
            .iter()
            .any(|p| p.body["kind"] == "failed")
            .then_some(())
    });
    drop(fakes);
    let _worker = start_worker(d, &addr, "w1");
    let done = submit_small(d, &addr);
    wait_done(d, &addr, done, WAIT);
    let posts = receiver.wait_posts(3, WAIT);
    // Nothing more comes: each end once.
    thread::sleep(Duration::from_millis(500));
    let posts_after = receiver.posts();
    assert_eq!(posts_after.len(), 3, "{posts_after:#?}");
    let kinds: Vec<(&str, u64)> = posts
        .iter()
        .map(|p| {
            (
                p.body["kind"].as_str().unwrap(),
                p.body["job"]["id"].as_u64().unwrap(),
            )
        })
        .collect();
    assert_eq!(
        kinds,
        [("cancelled", cancelled), ("failed", failed), ("done", done)]
    );
    assert!(
        posts.windows(2).all(|w| w[0].id() < w[1].id()),
        "{posts:#?}"
    );
    for post in &posts {
        assert_signed(post);
        assert_eq!(post.target, "/hook?token=abc");
        assert!(post.body["unix_ms"].as_u64().unwrap() > 1_600_000_000_000);
        assert_eq!(post.body["job"]["state"], post.body["kind"], "{post:?}");
        assert!(post.body["job"]["name"].is_string(), "{post:?}");
        assert!(post.body["job"]["detail"].is_string(), "{post:?}");
    }
    assert!(
        posts[1].body["job"]["error"].is_string(),
        "a failed job says why: {:?}",
        posts[1].body
    );
    assert_eq!(
        posts[2].body["job"]["tiles_done"],
        posts[2].body["job"]["tiles_total"]
    );
}

/// Four webhooks: one answering 500 twice (retried with backoff, then delivered), one
/// never answering, one down (both given up after their attempts, the reason logged),
/// and a healthy one, which gets every end at once, as if the others were not there.
#[test]
fn failing_receivers_are_retried_or_given_up_and_slow_no_one() {
    let _turn = shared();
    let dir = TempDir::new().unwrap();
    let d = dir.path();
    let flaky = Receiver::start(
        0,
        None,
        &[Answer::Status(500), Answer::Status(500)],
        Answer::Status(200),
    );
    let silent = Receiver::start(0, None, &[], Answer::Silent);
    let healthy = Receiver::healthy();
    let down = format!("http://127.0.0.1:{}/down", free_port());
    let http = format!("127.0.0.1:{}", free_port());
    let secret = secret_file(d);
    let (flaky_url, silent_url, healthy_url) =
        (flaky.url("http"), silent.url("http"), healthy.url("http"));
    let (coordinator, addr) = start_coordinator(
        d,
        &d.join("data"),
        "127.0.0.1:0",
        &[
            "--http",
            &http,
            "--webhook-secret-file",
            &secret,
            "--webhook",
            &silent_url,
            "--webhook",
            &down,
            "--webhook",
            &flaky_url,
            "--webhook",
            &healthy_url,
            "--webhook-attempts",
            "3",
            "--webhook-backoff",
            "200ms",
            "--webhook-timeout",
            "1s",
        ],
        "coordinator.log",
    );
    let _worker = start_worker(d, &addr, "w1");
    let jobs: Vec<u64> = (0..2).map(|_| submit_small(d, &addr)).collect();
    for &job in &jobs {
        wait_done(d, &addr, job, WAIT);
    }
    let got = healthy.wait_posts(2, WAIT);
    // At once: well within the silent receiver's timeout, which every end would wait
    // for if that receiver held anyone.
    let delays: Vec<u64> = got
        .iter()
        .map(|p| {
            p.unix_ms
                .saturating_sub(p.body["unix_ms"].as_u64().unwrap())
        })
        .collect();
    eprintln!(
        "webhooks: the healthy receiver got each end {delays:?} ms after it happened, beside \
         a silent receiver (1 s timeout), a down one and one answering 500"
    );
    assert!(delays.iter().all(|&ms| ms < 800), "{delays:?}");
    for (post, job) in got.iter().zip(&jobs) {
        assert_signed(post);
        assert_eq!(post.body["job"]["id"], *job);
    }

    // The flaky one: 500, 500, then 200 for the first end, after 200 ms and 400 ms.
    let flaky_posts = flaky.wait_posts(4, WAIT);
    let first = flaky_posts[0].id();
    assert!(
        flaky_posts[..3].iter().all(|p| p.id() == first),
        "{flaky_posts:#?}"
    );
    let gaps: Vec<u128> = flaky_posts[..3]
        .windows(2)
        .map(|w| w[1].at.duration_since(w[0].at).as_millis())
        .collect();
    eprintln!("webhooks: retries of a receiver answering 500 came {gaps:?} ms apart");
    assert!(gaps[0] >= 200 && gaps[1] >= 400, "{gaps:?}");
    assert!(gaps[0] < 2_000 && gaps[1] < 2_000, "{gaps:?}");
    assert!(flaky_posts[3].id() > first);

    // The silent and the down ones: given up, each end after 3 attempts.
    let down_label = label(&down).to_owned();
    let silent_label = label(&silent_url).to_owned();
    poll("the silent and down webhooks to give up", WAIT, || {
        let silent = metric(&http, "tessera_webhook_given_up_total", &silent_label)?;
        let down = metric(&http, "tessera_webhook_given_up_total", &down_label)?;
        (silent == 2.0 && down == 2.0).then_some(())
    });
    assert_eq!(silent.posts().len(), 6, "3 attempts for each end");
    assert_eq!(
        metric(&http, "tessera_webhook_failed_attempts_total", &down_label),
        Some(6.0)
    );
    assert_eq!(
        metric(
            &http,
            "tessera_webhook_delivered_total",
            label(&healthy_url)
        ),
        Some(2.0)
    );
    assert_eq!(
        metric(&http, "tessera_webhook_delivered_total", label(&flaky_url)),
        Some(2.0)
    );
    let log = coordinator.log_text();
    assert!(
        log.contains("event given up: no answer within 1000 ms (--webhook-timeout) (given up after 3 attempts)"),
        "{log}"
    );
    assert!(
        log.contains("event given up: cannot connect to 127.0.0.1"),
        "{log}"
    );
    assert!(
        !log.contains("token=abc"),
        "the query's credential is not logged"
    );
}

/// The coordinator killed while its receiver is down, with ends waiting, and restarted
/// once the receiver is up: every end is delivered, at least once.
#[test]
fn ends_waiting_across_a_kill_and_restart_are_delivered_at_least_once() {
    let _turn = shared();
    let dir = TempDir::new().unwrap();
    let d = dir.path();
    let port = free_port();
    let url = format!("http://127.0.0.1:{port}/hook");
    let listen = format!("127.0.0.1:{}", free_port());
    let args = [
        "--webhook",
        url.as_str(),
        "--webhook-attempts",
        "100",
        "--webhook-backoff",
        "100ms",
    ];
    let data = d.join("data");
    // A first end delivered before the outage: it must not come again.
    let early = Receiver::start(port, None, &[], Answer::Status(200));
    let (mut coordinator, addr) = start_coordinator(d, &data, &listen, &args, "coordinator-1.log");
    let worker = start_worker(d, &addr, "w1");
    let delivered_early = submit_small(d, &addr);
    early.wait_posts(1, WAIT);
    drop(early);
    thread::sleep(Duration::from_millis(200));
    let jobs: Vec<u64> = (0..4).map(|_| submit_small(d, &addr)).collect();
    for &job in &jobs {
        wait_done(d, &addr, job, WAIT);
    }
    // The receiver down: attempts fail meanwhile.
    thread::sleep(Duration::from_millis(300));
    coordinator.kill9();
    drop(worker);

    let receiver = Receiver::start(port, None, &[], Answer::Status(200));
    let restarted = Instant::now();
    let (_coordinator, again) = start_coordinator(d, &data, &listen, &args, "coordinator-2.log");
    assert_eq!(again, addr);
    let started = restarted.elapsed();
    let posts = receiver.wait_posts(jobs.len(), WAIT);
    let all_in = posts
        .iter()
        .map(|p| p.at.duration_since(restarted))
        .max()
        .unwrap();
    thread::sleep(Duration::from_millis(500));
    let posts = receiver.posts();
    let mut ids: Vec<u64> = posts.iter().map(Post::id).collect();
    let total = ids.len();
    ids.sort_unstable();
    ids.dedup();
    let jobs_posted: Vec<u64> = posts
        .iter()
        .map(|p| p.body["job"]["id"].as_u64().unwrap())
        .collect();
    for job in &jobs {
        assert!(jobs_posted.contains(job), "job {job} lost: {jobs_posted:?}");
    }
    assert!(
        !jobs_posted.contains(&delivered_early),
        "an end delivered before the kill is not sent again: {jobs_posted:?}"
    );
    eprintln!(
        "webhooks across kill -9: {} ends waiting, {total} posts after the restart, {} \
         duplicates; the coordinator started in {} ms and every end was in {} ms after the \
         restart began",
        jobs.len(),
        total - ids.len(),
        started.as_millis(),
        all_in.as_millis()
    );
}

/// The coordinator killed while a post is in flight (its receiver has it and has not
/// answered): after the restart that end is posted again, the others once: at least
/// once, the duplicate told apart by its id.
#[test]
fn an_end_posted_and_not_answered_before_a_kill_is_posted_again() {
    let _turn = shared();
    let dir = TempDir::new().unwrap();
    let d = dir.path();
    let receiver = Receiver::start(0, None, &[], Answer::Silent);
    let url = receiver.url("http");
    let listen = format!("127.0.0.1:{}", free_port());
    let args = ["--webhook", url.as_str(), "--webhook-timeout", "30s"];
    let data = d.join("data");
    let (mut coordinator, addr) = start_coordinator(d, &data, &listen, &args, "coordinator-1.log");
    let worker = start_worker(d, &addr, "w1");
    let jobs: Vec<u64> = (0..3).map(|_| submit_small(d, &addr)).collect();
    for &job in &jobs {
        wait_done(d, &addr, job, WAIT);
    }
    // The first end is with the receiver, unanswered; the others wait behind it.
    let held = receiver.wait_posts(1, WAIT)[0].id();
    coordinator.kill9();
    drop(worker);

    *receiver.shared.then.lock().unwrap() = Some(Answer::Status(200));
    let restarted = Instant::now();
    let (_coordinator, _) = start_coordinator(d, &data, &listen, &args, "coordinator-2.log");
    receiver.wait_posts(1 + jobs.len(), WAIT);
    let all_in = restarted.elapsed();
    thread::sleep(Duration::from_millis(500));
    let posts = receiver.posts();
    assert_eq!(posts.len(), 1 + jobs.len(), "{posts:#?}");
    let ids: Vec<u64> = posts.iter().map(Post::id).collect();
    assert_eq!(ids[1], held, "the unanswered end first again: {ids:?}");
    assert!(ids[1..].windows(2).all(|w| w[0] < w[1]), "{ids:?}");
    let mut posted_jobs: Vec<u64> = posts[1..]
        .iter()
        .map(|p| p.body["job"]["id"].as_u64().unwrap())
        .collect();
    posted_jobs.sort_unstable();
    assert_eq!(posted_jobs, jobs, "every end once after the restart");
    eprintln!(
        "webhooks across kill -9 with a post in flight: {} ends, {} posts, 1 duplicate (event \
         {held}); all delivered {} ms after the restart began",
        jobs.len(),
        posts.len(),
        all_in.as_millis()
    );
}

/// A self-signed certificate for 127.0.0.1: its PEM, and the server's TLS with it.
fn tls_server() -> (String, Arc<rustls::ServerConfig>) {
    let certified =
        rcgen::generate_simple_self_signed(vec!["127.0.0.1".to_owned()]).expect("a certificate");
    let key = rustls::pki_types::PrivateKeyDer::Pkcs8(certified.signing_key.serialize_der().into());
    let config = rustls::ServerConfig::builder_with_provider(Arc::new(
        rustls::crypto::ring::default_provider(),
    ))
    .with_safe_default_protocol_versions()
    .unwrap()
    .with_no_client_auth()
    .with_single_cert(vec![certified.cert.der().clone()], key)
    .expect("a server certificate");
    (certified.cert.pem(), Arc::new(config))
}

/// HTTPS: delivered when the receiver's certificate is signed by `--webhook-ca`,
/// refused (and given up, the reason logged) when it is not.
#[test]
fn https_receivers_are_verified_against_the_given_ca() {
    let _turn = shared();
    let dir = TempDir::new().unwrap();
    let d = dir.path();
    let (pem, config) = tls_server();
    let (other_pem, other_config) = tls_server();
    let trusted = Receiver::start(0, Some(config), &[], Answer::Status(200));
    let stranger = Receiver::start(0, Some(other_config), &[], Answer::Status(200));
    let ca = d.join("ca.pem");
    std::fs::write(&ca, &pem).unwrap();
    let _ = other_pem;
    let stranger_url = stranger.url("https");
    let (coordinator, addr) = start_coordinator(
        d,
        &d.join("data"),
        "127.0.0.1:0",
        &[
            "--webhook",
            &trusted.url("https"),
            "--webhook",
            &stranger_url,
            "--webhook-ca",
            path_str(&ca),
            "--webhook-attempts",
            "2",
            "--webhook-backoff",
            "100ms",
        ],
        "coordinator.log",
    );
    let _worker = start_worker(d, &addr, "w1");
    let job = submit_small(d, &addr);
    let posts = trusted.wait_posts(1, WAIT);
    assert_eq!(posts[0].body["job"]["id"], job);
    assert_eq!(posts[0].body["kind"], "done");
    assert_eq!(
        posts[0].header("Tessera-Signature"),
        None,
        "no secret: not signed"
    );
    let log = poll("the stranger's end given up", WAIT, || {
        let log = coordinator.log_text();
        log.contains("event given up: TLS with 127.0.0.1")
            .then_some(log)
    });
    assert!(
        log.contains("invalid peer certificate") && log.contains("given up after 2 attempts"),
        "{log}"
    );
    assert!(
        log.contains("--webhook-secret-file"),
        "warned of unsigned posts: {log}"
    );
    assert!(
        stranger.posts().is_empty(),
        "nothing crossed an unverified connection"
    );
}

/// With its receiver down and room for 2 waiting, 5 ends: the one being tried stays,
/// the newest 2 wait, the 2 oldest waiting are dropped and counted; once the receiver
/// is up, the 3 kept are delivered in order.
#[test]
fn a_full_queue_drops_its_oldest_waiting_ends_and_counts_them() {
    let _turn = shared();
    let dir = TempDir::new().unwrap();
    let d = dir.path();
    let port = free_port();
    let url = format!("http://127.0.0.1:{port}/hook");
    let http = format!("127.0.0.1:{}", free_port());
    let (coordinator, addr) = start_coordinator(
        d,
        &d.join("data"),
        "127.0.0.1:0",
        &[
            "--http",
            &http,
            "--webhook",
            &url,
            "--webhook-queue",
            "2",
            "--webhook-attempts",
            "100",
            "--webhook-backoff",
            "100ms",
        ],
        "coordinator.log",
    );
    let _worker = start_worker(d, &addr, "w1");
    let jobs: Vec<u64> = (0..5).map(|_| submit_small(d, &addr)).collect();
    for &job in &jobs {
        wait_done(d, &addr, job, WAIT);
    }
    let dropped = poll("2 ends dropped", WAIT, || {
        metric(&http, "tessera_webhook_dropped_total", &url).filter(|&n| n >= 2.0)
    });
    assert_eq!(dropped, 2.0);
    assert_eq!(
        metric(&http, "tessera_webhook_queue_depth", &url),
        Some(3.0)
    );
    let log = coordinator.log_text();
    assert_eq!(
        log.matches("the queue is full (2 waiting)").count(),
        2,
        "{log}"
    );

    // The ends in the order they happened, as the farm's event stream has them.
    let ends: Vec<u64> = http_get_text(&http, "/api/v1/events?after=0&follow=false&kinds=done")
        .lines()
        .filter_map(|l| l.strip_prefix("data:"))
        .map(|data| {
            let event: Value = serde_json::from_str(data.trim()).unwrap();
            event["id"].as_u64().unwrap()
        })
        .collect();
    assert_eq!(ends.len(), 5, "{ends:?}");

    let receiver = Receiver::start(port, None, &[], Answer::Status(200));
    let posts = receiver.wait_posts(3, WAIT);
    let ids: Vec<u64> = posts.iter().map(Post::id).collect();
    // The first end (being tried when the others came), then the newest two.
    assert_eq!(ids, [ends[0], ends[3], ends[4]]);
    poll("the queue to empty", WAIT, || {
        (metric(&http, "tessera_webhook_queue_depth", &url) == Some(0.0)).then_some(())
    });
}
