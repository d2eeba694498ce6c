//! Saved adaptive renders: every sample a `tessera render --state FILE` took, so that
//! `tessera refine FILE` can go on to a lower error target or a larger cap without
//! taking them again.
//!
//! The file holds the scene's text (a refine needs nothing else but the scene's mesh
//! files), the directory the mesh files were read from and the SHA-256 of each (a
//! refine refuses to go on once one has changed: the samples saved are of the old
//! one), the settings, the rung reached and each block's levels and sums. Layout: the magic line, a format
//! version, the SHA-256 of the rest, then the zstd-compressed bincode of [`Saved`].
//! The digest is checked before anything is decoded, and the blocks are checked again
//! by the renderer (`Region::new`) before a sample of them is used: a damaged or
//! edited file is refused with one line, never rendered from.

use std::path::{Path, PathBuf};

use anyhow::{bail, ensure, Context, Result};
use render::adaptive::BlockState;
use render::{Scene, Shape};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use crate::output::FileOutput;

const MAGIC: &[u8] = b"tessera render state\n";
/// 2: the mesh files' directory and SHA-256s.
const VERSION: u32 = 2;
/// The largest decompressed state accepted: far above any frame the limits allow at
/// the largest cap, far below what a hostile file could ask to allocate.
const MAX_DECODED: usize = 8 << 30;

/// What a saved render holds.
#[derive(Serialize, Deserialize)]
pub struct Saved {
    pub scene: String,
    /// The directory the scene's mesh files are named relative to: the scene file's,
    /// absolute and canonical, so that a refine from anywhere reads the same files.
    #[serde(with = "path_bytes")]
    pub mesh_dir: PathBuf,
    /// Each mesh file the scene names, once, in the order of the objects.
    pub meshes: Vec<SavedMesh>,
    pub width: u32,
    pub height: u32,
    pub aa: u32,
    pub max_depth: u32,
    /// The target the saved image was rendered to, in thousandths of a level.
    pub target_milli: u32,
    /// The rung of the saved image.
    pub rung: u32,
    pub blocks: Vec<BlockState>,
}

/// A mesh file as the state was saved with it.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct SavedMesh {
    /// The first object that names it (its index in `objects`).
    pub object: u32,
    /// The `file` string of the scene.
    pub name: String,
    pub sha256: [u8; 32],
}

/// The mesh files of `scene` (frame 1 of the scene file), each once: what a state
/// records of them.
pub fn meshes_of(scene: &Scene) -> Vec<SavedMesh> {
    let mut meshes: Vec<SavedMesh> = Vec::new();
    let mut named = std::collections::HashSet::new();
    for (i, object) in scene.objects.iter().enumerate() {
        if let Shape::Mesh(mesh) = &object.shape {
            if named.insert(mesh.file.name.as_str()) {
                meshes.push(SavedMesh {
                    object: u32::try_from(i).expect("fewer objects than u32::MAX"),
                    name: mesh.file.name.clone(),
                    sha256: mesh.file.sha256,
                });
            }
        }
    }
    meshes
}

/// Checks that `scene`, the saved scene read again with the mesh files as they are
/// now, has the mesh files the state was saved with: one line naming the first object
/// whose file changed.
pub fn check_meshes(saved: &Saved, scene: &Scene) -> Result<()> {
    let now = meshes_of(scene);
    for mesh in &now {
        let Some(then) = saved.meshes.iter().find(|m| m.name == mesh.name) else {
            bail!(
                "the render state is damaged: objects[{}].file is not among its mesh files",
                mesh.object
            );
        };
        if then.sha256 != mesh.sha256 {
            bail!(
                "{}",
                changed(mesh.object, &mesh.name, &then.sha256, &mesh.sha256)
            );
        }
    }
    ensure!(
        now.len() == saved.meshes.len(),
        "the render state is damaged: its mesh files are not the scene's"
    );
    Ok(())
}

