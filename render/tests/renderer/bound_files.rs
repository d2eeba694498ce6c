//! A scene parsed with its files bound in memory, under the names its parse from disk
//! recorded, renders the same bytes as from disk, in every format: a glTF's buffer file
//! in a subdirectory and above it, a mesh named by an absolute path, one file under two
//! names. And geometry kept in a cache is shared by every scene given it.

use std::collections::BTreeMap;
use std::sync::Arc;

use render::{buffer_name, parse_scene_with, FileRead, GeometryCache, MeshFiles, Scene, Shape};
use sha2::{Digest, Sha256};

use crate::mesh_support::{
    assert_same, differing_pixels, glb, gltf, gltf_with_buffer, mesh_object, obj, ply_ascii,
    ply_binary, render_scene, stl_ascii, stl_binary, Model, TempDir,
};

/// An octahedron, every coordinate exact in `f32`.
fn octahedron() -> Model {
    Model {
        positions: vec![
            [0.5, 0.0, 0.0],
            [-0.5, 0.0, 0.0],
            [0.0, 0.75, 0.0],
            [0.0, -0.5, 0.0],
            [0.0, 0.0, 0.5],
            [0.0, 0.0, -0.5],
        ],
        triangles: vec![
            [0, 2, 4],
            [4, 2, 1],
            [1, 2, 5],
            [5, 2, 0],
            [4, 3, 0],
            [1, 3, 4],
            [5, 3, 1],
            [0, 3, 5],
        ],
    }
}

/// A directory of mesh files of every kind, and a scene naming them (its text and
/// the names it writes, in object order after the floor).
struct Fixture {
    dir: TempDir,
    names: Vec<String>,
    text: String,
}

fn fixture() -> Fixture {
    let model = octahedron();
    let dir = TempDir::new("bound-files");
    for sub in ["tri", "models/bin", "shared", "abs"] {
        std::fs::create_dir_all(dir.path().join(sub)).unwrap();
    }
    dir.write("tri/model.obj", &obj(&model, false));
    dir.write("negative.obj", &obj(&model, true));
    dir.write("model.ply", &ply_ascii(&model));
    dir.write("big.ply", &ply_binary(&model, true, true));
    dir.write("model.stl", &stl_binary(&model));
    dir.write("ascii.stl", &stl_ascii(&model));
    dir.write("inline.gltf", &gltf(&model));
    dir.write("model.glb", &glb(&model));
    let (ship, ship_bin) = gltf_with_buffer(&model, "bin/ship.bin");
    dir.write("models/ship.gltf", &ship);
    dir.write("models/bin/ship.bin", &ship_bin);
    // The same buffer file by another way there.
    let (again, _) = gltf_with_buffer(&model, "./bin/../bin/ship.bin");
    dir.write("models/again.gltf", &again);
    let (up, up_bin) = gltf_with_buffer(&model, "../shared/up.bin");
    dir.write("models/up.gltf", &up);
    dir.write("shared/up.bin", &up_bin);
    let absolute = dir.write(
        "abs/model.stl",
        &stl_ascii(&model.mapped(|[x, y, z]| [y, x, z])),
    );
    let mut names: Vec<String> = [
        "tri/model.obj",
        "negative.obj",
        "model.ply",
        "big.ply",
        "model.stl",
        "ascii.stl",
        "inline.gltf",
        "model.glb",
        "models/ship.gltf",
        "models/again.gltf",
        "models/up.gltf",
        // The first file again, under another name.
        "./tri/../tri/model.obj",
    ]
    .map(str::to_owned)
    .into();
    names.push(absolute.to_str().unwrap().to_owned());
    let objects: Vec<String> = names
        .iter()
        .enumerate()
        .map(|(i, name)| {
            let (x, y) = ((i % 5) as f64 * 1.2 - 2.4, (i / 5) as f64 * 1.1 - 0.6);
            let transform = format!(
                r#""transform": {{"rotate": "0 {} 0", "translate": "{x} {y} 0"}}"#,
                i * 17
            );
            mesh_object(name, "0.8 0.5 0.3 0.2", &transform)
        })
        .collect();
    let text = format!(
        r#"{{
  "camera": {{"position": [0, 0.6, -6], "look_at": [0, 0.5, 0]}},
  "image": {{"width": 120, "height": 80}},
  "lights": [{{"position": "2 4 -3", "color": "0.9 0.9 0.9"}}],
  "objects": [
    {{"type": "plane", "normal": "0 1 0", "distance": -1.2, "color": "1 1 1 0.3"}},
    {}
  ]
}}"#,
        objects.join(",\n    ")
    );
    Fixture { dir, names, text }
}

