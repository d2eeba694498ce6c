//! Reading a scene file: JSON syntax, then every key checked by hand so that each error
//! names the exact place (`objects[2].radius`) and what is wrong with it.
//!
//! The reference reading ([`parse_reference`]) first reads the JSON into a
//! `serde_json::Value`; a typed serde derive cannot say
//! "`objects[1].color`: special must be 0, in (0, 1] or 2" with the object's index, and
//! the format has two spellings for vectors (a string or an array), so the walk is
//! explicit. A `Value` tree of a million objects is slow to build and several times the
//! size of the text, so a valid scene is read by [`fast`] instead, without the tree and
//! with the objects in parallel; the fast reading gives up on anything unusual, and then
//! the reference reads the text again and words the error. Both give the same scene.

mod animation;
mod fast;

pub use animation::MAX_TRACKS;

use serde_json::{Map, Value};

use crate::animation::AnimatedScene;
use crate::error::SceneError;
use crate::limits::{MAX_AA, MAX_DEPTH, MAX_SIDE};
use crate::mesh::MeshFiles;
use crate::scene::{CameraSpec, Light, Material, MeshObject, Object, Scene, Shape};
use crate::settings::{RenderSettings, Sampling, MAX_TARGET_MILLI, MIN_TARGET_MILLI};
use crate::transform::TransformSpec;
use crate::trig::fov_scale;
use crate::vec3::Vec3;

type Result<T> = std::result::Result<T, SceneError>;

/// Parses and validates a scene file's text.
///
/// Every error of the scene format is reported here, before any rendering: syntax
/// errors with line and column, everything else with the path of the offending value.
///
/// The objects are converted in parallel on the current rayon pool.
///
/// An animated scene gives its frame 1 (see [`parse_animated`] for the others).
pub fn parse_scene(text: &str) -> Result<Scene> {
    parse_animated(text).map(AnimatedScene::into_first_frame)
}

/// Parses and validates a scene file's text with its animation, if it has one.
///
/// A scene without an `"animation"` key is read the fast way when it can be, as by
/// [`parse_scene`]; the fast reading leaves the `"animation"` key (like every key it
/// does not know) to the reference reading.
///
/// A scene given as text alone cannot name mesh files: a `mesh` object is refused in one
/// line (see [`parse_animated_with`]).
pub fn parse_animated(text: &str) -> Result<AnimatedScene> {
    parse_animated_with(text, &MeshFiles::none())
}

/// [`parse_animated`] for a scene whose mesh files come from `files` (the scene file's
/// directory): each file is read once, and files of the same bytes share their
/// geometry.
pub fn parse_animated_with(text: &str, files: &MeshFiles) -> Result<AnimatedScene> {
    match fast::parse(text) {
        Some(base) => Ok(AnimatedScene {
            base,
            animation: None,
        }),
        None => parse_reference_animated(text, files),
    }
}

/// [`parse_scene`] with the mesh files of `files`.
pub fn parse_scene_with(text: &str, files: &MeshFiles) -> Result<Scene> {
    parse_animated_with(text, files).map(AnimatedScene::into_first_frame)
}

/// The reference reading of a scene as [`parse_scene`] gives it: frame 1 of an animated
/// scene. [`fast::parse`] must agree with it on every scene it accepts.
#[cfg(test)]
fn parse_reference(text: &str) -> Result<Scene> {
    parse_reference_animated(text, &MeshFiles::none()).map(AnimatedScene::into_first_frame)
}

