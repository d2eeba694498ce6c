//! The coordinator's status page in a real headless browser (Chromium): it loads, shows
//! a running job progressing with a live preview, and shows the finished image, the
//! same pixels as `tessera render`'s. Its controls, clicked with the mouse through the
//! DevTools protocol, pause, resume and delete jobs and disable and enable workers, as
//! `tessera status` and `tessera workers` then show; it warns when no worker can take
//! tiles, and on a farm with a client secret logs in with a form, over HTTPS with the
//! coordinator's own certificate. With eighteen jobs in a window of 1400 × 900 (and of
//! 1000 px), every control of the running job and its picture are in view, its time
//! left shows, and cancel asks first: declined, nothing is cancelled (the screenshot
//! taken there is README's; `TESSERA_SCREENSHOT_DIR=DIR` keeps a copy). The controls'
//! rules of access (token, content type, origin) are checked over plain HTTP.
//!
//! Needs Chromium (`chromium`, or the path in `TESSERA_CHROMIUM`). Without it the test
//! says so and passes, unless `TESSERA_REQUIRE_BROWSER=1` (as in CI), where a missing
//! browser fails it.

use std::path::Path;
use std::time::Duration;

use crate::support::browser::{browser_or_skip, dump_dom, trust_key, DevTools};
use crate::support::{
    client, free_port, http_get, http_post, http_request, json_error, ok, poll, render_reference,
    scene_path, shared, start_coordinator, start_coordinator_with_http, start_slow_worker,
    status_json, submit, tessera, tiles_done, tiles_total, wait_done,
};

/// The page's DOM, as a browser that loaded it and let it run for 2 s shows it.
fn page_dom(browser: &Path, profile: &Path, url: &str) -> String {
    let out = dump_dom(browser, profile, url, 2000);
    assert!(
        out.status.success(),
        "the browser failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// The attributes of the first element that starts with `prefix` (e.g. `<img id="picture"`).
fn element<'a>(html: &'a str, prefix: &str) -> Option<&'a str> {
    let start = html.find(prefix)?;
    let end = html[start..].find('>')?;
    Some(&html[start..start + end])
}

fn attribute<'a>(element: &'a str, name: &str) -> Option<&'a str> {
    let key = format!(" {name}=\"");
    let start = element.find(&key)? + key.len();
    let end = element[start..].find('"')?;
    Some(&element[start..start + end])
}

/// What the page shows of job `job`: (state, tiles done, tiles total) from its row,
/// and (tiles shown, final, rgb sum) from the picture, if loaded.
struct Seen {
    state: String,
    done: u32,
    total: u32,
    shown_tiles: Option<u32>,
    final_picture: bool,
    rgb_sum: Option<u64>,
}

fn seen(html: &str, job: u64) -> Option<Seen> {
    let row = element(html, &format!("<tr data-job=\"{job}\""))?;
    fn number<T: std::str::FromStr>(e: &str, name: &str) -> Option<T> {
        attribute(e, name).and_then(|v| v.parse().ok())
    }
    let picture = element(html, "<img id=\"picture\"")
        .filter(|img| attribute(img, "data-job") == Some(&job.to_string()));
    Some(Seen {
        state: attribute(row, "data-state")?.to_owned(),
        done: number(row, "data-tiles-done")?,
        total: number(row, "data-tiles-total")?,
        shown_tiles: picture.and_then(|img| number(img, "data-shown-tiles")),
        final_picture: picture.and_then(|img| attribute(img, "data-final")) == Some("true"),
        rgb_sum: picture.and_then(|img| number(img, "data-rgb-sum")),
    })
}

