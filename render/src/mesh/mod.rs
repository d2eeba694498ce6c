//! Triangle meshes read from files (the scene format, section 8): what a reader gives,
//! and what every reader shares; and the geometry every object that shows a file
//! shares, with what the tracer builds from it once (`accel`).
//!
//! Below the scene model, which holds mesh files, and above only the generic bounding
//! volume hierarchy: the readers know nothing of how meshes are traced.

pub(crate) mod accel;
pub mod gltf;
pub mod load;
pub mod obj;
pub mod ply;
pub mod stl;

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, OnceLock};

use thiserror::Error;

/// A corner without a normal of the file's ([`MeshData::corner_normals`]).
pub const NO_NORMAL: u32 = u32::MAX;

/// A mesh as its file gives it, before any transform: triangles numbered in file order
/// (faces split as fans), which is the order that breaks ties between them.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct MeshData {
    pub positions: Vec<[f64; 3]>,
    /// The file's normals, if it has any.
    pub normals: Vec<[f64; 3]>,
    /// Each triangle's three vertices, indices into `positions`.
    pub triangles: Vec<[u32; 3]>,
    /// Each triangle's corners' normals, indices into `normals`, [`NO_NORMAL`] where the
    /// file gives none.
    pub corner_normals: Vec<[u32; 3]>,
}

/// A mesh file as a scene names it: the name as written, its SHA-256 (which a state
/// file records; for a glTF, over the file and then the buffer files it reads), and its
/// geometry, shared by every object and every file of the
/// same bytes.
pub struct MeshFile {
    /// The `file` string of the scene.
    pub name: String,
    /// Where it was read: `name` resolved against the scene's directory.
    pub path: PathBuf,
    pub sha256: [u8; 32],
    pub geometry: Arc<MeshGeometry>,
}

impl MeshFile {
    /// The SHA-256 in lower-case hexadecimal.
    pub fn sha256_hex(&self) -> String {
        self.sha256.iter().map(|b| format!("{b:02x}")).collect()
    }
}

impl PartialEq for MeshFile {
    fn eq(&self, other: &Self) -> bool {
        self.name == other.name && self.sha256 == other.sha256
    }
}

impl std::fmt::Debug for MeshFile {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("MeshFile")
            .field("name", &self.name)
            .field("sha256", &self.sha256_hex())
            .field("triangles", &self.geometry.data.triangles.len())
            .finish()
    }
}

/// A mesh's triangles and what the tracer builds from them once, whatever the number
/// of objects that use it.
pub struct MeshGeometry {
    pub data: MeshData,
    /// The tracer's hierarchy over the triangles, built on first use.
    pub(crate) prepared: OnceLock<accel::MeshAccel>,
}

impl std::fmt::Debug for MeshGeometry {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("MeshGeometry")
            .field("triangles", &self.data.triangles.len())
            .finish()
    }
}

impl MeshGeometry {
    pub fn new(data: MeshData) -> Self {
        MeshGeometry {
            data,
            prepared: OnceLock::new(),
        }
    }
}

/// Where the mesh files a scene names come from: the directory of the scene file, or
/// nowhere (a scene given as text alone, as a farm receives it).
#[derive(Clone, Debug, Default)]
pub struct MeshFiles {
    dir: Option<PathBuf>,
    /// Files read so far, by SHA-256, so that copies of one file (or one file under
    /// two names) hold their geometry once; and by name, so that a file named by many
    /// objects is read once.
    by_hash: Arc<Mutex<HashMap<[u8; 32], Arc<MeshGeometry>>>>,
    by_name: Arc<Mutex<HashMap<String, Arc<MeshFile>>>>,
}

impl MeshFiles {
    /// No mesh files: a scene that names one is refused.
    pub fn none() -> Self {
        MeshFiles::default()
    }

    /// Mesh files relative to `dir`, the scene file's directory.
    pub fn beside(dir: impl Into<PathBuf>) -> Self {
        MeshFiles {
            dir: Some(dir.into()),
            ..MeshFiles::default()
        }
    }

