//! Where the files a scene names come from, and which of them it read.
//!
//! A scene rendered from its file reads its mesh files from the scene's directory. A
//! farm's worker has no such directory: it is given, with the scene, every file the
//! scene may read, bound in memory by name. Both are read through one [`Reader`], which
//! records each file it reads (its name, its own SHA-256, its size), so that a client,
//! parsing a scene from its file once, learns which files to send with it and under
//! which names the worker will ask for them ([`buffer_name`]).

use std::cell::RefCell;
use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::Arc;

use sha2::{Digest, Sha256};

use super::{load, lock, MeshData};
use crate::limits::MAX_MESH_FILE_BYTES;

/// The name of the buffer file `uri` of the glTF file a scene names `mesh_name`: the
/// directory part of `mesh_name` joined with `uri` (or `uri` alone if it is absolute),
/// `.` dropped and `dir/..` folded, lexically. Only `/` separates, as in a URI, so that
/// every machine gives one file one name; the uri is not percent-decoded (nor is it on
/// disk). A leading `..` is kept: the name is still relative to the scene's directory.
///
/// The files sent with a scene are bound under these names, and the record of the files
/// a scene reads gives them, so a client and a worker agree on them by construction.
/// A `data:` URI is not a file and has no name.
pub fn buffer_name(mesh_name: &str, uri: &str) -> String {
    let joined = if uri.starts_with('/') {
        uri.to_owned()
    } else {
        let dir = mesh_name.rfind('/').map_or("", |end| &mesh_name[..=end]);
        format!("{dir}{uri}")
    };
    let absolute = joined.starts_with('/');
    let mut parts: Vec<&str> = Vec::new();
    for part in joined.split('/') {
        match part {
            "" | "." => {}
            ".." => match parts.last() {
                Some(&last) if last != ".." => {
                    parts.pop();
                }
                // Above the root is the root.
                _ if absolute => {}
                _ => parts.push(".."),
            },
            part => parts.push(part),
        }
    }
    let body = parts.join("/");
    match (absolute, body.is_empty()) {
        (true, _) => format!("/{body}"),
        (false, true) => ".".to_owned(),
        (false, false) => body,
    }
}

/// A file a scene read: the name a scene's file or a glTF's buffer gives it (the
/// `file` key as written, or [`buffer_name`]), where it was read, and its own identity.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct FileRead {
    pub name: String,
    /// The name resolved against the scene's directory (for a bound file, the name).
    pub path: PathBuf,
    /// The SHA-256 of this file's bytes alone, whatever else a glTF reads with it.
    pub sha256: [u8; 32],
    pub size: u64,
}

impl FileRead {
    /// The SHA-256 in lower-case hexadecimal.
    pub fn sha256_hex(&self) -> String {
        self.sha256.iter().map(|b| format!("{b:02x}")).collect()
    }
}

/// The names a scene being resolved asked for and was not given.
pub(crate) type Missing = Arc<std::sync::Mutex<std::collections::BTreeSet<String>>>;

/// Where names are read from.
#[derive(Clone, Default)]
pub(crate) enum Source {
    /// Nowhere: a scene given as text alone.
    #[default]
    Nowhere,
    /// The scene file's directory.
    Dir(PathBuf),
    /// The files sent with the scene, by name.
    Bound(Arc<BTreeMap<String, Arc<[u8]>>>),
    /// The files given so far, by name, for a scene being resolved: a name not among
    /// them is recorded as missing ([`MeshFiles::probing`](super::MeshFiles::probing)).
    Probe(Arc<BTreeMap<String, Arc<[u8]>>>, Missing),
}

impl std::fmt::Debug for Source {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Source::Nowhere => f.write_str("Nowhere"),
            Source::Dir(dir) => f.debug_tuple("Dir").field(dir).finish(),
            Source::Bound(files) => f.debug_tuple("Bound").field(&files.keys()).finish(),
            Source::Probe(files, _) => f.debug_tuple("Probe").field(&files.keys()).finish(),
        }
    }
}

impl Source {
    /// Where the file `name` is: what its errors start with.
    pub(crate) fn path(&self, name: &str) -> PathBuf {
        match self {
            Source::Dir(dir) => dir.join(name),
            Source::Nowhere | Source::Bound(_) | Source::Probe(..) => PathBuf::from(name),
        }
    }

