//! The coordinator's status page in a real headless browser (Chromium): it loads, shows
//! a running job progressing with a live preview, and shows the finished image, the
//! same pixels as `tessera render`'s.
//!
//! Needs Chromium (`chromium`, or the path in `TESSERA_CHROMIUM`). Without it the test
//! says so and passes, unless `TESSERA_REQUIRE_BROWSER=1` (as in CI), where a missing
//! browser fails it.

mod common;

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

use common::{
    free_port, poll, render_reference, scene_path, start_coordinator, start_worker_with, submit,
};

fn chromium() -> Option<PathBuf> {
    if let Some(path) = std::env::var_os("TESSERA_CHROMIUM") {
        return Some(PathBuf::from(path));
    }
    [
        "/usr/bin/chromium",
        "/usr/bin/chromium-browser",
        "/usr/bin/google-chrome",
    ]
    .iter()
    .map(PathBuf::from)
    .find(|p| p.exists())
}

/// The page at `url` after its scripts have run for a moment, as HTML.
fn dump_dom(browser: &Path, profile: &Path, url: &str) -> String {
    let out = Command::new("timeout")
        .arg("60")
        .arg(browser)
        .args([
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-quic",
            "--no-first-run",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--virtual-time-budget=2000",
            "--dump-dom",
        ])
        .arg(format!("--user-data-dir={}", profile.display()))
        .arg(url)
        .output()
        .expect("cannot start the browser");
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
    let Some(browser) = chromium() else {
        assert!(
            std::env::var("TESSERA_REQUIRE_BROWSER").as_deref() != Ok("1"),
            "TESSERA_REQUIRE_BROWSER=1 but no Chromium found (install chromium or set TESSERA_CHROMIUM)"
        );
        eprintln!("skipped: no Chromium on this machine (set TESSERA_CHROMIUM)");
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let profile = dir.path().join("browser-profile");
    let http = format!("127.0.0.1:{}", free_port());
    let (_coordinator, addr) = start_coordinator(
        dir.path(),
        &dir.path().join("data"),
        "127.0.0.1:0",
        &["--http", &http],
        "coordinator.log",
    );
    // A slowed worker, so that the job runs long enough to be watched.
    let _worker = start_worker_with(dir.path(), &addr, "slow", &["--throttle", "150"]);
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
            let s = seen(&dump_dom(&browser, &profile, &page), job)?;
            assert_ne!(s.state, "done", "the job ended before the page saw it run");
            (s.state == "running" && s.done > 0 && s.shown_tiles.is_some()).then_some(s)
        },
    );
    assert!(first.done < first.total);
    assert!(!first.final_picture);
    // Progressing: later, more tiles in and a newer preview.
    let later = poll("the page to show progress", Duration::from_secs(60), || {
        let s = seen(&dump_dom(&browser, &profile, &page), job)?;
        (s.done > first.done && s.shown_tiles > first.shown_tiles).then_some(s)
    });
    assert!(later.done <= later.total);

    // Finished: the stored image, the same pixels as `tessera render`'s.
    let done = poll(
        "the page to show the finished image",
        Duration::from_secs(120),
        || {
            let s = seen(&dump_dom(&browser, &profile, &page), job)?;
            (s.state == "done" && s.final_picture).then_some(s)
        },
    );
    assert_eq!(done.done, done.total);
    let reference = render_reference(dir.path(), &seed, "reference.png", &settings);
    let expected: u64 = image::open(&reference)
        .unwrap()
        .to_rgb8()
        .as_raw()
        .iter()
        .map(|&b| u64::from(b))
        .sum();
    assert_eq!(done.rgb_sum, Some(expected), "the page shows other pixels");
}
