//! The scene model: what a scene file means once it has been read and validated.
//!
//! Values here are always valid (finite numbers, positive radii, non-zero normals,
//! settings within [`limits`](crate::limits)); [`crate::parse_scene`] is the only way in
//! from untrusted text.

use std::sync::Arc;

use crate::mesh::MeshFile;
use crate::settings::RenderSettings;
use crate::transform::{Affine, TransformSpec};
use crate::vec3::Vec3;

/// A validated scene, independent of image settings overrides.
#[derive(Clone, Debug, PartialEq)]
pub struct Scene {
    pub lights: Vec<Light>,
    pub objects: Vec<Object>,
    pub camera: CameraSpec,
    /// The image settings the scene asks for; a caller may override them.
    pub settings: RenderSettings,
    pub ambient: f64,
}

/// A point light. Its colour's optional 4th number is dropped at load time.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Light {
    pub position: Vec3,
    pub color: Vec3,
}

#[derive(Clone, Debug, PartialEq)]
pub struct Object {
    pub shape: Shape,
    /// The object's r g b; unused by the checkerboard material.
    pub color: Vec3,
    pub material: Material,
}

#[derive(Clone, Debug, PartialEq)]
pub enum Shape {
    Sphere {
        center: Vec3,
        radius: f64,
    },
    /// Points p with n̂·p = distance, where n̂ is `normal` normalised. The normal is
    /// kept as written; the tracer normalises it once when the scene is prepared.
    Plane {
        normal: Vec3,
        distance: f64,
    },
    /// The triangle v0 v1 v2 (section 8); a degenerate one is never hit.
    Triangle {
        vertices: [Vec3; 3],
    },
    /// The surface of the axis-aligned box between `min` and `max` (min < max on every
    /// axis).
    Box {
        min: Vec3,
        max: Vec3,
    },
    /// The triangles of a mesh file, transformed. Several objects may share one
    /// [`MeshFile`]: its geometry is then held once.
    Mesh(MeshObject),
}

/// A `mesh` object: its file, where the file's coordinates go, and how it is shaded.
#[derive(Clone, Debug, PartialEq)]
pub struct MeshObject {
    pub file: Arc<MeshFile>,
    /// The object's `transform` as written (the identity without one)...
    pub spec: TransformSpec,
    /// ... and as a map, p' = A·p + t.
    pub transform: Affine,
    /// `"shading": "smooth"`: interpolated vertex normals instead of the flat ones.
    pub smooth: bool,
}

impl Shape {
    /// Whether the shape is one of section 8's (triangle, box, mesh), which the farm
    /// does not render yet and the tracer traces through its own hierarchy.
    pub fn is_beyond_seed(&self) -> bool {
        matches!(
            self,
            Shape::Triangle { .. } | Shape::Box { .. } | Shape::Mesh(_)
        )
    }
}

/// The material chosen by a colour's 4th number (`special`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Material {
    /// `special` = 0.
    Matte,
    /// 0 < `special` ≤ 1: mirror reflection weighted by the coefficient, plus a highlight.
    Reflective(f64),
    /// `special` = 2: black and white unit squares in x and z.
    Checker,
}

/// Where the camera is, what it looks at, which way is up and how wide it sees.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CameraSpec {
    pub position: Vec3,
    pub look_at: Vec3,
    /// The world up vector (section 8; the seed's is 0 1 0).
    pub up: Vec3,
    /// The field of view across the shorter image side in degrees, if the scene gives
    /// one; without it the image plane is the seed's (k = 1 exactly).
    pub fov: Option<f64>,
}

impl CameraSpec {
    /// The seed's up axis.
    pub const WORLD_UP: Vec3 = Vec3::new(0.0, 1.0, 0.0);
}

impl Default for CameraSpec {
    fn default() -> Self {
        CameraSpec {
            position: Vec3::new(3.0, 1.5, -4.0),
            look_at: Vec3::ZERO,
            up: CameraSpec::WORLD_UP,
            fov: None,
        }
    }
}