    /// The bytes of the file `name`, held to the size limit as on disk, or one line
    /// starting with the file.
    fn fetch(&self, name: &str) -> Result<Bytes, String> {
        let path = self.path(name);
        match self {
            Source::Dir(_) => load::read(&path).map(Bytes::Read),
            Source::Bound(files) => {
                let shown = load::shown(&path);
                let bytes = files
                    .get(name)
                    .ok_or_else(|| format!("{shown}: not among the files sent with the scene"))?;
                if bytes.len() as u64 > MAX_MESH_FILE_BYTES {
                    return Err(format!(
                        "{shown}: more than the limit of {MAX_MESH_FILE_BYTES} bytes for a mesh file"
                    ));
                }
                Ok(Bytes::Bound(bytes.clone()))
            }
            Source::Probe(files, missing) => match files.get(name) {
                Some(_) => Source::Bound(Arc::clone(files)).fetch(name),
                None => {
                    lock(missing).insert(name.to_owned());
                    Err(format!("{}: not among the files given", load::shown(&path)))
                }
            },
            Source::Nowhere => Err(format!("{}: no files were given", load::shown(&path))),
        }
    }
}

/// A file's bytes: read from disk, or shared with the files bound in memory (copied
/// only where a reader must own them).
pub(crate) enum Bytes {
    Read(Vec<u8>),
    Bound(Arc<[u8]>),
}

impl std::ops::Deref for Bytes {
    type Target = [u8];
    fn deref(&self) -> &[u8] {
        match self {
            Bytes::Read(bytes) => bytes,
            Bytes::Bound(bytes) => bytes,
        }
    }
}

impl Bytes {
    fn into_vec(self) -> Vec<u8> {
        match self {
            Bytes::Read(bytes) => bytes,
            Bytes::Bound(bytes) => bytes.to_vec(),
        }
    }
}

/// A file's own identity in the record: hashed as it is read from disk (its bytes are
/// not kept); of a bound file, whose bytes stay at hand, hashed only if asked for, so
/// that a worker does not hash twice what it was sent.
#[derive(Debug)]
enum Identity {
    Known([u8; 32]),
    Bound(Arc<[u8]>),
}

#[derive(Debug)]
struct Entry {
    path: PathBuf,
    size: u64,
    identity: Identity,
}

/// The files read so far, by name.
#[derive(Debug, Default)]
pub(crate) struct Record(std::sync::Mutex<BTreeMap<String, Entry>>);

impl Record {
    /// Every file read, once, sorted by name.
    pub(crate) fn files(&self) -> Vec<FileRead> {
        lock(&self.0)
            .iter()
            .map(|(name, entry)| FileRead {
                name: name.clone(),
                path: entry.path.clone(),
                sha256: match &entry.identity {
                    Identity::Known(sha256) => *sha256,
                    Identity::Bound(bytes) => Sha256::digest(bytes).into(),
                },
                size: entry.size,
            })
            .collect()
    }
}

/// A mesh file's bytes and those of the buffer files it reads, gathered before it is
/// read as a mesh: enough to know its SHA-256, and so whether its geometry is built.
pub(crate) struct Gathered {
    bytes: Bytes,
    /// Each buffer file's uri and bytes (or why not), in the order the reader asks.
    buffers: Vec<(String, Result<Bytes, String>)>,
    /// Over the file, then its buffer files: `None` if one could not be read, or if the
    /// glTF could not be read far enough to tell them (its reader says why).
    pub(crate) sha256: Option<[u8; 32]>,
}

/// Reads files from a source into a record.
pub(crate) struct Reader<'a> {
    pub(crate) source: &'a Source,
    pub(crate) record: &'a Record,
}

