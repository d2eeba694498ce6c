//! `tessera render` of scenes with mesh objects: the mesh files are read relative to the
//! scene file (or where an absolute name says), whatever the current directory, and the
//! image is the renderer's own; a mesh file that is missing or malformed stops the
//! render with exactly one line on stderr naming the object (`objects[N].file`), the
//! file and, where the format has one, its line or record, and no image is written.

use std::path::Path;
use std::time::Duration;

use render::{parse_scene_with, render_frame, MeshFiles, Tracer};
use tempfile::TempDir;

use crate::support::{decode_rgb8, entries, path_str, shared, tessera, Run};

/// Every render here is tiny; a run this long means the binary hangs.
const TIMEOUT: Duration = Duration::from_secs(60);

/// A cube of side 1 standing on the floor, its faces quads (split as fans).
const CUBE_OBJ: &str = "# a cube\nv -0.5 0 -0.5\nv 0.5 0 -0.5\nv 0.5 1 -0.5\nv -0.5 1 -0.5\n\
                        v -0.5 0 0.5\nv 0.5 0 0.5\nv 0.5 1 0.5\nv -0.5 1 0.5\n\
                        f 1 2 3 4\nf 5 8 7 6\nf 1 5 6 2\nf 4 3 7 8\nf 1 4 8 5\nf 2 6 7 3\n";

/// A tetrahedron in ASCII PLY.
const TETRAHEDRON_PLY: &str = "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\n\
                               property float y\nproperty float z\nelement face 4\n\
                               property list uchar int vertex_indices\nend_header\n\
                               0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 2 1\n3 0 1 3\n3 0 3 2\n3 1 2 3\n";

/// A scene of a sphere and a floor, then the mesh objects given (JSON, comma-separated):
/// the first mesh is `objects[2]`.
fn scene(meshes: &str) -> String {
    format!(
        r#"{{"camera": {{"position": "2 2 -4", "look_at": "0 0.5 0"}},
  "image": {{"width": 80, "height": 60, "aa": 2}},
  "lights": [{{"position": "4 6 -5", "color": "1 1 1"}}],
  "objects": [
    {{"type": "sphere", "center": "-1.5 0.5 1", "radius": 0.5, "color": "0.9 0.9 0.9 0.5"}},
    {{"type": "plane", "normal": "0 1 0", "distance": 0, "color": "1 1 1 2"}},
    {meshes}
  ]}}"#
    )
}

/// A directory `scenes/` holding `scene.json` of `text` and `models/` with `files`.
fn scene_dir(text: &str, files: &[(&str, &[u8])]) -> TempDir {
    let dir = TempDir::new().expect("cannot create a temporary directory");
    let models = dir.path().join("scenes/models");
    std::fs::create_dir_all(&models).unwrap();
    std::fs::write(dir.path().join("scenes/scene.json"), text).unwrap();
    for (name, bytes) in files {
        std::fs::write(models.join(name), bytes).unwrap();
    }
    dir
}

/// `tessera render scenes/scene.json -o out.png`, run in `dir`.
fn render_in(dir: &Path) -> Run {
    tessera(
        dir,
        &["render", "scenes/scene.json", "-o", "out.png"],
        TIMEOUT,
    )
}

/// The run failed with exactly one `error: ` line, which it returns, and wrote nothing:
/// `dir` holds `scenes/` alone, and `scenes/` what it held before.
fn one_line_and_no_image(run: &Run, dir: &Path, scene_entries: &[String]) -> String {
    assert!(
        !run.status.success(),
        "the render succeeded: stderr {:?}",
        run.stderr
    );
    let lines: Vec<&str> = run.stderr.lines().collect();
    assert_eq!(lines.len(), 1, "one line on stderr, got {:?}", run.stderr);
    assert!(lines[0].starts_with("error: "), "{:?}", lines[0]);
    assert_eq!(run.stdout, "", "nothing on stdout");
    assert_eq!(entries(dir), ["scenes"], "no image, no temporary file");
    assert_eq!(entries(&dir.join("scenes")), scene_entries);
    lines[0].to_owned()
}

