//! Section 5's shading arithmetic that is not geometry: the checkerboard, the
//! highlight's power, the clip of light above white, and section 6's conversion to
//! bytes; each with a lane version that performs the same operations in the same order.

use crate::vec3::{Vec3, F4, M4, V4};

/// Black and white unit squares in x and z: white where floor(x) + floor(z) is odd.
pub(super) fn checker(p: Vec3) -> Vec3 {
    if checker_white(p) {
        Vec3::new(1.0, 1.0, 1.0)
    } else {
        Vec3::ZERO
    }
}

/// Whether the checkerboard is white at `p`.
#[inline(always)]
fn checker_white(p: Vec3) -> bool {
    floor_to_int(p.x).wrapping_add(floor_to_int(p.z)) & 1 == 1
}

/// [`checker_white`] for four points at once. Where |x| and |z| are below 2⁵¹ (always,
/// but for absurd coordinates), the parities of ⌊x⌋ and ⌊z⌋ come from SIMD additions and
/// comparisons ([`floor_odd`]); otherwise each lane takes the scalar path, which gives
/// the same answer.
#[inline(always)]
pub(super) fn checker_white_lanes(p: V4) -> M4 {
    let limit = F4::splat(FLOOR_PARITY_LIMIT);
    let small = p.x.map(f64::abs).lt(limit).and(p.z.map(f64::abs).lt(limit));
    if !small.all() {
        return M4::from_fn(|k| checker_white(p.lane(k)));
    }
    floor_odd(p.x).xor(floor_odd(p.z))
}

/// Lane by lane, whether ⌊x⌋ is odd, for |x| < 2⁵¹, with operations that vectorise
/// (AVX2 has no 64-bit arithmetic shift, hence the subtraction). y = x + 1.5·2⁵² lies
/// in [2⁵², 2⁵³), where the spacing of doubles is 1, so it is x rounded to the nearest
/// integer r plus an even constant, exactly: its lowest bit is r's parity, and
/// y − 1.5·2⁵² is r exactly. ⌊x⌋ is r, or r − 1 when r > x, which flips the parity.
#[inline(always)]
fn floor_odd(x: F4) -> M4 {
    let shift = F4::splat(FLOOR_PARITY_SHIFT);
    let y = x + shift;
    let r = y - shift;
    let odd = M4(y.0.map(|y| 0u64.wrapping_sub(y.to_bits() & 1)));
    odd.xor(r.gt(x))
}

/// 1.5 · 2⁵², the shift of [`floor_odd`].
const FLOOR_PARITY_SHIFT: f64 = 6_755_399_441_055_744.0;

/// The bound on |x| below which [`floor_odd`] is exact: 2⁵¹.
const FLOOR_PARITY_LIMIT: f64 = 2_251_799_813_685_248.0;

/// ⌊x⌋ as an integer, without a call into the C library. Beyond ±2⁶³ the conversion
/// saturates, and below −2⁶³ the correction wraps around to `i64::MAX`: only the
/// parity is used, and it is the same in every build (a plain `t - 1` would panic
/// there in a debug build and wrap in a release build).
fn floor_to_int(x: f64) -> i64 {
    let t = x as i64;
    if (t as f64) > x {
        t.wrapping_sub(1)
    } else {
        t
    }
}

/// x¹⁰ by repeated multiplication, bit-exact on every platform (unlike `powf`).
pub(super) fn pow10(x: f64) -> f64 {
    let x2 = x * x;
    let x4 = x2 * x2;
    let x8 = x4 * x4;
    x8 * x2
}

/// Section 5, step 6: light above white (r + g + b > 3) spills into every channel in
/// proportion, then each channel is clamped to [0, 1].
pub(super) fn clip(c: Vec3) -> Vec3 {
    let sum = c.x + c.y + c.z;
    let c = if sum > 3.0 {
        let excess = sum - 3.0;
        Vec3::new(
            c.x + excess * c.x / sum,
            c.y + excess * c.y / sum,
            c.z + excess * c.z / sum,
        )
    } else {
        c
    };
    Vec3::new(
        c.x.clamp(0.0, 1.0),
        c.y.clamp(0.0, 1.0),
        c.z.clamp(0.0, 1.0),
    )
}

