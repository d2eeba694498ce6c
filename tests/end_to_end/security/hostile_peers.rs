//! Hostile and broken peers against a real coordinator (the `tessera` binary, on
//! 127.0.0.1 only) while it renders a real job.
//!
//! What is proven: nothing crashes, nothing grows without bound, and other users are
//! unaffected. While a job renders on two workers and its `submit --wait` client
//! watches it, the coordinator is sent garbage, a wrong magic, a 4 GiB length prefix,
//! a truncated frame, requests that are wrong for the connection's state, a request
//! frame above the frame limit, a worker that lies about its tile, a peer that never
//! speaks, an HTTP request, a scene over 8 MiB, 200 idle connections at once, and
//! handshaken clients holding every connection slot. Each gets the documented answer
//! (a `Refused` frame saying why, an `Error` starting with "bad request", an HTTP 400,
//! a one-line client error naming the limit) and the connection is closed. Then:
//! the job is `done` with `tessera render`'s exact image, the workers never lost their
//! connection, the coordinator still runs and serves new clients (every connection
//! slot was released), its open files are back to what they were, and its resident
//! memory stayed below 300 MB throughout.
//!
//! Smaller tests: a scene above `--max-frame` is refused with one error line, the exact
//! handshake deadline of a silent peer, and the refusal of an oversized submit reaching
//! its client every time.
//!
//! Every wait has a deadline, and every process is killed and reaped by a guard, also
//! when an assertion fails.

use std::io::{ErrorKind, Read, Write};
use std::net::TcpStream;
use std::path::Path;
use std::process::{Command, Stdio};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::thread;
use std::time::{Duration, Instant};

use protocol::{ClientResponse, FromWorker, Hello, Role, ToWorker, Welcome};
use serde_json::Value;
use tempfile::TempDir;

use crate::support::wire::{read_frame, send_frame};
use crate::support::{self, one_error_line, Daemon, SplitMix};

/// The coordinator's `--handshake-timeout-ms` in these tests.
const HANDSHAKE: Duration = Duration::from_millis(1000);
/// The coordinator's `--max-connections` in these tests.
const MAX_CONNECTIONS: usize = 64;
/// The coordinator's default `--max-frame`.
const MAX_FRAME: u32 = 16 * 1024 * 1024;
/// The coordinator's limit on a scene's size.
const MAX_SCENE: usize = 8 * 1024 * 1024;
/// The most resident memory the coordinator may use at any time.
const MAX_RSS_KIB: u64 = 300 * 1024;
/// Longest any single read from the coordinator may take.
const READ_TIMEOUT: Duration = Duration::from_secs(10);

// ---------------------------------------------------------------------------------
// Raw protocol helpers.
// ---------------------------------------------------------------------------------

fn connect(addr: &str) -> TcpStream {
    let stream = TcpStream::connect(addr).expect("cannot connect to the coordinator");
    stream.set_read_timeout(Some(READ_TIMEOUT)).unwrap();
    stream.set_write_timeout(Some(READ_TIMEOUT)).unwrap();
    stream
}

fn read_welcome(stream: &mut TcpStream, what: &str) -> Welcome {
    let frame = read_frame(stream, what);
    protocol::wire::decode(&frame).unwrap_or_else(|e| panic!("{what}: not a Welcome: {e}"))
}

/// The coordinator closes the connection (an orderly end of stream) with nothing more.
fn expect_eof(stream: &mut TcpStream, what: &str) {
    let mut rest = [0; 64];
    match stream.read(&mut rest) {
        Ok(0) => {}
        Ok(n) => panic!(
            "{what}: {n} more bytes instead of a close: {:?}",
            &rest[..n]
        ),
        Err(e) => panic!("{what}: the connection was not closed: {e}"),
    }
}

/// Reads a `Refused` and the close that follows; returns its reason and when it came.
fn expect_refused(stream: &mut TcpStream, started: Instant, what: &str) -> (String, Duration) {
    let reason = match read_welcome(stream, what) {
        Welcome::Refused { reason } => reason,
        other => panic!("{what}: expected Refused, got {other:?}"),
    };
    let took = started.elapsed();
    expect_eof(stream, what);
    (reason, took)
}

