//! What the mesh tests share: the model files of the system's packages (CGAL's OFF
//! meshes and assimp's test models), a small OFF reader, writers of one model in every
//! format of the scene format's section 8, temporary directories, and scenes rendered
//! from a directory of mesh files.
//!
//! The models are required when `TESSERA_REQUIRE_MODELS=1` (CI installs them): a test
//! that lacks one then fails. Otherwise it says what it lacks and passes without
//! checking anything.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::OnceLock;

use base64::Engine;
use render::{parse_scene_with, render_frame, Image, MeshFiles, RenderSettings, Scene, Tracer};

/// The variable that makes a missing model a failure.
pub const REQUIRE_MODELS: &str = "TESSERA_REQUIRE_MODELS";

/// Where Debian's `assimp-testmodels` puts its files.
pub const ASSIMP: &str = "/usr/share/assimp/models";

/// The archive of Debian's `libcgal-demo` that holds CGAL's example meshes.
pub const CGAL_DATA: &str = "/usr/share/doc/libcgal-dev/data.tar.gz";

/// A model is missing: a failure when models are required, else a note and `None`.
pub fn missing<T>(what: &str) -> Option<T> {
    let required = std::env::var(REQUIRE_MODELS).is_ok_and(|v| v == "1");
    assert!(
        !required,
        "{what} is missing and {REQUIRE_MODELS}=1 (install the Debian packages \
         libcgal-demo and assimp-testmodels)"
    );
    eprintln!("note: {what} is missing: test skipped (set {REQUIRE_MODELS}=1 to fail instead)");
    None
}

/// The file `relative` of assimp's test models, if it is there.
pub fn assimp(relative: &str) -> Option<PathBuf> {
    let path = Path::new(ASSIMP).join(relative);
    if path.is_file() {
        Some(path)
    } else {
        missing(&path.display().to_string())
    }
}

/// A triangle mesh as the tests write it: double-precision positions and triangles.
#[derive(Clone, Debug, PartialEq)]
pub struct Model {
    pub positions: Vec<[f64; 3]>,
    pub triangles: Vec<[u32; 3]>,
}

impl Model {
    /// The model with every coordinate rounded to the nearest `f32` (so exact in every
    /// format, STL and glTF included).
    pub fn rounded_to_f32(&self) -> Model {
        Model {
            positions: self
                .positions
                .iter()
                .map(|p| p.map(|x| f64::from(x as f32)))
                .collect(),
            triangles: self.triangles.clone(),
        }
    }

    /// The model with `f` applied to every position.
    pub fn mapped(&self, f: impl Fn([f64; 3]) -> [f64; 3]) -> Model {
        Model {
            positions: self.positions.iter().map(|&p| f(p)).collect(),
            triangles: self.triangles.clone(),
        }
    }

    /// The smallest and largest coordinates.
    pub fn bounds(&self) -> ([f64; 3], [f64; 3]) {
        let mut lo = [f64::INFINITY; 3];
        let mut hi = [f64::NEG_INFINITY; 3];
        for p in &self.positions {
            for k in 0..3 {
                lo[k] = lo[k].min(p[k]);
                hi[k] = hi[k].max(p[k]);
            }
        }
        (lo, hi)
    }
}

/// Reads an OFF file (`OFF`, counts, vertices, faces of any size split as fans), as
/// CGAL writes them.
pub fn read_off(text: &str) -> Model {
    let mut words = text
        .lines()
        .map(|l| l.split('#').next().unwrap_or_default())
        .flat_map(str::split_whitespace);
    assert_eq!(words.next(), Some("OFF"), "an OFF file starts with OFF");
    let mut count = || -> usize { words.next().expect("a count").parse().expect("a count") };
    let (vertices, faces, _edges) = (count(), count(), count());
    let mut number = || -> f64 {
        words
            .next()
            .expect("a number")
            .parse()
            .expect("a finite number")
    };
    let positions: Vec<[f64; 3]> = (0..vertices)
        .map(|_| [number(), number(), number()])
        .collect();
    let mut triangles = Vec::new();
    let mut index = || -> u32 { words.next().expect("an index").parse().expect("an index") };
    for _ in 0..faces {
        let n = index();
        let corners: Vec<u32> = (0..n).map(|_| index()).collect();
        for k in 1..corners.len() - 1 {
            triangles.push([corners[0], corners[k], corners[k + 1]]);
        }
    }
    Model {
        positions,
        triangles,
    }
}