#[test]
fn the_status_page_shows_a_job_progressing_and_its_finished_image() {
    let _turn = shared();
    let Some(browser) = browser_or_skip() else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let profile = dir.path().join("browser-profile");
    let (_coordinator, addr, http) = start_coordinator_with_http(dir.path(), &[]);
    // A slowed worker, so that the job runs long enough to be watched.
    let Some(_worker) = start_slow_worker(
        "the_status_page_shows_a_job_progressing_and_its_finished_image",
        dir.path(),
        &addr,
        "slow",
        1.0 / 150.0,
        &[],
    ) else {
        return;
    };
    let seed = scene_path("seed.json");
    let settings = ["--width", "240", "--height", "160", "--aa", "3"];
    let mut args = vec![seed.as_str(), "--tile", "16"];
    args.extend(settings);
    let job = submit(dir.path(), &addr, &args);
    let page = format!("http://{http}/?job={job}");

    // Running, with a preview of the tiles so far.
    let first = poll(
        "the page to show the job running",
        Duration::from_secs(60),
        || {
            let s = seen(&page_dom(&browser, &profile, &page), job)?;
            assert_ne!(s.state, "done", "the job ended before the page saw it run");
            (s.state == "running" && s.done > 0 && s.shown_tiles.is_some()).then_some(s)
        },
    );
    assert!(first.done < first.total);
    assert!(!first.final_picture);
    // Progressing: later, more tiles in and a newer preview.
    let later = poll("the page to show progress", Duration::from_secs(60), || {
        let s = seen(&page_dom(&browser, &profile, &page), job)?;
        (s.done > first.done && s.shown_tiles > first.shown_tiles).then_some(s)
    });
    assert!(later.done <= later.total);

    // Finished: the stored image, the same pixels as `tessera render`'s.
    let done = poll(
        "the page to show the finished image",
        Duration::from_secs(120),
        || {
            let s = seen(&page_dom(&browser, &profile, &page), job)?;
            (s.state == "done" && s.final_picture).then_some(s)
        },
    );
    assert_eq!(done.done, done.total);
    let reference = render_reference(dir.path(), &seed, "reference.png", &settings);
    let expected: u64 = crate::support::decode_rgb8(&reference)
        .as_raw()
        .iter()
        .map(|&b| u64::from(b))
        .sum();
    assert_eq!(done.rgb_sum, Some(expected), "the page shows other pixels");
}

/// Clicks `selector` until `done` holds: a click can miss when the page lays itself out
/// again between finding the button and pressing it (a row above it added or removed
/// by a refresh), so one click proves nothing until its effect is seen.
fn click_until(page: &mut DevTools, what: &str, selector: &str, mut done: impl FnMut() -> bool) {
    poll(what, Duration::from_secs(30), || {
        if done() {
            return Some(());
        }
        page.click(selector);
        let until = std::time::Instant::now() + Duration::from_millis(1500);
        while std::time::Instant::now() < until {
            if done() {
                return Some(());
            }
            std::thread::sleep(Duration::from_millis(100));
        }
        None
    });
}

/// Clicks job `job`'s `action` button (cancel or delete) until the page asks whether
/// to go on: its "yes" button is there.
fn ask(page: &mut DevTools, action: &str, job: u64) {
    let yes = format!("button[data-action=\"confirm-{action}\"][data-job=\"{job}\"]");
    let shown = format!("document.querySelector({yes:?}) !== null");
    poll(
        &format!("the page to ask before {action} of job {job}"),
        Duration::from_secs(30),
        || {
            if page.eval(&shown) == true {
                return Some(());
            }
            page.click(&format!(
                "button[data-action=\"{action}\"][data-job=\"{job}\"]"
            ));
            std::thread::sleep(Duration::from_millis(300));
            None
        },
    );
}

