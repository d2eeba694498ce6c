//! glTF 2.0 (`.gltf` JSON and `.glb` binary), as the scene format (section 8) reads it:
//! the triangle primitives (modes 4, 5 and 6) of every mesh reached from the default
//! scene (`scene`, else `scenes[0]`), its root nodes in order, depth first, each node's
//! primitives in order, with the nodes' matrices or TRS applied to the positions (and
//! by their inverse transpose to the normals). Buffers are the GLB's binary chunk, data
//! URIs in base64, or files beside the `.gltf` (read by the caller's `file` function).
//!
//! Refused: any `extensionsRequired`, sparse or non-float positions, an index count of
//! a triangle list that is not a multiple of 3, nodes deeper than 64 levels or in a
//! cycle, a node reached a second time (glTF gives a node one parent at most: walking
//! a node again for each path to it would make a few nodes, each naming the next twice,
//! take forever), a singular node matrix. Every count and offset is checked against the
//! bytes there are before anything is read, and nothing is allocated from a count alone.
//! Since primitives and nodes may name the same accessors again and again, what they add
//! is held to the renderer's triangle limit (and three positions a triangle) before it
//! is read.

use serde_json::Value;

use super::{MeshData, MeshError, NO_NORMAL};
use crate::limits::MAX_MESH_TRIANGLES;

/// How deep nodes may nest.
pub const MAX_DEPTH: usize = 64;

/// A row-major 3 × 4 affine matrix [A | t].
type Affine = [[f64; 4]; 3];

const IDENTITY: Affine = [
    [1.0, 0.0, 0.0, 0.0],
    [0.0, 1.0, 0.0, 0.0],
    [0.0, 0.0, 1.0, 0.0],
];

fn fail(message: impl Into<String>) -> MeshError {
    MeshError::Format(message.into())
}

/// Reads a `.glb` file's bytes.
pub fn read_glb(
    bytes: &[u8],
    file: &dyn Fn(&str) -> Result<Vec<u8>, String>,
) -> Result<MeshData, MeshError> {
    let (json, bin) = glb_chunks(bytes)?;
    let document: Value =
        serde_json::from_slice(json).map_err(|e| fail(format!("the GLB's JSON: {e}")))?;
    read_document(&document, bin, file)
}

/// A GLB file's JSON chunk and its binary chunk, if it has one (of several of a kind,
/// the last).
fn glb_chunks(bytes: &[u8]) -> Result<(&[u8], Option<&[u8]>), MeshError> {
    let word = |at: usize| -> Result<u32, MeshError> {
        bytes
            .get(at..at + 4)
            .map(|b| u32::from_le_bytes(b.try_into().expect("4 bytes")))
            .ok_or_else(|| fail("the GLB file ends inside its header"))
    };
    if bytes.get(..4) != Some(b"glTF") {
        return Err(fail("not a GLB file (no `glTF` magic)"));
    }
    if word(4)? != 2 {
        return Err(fail(format!("GLB version {}, not 2", word(4)?)));
    }
    let mut at = 12;
    let mut json = None;
    let mut bin = None;
    while at < bytes.len() {
        let length = word(at)? as usize;
        let kind = word(at + 4)?;
        let chunk = bytes.get(at + 8..at + 8 + length).ok_or_else(|| {
            fail(format!(
                "a GLB chunk of {length} bytes at byte {at} goes past the end"
            ))
        })?;
        match kind {
            0x4E4F_534A => json = Some(chunk),
            0x004E_4942 => bin = Some(chunk),
            _ => {}
        }
        at += 8 + length;
    }
    let json = json.ok_or_else(|| fail("the GLB file has no JSON chunk"))?;
    Ok((json, bin))
}

/// The uris of the buffer files a `.gltf` (or, with `glb`, a `.glb`) reads, in the
/// order its reader asks for them, found without reading its mesh: what a file's
/// SHA-256 covers besides its own bytes, so that geometry already built for the same
/// bytes is found before any is read. `None` if the document cannot be read at all
/// (its reader then says why).
pub(crate) fn buffer_files(bytes: &[u8], glb: bool) -> Option<Vec<String>> {
    let json = if glb {
        glb_chunks(bytes).ok()?.0
    } else {
        bytes
    };
    let document: Value = serde_json::from_slice(json).ok()?;
    // As `load_buffer` tells them: a buffer without a uri is the GLB's chunk, and a
    // `data:` URI holds its bytes.
    let uris = document["buffers"].as_array().map(|list| {
        list.iter()
            .filter_map(|buffer| buffer["uri"].as_str())
            .filter(|uri| !uri.starts_with("data:"))
            .map(str::to_owned)
            .collect()
    });
    Some(uris.unwrap_or_default())
}