/// Checks the saved mesh files as they are now without reading them as meshes: for a
/// saved scene that no longer reads, one line saying which file is gone or changed, if
/// one is. `Ok` if every file is as it was.
pub fn check_mesh_files(saved: &Saved) -> Result<()> {
    for mesh in &saved.meshes {
        let path = saved.mesh_dir.join(&mesh.name);
        let gltf = path
            .extension()
            .is_some_and(|e| e.eq_ignore_ascii_case("gltf"));
        if gltf {
            // A glTF's digest covers the buffer files it reads: only reading it tells.
            let now = render::mesh::load::read(&path)
                .and_then(|bytes| render::mesh::load::parse_hashed(&path, &bytes))
                .map(|(_, sha)| sha);
            match now {
                Ok(now) if now == mesh.sha256 => continue,
                Ok(now) => bail!("{}", changed(mesh.object, &mesh.name, &mesh.sha256, &now)),
                Err(e) => bail!(
                    "objects[{}].file: {} cannot be read since the state was saved: {e}",
                    mesh.object,
                    mesh.name
                ),
            }
        }
        let now = file_sha256(&path).map_err(|e| {
            anyhow::anyhow!(
                "objects[{}].file: {} cannot be read since the state was saved: {}: {e}",
                mesh.object,
                mesh.name,
                path.display()
            )
        })?;
        if now != mesh.sha256 {
            bail!("{}", changed(mesh.object, &mesh.name, &mesh.sha256, &now));
        }
    }
    Ok(())
}

/// The SHA-256 of the file at `path`, read a part at a time (whatever its size now).
fn file_sha256(path: &Path) -> std::io::Result<[u8; 32]> {
    use std::io::Read;
    let mut file = std::fs::File::open(path)?;
    let mut hasher = Sha256::new();
    let mut buffer = vec![0u8; 1 << 16];
    loop {
        match file.read(&mut buffer) {
            Ok(0) => return Ok(hasher.finalize().into()),
            Ok(n) => hasher.update(&buffer[..n]),
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e) => return Err(e),
        }
    }
}

/// The line for a mesh file whose bytes are no longer those the state was saved with:
/// both SHA-256s, shortened to where they differ (8 hexadecimal digits at least).
fn changed(object: u32, name: &str, then: &[u8; 32], now: &[u8; 32]) -> String {
    let hex = |d: &[u8; 32]| d.iter().map(|b| format!("{b:02x}")).collect::<String>();
    let (then, now) = (hex(then), hex(now));
    let differ = then
        .bytes()
        .zip(now.bytes())
        .position(|(a, b)| a != b)
        .unwrap_or(then.len());
    let shown = (differ + 1).clamp(8, then.len());
    let short = |h: &str| {
        if shown < h.len() {
            format!("{}…", &h[..shown])
        } else {
            h.to_owned()
        }
    };
    format!(
        "objects[{object}].file: {name} changed since the state was saved (SHA-256 {} then, \
         {} now)",
        short(&then),
        short(&now)
    )
}

/// A path as the bytes the system names it with: any directory, UTF-8 or not, can be
/// saved (after the render it belongs to, where failing would lose the render).
mod path_bytes {
    use std::ffi::OsString;
    use std::os::unix::ffi::{OsStrExt, OsStringExt};
    use std::path::{Path, PathBuf};

    use serde::{Deserialize, Deserializer, Serializer};