/// What lies outside a `width` × `height` window of the status page (as a list of
/// problems, empty when all is in view): every control of the running job `job`, once
/// its row is scrolled to the middle of the window as a user would, must be inside it
/// and not covered (what is under its centre is itself); so must the selected job's
/// picture, beside the list; and no job's control may stick out left or right.
fn out_of_view(page: &mut DevTools, job: u64, width: u32, height: u32) -> Vec<String> {
    page.set_viewport(width, height);
    let problems = page.eval(&format!(
        r##"(() => {{
  const row = document.querySelector('tr[data-job="{job}"]');
  if (!row) return ["no row of job {job}"];
  row.scrollIntoView({{ block: "center" }});
  const w = document.documentElement.clientWidth, h = document.documentElement.clientHeight;
  const out = [];
  const at = r => [r.left, r.top, r.right, r.bottom].map(Math.round).join(",");
  const inside = (what, e) => {{
    if (!e) {{ out.push(what + ": missing"); return; }}
    const r = e.getBoundingClientRect();
    if (!(r.width > 0 && r.height > 0 && r.left >= 0 && r.top >= 0 && r.right <= w && r.bottom <= h)) {{
      out.push(what + " at " + at(r) + ", outside " + w + "x" + h);
      return;
    }}
    const hit = document.elementFromPoint(r.left + r.width / 2, r.top + r.height / 2);
    if (!hit || !(hit === e || e.contains(hit))) out.push(what + " covered by " + (hit ? hit.outerHTML.slice(0, 60) : "nothing"));
  }};
  for (const action of ["pause", "cancel", "priority"])
    inside(action + " of job {job}", row.querySelector('button[data-action="' + action + '"]'));
  inside("priority field of job {job}", row.querySelector("input"));
  const picture = document.getElementById("picture");
  if (picture.hidden || picture.dataset.job !== "{job}") out.push("the picture is not job {job}'s");
  inside("the picture", picture);
  for (const e of document.querySelectorAll("#jobs button, #jobs input")) {{
    const r = e.getBoundingClientRect();
    if (r.left < 0 || r.right > w) out.push((e.dataset.action || "input") + " of job " + e.dataset.job + " at " + at(r) + ", outside " + w + "x" + h);
  }}
  return out;
}})()"##
    ));
    problems
        .as_array()
        .expect("a list of problems")
        .iter()
        .map(|p| format!("at {width}x{height}: {}", p.as_str().unwrap_or_default()))
        .collect()
}

