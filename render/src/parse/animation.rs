//! Reading the `"animation"` key of a scene file into an [`Animation`].
//!
//! Kept apart from the static scene's reading because it is read after it and against
//! it: a track names an object or a light by its index and a field its type must have,
//! and every frame's values must make a valid scene. So the checks come in this order,
//! and the first problem found is the one reported:
//! 1. the structure, key by key (`frames`, `fps`, then each track: its target, its
//!    interpolation, its keys in order);
//! 2. each track in order, at every frame from 1 to `frames`: the interpolated value
//!    must be valid where the static scene's would have to be (finite, radius > 0,
//!    normal and up non-zero, r g b ≥ 0, 0 < fov < 180);
//! 3. the camera at every frame, when a track moves it: its view direction must exist
//!    and must not be parallel to the up axis;
//! 4. the transform of each mesh a track animates, at every frame, in the order of the
//!    objects: it must map (no zero scale, no singular matrix). Its parts come from
//!    several tracks, so the problem is the frame's, not one track's.
//!
//! Checking every frame is cheap (a few operations per track and frame, with at most
//! [`MAX_TRACKS`] tracks and [`MAX_FRAMES`] frames), and it means that every frame of an
//! accepted animation renders.

use std::collections::{BTreeMap, HashMap};

use serde_json::{Map, Value};

use super::{
    as_object, camera_problem, check_keys, fov_problem, join, matrix, number, required, type_name,
    vec3, whole_number, CameraProblem, Result,
};
use crate::animation::{
    Animation, Interpolation, Key, Kind, Target, Track, TransformPart, Value as KeyValue,
    MAX_FRAMES,
};
use crate::error::SceneError;
use crate::scene::{CameraSpec, MeshObject, Scene, Shape};
use crate::transform::TransformSpec;
use crate::vec3::Vec3;

/// The most tracks an animation may have.
pub const MAX_TRACKS: usize = 4096;

/// The most track values checked (tracks × frames): every frame of every track is
/// checked when the scene is read, by a coordinator too, so this bounds what one
/// submitted scene can cost it (0.3 s at the bound, 100 Catmull–Rom vector tracks of
/// 100,000 frames, on a 2-core Intel Xeon). Tracks of mesh transforms cost about four
/// times as much, each frame's transform being mapped (sines and cosines); a
/// coordinator refuses meshes before it reads the animation.
pub const MAX_TRACK_FRAMES: u64 = 10_000_000;

/// The frame rate when the file gives none.
const DEFAULT_FPS: f64 = 24.0;

/// Reads and checks the value of the `"animation"` key against the static scene `base`.
pub(super) fn parse(v: &Value, base: &Scene) -> Result<Animation> {
    let path = "animation";
    let obj = as_object(v, path)?;
    check_keys(obj, path, &["frames", "fps", "tracks"])?;
    let frames_path = join(path, "frames");
    let frames = whole_number(required(obj, path, "frames")?, &frames_path)?;
    if !(1..=MAX_FRAMES).contains(&frames) {
        return Err(SceneError::invalid(
            frames_path,
            format!("must be between 1 and {MAX_FRAMES}, got {frames}"),
        ));
    }
    let fps = match obj.get("fps") {
        Some(v) => {
            let fps_path = join(path, "fps");
            let fps = number(v, &fps_path)?;
            if fps <= 0.0 {
                return Err(SceneError::invalid(
                    fps_path,
                    format!("must be > 0, got {fps}"),
                ));
            }
            fps
        }
        None => DEFAULT_FPS,
    };
    let tracks = match obj.get("tracks") {
        Some(v) => parse_tracks(v, &join(path, "tracks"), frames, base)?,
        None => Vec::new(),
    };
    let animation = Animation {
        frames,
        fps,
        tracks,
    };
    check_frames(&animation, base)?;
    Ok(animation)
}