    pub fn serialize<S: Serializer>(path: &Path, s: S) -> Result<S::Ok, S::Error> {
        s.collect_seq(path.as_os_str().as_bytes())
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<PathBuf, D::Error> {
        Vec::<u8>::deserialize(d).map(|bytes| PathBuf::from(OsString::from_vec(bytes)))
    }
}

/// Writes `saved` to `out` atomically.
pub fn save(out: FileOutput, saved: &Saved) -> Result<()> {
    let encoded = bincode::serde::encode_to_vec(saved, bincode::config::standard())
        .context("cannot encode the render state")?;
    let compressed =
        zstd::bulk::compress(&encoded, 3).context("cannot compress the render state")?;
    let mut body = Vec::with_capacity(compressed.len() + 8);
    body.extend_from_slice(&VERSION.to_le_bytes());
    body.extend_from_slice(&(encoded.len() as u64).to_le_bytes());
    body.extend_from_slice(&compressed);
    let mut bytes = Vec::with_capacity(MAGIC.len() + 32 + body.len());
    bytes.extend_from_slice(MAGIC);
    bytes.extend_from_slice(&Sha256::digest(&body));
    bytes.extend_from_slice(&body);
    out.write(&bytes)
}

/// Reads and checks a saved render.
pub fn load(path: &Path) -> Result<Saved> {
    let bytes = std::fs::read(path)
        .with_context(|| format!("cannot read render state {}", path.display()))?;
    decode(&bytes).with_context(|| format!("{}", path.display()))
}

fn decode(bytes: &[u8]) -> Result<Saved> {
    let Some(rest) = bytes.strip_prefix(MAGIC) else {
        bail!("not a render state (saved by `tessera render --state`)");
    };
    ensure!(rest.len() >= 32 + 12, "the render state is truncated");
    let (digest, body) = rest.split_at(32);
    ensure!(
        Sha256::digest(body).as_slice() == digest,
        "the render state is damaged (its checksum does not match)"
    );
    let version = u32::from_le_bytes(body[..4].try_into().expect("4 bytes"));
    ensure!(
        version == VERSION,
        "render state format {version} is not the one this build reads ({VERSION})"
    );
    let size = u64::from_le_bytes(body[4..12].try_into().expect("8 bytes"));
    let size = usize::try_from(size)
        .ok()
        .filter(|&s| s <= MAX_DECODED)
        .context("the render state claims an impossible size")?;
    let encoded =
        zstd::bulk::decompress(&body[12..], size).context("the render state is damaged")?;
    let (saved, used): (Saved, usize) =
        bincode::serde::decode_from_slice(&encoded, bincode::config::standard())
            .context("the render state is damaged")?;
    ensure!(used == encoded.len(), "the render state has trailing bytes");
    Ok(saved)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> Saved {
        Saved {
            scene: "{}".into(),
            mesh_dir: PathBuf::from("/scenes"),
            meshes: Vec::new(),
            width: 8,
            height: 8,
            aa: 4,
            max_depth: 3,
            target_milli: 2000,
            rung: 17,
            blocks: Vec::new(),
        }
    }

    #[test]
    fn a_saved_state_reads_back_and_any_damage_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("r.state");
        save(crate::output::FileOutput::create(&path).unwrap(), &sample()).unwrap();
        let back = load(&path).unwrap();
        assert_eq!((back.rung, back.aa, back.scene.as_str()), (17, 4, "{}"));
        let good = std::fs::read(&path).unwrap();
        for at in [0, MAGIC.len() + 3, good.len() - 1] {
            let mut bad = good.clone();
            bad[at] ^= 0x40;
            let err = decode(&bad).err().expect("damage is noticed").to_string();
            assert!(err.contains("render state"), "{err}");
        }
        assert!(decode(&good[..good.len() - 5]).is_err());
    }

    /// `saved` written as a file of format `version`, its checksum right.
    fn encoded_as(saved: &Saved, version: u32) -> Vec<u8> {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("r.state");
        save(crate::output::FileOutput::create(&path).unwrap(), saved).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        let mut body = bytes[MAGIC.len() + 32..].to_vec();
        body[..4].copy_from_slice(&version.to_le_bytes());
        let mut out = MAGIC.to_vec();
        out.extend_from_slice(&Sha256::digest(&body));
        out.extend_from_slice(&body);
        out
    }

    #[test]
    fn the_mesh_files_directory_and_digests_read_back_and_other_formats_are_refused() {
        use std::os::unix::ffi::OsStringExt;
        let mut saved = sample();
        // Any directory the system can name, UTF-8 or not.
        saved.mesh_dir = PathBuf::from(std::ffi::OsString::from_vec(b"/scenes/\xff\xfe".to_vec()));
        saved.meshes = vec![
            SavedMesh {
                object: 0,
                name: "bunny.ply".into(),
                sha256: [7; 32],
            },
            SavedMesh {
                object: 3,
                name: "../shared/teapot.obj".into(),
                sha256: [0xab; 32],
            },
        ];
        let back = decode(&encoded_as(&saved, VERSION)).unwrap();
        assert_eq!(back.mesh_dir, saved.mesh_dir);
        assert_eq!(back.meshes, saved.meshes);
        // A state of the format before meshes (or any other) is refused in one line.
        for version in [1, VERSION + 1] {
            let err = decode(&encoded_as(&saved, version))
                .err()
                .unwrap()
                .to_string();
            assert_eq!(
                err,
                format!("render state format {version} is not the one this build reads (2)")
            );
        }
    }

