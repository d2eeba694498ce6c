//! The animated preview of a sequence job, end to end: a real `tessera` coordinator
//! (with `--http`) and workers on 127.0.0.1, and a sequence of three frames of
//! scenes/moving-spheres.json submitted through the client library.
//!
//! - Before any frame is done, `GET /api/jobs/ID/preview.gif` and `.../frames/1.png`
//!   answer 409; a job that is not a sequence, an unknown job and a frame the sequence
//!   does not have answer 404, each with a one-line message.
//! - Once done, the preview is a looping GIF of the three frames at the scene's 24 fps,
//!   at the frames' size (under the 320-pixel limit), with an `ETag` that a poll gets
//!   304 for; each frame's PNG is served as stored, and a damaged one is refused.
//! - `/api/status` lists the sequence with its frames, not its frame jobs; the status
//!   page (in headless Chromium, where there is one) shows "frames 3 / 3" and plays the
//!   preview.

use std::path::Path;
use std::time::Duration;

use coordinator::client::Client;
use protocol::{FrameRange, JobId, JobSpec, JobState, Overrides};
use transport::Endpoint;

use crate::support::browser::{browser_or_skip, dump_dom};
use crate::support::{
    free_port, header, http_request, json_error, poll, scene_path, shared, start_coordinator,
    start_worker,
};

const WIDTH: u32 = 64;
const HEIGHT: u32 = 48;
const JOB_TIMEOUT: Duration = Duration::from_secs(120);

/// `GET PATH` with extra header lines, which must be answered within 30 s: the status,
/// the head (lowercased) and the body.
fn get(addr: &str, path: &str, headers: &str) -> (u16, String, Vec<u8>) {
    let answer = http_request(addr, path, headers, Duration::from_secs(30))
        .unwrap_or_else(|| panic!("no answer from the HTTP listener to GET {path}"));
    (answer.status, answer.head, answer.body)
}

fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap()
}

fn submit(addr: &str, frames: Option<FrameRange>) -> JobId {
    let scene = std::fs::read_to_string(scene_path("moving-spheres.json")).unwrap();
    let spec = JobSpec {
        scene,
        overrides: Overrides {
            width: Some(WIDTH),
            height: Some(HEIGHT),
            aa: Some(1),
            tile_size: Some(16),
            ..Overrides::default()
        },
        priority: 0,
        verification: Default::default(),
        time_limit_ms: None,
        name: "preview".into(),
        submitter: "test".into(),
        frame: 1,
        frames,
        assets: Vec::new(),
        after: Vec::new(),
        require: Vec::new(),
    };
    runtime().block_on(async {
        let mut client = Client::connect(&Endpoint::plain(addr)).await.unwrap();
        client.submit(spec).await.unwrap()
    })
}

fn state(addr: &str, job: JobId) -> JobState {
    runtime().block_on(async {
        let mut client = Client::connect(&Endpoint::plain(addr)).await.unwrap();
        client.status(job).await.unwrap().state
    })
}

/// A frame of a GIF: its size, delay in hundredths of a second, and pixels.
struct GifFrame {
    width: u32,
    height: u32,
    delay_cs: u32,
    rgba: Vec<u8>,
}

/// The frames of a GIF, by the `gif` crate's decoder (the coordinator's encoder), in
/// RGBA; each frame of the previews covers the whole picture from its corner.
fn gif_frames(gif: &[u8]) -> Vec<GifFrame> {
    let mut options = gif::DecodeOptions::new();
    options.set_color_output(gif::ColorOutput::RGBA);
    let mut decoder = options.read_info(gif).expect("a GIF");
    let screen = (decoder.width(), decoder.height());
    let mut frames = Vec::new();
    while let Some(frame) = decoder.read_next_frame().expect("a GIF frame") {
        assert_eq!(
            (frame.left, frame.top, frame.width, frame.height),
            (0, 0, screen.0, screen.1),
            "a frame that does not cover the picture"
        );
        frames.push(GifFrame {
            width: u32::from(frame.width),
            height: u32::from(frame.height),
            delay_cs: u32::from(frame.delay),
            rgba: frame.buffer.to_vec(),
        });
    }
    frames
}

