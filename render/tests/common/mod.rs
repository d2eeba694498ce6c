//! What the render crate's integration tests share.

// Each test file uses its own part of this module.
#![allow(dead_code)]

use render::Vec3;

/// A small deterministic generator (SplitMix64), so that one proptest value seeds a
/// whole soup and its rays.
pub struct Mix(pub u64);

impl Mix {
    pub fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in [0, 1).
    pub fn unit(&mut self) -> f64 {
        (self.next() >> 11) as f64 / (1u64 << 53) as f64
    }

    /// Uniform in [-1, 1).
    pub fn signed(&mut self) -> f64 {
        2.0 * self.unit() - 1.0
    }

    pub fn below(&mut self, n: usize) -> usize {
        (self.next() % n as u64) as usize
    }

    pub fn vec(&mut self) -> Vec3 {
        Vec3::new(self.signed(), self.signed(), self.signed())
    }

    pub fn direction(&mut self) -> Vec3 {
        loop {
            let v = self.vec();
            let l = v.dot(v);
            if l > 1e-6 && l <= 1.0 {
                return v.normalize();
            }
        }
    }

    /// A direction along an axis, exactly: zero components stress the box test.
    pub fn axis(&mut self) -> Vec3 {
        let s = if self.next() & 1 == 0 { 1.0 } else { -1.0 };
        match self.below(3) {
            0 => Vec3::new(s, 0.0, 0.0),
            1 => Vec3::new(0.0, s, 0.0),
            _ => Vec3::new(0.0, 0.0, s),
        }
    }
}