    /// A scene of `objects` (JSON texts) with one light, read beside `dir`.
    fn scene_beside(dir: &Path, objects: &[&str]) -> (String, Scene) {
        let text = format!(
            r#"{{"camera": {{"position": "0 0 -5", "look_at": "0 0 0"}},
                "lights": [{{"position": "0 5 -5", "color": "1 1 1"}}],
                "objects": [{}]}}"#,
            objects.join(", ")
        );
        let scene = render::parse_scene_with(&text, &render::MeshFiles::beside(dir)).unwrap();
        (text, scene)
    }

    const TETRAHEDRON: &str =
        "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n";

    #[test]
    fn each_mesh_file_is_recorded_once_and_a_changed_or_missing_one_is_named() {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        std::fs::write(d.join("a.obj"), TETRAHEDRON).unwrap();
        std::fs::create_dir(d.join("sub")).unwrap();
        std::fs::write(
            d.join("sub/b.obj"),
            TETRAHEDRON.replace("v 0 0 1", "v 0 0 2"),
        )
        .unwrap();
        let mesh =
            |file: &str| format!(r#"{{"type": "mesh", "file": "{file}", "color": "1 0 0 0"}}"#);
        let sphere = r#"{"type": "sphere", "center": "0 0 0", "radius": 1, "color": "1 1 1 0"}"#;
        let (a, b) = (mesh("a.obj"), mesh("sub/b.obj"));
        let (text, scene) = scene_beside(d, &[sphere, &a, &b, &a]);
        let meshes = meshes_of(&scene);
        let digest = |path: &str| -> [u8; 32] {
            Sha256::digest(std::fs::read(d.join(path)).unwrap()).into()
        };
        assert_eq!(
            meshes,
            vec![
                SavedMesh {
                    object: 1,
                    name: "a.obj".into(),
                    sha256: digest("a.obj"),
                },
                SavedMesh {
                    object: 2,
                    name: "sub/b.obj".into(),
                    sha256: digest("sub/b.obj"),
                },
            ]
        );
        let saved = Saved {
            scene: text.clone(),
            mesh_dir: d.to_path_buf(),
            meshes,
            ..sample()
        };
        check_meshes(&saved, &scene).unwrap();
        check_mesh_files(&saved).unwrap();

        // b.obj changed, still a mesh: both checks name it, and both digests.
        std::fs::write(d.join("sub/b.obj"), TETRAHEDRON).unwrap();
        let (then, now) = (saved.meshes[1].sha256, digest("sub/b.obj"));
        let hex = |d: [u8; 32]| d.iter().map(|b| format!("{b:02x}")).collect::<String>();
        let (_, changed_scene) = scene_beside(d, &[sphere, &a, &b, &a]);
        let err = check_meshes(&saved, &changed_scene)
            .unwrap_err()
            .to_string();
        assert!(
            err.starts_with(
                "objects[2].file: sub/b.obj changed since the state was saved (SHA-256 "
            ) && err.contains(&format!("{}… then, ", &hex(then)[..8]))
                && err.ends_with(&format!("{}… now)", &hex(now)[..8])),
            "{err}"
        );
        assert_eq!(check_mesh_files(&saved).unwrap_err().to_string(), err);

        // a.obj gone.
        std::fs::remove_file(d.join("a.obj")).unwrap();
        let err = check_mesh_files(&saved).unwrap_err().to_string();
        assert!(
            err.starts_with(&format!(
                "objects[1].file: a.obj cannot be read since the state was saved: {}: ",
                d.join("a.obj").display()
            )),
            "{err}"
        );
        assert_eq!(err.lines().count(), 1, "{err}");

        // A state whose list is not the scene's is damaged.
        let fewer = Saved {
            meshes: saved.meshes[..1].to_vec(),
            scene: text,
            mesh_dir: d.to_path_buf(),
            ..sample()
        };
        let err = check_meshes(&fewer, &scene).unwrap_err().to_string();
        assert!(err.contains("damaged"), "{err}");
    }

    #[test]
    fn digests_are_shown_as_far_as_they_differ() {
        let then = [0x11; 32];
        let mut now = then;
        now[6] = 0x12;
        assert_eq!(
            changed(4, "m.stl", &then, &now),
            "objects[4].file: m.stl changed since the state was saved (SHA-256 \
             11111111111111… then, 11111111111112… now)"
        );
        now = [0x9f; 32];
        assert_eq!(
            changed(0, "m.stl", &then, &now),
            "objects[0].file: m.stl changed since the state was saved (SHA-256 \
             11111111… then, 9f9f9f9f… now)"
        );
    }
}
