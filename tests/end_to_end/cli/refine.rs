//! `tessera render --state` and `tessera refine`: a saved adaptive render goes on to a
//! lower error or a larger cap and gives, byte for byte, the image of a direct render
//! with the final settings; `--time-limit` stops at the best image reached; a damaged
//! state file, or one whose mesh files have changed or gone since, is refused with one
//! line and writes nothing.

use std::path::Path;
use std::time::Duration;

use crate::support::{ok, one_error_line, scene_path, shared, tessera, write_mesh_scene};

const LIMIT: Duration = Duration::from_secs(120);

/// Runs `tessera ARGS` in `dir`, which must succeed: what it printed on stderr.
fn succeeds(dir: &Path, args: &[&str]) -> String {
    ok(tessera(dir, args, LIMIT), &format!("tessera {args:?}")).stderr
}

/// Runs `tessera ARGS` in `dir`, which must fail with one `error: ` line: that line.
fn one_error(dir: &Path, args: &[&str]) -> String {
    one_error_line(&tessera(dir, args, LIMIT), &format!("tessera {args:?}"))
}

fn bytes(dir: &Path, name: &str) -> Vec<u8> {
    std::fs::read(dir.join(name)).unwrap_or_else(|e| panic!("{name}: {e}"))
}

const SIZE: [&str; 4] = ["--width", "240", "--height", "160"];

#[test]
fn a_refined_render_is_the_direct_render_byte_for_byte() {
    let _turn = shared();
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let scene = scene_path("seed.json");
    let render = |extra: &[&str]| {
        let mut args = vec!["render", scene.as_str(), "--sampler", "adaptive"];
        args.extend_from_slice(&SIZE);
        args.extend_from_slice(extra);
        succeeds(d, &args)
    };
    render(&[
        "--aa",
        "8",
        "--target-error",
        "4",
        "--state",
        "s.state",
        "-o",
        "coarse.png",
    ]);
    // A lower target, then a larger cap, each from the state the previous step left.
    succeeds(
        d,
        &[
            "refine",
            "s.state",
            "--target-error",
            "1.5",
            "-o",
            "fine.png",
        ],
    );
    render(&[
        "--aa",
        "8",
        "--target-error",
        "1.5",
        "-o",
        "direct-fine.png",
    ]);
    assert_eq!(bytes(d, "fine.png"), bytes(d, "direct-fine.png"));
    assert_ne!(bytes(d, "fine.png"), bytes(d, "coarse.png"));
    let line = succeeds(
        d,
        &["refine", "s.state", "--aa", "16", "--target-error", "0.8"],
    );
    assert!(
        line.contains("adaptive up to 16x16, target 0.8 levels"),
        "{line}"
    );
    render(&[
        "--aa",
        "16",
        "--target-error",
        "0.8",
        "-o",
        "direct-finer.png",
    ]);
    assert_eq!(bytes(d, "s.png"), bytes(d, "direct-finer.png"));
}

#[test]
fn a_time_limit_gives_the_image_reached_and_says_so() {
    let _turn = shared();
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let scene = scene_path("seed.json");
    let mut args = vec![
        "render",
        scene.as_str(),
        "--aa",
        "16",
        "--time-limit",
        "300ms",
    ];
    args.extend_from_slice(&SIZE);
    args.extend_from_slice(&["-o", "limited.png"]);
    let line = succeeds(d, &args);
    assert!(line.contains("no target"), "{line}");
    assert!(
        line.contains("as far as the time limit allowed") || line.contains("cap of"),
        "{line}"
    );
    assert!(bytes(d, "limited.png").starts_with(b"\x89PNG"));
    // A time limit is for adaptive sampling only; bad durations are one line.
    let e = one_error(
        d,
        &["render", &scene, "--time-limit", "1s", "--sampler", "grid"],
    );
    assert!(
        e.contains("--time-limit applies only to --sampler adaptive"),
        "{e}"
    );
    let e = one_error(d, &["render", &scene, "--time-limit=-2s"]);
    assert!(e.contains("--time-limit"), "{e}");
    let e = one_error(d, &["render", &scene, "--time-limit", "3parsecs"]);
    assert!(e.contains("--time-limit"), "{e}");
}

