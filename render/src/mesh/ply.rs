//! PLY, ASCII and binary (little- and big-endian), as the scene format (section 8)
//! reads it: the `vertex` element's `x y z` (and `nx ny nz` when all three are there),
//! the `face` element's `vertex_indices` or `vertex_index` list; comments, `obj_info`,
//! other elements and other properties are skipped.
//!
//! ASCII numbers are read to the nearest double whatever type the header declares (a
//! `property float` too). Nothing is allocated from the counts the header claims: the
//! records are read one by one, and a file that ends early is an error naming the
//! record it lacks. Triangles are made no further than the renderer's limit, and a list
//! no longer than a face within that limit is read (a face of one-byte indices makes
//! as many triangles as it has bytes, each of 24 bytes).

use super::{MeshData, MeshError};
use crate::limits::MAX_MESH_TRIANGLES;

/// A property's scalar type.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Scalar {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl Scalar {
    fn parse(name: &str) -> Option<Scalar> {
        Some(match name {
            "char" | "int8" => Scalar::I8,
            "uchar" | "uint8" => Scalar::U8,
            "short" | "int16" => Scalar::I16,
            "ushort" | "uint16" => Scalar::U16,
            "int" | "int32" => Scalar::I32,
            "uint" | "uint32" => Scalar::U32,
            "float" | "float32" => Scalar::F32,
            "double" | "float64" => Scalar::F64,
            _ => return None,
        })
    }

    fn size(self) -> usize {
        match self {
            Scalar::I8 | Scalar::U8 => 1,
            Scalar::I16 | Scalar::U16 => 2,
            Scalar::I32 | Scalar::U32 | Scalar::F32 => 4,
            Scalar::F64 => 8,
        }
    }
}

#[derive(Clone, Debug)]
enum Property {
    Scalar(String, Scalar),
    /// A list: the type of its count, the type of its items.
    List(String, Scalar, Scalar),
}

#[derive(Clone, Debug)]
struct Element {
    name: String,
    /// As the header claims it: never used to allocate.
    count: u64,
    properties: Vec<Property>,
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Format {
    Ascii,
    Little,
    Big,
}

/// Reads a PLY file's bytes.
pub fn read(bytes: &[u8]) -> Result<MeshData, MeshError> {
    let (format, elements, body, header_lines) = header(bytes)?;
    let mut mesh = MeshData::default();
    let text;
    let mut source = match format {
        Format::Ascii => {
            // A byte that is not UTF-8 becomes U+FFFD, which no number is: an error
            // on its own line.
            text = String::from_utf8_lossy(body);
            Source::Text(Lines::new(&text, header_lines))
        }
        Format::Little | Format::Big => Source::Binary {
            bytes: body,
            at: 0,
            big: format == Format::Big,
        },
    };
    let mut record = 0usize;
    // Where each face record's triangles start, with its record and line, so that an
    // index checked once every vertex is read names the face it came from.
    let mut faces: Vec<(usize, usize, usize, u64)> = Vec::new();
    for element in &elements {
        let role = Role::of(element);
        for index in 0..element.count {
            record += 1;
            let first = mesh.triangles.len();
            let values = match read_record(&mut source, element) {
                Ok(values) => values,
                Err(m) => {
                    let message =
                        format!("{} {} of {}: {m}", element.name, index + 1, element.count);
                    return Err(source_error(&source, record, message));
                }
            };
            role.take(&values, &mut mesh).map_err(|m| {
                source_error(
                    &source,
                    record,
                    format!("{} {}: {m}", element.name, index + 1),
                )
            })?;
            if mesh.triangles.len() > first {
                let line = match &source {
                    Source::Text(lines) => lines.line,
                    Source::Binary { .. } => 0,
                };
                faces.push((first, record, line, index + 1));
            }
        }
    }
    let vertices = mesh.positions.len();
    for (t, triangle) in mesh.triangles.iter().enumerate() {
        if let Some(&bad) = triangle.iter().find(|&&v| v as usize >= vertices) {
            let at = faces.partition_point(|f| f.0 <= t).saturating_sub(1);
            let (_, record, line, face) =
                faces
                    .get(at)
                    .copied()
                    .unwrap_or((0, t + 1, 0, t as u64 + 1));
            let message = format!(
                "face {face}: vertex index {bad} is out of range: the file has {vertices} vertices"
            );
            return Err(if line > 0 {
                MeshError::Line { line, message }
            } else {
                MeshError::Record { record, message }
            });
        }
    }
    Ok(mesh)
}

/// What the mesh takes from an element's records.
enum Role {
    Vertex {
        x: usize,
        y: usize,
        z: usize,
        normal: Option<[usize; 3]>,
    },
    Face {
        list: usize,
    },
    Skipped,
}

impl Role {
    fn of(element: &Element) -> Role {
        let find = |name: &str| {
            element
                .properties
                .iter()
                .position(|p| matches!(p, Property::Scalar(n, _) if n == name))
        };
        match element.name.as_str() {
            "vertex" => match (find("x"), find("y"), find("z")) {
                (Some(x), Some(y), Some(z)) => Role::Vertex {
                    x,
                    y,
                    z,
                    normal: match (find("nx"), find("ny"), find("nz")) {
                        (Some(a), Some(b), Some(c)) => Some([a, b, c]),
                        _ => None,
                    },
                },
                _ => Role::Skipped,
            },
            "face" => element
                .properties
                .iter()
                .position(|p| {
                    matches!(p, Property::List(n, _, _) if n == "vertex_indices" || n == "vertex_index")
                })
                .map_or(Role::Skipped, |list| Role::Face { list }),
            _ => Role::Skipped,
        }
    }

