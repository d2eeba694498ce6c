//! A minimal 3-vector of `f64`.
//!
//! Only `+ - * /` and `sqrt` are used here: these are correctly rounded by IEEE 754 on
//! every platform, so a pixel computed on one worker equals the same pixel computed on
//! any other, bit for bit.

use std::ops::{Add, AddAssign, Div, Mul, Neg, Sub};

/// A point, a direction or an RGB colour.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Vec3 {
    pub x: f64,
    pub y: f64,
    pub z: f64,
}

impl Vec3 {
    pub const ZERO: Vec3 = Vec3::new(0.0, 0.0, 0.0);

    pub const fn new(x: f64, y: f64, z: f64) -> Self {
        Vec3 { x, y, z }
    }

    pub fn dot(self, o: Vec3) -> f64 {
        self.x * o.x + self.y * o.y + self.z * o.z
    }

    pub fn cross(self, o: Vec3) -> Vec3 {
        Vec3::new(
            self.y * o.z - self.z * o.y,
            self.z * o.x - self.x * o.z,
            self.x * o.y - self.y * o.x,
        )
    }

    pub fn length(self) -> f64 {
        self.dot(self).sqrt()
    }

    /// The unit vector along `self`; callers guarantee a non-zero length.
    pub fn normalize(self) -> Vec3 {
        self / self.length()
    }

    /// Component-wise product (colour filtering).
    pub fn hadamard(self, o: Vec3) -> Vec3 {
        Vec3::new(self.x * o.x, self.y * o.y, self.z * o.z)
    }

    pub fn is_finite(self) -> bool {
        self.x.is_finite() && self.y.is_finite() && self.z.is_finite()
    }
}

impl Add for Vec3 {
    type Output = Vec3;
    fn add(self, o: Vec3) -> Vec3 {
        Vec3::new(self.x + o.x, self.y + o.y, self.z + o.z)
    }
}

impl AddAssign for Vec3 {
    fn add_assign(&mut self, o: Vec3) {
        *self = *self + o;
    }
}

impl Sub for Vec3 {
    type Output = Vec3;
    fn sub(self, o: Vec3) -> Vec3 {
        Vec3::new(self.x - o.x, self.y - o.y, self.z - o.z)
    }
}

impl Mul<f64> for Vec3 {
    type Output = Vec3;
    fn mul(self, s: f64) -> Vec3 {
        Vec3::new(self.x * s, self.y * s, self.z * s)
    }
}

impl Neg for Vec3 {
    type Output = Vec3;
    fn neg(self) -> Vec3 {
        Vec3::new(-self.x, -self.y, -self.z)
    }
}

impl Div<f64> for Vec3 {
    type Output = Vec3;
    fn div(self, s: f64) -> Vec3 {
        Vec3::new(self.x / s, self.y / s, self.z / s)
    }
}

/// How many rays (or spheres) the packet code handles side by side.
pub(crate) const LANES: usize = 4;

/// Four `f64`s handled side by side. Every operation is the scalar one applied to each
/// lane, written as plain loops over a fixed-size array so that the compiler turns them
/// into SIMD instructions; each lane is bit-for-bit what the scalar code computes.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub(crate) struct F4(pub [f64; LANES]);

/// One boolean per lane, as all-ones or all-zeros bits like a SIMD comparison's result,
/// so that tests and selections compile to SIMD instructions too.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct M4(pub [u64; LANES]);

impl F4 {
    #[inline(always)]
    pub fn splat(v: f64) -> F4 {
        F4([v; LANES])
    }

    #[inline(always)]
    pub fn map(self, f: impl Fn(f64) -> f64) -> F4 {
        // Written out rather than `array::map`, which is not always inlined, and then
        // runs without the instruction set of its caller.
        let a = self.0;
        F4([f(a[0]), f(a[1]), f(a[2]), f(a[3])])
    }

    #[inline(always)]
    pub fn zip(self, o: F4, f: impl Fn(f64, f64) -> f64) -> F4 {
        F4(std::array::from_fn(|k| f(self.0[k], o.0[k])))
    }

    #[inline(always)]
    pub fn test(self, o: F4, f: impl Fn(f64, f64) -> bool) -> M4 {
        M4::from_fn(|k| f(self.0[k], o.0[k]))
    }

    #[inline(always)]
    pub fn sqrt(self) -> F4 {
        self.map(f64::sqrt)
    }

    /// Lane by lane `f64::min`: the smaller, or the other operand where one is NaN.
    #[inline(always)]
    pub fn min(self, o: F4) -> F4 {
        self.zip(o, f64::min)
    }

    #[inline(always)]
    pub fn gt(self, o: F4) -> M4 {
        self.test(o, |a, b| a > b)
    }

    #[inline(always)]
    pub fn ge(self, o: F4) -> M4 {
        self.test(o, |a, b| a >= b)
    }