/// Opens a client connection: `Hello` as a client, `Accepted` back.
fn client_connection(addr: &str, what: &str) -> TcpStream {
    let mut stream = connect(addr);
    send_frame(&mut stream, &Hello::new(Role::Client).to_frame());
    match read_welcome(&mut stream, what) {
        Welcome::Accepted { .. } => stream,
        other => panic!("{what}: expected Accepted, got {other:?}"),
    }
}

/// Reads a `ClientResponse::Error` and the close that follows; returns its message.
fn expect_error_response(stream: &mut TcpStream, what: &str) -> String {
    let frame = read_frame(stream, what);
    let message = match protocol::wire::decode::<ClientResponse>(&frame) {
        Ok(ClientResponse::Error(refusal)) => {
            assert_eq!(
                refusal.kind,
                protocol::RefusalKind::Invalid,
                "{what}: {refusal}"
            );
            refusal.message
        }
        other => panic!("{what}: expected an Error response, got {other:?}"),
    };
    expect_eof(stream, what);
    message
}

/// Reads until the connection ends (orderly or reset); returns what came before.
fn read_until_closed(stream: &mut TcpStream, what: &str) -> Vec<u8> {
    let mut bytes = Vec::new();
    let mut buf = [0; 4096];
    loop {
        match stream.read(&mut buf) {
            Ok(0) => return bytes,
            Ok(n) => bytes.extend_from_slice(&buf[..n]),
            Err(e) if e.kind() == ErrorKind::ConnectionReset => return bytes,
            Err(e) => panic!("{what}: the connection was not closed: {e}"),
        }
    }
}

// ---------------------------------------------------------------------------------
// The hostile peers. Each checks its own answer and returns a line for the summary.
// ---------------------------------------------------------------------------------

/// A well-framed body of noise: refused as not a Tessera peer.
fn garbage_frame(addr: &str) -> String {
    let mut rng = SplitMix(0x06a7_ba6e);
    let mut noise: Vec<u8> = (0..1000).map(|_| rng.next_u64() as u8).collect();
    noise[0] = 0; // Not "TSRA".
    let mut stream = connect(addr);
    send_frame(&mut stream, &noise);
    let (reason, _) = expect_refused(&mut stream, Instant::now(), "a frame of noise");
    assert!(reason.contains("magic"), "a frame of noise: {reason:?}");
    format!("a frame of noise: refused ({reason})")
}

/// Raw noise whose first four bytes claim a 2 GiB frame: refused or closed at once.
fn raw_noise(addr: &str) -> String {
    let mut rng = SplitMix(0x0bad_b17e);
    let mut noise: Vec<u8> = (0..4096).map(|_| rng.next_u64() as u8).collect();
    noise[..4].copy_from_slice(&[0x7f, 0xff, 0xff, 0xff]);
    let mut stream = connect(addr);
    let started = Instant::now();
    // The coordinator may close before it has read everything: a failed write is fine.
    let _ = stream.write_all(&noise);
    let answer = read_until_closed(&mut stream, "raw noise");
    let took = started.elapsed();
    assert!(took < HANDSHAKE, "raw noise: closed only after {took:?}");
    format!(
        "4 KiB of raw noise: {} bytes back, closed in {took:?}",
        answer.len()
    )
}

/// The right frame layout with another magic: refused, and the reason says why.
fn wrong_magic(addr: &str) -> String {
    let mut hello = b"TSRB".to_vec();
    hello.extend(protocol::PROTOCOL_VERSION.to_le_bytes());
    hello.extend(0u32.to_le_bytes());
    let mut stream = connect(addr);
    send_frame(&mut stream, &hello);
    let (reason, _) = expect_refused(&mut stream, Instant::now(), "a wrong magic");
    assert!(
        reason.contains("magic") && reason.contains("TSRA"),
        "a wrong magic: {reason:?}"
    );
    format!("a wrong magic: refused ({reason})")
}

/// A length prefix of 4 GiB - 1 and nothing else: refused from the prefix alone, at
/// once, without waiting for (or allocating) the body.
fn huge_prefix(addr: &str) -> String {
    let mut stream = connect(addr);
    let started = Instant::now();
    stream.write_all(&[0xff; 4]).expect("cannot send");
    let (reason, took) = expect_refused(&mut stream, started, "a 4 GiB length prefix");
    assert!(
        took < HANDSHAKE && !reason.contains("no handshake"),
        "a 4 GiB length prefix must be refused from the prefix, not by the deadline: \
         {reason:?} after {took:?}"
    );
    format!("a 4 GiB - 1 length prefix: refused in {took:?} ({reason})")
}

