//! Wavefront OBJ, as the scene format (section 8) reads it: `v` lines (numbers after
//! the third ignored), `vn` lines, and `f` lines whose entries are `i`, `i/t`, `i//n` or
//! `i/t/n`; every other line is ignored. A negative index counts back from the last
//! vertex (or normal) read so far; a positive one may name any of the file, so the file's
//! `v` and `vn` lines are counted first, and every index is checked on its line. A face
//! of more than three corners is split as a fan (v0, vi, vi+1).
//!
//! Numbers are read to the nearest double (Rust's `f64` parsing is correctly rounded),
//! and `inf`, `nan` and anything not a finite number are errors. Nothing is allocated
//! from a count the file claims: OBJ has none, and the vectors grow with what is read,
//! triangles no further than the renderer's limit (a face of a line of corners makes as
//! many triangles, each larger than its corner's text).

use super::{MeshData, MeshError, NO_NORMAL};
use crate::limits::MAX_MESH_TRIANGLES;

/// Reads an OBJ file's text. Errors name the 1-based line; the first line in the file
/// that is wrong is the one named.
pub fn read(text: &str) -> Result<MeshData, MeshError> {
    let mut total = Counts::default();
    for line in text.lines() {
        match line.split_whitespace().next() {
            Some("v") => total.vertices += 1,
            Some("vn") => total.normals += 1,
            _ => {}
        }
    }
    let mut mesh = MeshData::default();
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
                let so_far = Counts {
                    vertices: mesh.positions.len(),
                    normals: mesh.normals.len(),
                };
                let mut corners = words.map(|entry| corner(entry, &so_far, &total));
                let mut next = || corners.next().transpose().map_err(at);
                let (first, mut previous) = match (next()?, next()?) {
                    (Some(first), Some(second)) => (first, second),
                    (first, _) => {
                        return Err(at(format!(
                            "a face of {} vertices: a face has at least 3",
                            usize::from(first.is_some())
                        )))
                    }
                };
                let mut count = 2;
                // The fan, made as the corners are read.
                while let Some(corner) = next()? {
                    if mesh.triangles.len() >= MAX_MESH_TRIANGLES {
                        return Err(at(format!(
                            "more than the limit of {MAX_MESH_TRIANGLES} triangles"
                        )));
                    }
                    mesh.triangles.push([first.0, previous.0, corner.0]);
                    mesh.corner_normals.push([first.1, previous.1, corner.1]);
                    previous = corner;
                    count += 1;
                }
                if count < 3 {
                    return Err(at("a face of 2 vertices: a face has at least 3".to_owned()));
                }
            }
            _ => {}
        }
    }
    Ok(mesh)
}

/// How many vertices and normals: in the file, or read so far.
#[derive(Clone, Copy, Debug, Default)]
struct Counts {
    vertices: usize,
    normals: usize,
}

/// A corner `i`, `i/t`, `i//n` or `i/t/n`: its vertex and its normal ([`NO_NORMAL`] if
/// none) as 0-based indices, negative ones counted back from those read `so_far`, each
/// checked against the file's `total`.
fn corner(entry: &str, so_far: &Counts, total: &Counts) -> Result<(u32, u32), String> {
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
    let vertex = index(vertex, so_far.vertices, total.vertices, "vertex", entry)?;
    let normal = match normal {
        None | Some("") => NO_NORMAL,
        Some(n) => index(n, so_far.normals, total.normals, "normal", entry)?,
    };
    Ok((vertex, normal))
}

/// A 1-based index as written (a negative one counting back from the `so_far` read),
/// checked against the file's `total`, as a 0-based `u32`.
fn index(text: &str, so_far: usize, total: usize, what: &str, entry: &str) -> Result<u32, String> {
    let value: i64 = text.parse().map_err(|_| {
        format!(
            "{}: {what} index {} is not an integer",
            super::quoted(entry),
            super::quoted(text)
        )
    })?;
    let value = match value {
        0 => {
            return Err(format!(
                "{}: {what} index 0 (indices start at 1)",
                super::quoted(entry)
            ))
        }
        v if v < 0 => {
            let absolute = so_far as i64 + 1 + v;
            if absolute < 1 {
                return Err(format!(
                    "{}: {what} index {v} counts back past the first {what} ({so_far} read so far)",
                    super::quoted(entry)
                ));
            }
            absolute
        }
        v => v,
    };
    if value as u64 > total as u64 {
        let plural = if what == "vertex" {
            "vertices"
        } else {
            "normals"
        };
        return Err(format!(
            "{what} index {value} is out of range: the file has {total} {plural}"
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
    fn the_first_line_in_error_is_named() {
        // An index out of range on line 4, a bad number on line 5.
        let error = read("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\nv 1 x 0\n")
            .unwrap_err()
            .to_string();
        assert_eq!(
            error,
            "line 4: vertex index 9 is out of range: the file has 4 vertices"
        );
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