#[test]
fn a_busy_farm_fits_at_1400_by_900_with_the_running_job_its_time_left_and_cancel_asked() {
    let _turn = shared();
    let Some(browser) = browser_or_skip() else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let (_coordinator, addr, http) = start_coordinator_with_http(dir.path(), &[]);
    // Eighteen jobs: seventeen small ones waiting behind a large one of a higher
    // priority, which a slowed worker renders part of and is then frozen (SIGSTOP),
    // so that it stays running; the last three small ones cancelled, so that their
    // rows offer retry and delete.
    let seed = scene_path("seed.json");
    let small = [
        seed.as_str(),
        "--width",
        "64",
        "--height",
        "48",
        "--tile",
        "16",
    ];
    let others: Vec<u64> = (0..17).map(|_| submit(dir.path(), &addr, &small)).collect();
    for job in &others[14..] {
        ok(
            client(dir.path(), &addr, &["cancel", &job.to_string()]),
            "cancel",
        );
    }
    let running = submit(
        dir.path(),
        &addr,
        &[
            &seed,
            "--width",
            "640",
            "--height",
            "480",
            "--aa",
            "4",
            "--tile",
            "16",
            "--priority",
            "10",
        ],
    );
    let Some((mut worker, _slow)) = start_slow_worker(
        "a_busy_farm_fits_at_1400_by_900_with_the_running_job_its_time_left_and_cancel_asked",
        dir.path(),
        &addr,
        "slow",
        1.0 / 150.0,
        &[],
    ) else {
        return;
    };
    poll(
        "a third of the large job done",
        Duration::from_secs(120),
        || {
            let status = status_json(dir.path(), &addr, running);
            assert_ne!(status["state"], "done", "{status}");
            (tiles_done(&status) * 3 >= tiles_total(&status)).then_some(())
        },
    );
    worker.signal("STOP");
    let mut page = DevTools::open(
        &browser,
        &dir.path().join("profile"),
        &format!("http://{http}/"),
        &dir.path().join("chromium.log"),
    );
    page.set_viewport(1400, 900);
    // The running job, selected as the newest running one: its picture and the time
    // left, as `tessera status` says it, in its row and in its line beside the list.
    let shown = format!(
        r#"(() => {{
  const row = document.querySelector('tr[data-job="{running}"]');
  const picture = document.getElementById("picture");
  const eta = row && row.querySelector(".eta");
  return row && row.dataset.state === "running" && eta && !picture.hidden && picture.dataset.job === "{running}"
    ? [eta.textContent, document.getElementById("job-info").textContent] : null;
}})()"#
    );
    let texts = poll(
        "the running job, its picture and its time left",
        Duration::from_secs(60),
        || {
            let texts = page.eval(&shown);
            (!texts.is_null()).then_some(texts)
        },
    );
    let (eta, info) = (texts[0].as_str().unwrap(), texts[1].as_str().unwrap());
    let seconds = eta
        .strip_prefix("about ")
        .and_then(|t| t.strip_suffix(" s left"))
        .unwrap_or_else(|| panic!("the time left reads {eta:?}"));
    assert!(
        seconds.parse::<f64>().is_ok_and(|s| s >= 0.0) && seconds.contains('.'),
        "{eta}"
    );
    assert!(info.contains(" s left"), "{info}");
    assert_eq!(
        page.eval("document.querySelectorAll('#jobs tr[data-job]').length"),
        18
    );

    // Every control of the running job, and its picture, in view at 1400 x 900 and in
    // a window of 1000 px.
    let mut problems = out_of_view(&mut page, running, 1400, 900);
    problems.extend(out_of_view(&mut page, running, 1000, 900));
    assert!(problems.is_empty(), "{problems:#?}");

    // As README shows it (TESSERA_SCREENSHOT_DIR keeps a copy).
    page.set_viewport(1400, 900);
    page.eval("window.scrollTo(0, 0)");
    std::thread::sleep(Duration::from_millis(600));
    let shot = dir.path().join("status-page.png");
    page.screenshot(&shot);
    assert_eq!(
        crate::support::decode_png(&std::fs::read(&shot).unwrap())
            .unwrap()
            .dimensions(),
        (1400, 900)
    );

    // Cancel asks; declined, nothing is cancelled and the job goes on.
    let state = || status_json(dir.path(), &addr, running)["state"].clone();
    ask(&mut page, "cancel", running);
    assert_eq!(state(), "running");
    let cancel = format!("button[data-action=\"cancel\"][data-job=\"{running}\"]");
    let back = format!("document.querySelector({cancel:?}) !== null");
    poll("the question declined", Duration::from_secs(30), || {
        if page.eval(&back) == true {
            return Some(());
        }
        page.click(&format!(
            "button[data-action=\"keep\"][data-job=\"{running}\"]"
        ));
        std::thread::sleep(Duration::from_millis(300));
        None
    });
    std::thread::sleep(Duration::from_millis(1000));
    assert_eq!(state(), "running");
    // Confirmed, it is cancelled.
    ask(&mut page, "cancel", running);
    click_until(
        &mut page,
        "the job cancelled once confirmed",
        &format!("button[data-action=\"confirm-cancel\"][data-job=\"{running}\"]"),
        || state() == "cancelled",
    );
}