/// A prefix of 100 bytes followed by 10: refused when the handshake deadline passes.
fn truncated_frame(addr: &str) -> String {
    let mut stream = connect(addr);
    let started = Instant::now();
    let mut bytes = 100u32.to_be_bytes().to_vec();
    bytes.extend([b'x'; 10]);
    stream.write_all(&bytes).expect("cannot send");
    let (reason, took) = expect_refused(&mut stream, started, "a truncated frame");
    assert!(
        reason.contains("handshake"),
        "a truncated frame: {reason:?}"
    );
    assert!(
        took >= HANDSHAKE.mul_f64(0.9) && took < 5 * HANDSHAKE,
        "a truncated frame refused after {took:?}, with a deadline of {HANDSHAKE:?}"
    );
    format!("a truncated frame: refused after {took:?} ({reason})")
}

/// A client that sends a message that is not a client request.
fn wrong_state(addr: &str, what: &str, body: &[u8]) -> String {
    let mut stream = client_connection(addr, what);
    send_frame(&mut stream, body);
    let message = expect_error_response(&mut stream, what);
    assert!(message.starts_with("bad request"), "{what}: {message:?}");
    format!("{what}: {message}")
}

/// A client request frame one byte above the frame limit: refused from its prefix.
fn oversize_request(addr: &str) -> String {
    let what = "a request frame above --max-frame";
    let mut stream = client_connection(addr, what);
    let started = Instant::now();
    stream
        .write_all(&(MAX_FRAME + 1).to_be_bytes())
        .expect("cannot send");
    let message = expect_error_response(&mut stream, what);
    let took = started.elapsed();
    assert!(message.starts_with("bad request"), "{what}: {message:?}");
    assert!(took < HANDSHAKE, "{what}: answered after {took:?}");
    format!("{what}: {message} (in {took:?})")
}

/// A peer that connects and never speaks: refused once the deadline passes.
fn silent_peer(addr: &str) -> String {
    let mut stream = connect(addr);
    let started = Instant::now();
    let (reason, took) = expect_refused(&mut stream, started, "a silent peer");
    assert!(reason.contains("handshake"), "a silent peer: {reason:?}");
    assert!(
        took >= HANDSHAKE.mul_f64(0.9) && took < 5 * HANDSHAKE,
        "a silent peer refused after {took:?}, with a deadline of {HANDSHAKE:?}"
    );
    format!("a silent peer: refused after {took:?} ({reason})")
}

/// A browser's request: an HTTP 400 in plain text.
fn browser_request(addr: &str) -> String {
    let mut stream = connect(addr);
    stream
        .write_all(b"GET / HTTP/1.1\r\nHost: x\r\n\r\n")
        .expect("cannot send");
    let answer = read_until_closed(&mut stream, "an HTTP request");
    let text = String::from_utf8_lossy(&answer);
    assert!(
        text.starts_with("HTTP/1.0 400"),
        "an HTTP request got {text:?}"
    );
    format!(
        "an HTTP request: {}",
        text.lines().next().unwrap_or_default()
    )
}

/// A worker that renders the canary honestly, then answers its first tile with the
/// wrong number of pixels: its connection is closed; the job is not harmed.
fn lying_worker(addr: &str) -> String {
    let what = "a worker sending a malformed tile";
    let mut stream = connect(addr);
    let hello = Hello::new(Role::Worker {
        name: "liar".into(),
        threads: 1,
        build: render::build_identity(),
        tags: Vec::new(),
    });
    send_frame(&mut stream, &hello.to_frame());
    match read_welcome(&mut stream, what) {
        Welcome::Accepted { .. } => {}
        other => panic!("{what}: expected Accepted, got {other:?}"),
    }
    let (job, tile) = loop {
        let frame = read_frame(&mut stream, what);
        match protocol::wire::decode::<ToWorker>(&frame) {
            Ok(ToWorker::Render { job, tile, .. }) => break (job, tile),
            Ok(ToWorker::Canary {
                scene,
                files,
                renders,
            }) => {
                let images = verify::canary::render(&scene, &files, &renders);
                let answer = FromWorker::CanaryDone { images };
                send_frame(&mut stream, &protocol::wire::encode(&answer));
            }
            Ok(_) => {}
            Err(e) => panic!("{what}: not a ToWorker message: {e}"),
        }
    };
    let lie = FromWorker::TileDone {
        job,
        tile,
        rgb: vec![0; 5],
        rays: 1,
        render_us: 1,
        samples: 1,
        error_sq_sum: 0.0,
    };
    send_frame(&mut stream, &protocol::wire::encode(&lie));
    let started = Instant::now();
    // Messages already queued for it may still arrive before the close.
    read_until_closed(&mut stream, what);
    let took = started.elapsed();
    assert!(took < HANDSHAKE, "{what}: closed only after {took:?}");
    format!("{what}: disconnected in {took:?}")
}