#[test]
fn damaged_or_foreign_states_are_refused_and_nothing_is_written() {
    let _turn = shared();
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let scene = scene_path("seed.json");
    let mut args = vec![
        "render",
        scene.as_str(),
        "--sampler",
        "adaptive",
        "--aa",
        "4",
        "--target-error",
        "3",
        "--state",
        "good.state",
        "-o",
        "good.png",
    ];
    args.extend_from_slice(&SIZE);
    succeeds(d, &args);
    let good = bytes(d, "good.state");
    let mut flipped = good.clone();
    let middle = flipped.len() / 2;
    flipped[middle] ^= 1;
    std::fs::write(d.join("flipped.state"), &flipped).unwrap();
    std::fs::write(d.join("short.state"), &good[..good.len() / 3]).unwrap();
    std::fs::write(d.join("scene.state"), std::fs::read(&scene).unwrap()).unwrap();
    for (file, says) in [
        ("flipped.state", "damaged"),
        ("short.state", "damaged"),
        ("scene.state", "not a render state"),
        ("missing.state", "cannot read render state"),
    ] {
        let e = one_error(d, &["refine", file, "--target-error", "1", "-o", "out.png"]);
        assert!(e.contains(file) && e.contains(says), "{file}: {e}");
        assert!(!d.join("out.png").exists(), "{file}: an image was written");
    }
    // The good state still refines, and --state needs adaptive sampling.
    succeeds(
        d,
        &[
            "refine",
            "good.state",
            "--target-error",
            "2",
            "-o",
            "out.png",
        ],
    );
    let e = one_error(d, &["render", &scene, "--state", "x.state"]);
    assert!(e.contains("--state"), "{e}");
    assert!(!d.join("x.state").exists());
}

#[test]
fn a_refine_stopped_at_the_cap_says_how_many_pixels_are_at_it() {
    let _turn = shared();
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let scene = scene_path("seed.json");
    let mut args = vec!["render", scene.as_str(), "--sampler", "adaptive"];
    args.extend_from_slice(&SIZE);
    args.extend_from_slice(&[
        "--aa",
        "4",
        "--target-error",
        "4",
        "--state",
        "s.state",
        "-o",
        "coarse.png",
    ]);
    succeeds(d, &args);
    // Far below what 16 samples can reach: the last rung, above the target.
    let said = succeeds(
        d,
        &[
            "refine",
            "s.state",
            "--target-error",
            "0.05",
            "-o",
            "fine.png",
        ],
    );
    let line = said
        .lines()
        .find(|l| l.contains("samples/pixel"))
        .unwrap_or_else(|| panic!("no summary: {said}"));
    let mean: f64 = line
        .split(" samples/pixel")
        .next()
        .and_then(|head| head.rsplit(' ').next())
        .and_then(|mean| mean.parse().ok())
        .unwrap_or_else(|| panic!("no mean: {line}"));
    // The sky's blocks have no error to take samples for: the mean is below the cap,
    // and the line says that not every pixel is at it.
    assert!(mean < 16.0, "{line}");
    assert!(!line.contains("every pixel at its cap"), "{line}");
    assert!(
        line.contains("% of the pixels at the cap of 16 samples"),
        "{line}"
    );
}

