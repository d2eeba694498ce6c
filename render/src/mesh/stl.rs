//! STL, ASCII and binary, as the scene format (section 8) reads it: binary exactly when
//! the file's size is 84 + 50·n for the count n its header gives, ASCII otherwise. The
//! stored facet normals are ignored, and vertices are not merged: each facet brings its
//! own three, so a smooth normal computed for an STL mesh is its flat normal.
//!
//! A binary file's count is believed only once the size agrees with it, so nothing is
//! allocated for a count the bytes do not hold; a count beyond the renderer's triangle
//! limit is refused before any facet is read, and an ASCII file's facets are read no
//! further than the limit.

use super::{MeshData, MeshError, NO_NORMAL};
use crate::limits::MAX_MESH_TRIANGLES;

/// Reads an STL file's bytes.
pub fn read(bytes: &[u8]) -> Result<MeshData, MeshError> {
    match binary_count(bytes) {
        Some(count) => read_binary(&bytes[84..], count),
        None => read_ascii(bytes),
    }
}

/// The facet count of a binary file, if the size is exactly that of one.
fn binary_count(bytes: &[u8]) -> Option<usize> {
    let header: [u8; 4] = bytes.get(80..84)?.try_into().ok()?;
    let count = u32::from_le_bytes(header) as u64;
    (bytes.len() as u64 == 84 + 50 * count).then_some(count as usize)
}

/// Facets of 50 bytes: a normal, three vertices (12 little-endian `f32` in all), two
/// attribute bytes. `f32` values are exact as doubles; a non-finite one is an error.
fn read_binary(records: &[u8], count: usize) -> Result<MeshData, MeshError> {
    if count > MAX_MESH_TRIANGLES {
        return Err(MeshError::Format(format!(
            "{count} facets, more than the limit of {MAX_MESH_TRIANGLES} triangles"
        )));
    }
    let mut mesh = MeshData::default();
    for (record, facet) in records.chunks_exact(50).take(count).enumerate() {
        let mut corners = [0u32; 3];
        for (k, corner) in corners.iter_mut().enumerate() {
            let mut v = [0.0; 3];
            for (axis, slot) in v.iter_mut().enumerate() {
                let at = 12 + 12 * k + 4 * axis;
                let value = f32::from_le_bytes(facet[at..at + 4].try_into().expect("4 bytes"));
                if !value.is_finite() {
                    return Err(MeshError::Record {
                        record: record + 1,
                        message: format!("vertex {} is not finite ({value})", k + 1),
                    });
                }
                *slot = f64::from(value);
            }
            *corner = push(&mut mesh, v);
        }
        mesh.triangles.push(corners);
        mesh.corner_normals.push([NO_NORMAL; 3]);
    }
    Ok(mesh)
}

fn push(mesh: &mut MeshData, v: [f64; 3]) -> u32 {
    mesh.positions.push(v);
    (mesh.positions.len() - 1) as u32
}