    fn take(&self, values: &[Value], mesh: &mut MeshData) -> Result<(), String> {
        match self {
            Role::Vertex { x, y, z, normal } => {
                let number = |i: usize| values[i].number();
                mesh.positions.push([number(*x)?, number(*y)?, number(*z)?]);
                if let Some([a, b, c]) = normal {
                    mesh.normals.push([number(*a)?, number(*b)?, number(*c)?]);
                }
                Ok(())
            }
            Role::Face { list } => {
                let Value::List(indices) = &values[*list] else {
                    unreachable!("a list property reads as a list");
                };
                if indices.len() < 3 {
                    return Err(format!(
                        "a face of {} vertices: a face has at least 3",
                        indices.len()
                    ));
                }
                let index = |v: f64| {
                    if v >= 0.0 && v <= f64::from(u32::MAX - 1) && v.fract() == 0.0 {
                        Ok(v as u32)
                    } else {
                        Err(format!("vertex index {v} is not one"))
                    }
                };
                let first = index(indices[0])?;
                for pair in indices[1..].windows(2) {
                    if mesh.triangles.len() >= MAX_MESH_TRIANGLES {
                        return Err(format!(
                            "more than the limit of {MAX_MESH_TRIANGLES} triangles"
                        ));
                    }
                    mesh.triangles
                        .push([first, index(pair[0])?, index(pair[1])?]);
                    // The corners' normals are the vertices' own, when the file has
                    // them: the same indices.
                    mesh.corner_normals.push(if mesh.normals.is_empty() {
                        [super::NO_NORMAL; 3]
                    } else {
                        [first, index(pair[0])?, index(pair[1])?]
                    });
                }
                Ok(())
            }
            Role::Skipped => Ok(()),
        }
    }
}

/// A property's value in a record.
enum Value {
    Number(f64),
    List(Vec<f64>),
}

impl Value {
    fn number(&self) -> Result<f64, String> {
        match self {
            Value::Number(v) => Ok(*v),
            Value::List(_) => Err("a list where a number is expected".into()),
        }
    }
}

/// Where the records come from.
enum Source<'a> {
    Text(Lines<'a>),
    Binary {
        bytes: &'a [u8],
        at: usize,
        big: bool,
    },
}

fn source_error(source: &Source<'_>, record: usize, message: String) -> MeshError {
    match source {
        Source::Text(lines) => MeshError::Line {
            line: lines.line,
            message,
        },
        Source::Binary { .. } => MeshError::Record { record, message },
    }
}

/// An ASCII body, one record a line.
struct Lines<'a> {
    lines: std::str::Lines<'a>,
    /// The line last read (1-based, counting the header's).
    line: usize,
}

