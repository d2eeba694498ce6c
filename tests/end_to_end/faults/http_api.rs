//! The HTTP API under the faults a pipeline meets: an upload whose connection is cut
//! in the middle of a request and resumed, a client frozen in the middle of its upload
//! while another finishes the file, and a hundred clients polling a job's status while
//! it renders. The figures of the last (the job's time and the coordinator's other
//! answers, quiet against polled) are `tessera-bench --suite api`'s; here the answers
//! are checked, and the image.

use std::io::Write;
use std::net::TcpStream;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::thread;
use std::time::{Duration, Instant};

use serde_json::{json, Value};
use sha2::{Digest, Sha256};
use tempfile::TempDir;

use crate::support::{
    assert_same_png, exclusive, free_port, path_str, poll, render_reference, scene_path,
    start_coordinator, start_worker, status_json, wait_for_workers, Site, REGISTER_TIMEOUT,
};

const TOKEN: &str = "0c4e6a8b2d1f3e5a7c9b0d2f4a6c8e1b";
const MIB: usize = 1 << 20;

/// `METHOD PATH` with the token and `body` (raw bytes for a PUT, JSON otherwise): the
/// status and the body's JSON (`null` when it is not JSON).
fn call(site: &Site, method: &str, path: &str, body: &[u8]) -> (u16, Value) {
    let answer = site.api(TOKEN, method, path, body);
    (
        answer.status,
        serde_json::from_slice(&answer.body).unwrap_or(Value::Null),
    )
}

/// A wavy grid of `n` × `n` vertices as OBJ text: a mesh file of some megabytes.
fn grid_obj(n: usize) -> Vec<u8> {
    let mut obj = String::with_capacity(n * n * 60);
    for j in 0..n {
        for i in 0..n {
            let (x, z) = (i as f64 / (n - 1) as f64, j as f64 / (n - 1) as f64);
            let y = 0.05 * (12.0 * x).sin() * (9.0 * z).cos();
            obj.push_str(&format!("v {:.6} {:.6} {:.6}\n", x - 0.5, y, z - 0.5));
        }
    }
    for j in 0..n - 1 {
        for i in 0..n - 1 {
            let a = j * n + i + 1;
            let (b, c, d) = (a + 1, a + n, a + n + 1);
            obj.push_str(&format!("f {a} {b} {d}\nf {a} {d} {c}\n"));
        }
    }
    obj.into_bytes()
}

/// A scene that draws `grid.obj` under a light.
fn grid_scene() -> Value {
    json!({
        "camera": { "position": "0 1.2 -1.4", "look_at": "0 0 0", "fov": 50 },
        "objects": [{ "type": "mesh", "file": "grid.obj", "color": "0.8 0.6 0.3 0" }],
        "lights": [{ "position": "2 4 -3", "color": "1 1 1" }]
    })
}

/// How many bytes of the file the store holds, as `files/lacking` says (the size once
/// it holds it all).
fn received(site: &Site, sha: &str, size: usize) -> u64 {
    let (status, lacking) = call(
        site,
        "POST",
        "/api/v1/files/lacking",
        json!({ "files": [{ "sha256": sha, "size": size }] })
            .to_string()
            .as_bytes(),
    );
    assert_eq!(status, 200, "{lacking}");
    match lacking["lacking"].as_array().unwrap().first() {
        Some(entry) => entry["received"].as_u64().unwrap(),
        None => size as u64,
    }
}

/// Opens a `PUT` to `path` declaring `declared` bytes and sends `part` of them, leaving
/// the request unfinished: the open connection.
fn unfinished_put(addr: &str, path: &str, declared: usize, part: &[u8]) -> TcpStream {
    let mut tcp = TcpStream::connect(addr).unwrap();
    let head = format!(
        "PUT {path} HTTP/1.1\r\nHost: {addr}\r\nAuthorization: Bearer {TOKEN}\r\n\
         Content-Type: application/octet-stream\r\nContent-Length: {declared}\r\n\
         Connection: close\r\n\r\n"
    );
    tcp.write_all(head.as_bytes()).unwrap();
    tcp.write_all(part).unwrap();
    tcp.flush().unwrap();
    tcp
}

