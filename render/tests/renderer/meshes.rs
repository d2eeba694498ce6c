//! Meshes (the scene format, section 8) compared byte for byte, never within a
//! tolerance: one model written in every format renders the same image; copies of a
//! file, instances and exact transforms give the bytes of the file transformed by
//! hand; tiles, threads, samplers and the instruction set change nothing; and the test
//! models that assimp ships load, render, or are refused in one line naming the file.
//!
//! The model is CGAL's cow (2,904 vertices, 5,804 triangles), read from its OFF file
//! by the tests' own reader and written by them in each format.

use std::sync::Arc;

use render::simd::Isa;
use render::{
    render_frame, render_tile, Image, Rect, RenderSettings, Sampling, Scene, Shape, Tracer,
};

use crate::mesh_support::{
    assert_same, assimp, cow, differing_pixels, glb, gltf, load, mesh_object, missing, obj,
    ply_ascii, ply_binary, render_in, render_scene, render_with, scene_text, stl_ascii, stl_binary,
    Model, TempDir, View, ASSIMP, COW_VIEW,
};
use crate::support::frame;

/// The cow's colour: slightly reflective, so that rays also leave the mesh.
const COW: &str = "0.8 0.5 0.3 0.2";

/// The scene of one mesh object naming `file` with `extra` keys, seen from `view`.
fn one_mesh(view: View, file: &str, extra: &str) -> String {
    scene_text(view, &mesh_object(file, COW, extra))
}

/// The floor and lights alone: what a mesh must change.
fn no_mesh(view: View) -> String {
    scene_text(
        view,
        r#"{"type": "sphere", "center": "0 -100 0", "radius": 1, "color": "0 0 0 0"}"#,
    )
}

/// Asserts that `image` shows a mesh: at least a twentieth of its pixels differ from
/// the empty scene's.
#[track_caller]
fn assert_shows_mesh(image: &Image, empty: &Image, what: &str) {
    let changed = differing_pixels(image, empty);
    let total = (image.width * image.height) as usize;
    assert!(
        changed * 20 >= total,
        "{what}: the mesh covers only {changed} of {total} pixels"
    );
}

/// The geometry of the `index`-th object, a mesh.
fn geometry(scene: &Scene, index: usize) -> &render::mesh::MeshData {
    match &scene.objects[index].shape {
        Shape::Mesh(m) => &m.file.geometry.data,
        other => panic!("objects[{index}] is not a mesh: {other:?}"),
    }
}

/// The shared geometry of the `index`-th object, a mesh.
fn shared(scene: &Scene, index: usize) -> &Arc<render::mesh::MeshGeometry> {
    match &scene.objects[index].shape {
        Shape::Mesh(m) => &m.file.geometry,
        other => panic!("objects[{index}] is not a mesh: {other:?}"),
    }
}

/// Each triangle's three positions, as a reader gave them.
fn corners(mesh: &render::mesh::MeshData) -> Vec<[[f64; 3]; 3]> {
    mesh.triangles
        .iter()
        .map(|t| t.map(|i| mesh.positions[i as usize]))
        .collect()
}

fn model_corners(model: &Model) -> Vec<[[f64; 3]; 3]> {
    model
        .triangles
        .iter()
        .map(|t| t.map(|i| model.positions[i as usize]))
        .collect()
}

// ---------------------------------------------------------------------------------
// One model, every format.
// ---------------------------------------------------------------------------------