/// Reads a `.gltf` file's text.
pub fn read_gltf(
    text: &[u8],
    file: &dyn Fn(&str) -> Result<Vec<u8>, String>,
) -> Result<MeshData, MeshError> {
    let document: Value = serde_json::from_slice(text).map_err(|e| MeshError::Line {
        line: e.line(),
        message: e.to_string(),
    })?;
    read_document(&document, None, file)
}

fn read_document(
    document: &Value,
    glb: Option<&[u8]>,
    file: &dyn Fn(&str) -> Result<Vec<u8>, String>,
) -> Result<MeshData, MeshError> {
    if let Some(required) = document["extensionsRequired"]
        .as_array()
        .filter(|r| !r.is_empty())
    {
        let names: Vec<String> = required
            .iter()
            .map(|v| {
                v.as_str()
                    .map_or_else(|| v.to_string(), |s| format!("{s:?}"))
            })
            .collect();
        return Err(fail(format!(
            "extensionsRequired {}: not supported",
            super::cut(&names.join(", "))
        )));
    }
    // glTF 1.0 files share the extension and mean something else.
    match &document["asset"]["version"] {
        Value::String(v) if v.split('.').next() == Some("2") => {}
        Value::String(v) => {
            return Err(fail(format!(
                "asset.version {:?}: only glTF 2.0 is read",
                super::cut(v)
            )))
        }
        _ => return Err(fail("asset.version is missing: not a glTF 2.0 file")),
    }
    let buffers = document["buffers"]
        .as_array()
        .map(|list| {
            list.iter()
                .enumerate()
                .map(|(i, buffer)| load_buffer(i, buffer, glb, file))
                .collect::<Result<Vec<_>, _>>()
        })
        .transpose()?
        .unwrap_or_default();
    let scene = match &document["scene"] {
        Value::Null => 0,
        v => index(v, "the default scene (`scene`)")?,
    };
    let roots = document["scenes"][scene]["nodes"]
        .as_array()
        .ok_or_else(|| fail(format!("scenes[{scene}] has no nodes")))?;
    let mut mesh = MeshData::default();
    let mut walked = Walked::default();
    for root in roots {
        let node = index(root, "a scene's node")?;
        walk(document, &buffers, node, &IDENTITY, &mut walked, &mut mesh)?;
    }
    Ok(mesh)
}

fn index(value: &Value, what: &str) -> Result<usize, MeshError> {
    value.as_u64().map(|v| v as usize).ok_or_else(|| {
        fail(format!(
            "{what} is not an index: {}",
            super::cut(&value.to_string())
        ))
    })
}

fn load_buffer(
    i: usize,
    buffer: &Value,
    glb: Option<&[u8]>,
    file: &dyn Fn(&str) -> Result<Vec<u8>, String>,
) -> Result<Vec<u8>, MeshError> {
    let bytes = match buffer["uri"].as_str() {
        None => glb
            .ok_or_else(|| {
                fail(format!(
                    "buffers[{i}] has no uri and there is no GLB binary chunk"
                ))
            })?
            .to_vec(),
        Some(uri) if uri.starts_with("data:") => {
            use base64::Engine;
            let data = uri
                .split_once(";base64,")
                .map(|(_, data)| data)
                .ok_or_else(|| fail(format!("buffers[{i}]: a data URI that is not base64")))?;
            base64::engine::general_purpose::STANDARD
                .decode(data)
                .map_err(|e| fail(format!("buffers[{i}]: {e}")))?
        }
        Some(uri) => {
            file(uri).map_err(|e| fail(format!("buffers[{i}] ({}): {e}", super::quoted(uri))))?
        }
    };
    let declared = buffer["byteLength"].as_u64().unwrap_or(0);
    if (bytes.len() as u64) < declared {
        return Err(fail(format!(
            "buffers[{i}] holds {} bytes, less than its byteLength {declared}",
            bytes.len()
        )));
    }
    Ok(bytes)
}

/// The nodes of the walk: those above the current one, and all those reached.
#[derive(Default)]
struct Walked {
    path: Vec<usize>,
    reached: std::collections::HashSet<usize>,
}