/// The files a record names, their bytes read from where it says they were read,
/// checked against the identity it gives them.
fn bind(read: &[FileRead]) -> BTreeMap<String, Arc<[u8]>> {
    read.iter()
        .map(|file| {
            let bytes = std::fs::read(&file.path).unwrap();
            assert_eq!(file.size, bytes.len() as u64, "{}", file.name);
            assert_eq!(
                file.sha256,
                <[u8; 32]>::from(Sha256::digest(&bytes)),
                "{}",
                file.name
            );
            (file.name.clone(), Arc::from(bytes))
        })
        .collect()
}

/// The mesh file of the `index`-th object.
fn mesh(scene: &Scene, index: usize) -> &render::MeshFile {
    match &scene.objects[index].shape {
        Shape::Mesh(m) => &m.file,
        other => panic!("objects[{index}] is not a mesh: {other:?}"),
    }
}

#[test]
fn bound_files_render_the_same_bytes_as_the_files_on_disk() {
    let fixture = fixture();
    let beside = MeshFiles::beside(fixture.dir.path());
    let from_disk = parse_scene_with(&fixture.text, &beside).unwrap();
    let read = beside.files_read();

    // Each file once, by name, sorted; buffer files by the shared rule, data URIs not.
    let absolute = fixture.names.last().unwrap().clone();
    let mut expected: Vec<String> = fixture
        .names
        .iter()
        .cloned()
        .chain([
            buffer_name("models/ship.gltf", "bin/ship.bin"),
            buffer_name("models/up.gltf", "../shared/up.bin"),
        ])
        .collect();
    expected.sort();
    expected.dedup();
    let names: Vec<&str> = read.iter().map(|f| f.name.as_str()).collect();
    assert_eq!(names, expected);
    assert!(names.contains(&"models/bin/ship.bin") && names.contains(&"shared/up.bin"));
    assert!(names.contains(&absolute.as_str()));
    assert_eq!(
        read.iter()
            .find(|f| f.name == absolute)
            .unwrap()
            .path
            .to_str(),
        Some(&*absolute)
    );

    let bound = MeshFiles::bound(bind(&read));
    let from_memory = parse_scene_with(&fixture.text, &bound).unwrap();
    for (i, name) in fixture.names.iter().enumerate() {
        let (disk, memory) = (mesh(&from_disk, i + 1), mesh(&from_memory, i + 1));
        assert_eq!(disk.sha256, memory.sha256, "{name}");
        assert_eq!(disk.geometry.data, memory.geometry.data, "{name}");
        assert_eq!(memory.path.to_str(), Some(name.as_str()));
    }
    // One file under two names: one geometry, in either scene.
    let twice = fixture.names.len() - 1;
    assert!(Arc::ptr_eq(
        &mesh(&from_memory, 1).geometry,
        &mesh(&from_memory, twice).geometry
    ));
    let image = render_scene(&from_disk);
    assert_same(&image, &render_scene(&from_memory), "bound files");
    // The meshes are in view: without them, a tenth of the picture or more changes.
    let start = fixture.text.find("{\"type\": \"mesh\"").unwrap();
    let floor = fixture.text[..start]
        .trim_end()
        .trim_end_matches(',')
        .to_owned()
        + "\n  ]\n}";
    let floor = render_scene(&parse_scene_with(&floor, &MeshFiles::none()).unwrap());
    assert!(differing_pixels(&image, &floor) > 120 * 80 / 10);

    // Read from memory, the same files are recorded, each where it was found.
    let again: Vec<_> = bound
        .files_read()
        .into_iter()
        .map(|f| {
            assert_eq!(f.path.to_str(), Some(f.name.as_str()));
            (f.name, f.sha256, f.size)
        })
        .collect();
    let first: Vec<_> = read
        .into_iter()
        .map(|f| (f.name, f.sha256, f.size))
        .collect();
    assert_eq!(again, first);
}