fn parse_tracks(v: &Value, path: &str, frames: u32, base: &Scene) -> Result<Vec<Track>> {
    let items = v.as_array().ok_or_else(|| {
        SceneError::invalid(path, format!("expected an array, got {}", type_name(v)))
    })?;
    if items.len() > MAX_TRACKS {
        return Err(SceneError::invalid(
            path,
            format!("at most {MAX_TRACKS} tracks, got {}", items.len()),
        ));
    }
    let checks = items.len() as u64 * u64::from(frames);
    if checks > MAX_TRACK_FRAMES {
        return Err(SceneError::invalid(
            path,
            format!(
                "{} tracks of {frames} frames are {checks} values to check, at most \
                 {MAX_TRACK_FRAMES}: use fewer tracks or frames",
                items.len()
            ),
        ));
    }
    let mut seen: HashMap<Target, usize> = HashMap::new();
    let mut tracks = Vec::with_capacity(items.len());
    for (i, item) in items.iter().enumerate() {
        let track_path = format!("{path}[{i}]");
        let track = parse_track(item, &track_path, frames, base)?;
        if let Some(first) = seen.insert(track.target, i) {
            return Err(SceneError::invalid(
                join(&track_path, "target"),
                format!("{} is already animated by tracks[{first}]", track.target),
            ));
        }
        if let Some((other, first)) = conflicting(&seen, track.target) {
            return Err(SceneError::invalid(
                join(&track_path, "target"),
                format!(
                    "{} cannot be combined with {other}, animated by tracks[{first}]",
                    track.target
                ),
            ));
        }
        tracks.push(track);
    }
    Ok(tracks)
}

/// The first track seen that animates the other side of a mesh's transform (its matrix
/// against its parts): the format does not combine them, in a track as in the file.
fn conflicting(seen: &HashMap<Target, usize>, target: Target) -> Option<(Target, usize)> {
    let Target::MeshTransform(i, part) = target else {
        return None;
    };
    let others: &[TransformPart] = match part {
        TransformPart::Matrix => &[
            TransformPart::Translate,
            TransformPart::Rotate,
            TransformPart::Scale,
        ],
        _ => &[TransformPart::Matrix],
    };
    others
        .iter()
        .map(|&other| Target::MeshTransform(i, other))
        .filter_map(|other| seen.get(&other).map(|&first| (other, first)))
        .min_by_key(|&(_, first)| first)
}

fn parse_track(v: &Value, path: &str, frames: u32, base: &Scene) -> Result<Track> {
    let obj = as_object(v, path)?;
    check_keys(obj, path, &["target", "interpolation", "keys"])?;
    let target_path = join(path, "target");
    let target = target(
        string(required(obj, path, "target")?, &target_path)?,
        &target_path,
        base,
    )?;
    let interpolation = match obj.get("interpolation") {
        Some(v) => {
            let p = join(path, "interpolation");
            match string(v, &p)? {
                "linear" => Interpolation::Linear,
                "catmull-rom" => Interpolation::CatmullRom,
                other => {
                    return Err(SceneError::invalid(
                        p,
                        format!(
                        "unknown interpolation {other:?} (expected \"linear\" or \"catmull-rom\")"
                    ),
                    ))
                }
            }
        }
        None => Interpolation::Linear,
    };
    let keys = parse_keys(obj, path, frames, target)?;
    Ok(Track {
        target,
        interpolation,
        keys,
    })
}

fn parse_keys(
    obj: &Map<String, Value>,
    path: &str,
    frames: u32,
    target: Target,
) -> Result<Vec<Key>> {
    let keys_path = join(path, "keys");
    let v = required(obj, path, "keys")?;
    let items = v.as_array().ok_or_else(|| {
        SceneError::invalid(
            &*keys_path,
            format!("expected an array, got {}", type_name(v)),
        )
    })?;
    if items.is_empty() {
        return Err(SceneError::invalid(keys_path, "must hold at least one key"));
    }
    let mut keys: Vec<Key> = Vec::with_capacity(items.len());
    for (j, item) in items.iter().enumerate() {
        let key_path = format!("{keys_path}[{j}]");
        let key = as_object(item, &key_path)?;
        check_keys(key, &key_path, &["frame", "value"])?;
        let frame_path = join(&key_path, "frame");
        let frame = whole_number(required(key, &key_path, "frame")?, &frame_path)?;
        if frame == 0 {
            return Err(SceneError::invalid(
                frame_path,
                "frames are numbered from 1, got 0",
            ));
        }
        if frame > frames {
            return Err(SceneError::invalid(
                frame_path,
                format!("{frame} is beyond the {frames} frames"),
            ));
        }
        if let Some(previous) = keys.last() {
            if frame <= previous.frame {
                return Err(SceneError::invalid(
                    frame_path,
                    format!(
                        "{frame} does not come after the previous key's frame {}",
                        previous.frame
                    ),
                ));
            }
        }
        let value_path = join(&key_path, "value");
        let value = key_value(required(key, &key_path, "value")?, &value_path, target)?;
        keys.push(Key { frame, value });
    }
    Ok(keys)
}

