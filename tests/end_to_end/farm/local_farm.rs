//! `tessera up`: a farm of its own on this machine, for one job. Its image is byte for
//! byte `tessera render`'s (every example scene without mesh files, 1 to 3 workers,
//! several tile sizes, the antialiasing `render` takes); it leaves no process behind,
//! whether it ends normally or is killed; stopped by a signal it removes its farm and
//! exits as a shell expects; an image it cannot write is refused before it starts
//! anything.

use std::path::Path;
use std::process::{Command, Stdio};
use std::thread;
use std::time::{Duration, Instant};

use tempfile::TempDir;

use crate::support::{
    all_scenes, assert_same_png, ok, path_str, poll, proc_stat, render_reference, scene_path,
    shared, tessera, Daemon, BIN, POLL,
};

/// Longest a job of these tests may take to finish.
const JOB_TIMEOUT: Duration = Duration::from_secs(60);
/// Longest `up` may take to start its farm.
const STARTUP_TIMEOUT: Duration = Duration::from_secs(10);

/// A small frame that still has many tiles, and partial tiles at the right and bottom
/// edges for most tile sizes.
const SMALL: &[&str] = &["--width", "200", "--height", "150"];

/// The process's arguments, empty if it is gone (or a zombie).
fn proc_cmdline(pid: u32) -> Vec<String> {
    std::fs::read(format!("/proc/{pid}/cmdline"))
        .map(|bytes| {
            bytes
                .split(|&b| b == 0)
                .filter(|a| !a.is_empty())
                .map(|a| String::from_utf8_lossy(a).into_owned())
                .collect()
        })
        .unwrap_or_default()
}

/// Every process id in `/proc`.
fn all_pids() -> Vec<u32> {
    std::fs::read_dir("/proc")
        .expect("cannot list /proc")
        .filter_map(|e| e.ok()?.file_name().to_str()?.parse().ok())
        .collect()
}

/// Whether `pid` is a running (not zombie) process whose arguments contain `marker`.
fn running_with(pid: u32, marker: &str) -> bool {
    proc_stat(pid).is_some_and(|s| s[0] != "Z")
        && proc_cmdline(pid).iter().any(|a| a.contains(marker))
}

/// The farm processes `tessera up` (process `up`) has started: its children started
/// with `--exit-on-stdin-eof`.
fn up_children(up: u32) -> Vec<u32> {
    all_pids()
        .into_iter()
        .filter(|&pid| {
            proc_stat(pid).is_some_and(|s| s[1] == up.to_string())
                && proc_cmdline(pid).iter().any(|a| a == "--exit-on-stdin-eof")
        })
        .collect()
}

/// Kills (SIGKILL) the still-running processes among `pids` that carry `marker`:
/// a failed test of `up` must not leave its farm behind either.
struct Reaper {
    pids: Vec<u32>,
    marker: String,
}

impl Drop for Reaper {
    fn drop(&mut self) {
        for &pid in &self.pids {
            if running_with(pid, &self.marker) {
                let _ = Command::new("kill")
                    .args(["-KILL", &pid.to_string()])
                    .status();
            }
        }
    }
}

/// Starts `tessera up ARGS` (output discarded) under a guard.
fn spawn_up(dir: &Path, args: &[&str]) -> Daemon {
    let child = Command::new(BIN)
        .arg("up")
        .args(args)
        .current_dir(dir)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .expect("cannot start tessera up");
    Daemon {
        name: "up".into(),
        child,
        log: None,
    }
}

/// Waits for `up`'s coordinator and `workers` workers to be running; returns their
/// pids and the coordinator's `--data` path.
fn watch_up_farm(up: u32, workers: usize) -> (Vec<u32>, String) {
    let pids = poll("tessera up's farm processes", STARTUP_TIMEOUT, || {
        let pids = up_children(up);
        (pids.len() == workers + 1).then_some(pids)
    });
    let data = pids
        .iter()
        .find_map(|&pid| {
            let args = proc_cmdline(pid);
            let i = args.iter().position(|a| a == "--data")?;
            args.get(i + 1).cloned()
        })
        .expect("one of up's children is a coordinator with --data");
    assert!(data.contains("tessera-up-"), "up's data path: {data}");
    (pids, data)
}

/// Waits up to 3 s for every process of `pids`, and every process of the machine
/// whose arguments contain `marker`, to be gone.
fn assert_all_gone(pids: &[u32], marker: &str, what: &str) {
    let deadline = Instant::now() + Duration::from_secs(3);
    loop {
        let left: Vec<u32> = pids
            .iter()
            .copied()
            .filter(|&pid| running_with(pid, "--exit-on-stdin-eof"))
            .chain(all_pids().into_iter().filter(|&p| running_with(p, marker)))
            .collect();
        if left.is_empty() {
            return;
        }
        assert!(
            Instant::now() < deadline,
            "{what}: processes still running 3 s later: {:?}",
            left.iter()
                .map(|&p| (p, proc_cmdline(p).join(" ")))
                .collect::<Vec<_>>()
        );
        thread::sleep(POLL);
    }
}

