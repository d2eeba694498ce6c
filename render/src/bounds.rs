//! Axis-aligned bounds in double precision and the slab test that never misses what it
//! bounds.
//!
//! The test computes each slab's entry and exit distances with one subtraction and one
//! multiplication by the reciprocal direction, each rounded; the exit distance is then
//! enlarged by 2γ₃ (γₙ = nε / (1 − nε)), which covers those roundings, so a ray that
//! meets a box in exact arithmetic also meets it here (Pharr, Jakob and Humphreys,
//! *Physically Based Rendering*, 4th ed., §6.1.2). A direction component of zero gives
//! infinite reciprocals; a NaN from 0·∞ (the ray in a slab's plane) leaves that slab
//! out, which can only widen the interval.

use crate::vec3::Vec3;

/// γₙ = nε / (1 − nε), ε = 2⁻⁵³: bounds the relative error of n roundings.
pub(crate) const fn gamma(n: u32) -> f64 {
    let e = f64::EPSILON * 0.5 * n as f64;
    e / (1.0 - e)
}

#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Bounds {
    pub lo: [f64; 3],
    pub hi: [f64; 3],
}

impl Bounds {
    pub const EMPTY: Bounds = Bounds {
        lo: [f64::INFINITY; 3],
        hi: [f64::NEG_INFINITY; 3],
    };

    pub fn of_point(p: Vec3) -> Bounds {
        let p = [p.x, p.y, p.z];
        Bounds { lo: p, hi: p }
    }

    pub fn grow(&mut self, p: Vec3) {
        self.grow_by([p.x, p.y, p.z]);
    }

    /// Grows to hold point `p`. Comparisons rather than `f64::min`, whose care for NaNs
    /// costs the hierarchy's build dearly: a NaN coordinate is left out either way.
    #[inline(always)]
    pub fn grow_by(&mut self, p: [f64; 3]) {
        for (k, &x) in p.iter().enumerate() {
            self.lo[k] = if x < self.lo[k] { x } else { self.lo[k] };
            self.hi[k] = if x > self.hi[k] { x } else { self.hi[k] };
        }
    }

    /// The bounds holding both (comparisons, as in [`Bounds::grow_by`]).
    #[inline(always)]
    pub fn union(&self, o: &Bounds) -> Bounds {
        Bounds {
            lo: std::array::from_fn(|k| {
                if o.lo[k] < self.lo[k] {
                    o.lo[k]
                } else {
                    self.lo[k]
                }
            }),
            hi: std::array::from_fn(|k| {
                if o.hi[k] > self.hi[k] {
                    o.hi[k]
                } else {
                    self.hi[k]
                }
            }),
        }
    }

    /// The bounds widened by `margin` on every side.
    pub fn widened(&self, margin: f64) -> Bounds {
        Bounds {
            lo: self.lo.map(|x| x - margin),
            hi: self.hi.map(|x| x + margin),
        }
    }

    pub fn centroid(&self, axis: usize) -> f64 {
        0.5 * (self.lo[axis] + self.hi[axis])
    }

    pub fn area(&self) -> f64 {
        let d: [f64; 3] = std::array::from_fn(|k| (self.hi[k] - self.lo[k]).max(0.0));
        d[0] * d[1] + d[1] * d[2] + d[2] * d[0]
    }

    /// The largest magnitude of any coordinate.
    pub fn magnitude(&self) -> f64 {
        self.lo
            .iter()
            .chain(&self.hi)
            .fold(0.0f64, |m, x| m.max(x.abs()))
    }

    /// The eight corners.
    pub fn corners(&self) -> [[f64; 3]; 8] {
        std::array::from_fn(|i| {
            std::array::from_fn(|k| {
                if i >> k & 1 == 0 {
                    self.lo[k]
                } else {
                    self.hi[k]
                }
            })
        })
    }
}

/// A ray prepared for slab tests: its origin and reciprocal direction.
#[derive(Clone, Copy, Debug)]
pub(crate) struct SlabRay {
    pub origin: [f64; 3],
    pub inv: [f64; 3],
}

/// 1 + 2γ₃, by which slab exit distances are enlarged.
pub(crate) const EXIT_SCALE: f64 = 1.0 + 2.0 * gamma(3);

impl SlabRay {
    pub fn new(origin: Vec3, dir: Vec3) -> Self {
        SlabRay {
            origin: [origin.x, origin.y, origin.z],
            inv: [1.0 / dir.x, 1.0 / dir.y, 1.0 / dir.z],
        }
    }

    /// The part of [0, `t_max`] where the ray is inside `b` widened by `margin`, if
    /// any: conservative, so the interval holds every point of that box on the ray.
    /// (The traversals test four boxes at once with the same operations:
    /// [`crate::hierarchy::WideRay::enter`]; this one is their reference in tests.)
    #[cfg(test)]
    pub fn enter(&self, b: &Bounds, margin: f64, t_max: f64) -> Option<(f64, f64)> {
        let mut t0 = 0.0f64;
        let mut t1 = t_max;
        for k in 0..3 {
            let mut near = (b.lo[k] - margin - self.origin[k]) * self.inv[k];
            let mut far = (b.hi[k] + margin - self.origin[k]) * self.inv[k];
            if near > far {
                std::mem::swap(&mut near, &mut far);
            }
            far *= EXIT_SCALE;
            if near > t0 {
                t0 = near;
            }
            if far < t1 {
                t1 = far;
            }
            if t0 > t1 {
                return None;
            }
        }
        Some((t0, t1))
    }
}