/// `solid … facet normal … outer loop, vertex x y z ×3, endloop, endfacet … endsolid`:
/// the `vertex` lines between `outer loop` and `endloop` make a facet, which must have
/// three; everything else is not looked at beyond its first word.
fn read_ascii(bytes: &[u8]) -> Result<MeshData, MeshError> {
    let text = std::str::from_utf8(bytes).map_err(|e| MeshError::Line {
        line: 1 + bytes[..e.valid_up_to()]
            .iter()
            .filter(|&&b| b == b'\n')
            .count(),
        message: "neither a binary STL (its size is not 84 + 50 × its facet count) nor text".into(),
    })?;
    let mut mesh = MeshData::default();
    let mut open: Option<(usize, Vec<u32>)> = None;
    let mut solid = false;
    for (number, line) in text.lines().enumerate() {
        let line_number = number + 1;
        let at = |message: String| MeshError::Line {
            line: line_number,
            message,
        };
        let mut words = line.split_whitespace();
        match words.next() {
            Some("solid") => solid = true,
            Some("outer") => {
                if open.is_some() {
                    return Err(at("`outer loop` inside another loop".into()));
                }
                open = Some((line_number, Vec::with_capacity(3)));
            }
            Some("vertex") => {
                let Some((_, corners)) = open.as_mut() else {
                    return Err(at("a vertex outside `outer loop` … `endloop`".into()));
                };
                let mut v = [0.0; 3];
                for (k, slot) in v.iter_mut().enumerate() {
                    let word = words
                        .next()
                        .ok_or_else(|| at(format!("{k} numbers where 3 are needed")))?;
                    *slot = super::number(word).map_err(at)?;
                }
                if corners.len() == 3 {
                    return Err(at("a fourth vertex in a facet: a facet has 3".into()));
                }
                corners.push(push(&mut mesh, v));
            }
            Some("endloop") => {
                let Some((_, corners)) = open.take() else {
                    return Err(at("`endloop` without `outer loop`".into()));
                };
                let corners: [u32; 3] = corners.try_into().map_err(|c: Vec<u32>| {
                    at(format!("a facet of {} vertices: a facet has 3", c.len()))
                })?;
                if mesh.triangles.len() >= MAX_MESH_TRIANGLES {
                    return Err(at(format!(
                        "more than the limit of {MAX_MESH_TRIANGLES} triangles"
                    )));
                }
                mesh.triangles.push(corners);
                mesh.corner_normals.push([NO_NORMAL; 3]);
            }
            _ => {}
        }
    }
    if let Some((line, _)) = open {
        return Err(MeshError::Line {
            line,
            message: "a loop never closed (`endloop`): the file is cut short".into(),
        });
    }
    if !solid {
        return Err(MeshError::Line {
            line: 1,
            message: "neither a binary STL (its size is not 84 + 50 × its facet count) nor an \
                      ASCII one (no `solid` line)"
                .into(),
        });
    }
    Ok(mesh)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn binary(facets: &[[[f32; 3]; 3]], claimed: u32) -> Vec<u8> {
        let mut bytes = vec![0u8; 80];
        bytes.extend_from_slice(&claimed.to_le_bytes());
        for facet in facets {
            bytes.extend_from_slice(&[0u8; 12]);
            for v in facet {
                for x in v {
                    bytes.extend_from_slice(&x.to_le_bytes());
                }
            }
            bytes.extend_from_slice(&[0u8; 2]);
        }
        bytes
    }

    const TRIANGLE: [[f32; 3]; 3] = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.5, 0.0]];

    #[test]
    fn binary_and_ascii_give_the_same_mesh() {
        let from_binary = read(&binary(&[TRIANGLE, TRIANGLE], 2)).unwrap();
        let ascii = "solid t\n facet normal 0 0 1\n  outer loop\n   vertex 0 0 0\n   vertex 1 0 0\n\
                     vertex 0 1.5 0\n  endloop\n endfacet\n facet normal 0 0 1\n outer loop\n\
                     vertex 0 0 0\n vertex 1 0 0\n vertex 0 1.5 0\n endloop\n endfacet\nendsolid t\n";
        let from_ascii = read(ascii.as_bytes()).unwrap();
        assert_eq!(from_binary, from_ascii);
        // Vertices are not merged.
        assert_eq!(from_binary.positions.len(), 6);
        assert_eq!(from_binary.triangles, vec![[0, 1, 2], [3, 4, 5]]);
    }

    #[test]
    fn a_count_the_bytes_do_not_hold_is_not_believed() {
        // Claims 4 billion facets in 134 bytes: read as text, which it is not.
        let lie = binary(&[TRIANGLE], u32::MAX);
        let error = read(&lie).unwrap_err().to_string();
        assert!(error.contains("neither a binary STL"), "{error}");
        // A truncated binary file is not one either.
        let mut cut = binary(&[TRIANGLE, TRIANGLE], 2);
        cut.truncate(cut.len() - 7);
        assert!(read(&cut).is_err());
    }

    #[test]
    fn bad_facets_name_their_line_or_record() {
        let error = |text: &str| read(text.as_bytes()).unwrap_err().to_string();
        assert_eq!(
            error("solid x\nouter loop\nvertex 0 0 0\nvertex 1 0 0\nendloop\n"),
            "line 5: a facet of 2 vertices: a facet has 3"
        );
        assert_eq!(
            error("solid x\nouter loop\nvertex 0 0 0\nvertex 1 nan 0\n"),
            "line 4: \"nan\" is not a finite number"
        );
        assert_eq!(
            error("solid x\nouter loop\nvertex 0 0 0\n"),
            "line 2: a loop never closed (`endloop`): the file is cut short"
        );
        let mut infinite = TRIANGLE;
        infinite[1][2] = f32::INFINITY;
        let error = read(&binary(&[TRIANGLE, infinite], 2))
            .unwrap_err()
            .to_string();
        assert_eq!(error, "record 2: vertex 2 is not finite (inf)");
    }
}