/// [`clip`] lane by lane, with the same operations in the same order. The spill into
/// other channels (and its divisions) is computed only when some lane is above white.
#[inline(always)]
pub(super) fn clip_lanes(c: V4) -> V4 {
    let sum = c.x + c.y + c.z;
    let three = F4::splat(3.0);
    let over = sum.gt(three);
    let c = if over.any() {
        let excess = sum - three;
        let spill = V4 {
            x: c.x + excess * c.x / sum,
            y: c.y + excess * c.y / sum,
            z: c.z + excess * c.z / sum,
        };
        over.select3(spill, c)
    } else {
        c
    };
    V4 {
        x: clamp_unit(c.x),
        y: clamp_unit(c.y),
        z: clamp_unit(c.z),
    }
}

/// Lane by lane `f64::clamp(x, 0, 1)`: NaN and −0 pass through unchanged.
#[inline(always)]
fn clamp_unit(x: F4) -> F4 {
    let (zero, one) = (F4::splat(0.0), F4::splat(1.0));
    let x = x.lt(zero).select(zero, x);
    x.gt(one).select(one, x)
}

/// Section 6: round(clamp(v, 0, 1) · 255).
#[inline(always)]
pub(crate) fn to_byte(v: f64) -> u8 {
    // round() halves away from zero; for x in [0, 255] that is trunc, plus one when the
    // (exact) fractional part is at least one half.
    let x = v.clamp(0.0, 1.0) * 255.0;
    let t = x as u8;
    if x - f64::from(t) >= 0.5 {
        t + 1
    } else {
        t
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_rng::Mix;
    use crate::vec3::LANES;

    /// The SIMD checker and clip agree with the scalar ones, at integers, halves (where
    /// rounding to nearest ties), signed zeros, near and beyond 2⁵¹ and on random points.
    #[test]
    fn lane_checker_and_clip_equal_the_scalar_ones() {
        let mut rng = Mix(3);
        let edges = [
            0.0,
            -0.0,
            0.5,
            -0.5,
            1.0,
            -1.0,
            1.5,
            -1.5,
            2.5,
            -2.5,
            1e-300,
            -1e-300,
            0.999_999_999_999_999_9,
            -0.999_999_999_999_999_9,
            FLOOR_PARITY_LIMIT - 0.5,
            -FLOOR_PARITY_LIMIT + 0.5,
            FLOOR_PARITY_LIMIT,
            -FLOOR_PARITY_LIMIT,
            4.0 * FLOOR_PARITY_LIMIT + 2.0,
            1e300,
            f64::INFINITY,
            f64::NAN,
        ];
        for case in 0..100_000 {
            let value = |rng: &mut Mix| match rng.next() % 3 {
                0 => edges[(rng.next() % edges.len() as u64) as usize],
                1 => (2.0 * rng.unit() - 1.0) * 100.0,
                _ => (rng.next() % 2001) as f64 / 2.0 - 500.0,
            };
            let points: [Vec3; LANES] =
                std::array::from_fn(|_| Vec3::new(value(&mut rng), 0.0, value(&mut rng)));
            let p = V4::from_lanes(points);
            let white = checker_white_lanes(p);
            for (k, point) in points.iter().enumerate() {
                assert_eq!(
                    white.get(k),
                    checker_white(*point),
                    "case {case}: {point:?}"
                );
            }
            let colors: [Vec3; LANES] = std::array::from_fn(|_| {
                let mut c = || match rng.next() % 4 {
                    0 => edges[(rng.next() % edges.len() as u64) as usize],
                    _ => 3.0 * rng.unit() - 0.5,
                };
                Vec3::new(c(), c(), c())
            });
            let c = V4::from_lanes(colors);
            let clipped = clip_lanes(c);
            for (k, color) in colors.iter().enumerate() {
                let bits = |c: Vec3| [c.x, c.y, c.z].map(f64::to_bits);
                assert_eq!(bits(clipped.lane(k)), bits(clip(*color)), "case {case}");
            }
        }
    }
}