    #[inline(always)]
    pub fn lt(self, o: F4) -> M4 {
        self.test(o, |a, b| a < b)
    }

    #[inline(always)]
    pub fn le(self, o: F4) -> M4 {
        self.test(o, |a, b| a <= b)
    }
}

impl M4 {
    pub const NONE: M4 = M4([0; LANES]);
    pub const ALL: M4 = M4([u64::MAX; LANES]);

    #[inline(always)]
    fn bits(b: bool) -> u64 {
        u64::from(b).wrapping_neg()
    }

    #[inline(always)]
    pub fn from_fn(f: impl Fn(usize) -> bool) -> M4 {
        M4(std::array::from_fn(|k| M4::bits(f(k))))
    }

    /// Lanes 0..n set.
    #[inline(always)]
    pub fn first(n: usize) -> M4 {
        M4::from_fn(|k| k < n)
    }

    #[inline(always)]
    pub fn get(self, k: usize) -> bool {
        self.0[k] != 0
    }

    /// Bit k set where lane k is.
    #[inline(always)]
    pub fn bitmask(self) -> u32 {
        (0..LANES).fold(0, |m, k| m | (((self.0[k] >> 63) as u32) << k))
    }

    #[inline(always)]
    pub fn any(self) -> bool {
        self.0.iter().fold(0, |a, &b| a | b) != 0
    }

    #[inline(always)]
    pub fn all(self) -> bool {
        self.0.iter().fold(u64::MAX, |a, &b| a & b) != 0
    }

    #[inline(always)]
    pub fn xor(self, o: M4) -> M4 {
        M4(std::array::from_fn(|k| self.0[k] ^ o.0[k]))
    }

    #[inline(always)]
    pub fn and(self, o: M4) -> M4 {
        M4(std::array::from_fn(|k| self.0[k] & o.0[k]))
    }

    #[inline(always)]
    pub fn or(self, o: M4) -> M4 {
        M4(std::array::from_fn(|k| self.0[k] | o.0[k]))
    }

    #[inline(always)]
    pub fn and_not(self, o: M4) -> M4 {
        M4(std::array::from_fn(|k| self.0[k] & !o.0[k]))
    }

    /// Lane by lane, `a` where the mask is set, else `b` (bit selection, so NaNs and
    /// signed zeros pass through unchanged).
    #[inline(always)]
    pub fn select(self, a: F4, b: F4) -> F4 {
        F4(std::array::from_fn(|k| {
            f64::from_bits((a.0[k].to_bits() & self.0[k]) | (b.0[k].to_bits() & !self.0[k]))
        }))
    }

    #[inline(always)]
    pub fn select3(self, a: V4, b: V4) -> V4 {
        V4 {
            x: self.select(a.x, b.x),
            y: self.select(a.y, b.y),
            z: self.select(a.z, b.z),
        }
    }
}

macro_rules! lane_op {
    ($trait:ident, $method:ident, $op:tt) => {
        impl $trait for F4 {
            type Output = F4;
            #[inline(always)]
            fn $method(self, o: F4) -> F4 {
                F4(std::array::from_fn(|k| self.0[k] $op o.0[k]))
            }
        }
        impl $trait<f64> for F4 {
            type Output = F4;
            #[inline(always)]
            fn $method(self, o: f64) -> F4 {
                let a = self.0;
                F4([a[0] $op o, a[1] $op o, a[2] $op o, a[3] $op o])
            }
        }
    };
}

lane_op!(Add, add, +);
lane_op!(Sub, sub, -);
lane_op!(Mul, mul, *);
lane_op!(Div, div, /);

impl Neg for F4 {
    type Output = F4;
    #[inline(always)]
    fn neg(self) -> F4 {
        self.map(|a| -a)
    }
}

/// Four 3-vectors in structure-of-arrays form: lane k is (x[k], y[k], z[k]). The
/// methods mirror [`Vec3`]'s with the same operations in the same order.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct V4 {
    pub x: F4,
    pub y: F4,
    pub z: F4,
}

impl V4 {
    #[inline(always)]
    pub fn splat(v: Vec3) -> V4 {
        V4 {
            x: F4::splat(v.x),
            y: F4::splat(v.y),
            z: F4::splat(v.z),
        }
    }

    #[cfg(test)]
    pub fn from_lanes(v: [Vec3; LANES]) -> V4 {
        V4 {
            x: F4(v.map(|v| v.x)),
            y: F4(v.map(|v| v.y)),
            z: F4(v.map(|v| v.z)),
        }
    }

    #[inline(always)]
    pub fn lane(&self, k: usize) -> Vec3 {
        Vec3::new(self.x.0[k], self.y.0[k], self.z.0[k])
    }

    #[inline(always)]
    pub fn set_lane(&mut self, k: usize, v: Vec3) {
        self.x.0[k] = v.x;
        self.y.0[k] = v.y;
        self.z.0[k] = v.z;
    }