#[test]
fn mesh_files_are_read_beside_the_scene_file_and_give_the_renderers_bytes() {
    let _turn = shared();
    let elsewhere = TempDir::new().unwrap();
    let tetrahedron = elsewhere.path().join("tetrahedron.ply");
    std::fs::write(&tetrahedron, TETRAHEDRON_PLY).unwrap();
    let meshes = format!(
        r#"{{"type": "mesh", "file": "models/cube.obj", "color": "0.8 0.5 0.3 0",
      "transform": {{"rotate": "0 30 0", "translate": "0.6 0 0"}}}},
    {{"type": "mesh", "file": {}, "color": "0.3 0.6 0.9 0.3", "shading": "smooth",
      "transform": {{"scale": 0.8, "translate": "-0.9 0 -0.8"}}}}"#,
        serde_json::to_string(path_str(&tetrahedron)).unwrap()
    );
    let text = scene(&meshes);
    let dir = scene_dir(&text, &[("cube.obj", CUBE_OBJ.as_bytes())]);
    // Run from the directory above the scene's: the names are not the current
    // directory's.
    let run = render_in(dir.path());
    assert!(run.status.success(), "stderr: {}", run.stderr);
    let png = decode_rgb8(&dir.path().join("out.png"));
    let scene = parse_scene_with(&text, &MeshFiles::beside(dir.path().join("scenes"))).unwrap();
    let expected = render_frame(&Tracer::new(&scene, scene.settings), 16, &|_| {}).image;
    assert_eq!(png.dimensions(), (80, 60));
    assert!(
        png.as_raw() == expected.rgb,
        "the PNG is not the renderer's image"
    );
    // The meshes show: a twentieth of the pixels are neither the floor's greys nor the
    // sky's black.
    let coloured = png
        .pixels()
        .filter(|p| p[0] != p[1] || p[1] != p[2])
        .count();
    assert!(
        coloured * 20 > 80 * 60,
        "only {coloured} pixels are neither grey nor black"
    );
}

#[test]
fn a_missing_mesh_file_is_named_in_one_line_and_no_image_is_written() {
    let _turn = shared();
    let text = scene(
        r#"{"type": "mesh", "file": "models/cube.obj", "color": "0.8 0.5 0.3 0"},
    {"type": "mesh", "file": "models/missing.obj", "color": "0.8 0.5 0.3 0"}"#,
    );
    let dir = scene_dir(&text, &[("cube.obj", CUBE_OBJ.as_bytes())]);
    let run = render_in(dir.path());
    let line = one_line_and_no_image(
        &run,
        dir.path(),
        &["models", "scene.json"].map(String::from),
    );
    assert!(
        line.starts_with("error: scenes/scene.json: objects[3].file: scenes/models/missing.obj: ")
            && line.contains("cannot read it"),
        "{line:?}"
    );
}

#[test]
fn a_malformed_mesh_file_is_named_with_its_line_or_record_and_no_image_is_written() {
    let _turn = shared();
    // A binary PLY cut in its second vertex: its record.
    let mut cut_ply = b"ply\nformat binary_little_endian 1.0\nelement vertex 3\n\
                        property float x\nproperty float y\nproperty float z\nelement face 1\n\
                        property list uchar int vertex_indices\nend_header\n"
        .to_vec();
    cut_ply.extend_from_slice(&[0; 12 + 5]);
    let cases: [(&str, &[u8], &str); 4] = [
        (
            "bad-number.obj",
            b"v 0 0 0\nv 1 0 0\n# a comment\nv 0 1 0\nv 0 1x 1\nf 1 2 3\n",
            "line 5: \"1x\" is not a finite number",
        ),
        (
            "bad-index.obj",
            b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nf 1 2 4\n",
            "line 5: vertex index 4 is out of range: the file has 3 vertices",
        ),
        (
            "cut.ply",
            &cut_ply,
            "record 2: vertex 2 of 3: the file ends before it",
        ),
        (
            "open.stl",
            b"solid x\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 0 0\n",
            "line 3: a loop never closed (`endloop`): the file is cut short",
        ),
    ];
    for (name, bytes, end) in cases {
        let text = scene(&format!(
            r#"{{"type": "mesh", "file": "models/cube.obj", "color": "0.8 0.5 0.3 0"}},
    {{"type": "mesh", "file": "models/cube.obj", "color": "0.8 0.5 0.3 0",
      "transform": {{"translate": "1 0 0"}}}},
    {{"type": "mesh", "file": "models/{name}", "color": "0.8 0.5 0.3 0"}}"#
        ));
        let dir = scene_dir(&text, &[("cube.obj", CUBE_OBJ.as_bytes()), (name, bytes)]);
        let run = render_in(dir.path());
        let line = one_line_and_no_image(
            &run,
            dir.path(),
            &["models", "scene.json"].map(String::from),
        );
        assert_eq!(
            line,
            format!("error: scenes/scene.json: objects[4].file: scenes/models/{name}: {end}"),
            "{name}"
        );
    }
}

#[test]
fn a_mesh_file_name_with_a_line_break_is_still_one_line() {
    let _turn = shared();
    // A JSON string may hold any character; the error quotes the name as a string
    // would be written, so that it stays one line.
    let text = scene(r#"{"type": "mesh", "file": "models/two\nlines.obj", "color": "1 1 1 0"}"#);
    let dir = scene_dir(&text, &[]);
    let run = render_in(dir.path());
    let line = one_line_and_no_image(
        &run,
        dir.path(),
        &["models", "scene.json"].map(String::from),
    );
    assert!(
        line.starts_with("error: scenes/scene.json: objects[2].file: ")
            && line.contains(r"two\nlines.obj")
            && line.contains("cannot read it"),
        "{line:?}"
    );
}
