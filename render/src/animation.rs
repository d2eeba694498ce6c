//! Animated scenes: a static scene plus keyframed tracks, and what frame k of it is.
//!
//! This is its own module because an animation is a *function from frame numbers to
//! static scenes*, not a new kind of scene: frame k is, by definition, the static scene
//! with each animated field set to its track's value at k and no animation left. The
//! renderer, the tiles, the farm and the samplers never see an animation, only the
//! frames, so everything that holds for a static scene (determinism, bit-identical
//! images in any tiling) holds for every frame.
//!
//! Interpolation decides pixels, so it uses only +, −, × and ÷ on `f64`, in a fixed
//! order, never `mul_add`, `powf`, `sin` or `cos` (architecture invariant 1): the same
//! frame gives the same bits on every machine. There is no orbit primitive; an orbit is
//! a Catmull–Rom track through keys on the circle.
//!
//! Reading the `"animation"` key of a scene file is in `parse::animation`; the model
//! here is always valid once it exists (every frame of every track has been checked).

use std::fmt;

use crate::scene::{CameraSpec, Scene, Shape};
use crate::transform::TransformSpec;
use crate::vec3::Vec3;

/// The largest frame count an animation may have.
pub const MAX_FRAMES: u32 = 100_000;

/// A scene as a file describes it: the static scene, and its animation if it has one.
#[derive(Clone, Debug, PartialEq)]
pub struct AnimatedScene {
    /// The scene as written, without the animation: the values of every field that no
    /// track animates.
    pub base: Scene,
    pub animation: Option<Animation>,
}

/// The `"animation"` key of a scene file, validated.
#[derive(Clone, Debug, PartialEq)]
pub struct Animation {
    /// Frames are numbered 1 to `frames`.
    pub frames: u32,
    /// Frames per second: for whoever plays the frames; it changes no pixel.
    pub fps: f64,
    /// At most one track per target.
    pub tracks: Vec<Track>,
}

/// The keyframes of one field.
#[derive(Clone, Debug, PartialEq)]
pub struct Track {
    pub target: Target,
    pub interpolation: Interpolation,
    /// At least one key, frames strictly increasing, all within 1..=frames.
    pub keys: Vec<Key>,
}

/// A key: the field's value at one frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Key {
    pub frame: u32,
    pub value: Value,
}

/// A numeric field's value: a number (radius, distance, field of view), three numbers
/// (positions, directions, r g b, a transform's parts) or a transform's 12 (its 3 × 4
/// matrix, row by row).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Value {
    Number(f64),
    Vector(Vec3),
    Matrix([f64; 12]),
}

/// Which of the [`Value`]s a target's keys hold.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kind {
    Number,
    Vector,
    Matrix,
}

/// How a track goes from one key to the next.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Interpolation {
    /// A straight line between two keys.
    Linear,
    /// A cubic Hermite spline through the keys, with Catmull–Rom tangents scaled for
    /// unevenly spaced keys; at the first and last key the end key is duplicated one
    /// segment beyond the end.
    CatmullRom,
}

impl Interpolation {
    pub fn name(self) -> &'static str {
        match self {
            Interpolation::Linear => "linear",
            Interpolation::CatmullRom => "catmull-rom",
        }
    }
}

/// Which field a track animates. Indices are into the scene's `objects` and `lights`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Target {
    CameraPosition,
    CameraLookAt,
    CameraUp,
    CameraFov,
    SphereCenter(usize),
    SphereRadius(usize),
    PlaneNormal(usize),
    PlaneDistance(usize),
    /// The object's r g b; its `special` (material) is not animated.
    ObjectColor(usize),
    LightPosition(usize),
    LightColor(usize),
    /// A part of a mesh's `transform`.
    MeshTransform(usize, TransformPart),
}

/// The keys of a mesh's `transform` a track may animate. A matrix and the other three
/// exclude each other, in a track as in the file.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum TransformPart {
    Translate,
    Rotate,
    Scale,
    Matrix,
}

