//! The studio in a real headless browser (Chromium, driven over the DevTools protocol)
//! on the farm `tessera studio` starts: the page opens the given scene; dragging the
//! camera with the mouse changes the picture; a sphere's radius typed into its field
//! changes it too; an invalid value shows the loader's error under the field while the
//! last good picture stays; the saved scene, named after the file the studio opened,
//! rendered by `tessera render`, gives the very pixels of the studio's final picture;
//! "Render" submits a stored job whose image is byte-identical to `tessera render`'s
//! and which `tessera list` shows. The latencies of camera drags (docs/performance.md)
//! are measured and printed, never asserted: the machine is shared.
//!
//! A coordinator's `--studio-scene` page labels every field by its key in the scene's
//! JSON, keeps each color on one line, and saves under the scene file's name or the
//! one typed.
//!
//! A scene with meshes opens with its files, a mesh is added from a file the page
//! uploads and moved, and Save's archive renders with `tessera render` to the studio's
//! very pixels; bad uploads and archives are refused in one line.
//!
//! Then, without a browser, the event stream through a 20 Mbit/s link
//! ([`ThrottleRelay`]) while the camera orbits ten edits a second: the reader decodes
//! every tile as the page does, is never dropped, and has the last edit's final
//! picture, `tessera render`'s very pixels, within a second; a reader that stops
//! reading is dropped meanwhile.
//!
//! The browser test needs Chromium: see `support/browser.rs`
//! (`TESSERA_REQUIRE_BROWSER=1` in CI).

use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpStream;
use std::path::Path;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use crate::support::browser::{base64, browser_or_skip, DevTools};
use crate::support::throttle_relay::ThrottleRelay;
use crate::support::{
    assert_same_png, entries, exclusive, http_get, http_post, json_error, ok, one_error_line, poll,
    shared, spawn_tessera, start_coordinator_with_http, tessera, wait_done, write_shapes_scene,
    Daemon, LOADER_REFUSAL,
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
    // Saved files go apart from start.json, which a download of the same name would
    // not replace.
    let downloads = dir.join("downloads");
    std::fs::create_dir(&downloads).unwrap();
    page.call(
        "Browser.setDownloadBehavior",
        serde_json::json!({ "behavior": "allow", "downloadPath": downloads.to_str().unwrap() }),
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
    // As docs/studio.md shows it (TESSERA_SCREENSHOT_DIR keeps a copy).
    page.set_viewport(1440, 717);
    page.screenshot(&dir.join("studio.png"));

    // Saved (under the name of the file it was opened with), then rendered by `tessera
    // render`: the studio's very pixels.
    assert!(page.click("#save"), "no Save button");
    let saved = downloads.join("start.json");
    poll("the saved scene", TIMEOUT, || {
        let text = std::fs::read_to_string(&saved).ok()?;
        serde_json::from_str::<serde_json::Value>(&text).ok()
    });
    ok(
        tessera(
            dir,
            &["render", "downloads/start.json", "-o", "render.png"],
            TIMEOUT,
        ),
        "tessera render of the saved scene",
    );
    let rendered = crate::support::decode_rgb8(&dir.join("render.png"));
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

/// What is wrong with the studio's sidebar as a user reads it, as a list (empty when
/// nothing is): every field is labelled by its key in the scene's JSON (`center`,
/// `color`, `look_at`, `max_depth`...), no label says "centre" or "colour", and each
/// color's picker and three numbers lie on one line inside the sidebar.
const SIDEBAR_PROBLEMS: &str = r##"(() => {
  const out = [];
  const fields = [...document.querySelectorAll("#side .field")];
  if (fields.length < 10) return ["only " + fields.length + " fields"];
  for (const f of fields) {
    const label = f.querySelector("label").textContent;
    const key = f.dataset.path.slice(f.dataset.path.lastIndexOf(".") + 1);
    const color = f.querySelector("input[type=color]");
    if (/centre|colour/.test(label)) out.push(f.dataset.path + ": labelled " + label);
    if (["position", "look_at", "aa", "max_depth", "center", "radius", "normal", "distance"].includes(key) || color) {
      if (label !== key) out.push(f.dataset.path + ": labelled " + JSON.stringify(label) + ", its key is " + key);
    }
    if (color) {
      const inputs = [...f.querySelectorAll("input")];
      const tops = inputs.map(i => Math.round(i.getBoundingClientRect().top));
      if (inputs.length !== 4 || new Set(tops).size !== 1) out.push(f.dataset.path + ": inputs at tops " + tops);
      const right = document.getElementById("side").getBoundingClientRect().right;
      for (const i of inputs) if (i.getBoundingClientRect().right > right) out.push(f.dataset.path + ": an input past the sidebar");
    }
  }
  return out;
})()"##;

