//! The watertight ray–triangle test of Woop, Benthin and Wald ("Watertight
//! Ray/Triangle Intersection", JCGT 2(1), 2013), in double precision, with the
//! conservative bound on the distance of Pharr, Jakob and Humphreys (*Physically Based
//! Rendering*, 4th ed., §6.5.3).
//!
//! The ray is made the +z axis of a sheared frame: its largest direction component
//! becomes z, and each vertex, relative to the origin, is sheared so that the ray runs
//! along z. The three edge functions are then 2-D cross products of the sheared
//! vertices, each computed from its two vertices alone, by the same operations whichever
//! triangle asks: two triangles sharing an edge compute the same value for it with
//! opposite signs, so a ray that meets the edge meets one of them (or both), never
//! neither. A vertex's sheared coordinates depend on the vertex and the ray only, so
//! the same holds at a shared vertex.
//!
//! The hit's distance is kept only if it exceeds the bound on its rounding error: a
//! ray leaving a surface does not meet a neighbouring triangle at a distance that is
//! only rounding.

use crate::bounds::gamma;
use crate::vec3::{Vec3, F4, V4};

/// A hit of a triangle: distance and barycentric coordinates (b0 + b1 + b2 = 1).
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct TriangleHit {
    pub t: f64,
    pub b: [f64; 3],
}

/// A ray set up for the test: the permutation and shear of its frame.
#[derive(Clone, Copy, Debug)]
pub(crate) struct ShearedRay {
    origin: Vec3,
    kx: usize,
    ky: usize,
    kz: usize,
    sx: f64,
    sy: f64,
    sz: f64,
}

fn get(v: Vec3, k: usize) -> f64 {
    match k {
        0 => v.x,
        1 => v.y,
        _ => v.z,
    }
}

impl ShearedRay {
    pub fn new(origin: Vec3, dir: Vec3) -> Self {
        let a = [dir.x.abs(), dir.y.abs(), dir.z.abs()];
        // The largest component (the first of equal ones).
        let kz = if a[0] >= a[1] && a[0] >= a[2] {
            0
        } else if a[1] >= a[2] {
            1
        } else {
            2
        };
        let kx = (kz + 1) % 3;
        let ky = (kx + 1) % 3;
        let dz = get(dir, kz);
        ShearedRay {
            origin,
            kx,
            ky,
            kz,
            sx: -get(dir, kx) / dz,
            sy: -get(dir, ky) / dz,
            sz: 1.0 / dz,
        }
    }

    /// The axes that become x, y and z of the ray's frame.
    pub fn axes(&self) -> (usize, usize, usize) {
        (self.kx, self.ky, self.kz)
    }

    /// The shear: x and y gain sx·z and sy·z, z is scaled by sz.
    pub fn shear(&self) -> (f64, f64, f64) {
        (self.sx, self.sy, self.sz)
    }

    /// A vertex in the ray's frame: sheared x and y, unscaled z.
    #[inline(always)]
    fn frame(&self, p: Vec3) -> [f64; 3] {
        let q = p - self.origin;
        let (x, y, z) = (get(q, self.kx), get(q, self.ky), get(q, self.kz));
        [x + self.sx * z, y + self.sy * z, z]
    }

    /// Four vertices in the ray's frame, lane by lane as [`ShearedRay::frame`].
    #[inline(always)]
    pub fn frame4(&self, p: V4) -> [F4; 3] {
        let q = [
            p.x - F4::splat(self.origin.x),
            p.y - F4::splat(self.origin.y),
            p.z - F4::splat(self.origin.z),
        ];
        let (x, y, z) = (q[self.kx], q[self.ky], q[self.kz]);
        [x + z * self.sx, y + z * self.sy, z]
    }