#[test]
fn an_upload_cut_in_the_middle_of_a_request_resumes_at_the_last_chunk_stored() {
    let _turn = exclusive();
    let dir = TempDir::new().unwrap();
    let d = dir.path();
    std::fs::write(d.join("client.token"), format!("{TOKEN}\n")).unwrap();
    let http = format!("127.0.0.1:{}", free_port());
    let token = d.join("client.token");
    let (_coordinator, addr) = start_coordinator(
        d,
        &d.join("data"),
        "127.0.0.1:0",
        &["--http", &http, "--client-token-file", path_str(&token)],
        "coordinator.log",
    );
    let site = Site::plain(&http);
    let obj = grid_obj(470);
    assert!(
        obj.len() > 14 * MIB,
        "a file past the frozen request: {}",
        obj.len()
    );
    std::fs::write(d.join("grid.obj"), &obj).unwrap();
    std::fs::write(d.join("grid.json"), grid_scene().to_string()).unwrap();
    let sha: String = Sha256::digest(&obj)
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect();
    let file = format!("/api/v1/files/{sha}-{}", obj.len());

    // An 8 MiB request cut after 5.5 MiB: the five whole chunks before the cut are kept.
    let cut = unfinished_put(
        &http,
        &format!("{file}?offset=0"),
        8 * MIB,
        &obj[..5 * MIB + MIB / 2],
    );
    cut.shutdown(std::net::Shutdown::Both).unwrap();
    drop(cut);
    poll(
        "the store to hold the chunks sent before the cut",
        Duration::from_secs(10),
        || (received(&site, &sha, obj.len()) == 5 * MIB as u64).then_some(()),
    );

    // A client frozen in the middle of its request (it sent 1.5 MiB more and then
    // nothing) holds nobody up: another resumes from what the store has and finishes.
    let frozen = unfinished_put(
        &http,
        &format!("{file}?offset={}", 5 * MIB),
        8 * MIB,
        &obj[5 * MIB..6 * MIB + MIB / 2],
    );
    let at = poll(
        "the frozen client's whole chunk to be stored",
        Duration::from_secs(10),
        || {
            let at = received(&site, &sha, obj.len());
            (at == 6 * MIB as u64).then_some(at as usize)
        },
    );
    let mut complete = false;
    let mut offset = at;
    while !complete {
        let end = (offset + 8 * MIB).min(obj.len());
        let (status, answer) = call(
            &site,
            "PUT",
            &format!("{file}?offset={offset}"),
            &obj[offset..end],
        );
        assert_eq!(status, 200, "{answer}");
        offset = answer["received"].as_u64().unwrap() as usize;
        complete = answer["complete"] == true;
        assert_eq!(offset, end, "{answer}");
    }
    // The frozen client wakes up and sends the rest of its request: bytes the store
    // already has, checked against them and accepted.
    let mut frozen = frozen;
    frozen
        .write_all(&obj[6 * MIB + MIB / 2..13 * MIB])
        .expect("the frozen client's request is still open");
    frozen
        .set_read_timeout(Some(Duration::from_secs(30)))
        .unwrap();
    let mut answer = String::new();
    std::io::Read::read_to_string(&mut frozen, &mut answer).unwrap();
    assert!(
        answer.starts_with("HTTP/1.1 200") && answer.contains("\"complete\":true"),
        "{answer}"
    );

    // The job of the file renders as `tessera render` renders the scene.
    let asset = json!({ "name": "grid.obj", "sha256": sha, "size": obj.len() });
    let job = json!({
        "scene": grid_scene(), "width": 96, "height": 64, "aa": 1, "assets": [asset],
    });
    let (status, submitted) = call(&site, "POST", "/api/v1/jobs", job.to_string().as_bytes());
    assert_eq!(status, 201, "{submitted}");
    let id = submitted["id"].as_u64().unwrap();
    let _worker = start_worker(d, &addr, "w1");
    let started = Instant::now();
    loop {
        let (status, job) = call(
            &site,
            "GET",
            &format!("/api/v1/jobs/{id}/wait?timeout=5"),
            b"",
        );
        assert_eq!(status, 200, "{job}");
        if job["state"] == "done" {
            break;
        }
        assert!(
            job["state"] == "queued" || job["state"] == "running",
            "{job}"
        );
        assert!(started.elapsed() < Duration::from_secs(90), "{job}");
    }
    let image = site
        .request(
            "GET",
            &format!("/api/v1/jobs/{id}/image.png"),
            &[("Authorization", &format!("Bearer {TOKEN}"))],
            b"",
            Duration::from_secs(30),
        )
        .unwrap();
    assert_eq!(image.status, 200);
    std::fs::write(d.join("fetched.png"), &image.body).unwrap();
    let reference = render_reference(
        d,
        path_str(&d.join("grid.json")),
        "reference.png",
        &["--width", "96", "--height", "64", "--aa", "1"],
    );
    assert_same_png(
        &d.join("fetched.png"),
        &reference,
        "the resumed upload's job",
    );
}