fn walk(
    document: &Value,
    buffers: &[Vec<u8>],
    node: usize,
    parent: &Affine,
    walked: &mut Walked,
    mesh: &mut MeshData,
) -> Result<(), MeshError> {
    if walked.path.contains(&node) {
        return Err(fail(format!("nodes[{node}] is its own ancestor: a cycle")));
    }
    if walked.path.len() >= MAX_DEPTH {
        return Err(fail(format!("nodes deeper than {MAX_DEPTH} levels")));
    }
    if !walked.reached.insert(node) {
        return Err(fail(format!(
            "nodes[{node}] is reached a second time: a node has at most one parent"
        )));
    }
    let value = &document["nodes"][node];
    if value.is_null() {
        return Err(fail(format!("nodes[{node}] does not exist")));
    }
    let local = node_matrix(value).map_err(|m| fail(format!("nodes[{node}]: {m}")))?;
    let matrix = compose(parent, &local);
    if determinant(&matrix) == 0.0 {
        return Err(fail(format!("nodes[{node}]: a singular matrix")));
    }
    if let Some(m) = value.get("mesh") {
        let m = index(m, "a node's mesh")?;
        let primitives = document["meshes"][m]["primitives"]
            .as_array()
            .ok_or_else(|| fail(format!("meshes[{m}] has no primitives")))?;
        for (p, primitive) in primitives.iter().enumerate() {
            add_primitive(document, buffers, primitive, &matrix, mesh)
                .map_err(|e| fail(format!("meshes[{m}].primitives[{p}]: {e}")))?;
        }
    }
    walked.path.push(node);
    if let Some(children) = value["children"].as_array() {
        for child in children {
            let child = index(child, "a node's child")?;
            walk(document, buffers, child, &matrix, walked, mesh)?;
        }
    }
    walked.path.pop();
    Ok(())
}

/// A node's own matrix: `matrix` (16 numbers, column-major), else T·R·S from
/// `translation`, `rotation` (a unit quaternion x, y, z, w) and `scale`.
fn node_matrix(node: &Value) -> Result<Affine, String> {
    let numbers = |key: &str, n: usize| -> Result<Option<Vec<f64>>, String> {
        match node.get(key) {
            None => Ok(None),
            Some(v) => {
                let list: Option<Vec<f64>> = v
                    .as_array()
                    .and_then(|a| a.iter().map(Value::as_f64).collect());
                match list {
                    Some(list) if list.len() == n && list.iter().all(|x| x.is_finite()) => {
                        Ok(Some(list))
                    }
                    _ => Err(format!("{key} is not {n} finite numbers")),
                }
            }
        }
    };
    if let Some(m) = numbers("matrix", 16)? {
        // Column-major: element (row r, column c) is m[4c + r].
        return Ok(std::array::from_fn(|r| {
            std::array::from_fn(|c| m[4 * c + r])
        }));
    }
    let t = numbers("translation", 3)?.unwrap_or(vec![0.0; 3]);
    let q = numbers("rotation", 4)?.unwrap_or(vec![0.0, 0.0, 0.0, 1.0]);
    let s = numbers("scale", 3)?.unwrap_or(vec![1.0; 3]);
    let (x, y, z, w) = (q[0], q[1], q[2], q[3]);
    let rotation = [
        [
            1.0 - 2.0 * (y * y + z * z),
            2.0 * (x * y - z * w),
            2.0 * (x * z + y * w),
        ],
        [
            2.0 * (x * y + z * w),
            1.0 - 2.0 * (x * x + z * z),
            2.0 * (y * z - x * w),
        ],
        [
            2.0 * (x * z - y * w),
            2.0 * (y * z + x * w),
            1.0 - 2.0 * (x * x + y * y),
        ],
    ];
    Ok(std::array::from_fn(|r| {
        [
            rotation[r][0] * s[0],
            rotation[r][1] * s[1],
            rotation[r][2] * s[2],
            t[r],
        ]
    }))
}

fn compose(a: &Affine, b: &Affine) -> Affine {
    std::array::from_fn(|r| {
        std::array::from_fn(|c| {
            let linear = a[r][0] * b[0][c] + a[r][1] * b[1][c] + a[r][2] * b[2][c];
            if c == 3 {
                linear + a[r][3]
            } else {
                linear
            }
        })
    })
}

fn determinant(m: &Affine) -> f64 {
    m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
        - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
        + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
}

