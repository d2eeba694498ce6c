//! Reading a scene file: JSON syntax, then every key checked by hand so that each error
//! names the exact place (`objects[2].radius`) and what is wrong with it.
//!
//! The JSON is first read into a `serde_json::Value`; a typed serde derive cannot say
//! "`objects[1].color`: special must be 0, in (0, 1] or 2" with the object's index, and
//! the format has two spellings for vectors (a string or an array), so the walk is
//! explicit.

use serde_json::{Map, Value};

use crate::error::SceneError;
use crate::limits::{MAX_AA, MAX_DEPTH, MAX_SIDE};
use crate::sampling::{Sampling, MAX_TARGET_MILLI, MIN_TARGET_MILLI};
use crate::scene::{CameraSpec, Light, Material, Object, RenderSettings, Scene, Shape};
use crate::vec3::Vec3;

type Result<T> = std::result::Result<T, SceneError>;

/// Parses and validates a scene file's text.
///
/// Every error of the scene format is reported here, before any rendering: syntax
/// errors with line and column, everything else with the path of the offending value.
pub fn parse_scene(text: &str) -> Result<Scene> {
    let root: Value = serde_json::from_str(text).map_err(|e| SceneError::Syntax {
        message: syntax_message(&e),
        line: e.line(),
        column: e.column(),
    })?;
    let root = as_object(&root, "scene")?;
    check_keys(
        root,
        "",
        &["lights", "objects", "camera", "image", "ambient"],
    )?;

    let lights = required_array(root, "", "lights")?
        .iter()
        .enumerate()
        .map(|(i, v)| parse_light(v, &format!("lights[{i}]")))
        .collect::<Result<Vec<_>>>()?;
    let objects = required_array(root, "", "objects")?
        .iter()
        .enumerate()
        .map(|(i, v)| parse_object(v, &format!("objects[{i}]")))
        .collect::<Result<Vec<_>>>()?;
    let camera = match root.get("camera") {
        Some(v) => parse_camera(v, "camera")?,
        None => CameraSpec::default(),
    };
    let settings = match root.get("image") {
        Some(v) => parse_image(v, "image")?,
        None => RenderSettings::default(),
    };
    let ambient = match root.get("ambient") {
        Some(v) => {
            let a = number(v, "ambient")?;
            if a < 0.0 {
                return Err(SceneError::invalid(
                    "ambient",
                    format!("must be >= 0, got {a}"),
                ));
            }
            a
        }
        None => 0.2,
    };
    Ok(Scene {
        lights,
        objects,
        camera,
        settings,
        ambient,
    })
}

/// serde_json appends " at line L column C" to its messages; we report those separately.
fn syntax_message(e: &serde_json::Error) -> String {
    let full = e.to_string();
    match full.rfind(" at line ") {
        Some(i) => full[..i].to_string(),
        None => full,
    }
}

/// Checks image settings (from the file or from a caller's overrides) against the
/// format's rules and Tessera's limits. `prefix` names where they came from.
pub fn validate_settings(s: &RenderSettings, prefix: &str) -> Result<()> {
    let key = |k: &str| join(prefix, k);
    for (name, value) in [("width", s.width), ("height", s.height)] {
        if value == 0 || value > MAX_SIDE {
            return Err(SceneError::invalid(
                key(name),
                format!("must be between 1 and {MAX_SIDE}, got {value}"),
            ));
        }
    }
    if s.aa == 0 || s.aa > MAX_AA {
        return Err(SceneError::invalid(
            key("aa"),
            format!("must be between 1 and {MAX_AA}, got {}", s.aa),
        ));
    }
    if s.max_depth > MAX_DEPTH {
        return Err(SceneError::invalid(
            key("max_depth"),
            format!("must be between 0 and {MAX_DEPTH}, got {}", s.max_depth),
        ));
    }
    if let Sampling::Adaptive { target_milli } = s.sampling {
        if !(MIN_TARGET_MILLI..=MAX_TARGET_MILLI).contains(&target_milli) {
            return Err(SceneError::invalid(
                key("target_error"),
                format!(
                    "must be between 0.001 and 255 levels, got {}",
                    f64::from(target_milli) / 1000.0
                ),
            ));
        }
    }
    Ok(())
}