/// CGAL's `data/meshes/NAME.off`, read from the archive once, or `None` (see
/// [`missing`]).
pub fn cgal(name: &'static str) -> Option<&'static Model> {
    static COW: OnceLock<Option<Model>> = OnceLock::new();
    assert_eq!(name, "cow", "only the cow is used");
    COW.get_or_init(|| {
        let member = format!("data/meshes/{name}.off");
        let out = std::process::Command::new("tar")
            .args(["-xzOf", CGAL_DATA, &member])
            .output();
        match out {
            Ok(out) if out.status.success() && !out.stdout.is_empty() => Some(read_off(
                std::str::from_utf8(&out.stdout).expect("an OFF file is text"),
            )),
            _ => missing(&format!("{member} of {CGAL_DATA}")),
        }
    })
    .as_ref()
}

/// CGAL's cow: 2,904 vertices, 5,804 triangles, about 1 × 0.6 × 0.3 around the origin,
/// its length along x and its back up.
pub fn cow() -> Option<&'static Model> {
    cgal("cow")
}

// ---------------------------------------------------------------------------------
// Writers: one model in every format. Doubles are written in Rust's shortest form,
// which reads back to the same double.
// ---------------------------------------------------------------------------------

/// Wavefront OBJ, with 1-based indices, or negative ones counting back from the last
/// vertex (all faces come after all vertices).
pub fn obj(model: &Model, negative: bool) -> Vec<u8> {
    let mut text = String::from("# written by the mesh tests\no model\n");
    for p in &model.positions {
        text += &format!("v {} {} {}\n", p[0], p[1], p[2]);
    }
    text += "g body\nusemtl none\n";
    let n = model.positions.len() as i64;
    for t in &model.triangles {
        let i = t.map(|v| {
            if negative {
                i64::from(v) - n
            } else {
                i64::from(v) + 1
            }
        });
        text += &format!("f {} {} {}\n", i[0], i[1], i[2]);
    }
    text.into_bytes()
}

/// ASCII PLY: `property float` declared, yet the numbers written as doubles (read to
/// the nearest double whatever the header says), with a comment, an unknown header line,
/// an extra vertex property and an extra element that are all ignored.
pub fn ply_ascii(model: &Model) -> Vec<u8> {
    let mut text = format!(
        "ply\nformat ascii 1.0\ncomment written by the mesh tests\nobj_info nothing\n\
         element vertex {}\nproperty float x\nproperty float y\nproperty float z\n\
         property uchar quality\nelement face {}\nproperty list uchar int vertex_indices\n\
         element note 1\nproperty int value\nend_header\n",
        model.positions.len(),
        model.triangles.len()
    );
    for p in &model.positions {
        text += &format!("{} {} {} 7\n", p[0], p[1], p[2]);
    }
    for t in &model.triangles {
        text += &format!("3 {} {} {}\n", t[0], t[1], t[2]);
    }
    text += "42\n";
    text.into_bytes()
}

/// Binary PLY, little- or big-endian, positions as doubles or (`single`) floats.
pub fn ply_binary(model: &Model, big: bool, single: bool) -> Vec<u8> {
    let (order, kind) = (
        if big { "big" } else { "little" },
        if single { "float" } else { "double" },
    );
    let mut bytes = format!(
        "ply\nformat binary_{order}_endian 1.0\ncomment written by the mesh tests\n\
         element vertex {}\nproperty {kind} x\nproperty {kind} y\nproperty {kind} z\n\
         element face {}\nproperty list uchar uint vertex_indices\nend_header\n",
        model.positions.len(),
        model.triangles.len()
    )
    .into_bytes();
    for p in &model.positions {
        for &x in p {
            match (single, big) {
                (true, true) => bytes.extend_from_slice(&(x as f32).to_be_bytes()),
                (true, false) => bytes.extend_from_slice(&(x as f32).to_le_bytes()),
                (false, true) => bytes.extend_from_slice(&x.to_be_bytes()),
                (false, false) => bytes.extend_from_slice(&x.to_le_bytes()),
            }
        }
    }
    for t in &model.triangles {
        bytes.push(3);
        for &i in t {
            if big {
                bytes.extend_from_slice(&i.to_be_bytes());
            } else {
                bytes.extend_from_slice(&i.to_le_bytes());
            }
        }
    }
    bytes
}

/// Binary STL: the model's coordinates as floats, a facet normal that is ignored.
pub fn stl_binary(model: &Model) -> Vec<u8> {
    let mut bytes = b"binary STL written by the mesh tests".to_vec();
    bytes.resize(80, b' ');
    bytes.extend_from_slice(&(model.triangles.len() as u32).to_le_bytes());
    for t in &model.triangles {
        // A wrong normal on purpose: the stored normals are ignored.
        for x in [0.0f32, 0.0, 1.0] {
            bytes.extend_from_slice(&x.to_le_bytes());
        }
        for &i in t {
            for x in model.positions[i as usize] {
                bytes.extend_from_slice(&(x as f32).to_le_bytes());
            }
        }
        bytes.extend_from_slice(&[0, 0]);
    }
    bytes
}