#[test]
fn the_studio_labels_fields_by_their_keys_and_saves_under_the_scene_file_name() {
    let _turn = shared();
    let Some(chromium) = browser_or_skip() else {
        return;
    };
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    std::fs::write(dir.join("my-room.json"), SCENE).unwrap();
    let (_coordinator, _addr, http) =
        start_coordinator_with_http(dir, &["--studio-scene", "my-room.json"]);
    let mut page = DevTools::open(
        &chromium,
        &dir.join("profile"),
        &format!("http://{http}/studio"),
        &dir.join("chromium.log"),
    );
    page.set_viewport(1400, 900);
    let downloads = dir.join("downloads");
    std::fs::create_dir(&downloads).unwrap();
    page.call(
        "Browser.setDownloadBehavior",
        serde_json::json!({ "behavior": "allow", "downloadPath": downloads.to_str().unwrap() }),
    );
    poll("the scene's fields", TIMEOUT, || {
        (page.eval("document.querySelectorAll('#side .field').length") != 0).then_some(())
    });
    let problems = page.eval(SIDEBAR_PROBLEMS);
    assert_eq!(problems, serde_json::json!([]), "{problems:#}");

    // Saved as the file the coordinator opened, the page's scene as it is.
    let scene: serde_json::Value =
        serde_json::from_str(page.eval("JSON.stringify(scene)").as_str().unwrap()).unwrap();
    let saved = |name: &str| {
        let path = downloads.join(name);
        poll(&format!("{name} saved"), TIMEOUT, || {
            let text = std::fs::read_to_string(&path).ok()?;
            serde_json::from_str::<serde_json::Value>(&text).ok()
        })
    };
    assert!(page.click("#save"), "no Save button");
    assert_eq!(saved("my-room.json"), scene);
    // Or as the user names it.
    let focused = page.eval(
        "(() => { const e = document.getElementById('save-name'); e.focus(); e.select(); return true; })()",
    );
    assert_eq!(focused, true);
    page.call("Input.insertText", serde_json::json!({ "text": "kitchen" }));
    assert!(page.click("#save"), "no Save button");
    assert_eq!(saved("kitchen.json"), scene);
    assert_eq!(entries(&downloads), ["kitchen.json", "my-room.json"]);
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

/// A scene with a mesh under `models/`, a box, a triangle, a sphere and the floor:
/// small, so that its final pictures come quickly on one worker.
const MESH_SCENE: &str = r#"{
  "camera": { "position": "0 1.5 -5", "look_at": "0 0 0" },
  "image": { "width": 240, "height": 160, "aa": 1 },
  "lights": [ { "position": "-7 10 -10", "color": "1 1 1" } ],
  "objects": [
    { "type": "mesh", "file": "models/cube.obj", "color": "0.5 1 0.5 0.3",
      "transform": { "scale": 0.7, "rotate": "0 30 0", "translate": "0 -0.3 0" } },
    { "type": "box", "min": "1 -1 1", "max": "2.5 -0.4 2", "color": "0.9 0.8 0.2 0" },
    { "type": "triangle", "vertices": ["-2.5 -1 0", "-1.5 -1 0", "-2 0.5 0"], "color": "0.9 0.3 0.3 0" },
    { "type": "sphere", "center": "2 0.5 0", "radius": 0.5, "color": "0.5 0.5 0.5 0.6" },
    { "type": "plan", "normal": "0 1 0", "distance": -1, "color": "0.5 0.25 0.2 2" }
  ]
}"#;

