//! Mutations of real mesh files (models no one here wrote, from the system's test model
//! package): each reader gives a mesh or a one-line error for every mutant, never a
//! panic, never more triangles than the bytes could describe. The count
//! is bounded so that the whole run takes a few seconds.

use std::path::{Path, PathBuf};

use render::mesh::load;

use crate::support::Mix;

/// The real files mutated: every format the readers know.
const FILES: &[&str] = &[
    "/usr/share/assimp/models/OBJ/WusonOBJ.obj",
    "/usr/share/assimp/models/OBJ/spider.obj",
    "/usr/share/assimp/models/PLY/Wuson.ply",
    "/usr/share/assimp/models/PLY/cube_binary.ply",
    "/usr/share/assimp/models/STL/Wuson.stl",
    "/usr/share/assimp/models/STL/Spider_binary.stl",
    "/usr/share/assimp/models/glTF2/2CylinderEngine-glTF-Binary/2CylinderEngine.glb",
];

/// The files, or none when the package is missing and not required.
fn files() -> Vec<PathBuf> {
    let present: Vec<PathBuf> = FILES
        .iter()
        .map(PathBuf::from)
        .filter(|p| p.exists())
        .collect();
    if present.len() < FILES.len() {
        assert!(
            std::env::var_os("TESSERA_REQUIRE_MODELS").is_none(),
            "the test models are missing: install the assimp-testmodels package"
        );
        eprintln!("note: assimp-testmodels is not installed; mutations of real files skipped");
        return Vec::new();
    }
    present
}

fn mutate(rng: &mut Mix, bytes: &[u8]) -> Vec<u8> {
    let mut out = bytes.to_vec();
    let at = |rng: &mut Mix, len: usize| (rng.next() % len.max(1) as u64) as usize;
    for _ in 0..1 + rng.next() % 4 {
        if out.is_empty() {
            break;
        }
        let i = at(rng, out.len());
        match rng.next() % 7 {
            0 => out[i] ^= 1 << (rng.next() % 8),
            1 => out[i] = b"0123456789-.eE \n/"[(rng.next() % 17) as usize],
            2 => out.truncate(i),
            3 => {
                let n = (rng.next() % 64) as usize;
                let end = (i + n).min(out.len());
                let copy = out[i..end].to_vec();
                out.splice(i..i, copy);
            }
            4 => {
                let end = (i + (rng.next() % 16) as usize).min(out.len());
                out.drain(i..end);
            }
            5 => out[i] = 0xFF,
            _ => {
                // A large number where a count or an index may be.
                let digits = b"999999999999";
                out.splice(i..i, digits.iter().copied());
            }
        }
    }
    out
}

#[test]
fn mutated_real_files_give_a_mesh_or_one_line() {
    let mut rng = Mix(41);
    for path in files() {
        let bytes = std::fs::read(&path).unwrap();
        let original = load::parse(&path, &bytes).expect("the real file loads");
        assert!(!original.triangles.is_empty());
        for case in 0..150 {
            let mutant = mutate(&mut rng, &bytes);
            let result = std::panic::catch_unwind(|| load::parse(Path::new(&path), &mutant));
            let Ok(result) = result else {
                panic!("{}: mutant {case} panicked", path.display());
            };
            match result {
                // A triangle takes at least a few bytes in every format (a shared index
                // in binary PLY, three in text), so the count is bounded by the size.
                Ok(mesh) => assert!(
                    mesh.triangles.len() <= 2 * mutant.len(),
                    "{}: mutant {case}: {} triangles from {} bytes",
                    path.display(),
                    mesh.triangles.len(),
                    mutant.len()
                ),
                Err(message) => assert!(
                    !message.contains('\n') && message.starts_with(&path.display().to_string()),
                    "{}: mutant {case}: {message:?}",
                    path.display()
                ),
            }
        }
    }
}