impl TransformPart {
    /// The key as a scene file writes it.
    pub fn name(self) -> &'static str {
        match self {
            TransformPart::Translate => "translate",
            TransformPart::Rotate => "rotate",
            TransformPart::Scale => "scale",
            TransformPart::Matrix => "matrix",
        }
    }

    /// Writes `value` into `spec`. A part other than the matrix changes a transform of
    /// parts only (reading the animation refused it on a matrix); the matrix replaces
    /// the whole transform.
    pub(crate) fn set(self, spec: &mut TransformSpec, value: Value) {
        match (self, spec, value) {
            (TransformPart::Matrix, spec, Value::Matrix(m)) => *spec = TransformSpec::Matrix(m),
            (
                TransformPart::Translate,
                TransformSpec::Parts { translate, .. },
                Value::Vector(v),
            ) => {
                *translate = v;
            }
            (TransformPart::Rotate, TransformSpec::Parts { rotate, .. }, Value::Vector(v)) => {
                *rotate = v;
            }
            (TransformPart::Scale, TransformSpec::Parts { scale, .. }, Value::Vector(v)) => {
                *scale = v;
            }
            _ => {}
        }
    }
}

impl Target {
    /// Which kind of value the field holds.
    pub fn kind(self) -> Kind {
        match self {
            Target::SphereRadius(_) | Target::PlaneDistance(_) | Target::CameraFov => Kind::Number,
            Target::MeshTransform(_, TransformPart::Matrix) => Kind::Matrix,
            _ => Kind::Vector,
        }
    }

    /// Whether the field is one of the camera's.
    pub fn is_camera(self) -> bool {
        matches!(
            self,
            Target::CameraPosition | Target::CameraLookAt | Target::CameraUp | Target::CameraFov
        )
    }

    /// Writes `value` into the camera's field, if the target is one.
    pub(crate) fn set_camera(self, camera: &mut CameraSpec, value: Value) {
        match (self, value) {
            (Target::CameraPosition, Value::Vector(v)) => camera.position = v,
            (Target::CameraLookAt, Value::Vector(v)) => camera.look_at = v,
            (Target::CameraUp, Value::Vector(v)) => camera.up = v,
            (Target::CameraFov, Value::Number(x)) => camera.fov = Some(x),
            _ => {}
        }
    }

    /// Writes `value` into the field of `scene`. The target was checked against this
    /// scene's objects and lights when the animation was read, so it exists and has the
    /// right shape; a mismatched value leaves the field as it was. A mesh's transform is
    /// written as its spec only: [`Animation::apply`] maps it.
    fn set(self, scene: &mut Scene, value: Value) {
        match (self, value) {
            (target, _) if target.is_camera() => target.set_camera(&mut scene.camera, value),
            (Target::MeshTransform(i, part), _) => {
                if let Shape::Mesh(mesh) = &mut scene.objects[i].shape {
                    part.set(&mut mesh.spec, value);
                }
            }
            (Target::SphereCenter(i), Value::Vector(v)) => {
                if let Shape::Sphere { center, .. } = &mut scene.objects[i].shape {
                    *center = v;
                }
            }
            (Target::SphereRadius(i), Value::Number(x)) => {
                if let Shape::Sphere { radius, .. } = &mut scene.objects[i].shape {
                    *radius = x;
                }
            }
            (Target::PlaneNormal(i), Value::Vector(v)) => {
                if let Shape::Plane { normal, .. } = &mut scene.objects[i].shape {
                    *normal = v;
                }
            }
            (Target::PlaneDistance(i), Value::Number(x)) => {
                if let Shape::Plane { distance, .. } = &mut scene.objects[i].shape {
                    *distance = x;
                }
            }
            (Target::ObjectColor(i), Value::Vector(v)) => scene.objects[i].color = v,
            (Target::LightPosition(i), Value::Vector(v)) => scene.lights[i].position = v,
            (Target::LightColor(i), Value::Vector(v)) => scene.lights[i].color = v,
            _ => {}
        }
    }
}

impl fmt::Display for Target {
    /// The target as a scene file writes it: `camera.position`, `objects[1].radius`.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match *self {
            Target::CameraPosition => write!(f, "camera.position"),
            Target::CameraLookAt => write!(f, "camera.look_at"),
            Target::SphereCenter(i) => write!(f, "objects[{i}].center"),
            Target::SphereRadius(i) => write!(f, "objects[{i}].radius"),
            Target::PlaneNormal(i) => write!(f, "objects[{i}].normal"),
            Target::PlaneDistance(i) => write!(f, "objects[{i}].distance"),
            Target::ObjectColor(i) => write!(f, "objects[{i}].color"),
            Target::LightPosition(i) => write!(f, "lights[{i}].position"),
            Target::LightColor(i) => write!(f, "lights[{i}].color"),
            Target::CameraUp => write!(f, "camera.up"),
            Target::CameraFov => write!(f, "camera.fov"),
            Target::MeshTransform(i, part) => write!(f, "objects[{i}].transform.{}", part.name()),
        }
    }
}

