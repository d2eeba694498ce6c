//! `tessera render` as a user runs it: the real binary, a fresh temporary directory as
//! the current directory for every run, and a time limit so that a hung render fails the
//! test instead of hanging CI.
//!
//! What is checked is the command's contract: a valid scene gives a PNG of the requested
//! size where it was asked for and a one-line summary; an invalid scene or setting gives
//! exactly one `error: ` line that names the offending key, a non-zero exit, and no file
//! at all (neither the image nor the temporary file it is written through).

use std::path::Path;
use std::time::Duration;

use render::limits::{MAX_AA, MAX_SIDE};
use tempfile::TempDir;

use crate::support::{decode_rgb8, entries, ok, scene_path, shared, tessera, Daemon, Run, BIN};

/// Every render here is tiny; a run this long means the binary hangs.
const TIMEOUT: Duration = Duration::from_secs(60);

/// The file name under which a test's scene is written in its temporary directory.
const SCENE: &str = "scene.json";

/// A temporary directory holding `text` as [`SCENE`].
fn dir_with_scene(text: &str) -> TempDir {
    let dir = TempDir::new().expect("cannot create a temporary directory");
    std::fs::write(dir.path().join(SCENE), text).expect("cannot write the scene");
    dir
}

/// The run succeeded and printed one summary line with the size and samples per pixel.
fn assert_rendered(run: &Run, width: u32, height: u32, samples: u32) {
    assert!(
        run.status.success(),
        "exit {:?}, stderr:\n{}",
        run.status,
        run.stderr
    );
    let lines: Vec<&str> = run.stderr.lines().collect();
    assert_eq!(
        lines.len(),
        1,
        "expected a one-line summary, got:\n{}",
        run.stderr
    );
    let summary = lines[0];
    assert!(
        summary.contains(&format!("{width}x{height}")),
        "size missing from {summary:?}"
    );
    // One sample is said in the singular.
    let per_pixel = match samples {
        1 => "1 sample/pixel".to_owned(),
        n => format!("{n} samples/pixel"),
    };
    assert!(
        summary.contains(&per_pixel),
        "samples per pixel missing from {summary:?}"
    );
}

/// The run failed with one `error: ` line, and left nothing but the scene file behind.
fn assert_refused(run: &Run, dir: &Path) -> Result<String, String> {
    if run.status.success() {
        return Err(format!("exit status 0 (stderr: {:?})", run.stderr));
    }
    let lines: Vec<&str> = run.stderr.lines().collect();
    if lines.len() != 1 || !lines[0].starts_with("error: ") {
        return Err(format!("stderr is not one `error: ` line:\n{}", run.stderr));
    }
    let left = entries(dir);
    if left != [SCENE] {
        return Err(format!("files left in the directory: {left:?}"));
    }
    Ok(lines[0].to_string())
}

#[test]
fn renders_seed_to_default_path_in_current_dir() {
    let _turn = shared();
    let dir = TempDir::new().unwrap();
    let run = tessera(
        dir.path(),
        &[
            "render",
            &scene_path("seed.json"),
            "--width",
            "60",
            "--height",
            "40",
        ],
        TIMEOUT,
    );
    assert_rendered(&run, 60, 40, 1);
    assert_eq!(run.stdout, "", "render prints nothing on stdout");
    // Only the image: the temporary file it was written through has been renamed.
    assert_eq!(entries(dir.path()), ["seed.png"]);
    let img = decode_rgb8(&dir.path().join("seed.png"));
    assert_eq!(img.dimensions(), (60, 40));
    assert!(
        img.pixels().any(|p| p != [0, 0, 0]),
        "the seed render is all black"
    );
}