/// A key's value, of the kind its target holds, spelled as the static scene spells the
/// field: a scale may be one number for all three axes.
fn key_value(v: &Value, path: &str, target: Target) -> Result<KeyValue> {
    Ok(match target.kind() {
        Kind::Number => KeyValue::Number(number(v, path)?),
        Kind::Vector
            if v.is_number()
                && matches!(target, Target::MeshTransform(_, TransformPart::Scale)) =>
        {
            let s = number(v, path)?;
            KeyValue::Vector(Vec3::new(s, s, s))
        }
        Kind::Vector => KeyValue::Vector(vec3(v, path)?),
        Kind::Matrix => KeyValue::Matrix(matrix(v, path)?),
    })
}

fn string<'a>(v: &'a Value, path: &str) -> Result<&'a str> {
    v.as_str().ok_or_else(|| {
        SceneError::invalid(path, format!("expected a string, got {}", type_name(v)))
    })
}

/// What a target string names: `camera.FIELD`, `objects[N].FIELD` or
/// `lights[N].FIELD`, checked against the scene.
fn target(text: &str, path: &str, base: &Scene) -> Result<Target> {
    let unknown = || {
        SceneError::invalid(
            path,
            format!(
                "unknown target {text:?} (expected camera.position, camera.look_at, camera.up, \
                 camera.fov, objects[N].FIELD, objects[N].transform.PART or lights[N].FIELD)"
            ),
        )
    };
    let (head, field) = text.split_once('.').ok_or_else(unknown)?;
    if head == "camera" {
        return camera_target(field, path);
    }
    let (list, index) = head
        .strip_suffix(']')
        .and_then(|h| h.split_once('['))
        .ok_or_else(unknown)?;
    if index.is_empty() || !index.bytes().all(|b| b.is_ascii_digit()) {
        return Err(unknown());
    }
    // More digits than a usize holds: certainly beyond the list.
    let i = index.parse::<usize>().unwrap_or(usize::MAX);
    match list {
        "objects" => {
            let object = base.objects.get(i).ok_or_else(|| {
                SceneError::invalid(
                    path,
                    format!(
                        "there is no objects[{index}]: the scene has {} objects",
                        base.objects.len()
                    ),
                )
            })?;
            object_target(&object.shape, i, field, path)
        }
        "lights" => {
            if i >= base.lights.len() {
                return Err(SceneError::invalid(
                    path,
                    format!(
                        "there is no lights[{index}]: the scene has {} lights",
                        base.lights.len()
                    ),
                ));
            }
            match field {
                "position" => Ok(Target::LightPosition(i)),
                "color" => Ok(Target::LightColor(i)),
                other => Err(SceneError::invalid(
                    path,
                    format!(
                        "lights[{i}] has no field {other:?} to animate (expected position or color)"
                    ),
                )),
            }
        }
        _ => Err(unknown()),
    }
}

fn camera_target(field: &str, path: &str) -> Result<Target> {
    match field {
        "position" => Ok(Target::CameraPosition),
        "look_at" => Ok(Target::CameraLookAt),
        "up" => Ok(Target::CameraUp),
        "fov" => Ok(Target::CameraFov),
        other => Err(SceneError::invalid(
            path,
            format!(
                "the camera has no field {other:?} to animate \
                 (expected position, look_at, up or fov)"
            ),
        )),
    }
}

