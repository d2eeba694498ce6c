//! A scene and its mesh files as one archive: what the studio's Save downloads for a
//! scene with meshes, and what `tessera render` reads back (docs/studio.md, "Saving a
//! scene with meshes").
//!
//! The archive is a plain tar (POSIX ustar, as `tar` writes it): the scene's JSON as a
//! member at its top level, named `*.json`, and every file the scene reads under the
//! name the scene gives it, relative to the scene (the archive's top level is the
//! scene's directory). Any `tar` lists, extracts and makes such archives, and `tessera
//! render` of the extracted scene file gives the same picture as of the archive.
//!
//! An archive is read into memory, never unpacked onto a disk, and what it may hold is
//! bounded: a member named outside the archive's own directory (absolute, or climbing
//! with `..`), a link or a device, more than [`MAX_MEMBERS`] members, a member over
//! the renderer's [`render::limits::MAX_MESH_FILE_BYTES`], or more than
//! [`MAX_ARCHIVE_BYTES`] in all is refused with one line naming it.

use std::collections::BTreeMap;
use std::io::Read;
use std::sync::Arc;

use serde_json::Value;

/// The most members an archive may hold: a job's files and its scene.
pub const MAX_MEMBERS: usize = protocol::MAX_JOB_ASSETS + 1;

/// The most bytes of members an archive may hold in all: everything is read into
/// memory before the scene is.
pub const MAX_ARCHIVE_BYTES: u64 = 4 << 30;

/// The most bytes one member may hold: a mesh file as large as the renderer reads.
pub const MAX_MEMBER_BYTES: u64 = render::limits::MAX_MESH_FILE_BYTES;