/// The inverse transpose of `m`'s linear part, which carries normals.
fn normal_matrix(m: &Affine) -> [[f64; 3]; 3] {
    let d = determinant(m);
    let c =
        |r0: usize, c0: usize, r1: usize, c1: usize| m[r0][c0] * m[r1][c1] - m[r0][c1] * m[r1][c0];
    // The cofactor matrix over the determinant: the inverse's transpose.
    [
        [c(1, 1, 2, 2) / d, -c(1, 0, 2, 2) / d, c(1, 0, 2, 1) / d],
        [-c(0, 1, 2, 2) / d, c(0, 0, 2, 2) / d, -c(0, 0, 2, 1) / d],
        [c(0, 1, 1, 2) / d, -c(0, 0, 1, 2) / d, c(0, 0, 1, 1) / d],
    ]
}

fn add_primitive(
    document: &Value,
    buffers: &[Vec<u8>],
    primitive: &Value,
    matrix: &Affine,
    mesh: &mut MeshData,
) -> Result<(), String> {
    let mode = primitive["mode"].as_u64().unwrap_or(4);
    if !matches!(mode, 4..=6) {
        return Ok(());
    }
    let position = primitive["attributes"]["POSITION"]
        .as_u64()
        .ok_or("no POSITION attribute")? as usize;
    let room = (3 * MAX_MESH_TRIANGLES).saturating_sub(mesh.positions.len());
    let positions = accessor(document, buffers, position, true, room as u64)?;
    let base = mesh.positions.len();
    for p in positions.chunks_exact(3) {
        mesh.positions.push(std::array::from_fn(|r| {
            matrix[r][0] * p[0] + matrix[r][1] * p[1] + matrix[r][2] * p[2] + matrix[r][3]
        }));
    }
    let count = mesh.positions.len() - base;
    let normal_base = mesh.normals.len();
    let has_normals = match primitive["attributes"]["NORMAL"].as_u64() {
        Some(n) => {
            let normals = accessor(document, buffers, n as usize, true, count as u64)?;
            if normals.len() / 3 != count {
                return Err(format!(
                    "{} normals for {count} positions",
                    normals.len() / 3
                ));
            }
            let carry = normal_matrix(matrix);
            for n in normals.chunks_exact(3) {
                mesh.normals.push(std::array::from_fn(|r| {
                    carry[r][0] * n[0] + carry[r][1] * n[1] + carry[r][2] * n[2]
                }));
            }
            true
        }
        None => false,
    };
    let room = MAX_MESH_TRIANGLES - mesh.triangles.len();
    // The most indices that make no more triangles than there is room for.
    let most = if mode == 4 { 3 * room + 2 } else { room + 2 };
    let indices: Vec<usize> = match primitive["indices"].as_u64() {
        Some(i) => accessor(document, buffers, i as usize, false, most as u64)?
            .into_iter()
            .map(|v| v as usize)
            .collect(),
        None => (0..count).collect(),
    };
    let made = if mode == 4 {
        indices.len() / 3
    } else {
        indices.len().saturating_sub(2)
    };
    if made > room {
        return Err(format!(
            "more than the limit of {MAX_MESH_TRIANGLES} triangles"
        ));
    }
    if let Some(&bad) = indices.iter().find(|&&i| i >= count) {
        return Err(format!(
            "index {bad} is out of range: the primitive has {count} positions"
        ));
    }
    let mut triangle = |a: usize, b: usize, c: usize| {
        mesh.triangles
            .push([(base + a) as u32, (base + b) as u32, (base + c) as u32]);
        mesh.corner_normals.push(if has_normals {
            [
                (normal_base + a) as u32,
                (normal_base + b) as u32,
                (normal_base + c) as u32,
            ]
        } else {
            [NO_NORMAL; 3]
        });
    };
    match mode {
        4 => {
            if !indices.len().is_multiple_of(3) {
                return Err(format!(
                    "{} indices of a triangle list: not a multiple of 3",
                    indices.len()
                ));
            }
            for t in indices.chunks_exact(3) {
                triangle(t[0], t[1], t[2]);
            }
        }
        5 => {
            for i in 2..indices.len() {
                // As glTF numbers them: triangle t is (t, t+1, t+2) for an even t and
                // (t, t+2, t+1) for an odd one, which keeps the winding.
                if i.is_multiple_of(2) {
                    triangle(indices[i - 2], indices[i - 1], indices[i]);
                } else {
                    triangle(indices[i - 2], indices[i], indices[i - 1]);
                }
            }
        }
        _ => {
            for i in 2..indices.len() {
                triangle(indices[0], indices[i - 1], indices[i]);
            }
        }
    }
    Ok(())
}

