//! Animated scenes through the real `tessera render`: a frame renders exactly as the
//! static scene of its values does (that is the definition of a frame), a sequence is
//! the frames one by one, and a bad animation or frame choice is one `error: ` line, a
//! non-zero exit and no file.

use std::path::{Path, PathBuf};
use std::time::Duration;

use tempfile::TempDir;

use crate::support::{entries, ok, one_error_line, orbit, scene_path, shared, tessera};

const TIMEOUT: Duration = Duration::from_secs(120);

/// Renders `args` in `dir` and returns the bytes of the PNG written to `out`.
fn render_to(dir: &Path, scene: &str, extra: &[&str], out: &str) -> Vec<u8> {
    let mut args = vec!["render", scene, "-o", out];
    args.extend_from_slice(extra);
    ok(tessera(dir, &args, TIMEOUT), &format!("tessera {args:?}"));
    std::fs::read(dir.join(out)).expect("the image was written")
}

#[test]
fn frame_17_renders_as_the_static_scene_of_its_values() {
    let _turn = shared();
    let dir = TempDir::new().unwrap();
    let text = std::fs::read_to_string(orbit()).unwrap();
    let animated = render::parse_animated(&text).unwrap();
    let frame = animated.frame(17).unwrap();
    // Frame 17 lies between keys: its camera is not any key's.
    assert!(animated.animation.as_ref().unwrap().tracks[0]
        .keys
        .iter()
        .all(|k| k.value != render::animation::Value::Vector(frame.camera.position)));
    let still = frame.to_json().unwrap();
    assert_eq!(render::parse_scene(&still).unwrap(), frame);
    let still_path: PathBuf = dir.path().join("frame17.json");
    std::fs::write(&still_path, &still).unwrap();

    let animated_png = render_to(dir.path(), &orbit(), &["--frame", "17"], "animated.png");
    let still_png = render_to(dir.path(), still_path.to_str().unwrap(), &[], "still.png");
    assert!(
        animated_png == still_png,
        "frame 17 differs from its static scene"
    );
    // And the frame is not just any frame.
    let frame_16 = render_to(dir.path(), &orbit(), &["--frame", "16"], "16.png");
    assert!(
        frame_16 != animated_png,
        "frames 16 and 17 are the same image"
    );
    // Without --frame, an animated scene renders its frame 1.
    let first = render_to(dir.path(), &orbit(), &[], "first.png");
    let frame_1 = render_to(dir.path(), &orbit(), &["--frame", "1"], "1.png");
    assert!(first == frame_1, "no --frame is not frame 1");
}

#[test]
fn a_sequence_is_its_frames_one_by_one() {
    let _turn = shared();
    let dir = TempDir::new().unwrap();
    let small = ["--width", "120", "--height", "80"];
    let mut args = vec!["render", "SCENE", "--frames", "3-5", "-o", "seq/"];
    let scene = scene_path("moving-spheres.json");
    args[1] = &scene;
    args.extend_from_slice(&small);
    let run = ok(
        tessera(dir.path(), &args, TIMEOUT),
        "tessera render --frames 3-5",
    );
    assert_eq!(run.stderr.lines().count(), 3, "{}", run.stderr);
    let seq = dir.path().join("seq");
    assert_eq!(
        entries(&seq),
        ["frame_0003.png", "frame_0004.png", "frame_0005.png"]
    );
    let mut images = Vec::new();
    for k in ["3", "4", "5"] {
        let mut extra = vec!["--frame", k];
        extra.extend_from_slice(&small);
        let single = render_to(dir.path(), &scene, &extra, &format!("single{k}.png"));
        let in_sequence = std::fs::read(seq.join(format!("frame_000{k}.png"))).unwrap();
        assert!(single == in_sequence, "frame {k} of the sequence differs");
        images.push(single);
    }
    assert!(images[0] != images[1] && images[1] != images[2]);

    // A scene without animation is one frame: --frames alone writes frame_0001.png.
    ok(
        tessera(
            dir.path(),
            &[
                "render",
                &scene_path("seed.json"),
                "--frames",
                "-o",
                "still",
            ],
            TIMEOUT,
        ),
        "tessera render --frames of a still scene",
    );
    assert_eq!(entries(&dir.path().join("still")), ["frame_0001.png"]);
}

#[test]
fn invalid_animation_keys_are_refused_through_the_binary() {
    let _turn = shared();
    let dir = TempDir::new().unwrap();
    let text = r#"{"lights": [], "objects": [{"type": "sphere", "center": "0 0 0", "radius": 1, "color": "1 1 1 0"}],
        "animation": {"frames": 120, "tracks": [{"target": "objects[0].radius",
            "keys": [{"frame": 1, "value": 1}, {"frame": 130, "value": 2}]}]}}"#;
    std::fs::write(dir.path().join("scene.json"), text).unwrap();
    for extra in [
        vec![],
        vec!["--frame", "1"],
        vec!["--frames", "1-3", "-o", "out"],
    ] {
        let mut args = vec!["render", "scene.json"];
        args.extend_from_slice(&extra);
        let run = tessera(dir.path(), &args, TIMEOUT);
        assert_eq!(
            one_error_line(&run, &format!("{extra:?}")),
            "error: scene.json: animation.tracks[0].keys[1].frame: 130 is beyond the 120 frames",
            "{extra:?}"
        );
        assert_eq!(entries(dir.path()), ["scene.json"], "{extra:?}");
    }
}

#[test]
fn invalid_frame_choices_are_refused_before_anything_is_written() {
    let _turn = shared();
    let dir = TempDir::new().unwrap();
    let orbit = orbit();
    let seed = scene_path("seed.json");
    let cases: [(&[&str], &str); 7] = [
        (
            &["render", &orbit, "--frames", "1-2", "-o", "orbit.png"],
            "error: orbit.png: a sequence is written one file per frame into a directory: give -o DIR/",
        ),
        (
            &["render", &orbit, "--frame", "122"],
            "error: ORBIT: frame 122 is beyond the scene's 121 frames",
        ),
        (
            &["render", &orbit, "--frames", "120-130", "-o", "out"],
            "error: ORBIT: --frames 120-130: frame 130 is beyond the scene's 121 frames",
        ),
        (
            &["render", &orbit, "--frames", "5-3", "-o", "out"],
            "error: invalid value '5-3' for '--frames [<A-B>]': the range ends (frame 3) before it starts (frame 5)",
        ),
        (
            &["render", &orbit, "--frames", "0-3", "-o", "out"],
            "error: invalid value '0-3' for '--frames [<A-B>]': frames are numbered from 1",
        ),
        (
            &["render", &orbit, "--frames", "3..5", "-o", "out"],
            "error: invalid value '3..5' for '--frames [<A-B>]': expected A-B, K or all (frame numbers from 1), got \"3..5\"",
        ),
        (
            &["render", &seed, "--frame", "2"],
            "error: SEED: frame 2: the scene has no animation, only frame 1",
        ),
    ];
    for (args, expected) in cases {
        let run = tessera(dir.path(), args, TIMEOUT);
        let expected = expected.replace("ORBIT", &orbit).replace("SEED", &seed);
        assert_eq!(
            one_error_line(&run, &format!("{args:?}")),
            expected,
            "{args:?}"
        );
        assert!(entries(dir.path()).is_empty(), "{args:?}");
    }
}
