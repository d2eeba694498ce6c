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

use crate::vec3::{Vec3, F4, M4, V4};

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
        if leaving {
            // Roots 0 and -2b: only the far wall, when the ray heads inside.
            let t = -2.0 * f.dot(dir);
            return (t > 0.0).then_some(t);
        }
        Self::hit_offset(f, f.dot(f) - self.radius2, self.radius2, dir)
    }

    /// [`SphereGeom::hit`] for a ray that does not leave the sphere, given
    /// f = origin − centre and c = f·f − r², which callers may compute once for many
    /// rays from one origin.
    #[inline]
    pub fn hit_offset(f: Vec3, c: f64, radius2: f64, dir: Vec3) -> Option<f64> {
        let b = f.dot(dir);
        if c > 0.0 && b >= 0.0 {
            // Outside and heading away: both roots are behind the origin.
            return None;
        }
        // Closest approach of the line to the centre, computed without cancellation.
        let l = f - dir * b;
        let disc = radius2 - l.dot(l);
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

/// Lane by lane, [`SphereGeom::hit`] without branches, so that a loop over four spheres
/// or over four rays becomes SIMD code: `f` = origin − centre, `c` = f·f − r², `d` the
/// unit direction, `leaving` where the ray leaves that sphere. Every lane performs the
/// same floating-point operations in the same order as the scalar test, so a hit has
/// the same bits; a miss is NaN (which no comparison accepts, exactly as `None`).
#[inline(always)]
pub(crate) fn sphere_hits(f: V4, c: F4, r2: F4, d: V4, leaving: M4) -> F4 {
    let zero = F4::splat(0.0);
    let nan = F4::splat(f64::NAN);
    let b = f.dot(d);
    let leave_t = b.map(|b| -2.0 * b);
    let leave = leaving.and(leave_t.gt(zero)).select(leave_t, nan);
    let l = f - d.scale(b);
    let disc = r2 - l.dot(l);
    let outside = c.gt(zero);
    let miss = outside.and(b.ge(zero)).or(disc.lt(zero));
    let alive = M4::ALL.and_not(leaving).and_not(miss);
    if !alive.any() {
        // Most tests end here: no square root, no division.
        return leave;
    }
    let root = disc.sqrt();
    let away = b.gt(zero);
    let neg_b = -b;
    let q = away.select(neg_b - root, neg_b + root);
    let near = c / q;
    let t = outside.select(near.min(q), away.select(near, q));
    alive.and(outside.or(t.gt(zero))).select(t, leave)
}

/// Lane by lane, [`PlaneGeom::hit`] given `num` = distance − n̂·origin and
/// `denom` = n̂·dir: the same division and the same checks, NaN for a miss.
#[inline(always)]
pub(crate) fn plane_hits(num: F4, denom: F4) -> F4 {
    let t = num / denom;
    // `t <= f64::MAX` is `t < ∞` (both refuse NaN), but written this way the two tests
    // stay SIMD comparisons: a bound of ∞ turns them into a test of the number's class,
    // which the compiler evaluates lane by lane in integer code.
    let hit = t.gt(F4::splat(0.0)).and(t.le(F4::splat(f64::MAX)));
    hit.select(t, F4::splat(f64::NAN))
}

/// Whether [`PlaneGeom::hit`] can return a hit at all for `num` / `denom`: a positive
/// quotient needs both non-zero and of one sign. A shadow ray heading away from a
/// plane is thus rejected without a division.
#[inline(always)]
pub(crate) fn plane_ahead(num: f64, denom: f64) -> bool {
    (num > 0.0 && denom > 0.0) || (num < 0.0 && denom < 0.0)
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::vec3::LANES;

    /// The tests' generator ([`crate::test_rng::Mix`]), drawing in [-1, 1).
    pub(crate) struct Mix(crate::test_rng::Mix);

    impl Mix {
        pub(crate) fn seeded(seed: u64) -> Self {
            Mix(crate::test_rng::Mix(seed))
        }

        pub(crate) fn next(&mut self) -> u64 {
            self.0.next()
        }

        /// Uniform in [-1, 1).
        pub(crate) fn unit(&mut self) -> f64 {
            (self.next() >> 11) as f64 / (1u64 << 52) as f64 - 1.0
        }

        pub(crate) fn vec(&mut self) -> Vec3 {
            Vec3::new(self.unit(), self.unit(), self.unit())
        }
    }

    fn same(a: Option<f64>, b: f64) -> bool {
        match a {
            Some(a) if !a.is_nan() => a.to_bits() == b.to_bits(),
            _ => b.is_nan(),
        }
    }

    #[test]
    fn lane_sphere_test_equals_the_scalar_one() {
        let mut rng = Mix::seeded(7);
        for case in 0..200_000 {
            let scale = [1e-3, 1.0, 1e3, 1e5][case % 4];
            let s = SphereGeom::new(rng.vec() * scale, scale * (rng.unit().abs() + 1e-3));
            // Four rays: from the sphere's surface (leaving it), near it, or anywhere;
            // aimed at it (grazing or through the centre) or anywhere.
            let rays: [(Vec3, Vec3, bool); LANES] = std::array::from_fn(|k| {
                let leaving = rng.next().is_multiple_of(3);
                let origin = if leaving {
                    s.center + rng.vec().normalize() * s.radius
                } else {
                    rng.vec() * (3.0 * scale)
                };
                let dir = if k % 2 == 0 {
                    let aim =
                        s.center + rng.vec().normalize() * (s.radius * (1.0 + rng.unit() * 1e-9));
                    (aim - origin).normalize()
                } else {
                    rng.vec().normalize()
                };
                (origin, dir, leaving)
            });
            let f = V4::from_lanes(rays.map(|(o, _, _)| o)) - V4::splat(s.center);
            let radius2 = F4::splat(s.radius2);
            let d = V4::from_lanes(rays.map(|(_, d, _)| d));
            let leaving = M4::from_fn(|k| rays[k].2);
            let lanes = sphere_hits(f, f.dot(f) - radius2, radius2, d, leaving);
            for (k, &(origin, dir, leaving)) in rays.iter().enumerate() {
                let scalar = s.hit(origin, dir, leaving);
                assert!(
                    same(scalar, lanes.0[k]),
                    "case {case} lane {k}: {scalar:?} vs {}",
                    lanes.0[k]
                );
            }
        }
    }

    #[test]
    fn lane_plane_test_equals_the_scalar_one() {
        let mut rng = Mix::seeded(11);
        for case in 0..100_000 {
            let plane = PlaneGeom::new(rng.vec(), rng.unit() * 10.0);
            let origin = rng.vec() * 20.0;
            let mut dir = rng.vec().normalize();
            if case % 5 == 0 {
                // Parallel to the plane.
                dir = (dir - plane.normal * plane.normal.dot(dir)).normalize();
            }
            let num = plane.distance - plane.normal.dot(origin);
            let denom = plane.normal.dot(dir);
            let t = plane_hits(F4::splat(num), F4::splat(denom));
            let scalar = plane.hit(origin, dir);
            assert!(same(scalar, t.0[0]), "case {case}");
            if scalar.is_some() {
                assert!(plane_ahead(num, denom));
            }
        }
    }
}