impl<'a> Lines<'a> {
    fn new(text: &'a str, header_lines: usize) -> Lines<'a> {
        Lines {
            lines: text.lines(),
            line: header_lines,
        }
    }
}

fn read_record(source: &mut Source<'_>, element: &Element) -> Result<Vec<Value>, String> {
    match source {
        Source::Text(lines) => {
            let line = loop {
                lines.line += 1;
                match lines.lines.next() {
                    None => return Err("the file ends before it".into()),
                    Some(l) if l.trim().is_empty() => continue,
                    Some(l) => break l,
                }
            };
            let mut words = line.split_whitespace();
            let mut next = || -> Result<f64, String> {
                let word = words.next().ok_or("the line ends early")?;
                super::number(word)
            };
            element
                .properties
                .iter()
                .map(|p| match p {
                    Property::Scalar(..) => next().map(Value::Number),
                    Property::List(..) => {
                        let n = list_length(next()?)?;
                        // Grown as the items are read, not sized by the count.
                        let mut items = Vec::new();
                        for _ in 0..n {
                            items.push(next()?);
                        }
                        Ok(Value::List(items))
                    }
                })
                .collect()
        }
        Source::Binary { bytes, at, big } => {
            let mut scalar = |kind: Scalar| -> Result<f64, String> {
                let size = kind.size();
                let raw = bytes
                    .get(*at..*at + size)
                    .ok_or("the file ends before it")?;
                *at += size;
                let mut b = [0u8; 8];
                b[..size].copy_from_slice(raw);
                if *big {
                    b[..size].reverse();
                }
                let value = match kind {
                    Scalar::I8 => f64::from(b[0] as i8),
                    Scalar::U8 => f64::from(b[0]),
                    Scalar::I16 => f64::from(i16::from_le_bytes([b[0], b[1]])),
                    Scalar::U16 => f64::from(u16::from_le_bytes([b[0], b[1]])),
                    Scalar::I32 => f64::from(i32::from_le_bytes([b[0], b[1], b[2], b[3]])),
                    Scalar::U32 => f64::from(u32::from_le_bytes([b[0], b[1], b[2], b[3]])),
                    Scalar::F32 => f64::from(f32::from_le_bytes([b[0], b[1], b[2], b[3]])),
                    Scalar::F64 => f64::from_le_bytes(b),
                };
                if value.is_finite() {
                    Ok(value)
                } else {
                    Err(format!("{value} is not a finite number"))
                }
            };
            element
                .properties
                .iter()
                .map(|p| match *p {
                    Property::Scalar(_, kind) => scalar(kind).map(Value::Number),
                    Property::List(_, count, item) => {
                        let n = list_length(scalar(count)?)?;
                        // Grown as the items are read, not sized by the count: a
                        // count the file does not hold ends at its last byte.
                        let mut items = Vec::new();
                        for _ in 0..n {
                            items.push(scalar(item)?);
                        }
                        Ok(Value::List(items))
                    }
                })
                .collect()
        }
    }
}

/// A list's count as its length: a whole number, and no more items than a face within
/// the triangle limit has.
fn list_length(n: f64) -> Result<u64, String> {
    if n < 0.0 || n.fract() != 0.0 {
        return Err(format!("a list of {n} items"));
    }
    let longest = MAX_MESH_TRIANGLES as u64 + 2;
    if n > longest as f64 {
        return Err(format!(
            "a list of {n} items, more than the {longest} of a face within the limit of \
             {MAX_MESH_TRIANGLES} triangles"
        ));
    }
    Ok(n as u64)
}

/// What the header says: the format, the elements, the body's bytes, and how many
/// lines the header takes.
type Header<'a> = (Format, Vec<Element>, &'a [u8], usize);

