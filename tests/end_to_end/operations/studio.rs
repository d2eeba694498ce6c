//! The studio in a real headless browser (Chromium, driven over the DevTools protocol)
//! on the farm `tessera studio` starts: the page opens the given scene; dragging the
//! camera with the mouse changes the picture; a sphere's radius typed into its field
//! changes it too; an invalid value shows the loader's error under the field while the
//! last good picture stays; the saved scene, rendered by `tessera render`, gives the
//! very pixels of the studio's final picture; "Render" submits a stored job whose image
//! is byte-identical to `tessera render`'s and which `tessera list` shows. The latencies
//! of camera drags (docs/performance.md) are measured and printed, never asserted: the
//! machine is shared.
//!
//! Needs Chromium: see `support/browser.rs` (`TESSERA_REQUIRE_BROWSER=1` in CI).

use std::path::Path;
use std::time::{Duration, Instant};

use crate::support::browser::{browser_or_skip, DevTools};
use crate::support::{
    assert_same_png, exclusive, http_get, http_post, ok, poll, shared, spawn_tessera, tessera,
    wait_done, Daemon,
};

const TIMEOUT: Duration = Duration::from_secs(60);
/// Camera drags whose latencies are measured.
const DRAGS: usize = 12;

/// The seed scene at the size of the latency goals (960 × 540, aa 2).
const SCENE: &str = r#"{
  "camera": { "position": "3 1.5 -4", "look_at": "0 0 0" },
  "image": { "width": 960, "height": 540, "aa": 2 },
  "lights": [
    { "position": "-7 10 -10", "color": "1 1 1 0" },
    { "position": "7 10 10", "color": "1 1 1 0" }
  ],
  "objects": [
    { "type": "sphere", "center": "0 0 0", "radius": 1, "color": "0.5 1 0.5 0.3" },
    { "type": "sphere", "center": "3 0 0", "radius": 1, "color": "0.5 0.5 0.5 0.6" },
    { "type": "plane", "normal": "0 1 0", "distance": -1, "color": "0.5 0.25 0.2 2" }
  ]
}"#;

/// A 32-bit FNV-1a of RGB bytes: the same sum the page computes of its canvas.
fn fnv(rgb: &[u8]) -> u32 {
    rgb.iter().fold(0x811c_9dc5u32, |h, &b| {
        (h ^ u32::from(b)).wrapping_mul(0x0100_0193)
    })
}

/// The canvas's RGB, hashed in the page as [`fnv`] does.
const CANVAS_HASH: &str = "(() => { const v = document.getElementById('view'); \
    const d = v.getContext('2d').getImageData(0, 0, v.width, v.height).data; \
    let h = 0x811c9dc5; for (let i = 0; i < d.length; i++) { if (i % 4 === 3) continue; \
    h = Math.imul(h ^ d[i], 0x01000193) >>> 0; } return h; })()";

/// The page's final picture generation (0 until one is complete).
fn final_generation(page: &mut DevTools) -> u64 {
    page.eval("Number(document.getElementById('view').dataset.finalGeneration || 0)")
        .as_u64()
        .unwrap_or(0)
}

/// Waits for a final picture of a generation after `after`, and for no edit in flight.
fn wait_final(page: &mut DevTools, after: u64, what: &str) -> u64 {
    poll(what, TIMEOUT, || {
        let g = final_generation(page);
        let idle = page.eval("!sending && !dirty").as_bool() == Some(true);
        let current = page.eval("generation").as_u64() == Some(g);
        (g > after && idle && current).then_some(g)
    })
}

/// Drags the mouse on the picture from its centre by (dx, dy) pixels, in steps.
fn drag(page: &mut DevTools, dx: f64, dy: f64) {
    let at = page.eval(
        "(() => { const r = document.getElementById('view').getBoundingClientRect(); \
         return [r.x + r.width / 2, r.y + r.height / 2]; })()",
    );
    let (x, y) = (at[0].as_f64().unwrap(), at[1].as_f64().unwrap());
    let mouse = |page: &mut DevTools, kind: &str, x: f64, y: f64| {
        page.call(
            "Input.dispatchMouseEvent",
            serde_json::json!({ "type": kind, "x": x, "y": y, "button": "left",
                                "buttons": 1, "clickCount": 1 }),
        );
    };
    mouse(page, "mousePressed", x, y);
    for step in 1..=4 {
        let f = f64::from(step) / 4.0;
        mouse(page, "mouseMoved", x + dx * f, y + dy * f);
    }
    mouse(page, "mouseReleased", x + dx, y + dy);
}