/// An accessor's values as doubles: `VEC3` of floats for positions and normals
/// (`float`), `SCALAR` of unsigned integers for indices. Its count, offset and stride
/// are checked against the bytes of its buffer view, and its count against `most`,
/// before a value is read.
fn accessor(
    document: &Value,
    buffers: &[Vec<u8>],
    i: usize,
    float: bool,
    most: u64,
) -> Result<Vec<f64>, String> {
    let a = &document["accessors"][i];
    if a.is_null() {
        return Err(format!("accessors[{i}] does not exist"));
    }
    if !a["sparse"].is_null() {
        return Err(format!("accessors[{i}] is sparse"));
    }
    let (components, size): (usize, usize) =
        match (float, a["type"].as_str(), a["componentType"].as_u64()) {
            (true, Some("VEC3"), Some(5126)) => (3, 4),
            (true, _, _) => {
                return Err(format!(
                    "accessors[{i}]: positions and normals must be VEC3 of float"
                ))
            }
            (false, Some("SCALAR"), Some(5121)) => (1, 1),
            (false, Some("SCALAR"), Some(5123)) => (1, 2),
            (false, Some("SCALAR"), Some(5125)) => (1, 4),
            (false, _, _) => {
                return Err(format!(
                    "accessors[{i}]: indices must be SCALAR of unsigned integers"
                ))
            }
        };
    let count = a["count"]
        .as_u64()
        .ok_or(format!("accessors[{i}] has no count"))?;
    let view_index = a["bufferView"]
        .as_u64()
        .ok_or(format!("accessors[{i}] has no bufferView"))? as usize;
    let view = &document["bufferViews"][view_index];
    let buffer = buffers
        .get(view["buffer"].as_u64().unwrap_or(u64::MAX) as usize)
        .ok_or(format!("bufferViews[{view_index}] names no buffer"))?;
    let view_offset = view["byteOffset"].as_u64().unwrap_or(0);
    let view_length = view["byteLength"].as_u64().unwrap_or(0);
    let element = (components * size) as u64;
    let stride = view["byteStride"].as_u64().unwrap_or(element).max(element);
    let offset = a["byteOffset"].as_u64().unwrap_or(0);
    // The last element must end inside the view, and the view inside the buffer (sums
    // that pass the largest number do not fit either).
    let end = if count == 0 {
        0
    } else {
        offset.saturating_add((count - 1).saturating_mul(stride).saturating_add(element))
    };
    if view_offset.saturating_add(view_length) > buffer.len() as u64 || end > view_length {
        return Err(format!(
            "accessors[{i}]: {count} elements do not fit in their buffer view"
        ));
    }
    if count > most {
        return Err(format!(
            "accessors[{i}]: {count} elements, more than the limit of \
             {MAX_MESH_TRIANGLES} triangles leaves room for"
        ));
    }
    let mut values = Vec::new();
    for k in 0..count {
        let start = (view_offset + offset + k * stride) as usize;
        for c in 0..components {
            let at = start + c * size;
            let b = &buffer[at..at + size];
            let value = match size {
                1 => f64::from(b[0]),
                2 => f64::from(u16::from_le_bytes([b[0], b[1]])),
                _ if float => f64::from(f32::from_le_bytes([b[0], b[1], b[2], b[3]])),
                _ => f64::from(u32::from_le_bytes([b[0], b[1], b[2], b[3]])),
            };
            if !value.is_finite() {
                return Err(format!("accessors[{i}]: element {k} is not finite"));
            }
            values.push(value);
        }
    }
    Ok(values)
}

#[cfg(test)]
mod tests {
    use super::*;
    use base64::Engine;

