//! A small deterministic generator for the tests of every layer: the random scenes of
//! the tracer's tests, and the rays and boxes of the hierarchies' and shapes' tests.
//! It sits below every module whose tests use it, so that no test reaches up the
//! crate's layering for it.

use crate::vec3::Vec3;

/// SplitMix64, for reproducible random scenes.
pub(crate) struct Mix(pub(crate) u64);

impl Mix {
    pub(crate) fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    pub(crate) fn unit(&mut self) -> f64 {
        (self.next() >> 11) as f64 / (1u64 << 53) as f64
    }

    pub(crate) fn vec(&mut self, scale: f64) -> Vec3 {
        let mut c = || (2.0 * self.unit() - 1.0) * scale;
        Vec3::new(c(), c(), c())
    }
}