/// A scene of 200,000 spheres, over 8 MiB: one error line naming the limit.
fn oversized_scene(dir: &Path, addr: &str) -> String {
    let scene = dir.join("huge.json");
    std::fs::write(&scene, huge_scene(200_000)).expect("cannot write the scene");
    let scene = scene.to_str().expect("UTF-8 path").to_owned();
    let run = support::client(dir, addr, &["submit", &scene]);
    let line = one_error_line(&run, "submit of a scene over 8 MiB");
    assert!(
        line.contains(&MAX_SCENE.to_string()) && line.contains("limit"),
        "the error names the limit: {line}"
    );
    format!("a scene over 8 MiB: {line}")
}

/// A valid scene with `spheres` spheres, written compactly.
fn huge_scene(spheres: usize) -> String {
    let mut scene = String::from(
        r#"{"camera":{"position":"0 0 -5","look_at":"0 0 0"},"lights":[{"position":"0 5 0","color":"1 1 1"}],"objects":["#,
    );
    for i in 0..spheres {
        if i > 0 {
            scene.push(',');
        }
        scene.push_str(&format!(
            r#"{{"type":"sphere","center":"{} {} 9","radius":0.1,"color":"1 1 1 0"}}"#,
            i % 100,
            i / 100
        ));
    }
    scene.push_str("]}");
    scene
}

/// 200 connections opened at once that never speak: beyond the limit they are
/// refused at once with "too many connections", the others when the handshake
/// deadline passes. Returns how many were refused for the limit.
fn flood(addr: &str) -> usize {
    let mut streams: Vec<TcpStream> = (0..200).map(|_| connect(addr)).collect();
    let started = Instant::now();
    let mut chunks = Vec::new();
    while !streams.is_empty() {
        chunks.push(streams.split_off(streams.len().saturating_sub(25)));
    }
    let reasons: Vec<String> = thread::scope(|s| {
        let handles: Vec<_> = chunks
            .into_iter()
            .map(|chunk| {
                s.spawn(move || {
                    chunk
                        .into_iter()
                        .map(|mut stream| {
                            let what = "one of 200 idle connections";
                            let reason = match read_welcome(&mut stream, what) {
                                Welcome::Refused { reason } => reason,
                                other => panic!("{what}: expected Refused, got {other:?}"),
                            };
                            let mut rest = [0; 16];
                            assert!(
                                matches!(stream.read(&mut rest), Ok(0)),
                                "{what}: not closed after the refusal"
                            );
                            reason
                        })
                        .collect::<Vec<_>>()
                })
            })
            .collect();
        handles
            .into_iter()
            .flat_map(|h| h.join().expect("a flood reader panicked"))
            .collect()
    });
    let too_many = reasons
        .iter()
        .filter(|r| r.contains("too many connections"))
        .count();
    let deadline = reasons.iter().filter(|r| r.contains("handshake")).count();
    assert_eq!(
        too_many + deadline,
        200,
        "every idle connection is refused for the limit or the deadline: {reasons:?}"
    );
    // How many meet the limit depends on how fast the flood connects compared with the
    // handshake deadline that frees slots; that the limit was met is what matters.
    assert!(
        too_many > 0,
        "no idle connection was refused for the limit of {MAX_CONNECTIONS}"
    );
    eprintln!(
        "200 idle connections: {too_many} refused for the limit, {deadline} at the deadline, \
         all answered within {:?}",
        started.elapsed()
    );
    too_many
}