/// A pyramid of 4 triangles on a square base, as an ASCII PLY: the mesh the page adds.
const PYRAMID_PLY: &str = "ply\nformat ascii 1.0\nelement vertex 5\nproperty float x\n\
    property float y\nproperty float z\nelement face 5\nproperty list uchar int vertex_indices\n\
    end_header\n-1 0 -1\n1 0 -1\n1 0 1\n-1 0 1\n0 1.5 0\n4 3 2 1 0\n3 0 1 4\n3 1 2 4\n3 2 3 4\n\
    3 3 0 4\n";

/// `DIR/scene.json` ([`MESH_SCENE`]) with its mesh in `DIR/models/cube.obj`.
fn write_studio_mesh_scene(dir: &Path) {
    std::fs::create_dir_all(dir.join("models")).unwrap();
    std::fs::write(dir.join("models/cube.obj"), crate::support::CUBE_OBJ).unwrap();
    std::fs::write(dir.join("scene.json"), MESH_SCENE).unwrap();
}

/// Sets the file input `selector` of the page to `path`, as a user picking it does
/// (the page gets its `change` event).
fn pick_file(page: &mut DevTools, selector: &str, path: &Path) {
    let document = page.call("DOM.getDocument", serde_json::json!({}));
    let node = page.call(
        "DOM.querySelector",
        serde_json::json!({ "nodeId": document["root"]["nodeId"], "selector": selector }),
    );
    assert_ne!(node["nodeId"], 0, "no {selector} on the page");
    page.call(
        "DOM.setFileInputFiles",
        serde_json::json!({ "files": [path.to_str().unwrap()], "nodeId": node["nodeId"] }),
    );
}

/// The text of the error shown under the field `path` (empty when there is none).
fn field_error(page: &mut DevTools, path: &str) -> String {
    page.eval(&format!(
        "(() => {{ const f = document.querySelector('.field[data-path=\"{path}\"]'); \
         return f ? f.querySelector('.error').textContent : 'no field {path}'; }})()"
    ))
    .as_str()
    .unwrap_or_default()
    .to_owned()
}

/// `tessera render ARGS` in `dir` to `out`: the picture's [`fnv`] sum.
fn rendered_sum(dir: &Path, scene: &str, out: &str) -> u64 {
    ok(
        tessera(dir, &["render", scene, "-o", out], TIMEOUT),
        &format!("tessera render {scene}"),
    );
    u64::from(fnv(crate::support::decode_rgb8(&dir.join(out)).as_raw()))
}