#[test]
fn a_hundred_clients_polling_a_job_are_all_answered_and_the_job_renders_the_same() {
    let _turn = exclusive();
    let dir = TempDir::new().unwrap();
    let d = dir.path();
    let http = format!("127.0.0.1:{}", free_port());
    let (_coordinator, addr) = start_coordinator(
        d,
        &d.join("data"),
        "127.0.0.1:0",
        &["--http", &http],
        "coordinator.log",
    );
    let _workers = [start_worker(d, &addr, "w1"), start_worker(d, &addr, "w2")];
    wait_for_workers(d, &addr, 2, REGISTER_TIMEOUT);
    // Some 5 CPU-seconds in 1,900 tiles: the image of `coordinator.rs`'s `VERY_LONG`,
    // whose reference the faults tests share.
    let scene = scene_path("lights.json");
    let args: &[&str] = &["--width", "2400", "--height", "1800", "--aa", "5"];
    let id = crate::support::submit_scene(d, &addr, &scene, args);

    let stop = Arc::new(AtomicBool::new(false));
    let polls = Arc::new(AtomicU64::new(0));
    let pollers: Vec<_> = (0..100)
        .map(|_| {
            let (stop, polls, site) = (stop.clone(), polls.clone(), Site::plain(&http));
            thread::spawn(move || {
                let path = format!("/api/v1/jobs/{id}");
                loop {
                    let answer = site
                        .request("GET", &path, &[], b"", Duration::from_secs(30))
                        .expect("a poll got no answer");
                    assert_eq!(
                        answer.status,
                        200,
                        "{}",
                        String::from_utf8_lossy(&answer.body)
                    );
                    let job: Value = serde_json::from_slice(&answer.body).expect("a job's JSON");
                    assert_eq!(job["id"], id, "{job}");
                    polls.fetch_add(1, Ordering::Relaxed);
                    if stop.load(Ordering::Relaxed) {
                        break;
                    }
                    thread::sleep(Duration::from_millis(20));
                }
            })
        })
        .collect();
    // The binary protocol's clients are answered meanwhile, and the job ends done.
    let started = Instant::now();
    let done = loop {
        let status = status_json(d, &addr, id);
        if status["state"] == "done" {
            break status;
        }
        assert!(
            status["state"] == "queued" || status["state"] == "running",
            "{status}"
        );
        assert!(started.elapsed() < Duration::from_secs(120), "{status}");
        thread::sleep(Duration::from_millis(50));
    };
    stop.store(true, Ordering::Relaxed);
    for poller in pollers {
        poller
            .join()
            .expect("a poller failed: see its message above");
    }
    let polls = polls.load(Ordering::Relaxed);
    assert!(polls >= 100, "each client polled at least once: {polls}");
    eprintln!(
        "{polls} polls answered during the job ({:.1} s, {} tiles)",
        started.elapsed().as_secs_f64(),
        done["tiles_total"]
    );
    crate::support::assert_job_image(d, &addr, id, &scene, args, "the job polled by 100 clients");
}