/// A frame number outside the scene's frames.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct FrameOutOfRange {
    pub frame: u64,
    /// The scene's frame count (1 for a scene without animation).
    pub frames: u32,
    pub animated: bool,
}

impl fmt::Display for FrameOutOfRange {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.frame == 0 {
            write!(f, "frame 0: frames are numbered from 1")
        } else if !self.animated {
            write!(
                f,
                "frame {}: the scene has no animation, only frame 1",
                self.frame
            )
        } else {
            write!(
                f,
                "frame {} is beyond the scene's {} frames",
                self.frame, self.frames
            )
        }
    }
}

impl std::error::Error for FrameOutOfRange {}

/// The name of frame `k` of a scene of `count` frames: `frame_0007.png`, with as many
/// digits as the count has, at least 4. `tessera render --frames`, the coordinator's
/// store and `tessera fetch` of a sequence all name frames so.
pub fn frame_file_name(k: u64, count: u32) -> String {
    let width = count.to_string().len().max(4);
    format!("frame_{k:0width$}.png")
}

impl AnimatedScene {
    /// How many frames the scene has: the animation's, or 1 for a static scene.
    pub fn frame_count(&self) -> u32 {
        self.animation.as_ref().map_or(1, |a| a.frames)
    }

    /// Frame `k` (1-based): the static scene with every animated field set to its
    /// track's value at `k`. A static scene has one frame, itself.
    pub fn frame(&self, k: u64) -> Result<Scene, FrameOutOfRange> {
        let frames = self.frame_count();
        if k == 0 || k > u64::from(frames) {
            return Err(FrameOutOfRange {
                frame: k,
                frames,
                animated: self.animation.is_some(),
            });
        }
        Ok(match &self.animation {
            Some(a) => a.apply(&self.base, k as u32),
            None => self.base.clone(),
        })
    }

    /// [`AnimatedScene::frame`], taking the scene: a static scene is given as it is,
    /// not copied (a copy of a million objects costs more than reading them).
    pub fn into_frame(self, k: u64) -> Result<Scene, FrameOutOfRange> {
        match self.animation {
            None if k == 1 => Ok(self.base),
            _ => self.frame(k),
        }
    }

    /// Frame 1, which is what rendering an animated scene without naming a frame means.
    pub fn into_first_frame(self) -> Scene {
        match &self.animation {
            Some(a) => a.apply(&self.base, 1),
            None => self.base,
        }
    }
}

impl Animation {
    /// `base` with every track's value at frame `k` written in, and each animated mesh's
    /// transform mapped anew from its spec at `k`. `k` is not checked against the frame
    /// count: before the first key a track holds its first value, after the last its
    /// last.
    pub fn apply(&self, base: &Scene, k: u32) -> Scene {
        let mut scene = base.clone();
        for track in &self.tracks {
            track.target.set(&mut scene, track.value_at(k));
        }
        for i in self.animated_meshes() {
            if let Shape::Mesh(mesh) = &mut scene.objects[i].shape {
                // Every frame's transform was mapped once already, when the animation
                // was read: this cannot fail for a frame of the animation.
                if let Ok(transform) = mesh.spec.affine() {
                    mesh.transform = transform;
                }
            }
        }
        scene
    }

    /// The objects whose transform a track animates, each once, in order.
    pub(crate) fn animated_meshes(&self) -> Vec<usize> {
        let mut meshes: Vec<usize> = self
            .tracks
            .iter()
            .filter_map(|t| match t.target {
                Target::MeshTransform(i, _) => Some(i),
                _ => None,
            })
            .collect();
        meshes.sort_unstable();
        meshes.dedup();
        meshes
    }
}

