//! Writing a static scene back as a scene file, so that a frame of an animation (or any
//! scene built in code) can be saved, sent to a farm or compared with a file written
//! by hand.
//!
//! The text reads back as the very same scene, to the bit: vectors and colours are
//! written as strings, which the reader parses with the correctly rounded
//! `str::parse::<f64>`, and Rust's shortest round-trip formatting gives them back
//! exactly. A lone number (a radius, a distance, the ambient term) must be a JSON
//! number, which the reader takes from serde_json; its decimal reading is not always
//! correctly rounded, so each such number is written in the first of a few nearby
//! spellings that serde_json reads back to the same bits.

use std::fmt::Write as _;

use crate::scene::{CameraSpec, Material, Scene, Shape};
use crate::transform::TransformSpec;
use crate::vec3::Vec3;

/// A number that no spelling tried makes serde_json read back exactly. Every number a
/// scene file can hold has one; a number computed otherwise (an interpolated radius)
/// may not: serde_json reads a JSON number of 17 or more digits with two roundings,
/// which skip some doubles altogether.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[error("{0:e} cannot be written so that it reads back to the same bits")]
pub struct Unwritable(pub f64);

impl Scene {
    /// The scene as a scene file (one line of JSON) that [`crate::parse_scene`] reads
    /// back to a scene equal to this one, bit for bit. The sampling is not part of a
    /// scene file and is not written.
    ///
    /// Fails only for a lone number (radius, distance, ambient) that no JSON number
    /// reads back to exactly; vectors and colours are always written exactly.
    pub fn to_json(&self) -> Result<String, Unwritable> {
        let mut s = String::from("{\"lights\": [");
        for (i, light) in self.lights.iter().enumerate() {
            if i > 0 {
                s.push_str(", ");
            }
            let _ = write!(
                s,
                "{{\"position\": \"{}\", \"color\": \"{}\"}}",
                vector(light.position),
                vector(light.color)
            );
        }
        s.push_str("], \"objects\": [");
        for (i, object) in self.objects.iter().enumerate() {
            if i > 0 {
                s.push_str(", ");
            }
            match &object.shape {
                &Shape::Sphere { center, radius } => {
                    let _ = write!(
                        s,
                        "{{\"type\": \"sphere\", \"center\": \"{}\", \"radius\": {}, ",
                        vector(center),
                        json_number(radius)?
                    );
                }
                &Shape::Plane { normal, distance } => {
                    let _ = write!(
                        s,
                        "{{\"type\": \"plane\", \"normal\": \"{}\", \"distance\": {}, ",
                        vector(normal),
                        json_number(distance)?
                    );
                }
                Shape::Triangle { vertices } => {
                    let _ = write!(
                        s,
                        "{{\"type\": \"triangle\", \"vertices\": [\"{}\", \"{}\", \"{}\"], ",
                        vector(vertices[0]),
                        vector(vertices[1]),
                        vector(vertices[2])
                    );
                }
                Shape::Box { min, max } => {
                    let _ = write!(
                        s,
                        "{{\"type\": \"box\", \"min\": \"{}\", \"max\": \"{}\", ",
                        vector(*min),
                        vector(*max)
                    );
                }
                Shape::Mesh(mesh) => {
                    let name = serde_json::to_string(&mesh.file.name).unwrap_or_default();
                    let _ = write!(s, "{{\"type\": \"mesh\", \"file\": {name}, ");
                    match mesh.spec {
                        TransformSpec::Matrix(m) => {
                            let numbers: Vec<String> = m.iter().map(|x| format!("{x:?}")).collect();
                            let _ = write!(
                                s,
                                "\"transform\": {{\"matrix\": \"{}\"}}, ",
                                numbers.join(" ")
                            );
                        }
                        TransformSpec::Parts {
                            scale,
                            rotate,
                            translate,
                        } => {
                            let _ = write!(
                                s,
                                "\"transform\": {{\"scale\": \"{}\", \"rotate\": \"{}\", \"translate\": \"{}\"}}, ",
                                vector(scale),
                                vector(rotate),
                                vector(translate)
                            );
                        }
                    }
                    if mesh.smooth {
                        s.push_str("\"shading\": \"smooth\", ");
                    }
                }
            }
            let special = match object.material {
                Material::Matte => 0.0,
                Material::Reflective(x) => x,
                Material::Checker => 2.0,
            };
            let _ = write!(s, "\"color\": \"{} {special:?}\"}}", vector(object.color));
        }
        let settings = &self.settings;
        let mut camera_extra = String::new();
        if self.camera.up != CameraSpec::WORLD_UP {
            let _ = write!(camera_extra, ", \"up\": \"{}\"", vector(self.camera.up));
        }
        if let Some(fov) = self.camera.fov {
            let _ = write!(camera_extra, ", \"fov\": {}", json_number(fov)?);
        }
        let _ = write!(
            s,
            "], \"camera\": {{\"position\": \"{}\", \"look_at\": \"{}\"{camera_extra}}}, \
             \"image\": {{\"width\": {}, \"height\": {}, \"aa\": {}, \"max_depth\": {}}}, \
             \"ambient\": {}}}",
            vector(self.camera.position),
            vector(self.camera.look_at),
            settings.width,
            settings.height,
            settings.aa,
            settings.max_depth,
            json_number(self.ambient)?
        );
        Ok(s)
    }
}

