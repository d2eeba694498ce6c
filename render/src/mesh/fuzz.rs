//! Mutations of small valid files of every format: each reader gives a mesh or an
//! error, never a panic, and never more triangles than the bytes could hold.

use proptest::prelude::*;

const OBJ: &str =
    "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvn 0 0 1\nf 1//1 2//1 3//1 4//1\nf -1 -2 -3\n";
const PLY: &str = "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n\
                   property float z\nelement face 1\nproperty list uchar int vertex_indices\n\
                   end_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n";
const STL: &str = "solid s\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 0 0\n\
                   vertex 0 1 0\nendloop\nendfacet\nendsolid s\n";

fn binary_ply() -> Vec<u8> {
    let mut bytes = b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\n\
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