/// `prefix.key`, with a key that is not a plain word quoted and escaped, so that an
/// error naming it stays on one line: `objects[0]."ce\nter"`.
fn join(prefix: &str, key: &str) -> String {
    let plain = !key.is_empty() && key.chars().all(|c| c.is_ascii_alphanumeric() || c == '_');
    let key = if plain {
        key.to_string()
    } else {
        format!("{key:?}")
    };
    if prefix.is_empty() {
        key
    } else {
        format!("{prefix}.{key}")
    }
}

fn type_name(v: &Value) -> &'static str {
    match v {
        Value::Null => "null",
        Value::Bool(_) => "a boolean",
        Value::Number(_) => "a number",
        Value::String(_) => "a string",
        Value::Array(_) => "an array",
        Value::Object(_) => "an object",
    }
}

fn as_object<'a>(v: &'a Value, path: &str) -> Result<&'a Map<String, Value>> {
    v.as_object().ok_or_else(|| {
        SceneError::invalid(path, format!("expected an object, got {}", type_name(v)))
    })
}

fn check_keys(obj: &Map<String, Value>, path: &str, allowed: &[&str]) -> Result<()> {
    match obj.keys().find(|k| !allowed.contains(&k.as_str())) {
        Some(k) => Err(SceneError::invalid(
            join(path, k),
            format!("unknown key (expected one of: {})", allowed.join(", ")),
        )),
        None => Ok(()),
    }
}

fn required<'a>(obj: &'a Map<String, Value>, path: &str, key: &str) -> Result<&'a Value> {
    obj.get(key).ok_or_else(|| {
        let place = if path.is_empty() { "scene" } else { path };
        SceneError::invalid(place, format!("missing key \"{key}\""))
    })
}

fn required_array<'a>(
    obj: &'a Map<String, Value>,
    path: &str,
    key: &str,
) -> Result<&'a Vec<Value>> {
    let v = required(obj, path, key)?;
    v.as_array().ok_or_else(|| {
        SceneError::invalid(
            join(path, key),
            format!("expected an array, got {}", type_name(v)),
        )
    })
}

fn finite(x: f64, path: &str) -> Result<f64> {
    if x.is_finite() {
        Ok(x)
    } else {
        Err(SceneError::invalid(
            path,
            format!("must be a finite number, got {x}"),
        ))
    }
}

fn number(v: &Value, path: &str) -> Result<f64> {
    match v.as_f64() {
        Some(x) => finite(x, path),
        None => Err(SceneError::invalid(
            path,
            format!("expected a number, got {}", type_name(v)),
        )),
    }
}

fn whole_number(v: &Value, path: &str) -> Result<u32> {
    match v.as_u64() {
        Some(n) => Ok(u32::try_from(n).unwrap_or(u32::MAX)),
        None => Err(SceneError::invalid(
            path,
            format!("expected a whole number >= 0, got {v}"),
        )),
    }
}

/// A list of numbers written either as a whitespace-separated string (the seed's way,
/// `" 7.0 10.0 10.0"`) or as a JSON array.
fn number_list(v: &Value, path: &str, what: &str) -> Result<Vec<f64>> {
    let values = match v {
        Value::String(s) => s
            .split_whitespace()
            .map(|word| {
                word.parse::<f64>().map_err(|_| {
                    SceneError::invalid(path, format!("expected {what}, {word:?} is not a number"))
                })
            })
            .collect::<Result<Vec<_>>>()?,
        Value::Array(items) => items
            .iter()
            .map(|item| {
                item.as_f64().ok_or_else(|| {
                    SceneError::invalid(
                        path,
                        format!("expected {what}, found {} in the array", type_name(item)),
                    )
                })
            })
            .collect::<Result<Vec<_>>>()?,
        other => {
            return Err(SceneError::invalid(
                path,
                format!(
                    "expected {what} as a string or an array, got {}",
                    type_name(other)
                ),
            ))
        }
    };
    for &x in &values {
        finite(x, path)?;
    }
    Ok(values)
}