#[test]
fn output_flag_writes_where_asked() {
    let _turn = shared();
    let dir = TempDir::new().unwrap();
    std::fs::create_dir(dir.path().join("out")).unwrap();
    let run = tessera(
        dir.path(),
        &[
            "render",
            &scene_path("seed.json"),
            "-o",
            "out/small.png",
            "--width",
            "60",
            "--height",
            "40",
        ],
        TIMEOUT,
    );
    assert_rendered(&run, 60, 40, 1);
    assert!(
        run.stderr.contains("small.png"),
        "summary should name the output: {}",
        run.stderr
    );
    assert_eq!(
        entries(dir.path()),
        ["out"],
        "no default seed.png beside it"
    );
    assert_eq!(entries(&dir.path().join("out")), ["small.png"]);
    assert_eq!(
        decode_rgb8(&dir.path().join("out/small.png")).dimensions(),
        (60, 40)
    );
}

#[test]
fn flags_override_the_scene_image_settings() {
    let _turn = shared();
    let dir = dir_with_scene(VALID_SCENE);

    // The scene's own settings first: 8x6, aa 1.
    let run = tessera(dir.path(), &["render", SCENE, "-o", "own.png"], TIMEOUT);
    assert_rendered(&run, 8, 6, 1);
    assert_eq!(
        decode_rgb8(&dir.path().join("own.png")).dimensions(),
        (8, 6)
    );

    let run = tessera(
        dir.path(),
        &[
            "render",
            SCENE,
            "-o",
            "flags.png",
            "--width",
            "32",
            "--height",
            "24",
            "--aa",
            "3",
            "--max-depth",
            "0",
        ],
        TIMEOUT,
    );
    assert_rendered(&run, 32, 24, 9);
    assert_eq!(
        decode_rgb8(&dir.path().join("flags.png")).dimensions(),
        (32, 24)
    );
}

/// The format requires the image not to depend on the number of threads: bit-identical.
#[test]
fn thread_count_does_not_change_the_image() {
    let _turn = shared();
    let dir = TempDir::new().unwrap();
    let scene = scene_path("seed.json");
    let mut images = Vec::new();
    for threads in ["1", "2", "3"] {
        let out = format!("t{threads}.png");
        let args = [
            "render",
            &scene,
            "-o",
            &out,
            "--width",
            "90",
            "--height",
            "70",
            "--aa",
            "2",
            "--threads",
            threads,
        ];
        let run = tessera(dir.path(), &args, TIMEOUT);
        assert_rendered(&run, 90, 70, 4);
        images.push((threads, decode_rgb8(&dir.path().join(out))));
    }
    for (threads, img) in &images[1..] {
        assert!(
            img == &images[0].1,
            "{threads} threads render differently from 1 thread"
        );
    }
}

/// The seed's own file, unchanged and at its own settings (600x400, aa 1), must render.
#[test]
fn exact_seed_scene_renders() {
    let _turn = shared();
    let dir = TempDir::new().unwrap();
    let run = tessera(dir.path(), &["render", &scene_path("seed.json")], TIMEOUT);
    assert_rendered(&run, 600, 400, 1);
    assert_eq!(
        decode_rgb8(&dir.path().join("seed.png")).dimensions(),
        (600, 400)
    );
}

/// A valid scene touching every part of the format; each invalid case below breaks one
/// thing in it. Kept tiny (8x6) so that a case which wrongly renders is still quick.
const VALID_SCENE: &str = r#"{
  "camera": { "position": "3 1.5 -4", "look_at": "0 0 0" },
  "image": { "width": 8, "height": 6, "aa": 1, "max_depth": 2 },
  "ambient": 0.2,
  "lights": [
    { "position": "-7 10 -10", "color": "1 1 1 0" }
  ],
  "objects": [
    { "type": "sphere", "center": "0 0 0", "radius": 1, "color": "0.5 1 0.5 0.3" },
    { "type": "sphere", "center": [3, 0, 0], "radius": 1.0, "color": [0.5, 0.5, 0.5, 0.6] },
    { "type": "sphere", "center": "-2 0 1", "radius": 0.5, "color": "0.9 0.1 0.1 0" },
    { "type": "plan", "normal": "0 1 0", "distance": -1, "color": "0.5 0.25 0.2 2" }
  ]
}"#;

