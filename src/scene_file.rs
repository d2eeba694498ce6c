//! Reading scene files: whole, for a job a coordinator will check; checked here by the
//! renderer's loader, for a scene a local farm will serve; or in parallel parts, for a
//! render on this machine.

use std::path::Path;

use anyhow::{anyhow, bail, Context, Result};
use serde_json::Value;

/// A scene file's text, for a farm: the coordinator checks it. A scene with mesh
/// objects is refused here, in one line: their files are on this machine, which a
/// farm's workers never see, and a farm does not render meshes yet.
pub fn read_scene(path: &Path) -> Result<String> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("cannot read scene file {}", path.display()))?;
    refuse_meshes(path, &text)?;
    Ok(text)
}

/// One line naming the first mesh object of the scene file at `path`, if it has any.
fn refuse_meshes(path: &Path, text: &str) -> Result<()> {
    if let Some((object, file)) = first_mesh(text) {
        let place = match file {
            Some(file) => format!("objects[{object}].file: {file}"),
            None => format!("objects[{object}]"),
        };
        bail!(
            "{}: {place}: a farm does not render meshes yet (their mesh files are not sent to \
             workers): render this scene on this machine with `tessera render`",
            path.display()
        );
    }
    Ok(())
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

/// A scene file's text, checked by the renderer's loader: its error is one line
/// prefixed with the file.
pub fn read_checked_scene(path: &Path) -> Result<String> {
    let text = read_scene(path)?;
    render::parse_scene(&text).map_err(|e| anyhow!("{}: {e}", path.display()))?;
    Ok(text)
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
    fn a_scene_with_a_mesh_is_refused_for_a_farm_naming_its_first_mesh() {
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
        assert_eq!(
            refuse_meshes(Path::new("scenes/bunny.json"), &text)
                .unwrap_err()
                .to_string(),
            "scenes/bunny.json: objects[2].file: meshes/bunny.ply: a farm does not render \
             meshes yet (their mesh files are not sent to workers): render this scene on this \
             machine with `tessera render`"
        );
        // Written with escapes, or without a file, a mesh is still one.
        let escaped = scene(r#"{"type": "m\u0065sh", "color": "1 1 1 0"}"#);
        assert!(!escaped.contains("mesh"));
        assert_eq!(first_mesh(&escaped), Some((0, None)));
        assert_eq!(
            refuse_meshes(Path::new("s.json"), &escaped)
                .unwrap_err()
                .to_string(),
            "s.json: objects[0]: a farm does not render meshes yet (their mesh files are not \
             sent to workers): render this scene on this machine with `tessera render`"
        );
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