impl Reader<'_> {
    /// The file `name`, recorded, with its own SHA-256 if it was computed. A name read
    /// again from disk (a buffer two glTFs share) must hold the same bytes: the record
    /// says what the scene was rendered from.
    fn read(&self, name: &str) -> Result<(Bytes, Option<[u8; 32]>), String> {
        let bytes = self.source.fetch(name)?;
        let path = self.source.path(name);
        let (identity, sha256) = match &bytes {
            Bytes::Bound(shared) => (Identity::Bound(shared.clone()), None),
            Bytes::Read(read) => {
                let sha256: [u8; 32] = Sha256::digest(read).into();
                (Identity::Known(sha256), Some(sha256))
            }
        };
        let mut record = lock(&self.record.0);
        match record.get(name) {
            Some(Entry {
                identity: Identity::Known(before),
                ..
            }) if Some(*before) != sha256 => {
                return Err(format!(
                    "{}: changed while the scene was read",
                    load::shown(&path)
                ));
            }
            Some(_) => {}
            None => {
                let size = bytes.len() as u64;
                record.insert(
                    name.to_owned(),
                    Entry {
                        path,
                        size,
                        identity,
                    },
                );
            }
        }
        Ok((bytes, sha256))
    }

    /// The mesh file `name` and its buffer files, read and hashed, not yet parsed.
    pub(crate) fn gather(&self, name: &str) -> Result<Gathered, String> {
        let (bytes, own) = self.read(name)?;
        let uris = match load::extension(&self.source.path(name)).as_str() {
            "gltf" => super::gltf::buffer_files(&bytes, false),
            "glb" => super::gltf::buffer_files(&bytes, true),
            _ => Some(Vec::new()),
        };
        let Some(uris) = uris else {
            return Ok(Gathered {
                bytes,
                buffers: Vec::new(),
                sha256: None,
            });
        };
        let buffers: Vec<_> = uris
            .into_iter()
            .map(|uri| {
                let buffer = self.read(&buffer_name(name, &uri)).map(|(b, _)| b);
                (uri, buffer)
            })
            .collect();
        let sha256 = match own {
            Some(own) if buffers.is_empty() => Some(own),
            _ if buffers.iter().any(|(_, b)| b.is_err()) => None,
            _ => {
                let mut hasher = Sha256::new();
                hasher.update(&*bytes);
                for buffer in buffers.iter().filter_map(|(_, b)| b.as_ref().ok()) {
                    hasher.update(&**buffer);
                }
                Some(hasher.finalize().into())
            }
        };
        Ok(Gathered {
            bytes,
            buffers,
            sha256,
        })
    }

    /// The mesh `gathered` for the file `name`, read, and its SHA-256: the reader is
    /// given the buffers gathered (which it asks for in the same order); where it asks
    /// for another, that is read then, and hashed as it is.
    pub(crate) fn parse(
        &self,
        name: &str,
        gathered: Gathered,
    ) -> Result<(MeshData, [u8; 32]), String> {
        let Gathered {
            bytes,
            buffers,
            sha256,
        } = gathered;
        let hasher = RefCell::new(Sha256::new());
        if sha256.is_none() {
            hasher.borrow_mut().update(&*bytes);
        }
        let pending = RefCell::new(buffers.into_iter());
        let file = |uri: &str| {
            let buffer = match pending.borrow_mut().next() {
                Some((gathered, buffer)) if gathered == uri => buffer?,
                _ => self.read(&buffer_name(name, uri))?.0,
            };
            if sha256.is_none() {
                hasher.borrow_mut().update(&*buffer);
            }
            Ok(buffer.into_vec())
        };
        let mesh = load::parse_with(&self.source.path(name), &bytes, &file)?;
        Ok((
            mesh,
            sha256.unwrap_or_else(|| hasher.into_inner().finalize().into()),
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn buffer_names_join_the_gltfs_directory_lexically() {
        for (mesh, uri, name) in [
            ("ship.gltf", "ship.bin", "ship.bin"),
            ("models/ship.gltf", "ship.bin", "models/ship.bin"),
            ("models/ship.gltf", "bin/ship.bin", "models/bin/ship.bin"),
            (
                "./models/./ship.gltf",
                "./bin//ship.bin",
                "models/bin/ship.bin",
            ),
            ("models/ship.gltf", "../shared/ship.bin", "shared/ship.bin"),
            ("models/a/../ship.gltf", "x/../ship.bin", "models/ship.bin"),
            ("ship.gltf", "../ship.bin", "../ship.bin"),
            ("../up/ship.gltf", "../../ship.bin", "../../ship.bin"),
            (
                "/data/models/ship.gltf",
                "ship.bin",
                "/data/models/ship.bin",
            ),
            ("/data/ship.gltf", "../../../ship.bin", "/ship.bin"),
            (
                "models/ship.gltf",
                "/elsewhere/ship.bin",
                "/elsewhere/ship.bin",
            ),
            ("models/ship.gltf", "my%20ship.bin", "models/my%20ship.bin"),
            ("models\\ship.gltf", "ship.bin", "ship.bin"),
            ("models/ship.gltf", "..", "."),
        ] {
            assert_eq!(buffer_name(mesh, uri), name, "{mesh} + {uri}");
        }
    }

    #[test]
    fn a_name_not_bound_is_one_line_naming_it() {
        let files = BTreeMap::from([("a.obj".to_owned(), Arc::from(&b"v"[..]))]);
        let source = Source::Bound(Arc::new(files));
        let error = source.fetch("models/b.obj").err().unwrap();
        assert_eq!(
            error,
            "models/b.obj: not among the files sent with the scene"
        );
        let odd = source.fetch("b\n.obj").err().unwrap();
        assert_eq!(odd.lines().count(), 1, "{odd}");
    }
}
