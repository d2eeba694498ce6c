//! Wavefront OBJ, as the scene format (section 8) reads it: `v` lines (numbers after
//! the third ignored), `vn` lines, and `f` lines whose entries are `i`, `i/t`, `i//n` or
//! `i/t/n`; every other line is ignored. A negative index counts back from the last
//! vertex (or normal) read so far; a positive one may name any of the file, so indices
//! are checked once the whole file is read. A face of more than three corners is split
//! as a fan (v0, vi, vi+1).
//!
//! Numbers are read to the nearest double (Rust's `f64` parsing is correctly rounded),
//! and `inf`, `nan` and anything not a finite number are errors. Nothing is allocated
//! from a count the file claims: OBJ has none, and the vectors grow with what is read.

use super::{MeshData, MeshError, NO_NORMAL};

/// Reads an OBJ file's text. Errors name the 1-based line.
pub fn read(text: &str) -> Result<MeshData, MeshError> {
    let mut mesh = MeshData::default();
    // Corners as written (1-based or negative, already made absolute), checked against
    // the counts once the file is read: (line, vertex, normal or None).
    let mut faces: Vec<(usize, [Corner; 3])> = Vec::new();
    for (number, line) in text.lines().enumerate() {
        let line_number = number + 1;
        let at = |message: String| MeshError::Line {
            line: line_number,
            message,
        };
        let mut words = line.split_whitespace();
        match words.next() {
            Some("v") => mesh.positions.push(vector(&mut words).map_err(at)?),
            Some("vn") => mesh.normals.push(vector(&mut words).map_err(at)?),
            Some("f") => {
                let corners = words
                    .map(|entry| corner(entry, mesh.positions.len(), mesh.normals.len()))
                    .collect::<Result<Vec<_>, _>>()
                    .map_err(at)?;
                if corners.len() < 3 {
                    return Err(at(format!(
                        "a face of {} vertices: a face has at least 3",
                        corners.len()
                    )));
                }
                for i in 1..corners.len() - 1 {
                    faces.push((line_number, [corners[0], corners[i], corners[i + 1]]));
                }
            }
            _ => {}
        }
    }
    let (vertices, normals) = (mesh.positions.len(), mesh.normals.len());
    for (line, corners) in faces {
        let at = |message: String| MeshError::Line { line, message };
        let mut triangle = [0u32; 3];
        let mut corner_normals = [NO_NORMAL; 3];
        for (k, c) in corners.iter().enumerate() {
            triangle[k] = index(c.vertex, vertices, "vertex").map_err(at)?;
            if let Some(n) = c.normal {
                corner_normals[k] = index(n, normals, "normal").map_err(at)?;
            }
        }
        mesh.triangles.push(triangle);
        mesh.corner_normals.push(corner_normals);
    }
    Ok(mesh)
}

/// One corner of a face: its vertex and normal as 0-based positions if known to be
/// in range so far, or as written for a positive index checked at the end.
#[derive(Clone, Copy, Debug)]
struct Corner {
    vertex: i64,
    normal: Option<i64>,
}

/// A corner `i`, `i/t`, `i//n` or `i/t/n`, its negative indices resolved against the
/// vertices and normals read so far (to 1-based indices).
fn corner(entry: &str, vertices: usize, normals: usize) -> Result<Corner, String> {
    let mut parts = entry.split('/');
    let vertex = parts.next().unwrap_or_default();
    let _texture = parts.next();
    let normal = parts.next();
    if parts.next().is_some() {
        return Err(format!(
            "{} is not a face corner (i, i/t, i//n or i/t/n)",
            super::quoted(entry)
        ));
    }
    let vertex = absolute(vertex, vertices, "vertex", entry)?;
    let normal = match normal {
        None | Some("") => None,
        Some(n) => Some(absolute(n, normals, "normal", entry)?),
    };
    Ok(Corner { vertex, normal })
}