/// Handshaken clients take every free connection slot; a new client is then refused
/// with a clear line, and served again once they have gone.
fn hold_every_slot(dir: &Path, addr: &str) -> usize {
    let mut held = Vec::new();
    loop {
        assert!(
            held.len() <= MAX_CONNECTIONS,
            "more connections than the limit"
        );
        let mut stream = connect(addr);
        send_frame(&mut stream, &Hello::new(Role::Client).to_frame());
        match read_welcome(&mut stream, "a client holding a slot") {
            Welcome::Accepted { .. } => held.push(stream),
            Welcome::Refused { reason } => {
                assert!(reason.contains("too many connections"), "{reason:?}");
                break;
            }
            other => panic!("unexpected {other:?}"),
        }
    }
    let count = held.len();
    let refused = support::client(dir, addr, &["list"]);
    let line = one_error_line(&refused, "list while every slot is held");
    assert!(line.contains("too many connections"), "{line}");
    drop(held);
    support::poll(
        "a client to be served once the slots are released",
        Duration::from_secs(5),
        || {
            support::client(dir, addr, &["list"])
                .status
                .success()
                .then_some(())
        },
    );
    count
}

// ---------------------------------------------------------------------------------
// Tests.
// ---------------------------------------------------------------------------------

/// Some 9 CPU-seconds in 4,275 tiles: it renders through every attack.
const JOB: &[&str] = &[
    "--width", "2400", "--height", "1800", "--aa", "4", "--tile", "32",
];