#[test]
fn refine_replaces_by_default_only_the_image_of_its_state() {
    let _turn = shared();
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let scene = scene_path("seed.json");
    // `render` writes ./seed.png, the image of seed.state.
    succeeds(
        d,
        &[
            "render",
            &scene,
            "--width",
            "96",
            "--height",
            "64",
            "--sampler",
            "adaptive",
            "--aa",
            "8",
            "--target-error",
            "4",
            "--state",
            "seed.state",
        ],
    );
    // Refining replaces it, again and again: each time the image of the state.
    succeeds(d, &["refine", "seed.state", "--target-error", "2"]);
    succeeds(d, &["refine", "seed.state", "--target-error", "1"]);

    // Another file under that name is left alone unless named with -o.
    let other = b"another image".to_vec();
    std::fs::write(d.join("seed.png"), &other).unwrap();
    assert_eq!(
        one_error(d, &["refine", "seed.state", "--target-error", "0.8"]),
        "error: seed.png: a file of that name exists, and it is not the image of seed.state: \
         give -o seed.png to replace it, or -o another name"
    );
    assert!(bytes(d, "seed.png") == other, "seed.png left as it was");
    succeeds(
        d,
        &[
            "refine",
            "seed.state",
            "--target-error",
            "0.8",
            "-o",
            "seed.png",
        ],
    );
    assert!(bytes(d, "seed.png") != other, "seed.png replaced");
}

#[test]
fn a_mesh_scene_refines_from_anywhere_until_its_mesh_file_changes() {
    let _turn = shared();
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    write_mesh_scene(d);
    // The scene named relative to the render's directory; the refines run elsewhere,
    // and read the mesh from beside the scene all the same.
    let elsewhere = d.join("elsewhere");
    std::fs::create_dir(&elsewhere).unwrap();
    let render = |extra: &[&str]| {
        let mut args = vec!["render", "cube.json", "--sampler", "adaptive", "--aa", "8"];
        args.extend_from_slice(&SIZE);
        args.extend_from_slice(extra);
        succeeds(d, &args)
    };
    render(&[
        "--target-error",
        "4",
        "--state",
        "s.state",
        "-o",
        "coarse.png",
    ]);
    succeeds(
        &elsewhere,
        &[
            "refine",
            "../s.state",
            "--target-error",
            "1.5",
            "-o",
            "fine.png",
        ],
    );
    render(&["--target-error", "1.5", "-o", "direct-fine.png"]);
    assert_eq!(bytes(&elsewhere, "fine.png"), bytes(d, "direct-fine.png"));
    assert_ne!(bytes(d, "direct-fine.png"), bytes(d, "coarse.png"));

    // The mesh changed (one vertex moved, or not a mesh any more): refused in one line
    // naming the object, the file and both digests; nothing written, the state kept.
    let state = bytes(d, "s.state");
    let refused = |what: &str| {
        let e = one_error(
            &elsewhere,
            &[
                "refine",
                "../s.state",
                "--target-error",
                "1",
                "-o",
                "out.png",
            ],
        );
        assert!(
            !elsewhere.join("out.png").exists(),
            "{what}: an image was written"
        );
        assert!(
            bytes(d, "s.state") == state,
            "{what}: the state was changed"
        );
        e
    };
    let moved = crate::support::CUBE_OBJ.replacen("v 1 1 1", "v 1 1.5 1", 1);
    std::fs::write(d.join("cube.obj"), &moved).unwrap();
    for (what, text) in [
        ("a vertex moved", moved.as_str()),
        ("no longer a mesh", "v 1 2\n"),
    ] {
        std::fs::write(d.join("cube.obj"), text).unwrap();
        let e = refused(what);
        assert!(
            e.starts_with(
                "error: ../s.state: objects[1].file: cube.obj changed since the state \
                 was saved (SHA-256 "
            ) && e.ends_with(" now)"),
            "{what}: {e}"
        );
    }
    // The mesh gone.
    std::fs::remove_file(d.join("cube.obj")).unwrap();
    let e = refused("gone");
    assert!(
        e.starts_with(
            "error: ../s.state: objects[1].file: cube.obj cannot be read since the \
             state was saved: "
        ),
        "{e}"
    );
    // Back as it was, the state refines again.
    std::fs::write(d.join("cube.obj"), crate::support::CUBE_OBJ).unwrap();
    succeeds(
        &elsewhere,
        &[
            "refine",
            "../s.state",
            "--target-error",
            "1.5",
            "-o",
            "again.png",
        ],
    );
    assert_eq!(bytes(&elsewhere, "again.png"), bytes(d, "direct-fine.png"));
}