/// Every scene, through `tessera up` with 1, 2 and 3 workers and three tile sizes
/// (16, 32 and 48: full, and partial edge tiles), gives `tessera render`'s PNG, scenes
/// that name mesh files included (their files travel with the job). The farms of a
/// scene's three worker counts run at the same time (each `up` has a farm of its own),
/// so that their start-ups and shut-downs overlap.
#[test]
fn up_gives_renders_image_for_every_scene_worker_count_and_tile_size() {
    let _turn = shared();
    let dir = TempDir::new().expect("cannot create a temporary directory");
    let scenes = all_scenes();
    assert!(
        scenes.iter().any(|p| p.ends_with("seed.json")),
        "scenes/ holds the example scenes: {scenes:?}"
    );
    for path in scenes {
        let scene = path_str(&path);
        let stem = path.file_stem().unwrap().to_string_lossy().into_owned();
        let reference = render_reference(dir.path(), scene, &format!("{stem}.png"), SMALL);
        thread::scope(|s| {
            for workers in ["1", "2", "3"] {
                let (dir, stem, reference) = (dir.path(), &stem, &reference);
                s.spawn(move || {
                    for tile in ["16", "32", "48"] {
                        let out = dir.join(format!("{stem}-w{workers}-t{tile}.png"));
                        let up = [
                            "up",
                            scene,
                            "--workers",
                            workers,
                            "--tile",
                            tile,
                            "-o",
                            path_str(&out),
                        ];
                        let args = [&up[..], SMALL].concat();
                        let what = format!("tessera {}", args.join(" "));
                        ok(tessera(dir, &args, JOB_TIMEOUT), &what);
                        assert_same_png(&out, reference, &what);
                    }
                });
            }
        });
    }
}

/// `tessera up` stops its coordinator and workers when it ends, and they stop by
/// themselves when `up` is killed.
#[test]
fn up_leaves_no_process_behind() {
    let _turn = shared();
    let dir = TempDir::new().expect("cannot create a temporary directory");
    let out = dir.path().join("out.png");
    let out = path_str(&out);

    // A normal run (about a second of rendering, to see its farm while it runs).
    let lights = scene_path("lights.json");
    let mut up = spawn_up(
        dir.path(),
        &[
            &lights,
            "--workers",
            "2",
            "-o",
            out,
            "--width",
            "1200",
            "--height",
            "900",
            "--aa",
            "4",
        ],
    );
    let (pids, data) = watch_up_farm(up.pid(), 2);
    let _reaper = Reaper {
        pids: pids.clone(),
        marker: "--exit-on-stdin-eof".into(),
    };
    let exit = poll("tessera up to finish", JOB_TIMEOUT, || {
        up.child.try_wait().expect("cannot wait for up")
    });
    assert!(exit.success(), "tessera up failed: {exit}");
    assert_all_gone(&pids, &data, "after tessera up ended");
    let up_dir = Path::new(&data)
        .parent()
        .expect("data is in up's directory");
    assert!(!up_dir.exists(), "up removed {}", up_dir.display());

    // A run killed mid-render.
    let hall = scene_path("hall-of-mirrors.json");
    let mut up = spawn_up(
        dir.path(),
        &[
            &hall,
            "--workers",
            "2",
            "-o",
            out,
            "--width",
            "1600",
            "--height",
            "1600",
            "--aa",
            "4",
        ],
    );
    let started = Instant::now();
    let (pids, data) = watch_up_farm(up.pid(), 2);
    let _reaper = Reaper {
        pids: pids.clone(),
        marker: "--exit-on-stdin-eof".into(),
    };
    thread::sleep(Duration::from_millis(300).saturating_sub(started.elapsed()));
    assert!(
        up.child.try_wait().expect("cannot wait for up").is_none(),
        "up ended before it could be killed"
    );
    up.child.kill().expect("cannot kill up");
    up.child.wait().expect("cannot reap up");
    assert_all_gone(&pids, &data, "after tessera up was killed");
    // A killed `up` cannot remove its temporary directory; do it for it.
    let up_dir = Path::new(&data)
        .parent()
        .expect("data is in up's directory");
    if up_dir
        .file_name()
        .is_some_and(|n| n.to_string_lossy().starts_with("tessera-up-"))
    {
        let _ = std::fs::remove_dir_all(up_dir);
    }
}

