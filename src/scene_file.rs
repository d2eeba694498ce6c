//! Reading scene files: whole, for a job a coordinator will check; checked here by the
//! renderer's loader, for a scene a local farm will serve; or in parallel parts, for a
//! render on this machine.

use std::path::Path;
use std::sync::Arc;

use anyhow::{anyhow, Context, Result};
use coordinator::client::LocalFile;
use serde_json::Value;
use sha2::Digest;

/// A scene file's text, for a farm: the coordinator checks it.
pub fn read_scene(path: &Path) -> Result<String> {
    std::fs::read_to_string(path)
        .with_context(|| format!("cannot read scene file {}", path.display()))
}

/// The files the scene `text` (of the file at `path`) names, hashed, for a farm: what
/// the renderer reads when it reads the scene from its file, each once. A scene that
/// names no mesh reads none (and is not parsed here: the coordinator checks it); one
/// whose files cannot be read is refused here, in `tessera render`'s words.
pub fn scene_files(path: &Path, text: &str) -> Result<Vec<LocalFile>> {
    if first_mesh(text).is_none() {
        return Ok(Vec::new());
    }
    let files = render::MeshFiles::beside(scene_dir(path));
    render::parse_animated_with(text, &files).map_err(|e| anyhow!("{}: {e}", path.display()))?;
    Ok(files
        .files_read()
        .into_iter()
        .map(|f| LocalFile {
            asset: protocol::AssetRef {
                name: f.name,
                key: protocol::AssetKey {
                    sha256: f.sha256,
                    size: f.size,
                },
            },
            path: f.path,
        })
        .collect())
}

/// The first object of type `mesh` in a scene's text: its index and, if it names one,
/// its file. A text that is not JSON has none (the coordinator says what is wrong with
/// it). Without `mesh` in it, even \u-escaped, a text has none and is not read again.
fn first_mesh(text: &str) -> Option<(usize, Option<String>)> {
    if !text.contains("mesh") && !text.contains("\\u") {
        return None;
    }
    let root: Value = serde_json::from_str(text).ok()?;
    root.get("objects")?
        .as_array()?
        .iter()
        .enumerate()
        .find(|(_, object)| object.get("type").and_then(Value::as_str) == Some("mesh"))
        .map(|(i, object)| {
            let file = object
                .get("file")
                .and_then(Value::as_str)
                .map(str::to_owned);
            (i, file)
        })
}

/// A scene file's text for a studio, checked by the renderer's loader, with the files
/// it reads (for a scene file, relative to its directory as `tessera render` reads
/// them; for an archive, its members), each read into memory once and bound to its
/// content: the coordinator puts them in its store and the page edits the scene with
/// them. An error is one line prefixed with the file.
pub fn read_studio_scene(path: &Path) -> Result<coordinator::server::StudioScene> {
    let name = |n: &std::ffi::OsStr| n.to_string_lossy().into_owned();
    if is_archive(path) {
        let archive = read_archive(path)?;
        let files = render::MeshFiles::bound(archive.files.clone());
        render::parse_animated_with(&archive.text, &files)
            .map_err(|e| anyhow!("{}: {e}", path.display()))?;
        let read = files
            .files_read()
            .into_iter()
            .map(|f| (f.name.clone(), Arc::clone(&archive.files[&f.name])))
            .collect();
        return Ok(coordinator::server::StudioScene {
            text: archive.text,
            file: archive.scene_name,
            files: read,
        });
    }
    let text = read_scene(path)?;
    let file = path.file_name().map(name).unwrap_or_default();
    if first_mesh(&text).is_none() {
        render::parse_scene(&text).map_err(|e| anyhow!("{}: {e}", path.display()))?;
        return Ok(coordinator::server::StudioScene {
            text,
            file,
            files: Vec::new(),
        });
    }
    let mut files = Vec::new();
    for local in scene_files(path, &text)? {
        let bytes = std::fs::read(&local.path)
            .with_context(|| format!("cannot read {}", local.path.display()))?;
        if <[u8; 32]>::from(sha2::Sha256::digest(&bytes)) != local.asset.key.sha256 {
            anyhow::bail!(
                "{}: {} changed while it was read: open the scene again",
                path.display(),
                local.path.display()
            );
        }
        files.push((local.asset.name, Arc::from(bytes)));
    }
    Ok(coordinator::server::StudioScene { text, file, files })
}

/// Whether `path` names a scene saved with its mesh files: a `.tar` archive
/// ([`coordinator::archive`]), by its extension, case-insensitive.
pub fn is_archive(path: &Path) -> bool {
    path.extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("tar"))
}

/// A scene archive's scene and files, read whole into memory and checked (names,
/// sizes, every mesh object's file present): one line prefixed with the archive.
pub fn read_archive(path: &Path) -> Result<coordinator::archive::SceneArchive> {
    let file = std::fs::File::open(path)
        .with_context(|| format!("cannot read scene archive {}", path.display()))?;
    coordinator::archive::read(std::io::BufReader::new(file))
        .map_err(|e| anyhow!("{}: {e}", path.display()))
}

/// The directory a scene file's mesh files are relative to: the file's own.
pub fn scene_dir(path: &Path) -> std::path::PathBuf {
    match path.parent() {
        Some(dir) if !dir.as_os_str().is_empty() => dir.to_path_buf(),
        _ => std::path::PathBuf::from("."),
    }
}

/// Files from this size are read in parallel parts, one per thread of the pool.
const PARALLEL_READ_MIN: u64 = 16 << 20;

