//! The pinhole camera of the scene format (section 2).

use crate::scene::CameraSpec;
use crate::settings::RenderSettings;
use crate::trig::fov_scale;
use crate::vec3::{Vec3, F4, V4};

/// The camera's orthonormal basis and the image geometry, computed once per render.
#[derive(Clone, Copy, Debug)]
pub struct Camera {
    position: Vec3,
    forward: Vec3,
    right: Vec3,
    up: Vec3,
    half_width: f64,
    half_height: f64,
    /// The shorter image side divided by k = 2·tan(fov/2): image-plane coordinates are
    /// pixels over it. Without a `fov`, k = 1 and this is the shorter side exactly, which
    /// spans the seed's field of view 2·atan(1/2).
    short_side: f64,
}

impl Camera {
    /// Builds the basis. The scene loader has already refused a camera that looks along
    /// the up axis, so the cross products here are non-zero.
    pub fn new(spec: &CameraSpec, settings: &RenderSettings) -> Self {
        let forward = (spec.look_at - spec.position).normalize();
        let right = spec.up.cross(forward).normalize();
        let up = forward.cross(right);
        let width = f64::from(settings.width);
        let height = f64::from(settings.height);
        Camera {
            position: spec.position,
            forward,
            right,
            up,
            half_width: width / 2.0,
            half_height: height / 2.0,
            short_side: match spec.fov {
                Some(fov) => width.min(height) / fov_scale(fov),
                None => width.min(height),
            },
        }
    }

    pub fn position(&self) -> Vec3 {
        self.position
    }

    /// The orthonormal basis (forward f, right r, up u) of section 2.
    pub(crate) fn basis(&self) -> (Vec3, Vec3, Vec3) {
        (self.forward, self.right, self.up)
    }

    /// The unit direction through the point (`px`, `py`) of the image plane, measured in
    /// pixels from the top-left corner (pixel column i with offset sx is `i + sx`).
    pub fn direction(&self, px: f64, py: f64) -> Vec3 {
        let x = (px - self.half_width) / self.short_side;
        let y = (self.half_height - py) / self.short_side;
        (self.forward + self.right * x + self.up * y).normalize()
    }

    /// [`Camera::direction`] for four image points at once, lane by lane: the same
    /// operations in the same order, so each lane has the bits of the scalar direction,
    /// but one SIMD square root and division serve four rays.
    #[inline(always)]
    pub(crate) fn directions(&self, px: F4, py: F4) -> V4 {
        self.directions_at(self.plane_x(px), self.plane_y(py))
    }

    /// The image-plane coordinate x of [`Camera::direction`] for four columns `px`.
    #[inline(always)]
    pub(crate) fn plane_x(&self, px: F4) -> F4 {
        (px - F4::splat(self.half_width)) / F4::splat(self.short_side)
    }

    /// The image-plane coordinate y of [`Camera::direction`] for four rows `py`.
    #[inline(always)]
    pub(crate) fn plane_y(&self, py: F4) -> F4 {
        (F4::splat(self.half_height) - py) / F4::splat(self.short_side)
    }

    /// The unit directions through the image-plane points (`x`, `y`), as
    /// [`Camera::direction`] computes them.
    #[inline(always)]
    pub(crate) fn directions_at(&self, x: F4, y: F4) -> V4 {
        let v =
            V4::splat(self.forward) + V4::splat(self.right).scale(x) + V4::splat(self.up).scale(y);
        v.div(v.dot(v).sqrt())
    }
}