#[test]
fn the_page_pauses_resumes_and_deletes_a_job_disables_and_drains_a_worker_and_warns() {
    let _turn = shared();
    let Some(browser) = browser_or_skip() else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let (_coordinator, addr, http) = start_coordinator_with_http(dir.path(), &[]);
    // No worker yet: the job waits, and the page says why.
    let seed = scene_path("seed.json");
    let job = submit(
        dir.path(),
        &addr,
        &[
            &seed, "--width", "160", "--height", "120", "--aa", "2", "--tile", "16",
        ],
    );
    let mut page = DevTools::open(
        &browser,
        &dir.path().join("profile"),
        &format!("http://{http}/?job={job}"),
        &dir.path().join("chromium.log"),
    );
    let banner = poll("the no-worker banner", Duration::from_secs(30), || {
        let text = page.eval(
            "(() => { const w = document.getElementById('warning'); return w && !w.hidden ? w.textContent : null; })()",
        );
        text.as_str().map(str::to_owned)
    });
    assert!(banner.contains("no worker is connected"), "{banner}");

    // Paused by a click, as `tessera status` shows.
    click_until(
        &mut page,
        "the job paused by its button",
        &format!("button[data-action=\"pause\"][data-job=\"{job}\"]"),
        || status_json(dir.path(), &addr, job)["state"] == "paused",
    );
    // The page shows it without a reload.
    poll(
        "the page to show the pause",
        Duration::from_secs(20),
        || {
            (page.eval(&format!(
                "document.querySelector('tr[data-job=\"{job}\"]').dataset.state"
            )) == "paused")
                .then_some(())
        },
    );

    // And in the job's events, beside the list.
    poll(
        "the pause among the job's events",
        Duration::from_secs(20),
        || {
            (page.eval("document.querySelectorAll('#events tr[data-event=\"paused\"]').length")
                == 1)
                .then_some(())
        },
    );

    // A worker joins; it gets nothing of the paused job; the banner goes.
    let Some((mut worker, _slow)) = start_slow_worker(
        "the_page_pauses_resumes_and_deletes_a_job_disables_and_drains_a_worker_and_warns",
        dir.path(),
        &addr,
        "clicky",
        1.0 / 50.0,
        &[],
    ) else {
        return;
    };
    poll("the banner to go", Duration::from_secs(30), || {
        (page.eval("document.getElementById('warning').hidden") == true).then_some(())
    });
    std::thread::sleep(Duration::from_millis(1000));
    assert_eq!(status_json(dir.path(), &addr, job)["tiles_done"], 0);

    // Disabled from the page: the worker row says so, and `tessera workers` too.
    let worker_field = |field: &str| {
        let run = client(dir.path(), &addr, &["workers", "--json"]);
        serde_json::from_str::<serde_json::Value>(run.stdout.trim())
            .map(|workers| workers[0][field].clone())
            .unwrap_or_default()
    };
    click_until(
        &mut page,
        "the worker disabled by its button",
        "tr[data-worker=\"clicky\"] button[data-action=\"disable\"]",
        || worker_field("disabled") == true,
    );
    poll(
        "the banner for a disabled farm",
        Duration::from_secs(20),
        || {
            let text = page.eval("document.getElementById('warning').textContent");
            text.as_str()
                .filter(|t| t.contains("disabled, draining, quarantined or unresponsive"))
                .map(drop)
        },
    );

    // Enabled and resumed from the page: the job renders to the end.
    click_until(
        &mut page,
        "the worker enabled by its button",
        "tr[data-worker=\"clicky\"] button[data-action=\"enable\"]",
        || worker_field("disabled") == false,
    );
    click_until(
        &mut page,
        "the job resumed by its button",
        &format!("button[data-action=\"resume\"][data-job=\"{job}\"]"),
        || status_json(dir.path(), &addr, job)["state"] != "paused",
    );
    wait_done(dir.path(), &addr, job, Duration::from_secs(120));
    // An ended job offers delete, which asks first; confirmed, it removes the job.
    ask(&mut page, "delete", job);
    click_until(
        &mut page,
        "the job deleted once confirmed",
        &format!("button[data-action=\"confirm-delete\"][data-job=\"{job}\"]"),
        || {
            let run = client(dir.path(), &addr, &["status", &job.to_string()]);
            !run.status.success() && run.stderr.contains(&format!("no job {job}"))
        },
    );
    // Drained from the page: the worker exits 0 and the page says no worker is left.
    click_until(
        &mut page,
        "the worker drained by its button",
        "tr[data-worker=\"clicky\"] button[data-action=\"drain\"]",
        // Draining, or already gone.
        || worker_field("draining") != false,
    );
    let exit = worker
        .wait_exit(Duration::from_secs(30))
        .expect("the drained worker did not exit");
    assert!(exit.success(), "the drained worker exited with {exit}");
    poll("the worker row to go", Duration::from_secs(20), || {
        (page.eval("document.querySelectorAll('tr[data-worker]').length") == 0).then_some(())
    });
}

