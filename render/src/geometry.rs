//! Ray–surface intersection, robust at every scale without a fixed epsilon.
//!
//! Self-intersection is avoided by knowing which surface a ray leaves, not by nudging
//! its origin or by ignoring hits closer than some ε: a ray leaving a plane cannot meet
//! that plane again, and a ray leaving a sphere meets it again only at the quadratic's
//! other root, which is `-2 (p − c)·d` exactly (the product of the roots is 0 for an
//! origin on the sphere). Both facts hold whatever the scene's scale, so there is no
//! constant that is too large for a 1e-3 sphere or too small at coordinates of 1e5.
//!
//! For other spheres the quadratic is solved in the cancellation-free form of
//! *Ray Tracing Gems* ch. 7: the discriminant as r² − |f − (f·d)d|² instead of b² − 4ac,
//! and the smaller root as c/q instead of a difference of nearly equal numbers.

use crate::vec3::Vec3;

/// A sphere ready for intersection.
#[derive(Clone, Copy, Debug)]
pub(crate) struct SphereGeom {
    pub center: Vec3,
    pub radius: f64,
    pub radius2: f64,
}

/// A plane n̂·p = distance with n̂ of unit length.
#[derive(Clone, Copy, Debug)]
pub(crate) struct PlaneGeom {
    pub normal: Vec3,
    pub distance: f64,
}

impl SphereGeom {
    pub fn new(center: Vec3, radius: f64) -> Self {
        SphereGeom {
            center,
            radius,
            radius2: radius * radius,
        }
    }

    /// The nearest t > 0 where the ray `origin + t·dir` (|dir| = 1) meets the sphere.
    /// `leaving` says the origin lies on this sphere (the ray was spawned from it).
    #[inline]
    pub fn hit(&self, origin: Vec3, dir: Vec3, leaving: bool) -> Option<f64> {
        let f = origin - self.center;
        let b = f.dot(dir);
        if leaving {
            // Roots 0 and -2b: only the far wall, when the ray heads inside.
            let t = -2.0 * b;
            return (t > 0.0).then_some(t);
        }
        let c = f.dot(f) - self.radius2;
        if c > 0.0 && b >= 0.0 {
            // Outside and heading away: both roots are behind the origin.
            return None;
        }
        // Closest approach of the line to the centre, computed without cancellation.
        let l = f - dir * b;
        let disc = self.radius2 - l.dot(l);
        if disc < 0.0 {
            return None;
        }
        let root = disc.sqrt();
        // q and c/q are the two roots; q never suffers cancellation.
        let q = if b > 0.0 { -b - root } else { -b + root };
        if c > 0.0 {
            // Outside, heading towards the centre: both roots ahead, take the nearer.
            Some((c / q).min(q))
        } else if b > 0.0 {
            // Inside (or on the surface), heading away from the centre: q < 0 ≤ c/q.
            let t = c / q;
            (t > 0.0).then_some(t)
        } else {
            // Inside, heading towards the centre: c/q ≤ 0 < q (q = 0 only for a ray
            // tangent at its own origin, which is not a hit).
            (q > 0.0).then_some(q)
        }
    }

    /// The outward unit normal at a point of the surface.
    #[inline]
    pub fn normal_at(&self, p: Vec3) -> Vec3 {
        (p - self.center) / self.radius
    }
}

impl PlaneGeom {
    pub fn new(normal: Vec3, distance: f64) -> Self {
        PlaneGeom {
            normal: normal.normalize(),
            distance,
        }
    }

    /// The t > 0 where the ray meets the plane. A ray leaving this plane never meets it
    /// again, so callers do not test it at all.
    #[inline]
    pub fn hit(&self, origin: Vec3, dir: Vec3) -> Option<f64> {
        let denom = self.normal.dot(dir);
        if denom == 0.0 {
            return None;
        }
        let t = (self.distance - self.normal.dot(origin)) / denom;
        (t > 0.0 && t.is_finite()).then_some(t)
    }
}