#[test]
fn hostile_peers_neither_crash_the_coordinator_nor_disturb_a_running_job() {
    let _turn = support::exclusive();
    let dir = TempDir::new().expect("cannot create a temporary directory");
    let dir = dir.path();
    let handshake_ms = HANDSHAKE.as_millis().to_string();
    let max_connections = MAX_CONNECTIONS.to_string();
    let (mut coordinator, addr) = support::start_coordinator(
        dir,
        &dir.join("data"),
        "127.0.0.1:0",
        &[
            "--handshake-timeout-ms",
            &handshake_ms,
            "--max-connections",
            &max_connections,
        ],
        "coordinator.log",
    );
    let _workers: Vec<Daemon> = ["w1", "w2"]
        .iter()
        .map(|name| support::start_worker(dir, &addr, name))
        .collect();
    support::poll("2 workers to register", Duration::from_secs(10), || {
        let run = support::client(dir, &addr, &["workers", "--json"]);
        let workers: Value = serde_json::from_str(run.stdout.trim()).ok()?;
        (workers.as_array()?.len() == 2).then_some(())
    });

    // The memory watch: the coordinator's largest resident set, until told to stop.
    let pid = coordinator.pid();
    let lights = support::scene_path("lights.json");
    let max_rss = AtomicU64::new(0);
    let stop_watch = AtomicBool::new(false);

    thread::scope(|s| {
        s.spawn(|| {
            while !stop_watch.load(Ordering::Relaxed) {
                if let Some(rss) = support::rss_kib(pid) {
                    max_rss.fetch_max(rss, Ordering::Relaxed);
                }
                thread::sleep(Duration::from_millis(20));
            }
        });
        let _stop = StopOnDrop(&stop_watch);

        // The real user: `submit --wait`, one connection for the whole job.
        let waited = dir.join("waited.png");
        let mut args = vec!["submit", lights.as_str(), "--wait", "--coordinator", &addr];
        args.extend(JOB);
        let mut user = Daemon {
            name: "submit --wait".into(),
            child: Command::new(support::BIN)
                .args(&args)
                .arg("-o")
                .arg(&waited)
                .current_dir(dir)
                .stdin(Stdio::null())
                .stdout(Stdio::null())
                .stderr(std::fs::File::create(dir.join("user.log")).unwrap())
                .spawn()
                .expect("cannot start the client"),
            log: Some(dir.join("user.log")),
        };
        let job = support::poll("the job to start", Duration::from_secs(20), || {
            let status = support::client(dir, &addr, &["list", "--json"]);
            let jobs: Value = serde_json::from_str(status.stdout.trim()).ok()?;
            let job = &jobs.as_array()?.first()?;
            (job["tiles_done"].as_u64()? > 0).then(|| job["id"].as_u64().expect("id"))
        });
        let fds_before = support::open_fds(pid).expect("the coordinator's open files");
        // The reference, rendered meanwhile: one more load on the machine.
        let reference = s.spawn(|| {
            let mut size = JOB.to_vec();
            size.truncate(JOB.len() - 2);
            support::render_reference(dir, &lights, "reference.png", &size)
        });
        let attacks_started = Instant::now();

        // 1. Broken and hostile peers, all at once.
        let heartbeat = protocol::wire::encode(&FromWorker::Heartbeat);
        let second_hello = Hello::new(Role::Client).to_frame();
        let addr = addr.as_str();
        let probes: Vec<Box<dyn FnOnce() -> String + Send + '_>> = vec![
            Box::new(|| garbage_frame(addr)),
            Box::new(|| raw_noise(addr)),
            Box::new(|| wrong_magic(addr)),
            Box::new(|| huge_prefix(addr)),
            Box::new(|| huge_prefix(addr)),
            Box::new(|| huge_prefix(addr)),
            Box::new(|| truncated_frame(addr)),
            Box::new(|| wrong_state(addr, "a worker's Heartbeat from a client", &heartbeat)),
            Box::new(|| wrong_state(addr, "a second Hello from a client", &second_hello)),
            Box::new(|| oversize_request(addr)),
            Box::new(|| silent_peer(addr)),
            Box::new(|| browser_request(addr)),
            Box::new(|| lying_worker(addr)),
            Box::new(|| oversized_scene(dir, addr)),
        ];
        let summary: Vec<String> = thread::scope(|p| {
            let handles: Vec<_> = probes.into_iter().map(|probe| p.spawn(probe)).collect();
            handles
                .into_iter()
                .map(|h| h.join().expect("a hostile peer's check failed"))
                .collect()
        });
        for line in &summary {
            eprintln!("{line}");
        }

        // 2. 200 idle connections at once.
        flood(addr);

        // 3. Every slot held by handshaken clients, then released.
        let held = hold_every_slot(dir, addr);
        eprintln!(
            "{held} handshaken clients held every free slot; attacks took {:.1} s",
            attacks_started.elapsed().as_secs_f64()
        );

        // The real user was not disturbed.
        let exit = user
            .wait_exit(Duration::from_secs(60))
            .expect("submit --wait still runs after 60 s");
        assert!(exit.success(), "submit --wait failed: {}", user.log_text());
        let status = support::try_status(dir, addr, job).expect("status after the attacks");
        assert_eq!(status["state"], "done", "{status}");
        assert_eq!(status["tiles_done"], status["tiles_total"], "{status}");
        let reference = reference.join().expect("the reference render panicked");
        support::assert_same_png(&waited, &reference, "the image submit --wait wrote");
        let fetched = support::fetch(dir, addr, job, "fetched.png");
        support::assert_same_png(&fetched, &reference, "the fetched image");

        // The workers never lost their connection.
        let run = support::ok(
            support::client(dir, addr, &["workers", "--json"]),
            "workers",
        );
        let workers: Value = serde_json::from_str(run.stdout.trim()).expect("workers --json");
        let mut names: Vec<&str> = workers
            .as_array()
            .expect("an array")
            .iter()
            .filter_map(|w| {
                (w["connected_ms"].as_u64()? >= attacks_started.elapsed().as_millis() as u64)
                    .then_some(w["name"].as_str()?)
            })
            .collect();
        names.sort_unstable();
        assert_eq!(
            names,
            ["w1", "w2"],
            "connected since before the attacks: {workers}"
        );

        // Still alive, serving, and holding no more than before.
        assert!(coordinator.is_running(), "the coordinator died");
        support::ok(
            support::client(dir, addr, &["list"]),
            "list after the attacks",
        );
        let fds = support::poll(
            "the coordinator's open files to be released",
            Duration::from_secs(5),
            || {
                let fds = support::open_fds(pid)?;
                (fds <= fds_before).then_some(fds)
            },
        );
        eprintln!("coordinator open files: {fds_before} during the job, {fds} after");
    });
    let max_rss = max_rss.load(Ordering::Relaxed);
    eprintln!("coordinator's largest resident set: {} MiB", max_rss / 1024);
    assert!(max_rss > 0, "the memory watch saw nothing");
    assert!(
        max_rss < MAX_RSS_KIB,
        "the coordinator's resident set reached {} MiB",
        max_rss / 1024
    );
    assert!(coordinator.is_running(), "the coordinator died");
}