/// Reads the header.
fn header(bytes: &[u8]) -> Result<Header<'_>, MeshError> {
    let mut format = None;
    let mut elements: Vec<Element> = Vec::new();
    let mut at = 0;
    let mut line_number = 0;
    loop {
        line_number += 1;
        let error = |message: String| MeshError::Line {
            line: line_number,
            message,
        };
        let Some(end) = bytes[at..].iter().position(|&b| b == b'\n') else {
            return Err(error("the header never ends (no `end_header`)".into()));
        };
        // Comments and unknown lines, which are ignored, may be in any encoding.
        let line = String::from_utf8_lossy(&bytes[at..at + end]);
        let line = line.trim_end_matches('\r');
        at += end + 1;
        let words: Vec<&str> = line.split_whitespace().collect();
        match words.as_slice() {
            ["ply"] if line_number == 1 => {}
            _ if line_number == 1 => return Err(error("not a PLY file (no `ply` line)".into())),
            ["format", kind, "1.0"] => {
                format = Some(match *kind {
                    "ascii" => Format::Ascii,
                    "binary_little_endian" => Format::Little,
                    "binary_big_endian" => Format::Big,
                    other => return Err(error(format!("unknown format {}", super::quoted(other)))),
                })
            }
            ["element", name, count] => elements.push(Element {
                name: (*name).to_owned(),
                count: count.parse().map_err(|_| {
                    error(format!(
                        "element count {} is not a number",
                        super::quoted(count)
                    ))
                })?,
                properties: Vec::new(),
            }),
            ["property", "list", count, item, name] => {
                let element = elements
                    .last_mut()
                    .ok_or_else(|| error("a property before any element".into()))?;
                let scalar = |t: &str| {
                    Scalar::parse(t)
                        .ok_or_else(|| error(format!("unknown type {}", super::quoted(t))))
                };
                element.properties.push(Property::List(
                    (*name).to_owned(),
                    scalar(count)?,
                    scalar(item)?,
                ));
            }
            ["property", kind, name] => {
                let element = elements
                    .last_mut()
                    .ok_or_else(|| error("a property before any element".into()))?;
                let kind = Scalar::parse(kind)
                    .ok_or_else(|| error(format!("unknown type {}", super::quoted(kind))))?;
                element
                    .properties
                    .push(Property::Scalar((*name).to_owned(), kind));
            }
            ["end_header"] => break,
            _ => {}
        }
    }
    let format = format.ok_or(MeshError::Line {
        line: line_number,
        message: "the header has no `format` line".into(),
    })?;
    Ok((format, elements, &bytes[at..], line_number))
}

#[cfg(test)]
mod tests {
    use super::*;

    const HEADER: &str = "element vertex 4\nproperty float x\nproperty float y\nproperty float z\n\
                          element face 1\nproperty list uchar int vertex_indices\nend_header\n";

    fn ascii() -> Vec<u8> {
        format!(
            "ply\nformat ascii 1.0\ncomment made by hand\n{HEADER}0.1 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 3\n"
        )
        .into_bytes()
    }