#[test]
fn up_refuses_an_image_it_cannot_write_before_starting_a_farm() {
    let _turn = shared();
    let dir = tempfile::tempdir().unwrap();
    let started = Instant::now();
    let run = tessera(
        dir.path(),
        &[
            "up",
            &scene_path("seed.json"),
            "-o",
            "no-such-dir/out.png",
            "--width",
            "4000",
            "--height",
            "4000",
        ],
        Duration::from_secs(20),
    );
    assert!(!run.status.success());
    let lines: Vec<&str> = run.stderr.lines().collect();
    assert!(
        lines.len() == 1 && lines[0].starts_with("error: cannot write no-such-dir/out.png"),
        "{:?}",
        run.stderr
    );
    assert!(
        started.elapsed() < Duration::from_secs(5),
        "{:?}",
        started.elapsed()
    );
}

#[test]
fn up_stopped_by_a_signal_removes_its_farm_and_exits_with_128_plus_the_signal() {
    let _turn = shared();
    let dir = tempfile::tempdir().unwrap();
    for (signal, code) in [("TERM", 143), ("INT", 130)] {
        // Its own temporary directory, to see what `up` leaves there.
        let tmp = dir.path().join(format!("tmp-{signal}"));
        std::fs::create_dir(&tmp).unwrap();
        let child = Command::new(BIN)
            .args([
                "up",
                &scene_path("seed.json"),
                "--aa",
                "16",
                "-o",
                "out.png",
            ])
            .args(["--width", "1200", "--height", "800"])
            .current_dir(dir.path())
            .env("TMPDIR", &tmp)
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(dir.path().join("up.log")).unwrap())
            .spawn()
            .unwrap();
        let mut up = Daemon {
            name: "up".into(),
            child,
            log: Some(dir.path().join("up.log")),
        };
        // The farm is up once its coordinator has a database.
        let farm = poll("the local farm", Duration::from_secs(30), || {
            std::fs::read_dir(&tmp)
                .ok()?
                .filter_map(Result::ok)
                .map(|e| e.path())
                .find(|p| p.join("data/tessera.db").exists())
        });
        std::thread::sleep(Duration::from_millis(500));
        up.signal(signal);
        let status = up
            .wait_exit(Duration::from_secs(20))
            .unwrap_or_else(|| panic!("up still running 20 s after SIG{signal}"));
        assert_eq!(status.code(), Some(code), "SIG{signal}: {}", up.log_text());
        let log = up.log_text();
        assert!(
            log.trim_end().ends_with(&format!(
                "error: interrupted by SIG{signal}: the local farm is stopped, no image written"
            )),
            "{log}"
        );
        assert!(!farm.exists(), "SIG{signal} left {} behind", farm.display());
        let left: Vec<_> = std::fs::read_dir(&tmp).unwrap().collect();
        assert!(left.is_empty(), "SIG{signal} left {left:?}");
        assert!(!dir.path().join("out.png").exists());
    }
}

#[test]
fn up_takes_the_antialiasing_render_takes() {
    let _turn = shared();
    let dir = tempfile::tempdir().unwrap();
    let args = [
        "up",
        &scene_path("seed.json"),
        "--aa",
        "20",
        "--width",
        "40",
        "--height",
        "30",
        "-o",
        "out.png",
    ];
    let run = ok(
        tessera(dir.path(), &args, Duration::from_secs(120)),
        "up --aa 20",
    );
    assert!(run.stderr.contains("out.png: 40x30"), "{}", run.stderr);
    let reference = render_reference(
        dir.path(),
        &scene_path("seed.json"),
        "reference.png",
        &["--aa", "20", "--width", "40", "--height", "30"],
    );
    assert_same_png(&dir.path().join("out.png"), &reference, "up --aa 20");
}

/// A hand-out larger than one call's bound (256 tiles): four workers of 64 threads,
/// connected before the job comes, take 512 tiles of its 4,800 at once, so the
/// coordinator hands them out over several calls. The image is `tessera render`'s,
/// byte for byte.
#[test]
fn a_hand_out_cut_into_bounded_calls_gives_renders_image() {
    let _turn = shared();
    let dir = tempfile::tempdir().unwrap();
    let (_coordinator, addr) = crate::support::start_coordinator_in(dir.path());
    let _workers: Vec<Daemon> = (1..=4)
        .map(|i| {
            let name = format!("w{i}");
            let args = [
                "worker",
                "--coordinator",
                &addr,
                "--threads",
                "64",
                "--name",
                &name,
            ];
            crate::support::spawn_tessera(dir.path(), &args, &format!("worker-{name}.log"))
        })
        .collect();
    crate::support::wait_for_workers(dir.path(), &addr, 4, Duration::from_secs(30));
    let size = ["--width", "640", "--height", "480"];
    let mut args = vec!["submit", "--wait", "-o", "out.png", "--tile", "8"];
    let scene = scene_path("seed.json");
    args.push(&scene);
    args.extend(size);
    let run = crate::support::client(dir.path(), &addr, &args);
    assert!(run.status.success(), "submit --wait: {}", run.stderr);
    let reference = render_reference(dir.path(), &scene, "reference.png", &size);
    assert_same_png(
        &dir.path().join("out.png"),
        &reference,
        "4 workers of 64 threads",
    );
}