fn vec3(v: &Value, path: &str) -> Result<Vec3> {
    let n = number_list(v, path, "3 numbers")?;
    match n[..] {
        [x, y, z] => Ok(Vec3::new(x, y, z)),
        _ => Err(SceneError::invalid(
            path,
            format!("expected 3 numbers, got {}", n.len()),
        )),
    }
}

/// Reads `r g b special` (or `r g b` where `allow_three`), checking r, g, b ≥ 0.
fn color(v: &Value, path: &str, allow_three: bool) -> Result<(Vec3, f64)> {
    let what = if allow_three {
        "3 or 4 numbers"
    } else {
        "4 numbers (r g b special)"
    };
    let n = number_list(v, path, what)?;
    let (rgb, special) = match (&n[..], allow_three) {
        (&[r, g, b, s], _) => ([r, g, b], s),
        (&[r, g, b], true) => ([r, g, b], 0.0),
        _ => {
            return Err(SceneError::invalid(
                path,
                format!("expected {what}, got {}", n.len()),
            ))
        }
    };
    if let Some(c) = rgb.iter().find(|c| **c < 0.0) {
        return Err(SceneError::invalid(
            path,
            format!("r, g and b must be >= 0, got {c}"),
        ));
    }
    Ok((Vec3::new(rgb[0], rgb[1], rgb[2]), special))
}

fn material(special: f64, path: &str) -> Result<Material> {
    if special == 0.0 {
        Ok(Material::Matte)
    } else if special > 0.0 && special <= 1.0 {
        Ok(Material::Reflective(special))
    } else if special == 2.0 {
        Ok(Material::Checker)
    } else {
        Err(SceneError::invalid(
            path,
            format!("special (4th number) must be 0, in (0, 1] or 2, got {special}"),
        ))
    }
}

fn parse_light(v: &Value, path: &str) -> Result<Light> {
    let obj = as_object(v, path)?;
    check_keys(obj, path, &["position", "color"])?;
    let position = vec3(required(obj, path, "position")?, &join(path, "position"))?;
    let (color, _ignored) = color(required(obj, path, "color")?, &join(path, "color"), true)?;
    Ok(Light { position, color })
}

fn parse_object(v: &Value, path: &str) -> Result<Object> {
    let obj = as_object(v, path)?;
    let type_path = join(path, "type");
    let kind = match required(obj, path, "type")? {
        Value::String(s) => s.as_str(),
        other => {
            return Err(SceneError::invalid(
                type_path,
                format!("expected a string, got {}", type_name(other)),
            ))
        }
    };
    let shape = match kind {
        "sphere" => {
            check_keys(obj, path, &["type", "center", "radius", "color"])?;
            let center = vec3(required(obj, path, "center")?, &join(path, "center"))?;
            let radius_path = join(path, "radius");
            let radius = number(required(obj, path, "radius")?, &radius_path)?;
            if radius <= 0.0 {
                return Err(SceneError::invalid(
                    radius_path,
                    format!("must be > 0, got {radius}"),
                ));
            }
            Shape::Sphere { center, radius }
        }
        "plan" | "plane" => {
            check_keys(obj, path, &["type", "normal", "distance", "color"])?;
            let normal_path = join(path, "normal");
            let normal = vec3(required(obj, path, "normal")?, &normal_path)?;
            let len = normal.length();
            if len == 0.0 || !len.is_finite() {
                return Err(SceneError::invalid(
                    normal_path,
                    "must be a non-zero vector of finite length",
                ));
            }
            let distance = number(required(obj, path, "distance")?, &join(path, "distance"))?;
            Shape::Plane { normal, distance }
        }
        other => {
            return Err(SceneError::invalid(
                type_path,
                format!(
                    "unknown object type {other:?} (expected \"sphere\", \"plan\" or \"plane\")"
                ),
            ))
        }
    };
    let color_path = join(path, "color");
    let (color, special) = color(required(obj, path, "color")?, &color_path, false)?;
    let material = material(special, &color_path)?;
    Ok(Object {
        shape,
        color,
        material,
    })
}