    fn binary(big: bool) -> Vec<u8> {
        let order = if big { "big" } else { "little" };
        let mut bytes = format!("ply\nformat binary_{order}_endian 1.0\n{HEADER}").into_bytes();
        let float = |v: f32| {
            if big {
                v.to_be_bytes()
            } else {
                v.to_le_bytes()
            }
        };
        let int = |v: i32| {
            if big {
                v.to_be_bytes()
            } else {
                v.to_le_bytes()
            }
        };
        for v in [
            [0.1f32, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [1.0, 1.0, 0.0],
            [0.0, 1.0, 0.0],
        ] {
            for x in v {
                bytes.extend_from_slice(&float(x));
            }
        }
        bytes.push(4);
        for i in 0..4 {
            bytes.extend_from_slice(&int(i));
        }
        bytes
    }

    #[test]
    fn ascii_numbers_are_doubles_whatever_the_header_declares() {
        let mesh = read(&ascii()).unwrap();
        // `property float`, yet 0.1 as the nearest double, not the nearest float.
        assert_eq!(mesh.positions[0], [0.1, 0.0, 0.0]);
        assert_eq!(mesh.triangles, vec![[0, 1, 2], [0, 2, 3]]);
    }

    #[test]
    fn both_byte_orders_read_alike() {
        let little = read(&binary(false)).unwrap();
        let big = read(&binary(true)).unwrap();
        assert_eq!(little, big);
        assert_eq!(little.positions[0][0], f64::from(0.1f32));
        assert_eq!(little.triangles, vec![[0, 1, 2], [0, 2, 3]]);
    }

    #[test]
    fn a_count_claimed_and_not_there_is_an_error_not_an_allocation() {
        let text = "ply\nformat binary_little_endian 1.0\nelement vertex 1000000000000\n\
                    property double x\nproperty double y\nproperty double z\nend_header\n";
        let error = read(text.as_bytes()).unwrap_err().to_string();
        assert_eq!(
            error,
            "record 1: vertex 1 of 1000000000000: the file ends before it"
        );
        let mut cut = ascii();
        cut.truncate(cut.len() - 12);
        let error = read(&cut).unwrap_err().to_string();
        assert_eq!(error, "line 14: vertex 4 of 4: the line ends early");
    }

    #[test]
    fn a_list_longer_than_the_file_ends_at_its_last_byte() {
        let mut bytes = b"ply\nformat binary_little_endian 1.0\nelement face 1\n\
                          property list uint int vertex_indices\nend_header\n"
            .to_vec();
        // Twenty million corners claimed (within the limit), one there.
        bytes.extend_from_slice(&20_000_000u32.to_le_bytes());
        bytes.extend_from_slice(&7i32.to_le_bytes());
        let error = read(&bytes).unwrap_err().to_string();
        assert_eq!(error, "record 1: face 1 of 1: the file ends before it");
    }

    #[test]
    fn a_list_longer_than_a_face_within_the_limit_is_not_read() {
        let mut bytes = b"ply\nformat binary_little_endian 1.0\nelement face 1\n\
                          property list uint uchar vertex_indices\nend_header\n"
            .to_vec();
        bytes.extend_from_slice(&u32::MAX.to_le_bytes());
        bytes.extend_from_slice(&[0; 4096]);
        let error = read(&bytes).unwrap_err().to_string();
        assert_eq!(
            error,
            format!(
                "record 1: face 1 of 1: a list of 4294967295 items, more than the {} of a \
                 face within the limit of {MAX_MESH_TRIANGLES} triangles",
                MAX_MESH_TRIANGLES + 2
            )
        );
    }

    #[test]
    fn bytes_that_are_not_utf8_matter_only_where_numbers_are() {
        // A Latin-1 comment is ignored like any comment.
        let mut bytes = b"ply\nformat ascii 1.0\ncomment caf\xe9\n".to_vec();
        bytes.extend_from_slice(&ascii()[b"ply\nformat ascii 1.0\n".len()..]);
        assert_eq!(read(&bytes).unwrap(), read(&ascii()).unwrap());
        // In a record, it is an error on the record's line.
        let mut body = ascii();
        let at = body.len() - 3;
        body[at] = 0xe9;
        let error = read(&body).unwrap_err().to_string();
        assert!(error.starts_with("line 15: face 1 of 1: "), "{error}");
    }

    #[test]
    fn mistakes_are_named() {
        let error = |text: &str| read(text.as_bytes()).unwrap_err().to_string();
        assert_eq!(error("obj\n"), "line 1: not a PLY file (no `ply` line)");
        assert_eq!(
            error("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nend_header\n0 nan 0\n"),
            "line 8: vertex 1 of 1: \"nan\" is not a finite number"
        );
        let bad_index =
            format!("ply\nformat ascii 1.0\n{HEADER}0 0 0\n1 0 0\n1 1 0\n0 1 0\n3 0 1 9\n");
        assert_eq!(
            error(&bad_index),
            "line 14: face 1: vertex index 9 is out of range: the file has 4 vertices"
        );
    }
}
