//! Triangle meshes read from files (the scene format, section 8): what a reader gives,
//! and what every reader shares.

pub mod gltf;
pub mod obj;
pub mod ply;
pub mod stl;

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
        _ => Err(format!("{word:?} is not a finite number")),
    }
}