/// The scene file's text. A large file is read in as many parts as the current rayon
/// pool has threads, each copied from the page cache by its own thread: one thread
/// copying a 186 MB scene of a million spheres took as long as rendering it.
pub fn read_in_parallel(path: &Path) -> std::io::Result<String> {
    use std::os::unix::fs::FileExt;
    let file = std::fs::File::open(path)?;
    let len = file.metadata()?.len();
    let threads = rayon::current_num_threads();
    if len < PARALLEL_READ_MIN || threads < 2 {
        return std::fs::read_to_string(path);
    }
    let len = usize::try_from(len).map_err(|_| std::io::ErrorKind::OutOfMemory)?;
    let mut bytes = vec![0u8; len];
    let part = len.div_ceil(threads);
    let mut parts: Vec<(usize, &mut [u8])> = bytes
        .chunks_mut(part)
        .enumerate()
        .map(|(i, chunk)| (i * part, chunk))
        .collect();
    use rayon::prelude::*;
    parts
        .par_iter_mut()
        .try_for_each(|(offset, chunk)| file.read_exact_at(chunk, *offset as u64))?;
    // Worded as `read_to_string` words it for a smaller file.
    String::from_utf8(bytes).map_err(|_| {
        std::io::Error::new(
            std::io::ErrorKind::InvalidData,
            "stream did not contain valid UTF-8",
        )
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pool(threads: usize) -> rayon::ThreadPool {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
    }

    #[test]
    fn a_scene_names_files_only_with_a_mesh_object_and_each_is_hashed_for_a_farm() {
        let scene = |objects: &str| {
            format!(
                r#"{{"camera": {{"position": "0 0 -5", "look_at": "0 0 0"}}, "lights": [],
                    "objects": [{objects}]}}"#
            )
        };
        let sphere = r#"{"type": "sphere", "center": "0 0 0", "radius": 1, "color": "1 1 1 0"}"#;
        let triangle = r#"{"type": "triangle", "vertices": ["0 0 0", "1 0 0", "0 1 0"],
                           "color": "1 1 1 0"}"#;
        let cube = r#"{"type": "box", "min": "0 0 0", "max": "1 1 1", "color": "1 1 1 0"}"#;
        let mesh = r#"{"type": "mesh", "file": "meshes/bunny.ply", "color": "1 1 1 0"}"#;
        // Spheres, planes, triangles and boxes go to a farm; a `mesh` named anywhere else
        // (a file called mesh.json, a value) is not an object.
        for text in [
            scene(sphere),
            scene(&format!("{triangle}, {cube}")),
            scene(
                r#"{"type": "sphere", "center": "0 0 0", "radius": 1, "color": "1 1 1",
                      "note": "mesh"}"#,
            )
            .replace("\"lights\": []", "\"lights\": [], \"mesh\": \"mesh\""),
            "not JSON, mesh".to_owned(),
        ] {
            assert_eq!(first_mesh(&text), None, "{text}");
        }
        let text = scene(&format!("{sphere}, {triangle}, {mesh}, {mesh}"));
        assert_eq!(
            first_mesh(&text),
            Some((2, Some("meshes/bunny.ply".to_owned())))
        );
        // Written with escapes, or without a file, a mesh is still one.
        let escaped = scene(r#"{"type": "m\u0065sh", "color": "1 1 1 0"}"#);
        assert!(!escaped.contains("mesh"));
        assert_eq!(first_mesh(&escaped), Some((0, None)));
        // The files a mesh scene reads, from the scene file's directory, each hashed.
        let dir = tempfile::tempdir().unwrap();
        std::fs::create_dir(dir.path().join("meshes")).unwrap();
        let obj = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n";
        std::fs::write(dir.path().join("meshes/tri.obj"), obj).unwrap();
        let mesh = r#"{"type": "mesh", "file": "meshes/tri.obj", "color": "1 1 1 0"}"#;
        let text = scene(&format!("{mesh}, {sphere}, {mesh}"));
        let path = dir.path().join("s.json");
        let files = scene_files(&path, &text).unwrap();
        assert_eq!(files.len(), 1, "{files:?}");
        assert_eq!(files[0].asset.name, "meshes/tri.obj");
        assert_eq!(files[0].asset.key.size, obj.len() as u64);
        assert_eq!(files[0].asset.key.sha256, assets::AssetId::of(obj).sha256);
        assert!(scene_files(&path, &scene(sphere)).unwrap().is_empty());
        // A file that is not there is the loader's one line, prefixed with the scene.
        let missing = scene(r#"{"type": "mesh", "file": "gone.obj", "color": "1 1 1 0"}"#);
        let error = scene_files(&path, &missing).unwrap_err().to_string();
        assert!(
            error.starts_with(&format!("{}: objects[0]", path.display())),
            "{error}"
        );
        assert!(error.contains("gone.obj"), "{error}");
    }

    #[test]
    fn a_large_scene_file_read_in_parts_is_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("large.json");
        // Not a multiple of the part size, with multi-byte characters across the parts.
        let line = "{\"type\": \"sphere\", \"name\": \"é€\"}\n";
        let text = line.repeat((PARALLEL_READ_MIN as usize) / line.len() + 1234);
        std::fs::write(&path, &text).unwrap();
        for threads in [1, 2, 3] {
            let read = pool(threads).install(|| read_in_parallel(&path)).unwrap();
            assert!(read == text, "{threads} threads");
        }
        // A byte that is not UTF-8 is the same one-line error as for a small file.
        let mut bytes = text.into_bytes();
        bytes.push(0xff);
        std::fs::write(&path, &bytes).unwrap();
        let error = pool(2).install(|| read_in_parallel(&path)).unwrap_err();
        std::fs::write(&path, b"{}\xff").unwrap();
        let small = std::fs::read_to_string(&path).unwrap_err();
        assert_eq!(error.to_string(), small.to_string());
    }
}