fn parse_camera(v: &Value, path: &str) -> Result<CameraSpec> {
    let obj = as_object(v, path)?;
    check_keys(obj, path, &["position", "look_at"])?;
    let default = CameraSpec::default();
    let position = match obj.get("position") {
        Some(v) => vec3(v, &join(path, "position"))?,
        None => default.position,
    };
    let look_at = match obj.get("look_at") {
        Some(v) => vec3(v, &join(path, "look_at"))?,
        None => default.look_at,
    };
    let forward = look_at - position;
    if forward == Vec3::ZERO {
        return Err(SceneError::invalid(
            join(path, "look_at"),
            "must differ from camera.position",
        ));
    }
    if !forward.is_finite() || !forward.length().is_normal() {
        return Err(SceneError::invalid(
            join(path, "look_at"),
            "is too far from or too close to camera.position to define a direction",
        ));
    }
    // The right axis is up × forward = (f.z, 0, -f.x): it vanishes (or underflows) when
    // the camera looks straight up or down.
    let f = forward.normalize();
    if !Vec3::new(f.z, 0.0, -f.x).length().is_normal() {
        return Err(SceneError::invalid(
            path,
            "the viewing direction (look_at - position) is parallel to the world up axis (0 1 0)",
        ));
    }
    Ok(CameraSpec { position, look_at })
}

fn parse_image(v: &Value, path: &str) -> Result<RenderSettings> {
    let obj = as_object(v, path)?;
    check_keys(obj, path, &["width", "height", "aa", "max_depth"])?;
    let mut s = RenderSettings::default();
    for (key, slot) in [
        ("width", &mut s.width),
        ("height", &mut s.height),
        ("aa", &mut s.aa),
        ("max_depth", &mut s.max_depth),
    ] {
        if let Some(v) = obj.get(key) {
            *slot = whole_number(v, &join(path, key))?;
        }
    }
    validate_settings(&s, path)?;
    Ok(s)
}

#[cfg(test)]
mod tests {
    use super::*;

    const SEED: &str = include_str!("../../scenes/seed.json");

    fn error_of(text: &str) -> String {
        parse_scene(text).unwrap_err().to_string()
    }

    /// A minimal valid scene with one object replaced.
    fn with_object(object: &str) -> String {
        format!(r#"{{"lights": [], "objects": [{object}]}}"#)
    }

    #[test]
    fn the_seed_scene_loads_with_its_values_and_the_defaults() {
        let s = parse_scene(SEED).unwrap();
        assert_eq!(s.lights.len(), 2);
        assert_eq!(s.lights[1].position, Vec3::new(7.0, 10.0, 10.0));
        assert_eq!(s.objects.len(), 3);
        assert_eq!(
            s.objects[0].shape,
            Shape::Sphere {
                center: Vec3::ZERO,
                radius: 1.0
            }
        );
        assert_eq!(s.objects[1].material, Material::Reflective(0.6));
        assert_eq!(s.objects[2].material, Material::Checker);
        assert_eq!(
            s.objects[2].shape,
            Shape::Plane {
                normal: Vec3::new(0.0, 1.0, 0.0),
                distance: -1.0
            }
        );
        assert_eq!(s.camera, CameraSpec::default());
        assert_eq!(s.settings, RenderSettings::default());
        assert_eq!(s.ambient, 0.2);
    }

    #[test]
    fn vectors_and_colours_may_be_arrays_and_planes_plane() {
        let s = parse_scene(
            r#"{"lights": [{"position": [1, 2, 3], "color": [1, 0.5, 0]}],
                "objects": [{"type": "plane", "normal": [0, 2, 0], "distance": 1,
                             "color": [1, 1, 1, 0]}],
                "camera": {"look_at": "0 0 1"},
                "image": {"width": 32, "aa": 3},
                "ambient": 0.5}"#,
        )
        .unwrap();
        assert_eq!(s.lights[0].color, Vec3::new(1.0, 0.5, 0.0));
        assert_eq!(s.objects[0].material, Material::Matte);
        assert_eq!(s.camera.position, CameraSpec::default().position);
        assert_eq!(s.camera.look_at, Vec3::new(0.0, 0.0, 1.0));
        assert_eq!(
            (s.settings.width, s.settings.height, s.settings.aa),
            (32, 400, 3)
        );
        assert_eq!(s.ambient, 0.5);
    }

