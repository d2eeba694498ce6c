use crate::animation::AnimatedScene;
use crate::mesh::MeshFiles;
use crate::scene::{CameraSpec, Shape};
use crate::transform::TransformSpec;
use crate::vec3::Vec3;
use crate::{parse_animated, parse_animated_with, parse_scene, parse_scene_with};

/// Two lights, two spheres and a plane, with `animation` as the animation key's
/// value.
fn scene(animation: &str) -> String {
    format!(
        r#"{{"lights": [{{"position": "-7 10 -10", "color": "1 1 1"}},
                         {{"position": "7 10 10", "color": "1 1 1"}}],
               "objects": [
                 {{"type": "sphere", "center": "0 0 0", "radius": 1, "color": "0.5 1 0.5 0.3"}},
                 {{"type": "sphere", "center": "3 0 0", "radius": 1, "color": "0.5 0.5 0.5 0.6"}},
                 {{"type": "plan", "normal": "0 1 0", "distance": -1, "color": "0.5 0.25 0.2 2"}}],
               "image": {{"width": 32, "height": 24}},
               "animation": {animation}}}"#
    )
}

/// An animation of 120 frames with the given tracks.
fn tracks(tracks: &str) -> String {
    scene(&format!(
        r#"{{"frames": 120, "fps": 24, "tracks": [{tracks}]}}"#
    ))
}

fn error_of(text: &str) -> String {
    let e = parse_animated(text).unwrap_err().to_string();
    // The same error when read as a plain scene (frame 1).
    assert_eq!(parse_scene(text).unwrap_err().to_string(), e);
    assert!(!e.contains('\n'), "{e}");
    e
}

const RADIUS: &str = r#"{"target": "objects[1].radius", "keys": [{"frame": 1, "value": 0.5}, {"frame": 120, "value": 1.0}]}"#;

