//! Triangle meshes read from files (the scene format, section 8): what a reader gives,
//! and what every reader shares; where the files come from and which were read
//! (`files`); and the geometry every object that shows a file shares, with what the
//! tracer builds from it once (`accel`), kept across scenes if asked (`cache`).
//!
//! Below the scene model, which holds mesh files, and above only the generic bounding
//! volume hierarchy: the readers know nothing of how meshes are traced.

pub(crate) mod accel;
mod cache;
mod files;
pub mod gltf;
pub mod load;
pub mod obj;
pub mod ply;
pub mod stl;

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, OnceLock};

use thiserror::Error;

pub use cache::{CacheStats, GeometryCache};
pub use files::{buffer_name, FileRead};

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
    /// Where it was read: `name` resolved against the scene's directory (for a file
    /// sent with the scene, `name` itself).
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

/// Where the mesh files a scene names come from: the directory of the scene file, the
/// files sent with the scene (bound in memory by name, as a farm's worker holds them),
/// or nowhere (a scene given as text alone). Every file read is recorded
/// ([`MeshFiles::files_read`]), and geometry may be shared across scenes through a
/// [`GeometryCache`].
#[derive(Clone, Debug, Default)]
pub struct MeshFiles {
    source: files::Source,
    record: Arc<files::Record>,
    cache: Option<GeometryCache>,
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
            source: files::Source::Dir(dir.into()),
            ..MeshFiles::default()
        }
    }

    /// The files sent with a scene, by name: a mesh by its `file` string exactly as the
    /// scene writes it, a glTF's buffer file by [`buffer_name`]. A scene parsed with
    /// them reads as it does from the files on disk; a name not among them is an
    /// error naming it.
    pub fn bound(files: BTreeMap<String, Arc<[u8]>>) -> Self {
        MeshFiles {
            source: files::Source::Bound(Arc::new(files)),
            ..MeshFiles::default()
        }
    }

    /// The files given so far with a scene being resolved, by name as in
    /// [`MeshFiles::bound`]: a name the scene reads that is not among them is recorded
    /// ([`MeshFiles::missing`]) and its mesh stands in as one triangle, so that one parse
    /// finds every file the scene names, and a glTF's buffer files once the glTF is
    /// among them. A client learns from it which files to send without knowing the
    /// scene format's rules (the coordinator's `resolve`); a scene is rendered only
    /// from [`MeshFiles::bound`] files.
    pub fn probing(files: BTreeMap<String, Arc<[u8]>>) -> Self {
        MeshFiles {
            source: files::Source::Probe(Arc::new(files), files::Missing::default()),
            ..MeshFiles::default()
        }
    }

    /// The names read but not given, sorted, of files [`MeshFiles::probing`]; none
    /// otherwise.
    pub fn missing(&self) -> Vec<String> {
        match &self.source {
            files::Source::Probe(_, missing) => lock(missing).iter().cloned().collect(),
            _ => Vec::new(),
        }
    }

    /// These files, their geometry found in and kept by `cache`: a file whose bytes
    /// (with a glTF's buffers) were read before, by any scene given the same cache, is
    /// not read again, and its hierarchy is built once for all of them.
    pub fn with_cache(mut self, cache: &GeometryCache) -> Self {
        self.cache = Some(cache.clone());
        self
    }

    /// The directory names are resolved against, if files are read from one.
    pub fn dir(&self) -> Option<&Path> {
        match &self.source {
            files::Source::Dir(dir) => Some(dir),
            _ => None,
        }
    }

    /// Every file read so far (meshes and a glTF's buffer files, not `data:` URIs),
    /// once each, sorted by name, with its own SHA-256: after a scene is parsed from its
    /// file, what must be sent with it for it to read the same elsewhere.
    pub fn files_read(&self) -> Vec<FileRead> {
        self.record.files()
    }

    /// The file `name` (as a scene writes it), read and checked, or one line saying
    /// why not, starting with the file's path.
    pub fn get(&self, name: &str) -> Result<Arc<MeshFile>, String> {
        if matches!(self.source, files::Source::Nowhere) {
            return Err(
                "a mesh file cannot be read here: the scene names a mesh file but no \
                 files were given with it"
                    .into(),
            );
        }
        if let Some(file) = lock(&self.by_name).get(name) {
            return Ok(file.clone());
        }
        match self.read(name) {
            Err(_) if !self.missing().is_empty() => Ok(Arc::new(MeshFile {
                name: name.to_string(),
                path: self.source.path(name),
                sha256: [0; 32],
                geometry: Arc::new(MeshGeometry::new(MeshData {
                    positions: vec![[0.0; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]],
                    triangles: vec![[0, 1, 2]],
                    corner_normals: vec![[NO_NORMAL; 3]],
                    normals: Vec::new(),
                })),
            })),
            read => read,
        }
    }

    /// [`MeshFiles::get`] of a file not read before.
    fn read(&self, name: &str) -> Result<Arc<MeshFile>, String> {
        let reader = files::Reader {
            source: &self.source,
            record: &self.record,
        };
        // Hashed before it is read as a mesh: a glTF's buffers are part of what it is,
        // and geometry already built for the same bytes need not be read again.
        let gathered = reader.gather(name)?;
        let known = gathered
            .sha256
            .and_then(|sha256| Some((sha256, self.known(&sha256)?)));
        let (sha256, geometry) = match known {
            Some(known) => known,
            None => {
                let (data, sha256) = reader.parse(name, gathered)?;
                (sha256, self.keep(sha256, data))
            }
        };
        let file = Arc::new(MeshFile {
            name: name.to_string(),
            path: self.source.path(name),
            sha256,
            geometry,
        });
        lock(&self.by_name).insert(name.to_string(), file.clone());
        Ok(file)
    }

    /// The geometry of bytes of SHA-256 `sha256`, if this scene or the cache holds it.
    fn known(&self, sha256: &[u8; 32]) -> Option<Arc<MeshGeometry>> {
        if let Some(geometry) = lock(&self.by_hash).get(sha256) {
            return Some(geometry.clone());
        }
        let geometry = self.cache.as_ref()?.get(sha256)?;
        lock(&self.by_hash).insert(*sha256, geometry.clone());
        Some(geometry)
    }

    /// `data`, just read from bytes of SHA-256 `sha256`, as the geometry this scene
    /// (and the cache) shares: the one held already if another file had the same bytes.
    fn keep(&self, sha256: [u8; 32], data: MeshData) -> Arc<MeshGeometry> {
        lock(&self.by_hash)
            .entry(sha256)
            .or_insert_with(|| {
                let geometry = Arc::new(MeshGeometry::new(data));
                match &self.cache {
                    Some(cache) => cache.keep(sha256, geometry),
                    None => geometry,
                }
            })
            .clone()
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
    fn probing_finds_every_file_a_scene_reads_a_gltfs_buffers_once_it_is_given() {
        let scene = r#"{"camera": {"position": "0 0 -5", "look_at": "0 0 0", "fov": 40},
            "image": {"width": 8, "height": 8}, "lights": [],
            "objects": [
                {"type": "mesh", "file": "a.obj", "color": "1 1 1 0"},
                {"type": "mesh", "file": "m/ship.gltf", "color": "1 1 1 0"},
                {"type": "mesh", "file": "b.obj", "color": "1 1 1 0"}]}"#;
        let obj: Arc<[u8]> = Arc::from(&b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"[..]);
        let mut bin = Vec::new();
        for x in [0f32, 0., 0., 1., 0., 0., 0., 1., 0.] {
            bin.extend_from_slice(&x.to_le_bytes());
        }
        let gltf = r#"{"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}],
            "nodes": [{"mesh": 0}], "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}],
            "buffers": [{"byteLength": 36, "uri": "ship.bin"}],
            "bufferViews": [{"buffer": 0, "byteLength": 36}],
            "accessors": [{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3"}]}"#;
        let probe = |given: &[(&str, Arc<[u8]>)]| {
            let files = MeshFiles::probing(
                given
                    .iter()
                    .map(|(n, b)| ((*n).to_owned(), b.clone()))
                    .collect(),
            );
            crate::parse_animated_with(scene, &files).unwrap();
            let read: Vec<String> = files.files_read().into_iter().map(|f| f.name).collect();
            (read, files.missing())
        };
        let (read, missing) = probe(&[("a.obj", obj.clone())]);
        assert_eq!(
            (read, missing),
            (
                vec!["a.obj".into()],
                vec!["b.obj".into(), "m/ship.gltf".into()]
            )
        );
        let with_gltf = [
            ("a.obj", obj.clone()),
            ("b.obj", obj.clone()),
            ("m/ship.gltf", Arc::from(gltf.as_bytes())),
        ];
        let (_, missing) = probe(&with_gltf);
        assert_eq!(missing, vec!["m/ship.bin".to_owned()]);
        let mut all = with_gltf.to_vec();
        all.push(("m/ship.bin", Arc::from(bin)));
        let (read, missing) = probe(&all);
        assert!(missing.is_empty(), "{missing:?}");
        assert_eq!(read, ["a.obj", "b.obj", "m/ship.bin", "m/ship.gltf"]);
        // A file given that is not a mesh is the scene's error once nothing is missing.
        let mut broken = all.clone();
        broken[0].1 = Arc::from(&b"not a mesh"[..]);
        let files = MeshFiles::probing(
            broken
                .iter()
                .map(|(n, b)| ((*n).to_owned(), b.clone()))
                .collect(),
        );
        assert!(crate::parse_animated_with(scene, &files).is_err());
    }

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
mod fuzz;