impl Track {
    /// The track's value at frame `k`: the first key's value up to the first key, the
    /// last key's from the last key on, a key's own value (the same bits) at its frame,
    /// and the interpolation between keys.
    pub fn value_at(&self, k: u32) -> Value {
        let keys = &self.keys;
        // The first key after frame k: the segment holding k starts just before it.
        let after = keys.partition_point(|key| key.frame <= k);
        if after == 0 {
            return keys[0].value;
        }
        let i = after - 1;
        if after == keys.len() || keys[i].frame == k {
            return keys[i].value;
        }
        match self.interpolation {
            Interpolation::Linear => {
                let (a, b) = (keys[i], keys[i + 1]);
                let t = segment_t(a.frame, b.frame, k);
                map2(a.value, b.value, |p, q| linear(p, q, t))
            }
            Interpolation::CatmullRom => {
                let [k0, k1, k2, k3] = catmull_rom_keys(keys, i);
                let t = segment_t(keys[i].frame, keys[i + 1].frame, k);
                let (g1, g2) = tangent_scales(k0.frame, k1.frame, k2.frame, k3.frame);
                map4(k0.value, k1.value, k2.value, k3.value, |p0, p1, p2, p3| {
                    catmull_rom(p0, p1, p2, p3, g1, g2, t)
                })
            }
        }
    }
}

/// Where frame `k` lies in the segment from frame `a` to frame `b` (a < k < b), as a
/// fraction: both differences are small integers, exact in f64, so the one division is
/// the only rounding.
fn segment_t(a: u32, b: u32, k: u32) -> f64 {
    f64::from(k - a) / f64::from(b - a)
}

/// The straight line from `p` (t = 0) to `q` (t = 1): p + (q − p)·t.
pub fn linear(p: f64, q: f64, t: f64) -> f64 {
    p + (q - p) * t
}

/// The four keys around segment `i` (from `keys[i]` to `keys[i + 1]`): the key before
/// and the key after, where the track has them; at an end, the end key again, with its
/// frame moved one segment beyond the end (so that no frame difference is zero), which
/// may put it before frame 1 or after the last frame.
fn catmull_rom_keys(keys: &[Key], i: usize) -> [PhantomKey; 4] {
    let k1 = PhantomKey::from(keys[i]);
    let k2 = PhantomKey::from(keys[i + 1]);
    let k0 = if i > 0 {
        PhantomKey::from(keys[i - 1])
    } else {
        PhantomKey {
            frame: k1.frame - (k2.frame - k1.frame),
            value: k1.value,
        }
    };
    let k3 = match keys.get(i + 2) {
        Some(k) => PhantomKey::from(*k),
        None => PhantomKey {
            frame: k2.frame + (k2.frame - k1.frame),
            value: k2.value,
        },
    };
    [k0, k1, k2, k3]
}

/// A key whose frame may lie outside the animation (a duplicated end key).
#[derive(Clone, Copy)]
struct PhantomKey {
    frame: i64,
    value: Value,
}

impl From<Key> for PhantomKey {
    fn from(k: Key) -> Self {
        PhantomKey {
            frame: i64::from(k.frame),
            value: k.value,
        }
    }
}

/// The factors that turn the central differences at the segment's two ends into
/// tangents measured over the segment: h / (f2 − f0) and h / (f3 − f1), h = f2 − f1.
/// With evenly spaced keys both are ½, the uniform Catmull–Rom spline.
fn tangent_scales(f0: i64, f1: i64, f2: i64, f3: i64) -> (f64, f64) {
    let h = (f2 - f1) as f64;
    (h / (f2 - f0) as f64, h / (f3 - f1) as f64)
}

/// The Catmull–Rom (cubic Hermite) spline from `p1` (t = 0) to `p2` (t = 1), with
/// tangents m1 = g1·(p2 − p0) and m2 = g2·(p3 − p1), evaluated as
/// p1 + t·(m1 + t·(c2 + t·c3)) with c2 = 3(p2 − p1) − 2·m1 − m2 and
/// c3 = 2(p1 − p2) + m1 + m2: each operation rounded on its own, in this order.
pub fn catmull_rom(p0: f64, p1: f64, p2: f64, p3: f64, g1: f64, g2: f64, t: f64) -> f64 {
    let m1 = g1 * (p2 - p0);
    let m2 = g2 * (p3 - p1);
    let c2 = 3.0 * (p2 - p1) - 2.0 * m1 - m2;
    let c3 = 2.0 * (p1 - p2) + m1 + m2;
    p1 + t * (m1 + t * (c2 + t * c3))
}