/// ASCII STL of the model's coordinates rounded to floats, written as the doubles they
/// are.
pub fn stl_ascii(model: &Model) -> Vec<u8> {
    let mut text = String::from("solid model\n");
    for t in &model.triangles {
        text += "  facet normal 0 0 1\n    outer loop\n";
        for &i in t {
            let p = model.positions[i as usize].map(|x| f64::from(x as f32));
            text += &format!("      vertex {} {} {}\n", p[0], p[1], p[2]);
        }
        text += "    endloop\n  endfacet\n";
    }
    text += "endsolid model\n";
    text.into_bytes()
}

/// The binary buffer of a glTF: positions as floats, then indices as `u32` or `u16`
/// (`short`), with the document's JSON naming them.
fn gltf_parts(model: &Model, short: bool, uri: Option<&str>) -> (String, Vec<u8>) {
    let mut buffer = Vec::new();
    for p in &model.positions {
        for &x in p {
            buffer.extend_from_slice(&(x as f32).to_le_bytes());
        }
    }
    let positions_length = buffer.len();
    for t in &model.triangles {
        for &i in t {
            if short {
                buffer.extend_from_slice(&u16::try_from(i).expect("a short index").to_le_bytes());
            } else {
                buffer.extend_from_slice(&i.to_le_bytes());
            }
        }
    }
    let indices_length = buffer.len() - positions_length;
    while buffer.len() % 4 != 0 {
        buffer.push(0);
    }
    let (lo, hi) = model.rounded_to_f32().bounds();
    let uri = uri.map_or(String::new(), |u| format!(r#", "uri": "{u}""#));
    let json = format!(
        r#"{{"asset": {{"version": "2.0", "generator": "the mesh tests"}},
  "scene": 0, "scenes": [{{"nodes": [0]}}],
  "nodes": [{{"mesh": 0, "name": "model"}}],
  "meshes": [{{"primitives": [{{"attributes": {{"POSITION": 0}}, "indices": 1, "mode": 4, "material": 0}}]}}],
  "materials": [{{"name": "ignored"}}],
  "buffers": [{{"byteLength": {}{uri}}}],
  "bufferViews": [{{"buffer": 0, "byteOffset": 0, "byteLength": {positions_length}, "target": 34962}},
                  {{"buffer": 0, "byteOffset": {positions_length}, "byteLength": {indices_length}, "target": 34963}}],
  "accessors": [{{"bufferView": 0, "componentType": 5126, "count": {}, "type": "VEC3",
                  "min": [{}, {}, {}], "max": [{}, {}, {}]}},
                {{"bufferView": 1, "componentType": {}, "count": {}, "type": "SCALAR"}}]}}"#,
        buffer.len(),
        model.positions.len(),
        lo[0],
        lo[1],
        lo[2],
        hi[0],
        hi[1],
        hi[2],
        if short { 5123 } else { 5125 },
        model.triangles.len() * 3
    );
    (json, buffer)
}

/// A `.gltf` whose buffer is a base64 data URI, indices as `u32`.
pub fn gltf(model: &Model) -> Vec<u8> {
    let (_, buffer) = gltf_parts(model, false, None);
    let data = base64::engine::general_purpose::STANDARD.encode(&buffer);
    let uri = format!("data:application/octet-stream;base64,{data}");
    gltf_parts(model, false, Some(&uri)).0.into_bytes()
}

/// A `.gltf` whose buffer is the file `uri` (relative to the `.gltf`), indices as
/// `u32`: the document and the buffer file's bytes.
pub fn gltf_with_buffer(model: &Model, uri: &str) -> (Vec<u8>, Vec<u8>) {
    let (json, buffer) = gltf_parts(model, false, Some(uri));
    (json.into_bytes(), buffer)
}

/// A `.glb`, indices as `u16`.
pub fn glb(model: &Model) -> Vec<u8> {
    let (json, buffer) = gltf_parts(model, true, None);
    let mut json = json.into_bytes();
    while json.len() % 4 != 0 {
        json.push(b' ');
    }
    let total = 12 + 8 + json.len() + 8 + buffer.len();
    let mut bytes = b"glTF".to_vec();
    bytes.extend_from_slice(&2u32.to_le_bytes());
    bytes.extend_from_slice(&(total as u32).to_le_bytes());
    bytes.extend_from_slice(&(json.len() as u32).to_le_bytes());
    bytes.extend_from_slice(b"JSON");
    bytes.extend_from_slice(&json);
    bytes.extend_from_slice(&(buffer.len() as u32).to_le_bytes());
    bytes.extend_from_slice(b"BIN\0");
    bytes.extend_from_slice(&buffer);
    bytes
}