/// Sets the flag when dropped: the memory watch stops even if an assertion fails.
struct StopOnDrop<'a>(&'a AtomicBool);

impl Drop for StopOnDrop<'_> {
    fn drop(&mut self) {
        self.0.store(true, Ordering::Relaxed);
    }
}

/// A coordinator with `--max-frame` 2 MiB, its address, and the file of a valid 3 MiB
/// scene (under the 8 MiB scene limit, over the frame limit).
fn small_frame_coordinator(dir: &Path) -> (Daemon, String, String) {
    let (coordinator, addr) = support::start_coordinator(
        dir,
        &dir.join("data"),
        "127.0.0.1:0",
        &["--max-frame", "2097152"],
        "coordinator.log",
    );
    let text = huge_scene(45_000);
    assert!(
        text.len() > 2 * 1024 * 1024 + 64 && text.len() < MAX_SCENE,
        "{}",
        text.len()
    );
    let scene = dir.join("three-mib.json");
    std::fs::write(&scene, text).expect("cannot write the scene");
    let scene = scene.to_str().expect("UTF-8 path").to_owned();
    (coordinator, addr, scene)
}

/// A submit whose frame is above `--max-frame` fails with one error line and leaves
/// no job; the coordinator then serves a normal job.
#[test]
fn a_submit_above_max_frame_is_refused_and_the_coordinator_serves_on() {
    let _turn = support::shared();
    let dir = TempDir::new().expect("cannot create a temporary directory");
    let dir = dir.path();
    let (mut coordinator, addr, scene) = small_frame_coordinator(dir);
    let _worker = support::start_worker(dir, &addr, "w1");
    let run = support::client(dir, &addr, &["submit", &scene]);
    let line = one_error_line(&run, "a submit above --max-frame");
    assert!(
        line.contains("frame") || line.contains(&addr),
        "the error says what or where: {line}"
    );
    eprintln!("{line}");
    assert!(coordinator.is_running(), "the coordinator died");
    let jobs = support::ok(support::client(dir, &addr, &["list", "--json"]), "list");
    assert_eq!(jobs.stdout.trim(), "[]", "the refused submit left no job");

    let seed = support::scene_path("seed.json");
    let small = ["--width", "200", "--height", "150"];
    let mut args = vec![seed.as_str()];
    args.extend(small);
    let job = support::submit(dir, &addr, &args);
    support::wait_done(dir, &addr, job, Duration::from_secs(30));
    let reference = support::render_reference(dir, &seed, "reference.png", &small);
    let out = support::fetch(dir, &addr, job, "out.png");
    support::assert_same_png(&out, &reference, "a job after the refused submit");
}

/// The coordinator's refusal of an oversized submit (`bad request: …`) reaches the
/// client every time.
#[test]
fn an_oversized_submit_always_gets_the_coordinators_refusal() {
    let _turn = support::shared();
    let dir = TempDir::new().expect("cannot create a temporary directory");
    let dir = dir.path();
    let (_coordinator, addr, scene) = small_frame_coordinator(dir);
    let lines: Vec<String> = (0..10)
        .map(|_| {
            let run = support::client(dir, &addr, &["submit", &scene]);
            one_error_line(&run, "a submit above --max-frame")
        })
        .collect();
    assert!(
        lines.iter().all(|l| l.contains("bad request")),
        "some clients did not get the refusal: {lines:#?}"
    );
}

/// A peer that never speaks is refused when the handshake deadline passes, not later.
#[test]
fn a_silent_peer_is_refused_at_the_handshake_deadline() {
    let _turn = support::exclusive();
    let dir = TempDir::new().expect("cannot create a temporary directory");
    let dir = dir.path();
    let handshake_ms = HANDSHAKE.as_millis().to_string();
    let (_coordinator, addr) = support::start_coordinator(
        dir,
        &dir.join("data"),
        "127.0.0.1:0",
        &["--handshake-timeout-ms", &handshake_ms],
        "coordinator.log",
    );
    let mut stream = connect(&addr);
    let (reason, took) = expect_refused(&mut stream, Instant::now(), "a silent peer");
    assert!(reason.contains("handshake"), "{reason:?}");
    assert!(
        took < HANDSHAKE.mul_f64(1.5),
        "a silent peer was refused after {took:?}, with a deadline of {HANDSHAKE:?}"
    );
}