    /// The hit of triangle (p0, p1, p2) at a distance in (0, `t_max`], if any.
    /// Degenerate triangles are never hit.
    #[inline(always)]
    pub fn hit(&self, p0: Vec3, p1: Vec3, p2: Vec3, t_max: f64) -> Option<TriangleHit> {
        let a = self.frame(p0);
        let b = self.frame(p1);
        let c = self.frame(p2);
        let e0 = b[0] * c[1] - b[1] * c[0];
        let e1 = c[0] * a[1] - c[1] * a[0];
        let e2 = a[0] * b[1] - a[1] * b[0];
        if (e0 < 0.0 || e1 < 0.0 || e2 < 0.0) && (e0 > 0.0 || e1 > 0.0 || e2 > 0.0) {
            return None;
        }
        let det = e0 + e1 + e2;
        if det == 0.0 || !det.is_finite() {
            return None;
        }
        let (az, bz, cz) = (a[2] * self.sz, b[2] * self.sz, c[2] * self.sz);
        let t_scaled = e0 * az + e1 * bz + e2 * cz;
        if det < 0.0 && (t_scaled >= 0.0 || t_scaled < t_max * det) {
            return None;
        }
        if det > 0.0 && (t_scaled <= 0.0 || t_scaled > t_max * det) {
            return None;
        }
        let inv_det = 1.0 / det;
        let t = t_scaled * inv_det;
        #[expect(
            clippy::neg_cmp_op_on_partial_ord,
            reason = "a NaN distance must be refused too"
        )]
        if !(t <= t_max) {
            return None;
        }
        // The distance must exceed its own error bound.
        let max_z = az.abs().max(bz.abs()).max(cz.abs());
        let delta_z = gamma(3) * max_z;
        let max_x = a[0].abs().max(b[0].abs()).max(c[0].abs());
        let max_y = a[1].abs().max(b[1].abs()).max(c[1].abs());
        let delta_x = gamma(5) * (max_x + max_z);
        let delta_y = gamma(5) * (max_y + max_z);
        let delta_e = 2.0 * (gamma(2) * max_x * max_y + delta_y * max_x + delta_x * max_y);
        let max_e = e0.abs().max(e1.abs()).max(e2.abs());
        let delta_t =
            3.0 * (gamma(3) * max_e * max_z + delta_e * max_z + delta_z * max_e) * inv_det.abs();
        if t <= delta_t {
            return None;
        }
        Some(TriangleHit {
            t,
            b: [e0 * inv_det, e1 * inv_det, e2 * inv_det],
        })
    }
}

/// The point of a triangle at barycentric coordinates `b`, and a bound on each of its
/// coordinates' rounding errors.
#[inline(always)]
pub(crate) fn point_at(p: [Vec3; 3], b: [f64; 3]) -> (Vec3, Vec3) {
    let terms = [p[0] * b[0], p[1] * b[1], p[2] * b[2]];
    let point = terms[0] + terms[1] + terms[2];
    let abs = |v: Vec3| Vec3::new(v.x.abs(), v.y.abs(), v.z.abs());
    let error = (abs(terms[0]) + abs(terms[1]) + abs(terms[2])) * gamma(7);
    (point, error)
}

/// The origin for a ray leaving a surface at `p` (with rounding errors up to `error`
/// per coordinate, geometric normal `n`) in direction `dir`: moved along the normal to
/// `dir`'s side by more than the error, and each coordinate rounded further away, so
/// that the origin is certainly on that side of the surface.
#[inline(always)]
pub(crate) fn spawn_origin(p: Vec3, error: Vec3, n: Vec3, dir: Vec3) -> Vec3 {
    let d = n.x.abs() * error.x + n.y.abs() * error.y + n.z.abs() * error.z;
    let mut offset = n * d;
    if dir.dot(n) < 0.0 {
        offset = -offset;
    }
    let moved = p + offset;
    let away = |x: f64, o: f64| {
        if o > 0.0 {
            x.next_up()
        } else if o < 0.0 {
            x.next_down()
        } else {
            x
        }
    };
    Vec3::new(
        away(moved.x, offset.x),
        away(moved.y, offset.y),
        away(moved.z, offset.z),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_ray_through_the_middle_hits_with_its_barycentrics() {
        let ray = ShearedRay::new(Vec3::new(0.25, 0.25, -1.0), Vec3::new(0.0, 0.0, 1.0));
        let hit = ray
            .hit(
                Vec3::new(0.0, 0.0, 0.0),
                Vec3::new(1.0, 0.0, 0.0),
                Vec3::new(0.0, 1.0, 0.0),
                f64::INFINITY,
            )
            .unwrap();
        assert_eq!(hit.t, 1.0);
        assert_eq!(hit.b, [0.5, 0.25, 0.25]);
        // Either winding, and not beyond t_max.
        assert!(ray
            .hit(
                Vec3::new(0.0, 0.0, 0.0),
                Vec3::new(0.0, 1.0, 0.0),
                Vec3::new(1.0, 0.0, 0.0),
                1.0
            )
            .is_some());
        assert!(ray
            .hit(
                Vec3::new(0.0, 0.0, 0.0),
                Vec3::new(0.0, 1.0, 0.0),
                Vec3::new(1.0, 0.0, 0.0),
                0.5
            )
            .is_none());
    }

    #[test]
    fn degenerate_and_behind_are_missed() {
        let ray = ShearedRay::new(Vec3::new(0.25, 0.0, -1.0), Vec3::new(0.0, 0.0, 1.0));
        let line = [
            Vec3::ZERO,
            Vec3::new(1.0, 0.0, 0.0),
            Vec3::new(2.0, 0.0, 0.0),
        ];
        assert!(ray.hit(line[0], line[1], line[2], f64::INFINITY).is_none());
        let back = ShearedRay::new(Vec3::new(0.25, 0.25, 1.0), Vec3::new(0.0, 0.0, 1.0));
        assert!(back
            .hit(
                Vec3::ZERO,
                Vec3::new(1.0, 0.0, 0.0),
                Vec3::new(0.0, 1.0, 0.0),
                f64::INFINITY
            )
            .is_none());
    }
}