/// Renders each file of `files` (written into `dir`) as the cow of the scene, flat and
/// smooth (smooth only for the files of `smooth`), and asserts they are the same bytes
/// as the first and that each file read gives `model`'s triangles exactly.
fn assert_formats_agree(dir: &TempDir, model: &Model, files: &[(&str, Vec<u8>)], smooth: &[&str]) {
    let expected = model_corners(model);
    let empty = render_in(dir.path(), &no_mesh(COW_VIEW));
    for shading in ["flat", "smooth"] {
        let mut reference: Option<(&str, Image)> = None;
        for (name, bytes) in files {
            if shading == "smooth" && !smooth.contains(name) {
                continue;
            }
            dir.write(name, bytes);
            let scene = load(
                dir.path(),
                &one_mesh(COW_VIEW, name, &format!(r#""shading": "{shading}""#)),
            );
            assert!(
                corners(geometry(&scene, 1)) == expected,
                "{name}: the triangles read are not the model's"
            );
            let image = render_scene(&scene);
            match &reference {
                None => {
                    assert_shows_mesh(&image, &empty, name);
                    reference = Some((name, image));
                }
                Some((first, bytes)) => {
                    assert_same(&image, bytes, &format!("{shading}: {name} against {first}"))
                }
            }
        }
    }
}

#[test]
fn one_model_in_every_format_gives_the_same_bytes() {
    let Some(cow) = cow() else { return };
    let dir = TempDir::new("mesh-formats");
    // Doubles: the formats that store them.
    let doubles = [
        ("cow.obj", obj(cow, false)),
        ("cow-negative-indices.OBJ", obj(cow, true)),
        ("cow-ascii.ply", ply_ascii(cow)),
        ("cow-little.ply", ply_binary(cow, false, false)),
        ("cow-big.Ply", ply_binary(cow, true, false)),
    ];
    let names: Vec<&str> = doubles.iter().map(|(n, _)| *n).collect();
    assert_formats_agree(&dir, cow, &doubles, &names);

    // Floats: STL and glTF store them, so every format of this group is given the
    // cow's coordinates rounded to floats, exact in all of them.
    let single = cow.rounded_to_f32();
    assert!(
        single != *cow,
        "the cow's doubles are not all floats already"
    );
    let floats = [
        ("cow32.obj", obj(&single, false)),
        ("cow32-ascii.ply", ply_ascii(&single)),
        ("cow32-little.ply", ply_binary(&single, false, true)),
        ("cow32-big.ply", ply_binary(&single, true, true)),
        ("cow32.gltf", gltf(&single)),
        ("cow32.GLB", glb(&single)),
        ("cow32-binary.stl", stl_binary(&single)),
        ("cow32-ascii.stl", stl_ascii(&single)),
    ];
    // An STL mesh's vertices are not shared between facets, so its smooth normals are
    // its flat ones: smooth shading is compared among the indexed formats only.
    let indexed: Vec<&str> = floats
        .iter()
        .map(|(n, _)| *n)
        .filter(|n| !n.ends_with(".stl"))
        .collect();
    assert_formats_agree(&dir, &single, &floats, &indexed);
}

// ---------------------------------------------------------------------------------
// Copies and instances.
// ---------------------------------------------------------------------------------

/// Three cows with different transforms, side by side.
const THREE: [&str; 3] = [
    r#""transform": {"scale": 0.6, "rotate": "0 30 0", "translate": "-0.75 -0.12 0.5"}"#,
    r#""transform": {"scale": "0.5 0.55 0.5", "rotate": "5 -75 0", "translate": "0.55 -0.14 0.9"}, "shading": "smooth""#,
    r#""transform": {"matrix": [0.45, 0, 0.12, 0.05, 0, 0.45, 0, -0.17, -0.12, 0, 0.45, -0.45]}"#,
];

/// Seeing the three cows.
const THREE_VIEW: View = View {
    position: [0.1, 0.75, -1.6],
    look_at: [-0.05, -0.15, 0.4],
};

fn three_cows(files: [&str; 3]) -> String {
    let objects: Vec<String> = files
        .iter()
        .zip(THREE)
        .map(|(file, extra)| mesh_object(file, COW, extra))
        .collect();
    scene_text(THREE_VIEW, &objects.join(",\n    "))
}

#[test]
fn copies_and_instances_give_the_same_bytes() {
    let Some(cow) = cow() else { return };
    let dir = TempDir::new("mesh-instances");
    let text = obj(cow, false);
    dir.write("cow.obj", &text);
    dir.write("copy-of-cow.obj", &text);
    dir.write("another-copy.obj", &text);
    // Files of other bytes (a comment added) and the same triangles.
    for k in 0..3 {
        let mut distinct = text.clone();
        distinct.extend_from_slice(format!("# distinct file {k}\n").as_bytes());
        dir.write(&format!("distinct-{k}.obj"), &distinct);
    }

    // One object: a file and its copy under another name.
    let original = render_in(dir.path(), &one_mesh(COW_VIEW, "cow.obj", ""));
    let copy = render_in(dir.path(), &one_mesh(COW_VIEW, "copy-of-cow.obj", ""));
    assert_same(&original, &copy, "a copy under another name");

    // Three objects: one file, three copies (shared by their bytes' hash), three
    // distinct files (not shared, so each mapped to world space once at preparation).
    let one_file = load(dir.path(), &three_cows(["cow.obj"; 3]));
    let copies = load(
        dir.path(),
        &three_cows(["cow.obj", "copy-of-cow.obj", "another-copy.obj"]),
    );
    let distinct = load(
        dir.path(),
        &three_cows(["distinct-0.obj", "distinct-1.obj", "distinct-2.obj"]),
    );
    for scene in [&one_file, &copies] {
        assert!(
            Arc::ptr_eq(shared(scene, 1), shared(scene, 2))
                && Arc::ptr_eq(shared(scene, 1), shared(scene, 3)),
            "one file and its copies hold their geometry once"
        );
    }
    assert!(
        !Arc::ptr_eq(shared(&distinct, 1), shared(&distinct, 2))
            && !Arc::ptr_eq(shared(&distinct, 2), shared(&distinct, 3)),
        "files of different bytes are read each on its own"
    );
    let reference = render_scene(&one_file);
    let empty = render_in(dir.path(), &no_mesh(THREE_VIEW));
    assert_shows_mesh(&reference, &empty, "three cows");
    assert_same(&render_scene(&copies), &reference, "three copies");
    assert_same(&render_scene(&distinct), &reference, "three distinct files");
}

// ---------------------------------------------------------------------------------
// Transforms against files transformed by hand.
// ---------------------------------------------------------------------------------

/// The rotation Rz·Ry·Rx of section 8 for angles that are multiples of 90°, exactly:
/// entries 0 and ±1.
fn quarter_turns(degrees: [i32; 3]) -> [[f64; 3]; 3] {
    let sin_cos = |d: i32| match d.rem_euclid(360) {
        0 => (0.0, 1.0),
        90 => (1.0, 0.0),
        180 => (0.0, -1.0),
        270 => (-1.0, 0.0),
        _ => panic!("{d} is not a multiple of 90"),
    };
    let (sx, cx) = sin_cos(degrees[0]);
    let (sy, cy) = sin_cos(degrees[1]);
    let (sz, cz) = sin_cos(degrees[2]);
    let rx = [[1.0, 0.0, 0.0], [0.0, cx, -sx], [0.0, sx, cx]];
    let ry = [[cy, 0.0, sy], [0.0, 1.0, 0.0], [-sy, 0.0, cy]];
    let rz = [[cz, -sz, 0.0], [sz, cz, 0.0], [0.0, 0.0, 1.0]];
    let mul = |x: [[f64; 3]; 3], y: [[f64; 3]; 3]| -> [[f64; 3]; 3] {
        std::array::from_fn(|i| std::array::from_fn(|j| (0..3).map(|k| x[i][k] * y[k][j]).sum()))
    };
    mul(rz, mul(ry, rx))
}

/// `r`·p for a matrix of entries 0 and ±1 with one non-zero entry a row: exact, and a
/// zero result is +0 as the renderer's `+ t` makes it.
fn turn(r: &[[f64; 3]; 3], p: [f64; 3]) -> [f64; 3] {
    std::array::from_fn(|i| {
        let k = (0..3).find(|&k| r[i][k] != 0.0).expect("a permutation");
        r[i][k] * p[k] + 0.0
    })
}

/// a + b, if that sum is exact in double.
fn exact_sum(a: f64, b: f64) -> Option<f64> {
    let s = a + b;
    let bb = s - a;
    let error = (a - (s - bb)) + (b - bb);
    (error == 0.0).then_some(s)
}

#[test]
fn quarter_turns_equal_the_file_turned_by_hand() {
    let Some(cow) = cow() else { return };
    let dir = TempDir::new("mesh-turns");
    dir.write("cow.obj", &obj(cow, false));
    let view = View {
        position: [0.8, 0.5, -0.9],
        look_at: [0.0, 0.0, 0.0],
    };
    let empty = render_in(dir.path(), &no_mesh(view));
    for angles in [
        [0, 90, 0],
        [90, 0, 0],
        [0, 0, 90],
        [0, 180, 0],
        [0, 270, 90],
    ] {
        let r = quarter_turns(angles);
        if angles == [0, 90, 0] {
            // Ry(90°): (x, y, z) → (z, y, −x).
            let p = [0.25, -0.5, 0.125];
            assert_eq!(turn(&r, p), [0.125, -0.5, -0.25]);
        }
        let name = format!("cow-turned-{}-{}-{}.obj", angles[0], angles[1], angles[2]);
        dir.write(&name, &obj(&cow.mapped(|p| turn(&r, p)), false));
        let [a, b, c] = angles;
        let transformed = render_in(
            dir.path(),
            &one_mesh(
                view,
                "cow.obj",
                &format!(r#""transform": {{"rotate": "{a} {b} {c}"}}"#),
            ),
        );
        let by_hand = render_in(dir.path(), &one_mesh(view, &name, ""));
        assert_shows_mesh(&by_hand, &empty, &name);
        assert_same(&transformed, &by_hand, &format!("rotate {angles:?}"));
    }
}

#[test]
fn exact_scales_turns_and_translations_equal_the_file_moved_by_hand() {
    let Some(cow) = cow() else { return };
    // Floats have 24 bits: halved and moved by these amounts they stay exact in double.
    let cow = cow.rounded_to_f32();
    let dir = TempDir::new("mesh-moves");
    dir.write("cow.obj", &obj(&cow, false));
    // Three instances of the file, each with its scale, turn and translation, against
    // three files moved by hand.
    let moves: [(f64, [i32; 3], [f64; 3]); 3] = [
        (0.5, [0, 90, 0], [0.25, -0.125, 0.5]),
        (0.5, [0, 0, 0], [-0.5, -0.125, 0.25]),
        (0.25, [0, 180, 0], [0.5, -0.25, -0.25]),
    ];
    let mut by_file = Vec::new();
    let mut by_transform = Vec::new();
    for (k, (scale, angles, t)) in moves.iter().enumerate() {
        let r = quarter_turns(*angles);
        let exact = std::cell::Cell::new(true);
        let moved = cow.mapped(|p| {
            let q = turn(&r, p.map(|x| x * scale));
            std::array::from_fn(|i| {
                exact_sum(q[i], t[i]).unwrap_or_else(|| {
                    exact.set(false);
                    q[i] + t[i]
                })
            })
        });
        if !exact.get() {
            eprintln!("note: move {k} is not exact in double: not compared");
            return;
        }
        let name = format!("cow-moved-{k}.obj");
        dir.write(&name, &obj(&moved, false));
        by_file.push(mesh_object(&name, COW, ""));
        let [a, b, c] = angles;
        by_transform.push(mesh_object(
            "cow.obj",
            COW,
            &format!(
                r#""transform": {{"scale": {scale}, "rotate": "{a} {b} {c}", "translate": [{}, {}, {}]}}"#,
                t[0], t[1], t[2]
            ),
        ));
    }
    let view = View {
        position: [0.2, 0.6, -1.1],
        look_at: [0.0, -0.15, 0.1],
    };
    let empty = render_in(dir.path(), &no_mesh(view));
    let moved = render_in(dir.path(), &scene_text(view, &by_file.join(",\n")));
    assert_shows_mesh(&moved, &empty, "three cows moved by hand");
    // One at a time (each instance alone), and the three together (one shared file).
    for k in 0..3 {
        let alone = render_in(dir.path(), &scene_text(view, &by_transform[k]));
        let by_hand = render_in(dir.path(), &scene_text(view, &by_file[k]));
        assert_same(&alone, &by_hand, &format!("move {k}"));
    }
    let instances = render_in(dir.path(), &scene_text(view, &by_transform.join(",\n")));
    assert_same(&instances, &moved, "three instances of one file");
}

// ---------------------------------------------------------------------------------
// Tiles, threads, samplers, instruction sets.
// ---------------------------------------------------------------------------------

/// A cow (smooth and reflective) among the other shapes: a mirror sphere, a box, a
/// loose triangle, on the checkered floor.
fn busy_scene(dir: &TempDir) -> Option<Scene> {
    let cow = cow()?;
    dir.write("cow.ply", &ply_binary(cow, false, false));
    let objects = [
        mesh_object("cow.ply", "0.8 0.5 0.3 0.3", r#""shading": "smooth""#),
        r#"{"type": "sphere", "center": "-0.8 0.1 0.7", "radius": 0.4, "color": "0.9 0.9 0.9 0.6"}"#.into(),
        r#"{"type": "box", "min": "0.45 -0.31 0.35", "max": "0.8 0.05 0.6", "color": "0.2 0.6 0.9 0"}"#.into(),
        r#"{"type": "triangle", "vertices": ["-0.7 -0.3 -0.5", "-0.3 -0.3 -0.6", "-0.5 0.25 -0.5"], "color": "0.9 0.2 0.2 0.5"}"#.into(),
    ];
    let view = View {
        position: [0.6, 0.8, -1.9],
        look_at: [0.0, -0.05, 0.2],
    };
    Some(load(dir.path(), &scene_text(view, &objects.join(",\n"))))
}

fn samplers() -> [Sampling; 3] {
    [
        Sampling::Grid,
        Sampling::Jittered,
        Sampling::adaptive(2.0).expect("a valid target"),
    ]
}

#[test]
fn tiles_threads_and_samplers_change_nothing() {
    let dir = TempDir::new("mesh-tiles");
    let Some(scene) = busy_scene(&dir) else {
        return;
    };
    for sampling in samplers() {
        for aa in [1, 2] {
            let settings = RenderSettings {
                width: 96,
                height: 72,
                aa,
                sampling,
                ..scene.settings
            };
            let tracer = Tracer::new(&scene, settings);
            let whole = frame(&tracer, 96, 1);
            for (tile, threads) in [(1, 2), (7, 2), (16, 3), (61, 1)] {
                let tiled = frame(&tracer, tile, threads);
                let what = format!("{sampling:?}, aa {aa}, tiles of {tile}, {threads} threads");
                assert_same(&tiled.image, &whole.image, &what);
                assert_eq!(tiled.rays, whole.rays, "{what}: rays");
                assert_eq!(tiled.samples, whole.samples, "{what}: samples");
            }
            // A rectangle rendered alone is the same pixels.
            let rect = Rect {
                x: 19,
                y: 11,
                width: 37,
                height: 29,
            };
            if sampling.target_error().is_some() {
                // Adaptive sampling renders regions of blocks, not tiles alone.
                continue;
            }
            let tile = render_tile(&tracer, rect).unwrap();
            for row in 0..rect.height {
                for col in 0..rect.width {
                    let i = ((row * rect.width + col) * 3) as usize;
                    assert_eq!(
                        tile.rgb[i..i + 3],
                        whole.image.pixel(rect.x + col, rect.y + row),
                        "{sampling:?}, aa {aa}: pixel ({}, {}) of a tile alone",
                        rect.x + col,
                        rect.y + row
                    );
                }
            }
        }
    }
}

#[test]
fn the_portable_path_gives_the_bytes_of_the_fastest() {
    let best = Isa::best();
    if cfg!(target_arch = "x86_64") {
        assert_eq!(
            best,
            Isa::Avx2,
            "this x86-64 processor lacks AVX2, so there is no second path to compare"
        );
    }
    let dir = TempDir::new("mesh-isa");
    let Some(scene) = busy_scene(&dir) else {
        return;
    };
    for sampling in samplers() {
        for bvh in [false, true] {
            let settings = RenderSettings {
                width: 96,
                height: 72,
                aa: 2,
                sampling,
                ..scene.settings
            };
            let render = |isa: Isa| {
                let tracer = Tracer::with_bvh(&scene, settings, bvh).with_isa(isa);
                assert_eq!(tracer.isa(), isa);
                render_frame(&tracer, 16, &|_| {})
            };
            let (fast, portable) = (render(best), render(Isa::Portable));
            let what = format!("{sampling:?}, bvh {bvh}");
            assert_same(&fast.image, &portable.image, &what);
            assert_eq!(fast.rays, portable.rays, "{what}: rays");
        }
    }
}

// ---------------------------------------------------------------------------------
// assimp's test models.
// ---------------------------------------------------------------------------------

/// A view of a model's bounding box from the front left and above, and the box.
fn framing(mesh: &render::mesh::MeshData) -> (View, [f64; 3], [f64; 3]) {
    let model = Model {
        positions: mesh.positions.clone(),
        triangles: Vec::new(),
    };
    let (lo, hi) = model.bounds();
    let center: [f64; 3] = std::array::from_fn(|k| (lo[k] + hi[k]) / 2.0);
    let size = (0..3).map(|k| hi[k] - lo[k]).fold(0.0, f64::max);
    let view = View {
        position: [
            center[0] + 0.9 * size,
            center[1] + 0.7 * size,
            center[2] - 1.4 * size,
        ],
        look_at: center,
    };
    (view, lo, hi)
}

/// A scene of the model file at `path` alone (a copy in `dir`), framed, with a light
/// by the camera and a floor under it.
fn model_scene(dir: &TempDir, name: &str, framed: (View, [f64; 3], [f64; 3])) -> String {
    let (view, lo, _) = framed;
    let [px, py, pz] = view.position;
    let [lx, ly, lz] = view.look_at;
    format!(
        r#"{{"camera": {{"position": [{px}, {py}, {pz}], "look_at": [{lx}, {ly}, {lz}]}},
  "image": {{"width": 120, "height": 90}},
  "lights": [{{"position": [{px}, {}, {pz}], "color": "1 1 1"}}],
  "objects": [{{"type": "plane", "normal": "0 1 0", "distance": {}, "color": "1 1 1 2"}},
              {{"type": "mesh", "file": "{}", "color": "0.7 0.7 0.75 0"}}]}}"#,
        py * 2.0,
        lo[1],
        dir.path().join(name).display()
    )
}

/// The pixels of `image` that are not black.
fn lit_pixels(image: &Image) -> usize {
    image
        .rgb
        .chunks_exact(3)
        .filter(|p| *p != [0, 0, 0])
        .count()
}

#[test]
fn wuson_obj_ply_and_stl_give_the_same_triangles_and_bytes() {
    let (Some(obj_path), Some(ply_path), Some(stl_path)) = (
        assimp("OBJ/WusonOBJ.obj"),
        assimp("PLY/Wuson.ply"),
        assimp("STL/Wuson.stl"),
    ) else {
        return;
    };
    let dir = TempDir::new("mesh-wuson");
    let read = |path: &std::path::Path| render::mesh::load::load(path).unwrap();
    let (from_obj, from_ply, from_stl) = (read(&obj_path), read(&ply_path), read(&stl_path));
    for (name, mesh) in [("OBJ", &from_obj), ("PLY", &from_ply), ("STL", &from_stl)] {
        assert_eq!(mesh.triangles.len(), 3_732, "{name}: triangles");
    }
    // The OBJ shares its 2,117 vertices, the PLY repeats them with each face's normal
    // (11,184), the binary STL has three floats for each facet; their triangles are the
    // same doubles, the STL's rounded to floats.
    assert_eq!(from_obj.positions.len(), 2_117);
    assert_eq!(from_ply.positions.len(), 11_184);
    let obj_corners = corners(&from_obj);
    assert!(
        obj_corners == corners(&from_ply),
        "the OBJ's and the PLY's triangles are the same doubles"
    );
    let rounded: Vec<[[f64; 3]; 3]> = obj_corners
        .iter()
        .map(|t| t.map(|p| p.map(|x| f64::from(x as f32))))
        .collect();
    assert!(
        rounded == corners(&from_stl),
        "the STL's triangles are the OBJ's rounded to floats"
    );
    // Flat shading uses the triangles alone: the same bytes. (Smooth shading differs:
    // the OBJ's normals are the vertices', the PLY's each face's own.)
    std::fs::copy(&obj_path, dir.path().join("wuson.obj")).unwrap();
    std::fs::copy(&ply_path, dir.path().join("wuson.ply")).unwrap();
    std::fs::copy(&stl_path, dir.path().join("wuson.stl")).unwrap();
    let single = Model {
        positions: rounded.iter().flatten().copied().collect(),
        triangles: (0..rounded.len() as u32)
            .map(|t| [3 * t, 3 * t + 1, 3 * t + 2])
            .collect(),
    };
    dir.write("wuson32.obj", &obj(&single, false));
    let framed = framing(&from_obj);
    let image = |name: &str| render_in(dir.path(), &model_scene(&dir, name, framed));
    let obj_image = image("wuson.obj");
    assert!(
        lit_pixels(&obj_image) * 4 > (obj_image.width * obj_image.height) as usize,
        "the Wuson renders"
    );
    assert_same(&image("wuson.ply"), &obj_image, "Wuson: PLY against OBJ");
    assert_same(
        &image("wuson.stl"),
        &image("wuson32.obj"),
        "Wuson: STL against the OBJ rounded to floats",
    );
}

/// A node's own matrix, column-major (glTF's order): `matrix`, else T·R·S.
fn node_matrix(node: &serde_json::Value) -> [f64; 16] {
    let numbers = |key: &str| -> Option<Vec<f64>> {
        node.get(key).map(|v| {
            v.as_array()
                .unwrap()
                .iter()
                .map(|x| x.as_f64().unwrap())
                .collect()
        })
    };
    if let Some(m) = numbers("matrix") {
        return m.try_into().unwrap();
    }
    let t = numbers("translation").unwrap_or(vec![0.0; 3]);
    let q = numbers("rotation").unwrap_or(vec![0.0, 0.0, 0.0, 1.0]);
    let s = numbers("scale").unwrap_or(vec![1.0; 3]);
    let (x, y, z, w) = (q[0], q[1], q[2], q[3]);
    let r = [
        [
            1.0 - 2.0 * (y * y + z * z),
            2.0 * (x * y - z * w),
            2.0 * (x * z + y * w),
        ],
        [
            2.0 * (x * y + z * w),
            1.0 - 2.0 * (x * x + z * z),
            2.0 * (y * z - x * w),
        ],
        [
            2.0 * (x * z - y * w),
            2.0 * (y * z + x * w),
            1.0 - 2.0 * (x * x + y * y),
        ],
    ];
    let mut m = [0.0; 16];
    for c in 0..3 {
        for row in 0..3 {
            m[4 * c + row] = r[row][c] * s[c];
        }
    }
    m[12..15].copy_from_slice(&t);
    m[15] = 1.0;
    m
}

fn multiply(a: &[f64; 16], b: &[f64; 16]) -> [f64; 16] {
    std::array::from_fn(|i| {
        let (c, r) = (i / 4, i % 4);
        (0..4).map(|k| a[4 * k + r] * b[4 * c + k]).sum()
    })
}

/// The positions of a GLB's triangles, each node's matrix applied, walked as section 8
/// says (the default scene's roots in order, depth first); and the number of nodes met.
fn glb_positions(bytes: &[u8]) -> (Vec<[f64; 3]>, usize) {
    let word = |at: usize| u32::from_le_bytes(bytes[at..at + 4].try_into().unwrap()) as usize;
    let json_length = word(12);
    let document: serde_json::Value = serde_json::from_slice(&bytes[20..20 + json_length]).unwrap();
    let bin = &bytes[20 + json_length + 8..];
    let mut positions = Vec::new();
    let mut met = 0;
    fn walk(
        d: &serde_json::Value,
        bin: &[u8],
        node: usize,
        parent: &[f64; 16],
        out: &mut Vec<[f64; 3]>,
        met: &mut usize,
    ) {
        *met += 1;
        let n = &d["nodes"][node];
        let m = multiply(parent, &node_matrix(n));
        if let Some(mesh) = n["mesh"].as_u64() {
            for p in d["meshes"][mesh as usize]["primitives"].as_array().unwrap() {
                let a = &d["accessors"][p["attributes"]["POSITION"].as_u64().unwrap() as usize];
                assert_eq!(a["componentType"], 5126);
                let view = &d["bufferViews"][a["bufferView"].as_u64().unwrap() as usize];
                let start = view["byteOffset"].as_u64().unwrap_or(0) as usize
                    + a["byteOffset"].as_u64().unwrap_or(0) as usize;
                let stride = view["byteStride"].as_u64().unwrap_or(12) as usize;
                for k in 0..a["count"].as_u64().unwrap() as usize {
                    let at = start + k * stride;
                    let v: [f64; 3] = std::array::from_fn(|c| {
                        let b = &bin[at + 4 * c..at + 4 * c + 4];
                        f64::from(f32::from_le_bytes(b.try_into().unwrap()))
                    });
                    out.push(std::array::from_fn(|r| {
                        m[r] * v[0] + m[4 + r] * v[1] + m[8 + r] * v[2] + m[12 + r]
                    }));
                }
            }
        }
        for child in n["children"].as_array().into_iter().flatten() {
            walk(d, bin, child.as_u64().unwrap() as usize, &m, out, met);
        }
    }
    let mut identity = [0.0; 16];
    for k in 0..4 {
        identity[5 * k] = 1.0;
    }
    let scene = document["scene"].as_u64().unwrap_or(0) as usize;
    for root in document["scenes"][scene]["nodes"].as_array().unwrap() {
        walk(
            &document,
            bin,
            root.as_u64().unwrap() as usize,
            &identity,
            &mut positions,
            &mut met,
        );
    }
    (positions, met)
}

#[test]
fn the_two_cylinder_engine_loads_with_every_node_transform() {
    let Some(path) = assimp("glTF2/2CylinderEngine-glTF-Binary/2CylinderEngine.glb") else {
        return;
    };
    let bytes = std::fs::read(&path).unwrap();
    let mesh = render::mesh::load::load(&path).unwrap();
    // 67 of the 82 nodes show one of 29 meshes: 121,496 triangles in all.
    assert_eq!(mesh.triangles.len(), 121_496);
    let (expected, nodes) = glb_positions(&bytes);
    assert_eq!(nodes, 82, "every node is reached");
    assert_eq!(mesh.positions.len(), expected.len());
    // The positions with the nodes' matrices applied (composed here in another order,
    // so within rounding); the file's own positions are not: the matrices move them.
    let (view, lo, hi) = framing(&mesh);
    let size = (0..3).map(|k| hi[k] - lo[k]).fold(0.0, f64::max);
    for (k, (got, want)) in mesh.positions.iter().zip(&expected).enumerate() {
        for c in 0..3 {
            assert!(
                (got[c] - want[c]).abs() <= 1e-9 * size,
                "position {k}: {got:?}, expected {want:?}"
            );
        }
    }
    assert!(
        size > 100.0,
        "the engine is a few hundred units across ({size})"
    );
    let dir = TempDir::new("mesh-engine");
    std::fs::copy(&path, dir.path().join("engine.glb")).unwrap();
    let image = render_in(dir.path(), &model_scene(&dir, "engine.glb", (view, lo, hi)));
    let lit = lit_pixels(&image);
    assert!(
        lit * 5 > (image.width * image.height) as usize,
        "the engine renders: {lit} pixels are not black"
    );
}

/// What reading a test model must give.
enum Expect {
    /// It loads, with this many triangles.
    Loads(usize),
    /// It is refused for this required extension (named in the line, which ends
    /// with `not supported`).
    Unsupported(&'static str),
    /// It is refused with this (the end of the line after the file's path).
    Refused(&'static str),
}

use Expect::{Loads, Refused, Unsupported};

/// Every OBJ, PLY, STL and glTF 2.0 file of assimp's test models, beside the large
/// sample collections: the invalid ones (its `invalid/` directory and the glTF
/// directories made to break readers) and the others, with what section 8 makes of
/// each.
const MODELS: &[(&str, Expect)] = &[
    // assimp's invalid files.
    (
        "invalid/empty.obj",
        Refused("no triangle that is not degenerate: nothing to hit"),
    ),
    (
        "invalid/empty.ply",
        Refused("line 1: the header never ends (no `end_header`)"),
    ),
    // Vertex index 12 of 8 on line 23 (and index 0 on line 28).
    (
        "invalid/malformed.obj",
        Refused("line 23: vertex index 12 is out of range: the file has 8 vertices"),
    ),
    (
        "invalid/malformed2.obj",
        Refused("line 23: a face of 0 vertices: a face has at least 3"),
    ),
    // A face list inside the vertex element, and no face element.
    (
        "PLY/issue623.ply",
        Refused("line 13: vertex 1 of 24: the line ends early"),
    ),
    (
        "PLY/pond.0.ply",
        Refused("record 693: vertex 693 of 70051: NaN is not a finite number"),
    ),
    (
        "PLY/points.ply",
        Refused("no triangle that is not degenerate: nothing to hit"),
    ),
    (
        "OBJ/number_formats.obj",
        Refused("line 11: \"3.1+e2\" is not a finite number"),
    ),
    // UTF-16: no line starts with `v` or `f` read as UTF-8.
    (
        "OBJ/box_UTF16BE.obj",
        Refused("no triangle that is not degenerate: nothing to hit"),
    ),
    (
        "OBJ/point_cloud.obj",
        Refused("no triangle that is not degenerate: nothing to hit"),
    ),
    (
        "OBJ/testline.obj",
        Refused("no triangle that is not degenerate: nothing to hit"),
    ),
    (
        "OBJ/testpoints.obj",
        Refused("no triangle that is not degenerate: nothing to hit"),
    ),
    (
        "glTF2/BoxWithInfinites-glTF-Binary/BoxWithInfinites.glb",
        Refused("meshes[0].primitives[0]: accessors[2]: element 0 is not finite"),
    ),
    (
        "glTF2/IncorrectVertexArrays/Cube.gltf",
        Refused("meshes[1].primitives[0]: 35 indices of a triangle list: not a multiple of 3"),
    ),
    (
        "glTF2/IndexOutOfRange/IndexOutOfRange.gltf",
        Refused(
            "meshes[0].primitives[0]: index 255 is out of range: the primitive has 24 positions",
        ),
    ),
    (
        "glTF2/IndexOutOfRange/AllIndicesOutOfRange.gltf",
        Refused(
            "meshes[0].primitives[0]: index 65535 is out of range: the primitive has 24 positions",
        ),
    ),
    ("glTF2/MissingBin/BoxTextured.gltf", Refused("(os error 2)")),
    (
        "glTF2/RecursiveNodes/RecursiveNodes.gltf",
        Refused("nodes[0] is its own ancestor: a cycle"),
    ),
    // `"scene": "hello"`: its buffer is missing beside it too, which is what is said.
    (
        "glTF2/SchemaFailures/sceneWrongType.gltf",
        Refused("(os error 2)"),
    ),
    (
        "glTF2/TestNoRootNode/NoScene.gltf",
        Refused("scenes[0] has no nodes"),
    ),
    (
        "glTF2/TestNoRootNode/SceneWithoutNodes.gltf",
        Refused("scenes[0] has no nodes"),
    ),
    (
        "glTF2/wrongTypes/badArray.gltf",
        Refused("meshes[0] has no primitives"),
    ),
    (
        "glTF2/draco/2CylinderEngine.gltf",
        Unsupported("KHR_draco_mesh_compression"),
    ),
    (
        "glTF2/BoxTextured-glTF-techniqueWebGL/BoxTextured.gltf",
        Unsupported("KHR_technique_webgl"),
    ),
    // Wrong types in what section 8 ignores (materials, names): valid here.
    ("glTF2/wrongTypes/badExtension.gltf", Loads(12)),
    ("glTF2/wrongTypes/badNumber.gltf", Loads(12)),
    ("glTF2/wrongTypes/badObject.gltf", Loads(12)),
    ("glTF2/wrongTypes/badString.gltf", Loads(12)),
    ("glTF2/wrongTypes/badUint.gltf", Loads(12)),
    // glTF 1.0, which section 8 does not read.
    (
        "glTF/BoxTextured-glTF-Binary/BoxTextured.glb",
        Refused("GLB version 1, not 2"),
    ),
    (
        "glTF/BoxTextured-glTF/BoxTextured.gltf",
        Refused("asset.version \"1.0\": only glTF 2.0 is read"),
    ),
    (
        "glTF/TwoBoxes/TwoBoxes.gltf",
        Refused("asset.version \"1.0\": only glTF 2.0 is read"),
    ),
    // The others.
    ("OBJ/WusonOBJ.obj", Loads(3_732)),
    ("OBJ/box.obj", Loads(12)),
    ("OBJ/box_longline.obj", Loads(944)),
    ("OBJ/box_mat_with_spaces.obj", Loads(12)),
    ("OBJ/box_without_lineending.obj", Loads(12)),
    ("OBJ/concave_polygon.obj", Loads(64)),
    ("OBJ/cube_usemtl.obj", Loads(12)),
    ("OBJ/cube_with_vertexcolors.obj", Loads(12)),
    ("OBJ/empty_mat.obj", Loads(256)),
    ("OBJ/multiple_spaces.obj", Loads(1)),
    ("OBJ/regr_3429812.obj", Loads(4)),
    // A material named in Latin-1, not UTF-8: ignored with the line.
    ("OBJ/regr01.obj", Loads(2_710)),
    ("OBJ/spider.obj", Loads(1_368)),
    ("OBJ/testmixed.obj", Loads(12)),
    ("PLY/Wuson.ply", Loads(3_732)),
    ("PLY/cube.ply", Loads(12)),
    ("PLY/cube_binary.ply", Loads(12)),
    ("PLY/cube_uv.ply", Loads(12)),
    ("PLY/float-color.ply", Loads(1)),
    ("STL/3DSMaxExport.STL", Loads(2_000)),
    ("STL/Spider_ascii.stl", Loads(1_368)),
    ("STL/Spider_binary.stl", Loads(1_368)),
    ("STL/Wuson.stl", Loads(3_732)),
    ("STL/sphereWithHole.stl", Loads(285)),
    ("STL/triangle.stl", Loads(1)),
    ("STL/triangle_with_empty_solid.stl", Loads(1)),
    ("STL/triangle_with_two_solids.stl", Loads(2)),
    (
        "glTF2/2CylinderEngine-glTF-Binary/2CylinderEngine.glb",
        Loads(121_496),
    ),
    (
        "glTF2/BoxBadNormals-glTF-Binary/BoxBadNormals.glb",
        Loads(12),
    ),
    ("glTF2/BoxTextured-glTF/BoxTextured.gltf", Loads(12)),
    ("glTF2/BoxTextured-glTF-Binary/BoxTextured.glb", Loads(12)),
    (
        "glTF2/BoxTextured-glTF-Embedded/BoxTextured.gltf",
        Loads(12),
    ),
    ("glTF2/ClearCoat-glTF/ClearCoatTest.gltf", Loads(37_116)),
    ("glTF2/cameras/Cameras.gltf", Loads(2)),
    ("glTF2/simple_skin/simple_skin.gltf", Loads(8)),
];

#[test]
fn assimp_test_models_load_or_are_refused_in_one_line_naming_the_file() {
    if !std::path::Path::new(ASSIMP).is_dir() {
        missing::<()>(ASSIMP);
        return;
    }
    let mut wrong = Vec::new();
    for (relative, expect) in MODELS {
        let Some(path) = assimp(relative) else { return };
        let started = std::time::Instant::now();
        let result = render::mesh::load::load(&path);
        assert!(
            started.elapsed().as_secs() < 5,
            "{relative}: read in {:?}",
            started.elapsed()
        );
        let prefix = format!("{}: ", path.display());
        let one_line = |e: &str| e.starts_with(&prefix) && !e.contains('\n');
        match (expect, result) {
            (Loads(n), Ok(mesh)) if mesh.triangles.len() == *n => {}
            (Refused(end), Err(e)) => {
                if !one_line(&e) || !e.ends_with(end) {
                    wrong.push(format!("{relative}: refused with {e:?}, expected {end:?}"));
                }
            }
            (Unsupported(name), Err(e)) => {
                let said = e.contains("extensionsRequired") && e.contains(name);
                if !one_line(&e) || !said || !e.ends_with(": not supported") {
                    wrong.push(format!("{relative}: refused with {e:?}, expected {name}"));
                }
            }
            (Loads(n), Ok(mesh)) => wrong.push(format!(
                "{relative}: {} triangles, expected {n}",
                mesh.triangles.len()
            )),
            (Loads(n), Err(e)) => {
                wrong.push(format!("{relative}: refused ({e}), expected {n} triangles"))
            }
            (Refused(end), Ok(mesh)) => wrong.push(format!(
                "{relative}: loaded ({} triangles), expected a refusal ending {end:?}",
                mesh.triangles.len()
            )),
            (Unsupported(name), Ok(_)) => wrong.push(format!(
                "{relative}: loaded, expected a refusal of the extension {name}"
            )),
        }
    }
    assert!(wrong.is_empty(), "{}", wrong.join("\n"));

    // Through a scene, the refusal also names the object.
    let dir = TempDir::new("mesh-refused");
    let Some(malformed) = assimp("invalid/malformed2.obj") else {
        return;
    };
    let text = scene_text(
        COW_VIEW,
        &format!(
            r#"{{"type": "sphere", "center": "0 0 0", "radius": 0.5, "color": "1 0 0 0"}},
            {}"#,
            mesh_object(malformed.to_str().unwrap(), COW, "")
        ),
    );
    let error = render::parse_scene_with(&text, &render::MeshFiles::beside(dir.path()))
        .unwrap_err()
        .to_string();
    assert_eq!(
        error,
        format!(
            "objects[2].file: {}: line 23: a face of 0 vertices: a face has at least 3",
            malformed.display()
        )
    );
}

#[test]
fn a_scene_without_meshes_renders_as_before() {
    // The scenes of `scenes/` without meshes: read with mesh files allowed, they are
    // the same scenes and give the same bytes as read without.
    let dir = concat!(env!("CARGO_MANIFEST_DIR"), "/../scenes");
    let mut count = 0;
    for entry in std::fs::read_dir(dir).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_none_or(|e| e != "json") {
            continue;
        }
        let text = std::fs::read_to_string(&path).unwrap();
        // The mesh scenes of `scenes/` are not for this test.
        let Ok(plain) = render::parse_scene(&text) else {
            assert!(text.contains("\"mesh\""), "{}", path.display());
            continue;
        };
        let with_files = load(path.parent().unwrap(), &text);
        assert!(plain == with_files, "{}", path.display());
        let settings = RenderSettings {
            width: 64,
            height: 48,
            ..plain.settings
        };
        assert_same(
            &render_with(&with_files, settings),
            &render_with(&plain, settings),
            &path.display().to_string(),
        );
        count += 1;
    }
    assert!(count >= 5, "the example scenes are found");
}