    /// A document with one buffer holding `positions` (floats) and `indices` (u16),
    /// its nodes as given.
    fn document(
        positions: &[[f32; 3]],
        indices: &[u16],
        mode: u64,
        nodes: &str,
        roots: &str,
    ) -> String {
        let mut bytes = Vec::new();
        for p in positions {
            for x in p {
                bytes.extend_from_slice(&x.to_le_bytes());
            }
        }
        let index_offset = bytes.len();
        for i in indices {
            bytes.extend_from_slice(&i.to_le_bytes());
        }
        let data = base64::engine::general_purpose::STANDARD.encode(&bytes);
        format!(
            r#"{{"asset": {{"version": "2.0"}}, "scene": 0, "scenes": [{{"nodes": {roots}}}],
            "nodes": {nodes},
            "meshes": [{{"primitives": [{{"attributes": {{"POSITION": 0}}, "indices": 1, "mode": {mode}}}]}}],
            "buffers": [{{"byteLength": {}, "uri": "data:application/octet-stream;base64,{data}"}}],
            "bufferViews": [{{"buffer": 0, "byteOffset": 0, "byteLength": {index_offset}}},
                            {{"buffer": 0, "byteOffset": {index_offset}, "byteLength": {}}}],
            "accessors": [{{"bufferView": 0, "componentType": 5126, "count": {}, "type": "VEC3"}},
                          {{"bufferView": 1, "componentType": 5123, "count": {}, "type": "SCALAR"}}]}}"#,
            bytes.len(),
            indices.len() * 2,
            positions.len(),
            indices.len()
        )
    }

    const SQUARE: [[f32; 3]; 4] = [
        [0.0, 0.0, 0.0],
        [1.0, 0.0, 0.0],
        [1.0, 1.0, 0.0],
        [0.0, 1.0, 0.0],
    ];

    fn no_files(name: &str) -> Result<Vec<u8>, String> {
        Err(format!("no file {name}"))
    }

    fn read(text: &str) -> Result<MeshData, MeshError> {
        read_gltf(text.as_bytes(), &no_files)
    }

    #[test]
    fn node_transforms_apply_to_positions() {
        let nodes =
            r#"[{"children": [1], "translation": [10, 0, 0]}, {"mesh": 0, "scale": [2, 2, 2]}]"#;
        let mesh = read(&document(&SQUARE, &[0, 1, 2, 0, 2, 3], 4, nodes, "[0]")).unwrap();
        assert_eq!(mesh.triangles, vec![[0, 1, 2], [0, 2, 3]]);
        assert_eq!(mesh.positions[2], [12.0, 2.0, 0.0]);
    }

    #[test]
    fn strips_and_fans_make_the_same_square() {
        let nodes = r#"[{"mesh": 0}]"#;
        let fan = read(&document(&SQUARE, &[0, 1, 2, 3], 6, nodes, "[0]")).unwrap();
        assert_eq!(fan.triangles, vec![[0, 1, 2], [0, 2, 3]]);
        let strip = read(&document(&SQUARE, &[1, 2, 0, 3], 5, nodes, "[0]")).unwrap();
        assert_eq!(strip.triangles, vec![[1, 2, 0], [2, 3, 0]]);
    }

    #[test]
    fn versions_other_than_2_and_a_default_scene_that_is_no_index_are_refused() {
        let read = |text: &str| read_gltf(text.as_bytes(), &|_| Err("no files".into()));
        assert_eq!(
            read(r#"{"asset": {"version": "1.0"}, "scenes": []}"#)
                .unwrap_err()
                .to_string(),
            "asset.version \"1.0\": only glTF 2.0 is read"
        );
        assert_eq!(
            read(r#"{"scenes": []}"#).unwrap_err().to_string(),
            "asset.version is missing: not a glTF 2.0 file"
        );
        assert_eq!(
            read(r#"{"asset": {"version": "2.0"}, "scene": "hello", "scenes": []}"#)
                .unwrap_err()
                .to_string(),
            "the default scene (`scene`) is not an index: \"hello\""
        );
    }

    #[test]
    fn cycles_depth_singular_matrices_and_bad_indices_are_refused() {
        let error = |nodes: &str, indices: &[u16]| {
            read(&document(&SQUARE, indices, 4, nodes, "[0]"))
                .unwrap_err()
                .to_string()
        };
        let square = [0, 1, 2, 0, 2, 3];
        assert_eq!(
            error(
                r#"[{"children": [1]}, {"children": [0], "mesh": 0}]"#,
                &square
            ),
            "nodes[0] is its own ancestor: a cycle"
        );
        let deep: Vec<String> = (0..70)
            .map(|i| format!(r#"{{"children": [{}]}}"#, i + 1))
            .chain(std::iter::once("{}".to_owned()))
            .collect();
        assert_eq!(
            error(&format!("[{}]", deep.join(",")), &square),
            format!("nodes deeper than {MAX_DEPTH} levels")
        );
        assert_eq!(
            error(r#"[{"mesh": 0, "scale": [1, 0, 1]}]"#, &square),
            "nodes[0]: a singular matrix"
        );
        assert_eq!(
            error(r#"[{"mesh": 0}]"#, &[0, 1, 2, 0]),
            "meshes[0].primitives[0]: 4 indices of a triangle list: not a multiple of 3"
        );
        assert_eq!(
            error(r#"[{"mesh": 0}]"#, &[0, 1, 9]),
            "meshes[0].primitives[0]: index 9 is out of range: the primitive has 4 positions"
        );
        // Each node naming the next twice: 2^60 paths to the last one.
        let lattice: Vec<String> = (1..60)
            .map(|i| format!(r#"{{"children": [{i}, {i}]}}"#))
            .chain(std::iter::once(r#"{"mesh": 0}"#.to_owned()))
            .collect();
        assert_eq!(
            error(&format!("[{}]", lattice.join(",")), &square),
            "nodes[59] is reached a second time: a node has at most one parent"
        );
        assert_eq!(
            read(&document(&SQUARE, &square, 4, r#"[{"mesh": 0}]"#, "[0, 0]"))
                .unwrap_err()
                .to_string(),
            "nodes[0] is reached a second time: a node has at most one parent"
        );
        let required = r#"{"extensionsRequired": ["KHR_draco_mesh_compression"]}"#;
        assert!(read(required)
            .unwrap_err()
            .to_string()
            .starts_with("extensionsRequired"));
    }

    #[test]
    fn a_count_the_buffer_does_not_hold_is_refused_before_reading() {
        let text = document(&SQUARE, &[0, 1, 2], 4, r#"[{"mesh": 0}]"#, "[0]").replace(
            r#""count": 4, "type": "VEC3""#,
            r#""count": 1000000000000, "type": "VEC3""#,
        );
        assert_eq!(
            read(&text).unwrap_err().to_string(),
            "meshes[0].primitives[0]: accessors[0]: 1000000000000 elements do not fit in their buffer view"
        );
    }

    #[test]
    fn an_offset_whose_end_passes_the_largest_number_is_refused() {
        let text = document(&SQUARE, &[0, 1, 2], 4, r#"[{"mesh": 0}]"#, "[0]").replace(
            r#""count": 4, "type": "VEC3""#,
            r#""count": 4, "byteOffset": 18446744073709551615, "type": "VEC3""#,
        );
        assert_eq!(
            read(&text).unwrap_err().to_string(),
            "meshes[0].primitives[0]: accessors[0]: 4 elements do not fit in their buffer view"
        );
    }

    #[test]
    fn a_glb_reads_as_its_json_and_binary_chunk() {
        let mut positions = Vec::new();
        for p in SQUARE {
            for x in p {
                positions.extend_from_slice(&x.to_le_bytes());
            }
        }
        let json = format!(
            r#"{{"asset": {{"version": "2.0"}}, "scenes": [{{"nodes": [0]}}], "nodes": [{{"mesh": 0}}],
            "meshes": [{{"primitives": [{{"attributes": {{"POSITION": 0}}, "mode": 6}}]}}],
            "buffers": [{{"byteLength": {0}}}], "bufferViews": [{{"buffer": 0, "byteLength": {0}}}],
            "accessors": [{{"bufferView": 0, "componentType": 5126, "count": 4, "type": "VEC3"}}]}}  "#,
            positions.len()
        );
        let mut glb = b"glTF".to_vec();
        glb.extend_from_slice(&2u32.to_le_bytes());
        glb.extend_from_slice(&0u32.to_le_bytes());
        glb.extend_from_slice(&(json.len() as u32).to_le_bytes());
        glb.extend_from_slice(&0x4E4F_534Au32.to_le_bytes());
        glb.extend_from_slice(json.as_bytes());
        glb.extend_from_slice(&(positions.len() as u32).to_le_bytes());
        glb.extend_from_slice(&0x004E_4942u32.to_le_bytes());
        glb.extend_from_slice(&positions);
        let mesh = read_glb(&glb, &no_files).unwrap();
        assert_eq!(mesh.triangles, vec![[0, 1, 2], [0, 2, 3]]);
        assert_eq!(mesh.positions[2], [1.0, 1.0, 0.0]);
    }
}