#[test]
fn an_animation_is_read_with_its_tracks() {
    let s = parse_animated(&tracks(&format!(
        r#"{{"target": "camera.position", "interpolation": "catmull-rom",
                 "keys": [{{"frame": 1, "value": "0 1 -5"}}, {{"frame": 61, "value": [5, 1, 0]}}]}},
               {RADIUS}"#
    )))
    .unwrap();
    let a = s.animation.as_ref().unwrap();
    assert_eq!((a.frames, a.fps, a.tracks.len()), (120, 24.0, 2));
    assert_eq!(s.frame_count(), 120);
    // Defaults: 24 frames per second, no tracks.
    let s = parse_animated(&scene(r#"{"frames": 3}"#)).unwrap();
    let a = s.animation.as_ref().unwrap();
    assert_eq!((a.frames, a.fps, a.tracks.len()), (3, 24.0, 0));
    assert_eq!(s.frame(3).unwrap(), s.base);
}

/// Frame k is the static scene with the interpolated values written by hand.
#[test]
fn frame_k_is_the_static_scene_with_the_interpolated_values() {
    let text = tracks(&format!(
        r#"{{"target": "camera.position", "keys": [{{"frame": 11, "value": "0 1 -5"}}, {{"frame": 21, "value": "10 1 -5"}}]}},
               {RADIUS},
               {{"target": "objects[0].color", "keys": [{{"frame": 1, "value": "0 0 0"}}, {{"frame": 3, "value": "1 0.5 0.25"}}]}},
               {{"target": "lights[1].position", "interpolation": "catmull-rom",
                 "keys": [{{"frame": 1, "value": "0 0 0"}}, {{"frame": 5, "value": "4 0 0"}}, {{"frame": 9, "value": "8 0 0"}}, {{"frame": 13, "value": "12 0 0"}}]}},
               {{"target": "objects[2].distance", "keys": [{{"frame": 60, "value": -2}}]}}"#
    ));
    let animated = parse_animated(&text).unwrap();
    let by_hand = |camera_x: f64, radius: f64, rgb: Vec3, light_x: f64| {
        let mut s = parse_scene(&scene(r#"{"frames": 1}"#)).unwrap();
        s.camera = CameraSpec {
            position: Vec3::new(camera_x, 1.0, -5.0),
            look_at: Vec3::ZERO,
            ..CameraSpec::default()
        };
        s.objects[1].shape = Shape::Sphere {
            center: Vec3::new(3.0, 0.0, 0.0),
            radius,
        };
        s.objects[0].color = rgb;
        s.lights[1].position = Vec3::new(light_x, 0.0, 0.0);
        s.objects[2].shape = Shape::Plane {
            normal: Vec3::new(0.0, 1.0, 0.0),
            distance: -2.0,
        };
        s
    };
    // Frame 1: every track at its first key (the camera and the plane hold theirs).
    assert_eq!(
        animated.frame(1).unwrap(),
        by_hand(0.0, 0.5, Vec3::ZERO, 0.0)
    );
    // Frame 2: the colour halfway; the radius 1/119 of the way.
    assert_eq!(
        animated.frame(2).unwrap(),
        by_hand(
            0.0,
            0.5 + (1.0 - 0.5) * (1.0 / 119.0),
            Vec3::new(0.5, 0.25, 0.125),
            0.71875
        )
    );
    // Frame 16: the camera halfway between its keys; the light past its last key.
    assert_eq!(
        animated.frame(16).unwrap(),
        by_hand(
            5.0,
            0.5 + 0.5 * (15.0 / 119.0),
            Vec3::new(1.0, 0.5, 0.25),
            12.0
        )
    );
    // Frame 7: the light between inner keys of a straight line stays on it.
    assert_eq!(animated.frame(7).unwrap().lights[1].position.x, 6.0);
    // Frame 120: the last keys.
    assert_eq!(
        animated.frame(120).unwrap(),
        by_hand(10.0, 1.0, Vec3::new(1.0, 0.5, 0.25), 12.0)
    );
    // Without a frame, an animated scene is its frame 1; the static part is kept.
    assert_eq!(parse_scene(&text).unwrap(), animated.frame(1).unwrap());
    assert_eq!(animated.base.objects[2].material, crate::Material::Checker);
    let AnimatedScene { base, .. } = animated;
    assert_eq!(
        base.objects[1].shape,
        Shape::Sphere {
            center: Vec3::new(3.0, 0.0, 0.0),
            radius: 1.0
        }
    );
}

#[test]
fn the_example_animations_load_and_every_frame_is_a_scene() {
    for (text, frames) in [
        (include_str!("../../../../scenes/seed-orbit.json"), 121),
        (include_str!("../../../../scenes/moving-spheres.json"), 48),
    ] {
        let a = parse_animated(text).unwrap();
        assert_eq!(a.frame_count(), frames);
        for k in 1..=u64::from(frames) {
            let frame = a.frame(k).unwrap();
            // Each frame is a static scene that reads back as itself.
            if let Ok(json) = frame.to_json() {
                assert_eq!(parse_scene(&json).unwrap(), frame, "frame {k}");
            }
        }
    }
    // The orbit comes back to where it started, on the circle at its keys.
    let orbit = parse_animated(include_str!("../../../../scenes/seed-orbit.json")).unwrap();
    assert_eq!(orbit.frame(1).unwrap(), orbit.frame(121).unwrap());
    assert_eq!(orbit.frame(1).unwrap(), orbit.base);
    let p = orbit.frame(31).unwrap().camera.position;
    assert_eq!(p, Vec3::new(-3.5, 1.5, 0.0));
}

#[test]
fn error_animation_not_an_object() {
    assert_eq!(
        error_of(&scene("[]")),
        "animation: expected an object, got an array"
    );
}

#[test]
fn error_unknown_key() {
    assert_eq!(
        error_of(&scene(r#"{"frames": 2, "loop": true}"#)),
        "animation.loop: unknown key (expected one of: frames, fps, tracks)"
    );
}

#[test]
fn error_frames_missing_or_out_of_range() {
    assert_eq!(
        error_of(&scene(r#"{"fps": 24}"#)),
        "animation: missing key \"frames\""
    );
    assert_eq!(
        error_of(&scene(r#"{"frames": 0}"#)),
        "animation.frames: must be between 1 and 100000, got 0"
    );
    assert_eq!(
        error_of(&scene(r#"{"frames": 100001}"#)),
        "animation.frames: must be between 1 and 100000, got 100001"
    );
    assert_eq!(
        error_of(&scene(r#"{"frames": 2.5}"#)),
        "animation.frames: expected a whole number >= 0, got 2.5"
    );
}

#[test]
fn error_fps_not_positive() {
    assert_eq!(
        error_of(&scene(r#"{"frames": 2, "fps": 0}"#)),
        "animation.fps: must be > 0, got 0"
    );
    assert_eq!(
        error_of(&scene(r#"{"frames": 2, "fps": "24"}"#)),
        "animation.fps: expected a number, got a string"
    );
}

#[test]
fn error_too_many_tracks() {
    let many = vec![RADIUS; super::MAX_TRACKS + 1].join(", ");
    assert_eq!(
        error_of(&tracks(&many)),
        format!(
            "animation.tracks: at most {} tracks, got {}",
            super::MAX_TRACKS,
            super::MAX_TRACKS + 1
        )
    );
}

#[test]
fn error_too_many_track_frames() {
    let text = scene(&format!(
        r#"{{"frames": 100000, "tracks": [{}]}}"#,
        vec![RADIUS; 101].join(", ")
    ));
    assert_eq!(
        error_of(&text),
        "animation.tracks: 101 tracks of 100000 frames are 10100000 values to check, at \
             most 10000000: use fewer tracks or frames"
    );
}

#[test]
fn error_key_frame_beyond_the_frames() {
    assert_eq!(
        error_of(&tracks(&format!(
            r#"{RADIUS}, {RADIUS}, {{"target": "camera.look_at", "keys": [{{"frame": 1, "value": "0 0 0"}}, {{"frame": 130, "value": "0 0 1"}}]}}"#
        ))),
        // The duplicate comes first: tracks are read in order.
        "animation.tracks[1].target: objects[1].radius is already animated by tracks[0]"
    );
    assert_eq!(
        error_of(&tracks(
            r#"{"target": "camera.look_at", "keys": [{"frame": 1, "value": "0 0 0"}, {"frame": 130, "value": "0 0 1"}]}"#
        )),
        "animation.tracks[0].keys[1].frame: 130 is beyond the 120 frames"
    );
}

#[test]
fn error_key_frame_zero() {
    assert_eq!(
        error_of(&tracks(
            r#"{"target": "camera.look_at", "keys": [{"frame": 0, "value": "0 0 0"}]}"#
        )),
        "animation.tracks[0].keys[0].frame: frames are numbered from 1, got 0"
    );
}

#[test]
fn error_key_frames_not_increasing() {
    assert_eq!(
        error_of(&tracks(
            r#"{"target": "camera.look_at", "keys": [{"frame": 1, "value": "0 0 0"}, {"frame": 61, "value": "0 0 1"}, {"frame": 40, "value": "0 0 2"}]}"#
        )),
        "animation.tracks[0].keys[2].frame: 40 does not come after the previous key's frame 61"
    );
    assert_eq!(
        error_of(&tracks(
            r#"{"target": "camera.look_at", "keys": [{"frame": 5, "value": "0 0 0"}, {"frame": 5, "value": "0 0 1"}]}"#
        )),
        "animation.tracks[0].keys[1].frame: 5 does not come after the previous key's frame 5"
    );
}

#[test]
fn error_no_keys() {
    assert_eq!(
        error_of(&tracks(r#"{"target": "camera.look_at", "keys": []}"#)),
        "animation.tracks[0].keys: must hold at least one key"
    );
    assert_eq!(
        error_of(&tracks(r#"{"target": "camera.look_at"}"#)),
        "animation.tracks[0]: missing key \"keys\""
    );
    assert_eq!(
        error_of(&tracks(
            r#"{"target": "camera.look_at", "keys": [{"frame": 1, "value": "0 0 0", "ease": 1}]}"#
        )),
        "animation.tracks[0].keys[0].ease: unknown key (expected one of: frame, value)"
    );
}

#[test]
fn error_unknown_object_or_light() {
    assert_eq!(
        error_of(&tracks(
            r#"{"target": "objects[3].radius", "keys": [{"frame": 1, "value": 1}]}"#
        )),
        "animation.tracks[0].target: there is no objects[3]: the scene has 3 objects"
    );
    assert_eq!(
        error_of(&tracks(
            r#"{"target": "lights[2].position", "keys": [{"frame": 1, "value": "0 0 0"}]}"#
        )),
        "animation.tracks[0].target: there is no lights[2]: the scene has 2 lights"
    );
}

#[test]
fn error_unknown_target() {
    assert_eq!(
        error_of(&tracks(
            r#"{"target": "sun.position", "keys": [{"frame": 1, "value": "0 0 0"}]}"#
        )),
        "animation.tracks[0].target: unknown target \"sun.position\" (expected camera.position, camera.look_at, camera.up, camera.fov, objects[N].FIELD, objects[N].transform.PART or lights[N].FIELD)"
    );
    assert_eq!(
        error_of(&tracks(
            r#"{"target": "objects[-1].radius", "keys": [{"frame": 1, "value": 1}]}"#
        )),
        "animation.tracks[0].target: unknown target \"objects[-1].radius\" (expected camera.position, camera.look_at, camera.up, camera.fov, objects[N].FIELD, objects[N].transform.PART or lights[N].FIELD)"
    );
    assert_eq!(
        error_of(&tracks(
            r#"{"target": "camera.zoom", "keys": [{"frame": 1, "value": 1}]}"#
        )),
        "animation.tracks[0].target: the camera has no field \"zoom\" to animate (expected position, look_at, up or fov)"
    );
}

#[test]
fn error_field_the_object_does_not_have() {
    assert_eq!(
        error_of(&tracks(
            r#"{"target": "objects[2].radius", "keys": [{"frame": 1, "value": 1}]}"#
        )),
        "animation.tracks[0].target: objects[2] is a plane, which has no field \"radius\" to animate (expected normal, distance or color)"
    );
    assert_eq!(
        error_of(&tracks(
            r#"{"target": "objects[0].normal", "keys": [{"frame": 1, "value": "0 1 0"}]}"#
        )),
        "animation.tracks[0].target: objects[0] is a sphere, which has no field \"normal\" to animate (expected center, radius or color)"
    );
    assert_eq!(
        error_of(&tracks(
            r#"{"target": "lights[0].radius", "keys": [{"frame": 1, "value": 1}]}"#
        )),
        "animation.tracks[0].target: lights[0] has no field \"radius\" to animate (expected position or color)"
    );
}

#[test]
fn error_wrong_value_type() {
    assert_eq!(
        error_of(&tracks(
            r#"{"target": "objects[0].radius", "keys": [{"frame": 1, "value": "1 2 3"}]}"#
        )),
        "animation.tracks[0].keys[0].value: expected a number, got a string"
    );
    assert_eq!(
        error_of(&tracks(
            r#"{"target": "objects[0].center", "keys": [{"frame": 1, "value": 2}]}"#
        )),
        "animation.tracks[0].keys[0].value: expected 3 numbers as a string or an array, got a number"
    );
    // A colour track animates r g b only: the material (special) stays the scene's.
    assert_eq!(
        error_of(&tracks(
            r#"{"target": "objects[0].color", "keys": [{"frame": 1, "value": "1 1 1 0.5"}]}"#
        )),
        "animation.tracks[0].keys[0].value: expected 3 numbers, got 4"
    );
}

#[test]
fn error_unknown_interpolation() {
    assert_eq!(
        error_of(&tracks(
            r#"{"target": "objects[0].radius", "interpolation": "cubic", "keys": [{"frame": 1, "value": 1}]}"#
        )),
        "animation.tracks[0].interpolation: unknown interpolation \"cubic\" (expected \"linear\" or \"catmull-rom\")"
    );
}

#[test]
fn error_radius_not_positive_at_some_frame() {
    // Catmull-Rom overshoots below zero between keys that are all positive.
    assert_eq!(
        error_of(&tracks(
            r#"{"target": "objects[0].radius", "interpolation": "catmull-rom",
                    "keys": [{"frame": 1, "value": 10}, {"frame": 2, "value": 10}, {"frame": 3, "value": 0.01}, {"frame": 100, "value": 0.01}]}"#
        )),
        "animation.tracks[0]: at frame 4, objects[0].radius must be > 0, got -0.08984777926475086"
    );
    assert_eq!(
        error_of(&tracks(
            r#"{"target": "objects[1].radius", "keys": [{"frame": 1, "value": 1}, {"frame": 3, "value": -1}]}"#
        )),
        "animation.tracks[0]: at frame 2, objects[1].radius must be > 0, got 0"
    );
}

#[test]
fn error_zero_normal_at_some_frame() {
    assert_eq!(
        error_of(&tracks(
            r#"{"target": "objects[2].normal", "keys": [{"frame": 1, "value": "0 1 0"}, {"frame": 11, "value": "0 -1 0"}]}"#
        )),
        "animation.tracks[0]: at frame 6, objects[2].normal must be a non-zero vector of finite length"
    );
}

#[test]
fn error_negative_colour_at_some_frame() {
    assert_eq!(
        error_of(&tracks(
            r#"{"target": "lights[1].color", "keys": [{"frame": 1, "value": "1 1 1"}, {"frame": 2, "value": "-1 1 1"}]}"#
        )),
        "animation.tracks[0]: at frame 2, lights[1].color must have r, g and b >= 0, got -1"
    );
}

#[test]
fn error_not_finite_at_some_frame() {
    assert_eq!(
        error_of(&tracks(
            r#"{"target": "objects[0].center", "keys": [{"frame": 1, "value": "-1e308 0 0"}, {"frame": 3, "value": "1e308 0 0"}]}"#
        )),
        "animation.tracks[0]: at frame 2, objects[0].center is not finite: inf 0 0"
    );
    assert_eq!(
        error_of(&tracks(
            r#"{"target": "objects[2].distance", "keys": [{"frame": 1, "value": -1e308}, {"frame": 5, "value": 1.7e308}]}"#
        )),
        "animation.tracks[0]: at frame 2, objects[2].distance is not a finite number: inf"
    );
}

#[test]
fn error_camera_vertical_at_some_frame() {
    // Default camera at (3, 1.5, -4); the look-at point passes above it at frame 31.
    assert_eq!(
        error_of(&tracks(
            r#"{"target": "camera.look_at", "keys": [{"frame": 1, "value": "3 5 -34"}, {"frame": 61, "value": "3 5 26"}]}"#
        )),
        "animation: at frame 31, the camera's viewing direction (look_at - position) is parallel to the world up axis (0 1 0)"
    );
    assert_eq!(
        error_of(&tracks(
            r#"{"target": "camera.position", "keys": [{"frame": 1, "value": "0 0 -2"}, {"frame": 3, "value": "0 0 2"}]}"#
        )),
        "animation: at frame 2, camera.look_at equals camera.position"
    );
    assert_eq!(
        error_of(&tracks(
            r#"{"target": "camera.position", "keys": [{"frame": 7, "value": "1e-310 0 0"}]}"#
        )),
        "animation: at frame 1, camera.look_at is too far from or too close to camera.position to define a direction"
    );
}

/// A directory of the system's temporary one holding `tri.obj`, one triangle, for
/// the scenes of [`meshes`]; removed when dropped, even by a failing test.
struct MeshDir(std::path::PathBuf);

impl MeshDir {
    fn new(test: &str) -> Self {
        let dir =
            std::env::temp_dir().join(format!("tessera-animation-{}-{test}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::write(dir.join("tri.obj"), "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n").unwrap();
        MeshDir(dir)
    }

    fn files(&self) -> MeshFiles {
        MeshFiles::beside(&self.0)
    }

    fn parse(&self, text: &str) -> AnimatedScene {
        parse_animated_with(text, &self.files()).unwrap()
    }

    /// The error, the same when the scene is read as its frame 1.
    fn error_of(&self, text: &str) -> String {
        let e = parse_animated_with(text, &self.files())
            .unwrap_err()
            .to_string();
        assert_eq!(
            parse_scene_with(text, &self.files())
                .unwrap_err()
                .to_string(),
            e
        );
        assert!(!e.contains('\n'), "{e}");
        e
    }
}

impl Drop for MeshDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// A sphere, a box, a mesh without a transform (objects[2]) and one with `transform`
/// (objects[3]), animated by `tracks` over 120 frames.
fn meshes(transform: &str, tracks: &str) -> String {
    format!(
        r#"{{"lights": [{{"position": "-7 10 -10", "color": "1 1 1"}}],
               "objects": [
                 {{"type": "sphere", "center": "0 0 0", "radius": 1, "color": "0.5 1 0.5 0"}},
                 {{"type": "box", "min": "-1 -1 -1", "max": "1 1 1", "color": "1 1 1 0"}},
                 {{"type": "mesh", "file": "tri.obj", "color": "1 0 0 0"}},
                 {{"type": "mesh", "file": "tri.obj", "transform": {transform}, "color": "0 0 1 0"}}],
               "image": {{"width": 32, "height": 24}},
               "animation": {{"frames": 120, "tracks": [{tracks}]}}}}"#
    )
}

fn spec_of(scene: &crate::Scene, i: usize) -> (TransformSpec, crate::transform::Affine) {
    match &scene.objects[i].shape {
        Shape::Mesh(mesh) => (mesh.spec, mesh.transform),
        other => panic!("not a mesh: {other:?}"),
    }
}

fn parts(scale: Vec3, rotate: Vec3, translate: Vec3) -> TransformSpec {
    TransformSpec::Parts {
        scale,
        rotate,
        translate,
    }
}

#[test]
fn a_mesh_transform_is_interpolated_and_mapped_at_frame_k() {
    let dir = MeshDir::new("parts");
    let animated = dir.parse(&meshes(
        r#"{"scale": 2, "rotate": "0 0 30"}"#,
        r#"{"target": "objects[2].transform.translate", "keys": [{"frame": 1, "value": "0 0 0"}, {"frame": 11, "value": [10, 0, -5]}]},
               {"target": "objects[3].transform.scale", "keys": [{"frame": 1, "value": 2}, {"frame": 11, "value": "2 4 2"}]},
               {"target": "objects[3].transform.rotate", "keys": [{"frame": 3, "value": "0 0 30"}, {"frame": 7, "value": "0 90 30"}]}"#,
    ));
    let frame = animated.frame(5).unwrap();
    // A mesh without a transform animates from the identity parts.
    let expected = parts(
        Vec3::new(1.0, 1.0, 1.0),
        Vec3::ZERO,
        Vec3::new(4.0, 0.0, -2.0),
    );
    assert_eq!(spec_of(&frame, 2), (expected, expected.affine().unwrap()));
    // The untouched parts keep the file's values; a number scale is all three axes.
    let expected = parts(
        Vec3::new(2.0, 2.8, 2.0),
        Vec3::new(0.0, 45.0, 30.0),
        Vec3::ZERO,
    );
    assert_eq!(spec_of(&frame, 3), (expected, expected.affine().unwrap()));
    // Before the first key and from the last key on, the end keys hold.
    assert_eq!(
        spec_of(&animated.frame(1).unwrap(), 3),
        spec_of(&animated.base, 3)
    );
    let last = animated.frame(120).unwrap();
    let expected = parts(
        Vec3::new(2.0, 4.0, 2.0),
        Vec3::new(0.0, 90.0, 30.0),
        Vec3::ZERO,
    );
    assert_eq!(spec_of(&last, 3), (expected, expected.affine().unwrap()));
    // The frame's transform is the one it renders with: the vertex (1, 0, 0) scaled
    // by 2 and turned a quarter about y lands on (0, 0, -2), exactly.
    assert_eq!(spec_of(&last, 3).1.point([1.0, 0.0, 0.0]).z, -2.0);
    // A frame is a static scene: written back, it reads back the same.
    let json = frame.to_json().unwrap();
    assert_eq!(parse_scene_with(&json, &dir.files()).unwrap(), frame);
    // The base is the file's.
    assert_eq!(spec_of(&animated.base, 2).0, TransformSpec::IDENTITY);
}

#[test]
fn a_mesh_matrix_is_interpolated_number_by_number() {
    let dir = MeshDir::new("matrix");
    let animated = dir.parse(&meshes(
        r#"{"matrix": "1 0 0 0 0 1 0 0 0 0 1 0"}"#,
        r#"{"target": "objects[2].transform.matrix", "keys": [{"frame": 1, "value": "1 0 0 0 0 1 0 0 0 0 1 0"}, {"frame": 3, "value": [3, 0, 0, 4, 0, 1, 0, 0, 0, 0, 1, -2]}]},
               {"target": "objects[3].transform.matrix", "keys": [{"frame": 2, "value": "0 0 2 1 0 3 0 2 4 0 0 3"}]}"#,
    ));
    let frame = animated.frame(2).unwrap();
    let (spec, affine) = spec_of(&frame, 2);
    assert_eq!(
        spec,
        TransformSpec::Matrix([2.0, 0.0, 0.0, 2.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, -1.0])
    );
    assert_eq!(affine.point([1.0, 1.0, 1.0]), Vec3::new(4.0, 1.0, 0.0));
    let (_, affine) = spec_of(&animated.frame(1).unwrap(), 3);
    assert_eq!(affine.point([1.0, 1.0, 1.0]), Vec3::new(3.0, 5.0, 7.0));
}

#[test]
fn error_transform_on_an_object_that_is_not_a_mesh() {
    let dir = MeshDir::new("not-a-mesh");
    let one = |target: &str, value: &str| {
        dir.error_of(&meshes(
            "{}",
            &format!(r#"{{"target": "{target}", "keys": [{{"frame": 1, "value": {value}}}]}}"#),
        ))
    };
    assert_eq!(
        one("objects[0].transform.scale", "2"),
        "animation.tracks[0].target: objects[0] is a sphere, which has no field \"transform.scale\" to animate (expected center, radius or color)"
    );
    assert_eq!(
        one("objects[1].transform.translate", r#""0 1 0""#),
        "animation.tracks[0].target: objects[1] is a box, which has no field \"transform.translate\" to animate (expected color)"
    );
    assert_eq!(
        one("objects[2].transform.shear", r#""0 1 0""#),
        "animation.tracks[0].target: objects[2] is a mesh, which has no field \"transform.shear\" to animate (expected transform.translate, transform.rotate, transform.scale, transform.matrix or color)"
    );
    assert_eq!(
        one("objects[2].transform", r#""0 1 0""#),
        "animation.tracks[0].target: objects[2] is a mesh, which has no field \"transform\" to animate (expected transform.translate, transform.rotate, transform.scale, transform.matrix or color)"
    );
    assert_eq!(
        one("objects[2].transform.matrix", r#""1 0 0 0 0 1 0 0 0 0 1""#),
        "animation.tracks[0].keys[0].value: expected 12 numbers (a 3 x 4 matrix, row by row), got 11"
    );
    assert_eq!(
        one("objects[2].transform.rotate", "90"),
        "animation.tracks[0].keys[0].value: expected 3 numbers as a string or an array, got a number"
    );
}

#[test]
fn error_matrix_combined_with_parts() {
    let dir = MeshDir::new("mix");
    const MATRIX: &str = r#"{"target": "objects[3].transform.matrix", "keys": [{"frame": 1, "value": "1 0 0 0 0 1 0 0 0 0 1 0"}]}"#;
    assert_eq!(
        dir.error_of(&meshes(r#"{"rotate": "0 90 0"}"#, MATRIX)),
        "animation.tracks[0].target: objects[3].transform.matrix cannot be animated: the mesh's transform gives scale, rotate or translate, which cannot be combined with matrix"
    );
    assert_eq!(
        dir.error_of(&meshes(
            r#"{"matrix": "1 0 0 0 0 1 0 0 0 0 1 0"}"#,
            r#"{"target": "objects[3].transform.scale", "keys": [{"frame": 1, "value": 2}]}"#
        )),
        "animation.tracks[0].target: objects[3].transform.scale cannot be animated: the mesh's transform is a matrix, which cannot be combined with scale (animate objects[3].transform.matrix instead)"
    );
    assert_eq!(
        dir.error_of(&meshes(
            "{}",
            &format!(
                r#"{{"target": "objects[3].transform.rotate", "keys": [{{"frame": 1, "value": "0 0 0"}}]}}, {MATRIX}"#
            )
        )),
        "animation.tracks[1].target: objects[3].transform.matrix cannot be combined with objects[3].transform.rotate, animated by tracks[0]"
    );
    assert_eq!(
        dir.error_of(&meshes(
            "{}",
            &format!(
                r#"{MATRIX}, {{"target": "objects[3].transform.translate", "keys": [{{"frame": 1, "value": "0 0 0"}}]}}"#
            )
        )),
        "animation.tracks[1].target: objects[3].transform.translate cannot be combined with objects[3].transform.matrix, animated by tracks[0]"
    );
    // Identity parts (or none) say nothing a matrix contradicts.
    dir.parse(&meshes(r#"{"scale": 1}"#, MATRIX));
    dir.parse(&meshes("{}", MATRIX));
}

#[test]
fn error_zero_scale_at_some_frame() {
    let dir = MeshDir::new("zero-scale");
    assert_eq!(
        dir.error_of(&meshes(
            "{}",
            r#"{"target": "objects[2].transform.scale", "keys": [{"frame": 1, "value": "1 1 1"}, {"frame": 73, "value": "1 -1 1"}]}"#
        )),
        "animation: at frame 37, objects[2].transform: scale must have no zero component, got 1 0 1"
    );
    // The scale's parts come from the file where no track gives them.
    assert_eq!(
        dir.error_of(&meshes(
            r#"{"scale": "3 2 1", "translate": "0 0 5"}"#,
            r#"{"target": "objects[3].transform.translate", "keys": [{"frame": 1, "value": "0 0 5"}]},
                   {"target": "objects[3].transform.scale", "keys": [{"frame": 1, "value": 2}, {"frame": 5, "value": -2}]}"#
        )),
        "animation: at frame 3, objects[3].transform: scale must have no zero component, got 0 0 0"
    );
}

#[test]
fn error_singular_or_infinite_matrix_at_some_frame() {
    let dir = MeshDir::new("singular");
    assert_eq!(
        dir.error_of(&meshes(
            "{}",
            r#"{"target": "objects[2].transform.matrix", "keys": [{"frame": 1, "value": "1 0 0 0 0 1 0 0 0 0 1 0"}, {"frame": 73, "value": "-1 0 0 0 0 1 0 0 0 0 1 0"}]}"#
        )),
        "animation: at frame 37, objects[2].transform: the matrix is singular (det(A) = 0): it flattens the mesh"
    );
    assert_eq!(
        dir.error_of(&meshes(
            "{}",
            r#"{"target": "objects[2].transform.matrix", "keys": [{"frame": 1, "value": "1 0 0 -1e308 0 1 0 0 0 0 1 0"}, {"frame": 3, "value": "1 0 0 1e308 0 1 0 0 0 0 1 0"}]}"#
        )),
        "animation.tracks[0]: at frame 2, objects[2].transform.matrix is not finite: 1 0 0 inf 0 1 0 0 0 0 1 0"
    );
}

#[test]
fn the_camera_fov_and_up_are_animated() {
    let animated = parse_animated(&tracks(
        r#"{"target": "camera.fov", "keys": [{"frame": 1, "value": 40}, {"frame": 11, "value": 60}]},
               {"target": "camera.up", "keys": [{"frame": 1, "value": "0 1 0"}, {"frame": 3, "value": [1, 1, 0]}]}"#,
    ))
    .unwrap();
    assert_eq!(animated.base.camera, CameraSpec::default());
    let frame = animated.frame(2).unwrap();
    assert_eq!(frame.camera.fov, Some(42.0));
    assert_eq!(frame.camera.up, Vec3::new(0.5, 1.0, 0.0));
    let frame = animated.frame(6).unwrap();
    assert_eq!(frame.camera.fov, Some(50.0));
    assert_eq!(frame.camera.up, Vec3::new(1.0, 1.0, 0.0));
    assert_eq!(parse_scene(&frame.to_json().unwrap()).unwrap(), frame);
}

#[test]
fn error_fov_out_of_range_at_some_frame() {
    assert_eq!(
        error_of(&tracks(
            r#"{"target": "camera.fov", "keys": [{"frame": 1, "value": 100}, {"frame": 3, "value": 300}]}"#
        )),
        "animation.tracks[0]: at frame 2, camera.fov must be between 0 and 180 degrees (exclusive), got 200"
    );
    assert_eq!(
        error_of(&tracks(
            r#"{"target": "camera.fov", "keys": [{"frame": 1, "value": 10}, {"frame": 3, "value": -10}]}"#
        )),
        "animation.tracks[0]: at frame 2, camera.fov must be between 0 and 180 degrees (exclusive), got 0"
    );
    assert_eq!(
        error_of(&tracks(
            r#"{"target": "camera.fov", "keys": [{"frame": 1, "value": "60"}]}"#
        )),
        "animation.tracks[0].keys[0].value: expected a number, got a string"
    );
}

#[test]
fn error_up_parallel_or_zero_at_some_frame() {
    // The camera looks along +z from frame 1; the up vector passes through 0 0 1.
    assert_eq!(
        error_of(&tracks(
            r#"{"target": "camera.position", "keys": [{"frame": 1, "value": "0 0 -5"}]},
                   {"target": "camera.up", "keys": [{"frame": 1, "value": "0 1 0"}, {"frame": 3, "value": "0 -1 2"}]}"#
        )),
        "animation: at frame 2, the camera's viewing direction (look_at - position) is parallel to the up vector (0 0 1)"
    );
    assert_eq!(
        error_of(&tracks(
            r#"{"target": "camera.up", "keys": [{"frame": 1, "value": "0 1 0"}, {"frame": 3, "value": "0 -1 0"}]}"#
        )),
        "animation.tracks[0]: at frame 2, camera.up must be a non-zero vector of finite length"
    );
}