    /// The directory names are resolved against, if files may be read at all.
    pub fn dir(&self) -> Option<&Path> {
        self.dir.as_deref()
    }

    /// The file `name` (as a scene writes it), read and checked, or one line saying
    /// why not, starting with the file's path.
    pub fn get(&self, name: &str) -> Result<Arc<MeshFile>, String> {
        let Some(dir) = &self.dir else {
            return Err(
                "a mesh file cannot be read here: a scene with meshes is rendered from its \
                 file by `tessera render` (a farm does not render meshes yet)"
                    .into(),
            );
        };
        if let Some(file) = lock(&self.by_name).get(name) {
            return Ok(file.clone());
        }
        let path = dir.join(name);
        let bytes = load::read(&path)?;
        // Read before the bytes are compared: a glTF's buffers are part of what it is.
        let (data, sha256) = load::parse_hashed(&path, &bytes)?;
        drop(bytes);
        let geometry = lock(&self.by_hash)
            .entry(sha256)
            .or_insert_with(|| Arc::new(MeshGeometry::new(data)))
            .clone();
        let file = Arc::new(MeshFile {
            name: name.to_string(),
            path,
            sha256,
            geometry,
        });
        lock(&self.by_name).insert(name.to_string(), file.clone());
        Ok(file)
    }
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

/// Why a mesh file cannot be read; the caller adds the object and the file's name.
#[derive(Clone, Debug, PartialEq, Error)]
pub enum MeshError {
    /// A text format's line (1-based).
    #[error("line {line}: {message}")]
    Line { line: usize, message: String },
    /// A binary format's record (1-based: a facet, a vertex, a face).
    #[error("record {record}: {message}")]
    Record { record: usize, message: String },
    /// A structured format's mistake, saying where in the file's own terms
    /// (`nodes[3]`, `accessors[2]`).
    #[error("{0}")]
    Format(String),
}

/// A number as the text formats write it, read to the nearest double: finite only.
pub(crate) fn number(word: &str) -> Result<f64, String> {
    match word.parse::<f64>() {
        Ok(value) if value.is_finite() => Ok(value),
        _ => Err(format!("{} is not a finite number", quoted(word))),
    }
}

/// How much of a word of a file an error shows.
const SHOWN: usize = 32;

/// The first [`SHOWN`] bytes of `text` (cut on a character) and its length, if it is
/// longer: a file's word in an error, which must stay one short line whatever the file
/// holds (a number of 500 million digits).
fn shown(text: &str) -> (&str, Option<usize>) {
    if text.len() <= 2 * SHOWN {
        return (text, None);
    }
    let mut end = SHOWN;
    while !text.is_char_boundary(end) {
        end -= 1;
    }
    (&text[..end], Some(text.len()))
}

/// A word of a file as an error quotes it (escaped, so on one line): whole if it is
/// short, else its start and its length.
pub(crate) fn quoted(word: &str) -> String {
    match shown(word) {
        (all, None) => format!("{all:?}"),
        (start, Some(len)) => format!("{start:?}… ({len} bytes)"),
    }
}

/// Text of a file an error shows as it is (a JSON value written back, which is on one
/// line): whole if it is short, else its start and its length.
pub(crate) fn cut(text: &str) -> String {
    match shown(text) {
        (all, None) => all.to_owned(),
        (start, Some(len)) => format!("{start}… ({len} bytes)"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn errors_quote_long_words_by_their_start_and_length() {
        assert_eq!(
            number("1e400").unwrap_err(),
            "\"1e400\" is not a finite number"
        );
        let long = "7".repeat(1 << 20);
        assert_eq!(
            number(&long).unwrap_err(),
            format!(
                "\"{}\"… (1048576 bytes) is not a finite number",
                &long[..SHOWN]
            )
        );
        // Cut on a character, and escaped: still one line.
        let text = format!("{}é\n{}", "a".repeat(SHOWN - 1), "b".repeat(100));
        assert_eq!(
            quoted(&text),
            format!("\"{}\"… (134 bytes)", "a".repeat(SHOWN - 1))
        );
        assert_eq!(cut("[1, 2]"), "[1, 2]");
        assert_eq!(
            cut(&"x".repeat(65)),
            format!("{}… (65 bytes)", "x".repeat(SHOWN))
        );
    }
}

#[cfg(test)]
mod fuzz {
    //! Mutations of small valid files of every format: each reader gives a mesh or an
    //! error, never a panic, and never more triangles than the bytes could hold.

    use proptest::prelude::*;

    const OBJ: &str =
        "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvn 0 0 1\nf 1//1 2//1 3//1 4//1\nf -1 -2 -3\n";
    const PLY: &str =
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n\
                       property float z\nelement face 1\nproperty list uchar int vertex_indices\n\
                       end_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n";
    const STL: &str = "solid s\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 0 0\n\
                       vertex 0 1 0\nendloop\nendfacet\nendsolid s\n";

    fn binary_ply() -> Vec<u8> {
        let mut bytes =
            b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\n\
                          property float y\nproperty float z\nelement face 1\n\
                          property list uchar int vertex_indices\nend_header\n"
                .to_vec();
        for v in [[0f32, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]] {
            for x in v {
                bytes.extend_from_slice(&x.to_le_bytes());
            }
        }
        bytes.push(3);
        for i in 0..3i32 {
            bytes.extend_from_slice(&i.to_le_bytes());
        }
        bytes
    }

    /// A glTF of one triangle, its buffer a data URI.
    fn gltf() -> Vec<u8> {
        use base64::Engine;
        let mut bytes = Vec::new();
        for x in [0f32, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0] {
            bytes.extend_from_slice(&x.to_le_bytes());
        }
        let data = base64::engine::general_purpose::STANDARD.encode(&bytes);
        format!(
            r#"{{"asset": {{"version": "2.0"}}, "scenes": [{{"nodes": [0]}}], "nodes": [{{"mesh": 0, "translation": [1, 2, 3]}}],
            "meshes": [{{"primitives": [{{"attributes": {{"POSITION": 0}}}}]}}],
            "buffers": [{{"byteLength": 36, "uri": "data:application/octet-stream;base64,{data}"}}],
            "bufferViews": [{{"buffer": 0, "byteLength": 36}}],
            "accessors": [{{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3"}}]}}"#
        )
        .into_bytes()
    }

    /// `bytes` with each (position, byte) of `edits` written over it, and cut to
    /// `keep` of its length.
    fn mutate(bytes: &[u8], edits: &[(usize, u8)], keep: f64) -> Vec<u8> {
        let mut out = bytes.to_vec();
        for &(at, byte) in edits {
            let len = out.len();
            out[at % len] = byte;
        }
        out.truncate((out.len() as f64 * keep) as usize);
        out
    }

    fn check(result: Result<super::MeshData, super::MeshError>, len: usize) {
        if let Ok(mesh) = result {
            // A triangle needs at least a byte of the file; a corner, a vertex read.
            assert!(mesh.triangles.len() <= len.max(1) * 2);
            assert_eq!(mesh.triangles.len(), mesh.corner_normals.len());
            let n = mesh.positions.len() as u32;
            assert!(mesh.triangles.iter().flatten().all(|&v| v < n));
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(256))]
        #[test]
        fn mutated_files_never_panic(
            edits in proptest::collection::vec((0usize..4096, any::<u8>()), 0..8),
            keep in 0.0f64..=1.0,
        ) {
            let none = |name: &str| Err(format!("no file {name}"));
            let gltf = gltf();
            assert_eq!(super::gltf::read_gltf(&gltf, &none).map(|m| m.triangles.len()), Ok(1));
            for original in [OBJ.as_bytes(), PLY.as_bytes(), STL.as_bytes(), &binary_ply(), &gltf] {
                let bytes = mutate(original, &edits, keep);
                let len = bytes.len();
                if let Ok(text) = std::str::from_utf8(&bytes) {
                    check(super::obj::read(text), len);
                }
                check(super::ply::read(&bytes), len);
                check(super::stl::read(&bytes), len);
                check(super::gltf::read_gltf(&bytes, &none), len);
                check(super::gltf::read_glb(&bytes, &none), len);
            }
        }
    }
}