#[test]
fn a_file_not_sent_is_one_line_naming_it() {
    let fixture = fixture();
    let beside = MeshFiles::beside(fixture.dir.path());
    parse_scene_with(&fixture.text, &beside).unwrap();
    let mut files = bind(&beside.files_read());

    files.remove("models/bin/ship.bin");
    let error = parse_scene_with(&fixture.text, &MeshFiles::bound(files.clone()))
        .unwrap_err()
        .to_string();
    assert_eq!(
        error,
        "objects[9].file: models/ship.gltf: buffers[0] (\"bin/ship.bin\"): \
         models/bin/ship.bin: not among the files sent with the scene"
    );

    files.remove("model.ply");
    let error = parse_scene_with(&fixture.text, &MeshFiles::bound(files))
        .unwrap_err()
        .to_string();
    assert_eq!(
        error,
        "objects[3].file: model.ply: not among the files sent with the scene"
    );

    let error = parse_scene_with(&fixture.text, &MeshFiles::none())
        .unwrap_err()
        .to_string();
    assert_eq!(
        error,
        "objects[1].file: a mesh file cannot be read here: the scene names a mesh file but \
         no files were given with it"
    );
}

#[test]
fn a_cache_shares_geometry_across_scenes_and_drops_what_does_not_fit() {
    let fixture = fixture();
    let beside = MeshFiles::beside(fixture.dir.path());
    let reference = parse_scene_with(&fixture.text, &beside).unwrap();
    let files = bind(&beside.files_read());
    let distinct = (1..=fixture.names.len())
        .map(|i| mesh(&reference, i).sha256)
        .collect::<std::collections::BTreeSet<_>>()
        .len();

    let cache = GeometryCache::new(1_000);
    let parse = |cache: &GeometryCache| {
        let bound = MeshFiles::bound(files.clone()).with_cache(cache);
        parse_scene_with(&fixture.text, &bound).unwrap()
    };
    let first = parse(&cache);
    let stats = cache.stats();
    assert_eq!(
        (stats.entries, stats.hits, stats.misses),
        (distinct, 0, distinct as u64)
    );
    assert_eq!(stats.triangles, 8 * distinct as u64);
    let second = parse(&cache.clone());
    assert_eq!(cache.stats().hits, distinct as u64);
    assert_eq!(cache.stats().misses, distinct as u64);
    for i in 1..=fixture.names.len() {
        assert!(Arc::ptr_eq(
            &mesh(&first, i).geometry,
            &mesh(&second, i).geometry
        ));
        assert_eq!(mesh(&first, i).sha256, mesh(&reference, i).sha256);
    }
    assert_same(&render_scene(&reference), &render_scene(&second), "cached");

    // Room for two: each scene reads every file again, and the cache keeps the last two.
    let small = GeometryCache::new(16);
    let (a, b) = (parse(&small), parse(&small));
    assert!(!Arc::ptr_eq(&mesh(&a, 1).geometry, &mesh(&b, 1).geometry));
    assert_eq!((small.stats().entries, small.stats().triangles), (2, 16));
    assert_eq!(small.stats().hits, 0);
    // Smaller than one: nothing kept, every geometry still used.
    let none = GeometryCache::new(7);
    assert_same(
        &render_scene(&reference),
        &render_scene(&parse(&none)),
        "nothing kept",
    );
    assert_eq!(none.stats().entries, 0);
}
