//! The rays of the integrator, alone and in packets of four, and where a ray sits on
//! its reflection path.

use crate::vec3::{Vec3, M4, V4};

/// Marks a ray that leaves no surface (a camera ray); no object has this index.
pub(crate) const FROM_CAMERA: u32 = u32::MAX;

/// A reflection path whose weight (the product of its `special` factors) is below this
/// contributes less than a quarter of an 8-bit level, so it is not traced (section 5,
/// step 4 allows it).
const MIN_PATH_WEIGHT: f64 = 1.0 / 1024.0;

/// A ray `origin + t·dir` (|dir| = 1) leaving object `from` ([`FROM_CAMERA`] for a
/// camera ray): the nearest-hit search skips that object, or for a sphere tests only its
/// far wall.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Ray {
    pub origin: Vec3,
    pub dir: Vec3,
    pub from: u32,
}

impl Ray {
    /// A camera ray from `eye` along `dir`.
    #[inline(always)]
    pub fn camera(eye: Vec3, dir: Vec3) -> Ray {
        Ray {
            origin: eye,
            dir,
            from: FROM_CAMERA,
        }
    }

    /// The point at distance `t`.
    #[inline(always)]
    pub fn at(&self, t: f64) -> Vec3 {
        self.origin + self.dir * t
    }
}

/// Up to four rays that all leave the same object (or the camera), traced together: the
/// lanes of `active` hold real rays, the others are ignored.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Packet {
    pub origin: V4,
    pub dir: V4,
    pub from: u32,
    pub active: M4,
}

impl Packet {
    /// The ray of lane `k`.
    #[inline(always)]
    pub fn lane(&self, k: usize) -> Ray {
        Ray {
            origin: self.origin.lane(k),
            dir: self.dir.lane(k),
            from: self.from,
        }
    }

    /// The same rays with only the lanes of `active` live.
    #[inline(always)]
    pub fn with_active(self, active: M4) -> Packet {
        Packet { active, ..self }
    }
}

/// Where a ray sits on its reflection path: its reflection depth, and its weight, the
/// product of the `special` factors that scale its contribution to the pixel.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Path {
    pub depth: u32,
    pub weight: f64,
}

impl Path {
    /// A camera ray's path.
    pub const CAMERA: Path = Path {
        depth: 0,
        weight: 1.0,
    };

    /// The path of the mirror reflection off a surface of coefficient `special`, if it
    /// is traced at all: within `max_depth` and heavy enough to matter.
    #[inline(always)]
    pub fn reflected(self, special: f64, max_depth: u32) -> Option<Path> {
        let weight = self.weight * special;
        (special > 0.0 && self.depth < max_depth && weight >= MIN_PATH_WEIGHT).then_some(Path {
            depth: self.depth + 1,
            weight,
        })
    }
}