/// A scene with meshes in the studio: opened with its mesh file (read beside it and put
/// in the coordinator's store), its picture `tessera render`'s; a mesh added from a file
/// the page uploads, moved, rotated and scaled (an invalid scale shows the loader's
/// error under its field), the picture following; Save downloads one archive of the
/// scene and its files, which `tessera render` renders to the studio's very pixels.
#[test]
fn the_studio_edits_a_mesh_scene_adds_a_mesh_and_saves_an_archive_tessera_render_gives() {
    let _turn = shared();
    let Some(chromium) = browser_or_skip() else {
        return;
    };
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    write_studio_mesh_scene(dir);
    std::fs::write(dir.join("pyramid.ply"), PYRAMID_PLY).unwrap();
    let _studio: Daemon = spawn_tessera(
        dir,
        &[
            "studio",
            "scene.json",
            "--workers",
            "1",
            "--threads-per-worker",
            "1",
        ],
        "studio.log",
    );
    let url = printed(dir, "studio on ");
    let mut page = DevTools::open(
        &chromium,
        &dir.join("profile"),
        &url,
        &dir.join("chromium.log"),
    );
    page.set_viewport(1400, 900);
    let downloads = dir.join("downloads");
    std::fs::create_dir(&downloads).unwrap();
    page.call(
        "Browser.setDownloadBehavior",
        serde_json::json!({ "behavior": "allow", "downloadPath": downloads.to_str().unwrap() }),
    );

    // Opened with its mesh, listed with the box and the triangle: `tessera render`'s
    // picture.
    let generation = wait_final(&mut page, 0, "the mesh scene's first final picture");
    let titles = page.eval(
        "[...document.querySelectorAll('#objects .entry header .grow')].map(e => e.textContent)",
    );
    assert_eq!(
        titles,
        serde_json::json!([
            "mesh 1: models/cube.obj",
            "box 2",
            "triangle 3",
            "sphere 4",
            "plane 5"
        ])
    );
    let opened = page.eval(CANVAS_HASH).as_u64().unwrap();
    assert_eq!(
        opened,
        rendered_sum(dir, "scene.json", "opened.png"),
        "the studio's picture of the opened mesh scene differs from `tessera render`'s"
    );

    // A mesh added from a file the user picks: uploaded, listed, rendered.
    pick_file(&mut page, "#add-mesh-file", &dir.join("pyramid.ply"));
    let generation = wait_final(&mut page, generation, "the picture with the added mesh");
    let added = page.eval("JSON.stringify(scene.objects[5])");
    let added: serde_json::Value = serde_json::from_str(added.as_str().unwrap()).unwrap();
    assert_eq!(added["type"], "mesh");
    assert_eq!(added["file"], "meshes/pyramid.ply");
    assert_ne!(page.eval(CANVAS_HASH).as_u64().unwrap(), opened);

    // Moved, rotated and scaled; a scale of 0 is the loader's error under its field.
    let scale = "objects[5].transform.scale";
    type_into(&mut page, scale, "0");
    let error = poll("the scale's error", TIMEOUT, || {
        let e = field_error(&mut page, scale);
        (!e.is_empty()).then_some(e)
    });
    assert!(
        error.starts_with("objects[5].transform: scale must have no zero component"),
        "{error}"
    );
    type_into(&mut page, scale, "0.6");
    type_into(&mut page, "objects[5].transform.translate.x", "-0.8");
    type_into(&mut page, "objects[5].transform.translate.z", "-1");
    type_into(&mut page, "objects[5].transform.rotate.y", "45");
    wait_final(&mut page, generation, "the picture of the moved mesh");
    assert_eq!(field_error(&mut page, scale), "");
    let transform = page.eval("JSON.stringify(scene.objects[5].transform)");
    let transform: serde_json::Value = serde_json::from_str(transform.as_str().unwrap()).unwrap();
    assert_eq!(
        transform,
        serde_json::json!({ "translate": [-0.8, 0, -1], "rotate": [0, 45, 0], "scale": 0.6 })
    );
    let studio_final = page.eval(CANVAS_HASH).as_u64().unwrap();

    // Saved as one archive: the scene and both mesh files, which `tessera render`
    // renders to the studio's very pixels.
    assert!(page.click("#save"), "no Save button");
    let archive = downloads.join("scene.tar");
    poll("the saved archive", TIMEOUT, || {
        (std::fs::metadata(&archive).ok()?.len() > 0).then_some(())
    });
    let listed = std::process::Command::new("tar")
        .arg("tf")
        .arg(&archive)
        .output()
        .expect("tar runs");
    assert_eq!(
        String::from_utf8_lossy(&listed.stdout),
        "scene.json\nmeshes/pyramid.ply\nmodels/cube.obj\n"
    );
    assert_eq!(
        rendered_sum(dir, "downloads/scene.tar", "saved.png"),
        studio_final,
        "the studio's final picture differs from `tessera render` of the saved archive"
    );
}

/// A tar of `members` written byte by byte, as a hostile tool could: names the
/// coordinator's own archives never hold.
fn hostile_tar(members: &[(&str, &[u8])]) -> Vec<u8> {
    let mut out = Vec::new();
    for (name, bytes) in members {
        let mut header = [0u8; 512];
        header[..name.len()].copy_from_slice(name.as_bytes());
        header[100..107].copy_from_slice(b"0000644");
        header[124..135].copy_from_slice(format!("{:011o}", bytes.len()).as_bytes());
        header[136..147].copy_from_slice(b"00000000000");
        header[156] = b'0';
        header[148..156].copy_from_slice(b"        ");
        let sum: u32 = header.iter().map(|&b| u32::from(b)).sum();
        header[148..155].copy_from_slice(format!("{sum:06o}\0").as_bytes());
        out.extend_from_slice(&header);
        out.extend_from_slice(bytes);
        out.resize(out.len().div_ceil(512) * 512, 0);
    }
    out.resize(out.len() + 1024, 0);
    out
}