    #[inline(always)]
    pub fn dot(self, o: V4) -> F4 {
        self.x * o.x + self.y * o.y + self.z * o.z
    }

    #[inline(always)]
    pub fn hadamard(self, o: V4) -> V4 {
        V4 {
            x: self.x * o.x,
            y: self.y * o.y,
            z: self.z * o.z,
        }
    }

    #[inline(always)]
    pub fn scale(self, s: F4) -> V4 {
        V4 {
            x: self.x * s,
            y: self.y * s,
            z: self.z * s,
        }
    }

    #[inline(always)]
    pub fn div(self, s: F4) -> V4 {
        V4 {
            x: self.x / s,
            y: self.y / s,
            z: self.z / s,
        }
    }
}

impl Add for V4 {
    type Output = V4;
    #[inline(always)]
    fn add(self, o: V4) -> V4 {
        V4 {
            x: self.x + o.x,
            y: self.y + o.y,
            z: self.z + o.z,
        }
    }
}

impl Sub for V4 {
    type Output = V4;
    #[inline(always)]
    fn sub(self, o: V4) -> V4 {
        V4 {
            x: self.x - o.x,
            y: self.y - o.y,
            z: self.z - o.z,
        }
    }
}

impl Neg for V4 {
    type Output = V4;
    #[inline(always)]
    fn neg(self) -> V4 {
        V4 {
            x: -self.x,
            y: -self.y,
            z: -self.z,
        }
    }
}

/// A divisor fixed in advance. When it is a power of two whose reciprocal is a normal
/// number, 1/d is exact, and y · (1/d) and y / d are the same real number rounded once:
/// the multiplication, much cheaper, gives the bits of the division for every y.
/// Otherwise it divides.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Divisor {
    value: f64,
    reciprocal: Option<f64>,
}

impl Divisor {
    pub fn new(value: f64) -> Self {
        const MANTISSA: u64 = (1 << 52) - 1;
        let inverse = 1.0 / value;
        let exact = value.is_normal() && inverse.is_normal() && value.to_bits() & MANTISSA == 0;
        Divisor {
            value,
            reciprocal: exact.then_some(inverse),
        }
    }

    /// A count of samples, k ≥ 1, as a divisor, without a division of its own when k
    /// is a power of two (2⁻ᵉ is built from its exponent bits).
    #[inline(always)]
    pub fn count(k: u32) -> Self {
        let reciprocal = k
            .is_power_of_two()
            .then(|| f64::from_bits(u64::from(1023 - k.trailing_zeros()) << 52));
        Divisor {
            value: f64::from(k),
            reciprocal,
        }
    }

    /// 1 / the divisor, when it is exact.
    pub fn reciprocal(self) -> Option<f64> {
        self.reciprocal
    }

    #[inline(always)]
    pub fn divide4(self, y: F4) -> F4 {
        match self.reciprocal {
            Some(r) => y * r,
            None => y / self.value,
        }
    }

    #[inline(always)]
    pub fn divide3(self, y: Vec3) -> Vec3 {
        match self.reciprocal {
            Some(r) => y * r,
            None => y / self.value,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Dividing through a [`Divisor`] gives the bits of the division, for powers of two
    /// (multiplied) and other divisors (divided), on normal, subnormal, huge, zero,
    /// infinite and NaN dividends.
    #[test]
    fn divisors_give_the_bits_of_the_division() {
        let mut state = 0x1234_5678_9ABC_DEF0_u64;
        let mut next = || {
            state = state
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            state
        };
        let divisors = [
            1.0,
            2.0,
            4.0,
            0.5,
            3.0,
            9.0,
            1024.0,
            0.1,
            1e-300,
            2f64.powi(-1022),
            2f64.powi(1023),
        ];
        for k in 1..=70u32 {
            let by_count = Divisor::count(k);
            let by_value = Divisor::new(f64::from(k));
            assert_eq!(by_count.reciprocal.is_some(), k.is_power_of_two(), "{k}");
            assert_eq!(by_count.reciprocal, by_value.reciprocal, "{k}");
        }
        for case in 0..200_000 {
            let d = if case % 2 == 0 {
                divisors[case % divisors.len()]
            } else {
                f64::from(next() as u32 % 70 + 1)
            };
            let y = match case % 7 {
                0 => f64::from_bits(next() & !(0x7FF << 52)),
                1 => [
                    0.0,
                    -0.0,
                    f64::INFINITY,
                    f64::NAN,
                    f64::MAX,
                    f64::MIN_POSITIVE,
                ][case % 6],
                _ => f64::from_bits(next()),
            };
            let got = Divisor::new(d).divide4(F4::splat(y)).0[0];
            let want = y / d;
            assert!(
                got.to_bits() == want.to_bits() || (got.is_nan() && want.is_nan()),
                "{y:e} / {d:e}: {got:e} against {want:e}"
            );
        }
    }
}