#[test]
fn the_page_controls_follow_the_client_secret() {
    let _turn = shared();
    let dir = tempfile::tempdir().unwrap();
    let http = format!("127.0.0.1:{}", free_port());
    std::fs::write(dir.path().join("client.token"), "page-secret\n").unwrap();
    let (_coordinator, addr) = start_coordinator(
        dir.path(),
        &dir.path().join("data"),
        "127.0.0.1:0",
        &["--http", &http, "--client-token-file", "client.token"],
        "coordinator.log",
    );
    let run = tessera(
        dir.path(),
        &[
            "submit",
            &scene_path("seed.json"),
            "--width",
            "32",
            "--height",
            "32",
            "--coordinator",
            &addr,
            "--token-file",
            "client.token",
        ],
        Duration::from_secs(60),
    );
    let job: u64 = ok(run, "submit").stdout.trim().parse().unwrap();
    let pause = format!("/api/jobs/{job}/pause");
    let json = ("Content-Type", "application/json");
    let one_line_error = |body: &str| json_error(body.as_bytes());

    let (code, body) = http_post(&http, &pause, &[json], "{}");
    assert_eq!(code, 401, "{body}");
    assert!(one_line_error(&body).contains("Authorization: Bearer"));
    let (code, body) = http_post(
        &http,
        &pause,
        &[json, ("Authorization", "Bearer nope")],
        "{}",
    );
    assert_eq!(code, 403, "{body}");
    assert_eq!(one_line_error(&body), "wrong client token");
    // A cross-site form, even with the token, is refused.
    let good = ("Authorization", "Bearer page-secret");
    let (code, body) = http_post(
        &http,
        &pause,
        &[("Content-Type", "application/x-www-form-urlencoded"), good],
        "a=1",
    );
    assert_eq!(code, 415, "{body}");
    let (code, body) = http_post(
        &http,
        &pause,
        &[json, good, ("Origin", "http://elsewhere.example")],
        "{}",
    );
    assert_eq!(code, 403, "{body}");
    // Nothing changed so far.
    let status = |dir: &Path| {
        let run = tessera(
            dir,
            &[
                "status",
                &job.to_string(),
                "--json",
                "--coordinator",
                &addr,
                "--token-file",
                "client.token",
            ],
            Duration::from_secs(60),
        );
        let v: serde_json::Value = serde_json::from_str(ok(run, "status").stdout.trim()).unwrap();
        v
    };
    assert_eq!(status(dir.path())["state"], "queued");

    let origin = format!("http://{http}");
    let (code, body) = http_post(&http, &pause, &[json, good, ("Origin", &origin)], "{}");
    assert_eq!(code, 200, "{body}");
    assert_eq!(status(dir.path())["state"], "paused");
    let (code, body) = http_post(
        &http,
        &format!("/api/jobs/{job}/priority"),
        &[json, good],
        r#"{"priority": 7}"#,
    );
    assert_eq!(code, 200, "{body}");
    assert_eq!(status(dir.path())["priority"], 7);
    // The studio's controls follow the same secret: a view is opened, and a scene
    // submitted, only with it.
    let (code, body) = http_post(&http, "/api/studio/open", &[json], "{}");
    assert_eq!(code, 401, "{body}");
    let (code, body) = http_post(
        &http,
        "/api/studio/open",
        &[json, ("Authorization", "Bearer nope")],
        "{}",
    );
    assert_eq!(code, 403, "{body}");
    let (code, body) = http_post(&http, "/api/studio/open", &[json, good], "{}");
    assert_eq!(code, 200, "{body}");
    let session = serde_json::from_str::<serde_json::Value>(&body).unwrap()["session"]
        .as_str()
        .unwrap()
        .to_owned();
    assert_eq!(session.len(), 32, "128 random bits in hex: {session}");
    let scene = std::fs::read_to_string(scene_path("seed.json")).unwrap();
    let edit = format!(r#"{{"session": "{session}", "scene": {scene}}}"#);
    let (code, body) = http_post(&http, "/api/studio/view", &[json], &edit);
    assert_eq!(code, 401, "{body}");
    let (code, body) = http_post(&http, "/api/studio/view", &[json, good], &edit);
    assert_eq!(code, 200, "{body}");
    let job_body = format!(r#"{{"scene": {scene}, "settings": {{"sampler": "wobbly"}}}}"#);
    let (code, body) = http_post(&http, "/api/studio/submit", &[json, good], &job_body);
    assert_eq!(code, 422, "{body}");
    assert_eq!(
        one_line_error(&body),
        "job.sampler: \"wobbly\" is not a sampler: grid, jittered or adaptive"
    );
    let (code, body) = http_post(&http, "/api/studio/submit", &[json], &job_body);
    assert_eq!(code, 401, "{body}");

    // Mistakes are one-line JSON errors.
    let (code, body) = http_post(&http, "/api/jobs/999/pause", &[json, good], "{}");
    assert_eq!(code, 404, "{body}");
    assert_eq!(one_line_error(&body), "no job 999 on this coordinator");
    let refusal: serde_json::Value = serde_json::from_str(&body).unwrap();
    assert_eq!(refusal["kind"], "not_found", "{body}");
    let (code, body) = http_post(&http, "/api/workers/ghost/drain", &[json, good], "{}");
    assert_eq!(code, 404, "{body}");
    assert!(one_line_error(&body).starts_with("no worker \"ghost\""));
    let (code, body) = http_post(
        &http,
        &format!("/api/jobs/{job}/delete"),
        &[json, good],
        "{}",
    );
    assert_eq!(code, 409, "{body}");
    assert!(one_line_error(&body).contains("cancel"), "{body}");
    let (code, body) = http_post(
        &http,
        &format!("/api/jobs/{job}/cancel"),
        &[json, good],
        "{}",
    );
    assert_eq!(code, 200, "{body}");
    assert_eq!(status(dir.path())["state"], "cancelled");
    // Retried from the page: back in the queue, still paused no more.
    let retry = format!("/api/jobs/{job}/retry");
    let (code, body) = http_post(&http, &retry, &[json], "{}");
    assert_eq!(code, 401, "a retry without the token: {body}");
    let (code, body) = http_post(&http, &retry, &[json, good], "{}");
    assert_eq!(code, 200, "{body}");
    assert_eq!(status(dir.path())["state"], "queued");
    let (code, body) = http_post(&http, &retry, &[json, good], "{}");
    assert_eq!(code, 409, "a queued job retried: {body}");
    assert!(
        one_line_error(&body).contains("cannot be retried"),
        "{body}"
    );

    // The job's events, as the page shows them, say who did what, in order.
    // Read with the secret, as every read of a farm that has one.
    let read = |path: &str| {
        let answer = http_request(
            &http,
            path,
            "Authorization: Bearer page-secret\r\n",
            Duration::from_secs(10),
        )
        .expect("the coordinator answers");
        (answer.status, answer.body)
    };
    let (code, _) = http_get(&http, &format!("/api/jobs/{job}/events")).unwrap();
    assert_eq!(code, 401, "the events without the secret");
    let (code, body) = read(&format!("/api/jobs/{job}/events"));
    assert_eq!(code, 200);
    let events: serde_json::Value = serde_json::from_slice(&body).unwrap();
    let kinds: Vec<&str> = events
        .as_array()
        .unwrap()
        .iter()
        .map(|e| e["event"].as_str().unwrap())
        .collect();
    assert_eq!(
        kinds,
        [
            "submitted",
            "paused",
            "priority",
            "cancel",
            "cancelled",
            "retried"
        ],
        "{events}"
    );
    let first = events[0]["seq"].as_u64().unwrap();
    let (_, body) = read(&format!("/api/jobs/{job}/events?after={first}"));
    let rest: serde_json::Value = serde_json::from_slice(&body).unwrap();
    assert_eq!(rest.as_array().unwrap().len(), kinds.len() - 1, "{rest}");
    let (code, _) = read("/api/jobs/999/events");
    assert_eq!(code, 404);
}

#[test]
fn the_page_logs_in_with_a_form_over_tls_and_leaves_no_secret_to_scripts() {
    let _turn = shared();
    let Some(browser) = browser_or_skip() else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let http = format!("127.0.0.1:{}", free_port());
    std::fs::write(dir.path().join("client.token"), "tab-secret\n").unwrap();
    let data = dir.path().join("data");
    let (_coordinator, addr) = start_coordinator(
        dir.path(),
        &data,
        "127.0.0.1:0",
        &[
            "--http",
            &http,
            "--client-token-file",
            "client.token",
            "--tls-auto",
        ],
        "coordinator.log",
    );
    let fingerprint = tessera(
        dir.path(),
        &[
            "coordinator",
            "--data",
            "data",
            "--tls-auto",
            "--print-fingerprint",
        ],
        Duration::from_secs(30),
    )
    .stdout
    .trim()
    .to_owned();
    let with_token = |args: &[&str]| {
        let mut all: Vec<&str> = args.to_vec();
        all.extend(["--coordinator", &addr, "--token-file", "client.token"]);
        all.extend(["--tls-fingerprint", &fingerprint]);
        tessera(dir.path(), &all, Duration::from_secs(60))
    };
    let seed = scene_path("seed.json");
    let run = with_token(&["submit", &seed, "--width", "32", "--height", "32"]);
    let job: u64 = ok(run, "submit").stdout.trim().parse().unwrap();
    let state = || {
        let run = with_token(&["status", &job.to_string(), "--json"]);
        let v: serde_json::Value = serde_json::from_str(ok(run, "status").stdout.trim()).unwrap();
        v["state"].as_str().unwrap_or_default().to_owned()
    };
    // The browser trusts the coordinator's own key, as a user who checked its
    // fingerprint would: the page is served over HTTPS with the protocol's certificate.
    let mut page = DevTools::open_with(
        &browser,
        &dir.path().join("profile"),
        &format!("https://{http}/?job={job}"),
        &dir.path().join("chromium.log"),
        &[trust_key(&data.join("tls").join("key.pem"))],
    );
    // Nothing of the farm without the secret: the form, and no job.
    poll("the login form", Duration::from_secs(30), || {
        (page.eval("document.getElementById('login-form').hidden") == false).then_some(())
    });
    assert_eq!(page.eval("location.protocol"), "https:");
    assert_eq!(page.eval("document.querySelectorAll('#jobs tr').length"), 0);
    // A wrong token is said so, and the form stays.
    page.eval("document.getElementById('token').value = 'not-it'");
    assert!(page.click("#login-form button[type=\"submit\"]"));
    poll("the refusal", Duration::from_secs(20), || {
        (page.eval("document.getElementById('control-note').textContent") == "wrong client token")
            .then_some(())
    });
    assert_eq!(
        page.eval("document.getElementById('login-form').hidden"),
        false
    );
    // The right one: the jobs appear, and the controls work.
    page.eval("document.getElementById('token').value = 'tab-secret'");
    assert!(page.click("#login-form button[type=\"submit\"]"));
    let pause = format!("button[data-action=\"pause\"][data-job=\"{job}\"]");
    poll("the pause button", Duration::from_secs(30), || {
        page.click(&pause).then_some(())
    });
    poll("the job to be paused", Duration::from_secs(20), || {
        (state() == "paused").then_some(())
    });
    // The session is a cookie no script can read, and the secret is kept nowhere.
    assert_eq!(page.eval("document.cookie"), "");
    assert_eq!(page.eval("sessionStorage.length + localStorage.length"), 0);
    assert_eq!(page.eval("document.getElementById('token').value"), "");
    // A reload keeps the session: no form, the job is there.
    let resume = format!("button[data-action=\"resume\"][data-job=\"{job}\"]");
    // The old document is marked, so that only the reloaded one's button is clicked.
    page.eval("window.beforeReload = true; location.reload()");
    poll("the job after a reload", Duration::from_secs(30), || {
        let shown = format!(
            "window.beforeReload === undefined && document.querySelector('{}') !== null",
            resume.replace('\'', "\\'")
        );
        (page.eval(&shown) == true).then_some(())
    });
    assert!(page.click(&resume));
    poll("the job to be resumed", Duration::from_secs(20), || {
        (state() == "queued").then_some(())
    });
    assert_eq!(
        page.eval("document.getElementById('login-form').hidden"),
        true,
        "the page asked again"
    );
}