// ---------------------------------------------------------------------------------
// Temporary directories and scenes.
// ---------------------------------------------------------------------------------

/// A fresh directory under the system's temporary one, removed when dropped.
pub struct TempDir(PathBuf);

impl TempDir {
    pub fn new(what: &str) -> TempDir {
        static COUNT: AtomicU64 = AtomicU64::new(0);
        let path = std::env::temp_dir().join(format!(
            "tessera-{what}-{}-{}",
            std::process::id(),
            COUNT.fetch_add(1, Ordering::Relaxed)
        ));
        std::fs::create_dir_all(&path).expect("cannot create a temporary directory");
        TempDir(path)
    }

    pub fn path(&self) -> &Path {
        &self.0
    }

    /// Writes `bytes` as `name` in the directory; its path.
    pub fn write(&self, name: &str, bytes: &[u8]) -> PathBuf {
        let path = self.0.join(name);
        std::fs::write(&path, bytes).expect("cannot write a test file");
        path
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// A camera: where it is and what it looks at.
#[derive(Clone, Copy, Debug)]
pub struct View {
    pub position: [f64; 3],
    pub look_at: [f64; 3],
}

/// Looking at the cow from the front left and above.
pub const COW_VIEW: View = View {
    position: [0.7, 0.4, -1.0],
    look_at: [0.0, -0.02, 0.0],
};

/// A scene of `objects` (JSON objects, comma-separated) over a checkered floor just
/// under the cow's hooves, lit by two lights, at 160 × 120.
pub fn scene_text(view: View, objects: &str) -> String {
    let [px, py, pz] = view.position;
    let [lx, ly, lz] = view.look_at;
    format!(
        r#"{{
  "camera": {{"position": [{px}, {py}, {pz}], "look_at": [{lx}, {ly}, {lz}]}},
  "image": {{"width": 160, "height": 120}},
  "lights": [{{"position": "2 4 -3", "color": "0.9 0.9 0.9"}},
             {{"position": "-3 2 -1", "color": "0.3 0.3 0.35"}}],
  "objects": [
    {{"type": "plane", "normal": "0 1 0", "distance": -0.31, "color": "1 1 1 2"}},
    {objects}
  ]
}}"#
    )
}

/// A `mesh` object naming `file`, with `extra` keys (`"transform": …`, `"shading": …`)
/// if any.
pub fn mesh_object(file: &str, color: &str, extra: &str) -> String {
    let extra = if extra.is_empty() {
        String::new()
    } else {
        format!(", {extra}")
    };
    format!(r#"{{"type": "mesh", "file": "{file}", "color": "{color}"{extra}}}"#)
}

/// The scene `text`, its mesh files read from `dir`.
pub fn load(dir: &Path, text: &str) -> Scene {
    parse_scene_with(text, &MeshFiles::beside(dir))
        .unwrap_or_else(|e| panic!("the scene loads: {e}\n{text}"))
}

/// The scene at its own settings, in tiles of 16, on the current pool.
pub fn render_scene(scene: &Scene) -> Image {
    render_with(scene, scene.settings)
}

/// The scene at `settings`, in tiles of 16, on the current pool.
pub fn render_with(scene: &Scene, settings: RenderSettings) -> Image {
    render_frame(&Tracer::new(scene, settings), 16, &|_| {}).image
}

/// The scene `text` with its mesh files in `dir`, rendered.
pub fn render_in(dir: &Path, text: &str) -> Image {
    render_scene(&load(dir, text))
}

/// How many pixels of `a` and `b` differ.
pub fn differing_pixels(a: &Image, b: &Image) -> usize {
    assert_eq!((a.width, a.height), (b.width, b.height));
    a.rgb
        .chunks_exact(3)
        .zip(b.rgb.chunks_exact(3))
        .filter(|(p, q)| p != q)
        .count()
}

/// Where two images that must be the same first differ, for a failure's message.
pub fn first_difference(a: &Image, b: &Image) -> String {
    let n = differing_pixels(a, b);
    let first = a
        .rgb
        .chunks_exact(3)
        .zip(b.rgb.chunks_exact(3))
        .position(|(p, q)| p != q);
    match first {
        None => "the same bytes".into(),
        Some(i) => {
            let (x, y) = (i as u32 % a.width, i as u32 / a.width);
            format!(
                "{n} pixels differ, the first at ({x}, {y}): {:?} and {:?}",
                a.pixel(x, y),
                b.pixel(x, y)
            )
        }
    }
}

/// Asserts that `a` and `b` are the same bytes.
#[track_caller]
pub fn assert_same(a: &Image, b: &Image, what: &str) {
    assert!(a == b, "{what}: {}", first_difference(a, b));
}