/// `x y z`, each in Rust's shortest spelling that parses back to the same bits.
fn vector(v: Vec3) -> String {
    format!("{:?} {:?} {:?}", v.x, v.y, v.z)
}

/// A JSON number as the scene reader reads it.
fn read(text: &str) -> Option<f64> {
    serde_json::from_str::<serde_json::Value>(text)
        .ok()?
        .as_f64()
}

/// A JSON number that serde_json reads as exactly `x`: the shortest spelling if it
/// does, else a 17- to 19-digit one, nudged by a few units in its last digit.
fn json_number(x: f64) -> Result<String, Unwritable> {
    // Read the way the scene reader reads it: a `Value`, then `as_f64`.
    let reads_back = |text: &str| read(text).map(f64::to_bits) == Some(x.to_bits());
    let shortest = format!("{x:?}");
    if reads_back(&shortest) && shortest.bytes().all(|b| b != b'i' && b != b'N') {
        return Ok(shortest);
    }
    if !x.is_finite() {
        return Err(Unwritable(x));
    }
    // d.ddd…e±N with 17 to 19 significant digits: the significand m as an integer,
    // then m and its neighbours m ± 1, m ± 2, … (serde_json may read m a unit or two
    // off, and reads a longer significand more closely).
    for precision in 16..=18usize {
        let exact = format!("{x:.precision$e}");
        let (mantissa, exponent) = exact.split_once('e').ok_or(Unwritable(x))?;
        let sign = if mantissa.starts_with('-') { "-" } else { "" };
        let digits: i64 = mantissa
            .trim_start_matches('-')
            .replace('.', "")
            .parse()
            .map_err(|_| Unwritable(x))?;
        let exponent: i64 = exponent.parse().map_err(|_| Unwritable(x))?;
        let exponent = exponent - precision as i64;
        for step in 0..=64i64 {
            for m in [digits + step, digits - step] {
                let text = format!("{sign}{m}e{exponent}");
                if reads_back(&text) {
                    return Ok(text);
                }
            }
        }
    }
    Err(Unwritable(x))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_number_a_file_can_hold_is_written_so_that_it_reads_back_exactly() {
        // Numbers as the reader reads them from 17-digit spellings about 1e-30 to 1e30
        // in size, either sign, from a fixed pseudo-random walk.
        let mut state = 0x9e37_79b9_7f4a_7c15u64;
        for _ in 0..20_000 {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            let digits = 10_000_000_000_000_000 + state % 90_000_000_000_000_000;
            let exponent = (state >> 57) as i64 - 64 + 14;
            let sign = if state & 1 == 1 { "-" } else { "" };
            let x = read(&format!("{sign}{digits}e{exponent}")).unwrap();
            let text = json_number(x).unwrap();
            assert_eq!(read(&text).unwrap().to_bits(), x.to_bits(), "{text}");
        }
        for x in [0.0, -0.0, 1.0, 0.1, 0.7071067811865475, 1e-300, 5e-324] {
            let text = json_number(x).unwrap();
            assert_eq!(read(&text).unwrap().to_bits(), x.to_bits(), "{text}");
        }
    }

    #[test]
    fn a_scene_written_reads_back_equal() {
        for text in [
            include_str!("../../scenes/seed.json"),
            include_str!("../../scenes/hall-of-mirrors.json"),
            include_str!("../../scenes/lights.json"),
            include_str!("../../scenes/reflections.json"),
            include_str!("../../scenes/tilted.json"),
        ] {
            let scene = crate::parse_scene(text).unwrap();
            let written = scene.to_json().unwrap();
            let again = crate::parse_scene(&written).unwrap();
            assert_eq!(format!("{again:?}"), format!("{scene:?}"), "{written}");
        }
    }
}