/// A 1-based index as written, a negative one made absolute against `count` read so
/// far.
fn absolute(text: &str, count: usize, what: &str, entry: &str) -> Result<i64, String> {
    let value: i64 = text.parse().map_err(|_| {
        format!(
            "{}: {what} index {} is not an integer",
            super::quoted(entry),
            super::quoted(text)
        )
    })?;
    match value {
        0 => Err(format!(
            "{}: {what} index 0 (indices start at 1)",
            super::quoted(entry)
        )),
        v if v < 0 => {
            let absolute = count as i64 + 1 + v;
            if absolute < 1 {
                Err(format!(
                    "{}: {what} index {v} counts back past the first {what} ({count} read so far)",
                    super::quoted(entry)
                ))
            } else {
                Ok(absolute)
            }
        }
        v => Ok(v),
    }
}

/// A checked 1-based index as a 0-based `u32`.
fn index(value: i64, count: usize, what: &str) -> Result<u32, String> {
    if value < 1 || value as u64 > count as u64 {
        let plural = if what == "vertex" {
            "vertices"
        } else {
            "normals"
        };
        return Err(format!(
            "{what} index {value} is out of range: the file has {count} {plural}"
        ));
    }
    u32::try_from(value - 1).map_err(|_| format!("{what} index {value} is too large"))
}

/// Three finite numbers (more are ignored).
fn vector<'a>(words: &mut impl Iterator<Item = &'a str>) -> Result<[f64; 3], String> {
    let mut v = [0.0; 3];
    for (k, slot) in v.iter_mut().enumerate() {
        let word = words
            .next()
            .ok_or_else(|| format!("{} numbers where 3 are needed", k))?;
        *slot = super::number(word)?;
    }
    Ok(v)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_vertices_faces_fans_and_normals() {
        let text = "# a quad and a triangle\nv 0 0 0\nv 1 0 0 7\nv 1 1 0\nv 0 1 0\n\
                    vn 0 0 1\nf 1 2 3 4\nf -4//1 -3//-1 -2\ng ignored\nusemtl x\n";
        let mesh = read(text).unwrap();
        assert_eq!(mesh.positions.len(), 4);
        assert_eq!(mesh.positions[1], [1.0, 0.0, 0.0]);
        assert_eq!(mesh.triangles, vec![[0, 1, 2], [0, 2, 3], [0, 1, 2]]);
        assert_eq!(mesh.corner_normals[2], [0, 0, NO_NORMAL]);
        assert_eq!(mesh.corner_normals[0], [NO_NORMAL; 3]);
    }

    #[test]
    fn positive_indices_may_name_later_vertices() {
        let mesh = read("f 1 2 3\nv 0 0 0\nv 1 0 0\nv 0 1 0\n").unwrap();
        assert_eq!(mesh.triangles, vec![[0, 1, 2]]);
    }

    #[test]
    fn numbers_are_read_to_the_nearest_double() {
        let mesh = read("v 0.1 1e-3 -2.5E+2\n").unwrap();
        assert_eq!(mesh.positions[0], [0.1, 0.001, -250.0]);
    }

    #[test]
    fn mistakes_name_their_line() {
        let error = |text: &str| read(text).unwrap_err().to_string();
        assert_eq!(
            error("v 0 0 0\nv 1 nan 0\n"),
            "line 2: \"nan\" is not a finite number"
        );
        assert_eq!(
            error("v 0 0 0\nv inf 0 0\n"),
            "line 2: \"inf\" is not a finite number"
        );
        assert_eq!(error("v 0 0\n"), "line 1: 2 numbers where 3 are needed");
        assert_eq!(
            error("v 0 0 0\nv 1 0 0\nf 1 2\n"),
            "line 3: a face of 2 vertices: a face has at least 3"
        );
        assert_eq!(
            error("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n"),
            "line 4: vertex index 4 is out of range: the file has 3 vertices"
        );
        assert!(error("v 0 0 0\nf 0 1 1\n").starts_with("line 2: \"0\": vertex index 0"));
        assert!(error("v 0 0 0\nf -2 1 1\n").contains("counts back past the first vertex"));
        assert!(error("f 1/2/3/4 1 1\n").contains("is not a face corner"));
    }
}
