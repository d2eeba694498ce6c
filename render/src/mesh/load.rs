//! Reading a mesh file named by a scene: the reader chosen by the extension, the file's
//! size and triangle count held to the renderer's limits, and a mesh with nothing to
//! hit refused, each mistake one line naming the file.

use std::path::Path;

use super::MeshData;
use crate::limits::{MAX_MESH_FILE_BYTES, MAX_MESH_TRIANGLES};

/// The mesh in the file at `path` (`.obj`, `.ply`, `.stl`, `.gltf` or `.glb`, in any
/// case), or one line saying what is wrong, starting with the file's path.
pub fn load(path: &Path) -> Result<MeshData, String> {
    let bytes = read(path)?;
    parse(path, &bytes)
}

/// The bytes of the mesh file at `path`, held to the file size limit, or one line
/// starting with the file's path.
pub fn read(path: &Path) -> Result<Vec<u8>, String> {
    use std::io::Read;
    let name = shown(path);
    let file = std::fs::File::open(path).map_err(|e| format!("{name}: cannot read it: {e}"))?;
    let mut bytes = Vec::new();
    // One byte more than the limit tells a file that is too large, whatever its
    // metadata claims (a pipe, a file still growing).
    file.take(MAX_MESH_FILE_BYTES + 1)
        .read_to_end(&mut bytes)
        .map_err(|e| format!("{name}: cannot read it: {e}"))?;
    if bytes.len() as u64 > MAX_MESH_FILE_BYTES {
        return Err(format!(
            "{name}: more than the limit of {MAX_MESH_FILE_BYTES} bytes for a mesh file"
        ));
    }
    Ok(bytes)
}

/// The mesh in `bytes`, read from the file at `path` (whose extension chooses the
/// reader, and beside which a glTF finds its buffers).
pub fn parse(path: &Path, bytes: &[u8]) -> Result<MeshData, String> {
    parse_hashed(path, bytes).map(|(mesh, _)| mesh)
}

/// [`parse`], and the SHA-256 of what the mesh was read from: the file's bytes, then
/// those of each buffer file it named, in the order read. For a file that names no
/// other file, that is the file's own SHA-256.
pub fn parse_hashed(path: &Path, bytes: &[u8]) -> Result<(MeshData, [u8; 32]), String> {
    use sha2::{Digest, Sha256};
    let hasher = std::cell::RefCell::new(Sha256::new());
    hasher.borrow_mut().update(bytes);
    let beside = |uri: &str| {
        let file = path.parent().unwrap_or(Path::new(".")).join(uri);
        let buffer = read(&file)?;
        hasher.borrow_mut().update(&buffer);
        Ok(buffer)
    };
    let mesh = parse_with(path, bytes, &beside)?;
    Ok((mesh, hasher.into_inner().finalize().into()))
}

/// The mesh in `bytes`, the file `path` names (its extension chooses the reader, and
/// an error starts with it), a glTF's buffer files given by `file` from their uris:
/// read from a directory or from the files sent with a scene alike.
pub(crate) fn parse_with(
    path: &Path,
    bytes: &[u8],
    file: &dyn Fn(&str) -> Result<Vec<u8>, String>,
) -> Result<MeshData, String> {
    let name = shown(path);
    let extension = extension(path);
    let mesh = match extension.as_str() {
        "obj" => {
            // The lines the reader ignores (materials, groups, comments) may be in any
            // encoding: a byte that is not UTF-8 becomes U+FFFD, which no number or
            // index is, so it is an error on its own line where it matters.
            super::obj::read(&String::from_utf8_lossy(bytes))
        }
        "ply" => super::ply::read(bytes),
        "stl" => super::stl::read(bytes),
        "gltf" => super::gltf::read_gltf(bytes, file),
        "glb" => super::gltf::read_glb(bytes, file),
        _ => {
            return Err(format!(
                "{name}: unknown mesh format {extension:?}: .obj, .ply, .stl, .gltf or .glb"
            ))
        }
    }
    .map_err(|e| format!("{name}: {e}"))?;
    if mesh.triangles.len() > MAX_MESH_TRIANGLES {
        return Err(format!(
            "{name}: {} triangles, more than the limit of {MAX_MESH_TRIANGLES}",
            mesh.triangles.len()
        ));
    }
    if !mesh.triangles.iter().any(|t| !degenerate(&mesh, *t)) {
        return Err(format!(
            "{name}: no triangle that is not degenerate: nothing to hit"
        ));
    }
    Ok(mesh)
}