/// The reference reading: every check in a fixed order, so that among several errors
/// the same one is always reported. The animation, if any, is read last: it names the
/// scene's objects and lights.
fn parse_reference_animated(text: &str, files: &MeshFiles) -> Result<AnimatedScene> {
    let root: Value = serde_json::from_str(text).map_err(|e| SceneError::Syntax {
        message: syntax_message(&e),
        line: e.line(),
        column: e.column(),
    })?;
    let root = as_object(&root, "scene")?;
    check_keys(
        root,
        "",
        &[
            "lights",
            "objects",
            "camera",
            "image",
            "ambient",
            "animation",
        ],
    )?;

    let lights = required_array(root, "", "lights")?
        .iter()
        .enumerate()
        .map(|(i, v)| parse_light(v, &format!("lights[{i}]")))
        .collect::<Result<Vec<_>>>()?;
    let objects = required_array(root, "", "objects")?
        .iter()
        .enumerate()
        .map(|(i, v)| parse_object(v, &format!("objects[{i}]"), files))
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
    let base = Scene {
        lights,
        objects,
        camera,
        settings,
        ambient,
    };
    let animation = match root.get("animation") {
        Some(v) => Some(animation::parse(v, &base)?),
        None => None,
    };
    Ok(AnimatedScene { base, animation })
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

fn parse_object(v: &Value, path: &str, files: &MeshFiles) -> Result<Object> {
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
        "triangle" => {
            check_keys(obj, path, &["type", "vertices", "color"])?;
            let vertices_path = join(path, "vertices");
            let list = required(obj, path, "vertices")?;
            let items = match list.as_array() {
                Some(items) if items.len() == 3 => items,
                _ => {
                    return Err(SceneError::invalid(
                        vertices_path,
                        format!("expected an array of 3 vectors, got {}", describe(list)),
                    ))
                }
            };
            let mut vertices = [Vec3::ZERO; 3];
            for (k, item) in items.iter().enumerate() {
                vertices[k] = vec3(item, &format!("{vertices_path}[{k}]"))?;
            }
            Shape::Triangle { vertices }
        }
        "box" => {
            check_keys(obj, path, &["type", "min", "max", "color"])?;
            let min = vec3(required(obj, path, "min")?, &join(path, "min"))?;
            let max_path = join(path, "max");
            let max = vec3(required(obj, path, "max")?, &max_path)?;
            if !(min.x < max.x && min.y < max.y && min.z < max.z) {
                return Err(SceneError::invalid(
                    max_path,
                    format!(
                        "must exceed min on every axis, got min {} {} {} and max {} {} {}",
                        min.x, min.y, min.z, max.x, max.y, max.z
                    ),
                ));
            }
            Shape::Box { min, max }
        }
        "mesh" => {
            check_keys(
                obj,
                path,
                &["type", "file", "color", "transform", "shading"],
            )?;
            let file_path = join(path, "file");
            let name = match required(obj, path, "file")? {
                Value::String(s) if !s.is_empty() => s.as_str(),
                other => {
                    return Err(SceneError::invalid(
                        file_path,
                        format!("expected a file name, got {}", describe(other)),
                    ))
                }
            };
            let smooth = match obj.get("shading") {
                None => false,
                Some(Value::String(s)) if s == "flat" => false,
                Some(Value::String(s)) if s == "smooth" => true,
                Some(other) => {
                    return Err(SceneError::invalid(
                        join(path, "shading"),
                        format!("expected \"flat\" or \"smooth\", got {other}"),
                    ))
                }
            };
            let transform_path = join(path, "transform");
            let spec = match obj.get("transform") {
                Some(v) => parse_transform(v, &transform_path)?,
                None => TransformSpec::IDENTITY,
            };
            let transform = spec
                .affine()
                .map_err(|m| SceneError::invalid(&transform_path, m))?;
            let file = files
                .get(name)
                .map_err(|m| SceneError::invalid(&file_path, m))?;
            Shape::Mesh(MeshObject {
                file,
                spec,
                transform,
                smooth,
            })
        }
        other => {
            return Err(SceneError::invalid(
                type_path,
                format!(
                    "unknown object type {other:?} (expected \"sphere\", \"plane\", \"triangle\", \"box\" or \"mesh\")"
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

/// A mesh's `transform`: `scale`, `rotate`, `translate`, or `matrix` alone.
pub(crate) fn parse_transform(v: &Value, path: &str) -> Result<TransformSpec> {
    let obj = as_object(v, path)?;
    check_keys(obj, path, &["scale", "rotate", "translate", "matrix"])?;
    if let Some(m) = obj.get("matrix") {
        if let Some(other) = ["scale", "rotate", "translate"]
            .into_iter()
            .find(|k| obj.contains_key(*k))
        {
            return Err(SceneError::invalid(
                join(path, other),
                "cannot be combined with matrix",
            ));
        }
        return Ok(TransformSpec::Matrix(matrix(m, &join(path, "matrix"))?));
    }
    let scale = match obj.get("scale") {
        None => Vec3::new(1.0, 1.0, 1.0),
        Some(v @ Value::Number(_)) => {
            let s = number(v, &join(path, "scale"))?;
            Vec3::new(s, s, s)
        }
        Some(v) => vec3(v, &join(path, "scale"))?,
    };
    let rotate = match obj.get("rotate") {
        None => Vec3::ZERO,
        Some(v) => vec3(v, &join(path, "rotate"))?,
    };
    let translate = match obj.get("translate") {
        None => Vec3::ZERO,
        Some(v) => vec3(v, &join(path, "translate"))?,
    };
    Ok(TransformSpec::Parts {
        scale,
        rotate,
        translate,
    })
}

/// A transform's `matrix`: 12 numbers, as a string or an array.
fn matrix(v: &Value, path: &str) -> Result<[f64; 12]> {
    let n = number_list(v, path, "12 numbers (a 3 x 4 matrix, row by row)")?;
    n.as_slice().try_into().map_err(|_| {
        SceneError::invalid(
            path,
            format!(
                "expected 12 numbers (a 3 x 4 matrix, row by row), got {}",
                n.len()
            ),
        )
    })
}

/// A value as an error message names it: strings and short values in full.
fn describe(v: &Value) -> String {
    match v {
        Value::Array(items) => format!("an array of {}", items.len()),
        Value::String(s) if s.is_empty() => "an empty string".into(),
        other => type_name(other).into(),
    }
}

fn parse_camera(v: &Value, path: &str) -> Result<CameraSpec> {
    let obj = as_object(v, path)?;
    check_keys(obj, path, &["position", "look_at", "fov", "up"])?;
    let default = CameraSpec::default();
    let position = match obj.get("position") {
        Some(v) => vec3(v, &join(path, "position"))?,
        None => default.position,
    };
    let look_at = match obj.get("look_at") {
        Some(v) => vec3(v, &join(path, "look_at"))?,
        None => default.look_at,
    };
    let up = match obj.get("up") {
        Some(v) => vec3(v, &join(path, "up"))?,
        None => default.up,
    };
    let fov = match obj.get("fov") {
        Some(v) => {
            let fov_path = join(path, "fov");
            let fov = number(v, &fov_path)?;
            if let Some(problem) = fov_problem(fov) {
                return Err(SceneError::invalid(fov_path, problem));
            }
            Some(fov)
        }
        None => None,
    };
    let camera = CameraSpec {
        position,
        look_at,
        up,
        fov,
    };
    match camera_problem(&camera) {
        None => {}
        Some(CameraProblem::Vertical) => {
            let place = if obj.contains_key("up") {
                join(path, "up")
            } else {
                path.to_string()
            };
            return Err(SceneError::invalid(place, vertical_message(up)));
        }
        Some(problem) => {
            return Err(SceneError::invalid(
                join(path, "look_at"),
                problem.message(),
            ))
        }
    }
    Ok(camera)
}

/// Why a field of view is not one, if it is not: 0 < fov < 180 with a finite, non-zero
/// image plane.
pub(crate) fn fov_problem(fov: f64) -> Option<String> {
    let k = fov_scale(fov);
    (!(fov > 0.0 && fov < 180.0 && k.is_normal()))
        .then(|| format!("must be between 0 and 180 degrees (exclusive), got {fov}"))
}

/// What the camera check says about a view along the up vector.
pub(crate) fn vertical_message(up: Vec3) -> String {
    if !up.is_finite() || !up.length().is_normal() {
        format!(
            "up must be a non-zero vector, got {} {} {}",
            up.x, up.y, up.z
        )
    } else if up == CameraSpec::WORLD_UP {
        VERTICAL.to_string()
    } else {
        format!(
            "the viewing direction (look_at - position) is parallel to the up vector ({} {} {})",
            up.x, up.y, up.z
        )
    }
}

/// What the camera check says about a vertical view (with the path `camera`).
const VERTICAL: &str =
    "the viewing direction (look_at - position) is parallel to the world up axis (0 1 0)";

/// Why a camera position and look-at point give no camera.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum CameraProblem {
    Same,
    NoDirection,
    Vertical,
}

impl CameraProblem {
    fn message(self) -> &'static str {
        match self {
            CameraProblem::Same => "must differ from camera.position",
            CameraProblem::NoDirection => {
                "is too far from or too close to camera.position to define a direction"
            }
            CameraProblem::Vertical => VERTICAL,
        }
    }
}

/// The camera's checks, shared by the static scene and every frame of an animation.
pub(crate) fn camera_problem(camera: &CameraSpec) -> Option<CameraProblem> {
    let forward = camera.look_at - camera.position;
    if forward == Vec3::ZERO {
        return Some(CameraProblem::Same);
    }
    if !forward.is_finite() || !forward.length().is_normal() {
        return Some(CameraProblem::NoDirection);
    }
    // The right axis is up × forward: it vanishes (or underflows) when the camera looks
    // along the up vector (with the seed's up, straight up or down).
    let f = forward.normalize();
    let up = camera.up;
    if !up.is_finite() || !up.length().is_normal() || !up.cross(f).length().is_normal() {
        return Some(CameraProblem::Vertical);
    }
    None
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
mod tests;