/// The field `field` of `objects[i]`, whose shape is `shape`.
fn object_target(shape: &Shape, i: usize, field: &str, path: &str) -> Result<Target> {
    let part = field.strip_prefix("transform.").and_then(transform_part);
    match (shape, field, part) {
        (Shape::Sphere { .. }, "center", _) => Ok(Target::SphereCenter(i)),
        (Shape::Sphere { .. }, "radius", _) => Ok(Target::SphereRadius(i)),
        (Shape::Plane { .. }, "normal", _) => Ok(Target::PlaneNormal(i)),
        (Shape::Plane { .. }, "distance", _) => Ok(Target::PlaneDistance(i)),
        (_, "color", _) => Ok(Target::ObjectColor(i)),
        (Shape::Mesh(mesh), _, Some(part)) => mesh_target(mesh, i, part, path),
        _ => {
            let (name, fields) = match shape {
                Shape::Sphere { .. } => ("sphere", "center, radius or color"),
                Shape::Plane { .. } => ("plane", "normal, distance or color"),
                Shape::Triangle { .. } => ("triangle", "color"),
                Shape::Box { .. } => ("box", "color"),
                Shape::Mesh(_) => (
                    "mesh",
                    "transform.translate, transform.rotate, transform.scale, \
                     transform.matrix or color",
                ),
            };
            Err(SceneError::invalid(
                path,
                format!(
                    "objects[{i}] is a {name}, which has no field {field:?} to animate \
                     (expected {fields})"
                ),
            ))
        }
    }
}

fn transform_part(name: &str) -> Option<TransformPart> {
    match name {
        "translate" => Some(TransformPart::Translate),
        "rotate" => Some(TransformPart::Rotate),
        "scale" => Some(TransformPart::Scale),
        "matrix" => Some(TransformPart::Matrix),
        _ => None,
    }
}

/// A part of the transform of the mesh `objects[i]`. A matrix replaces the whole
/// transform, so, as the format does not combine them, it is refused where the file
/// gives parts and the parts where it gives a matrix. A mesh without a transform has
/// the identity parts, which nothing contradicts (and which is how a scene written back
/// spells a mesh without one): any part may animate it.
fn mesh_target(mesh: &MeshObject, i: usize, part: TransformPart, path: &str) -> Result<Target> {
    let target = Target::MeshTransform(i, part);
    let problem = match (mesh.spec, part) {
        (TransformSpec::Matrix(_), TransformPart::Matrix) => None,
        (TransformSpec::Matrix(_), _) => Some(format!(
            "the mesh's transform is a matrix, which cannot be combined with {} (animate \
             objects[{i}].transform.matrix instead)",
            part.name()
        )),
        (spec, TransformPart::Matrix) if spec != TransformSpec::IDENTITY => Some(
            "the mesh's transform gives scale, rotate or translate, which cannot be combined \
             with matrix"
                .to_string(),
        ),
        _ => None,
    };
    match problem {
        None => Ok(target),
        Some(problem) => Err(SceneError::invalid(
            path,
            format!("{target} cannot be animated: {problem}"),
        )),
    }
}

/// Steps 2 to 4 of the module's checks.
fn check_frames(animation: &Animation, base: &Scene) -> Result<()> {
    check_values(animation)?;
    check_cameras(animation, base)?;
    check_transforms(animation, base)
}

/// Step 2: every frame of every track.
fn check_values(animation: &Animation) -> Result<()> {
    for (i, track) in animation.tracks.iter().enumerate() {
        for k in 1..=animation.frames {
            if let Some(problem) = value_problem(track.target, track.value_at(k)) {
                return Err(SceneError::invalid(
                    format!("animation.tracks[{i}]"),
                    format!("at frame {k}, {} {problem}", track.target),
                ));
            }
        }
    }
    Ok(())
}