#[test]
fn a_sequence_has_an_animated_preview_its_frames_and_a_page_that_plays_it() {
    let _turn = shared();
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let http = format!("127.0.0.1:{}", free_port());
    let (_coordinator, addr) = start_coordinator(
        dir.path(),
        &data,
        "127.0.0.1:0",
        &["--http", &http],
        "coordinator.log",
    );

    // No worker yet: nothing is done.
    let sequence = submit(&addr, Some(FrameRange { first: 1, last: 3 }));
    let single = submit(&addr, None);
    let (code, _, body) = get(&http, &format!("/api/jobs/{sequence}/preview.gif"), "");
    assert_eq!(code, 409, "{}", json_error(&body));
    assert!(
        json_error(&body).contains("no preview yet"),
        "{}",
        json_error(&body)
    );
    let (code, _, body) = get(&http, &format!("/api/jobs/{sequence}/frames/1.png"), "");
    assert_eq!(code, 409, "{}", json_error(&body));
    let (code, _, body) = get(&http, &format!("/api/jobs/{single}/preview.gif"), "");
    assert_eq!(code, 404);
    assert!(
        json_error(&body).contains("not a sequence"),
        "{}",
        json_error(&body)
    );
    let (code, _, body) = get(&http, "/api/jobs/999/preview.gif", "");
    assert_eq!(code, 404);
    assert!(
        json_error(&body).starts_with("no job 999"),
        "{}",
        json_error(&body)
    );
    for path in [
        "frames/4.png",
        "frames/0.png",
        "frames/one.png",
        "frames/1.gif",
    ] {
        let (code, _, body) = get(&http, &format!("/api/jobs/{sequence}/{path}"), "");
        assert_eq!(code, 404, "{path}: {}", json_error(&body));
    }

    let _workers = [
        start_worker(dir.path(), &addr, "w1"),
        start_worker(dir.path(), &addr, "w2"),
    ];
    poll("the sequence to be done", JOB_TIMEOUT, || {
        let s = state(&addr, sequence);
        assert!(
            !s.is_final() || s == JobState::Done,
            "the sequence is {s:?}"
        );
        (s == JobState::Done).then_some(())
    });

    // The preview: three frames, at their size, 24 fps (4 hundredths), looping.
    let (code, head, gif) = get(&http, &format!("/api/jobs/{sequence}/preview.gif"), "");
    assert_eq!(code, 200);
    assert_eq!(header(&head, "content-type"), Some("image/gif"));
    assert!(
        gif.windows(11).any(|w| w == b"NETSCAPE2.0"),
        "a looping GIF"
    );
    let frames = gif_frames(&gif);
    assert_eq!(frames.len(), 3);
    for frame in &frames {
        assert_eq!(
            (frame.width, frame.height, frame.delay_cs),
            (WIDTH, HEIGHT, 4)
        );
    }
    assert_ne!(
        frames[0].rgba, frames[2].rgba,
        "the spheres move between frames"
    );
    // A poll of the same frames: 304, nothing made again.
    let tag = header(&head, "etag").expect("an ETag").to_owned();
    let (code, again, body) = get(
        &http,
        &format!("/api/jobs/{sequence}/preview.gif"),
        &format!("If-None-Match: {tag}\r\n"),
    );
    assert_eq!((code, body.len()), (304, 0));
    assert_eq!(header(&again, "etag"), Some(tag.as_str()));

    // Each frame as stored, its checksum its ETag.
    for k in 1..=3 {
        let (code, head, png) = get(&http, &format!("/api/jobs/{sequence}/frames/{k}.png"), "");
        assert_eq!(code, 200, "frame {k}");
        assert_eq!(header(&head, "content-type"), Some("image/png"));
        let stored = data.join(format!("jobs/{sequence}/frame_{k:04}.png"));
        assert_eq!(png, std::fs::read(&stored).unwrap(), "frame {k}");
        let decoded = crate::support::decode_png(&png).unwrap();
        assert_eq!(decoded.dimensions(), (WIDTH, HEIGHT));
        assert!(
            header(&head, "etag").is_some_and(|t| t.len() == 66),
            "{head}"
        );
    }

    // The farm's state as the page reads it: the sequence with its frames, not its
    // frame jobs.
    let (code, _, body) = get(&http, "/api/status", "");
    assert_eq!(code, 200);
    let farm: serde_json::Value = serde_json::from_slice(&body).unwrap();
    let ids: Vec<u64> = farm["jobs"]
        .as_array()
        .unwrap()
        .iter()
        .map(|j| j["id"].as_u64().unwrap())
        .collect();
    assert_eq!(ids, vec![sequence, single]);
    let listed = &farm["jobs"][0];
    assert_eq!(listed["state"], "done");
    assert_eq!(listed["frames"]["done"], 3);
    assert_eq!(listed["frames"]["done_prefix"], 3);
    assert_eq!(listed["frames"]["failed"], 0);
    assert!(farm["jobs"][1]["frames"].is_null());

    page_shows_the_frames_and_plays_the_preview(dir.path(), &http, sequence);

    // A damaged frame is not served.
    let stored = data.join(format!("jobs/{sequence}/frame_0002.png"));
    let mut bytes = std::fs::read(&stored).unwrap();
    let middle = bytes.len() / 2;
    bytes[middle] ^= 0x40;
    std::fs::write(&stored, bytes).unwrap();
    let (code, _, body) = get(&http, &format!("/api/jobs/{sequence}/frames/2.png"), "");
    assert_eq!(code, 500);
    assert!(
        json_error(&body).contains("damaged"),
        "{}",
        json_error(&body)
    );
}

/// The status page of `job`, in headless Chromium if there is one: "frames 3 / 3" and
/// the preview loaded, at the frames' size.
fn page_shows_the_frames_and_plays_the_preview(dir: &Path, http: &str, job: JobId) {
    let Some(chromium) = browser_or_skip() else {
        return;
    };
    let profile = dir.join("browser-profile");
    let url = format!("http://{http}/?job={job}");
    let html = poll("the page to play the preview", JOB_TIMEOUT, || {
        let out = dump_dom(&chromium, &profile, &url, 3000);
        let html = String::from_utf8_lossy(&out.stdout).into_owned();
        (html.contains("data-preview=\"3\"") && html.contains("frames 3 / 3")).then_some(html)
    });
    let img = html
        .split("<img id=\"picture\"")
        .nth(1)
        .and_then(|rest| rest.split('>').next())
        .expect("the picture");
    assert!(img.contains(&format!("data-job=\"{job}\"")), "{img}");
    assert!(img.contains(&format!("data-width=\"{WIDTH}\"")), "{img}");
    assert!(img.contains("preview.gif"), "{img}");
    assert!(!img.contains(" hidden"), "{img}");
    let frames = html
        .split("<p id=\"frames\"")
        .nth(1)
        .and_then(|rest| rest.split("</p>").next())
        .expect("the frames line");
    assert!(frames.contains("data-done=\"3\""), "{frames}");
    assert!(frames.contains("data-failed=\"0\""), "{frames}");
}
