//! Scenes of section 8's shapes, written into a test's directory: triangles and boxes
//! (which need no file), and a mesh read from an OBJ file beside its scene.

use std::path::{Path, PathBuf};

/// A cube from -1 to 1 on every axis, as 12 triangles (each face split in two).
pub const CUBE_OBJ: &str = "\
# a cube of 12 triangles
v -1 -1 -1
v 1 -1 -1
v 1 1 -1
v -1 1 -1
v -1 -1 1
v 1 -1 1
v 1 1 1
v -1 1 1
f 1 4 3
f 1 3 2
f 5 6 7
f 5 7 8
f 1 2 6
f 1 6 5
f 4 8 7
f 4 7 3
f 1 5 8
f 1 8 4
f 2 3 7
f 2 7 6
";

/// The seed's lights and floor around `objects` (JSON texts).
fn scene(objects: &[&str]) -> String {
    format!(
        r#"{{
  "lights": [
    {{"position": "-7 10 -10", "color": "1 1 1"}},
    {{"position": "7 10 10", "color": "1 1 1"}}
  ],
  "objects": [
    {},
    {{"type": "plan", "normal": "0 1 0", "distance": -1, "color": "0.5 0.25 0.2 2"}}
  ]
}}
"#,
        objects.join(",\n    ")
    )
}

/// `DIR/shapes.json`: triangles (a pyramid and one alone), boxes and a mirror sphere,
/// all in front of the seed's camera.
pub fn write_shapes_scene(dir: &Path) -> PathBuf {
    let text = scene(&[
        r#"{"type": "box", "min": "-2.5 -1 -0.5", "max": "-1.5 0.5 0.5", "color": "0.2 0.4 0.9 0.3"}"#,
        r#"{"type": "box", "min": "1 -1 1", "max": "4 -0.6 2", "color": "0.9 0.8 0.2 0"}"#,
        r#"{"type": "triangle", "vertices": ["-0.8 -1 -0.8", "0.8 -1 -0.8", "0 0.6 0"], "color": "0.9 0.3 0.3 0"}"#,
        r#"{"type": "triangle", "vertices": ["0.8 -1 -0.8", "0.8 -1 0.8", "0 0.6 0"], "color": "0.3 0.9 0.3 0"}"#,
        r#"{"type": "triangle", "vertices": ["-0.8 -1 0.8", "-0.8 -1 -0.8", "0 0.6 0"], "color": "0.3 0.3 0.9 0"}"#,
        r#"{"type": "triangle", "vertices": ["1.5 1.5 0", "3.5 1.2 0.5", "2.5 2.8 -0.5"], "color": "1 1 1 0.5"}"#,
        r#"{"type": "sphere", "center": "3 0 0", "radius": 1, "color": "0.5 0.5 0.5 0.6"}"#,
    ]);
    let path = dir.join("shapes.json");
    std::fs::write(&path, text).expect("cannot write the scene");
    path
}

/// `DIR/cube.obj` ([`CUBE_OBJ`]) and `DIR/cube.json`, a scene of two instances of it
/// (one rotated, one smooth-shaded and scaled) beside a mirror sphere, naming the file
/// as `cube.obj`.
pub fn write_mesh_scene(dir: &Path) -> PathBuf {
    std::fs::write(dir.join("cube.obj"), CUBE_OBJ).expect("cannot write the mesh");
    let text = scene(&[
        r#"{"type": "sphere", "center": "3 0 0", "radius": 1, "color": "0.5 0.5 0.5 0.6"}"#,
        r#"{"type": "mesh", "file": "cube.obj", "color": "0.5 1 0.5 0.3",
       "transform": {"scale": 0.7, "rotate": "0 30 0", "translate": "0 -0.3 0"}}"#,
        r#"{"type": "mesh", "file": "cube.obj", "color": "0.9 0.5 0.2 0", "shading": "smooth",
       "transform": {"scale": "0.4 0.8 0.4", "translate": "-2.2 -0.2 1"}}"#,
    ]);
    let path = dir.join("cube.json");
    std::fs::write(&path, text).expect("cannot write the scene");
    path
}

/// What a coordinator answers when [`write_mesh_scene`]'s scene reaches it without its
/// files (a job naming none, or a studio edit): the renderer's own line.
pub const LOADER_REFUSAL: &str = "objects[1].file: a mesh file cannot be read here: the \
    scene names a mesh file but no files were given with it";