/// The extension of `path` in lower case, which chooses the reader (empty if none).
pub(crate) fn extension(path: &Path) -> String {
    path.extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase)
        .unwrap_or_default()
}

/// A path as an error names it: as it is, or quoted and escaped if it holds a line
/// break or another control character (a scene's `file` may hold any), so that the
/// error stays one line.
pub fn shown(path: &Path) -> String {
    let text = path.display().to_string();
    if text.chars().any(char::is_control) {
        format!("{text:?}")
    } else {
        text
    }
}

/// Whether (v1 − v0) × (v2 − v0) is exactly zero in double, in the file's coordinates:
/// such a triangle is never hit (the scene format, section 8).
pub fn degenerate(mesh: &MeshData, [a, b, c]: [u32; 3]) -> bool {
    let p = |i: u32| mesh.positions[i as usize];
    let (v0, v1, v2) = (p(a), p(b), p(c));
    let e1 = [v1[0] - v0[0], v1[1] - v0[1], v1[2] - v0[2]];
    let e2 = [v2[0] - v0[0], v2[1] - v0[1], v2[2] - v0[2]];
    let cross = [
        e1[1] * e2[2] - e1[2] * e2[1],
        e1[2] * e2[0] - e1[0] * e2[2],
        e1[0] * e2[1] - e1[1] * e2[0],
    ];
    cross == [0.0; 3]
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A file of `text` under a fresh directory of the system's temporary one.
    fn file(name: &str, text: &[u8]) -> std::path::PathBuf {
        let dir = std::env::temp_dir().join(format!(
            "tessera-mesh-load-{}-{}",
            std::process::id(),
            name.replace('.', "-")
        ));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join(name);
        std::fs::write(&path, text).unwrap();
        path
    }

    #[test]
    fn the_extension_chooses_the_reader_in_any_case() {
        let path = file("Tri.OBJ", b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n");
        assert_eq!(load(&path).unwrap().triangles, vec![[0, 1, 2]]);
        let unknown = file("tri.off", b"OFF\n");
        assert!(load(&unknown)
            .unwrap_err()
            .ends_with("unknown mesh format \"off\": .obj, .ply, .stl, .gltf or .glb"));
        for made in [path, unknown] {
            std::fs::remove_dir_all(made.parent().unwrap()).unwrap();
        }
    }

    #[test]
    fn bytes_that_are_not_utf8_matter_only_where_numbers_are() {
        // A material named in Latin-1 is ignored like any material.
        let path = file(
            "latin1.obj",
            b"usemtl caf\xe9\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
        );
        assert_eq!(load(&path).unwrap().triangles, vec![[0, 1, 2]]);
        let bad = file("latin1-number.obj", b"v 0 0 0\nv 1 \xe9 0\n");
        assert_eq!(
            load(&bad).unwrap_err(),
            format!(
                "{}: line 2: \"\u{fffd}\" is not a finite number",
                bad.display()
            )
        );
        for made in [path, bad] {
            std::fs::remove_dir_all(made.parent().unwrap()).unwrap();
        }
    }

    #[test]
    fn a_name_with_a_line_break_is_quoted_on_one_line() {
        let missing = std::env::temp_dir().join("tessera-no-such\nmesh.obj");
        let error = load(&missing).unwrap_err();
        assert!(
            error.starts_with(&format!(
                "{:?}: cannot read it",
                missing.display().to_string()
            )),
            "{error}"
        );
        assert_eq!(error.lines().count(), 1);
    }

    #[test]
    fn mistakes_name_the_file_and_the_line() {
        let path = file("bad.obj", b"v 0 0 0\nv 1 x 0\n");
        assert_eq!(
            load(&path).unwrap_err(),
            format!("{}: line 2: \"x\" is not a finite number", path.display())
        );
        let flat = file("flat.obj", b"v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n");
        assert!(load(&flat)
            .unwrap_err()
            .ends_with("no triangle that is not degenerate: nothing to hit"));
        let missing = std::env::temp_dir().join("tessera-no-such-mesh.obj");
        assert!(load(&missing).unwrap_err().contains("cannot read it"));
        for made in [path, flat] {
            std::fs::remove_dir_all(made.parent().unwrap()).unwrap();
        }
    }
}