/// What a studio refuses, each in one line: a coordinator's `--studio-scene` with
/// meshes gives the page its files, by content; an edit naming a mesh without them is
/// the loader's refusal, and triangles and boxes need none; an upload too large for
/// the store, not a mesh, with a hash that is not its bytes', or not sent as bytes; and
/// `tessera render` of an archive with a member outside it, or without a mesh's file.
#[test]
fn a_studio_refuses_bad_uploads_and_tessera_render_bad_archives_in_one_line() {
    let _turn = shared();
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    write_studio_mesh_scene(dir);
    let (_coordinator, _addr, http) = start_coordinator_with_http(
        dir,
        &["--studio-scene", "scene.json", "--max-file-bytes", "4096"],
    );
    let (code, body) = http_get(&http, "/api/studio/scene").unwrap();
    assert_eq!(code, 200);
    let opened: serde_json::Value = serde_json::from_slice(&body).unwrap();
    assert_eq!(opened["file"], "scene.json");
    let cube = crate::support::CUBE_OBJ.as_bytes();
    assert_eq!(
        opened["assets"],
        serde_json::json!([{ "name": "models/cube.obj",
            "sha256": assets::AssetId::of(cube).hex(), "size": cube.len() }])
    );

    // Edits: without the scene's files, the loader's refusal; with them, a picture;
    // triangles and boxes need none.
    let json = ("Content-Type", "application/json");
    let (code, body) = http_post(&http, "/api/studio/open", &[json], "{}");
    assert_eq!(code, 200, "{body}");
    let answer: serde_json::Value = serde_json::from_str(&body).unwrap();
    let session = answer["session"].as_str().unwrap().to_owned();
    let scene = opened["scene"].to_string();
    let edit = |assets: &str| {
        http_post(
            &http,
            "/api/studio/view",
            &[json],
            &format!(r#"{{"session": "{session}", "scene": {scene}, "assets": {assets}}}"#),
        )
    };
    let (code, body) = edit("[]");
    assert_eq!(code, 422, "{body}");
    assert_eq!(
        json_error(body.as_bytes()),
        LOADER_REFUSAL.replace("objects[1]", "objects[0]")
    );
    let (code, body) = edit(&opened["assets"].to_string());
    assert_eq!(code, 200, "{body}");
    let shapes = std::fs::read_to_string(write_shapes_scene(dir)).unwrap();
    let (code, body) = http_post(
        &http,
        "/api/studio/view",
        &[json],
        &format!(r#"{{"session": "{session}", "scene": {shapes}}}"#),
    );
    assert_eq!(code, 200, "{body}");

    // Uploads: bytes only, at most the store's limit per file, a mesh, its own hash.
    let bytes = ("Content-Type", "application/octet-stream");
    let upload = |name: &str, headers: &[(&str, &str)], body: &str| {
        let (code, answer) = http_post(
            &http,
            &format!("/api/studio/files?name={name}"),
            headers,
            body,
        );
        (code, json_error(answer.as_bytes()))
    };
    let tri = "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n";
    let (code, _) = upload("meshes/tri.obj", &[json], tri);
    assert_eq!(code, 415);
    let large = format!("# {}\n{tri}", "x".repeat(5000));
    assert_eq!(
        upload("meshes/big.obj", &[bytes], &large),
        (
            413,
            format!(
                "meshes/big.obj: {} bytes, more than the 4096 a file may have on this farm",
                large.len()
            )
        )
    );
    let (code, error) = upload("meshes/t.obj", &[bytes], "v 0 0 0\nf 1 2 9\n");
    assert_eq!(code, 422, "{error}");
    assert!(
        error.starts_with("meshes/t.obj") && !error.contains('\n'),
        "{error}"
    );
    assert_eq!(
        upload("notes.txt", &[bytes], tri),
        (
            422,
            "notes.txt: not a mesh file: the studio reads .obj, .ply, .stl, .glb and .gltf"
                .to_owned()
        )
    );
    let (code, error) = upload(&format!("t.obj&sha256={}", "0".repeat(64)), &[bytes], tri);
    assert_eq!(code, 400, "{error}");
    assert!(error.contains("nothing stored"), "{error}");
    let (code, error) = upload("../t.obj", &[bytes], tri);
    assert_eq!(code, 422, "{error}");
    let (code, answer) = http_post(
        &http,
        "/api/studio/files?name=meshes/tri.obj",
        &[bytes],
        tri,
    );
    assert_eq!(code, 200, "{answer}");
    let stored: serde_json::Value = serde_json::from_str(&answer).unwrap();
    assert_eq!(stored["sha256"], assets::AssetId::of(tri.as_bytes()).hex());

    // Archives: a member outside the archive, and a mesh's file missing, are refused.
    let text = MESH_SCENE.as_bytes();
    std::fs::write(
        dir.join("climbing.tar"),
        hostile_tar(&[("s.json", text), ("models/cube.obj", cube), ("../x", b"x")]),
    )
    .unwrap();
    let run = tessera(dir, &["render", "climbing.tar"], TIMEOUT);
    assert_eq!(
        one_error_line(&run, "tessera render climbing.tar"),
        "error: climbing.tar: member 2 (\"../x\"): a name climbing out with `..`: a member \
         must be inside the archive"
    );
    std::fs::write(dir.join("missing.tar"), hostile_tar(&[("s.json", text)])).unwrap();
    let run = tessera(dir, &["render", "missing.tar"], TIMEOUT);
    assert_eq!(
        one_error_line(&run, "tessera render missing.tar"),
        "error: missing.tar: objects[0].file: \"models/cube.obj\" is not in the archive"
    );
    assert!(!dir.join("x").exists() && !dir.join("climbing.png").exists());
}

/// The link of the throughput test: 20 Mbit/s each way.
const LINK_BYTES_PER_SECOND: u64 = 2_500_000;
/// The orbit: ten camera edits a second for 30 s, once around the scene.
const ORBIT_EDITS: u32 = 300;
const ORBIT_TICK: Duration = Duration::from_millis(100);
/// From the last edit sent to its final picture decoded at the far end of the link, on
/// a quiet farm.
const FINAL_WITHIN: Duration = Duration::from_secs(1);

/// The seed scene with the camera `n` steps of [`ORBIT_EDITS`] around the scene.
fn orbit_scene(n: u32) -> String {
    let angle = std::f64::consts::TAU * f64::from(n) / f64::from(ORBIT_EDITS);
    let (x, z) = (5.0 * angle.sin(), -5.0 * angle.cos());
    SCENE.replace(
        r#""position": "3 1.5 -4""#,
        &format!(r#""position": "{x:.6} 1.5 {z:.6}""#),
    )
}

/// What a reader of the event stream has seen, painted as the page paints it.
#[derive(Default)]
struct Seen {
    /// The picture, RGB8 of the frame, and the generation on it.
    canvas: Vec<u8>,
    frame: (u32, u32),
    generation: u64,
    /// The newest final picture: its generation, when it was complete, its pixels.
    last_final: Option<(u64, Instant, Vec<u8>)>,
    tiles: u64,
    /// When the stream ended (the coordinator dropped the reader), and why.
    ended: Option<(Instant, String)>,
}

impl Seen {
    /// A tile event: its PNG decoded and painted unless it is of an older generation.
    fn tile(&mut self, event: &serde_json::Value) {
        let field = |k: &str| {
            event[k]
                .as_u64()
                .unwrap_or_else(|| panic!("tile {k}: {event}")) as u32
        };
        let generation = u64::from(field("generation"));
        if generation < self.generation {
            return;
        }
        self.generation = generation;
        self.tiles += 1;
        let (w, h, scale) = (field("width"), field("height"), field("scale"));
        let frame = (field("frame_width"), field("frame_height"));
        if self.frame != frame {
            self.frame = frame;
            self.canvas = vec![0; frame.0 as usize * frame.1 as usize * 3];
        }
        let png = base64(event["png"].as_str().expect("a tile's png"));
        let pixels = crate::support::decode_png(&png).expect("a tile's PNG");
        assert_eq!(pixels.dimensions(), (w, h), "{event}");
        let (x0, y0) = (field("x") * scale, field("y") * scale);
        for (px, py, rgb) in pixels.enumerate_pixels() {
            for dy in 0..scale {
                for dx in 0..scale {
                    let (x, y) = (x0 + px * scale + dx, y0 + py * scale + dy);
                    if x < frame.0 && y < frame.1 {
                        let at = (y as usize * frame.0 as usize + x as usize) * 3;
                        self.canvas[at..at + 3].copy_from_slice(&rgb);
                    }
                }
            }
        }
    }

    /// A pass event: the final picture of the generation on the canvas is complete.
    fn pass(&mut self, event: &serde_json::Value) {
        let generation = event["generation"].as_u64().expect("a pass's generation");
        if event["last"] == true && generation == self.generation {
            self.last_final = Some((generation, Instant::now(), self.canvas.clone()));
        }
    }
}

/// Follows the event stream of `session` at `addr` (HTTP/1.0: the body ends when the
/// coordinator ends the stream) into `seen` until it ends.
fn follow(addr: &str, session: &str, seen: &Mutex<Seen>) {
    let mut stream = TcpStream::connect(addr).expect("cannot reach the studio");
    write!(
        stream,
        "GET /api/studio/stream?session={session} HTTP/1.0\r\nHost: {addr}\r\n\r\n"
    )
    .unwrap();
    let mut reader = BufReader::new(stream);
    let mut line = String::new();
    let mut status = None;
    let why = loop {
        line.clear();
        match reader.read_line(&mut line) {
            Ok(0) => break "end of stream".to_owned(),
            Ok(_) => {}
            Err(e) => break e.to_string(),
        }
        if status.is_none() {
            status = Some(line.clone());
            assert!(line.contains(" 200 "), "the stream answered {line}");
        }
        if line == "\r\n" {
            break String::new();
        }
    };
    assert!(why.is_empty(), "the stream's head: {why}");
    let mut name = String::new();
    let why = loop {
        line.clear();
        match reader.read_line(&mut line) {
            Ok(0) => break "end of stream".to_owned(),
            Ok(_) => {}
            Err(e) => break e.to_string(),
        }
        let text = line.trim_end_matches(['\r', '\n']);
        if let Some(value) = text.strip_prefix("event:") {
            name = value.trim().to_owned();
        } else if let Some(data) = text.strip_prefix("data:") {
            let event: serde_json::Value =
                serde_json::from_str(data.trim()).expect("an event's JSON");
            let mut seen = seen.lock().unwrap();
            match name.as_str() {
                "tile" => seen.tile(&event),
                "pass" => seen.pass(&event),
                other => panic!("an event {other:?}: {event}"),
            }
        }
    };
    seen.lock().unwrap().ended = Some((Instant::now(), why));
}

#[test]
fn a_page_behind_a_20_mbit_link_keeps_up_with_a_camera_orbit() {
    let _turn = exclusive();
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    std::fs::write(dir.join("start.json"), SCENE).unwrap();
    let _studio: Daemon = spawn_tessera(
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
    let link = ThrottleRelay::start(&http, LINK_BYTES_PER_SECOND);
    let remote = link.address().to_owned();
    let json = ("Content-Type", "application/json");
    let (code, body) = http_post(&remote, "/api/studio/open", &[json], "{}");
    assert_eq!(code, 200, "{body}");
    let answer: serde_json::Value = serde_json::from_str(&body).unwrap();
    let session = answer["session"].as_str().unwrap().to_owned();

    let seen = Arc::new(Mutex::new(Seen::default()));
    let reader = {
        let (remote, session, seen) = (remote.clone(), session.clone(), Arc::clone(&seen));
        std::thread::spawn(move || follow(&remote, &session, &seen))
    };
    // A second page of the view that stops reading at once, on the farm's own host.
    let mut stopped = TcpStream::connect(&http).unwrap();
    write!(
        stopped,
        "GET /api/studio/stream?session={session} HTTP/1.0\r\nHost: {http}\r\n\r\n"
    )
    .unwrap();

    let edit = |n: u32| {
        let (code, body) = http_post(
            &remote,
            "/api/studio/view",
            &[json],
            &format!(r#"{{"session": "{session}", "scene": {}}}"#, orbit_scene(n)),
        );
        assert_eq!(code, 200, "edit {n}: {body}");
        let answer: serde_json::Value = serde_json::from_str(&body).unwrap();
        answer["generation"].as_u64().unwrap()
    };
    let start = Instant::now();
    let mut last = (0, start);
    for n in 0..ORBIT_EDITS {
        let at = start + ORBIT_TICK * n;
        std::thread::sleep(at.saturating_duration_since(Instant::now()));
        let sent = Instant::now();
        last = (edit(n), sent);
        assert!(
            !reader.is_finished() || seen.lock().unwrap().ended.is_some(),
            "the reader failed at edit {n}"
        );
        if let Some((when, why)) = &seen.lock().unwrap().ended {
            panic!(
                "the reader was dropped {:?} into the orbit, at edit {n}: {why}",
                when.duration_since(start)
            );
        }
    }
    let orbit = start.elapsed();
    let (generation, sent) = last;
    let (final_at, picture) = poll("the last edit's final picture", TIMEOUT, || {
        let seen = seen.lock().unwrap();
        assert!(
            !reader.is_finished() || seen.ended.is_some(),
            "the reader failed"
        );
        if let Some((when, why)) = &seen.ended {
            panic!(
                "the reader was dropped {:?} after the orbit: {why}",
                when.duration_since(start + orbit)
            );
        }
        let (g, at, picture) = seen.last_final.as_ref()?;
        (*g == generation).then(|| (*at, picture.clone()))
    });
    let latency = final_at.duration_since(sent);
    let bytes = link.downstream_bytes();
    let tiles = seen.lock().unwrap().tiles;
    eprintln!(
        "studio stream through a 20 Mbit/s link, 960x540 aa 2, 2 local workers: {ORBIT_EDITS} \
         edits in {:.1} s, {bytes} bytes down ({:.1} kB per edit, {:.2} MB/s), {tiles} tiles \
         painted; the last edit's final picture {:.0} ms after it was sent",
        orbit.as_secs_f64(),
        bytes as f64 / f64::from(ORBIT_EDITS) / 1e3,
        bytes as f64 / orbit.as_secs_f64() / 1e6,
        latency.as_secs_f64() * 1e3
    );
    assert!(
        latency <= FINAL_WITHIN,
        "the last edit's final picture came {latency:?} after it was sent"
    );

    // The picture is `tessera render`'s of the same scene, byte for byte.
    std::fs::write(dir.join("last.json"), orbit_scene(ORBIT_EDITS - 1)).unwrap();
    ok(
        tessera(dir, &["render", "last.json", "-o", "last.png"], TIMEOUT),
        "tessera render of the last edit",
    );
    let rendered = crate::support::decode_rgb8(&dir.join("last.png"));
    assert_eq!(rendered.dimensions(), (960, 540));
    let differing = rendered
        .as_raw()
        .chunks(3)
        .zip(picture.chunks(3))
        .filter(|(a, b)| a != b)
        .count();
    assert_eq!(
        differing, 0,
        "pixels of the streamed final picture that differ from `tessera render`'s"
    );

    // The page that stopped reading was dropped: what the kernel took for it before it
    // stopped, then the end of its stream.
    stopped
        .set_read_timeout(Some(Duration::from_secs(5)))
        .unwrap();
    let mut queued = Vec::new();
    let end = stopped.read_to_end(&mut queued);
    assert!(
        end.is_ok(),
        "a page that stopped reading still has its stream after {} bytes: {end:?}",
        queued.len()
    );
    assert!(
        queued.starts_with(b"HTTP/1.0 200"),
        "{:?}",
        &queued[..queued.len().min(100)]
    );
    eprintln!(
        "the page that stopped reading was dropped, having been sent {} bytes",
        queued.len()
    );
    drop(link);
    reader.join().unwrap();
}