/// [`VALID_SCENE`] with `from` (which must occur exactly once) replaced by `to`.
fn edit(from: &str, to: &str) -> String {
    assert_eq!(
        VALID_SCENE.matches(from).count(),
        1,
        "{from:?} must occur once in VALID_SCENE"
    );
    VALID_SCENE.replace(from, to)
}

/// Without this, every invalid case could pass for a reason unrelated to its edit.
#[test]
fn the_base_of_the_invalid_cases_is_valid() {
    let _turn = shared();
    let dir = dir_with_scene(VALID_SCENE);
    let run = tessera(dir.path(), &["render", SCENE], TIMEOUT);
    assert_rendered(&run, 8, 6, 1);
    assert_eq!(entries(dir.path()), [SCENE, "scene.png"]);
}

#[test]
fn invalid_scenes_are_refused_with_one_line_naming_the_problem() {
    let _turn = shared();
    let too_wide = MAX_SIDE + 1;
    let cases: Vec<(&str, String, Vec<String>)> = vec![
        (
            "JSON syntax error",
            edit(r#""radius": 0.5,"#, r#""radius": 0.5,,"#),
            frags(&["not valid JSON", "line 11", "column"]),
        ),
        (
            "top level not an object",
            "[1, 2, 3]".into(),
            frags(&["scene: expected an object, got an array"]),
        ),
        (
            "missing objects",
            r#"{ "lights": [] }"#.into(),
            frags(&[r#"scene: missing key "objects""#]),
        ),
        (
            "missing lights",
            r#"{ "objects": [] }"#.into(),
            frags(&[r#"scene: missing key "lights""#]),
        ),
        (
            "unknown top-level key",
            edit(r#""ambient": 0.2,"#, r#""ambient": 0.2, "fog": 1,"#),
            frags(&["fog: unknown key"]),
        ),
        (
            "unknown key in an object",
            edit(r#""radius": 0.5,"#, r#""radius": 0.5, "shiny": true,"#),
            frags(&["objects[2].shiny: unknown key"]),
        ),
        (
            "unknown object type",
            edit(r#""type": "plan""#, r#""type": "cube""#),
            frags(&["objects[3].type", r#"unknown object type "cube""#]),
        ),
        (
            "sphere radius 0",
            edit(r#""radius": 0.5"#, r#""radius": 0"#),
            frags(&["objects[2].radius: must be > 0, got 0"]),
        ),
        (
            "sphere radius -1",
            edit(r#""radius": 0.5"#, r#""radius": -1"#),
            frags(&["objects[2].radius: must be > 0, got -1"]),
        ),
        (
            "sphere without radius",
            edit(r#""radius": 0.5, "#, ""),
            frags(&[r#"objects[2]: missing key "radius""#]),
        ),
        (
            "plane with a zero normal",
            edit(r#""normal": "0 1 0""#, r#""normal": "0 0 0""#),
            frags(&["objects[3].normal", "non-zero"]),
        ),
        (
            "vector of 2 numbers",
            edit(r#""center": "-2 0 1""#, r#""center": "-2 0""#),
            frags(&["objects[2].center: expected 3 numbers, got 2"]),
        ),
        (
            "vector with a word",
            edit(r#""center": "-2 0 1""#, r#""center": "-2 zero 1""#),
            frags(&["objects[2].center", r#""zero" is not a number"#]),
        ),
        (
            "vector given as a number",
            edit(r#""center": "-2 0 1""#, r#""center": 5"#),
            frags(&["objects[2].center", "got a number"]),
        ),
        (
            "object colour of 3 numbers",
            edit(r#""0.9 0.1 0.1 0""#, r#""0.9 0.1 0.1""#),
            frags(&["objects[2].color", "4 numbers", "got 3"]),
        ),
        (
            "negative r",
            edit(r#""0.9 0.1 0.1 0""#, r#""-0.9 0.1 0.1 0""#),
            frags(&["objects[2].color", ">= 0, got -0.9"]),
        ),
        (
            "negative g",
            edit(r#""0.9 0.1 0.1 0""#, r#""0.9 -0.1 0.1 0""#),
            frags(&["objects[2].color", ">= 0, got -0.1"]),
        ),
        (
            "negative b",
            edit(r#"[0.5, 0.5, 0.5, 0.6]"#, r#"[0.5, 0.5, -2, 0.6]"#),
            frags(&["objects[1].color", ">= 0, got -2"]),
        ),
        (
            "special 1.5",
            edit(r#""0.9 0.1 0.1 0""#, r#""0.9 0.1 0.1 1.5""#),
            frags(&["objects[2].color", "special", "got 1.5"]),
        ),
        (
            "special -0.5",
            edit(r#""0.9 0.1 0.1 0""#, r#""0.9 0.1 0.1 -0.5""#),
            frags(&["objects[2].color", "special", "got -0.5"]),
        ),
        (
            "special 3",
            edit(r#""0.9 0.1 0.1 0""#, r#""0.9 0.1 0.1 3""#),
            frags(&["objects[2].color", "special", "got 3"]),
        ),
        (
            "inf in a string vector",
            edit(r#""center": "-2 0 1""#, r#""center": "-2 inf 1""#),
            frags(&["objects[2].center: must be a finite number, got inf"]),
        ),
        (
            "NaN in a string vector",
            edit(r#""normal": "0 1 0""#, r#""normal": "0 NaN 0""#),
            frags(&["objects[3].normal: must be a finite number, got NaN"]),
        ),
        (
            "camera looking straight down",
            edit(r#""position": "3 1.5 -4""#, r#""position": "0 5 0""#),
            frags(&["camera", "parallel to the world up axis"]),
        ),
        (
            "camera position equal to look_at",
            edit(r#""position": "3 1.5 -4""#, r#""position": "0 0 0""#),
            frags(&["camera.look_at: must differ from camera.position"]),
        ),
        (
            "image width 0",
            edit(r#""width": 8"#, r#""width": 0"#),
            frags(&[&format!(
                "image.width: must be between 1 and {MAX_SIDE}, got 0"
            )]),
        ),
        (
            "image height 0",
            edit(r#""height": 6"#, r#""height": 0"#),
            frags(&[&format!(
                "image.height: must be between 1 and {MAX_SIDE}, got 0"
            )]),
        ),
        (
            "image aa 0",
            edit(r#""aa": 1"#, r#""aa": 0"#),
            frags(&[&format!("image.aa: must be between 1 and {MAX_AA}, got 0")]),
        ),
        (
            "image width above the limit",
            edit(r#""width": 8"#, &format!(r#""width": {too_wide}"#)),
            frags(&[&format!(
                "image.width: must be between 1 and {MAX_SIDE}, got {too_wide}"
            )]),
        ),
        (
            "non-integer width",
            edit(r#""width": 8"#, r#""width": 600.5"#),
            frags(&["image.width", "whole number", "600.5"]),
        ),
        (
            "negative ambient",
            edit(r#""ambient": 0.2"#, r#""ambient": -0.1"#),
            frags(&["ambient: must be >= 0, got -0.1"]),
        ),
        (
            "lights entry not an object",
            edit(
                r#"{ "position": "-7 10 -10", "color": "1 1 1 0" }"#,
                r#""-7 10 -10""#,
            ),
            frags(&["lights[0]: expected an object, got a string"]),
        ),
        (
            "light colour of 2 numbers",
            edit(r#""color": "1 1 1 0""#, r#""color": "1 1""#),
            frags(&["lights[0].color", "got 2"]),
        ),
    ];

    let mut failures = Vec::new();
    for (name, text, fragments) in &cases {
        let dir = dir_with_scene(text);
        let run = tessera(dir.path(), &["render", SCENE], TIMEOUT);
        match assert_refused(&run, dir.path()) {
            Err(why) => failures.push(format!("{name}: {why}")),
            Ok(line) => {
                // The scene file is named so the user knows which file to fix.
                for fragment in fragments.iter().map(String::as_str).chain([SCENE]) {
                    if !line.contains(fragment) {
                        failures.push(format!("{name}: {line:?} does not contain {fragment:?}"));
                    }
                }
            }
        }
    }
    assert!(
        failures.is_empty(),
        "{} of {} cases failed:\n{}",
        failures.len(),
        cases.len(),
        failures.join("\n")
    );
}

fn frags(fragments: &[&str]) -> Vec<String> {
    fragments.iter().map(|f| f.to_string()).collect()
}

#[test]
fn missing_scene_file_is_named() {
    let _turn = shared();
    let dir = TempDir::new().unwrap();
    let run = tessera(dir.path(), &["render", "no-such-scene.json"], TIMEOUT);
    assert!(!run.status.success());
    let lines: Vec<&str> = run.stderr.lines().collect();
    assert_eq!(lines.len(), 1, "stderr:\n{}", run.stderr);
    assert!(
        lines[0].starts_with("error: ") && lines[0].contains("no-such-scene.json"),
        "{:?}",
        lines[0]
    );
    assert!(
        entries(dir.path()).is_empty(),
        "left behind: {:?}",
        entries(dir.path())
    );
}

/// clap rejects these before the scene is even read: its message is its own (several
/// lines of usage), so only the exit status and the absence of output are the contract.
#[test]
fn out_of_range_flags_are_rejected() {
    let _turn = shared();
    let too_wide = (MAX_SIDE + 1).to_string();
    let too_much_aa = (MAX_AA + 1).to_string();
    let cases: [&[&str]; 6] = [
        &["--width", "0"],
        &["--height", "0"],
        &["--aa", "0"],
        &["--width", &too_wide],
        &["--aa", &too_much_aa],
        &["--width", "-5"],
    ];
    for flags in cases {
        let dir = dir_with_scene(VALID_SCENE);
        let mut args = vec!["render", SCENE];
        args.extend_from_slice(flags);
        let run = tessera(dir.path(), &args, TIMEOUT);
        assert!(!run.status.success(), "{flags:?} accepted: {}", run.stderr);
        assert!(!run.stderr.is_empty(), "{flags:?}: no message");
        assert_eq!(entries(dir.path()), [SCENE], "{flags:?} left files behind");
    }
}

#[test]
fn output_in_a_missing_directory_is_an_error() {
    let _turn = shared();
    let dir = dir_with_scene(VALID_SCENE);
    let run = tessera(
        dir.path(),
        &["render", SCENE, "-o", "no-such-dir/out.png"],
        TIMEOUT,
    );
    let line = assert_refused(&run, dir.path()).unwrap_or_else(|why| panic!("{why}"));
    assert!(
        line.contains("no-such-dir/out.png"),
        "the error should name the output: {line:?}"
    );
}

#[test]
fn an_output_that_cannot_be_written_is_refused_before_rendering() {
    let _turn = shared();
    let dir = dir_with_scene(VALID_SCENE);
    std::fs::create_dir(dir.path().join("d.png")).unwrap();
    // A render of minutes: refused within seconds, before any of it, or the run is
    // killed and the test fails.
    let big = ["--width", "4000", "--height", "4000", "--aa", "16"];
    for (out, says) in [
        ("no-such-dir/out.png", "cannot write no-such-dir/out.png"),
        ("out.jpg", "out.jpg: tessera writes PNG images only"),
        ("out", "out: tessera writes PNG images only"),
        ("d.png", "cannot write d.png: it is a directory"),
    ] {
        let mut args = vec!["render", SCENE, "-o", out];
        args.extend(big);
        let run = tessera(dir.path(), &args, Duration::from_secs(10));
        let mut left = entries(dir.path());
        left.retain(|name| name != "d.png");
        assert_eq!(left, [SCENE], "-o {out} left files behind");
        assert!(!run.status.success(), "-o {out} accepted");
        let lines: Vec<&str> = run.stderr.lines().collect();
        assert!(
            lines.len() == 1 && lines[0].starts_with(&format!("error: {says}")),
            "-o {out}: {:?}",
            run.stderr
        );
    }
}

#[test]
fn a_state_file_that_cannot_be_written_is_refused_before_rendering() {
    let _turn = shared();
    let dir = dir_with_scene(VALID_SCENE);
    std::fs::create_dir(dir.path().join("d.state")).unwrap();
    // An adaptive render of minutes: refused before any of it, or the run is killed.
    let big = [
        "--width",
        "4000",
        "--height",
        "4000",
        "--aa",
        "16",
        "--sampler",
        "adaptive",
        "--target-error",
        "0.1",
    ];
    for (state, says) in [
        ("no-such-dir/x.state", "cannot write no-such-dir/x.state"),
        ("d.state", "cannot write d.state: it is a directory"),
    ] {
        let mut args = vec!["render", SCENE, "-o", "out.png", "--state", state];
        args.extend(big);
        let run = tessera(dir.path(), &args, Duration::from_secs(10));
        let mut left = entries(dir.path());
        left.retain(|name| name != "d.state");
        assert_eq!(left, [SCENE], "--state {state} left files behind");
        assert!(!run.status.success(), "--state {state} accepted");
        let lines: Vec<&str> = run.stderr.lines().collect();
        assert!(
            lines.len() == 1 && lines[0].starts_with(&format!("error: {says}")),
            "--state {state}: {:?}",
            run.stderr
        );
    }
}

#[test]
fn an_interrupted_render_leaves_nothing_behind() {
    let _turn = shared();
    let dir = dir_with_scene(VALID_SCENE);
    // A render of minutes, interrupted once it is under way: the output was checked
    // at the start, and nothing of that check, nor any partial image, may remain.
    let mut command = std::process::Command::new(BIN);
    command
        .current_dir(dir.path())
        .args(["render", SCENE, "-o", "out.png", "--width", "4000"])
        .args(["--height", "4000", "--aa", "16", "--threads", "1"])
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null());
    // SIGINT as at a terminal: a process started in the background by a shell without
    // job control (`cmd &` in a script, as some CI runners start the tests) inherits
    // SIGINT ignored, and so would the render, which then never stops.
    use std::os::unix::process::CommandExt;
    // SAFETY: between fork and exec the child only calls `signal`, which is
    // async-signal-safe, and touches no memory of the parent.
    unsafe {
        command.pre_exec(|| {
            libc::signal(libc::SIGINT, libc::SIG_DFL);
            Ok(())
        });
    }
    let child = command.spawn().expect("cannot start tessera");
    let mut render = Daemon {
        name: "render".into(),
        child,
        log: None,
    };
    std::thread::sleep(Duration::from_millis(700));
    render.signal("INT");
    let status = render
        .wait_exit(Duration::from_secs(10))
        .expect("render did not stop on SIGINT");
    assert!(!status.success());
    assert_eq!(entries(dir.path()), [SCENE]);
}

#[test]
fn one_of_anything_is_said_in_the_singular() {
    let _turn = shared();
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let seed = scene_path("seed.json");
    let small = ["--width", "16", "--height", "16", "--aa", "1"];
    let line = |args: &[&str]| {
        let mut all = args.to_vec();
        all.extend(small);
        let run = ok(tessera(d, &all, Duration::from_secs(60)), &all.join(" "));
        run.stderr.lines().last().unwrap_or_default().to_owned()
    };
    let grid = line(&["render", &seed, "-o", "grid.png", "--threads", "1"]);
    assert!(
        grid.contains(": 16x16, 1 sample/pixel (grid 1x1, 256 in all),")
            && grid.ends_with("(1 thread)"),
        "{grid}"
    );
    let adaptive = line(&[
        "render",
        &seed,
        "-o",
        "a.png",
        "--threads",
        "1",
        "--target-error",
        "1",
    ]);
    assert!(
        adaptive.contains("adaptive up to 1x1, target 1 level,")
            && adaptive.contains("every pixel at its cap of 1 sample,"),
        "{adaptive}"
    );
    let up = line(&[
        "up",
        &seed,
        "-o",
        "up.png",
        "--workers",
        "1",
        "--tile",
        "16",
    ]);
    assert!(
        up.contains(", 1 tile, rendered in") && up.ends_with("(1 worker)"),
        "{up}"
    );
}