/// Step 3: the camera at every frame, when a track moves it (its position, look-at
/// point or up vector; a field of view is valid on its own, step 2).
fn check_cameras(animation: &Animation, base: &Scene) -> Result<()> {
    let tracks: Vec<&Track> = animation
        .tracks
        .iter()
        .filter(|t| t.target.is_camera() && t.target != Target::CameraFov)
        .collect();
    if tracks.is_empty() {
        return Ok(());
    }
    for k in 1..=animation.frames {
        let mut camera = base.camera;
        for track in &tracks {
            track.target.set_camera(&mut camera, track.value_at(k));
        }
        let problem = match camera_problem(&camera) {
            None => continue,
            Some(CameraProblem::Same) => "camera.look_at equals camera.position".to_string(),
            Some(CameraProblem::NoDirection) => {
                "camera.look_at is too far from or too close to camera.position to define a \
                 direction"
                    .to_string()
            }
            Some(CameraProblem::Vertical) => vertical_at_frame(camera.up),
        };
        return Err(SceneError::invalid(
            "animation",
            format!("at frame {k}, {problem}"),
        ));
    }
    Ok(())
}

/// What step 3 says of a camera that looks along its up vector, which step 2 (or the
/// static scene's check) made non-zero.
fn vertical_at_frame(up: Vec3) -> String {
    if up == CameraSpec::WORLD_UP {
        "the camera's viewing direction (look_at - position) is parallel to the world up \
         axis (0 1 0)"
            .to_string()
    } else {
        format!(
            "the camera's viewing direction (look_at - position) is parallel to the up vector \
             ({} {} {})",
            up.x, up.y, up.z
        )
    }
}

/// Step 4: each animated mesh's transform at every frame, mapped as the frame maps it
/// ([`Animation::apply`]): a zero scale or a singular matrix would flatten the mesh.
fn check_transforms(animation: &Animation, base: &Scene) -> Result<()> {
    let mut parts: BTreeMap<usize, Vec<(TransformPart, &Track)>> = BTreeMap::new();
    for track in &animation.tracks {
        if let Target::MeshTransform(i, part) = track.target {
            parts.entry(i).or_default().push((part, track));
        }
    }
    for (i, tracks) in parts {
        let Shape::Mesh(mesh) = &base.objects[i].shape else {
            continue;
        };
        for k in 1..=animation.frames {
            let mut spec = mesh.spec;
            for (part, track) in &tracks {
                part.set(&mut spec, track.value_at(k));
            }
            if let Err(problem) = spec.affine() {
                return Err(SceneError::invalid(
                    "animation",
                    format!("at frame {k}, objects[{i}].transform: {problem}"),
                ));
            }
        }
    }
    Ok(())
}

/// What is wrong with a field's value, worded to follow the field's name; `None` if
/// the static scene could hold it.
fn value_problem(target: Target, value: KeyValue) -> Option<String> {
    match value {
        KeyValue::Number(x) => {
            if !x.is_finite() {
                return Some(format!("is not a finite number: {x}"));
            }
            if matches!(target, Target::SphereRadius(_)) && x <= 0.0 {
                return Some(format!("must be > 0, got {x}"));
            }
            if target == Target::CameraFov {
                return fov_problem(x);
            }
        }
        KeyValue::Vector(v) => {
            if !v.is_finite() {
                return Some(format!("is not finite: {} {} {}", v.x, v.y, v.z));
            }
            match target {
                Target::PlaneNormal(_) => {
                    let len = v.length();
                    if len == 0.0 || !len.is_finite() {
                        return Some("must be a non-zero vector of finite length".into());
                    }
                }
                // As the camera's check has it: a length too small for a direction is
                // none.
                Target::CameraUp if !v.length().is_normal() => {
                    return Some("must be a non-zero vector of finite length".into());
                }
                Target::ObjectColor(_) | Target::LightColor(_) => {
                    if let Some(c) = [v.x, v.y, v.z].into_iter().find(|c| *c < 0.0) {
                        return Some(format!("must have r, g and b >= 0, got {c}"));
                    }
                }
                _ => {}
            }
        }
        KeyValue::Matrix(m) => {
            if m.iter().any(|x| !x.is_finite()) {
                let numbers: Vec<String> = m.iter().map(f64::to_string).collect();
                return Some(format!("is not finite: {}", numbers.join(" ")));
            }
        }
    }
    None
}

#[cfg(test)]
mod tests;