/// What is wrong with an archive, in one line naming the member.
#[derive(Debug, thiserror::Error)]
pub enum ArchiveError {
    #[error("not a readable tar archive: {0}")]
    Tar(#[source] std::io::Error),
    #[error("member {index} ({name:?}): {why}")]
    Member {
        index: usize,
        name: String,
        why: String,
    },
    #[error("more than {MAX_MEMBERS} members")]
    TooManyMembers,
    #[error("more than {MAX_ARCHIVE_BYTES} bytes of members in all")]
    TooLarge,
    #[error("no scene: the archive holds no .json member at its top level")]
    NoScene,
    #[error("two scenes: {0:?} and {1:?} are both .json members at its top level")]
    TwoScenes(String, String),
    #[error("objects[{object}].file: {name:?} is not in the archive")]
    Missing { object: usize, name: String },
    #[error("{name:?}: {why}")]
    Name { name: String, why: &'static str },
    #[error("cannot write the archive: {0}")]
    Write(#[source] std::io::Error),
}

/// A scene read from an archive: its member's name, its text, and the other members
/// by name, as [`render::MeshFiles::bound`] takes them.
#[derive(Debug)]
pub struct SceneArchive {
    pub scene_name: String,
    pub text: String,
    pub files: BTreeMap<String, Arc<[u8]>>,
}

/// Why `name` cannot be a member's name as the scene writes it, if it cannot: a member
/// lives in the archive's own directory, so a name is relative, without `.` or `..`
/// parts or empty parts (a scene naming `./a.obj` or `m//a.obj` would not find the
/// member `a.obj` or `m/a.obj` the archive holds under it).
pub fn unsafe_name(name: &str) -> Option<&'static str> {
    if name.is_empty() {
        Some("an empty name")
    } else if name.starts_with('/') {
        Some("an absolute name: a member must be inside the archive")
    } else if name.contains('\0') || name.contains('\\') {
        Some("a name with a NUL or a backslash")
    } else if name.split('/').any(|part| part == "..") {
        Some("a name climbing out with `..`: a member must be inside the archive")
    } else if name.split('/').any(|part| part.is_empty() || part == ".") {
        Some("a name with an empty or `.` part")
    } else {
        None
    }
}

/// Reads an archive from `reader`: the scene and its files, each checked as the module
/// says. Directory members are skipped (`tar -c` of a directory writes them); a
/// leading `./` (`tar -C dir -c .`) is dropped.
pub fn read(reader: impl Read) -> Result<SceneArchive, ArchiveError> {
    let mut archive = tar::Archive::new(reader);
    let mut scene: Option<(String, Vec<u8>)> = None;
    let mut files = BTreeMap::new();
    let mut total = 0u64;
    let entries = archive.entries().map_err(ArchiveError::Tar)?;
    for (index, entry) in entries.enumerate() {
        if index >= MAX_MEMBERS {
            return Err(ArchiveError::TooManyMembers);
        }
        let mut entry = entry.map_err(ArchiveError::Tar)?;
        let raw = entry.path_bytes().into_owned();
        let shown = String::from_utf8_lossy(&raw).into_owned();
        let member = |why: String| ArchiveError::Member {
            index,
            name: shown.clone(),
            why,
        };
        let kind = entry.header().entry_type();
        let name =
            std::str::from_utf8(&raw).map_err(|_| member("a name that is not UTF-8".into()))?;
        let name = name.strip_prefix("./").unwrap_or(name);
        if kind.is_dir() {
            if name.is_empty() || name == "." {
                continue;
            }
            let trimmed = name.trim_end_matches('/');
            if let Some(why) = unsafe_name(trimmed) {
                return Err(member(why.into()));
            }
            continue;
        }
        if let Some(why) = unsafe_name(name) {
            return Err(member(why.into()));
        }
        if !(kind.is_file() || kind == tar::EntryType::Continuous) {
            return Err(member(
                "not a regular file (a link, a device or a FIFO): refused".into(),
            ));
        }
        let size = entry.size();
        if size > MAX_MEMBER_BYTES {
            return Err(member(format!(
                "{size} bytes, over the limit of {MAX_MEMBER_BYTES} for one file"
            )));
        }
        total += size;
        if total > MAX_ARCHIVE_BYTES {
            return Err(ArchiveError::TooLarge);
        }
        let mut bytes = Vec::with_capacity(size as usize);
        (&mut entry)
            .take(size)
            .read_to_end(&mut bytes)
            .map_err(|e| member(format!("cannot read it: {e}")))?;
        if bytes.len() as u64 != size {
            return Err(member("cut short".into()));
        }
        let top_level_json = !name.contains('/') && name.to_ascii_lowercase().ends_with(".json");
        if top_level_json {
            if let Some((first, _)) = &scene {
                return Err(ArchiveError::TwoScenes(first.clone(), name.to_owned()));
            }
            scene = Some((name.to_owned(), bytes));
        } else if files.insert(name.to_owned(), Arc::from(bytes)).is_some() {
            return Err(member("a second member of this name".into()));
        }
    }
    let (scene_name, text) = scene.ok_or(ArchiveError::NoScene)?;
    let text = String::from_utf8(text).map_err(|_| ArchiveError::Member {
        index: 0,
        name: scene_name.clone(),
        why: "the scene is not UTF-8".into(),
    })?;
    let archive = SceneArchive {
        scene_name,
        text,
        files,
    };
    archive.check_files()?;
    Ok(archive)
}

impl SceneArchive {
    /// Every mesh object's file is a member: the first that is not is named by its
    /// object, before the loader reads anything. (A glTF's buffer missing is the
    /// loader's error, naming the buffer.)
    fn check_files(&self) -> Result<(), ArchiveError> {
        // A text that is not JSON is the loader's error, with its line and column.
        let Ok(root) = serde_json::from_str::<Value>(&self.text) else {
            return Ok(());
        };
        for (object, name) in mesh_files(&root) {
            if !self.files.contains_key(name) {
                return Err(ArchiveError::Missing {
                    object,
                    name: name.to_owned(),
                });
            }
        }
        Ok(())
    }
}

/// The `file` of every `mesh` object of a scene, with the object's index.
pub fn mesh_files(root: &Value) -> Vec<(usize, &str)> {
    let Some(objects) = root.get("objects").and_then(Value::as_array) else {
        return Vec::new();
    };
    objects
        .iter()
        .enumerate()
        .filter(|(_, o)| o.get("type").and_then(Value::as_str) == Some("mesh"))
        .filter_map(|(i, o)| o.get("file").and_then(Value::as_str).map(|f| (i, f)))
        .collect()
}

/// Writes an archive: the scene `text` as `scene_name`, then `files` in the order
/// given, each under its name. Every name must pass [`unsafe_name`] (and the scene's
/// be at the top level): what is written reads back. Members carry no owner, time or
/// mode of this machine, so the same scene and files make the same bytes.
pub fn write(
    scene_name: &str,
    text: &str,
    files: &[(String, Arc<[u8]>)],
) -> Result<Vec<u8>, ArchiveError> {
    if scene_name.contains('/') || !scene_name.to_ascii_lowercase().ends_with(".json") {
        return Err(ArchiveError::Name {
            name: scene_name.to_owned(),
            why: "a scene's member is a .json name at the archive's top level",
        });
    }
    let mut builder = tar::Builder::new(Vec::new());
    let members = std::iter::once((scene_name, text.as_bytes()))
        .chain(files.iter().map(|(n, b)| (n.as_str(), &b[..])));
    for (name, bytes) in members {
        if let Some(why) = unsafe_name(name) {
            return Err(ArchiveError::Name {
                name: name.to_owned(),
                why,
            });
        }
        let mut header = tar::Header::new_ustar();
        header.set_size(bytes.len() as u64);
        header.set_mode(0o644);
        header.set_mtime(0);
        header.set_uid(0);
        header.set_gid(0);
        header.set_entry_type(tar::EntryType::Regular);
        builder
            .append_data(&mut header, name, bytes)
            .map_err(ArchiveError::Write)?;
    }
    builder.into_inner().map_err(ArchiveError::Write)
}

#[cfg(test)]
mod tests {
    use super::*;

    const SCENE: &str = r#"{"camera": {"position": "0 0 -5", "look_at": "0 0 0"},
        "objects": [{"type": "mesh", "file": "meshes/tri.obj", "color": "1 1 1 0"}]}"#;
    const OBJ: &[u8] = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n";

    fn files() -> Vec<(String, Arc<[u8]>)> {
        vec![("meshes/tri.obj".to_owned(), Arc::from(OBJ))]
    }

    /// A tar with one member of any name and type, written byte by byte as a hostile
    /// tool could (the builder refuses such names itself).
    fn raw_tar(members: &[(&str, tar::EntryType, &[u8])]) -> Vec<u8> {
        let mut out = Vec::new();
        for (name, kind, bytes) in members {
            let mut header = tar::Header::new_old();
            header.as_old_mut().name[..name.len()].copy_from_slice(name.as_bytes());
            header.set_size(bytes.len() as u64);
            header.set_mode(0o644);
            header.set_entry_type(*kind);
            header.set_cksum();
            out.extend_from_slice(header.as_bytes());
            out.extend_from_slice(bytes);
            out.resize(out.len().div_ceil(512) * 512, 0);
        }
        out.resize(out.len() + 1024, 0);
        out
    }

    #[test]
    fn an_archive_written_reads_back_as_the_scene_and_its_files_the_same_bytes_each_time() {
        let bytes = write("room.json", SCENE, &files()).unwrap();
        assert_eq!(bytes, write("room.json", SCENE, &files()).unwrap());
        let back = read(&bytes[..]).unwrap();
        assert_eq!(back.scene_name, "room.json");
        assert_eq!(back.text, SCENE);
        assert_eq!(back.files.len(), 1);
        assert_eq!(&back.files["meshes/tri.obj"][..], OBJ);
        // A long name (over ustar's 100 bytes) reads back too.
        let long = format!("{}/m.obj", "d".repeat(150));
        let scene = SCENE.replace("meshes/tri.obj", &long);
        let bytes = write("s.json", &scene, &[(long.clone(), Arc::from(OBJ))]).unwrap();
        assert!(read(&bytes[..]).unwrap().files.contains_key(&long));
    }

    #[test]
    fn unsafe_names_links_a_missing_file_and_scenes_not_one_are_refused_in_one_line() {
        for (name, word) in [
            ("../x.obj", ".."),
            ("meshes/../../x.obj", ".."),
            ("/etc/passwd", "absolute"),
            ("a//b.obj", "empty"),
        ] {
            let tar = raw_tar(&[
                ("s.json", tar::EntryType::Regular, SCENE.as_bytes()),
                (name, tar::EntryType::Regular, OBJ),
            ]);
            let error = read(&tar[..]).unwrap_err().to_string();
            assert!(
                error.contains(word) && error.contains(name),
                "{name}: {error}"
            );
            assert!(!error.contains('\n'), "{error}");
            assert!(write("s.json", SCENE, &[(name.to_owned(), Arc::from(OBJ))]).is_err());
        }
        let link = raw_tar(&[
            ("s.json", tar::EntryType::Regular, SCENE.as_bytes()),
            ("meshes/tri.obj", tar::EntryType::Symlink, b""),
        ]);
        let error = read(&link[..]).unwrap_err().to_string();
        assert!(error.contains("not a regular file"), "{error}");
        let missing = raw_tar(&[("s.json", tar::EntryType::Regular, SCENE.as_bytes())]);
        let error = read(&missing[..]).unwrap_err().to_string();
        assert_eq!(
            error,
            "objects[0].file: \"meshes/tri.obj\" is not in the archive"
        );
        let none = raw_tar(&[("meshes/tri.obj", tar::EntryType::Regular, OBJ)]);
        assert!(matches!(read(&none[..]), Err(ArchiveError::NoScene)));
        let two = raw_tar(&[
            ("a.json", tar::EntryType::Regular, b"{}"),
            ("b.json", tar::EntryType::Regular, b"{}"),
        ]);
        assert!(matches!(read(&two[..]), Err(ArchiveError::TwoScenes(..))));
        assert!(matches!(
            read(&b"not a tar at all, surely"[..]),
            Err(ArchiveError::Tar(_) | ArchiveError::NoScene)
        ));
        // A directory member and a leading ./, as `tar -C dir -c .` writes them, are fine.
        let tool = raw_tar(&[
            ("./", tar::EntryType::Directory, b""),
            ("./s.json", tar::EntryType::Regular, SCENE.as_bytes()),
            ("./meshes/", tar::EntryType::Directory, b""),
            ("./meshes/tri.obj", tar::EntryType::Regular, OBJ),
        ]);
        assert_eq!(read(&tool[..]).unwrap().files.len(), 1);
    }

    #[test]
    fn too_many_members_are_refused() {
        let empty: &[u8] = b"";
        let names: Vec<String> = (0..=MAX_MEMBERS).map(|i| format!("f{i}")).collect();
        let members: Vec<(&str, tar::EntryType, &[u8])> = names
            .iter()
            .map(|n| (n.as_str(), tar::EntryType::Regular, empty))
            .collect();
        let tar = raw_tar(&members);
        assert!(matches!(read(&tar[..]), Err(ArchiveError::TooManyMembers)));
    }
}