/// Replaces the text of the input `path` as a user does: focus, select all, type.
fn type_into(page: &mut DevTools, path: &str, text: &str) {
    let found = page.eval(&format!(
        "(() => {{ const e = document.querySelector('input[data-path=\"{path}\"]'); \
         if (!e) return false; e.focus(); e.select(); return true; }})()"
    ));
    assert_eq!(found.as_bool(), Some(true), "no input {path}");
    page.call("Input.insertText", serde_json::json!({ "text": text }));
}

/// The p-th percentile (0..=100) of `values`, nearest rank.
fn percentile(values: &[f64], p: f64) -> f64 {
    let mut sorted = values.to_vec();
    sorted.sort_by(f64::total_cmp);
    let rank = ((p / 100.0) * sorted.len() as f64).ceil() as usize;
    sorted[rank.clamp(1, sorted.len()) - 1]
}

/// The stdout line of `tessera studio` that starts with `prefix`, once printed.
fn printed(dir: &Path, prefix: &str) -> String {
    poll("the studio's address", TIMEOUT, || {
        let out = std::fs::read_to_string(dir.join("studio.log.out")).ok()?;
        out.lines()
            .find_map(|l| l.strip_prefix(prefix).map(str::to_owned))
    })
}

#[test]
fn the_studio_renders_edits_and_camera_drags_and_saves_what_tessera_render_gives() {
    let _turn = exclusive();
    let Some(chromium) = browser_or_skip() else {
        return;
    };
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    std::fs::write(dir.join("start.json"), SCENE).unwrap();
    let mut studio: Daemon = spawn_tessera(
        dir,
        &[
            "studio",
            "start.json",
            "--workers",
            "2",
            "--threads-per-worker",
            "1",
        ],
        "studio.log",
    );
    let url = printed(dir, "studio on ");
    let http = url
        .trim_start_matches("http://")
        .trim_end_matches("/studio")
        .to_owned();
    let farm = printed(dir, "farm: coordinator ");
    let coordinator = farm.split_whitespace().next().unwrap().to_owned();
    assert!(http.starts_with("127.0.0.1:"), "{url}");

    // Its endpoints take only what the page sends: JSON from its own origin; a stream
    // only of a view the coordinator opened.
    let (code, _) = http_post(&http, "/api/studio/open", &[], "{}");
    assert_eq!(code, 415);
    let json = ("Content-Type", "application/json");
    let (code, _) = http_post(
        &http,
        "/api/studio/open",
        &[json, ("Origin", "http://evil.example")],
        "{}",
    );
    assert_eq!(code, 403);
    let (code, body) = http_get(&http, "/api/studio/stream?session=guessed").unwrap();
    assert_eq!(code, 404, "{}", String::from_utf8_lossy(&body));
    let (code, body) = http_post(
        &http,
        "/api/studio/view",
        &[json],
        &format!(r#"{{"session": "guessed", "scene": {SCENE}}}"#),
    );
    assert_eq!(code, 422, "{body}");
    assert!(body.contains("no studio view"), "{body}");

    let mut page = DevTools::open(
        &chromium,
        &dir.join("profile"),
        &url,
        &dir.join("chromium.log"),
    );
    page.call(
        "Browser.setDownloadBehavior",
        serde_json::json!({ "behavior": "allow", "downloadPath": dir.to_str().unwrap() }),
    );
    let first = wait_final(&mut page, 0, "the first final picture");
    // The page opened the scene it was given (960 × 540), not its own default.
    assert_eq!(
        page.eval("JSON.stringify([scene.image.width, scene.image.height, scene.image.aa])"),
        "[960,540,2]"
    );
    let mut shown = page.eval(CANVAS_HASH).as_u64().unwrap();
    // The page's own start (its script, the first layout) is not streaming.
    page.eval("window.studioStats.longestTaskMs = 0");
    let count = |page: &mut DevTools, key: &str| {
        page.eval(&format!("window.studioStats.{key}.length"))
            .as_u64()
            .unwrap() as usize
    };
    let firsts_before = count(&mut page, "firstPaintMs");
    let fulls_before = count(&mut page, "fullMs");

    // Camera drags: each changes the picture; the page measures how long the first
    // updated picture and the full one take after each edit.
    let mut generation = first;
    for i in 0..DRAGS {
        let sign = if i % 2 == 0 { 1.0 } else { -1.0 };
        drag(&mut page, 40.0 * sign, 6.0);
        generation = wait_final(&mut page, generation, "the picture after a drag");
        let now = page.eval(CANVAS_HASH).as_u64().unwrap();
        assert_ne!(now, shown, "drag {i}: the picture did not change");
        shown = now;
    }
    let stats = page.eval("JSON.stringify(window.studioStats)");
    let stats: serde_json::Value = serde_json::from_str(stats.as_str().unwrap()).unwrap();
    let list = |key: &str| -> Vec<f64> {
        stats[key]
            .as_array()
            .unwrap()
            .iter()
            .filter_map(serde_json::Value::as_f64)
            .collect()
    };
    // Every edit the drags made whose picture was shown (an edit superseded before any
    // of its tiles came has none); the page's own first picture is not a drag's.
    let (firsts, fulls) = (list("firstPaintMs"), list("fullMs"));
    let firsts = &firsts[firsts_before..];
    let fulls = &fulls[fulls_before..];
    assert!(firsts.len() >= DRAGS && fulls.len() >= DRAGS, "{stats}");
    eprintln!(
        "studio latency after a camera drag, 960x540 aa 2, 2 local workers: first picture \
         p50 {:.0} ms p95 {:.0} ms; full picture p50 {:.0} ms p95 {:.0} ms; longest task \
         {:.0} ms ({} edits by {DRAGS} drags)",
        percentile(firsts, 50.0),
        percentile(firsts, 95.0),
        percentile(fulls, 50.0),
        percentile(fulls, 95.0),
        stats["longestTaskMs"].as_f64().unwrap_or(0.0),
        firsts.len()
    );
    eprintln!(
        "first pictures (ms): {firsts:.0?}; full pictures (ms): {fulls:.0?}; edits answered \
         (ms): {:.0?}; first tiles arrived (ms): {:.0?}",
        list("answerMs"),
        list("firstArrivalMs")
    );
    assert_eq!(stats["longTasksObserved"], true, "{stats}");

    // A sphere's radius typed into its field.
    type_into(&mut page, "objects[0].radius", "1.4");
    generation = wait_final(&mut page, generation, "the picture after a radius edit");
    assert_eq!(page.eval("scene.objects[0].radius").as_f64(), Some(1.4));
    let now = page.eval(CANVAS_HASH).as_u64().unwrap();
    assert_ne!(now, shown, "the radius edit did not change the picture");
    shown = now;

    // An invalid one: the loader's error under the field, the last picture kept.
    type_into(&mut page, "objects[0].radius", "-2");
    let error = poll("the radius error", TIMEOUT, || {
        let text = page.eval(
            "(() => { const f = document.querySelector('.field[data-path=\"objects[0].radius\"]'); \
             const e = f && f.querySelector('.error'); \
             return e && !e.hidden && f.classList.contains('invalid') ? e.textContent : null; })()",
        );
        text.as_str().map(str::to_owned)
    });
    assert_eq!(error, "objects[0].radius: must be > 0, got -2");
    std::thread::sleep(Duration::from_millis(1500));
    assert_eq!(page.eval("generation").as_u64(), Some(generation));
    assert_eq!(page.eval(CANVAS_HASH).as_u64().unwrap(), shown);

    type_into(&mut page, "objects[0].radius", "1.25");
    wait_final(
        &mut page,
        generation,
        "the picture after the radius is mended",
    );
    let studio_final = page.eval(CANVAS_HASH).as_u64().unwrap();

    // Saved, then rendered by `tessera render`: the studio's very pixels.
    assert!(page.click("#save"), "no Save button");
    let saved = dir.join("scene.json");
    poll("the saved scene", TIMEOUT, || {
        let text = std::fs::read_to_string(&saved).ok()?;
        serde_json::from_str::<serde_json::Value>(&text).ok()
    });
    ok(
        tessera(dir, &["render", "scene.json", "-o", "render.png"], TIMEOUT),
        "tessera render of the saved scene",
    );
    let rendered = image::open(dir.join("render.png")).unwrap().to_rgb8();
    assert_eq!(rendered.dimensions(), (960, 540));
    assert_eq!(
        u64::from(fnv(rendered.as_raw())),
        studio_final,
        "the studio's final picture differs from `tessera render` of the saved scene"
    );

    // "Render": a stored job, listed, whose image is `tessera render`'s, byte for byte.
    assert!(page.click("#submit"), "no Render button");
    let job = poll("the submitted job", TIMEOUT, || {
        let text = page.eval("document.getElementById('submitted').textContent");
        let text = text.as_str()?.strip_prefix("job ")?;
        text.split(':').next()?.trim().parse::<u64>().ok()
    });
    wait_done(dir, &coordinator, job, TIMEOUT);
    let listed = ok(
        tessera(dir, &["list", "--coordinator", &coordinator], TIMEOUT),
        "tessera list",
    );
    assert!(
        listed
            .stdout
            .lines()
            .any(|l| l.starts_with(&format!("{job} ")) && l.contains("studio")),
        "{}",
        listed.stdout
    );
    let (code, png) = http_get(&http, &format!("/jobs/{job}/image.png")).unwrap();
    assert_eq!(code, 200);
    std::fs::write(dir.join("job.png"), png).unwrap();
    assert_same_png(
        &dir.join("job.png"),
        &dir.join("render.png"),
        "the studio's job",
    );
    // The views' passes are not jobs anyone sees.
    assert_eq!(listed.stdout.lines().count(), 2, "{}", listed.stdout);

    // Ctrl-C: the farm stops, its files go, the command exits 0.
    drop(page);
    studio.signal("INT");
    let status = studio
        .wait_exit(TIMEOUT)
        .expect("tessera studio did not stop on SIGINT");
    assert!(status.success(), "{status}: {}", studio.log_text());
    let started = Instant::now();
    poll("the local farm gone", TIMEOUT, || {
        let up = std::net::TcpStream::connect(&coordinator).is_ok();
        (!up).then_some(started.elapsed())
    });
}

#[test]
fn a_studio_of_an_invalid_scene_or_address_stops_before_starting_anything() {
    let _turn = shared();
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    std::fs::write(
        dir.join("bad.json"),
        SCENE.replace("\"radius\": 1,", "\"radius\": -1,"),
    )
    .unwrap();
    let run = tessera(dir, &["studio", "bad.json"], TIMEOUT);
    assert!(!run.status.success());
    assert_eq!(
        run.stderr.trim(),
        "error: bad.json: objects[0].radius: must be > 0, got -1"
    );
    assert!(run.stdout.is_empty(), "{}", run.stdout);
    let run = tessera(dir, &["studio", "--http", "0.0.0.0:0"], TIMEOUT);
    assert!(!run.status.success());
    assert!(run.stderr.contains("loopback only"), "{}", run.stderr);
    // A coordinator's --studio-scene is checked at start like any scene.
    let run = tessera(
        dir,
        &[
            "coordinator",
            "--listen",
            "127.0.0.1:0",
            "--data",
            "data",
            "--studio-scene",
            "bad.json",
        ],
        TIMEOUT,
    );
    assert!(!run.status.success());
    assert!(
        run.stderr
            .contains("bad.json: objects[0].radius: must be > 0, got -1"),
        "{}",
        run.stderr
    );
}