    #[test]
    fn errors_name_the_place_and_the_problem() {
        let sphere = |radius: &str| {
            with_object(&format!(
                r#"{{"type": "sphere", "center": "0 0 0", "radius": {radius}, "color": "1 1 1 0"}}"#
            ))
        };
        assert_eq!(
            error_of(&sphere("-1")),
            "objects[0].radius: must be > 0, got -1"
        );
        assert_eq!(
            error_of(&sphere("0")),
            "objects[0].radius: must be > 0, got 0"
        );
        assert_eq!(
            error_of(&sphere("\"big\"")),
            "objects[0].radius: expected a number, got a string"
        );
        assert_eq!(
            error_of(&with_object(
                r#"{"type": "sphere", "center": "0 0 0", "radius": 1, "color": "1 1 1 1.5"}"#
            )),
            "objects[0].color: special (4th number) must be 0, in (0, 1] or 2, got 1.5"
        );
        assert_eq!(
            error_of(&with_object(r#"{"type": "cube"}"#)),
            "objects[0].type: unknown object type \"cube\" (expected \"sphere\", \"plan\" or \"plane\")"
        );
        assert_eq!(
            error_of(&with_object(
                r#"{"type": "plan", "normal": "0 0 0", "distance": 1, "color": "1 1 1 0"}"#
            )),
            "objects[0].normal: must be a non-zero vector of finite length"
        );
        assert_eq!(
            error_of(&with_object(
                r#"{"type": "sphere", "center": "0 0 inf", "radius": 1, "color": "1 1 1 0"}"#
            )),
            "objects[0].center: must be a finite number, got inf"
        );
        assert_eq!(
            error_of(&with_object(
                r#"{"type": "sphere", "center": "0 0", "radius": 1, "color": "1 1 1 0"}"#
            )),
            "objects[0].center: expected 3 numbers, got 2"
        );
        assert_eq!(
            error_of(&with_object(r#"{"type": "sphere", "centre": "0 0 0"}"#)),
            "objects[0].centre: unknown key (expected one of: type, center, radius, color)"
        );
        assert_eq!(
            error_of(r#"{"lights": []}"#),
            "scene: missing key \"objects\""
        );
        assert_eq!(
            error_of(r#"{"lights": [], "objects": [], "image": {"width": 0}}"#),
            "image.width: must be between 1 and 16384, got 0"
        );
        assert_eq!(
            error_of(r#"{"lights": [], "objects": [], "camera": {"position": "0 5 0"}}"#),
            "camera: the viewing direction (look_at - position) is parallel to the world up axis (0 1 0)"
        );
        assert_eq!(
            error_of("{\"lights\": [],\n \"objects\": [}"),
            "not valid JSON: expected value at line 2, column 14"
        );
    }

    #[test]
    fn overrides_are_checked_against_the_limits() {
        let ok = RenderSettings::default();
        assert!(validate_settings(&ok, "").is_ok());
        let too_wide = RenderSettings {
            width: MAX_SIDE + 1,
            ..ok
        };
        assert_eq!(
            validate_settings(&too_wide, "").unwrap_err().to_string(),
            format!(
                "width: must be between 1 and {MAX_SIDE}, got {}",
                MAX_SIDE + 1
            )
        );
        let no_aa = RenderSettings { aa: 0, ..ok };
        assert!(validate_settings(&no_aa, "image")
            .unwrap_err()
            .to_string()
            .starts_with("image.aa:"));
    }
}