fn map2(a: Value, b: Value, f: impl Fn(f64, f64) -> f64) -> Value {
    match (a, b) {
        (Value::Number(p), Value::Number(q)) => Value::Number(f(p, q)),
        (Value::Vector(p), Value::Vector(q)) => {
            Value::Vector(Vec3::new(f(p.x, q.x), f(p.y, q.y), f(p.z, q.z)))
        }
        (Value::Matrix(p), Value::Matrix(q)) => {
            Value::Matrix(std::array::from_fn(|i| f(p[i], q[i])))
        }
        // A track's keys all have the target's kind; reading the file made sure.
        _ => a,
    }
}

fn map4(a: Value, b: Value, c: Value, d: Value, f: impl Fn(f64, f64, f64, f64) -> f64) -> Value {
    match (a, b, c, d) {
        (Value::Number(p), Value::Number(q), Value::Number(r), Value::Number(s)) => {
            Value::Number(f(p, q, r, s))
        }
        (Value::Vector(p), Value::Vector(q), Value::Vector(r), Value::Vector(s)) => {
            Value::Vector(Vec3::new(
                f(p.x, q.x, r.x, s.x),
                f(p.y, q.y, r.y, s.y),
                f(p.z, q.z, r.z, s.z),
            ))
        }
        (Value::Matrix(p), Value::Matrix(q), Value::Matrix(r), Value::Matrix(s)) => {
            Value::Matrix(std::array::from_fn(|i| f(p[i], q[i], r[i], s[i])))
        }
        _ => b,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn track(interpolation: Interpolation, keys: &[(u32, f64)]) -> Track {
        Track {
            target: Target::SphereRadius(0),
            interpolation,
            keys: keys
                .iter()
                .map(|&(frame, x)| Key {
                    frame,
                    value: Value::Number(x),
                })
                .collect(),
        }
    }

    fn number(v: Value) -> f64 {
        match v {
            Value::Number(x) => x,
            other => panic!("not a number: {other:?}"),
        }
    }

    #[test]
    fn linear_is_exact_at_the_keys_and_halfway_between() {
        let t = track(Interpolation::Linear, &[(1, 0.1), (11, 0.7), (21, -3.0)]);
        assert_eq!(number(t.value_at(1)).to_bits(), 0.1f64.to_bits());
        assert_eq!(number(t.value_at(11)).to_bits(), 0.7f64.to_bits());
        assert_eq!(number(t.value_at(21)).to_bits(), (-3.0f64).to_bits());
        let t = track(Interpolation::Linear, &[(1, 2.0), (5, 4.0), (7, 1.0)]);
        assert_eq!(number(t.value_at(3)), 3.0);
        assert_eq!(number(t.value_at(2)), 2.5);
        assert_eq!(number(t.value_at(6)), 2.5);
    }

    #[test]
    fn a_track_holds_its_end_values_before_the_first_and_after_the_last_key() {
        for interpolation in [Interpolation::Linear, Interpolation::CatmullRom] {
            let t = track(interpolation, &[(10, 2.0), (20, 4.0), (30, 1.0)]);
            for k in [0, 1, 9, 10] {
                assert_eq!(number(t.value_at(k)), 2.0, "{k}");
            }
            for k in [30, 31, 1000, u32::MAX] {
                assert_eq!(number(t.value_at(k)), 1.0, "{k}");
            }
            let one = track(interpolation, &[(5, 7.5)]);
            for k in [1, 5, 9] {
                assert_eq!(number(one.value_at(k)), 7.5);
            }
        }
    }

    #[test]
    fn catmull_rom_passes_through_its_keys_and_is_smooth_between() {
        let keys = [(1, 0.3), (4, 1.7), (10, -0.2), (13, 5.0), (20, 0.1)];
        let t = track(Interpolation::CatmullRom, &keys);
        for (frame, x) in keys {
            assert_eq!(number(t.value_at(frame)).to_bits(), x.to_bits(), "{frame}");
        }
        // The spline itself is exact at its ends, too (t = 0 and t = 1 up to rounding).
        assert_eq!(catmull_rom(9.0, 0.3, 1.7, 2.0, 0.5, 0.5, 0.0), 0.3);
        assert!((catmull_rom(9.0, 0.3, 1.7, 2.0, 0.5, 0.5, 1.0) - 1.7).abs() < 1e-15);
        // Evenly spaced keys on a line: between inner keys, the uniform spline is the line.
        let line = track(
            Interpolation::CatmullRom,
            &[(1, 0.0), (5, 4.0), (9, 8.0), (13, 12.0)],
        );
        for k in 5..=9 {
            assert_eq!(number(line.value_at(k)), f64::from(k - 1), "{k}");
        }
        // Halfway between two keys with keys on either side: the uniform formula
        // (−p0 + 9p1 + 9p2 − p3)/16.
        let t = track(
            Interpolation::CatmullRom,
            &[(1, 0.0), (3, 1.0), (5, 3.0), (7, 2.0)],
        );
        assert_eq!(number(t.value_at(4)), (-0.0 + 9.0 + 27.0 - 2.0) / 16.0);
        // At an end the end key is duplicated, so the tangent there is half the chord:
        // between two keys only, the curve is 0.5t + 1.5t² − t³, not the straight line.
        let two = track(Interpolation::CatmullRom, &[(1, 0.0), (5, 1.0)]);
        assert_eq!(number(two.value_at(3)), 0.5);
        assert_eq!(number(two.value_at(2)), 0.203125);
        assert_eq!(number(line.value_at(2)), 0.71875);
    }

    #[test]
    fn vectors_are_interpolated_component_by_component() {
        let t = Track {
            target: Target::CameraPosition,
            interpolation: Interpolation::Linear,
            keys: vec![
                Key {
                    frame: 1,
                    value: Value::Vector(Vec3::new(0.0, 1.0, -4.0)),
                },
                Key {
                    frame: 3,
                    value: Value::Vector(Vec3::new(2.0, 1.0, 4.0)),
                },
            ],
        };
        assert_eq!(t.value_at(2), Value::Vector(Vec3::new(1.0, 1.0, 0.0)));
    }

    #[test]
    fn matrices_are_interpolated_number_by_number() {
        let keys = [(1, 0.3), (4, 1.7), (10, -0.2), (13, 5.0)];
        for interpolation in [Interpolation::Linear, Interpolation::CatmullRom] {
            let numbers = track(interpolation, &keys);
            // Entry j of each key is the number key times j + 1.
            let matrices = Track {
                target: Target::MeshTransform(0, TransformPart::Matrix),
                interpolation,
                keys: numbers
                    .keys
                    .iter()
                    .map(|key| Key {
                        frame: key.frame,
                        value: Value::Matrix(std::array::from_fn(|j| {
                            number(key.value) * (j + 1) as f64
                        })),
                    })
                    .collect(),
            };
            let sevens = track(interpolation, &keys.map(|(frame, x)| (frame, x * 7.0)));
            for k in 1..=14 {
                let Value::Matrix(m) = matrices.value_at(k) else {
                    panic!("not a matrix");
                };
                assert_eq!(m[6], number(sevens.value_at(k)), "{k}");
                assert_eq!(m[0], number(numbers.value_at(k)), "{k}");
            }
        }
    }

    #[test]
    fn frames_outside_the_scene_are_refused_with_one_line() {
        // What `{"lights": [], "objects": []}` reads as.
        let base = Scene {
            lights: vec![],
            objects: vec![],
            camera: crate::scene::CameraSpec::default(),
            settings: crate::settings::RenderSettings::default(),
            ambient: 0.2,
        };
        let still = AnimatedScene {
            base: base.clone(),
            animation: None,
        };
        assert_eq!(still.frame(1).unwrap(), base);
        assert_eq!(
            still.frame(2).unwrap_err().to_string(),
            "frame 2: the scene has no animation, only frame 1"
        );
        let moving = AnimatedScene {
            base,
            animation: Some(Animation {
                frames: 120,
                fps: 24.0,
                tracks: vec![],
            }),
        };
        assert_eq!(
            moving.frame(0).unwrap_err().to_string(),
            "frame 0: frames are numbered from 1"
        );
        assert_eq!(
            moving.frame(121).unwrap_err().to_string(),
            "frame 121 is beyond the scene's 120 frames"
        );
        assert!(moving.frame(120).is_ok());
    }
}
