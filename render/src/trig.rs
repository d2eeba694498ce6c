//! Sines, cosines and tangents of angles in degrees, computed by the renderer itself so
//! that a transform's rotation and a camera's field of view give the same bytes on
//! every machine (the scene format, section 8: "not by the platform's libm").
//!
//! Only additions, multiplications and divisions of `f64` are used, in a fixed order:
//! IEEE 754 makes each exact to the same rounding everywhere, and Rust never fuses
//! them. The angle is first reduced in degrees, where the reduction by 360° and by
//! quarter turns is exact, so that a multiple of 90° gives exactly 0, 1 or −1; the rest,
//! at most 45°, goes to radians and through Taylor series long enough for the double
//! precision of that range.

/// The sine and cosine of `degrees`: exact (0, ±1) at multiples of 90°, within a few
/// units in the last place elsewhere. Not finite for an angle that is not.
pub fn sin_cos_deg(degrees: f64) -> (f64, f64) {
    if !degrees.is_finite() {
        return (f64::NAN, f64::NAN);
    }
    // Exact: `%` of doubles is the exact remainder. A negative angle is reduced as its
    // magnitude (the sine is odd, the cosine even), since adding 360 to a negative
    // remainder would round.
    let turn = degrees.abs() % 360.0;
    // The nearest quarter turn, and the rest in [-45, 45]: both exact (the rest is the
    // difference of two numbers within a factor of two of each other).
    let quarter = (turn / 90.0).round();
    let rest = turn - quarter * 90.0;
    let (s, c) = sin_cos_small(rest * (std::f64::consts::PI / 180.0));
    let (s, c) = match quarter as i64 % 4 {
        0 => (s, c),
        1 => (c, -s),
        2 => (-s, -c),
        _ => (-c, s),
    };
    if degrees < 0.0 {
        (-s, c)
    } else {
        (s, c)
    }
}

/// The tangent of `degrees`, as the quotient of [`sin_cos_deg`]: infinite at odd
/// multiples of 90°, exactly 1 at 45°.
pub fn tan_deg(degrees: f64) -> f64 {
    let (s, c) = sin_cos_deg(degrees);
    s / c
}

/// k = 2·tan(fov/2) of a field of view in degrees, computed the same on every machine:
/// the camera scales its image plane by it, and the scene reader refuses a `fov` for
/// which it is not a normal number.
pub(crate) fn fov_scale(fov: f64) -> f64 {
    2.0 * tan_deg(fov / 2.0)
}

/// The sine and cosine of `x`, |x| ≤ π/4, by their Taylor series to the terms in x¹⁹
/// and x²⁰: the first term left out is below 2⁻⁵³ of the result over that range.
fn sin_cos_small(x: f64) -> (f64, f64) {
    let x2 = x * x;
    // Horner's scheme over the reciprocal factorials, the smallest term first.
    const SIN: [f64; 10] = [
        1.0,
        -1.0 / 6.0,
        1.0 / 120.0,
        -1.0 / 5040.0,
        1.0 / 362_880.0,
        -1.0 / 39_916_800.0,
        1.0 / 6_227_020_800.0,
        -1.0 / 1_307_674_368_000.0,
        1.0 / 355_687_428_096_000.0,
        -1.0 / 121_645_100_408_832_000.0,
    ];
    const COS: [f64; 11] = [
        1.0,
        -1.0 / 2.0,
        1.0 / 24.0,
        -1.0 / 720.0,
        1.0 / 40_320.0,
        -1.0 / 3_628_800.0,
        1.0 / 479_001_600.0,
        -1.0 / 87_178_291_200.0,
        1.0 / 20_922_789_888_000.0,
        -1.0 / 6_402_373_705_728_000.0,
        1.0 / 2_432_902_008_176_640_000.0,
    ];
    let horner = |coefficients: &[f64]| {
        coefficients
            .iter()
            .rev()
            .fold(0.0, |sum, &coefficient| sum * x2 + coefficient)
    };
    (x * horner(&SIN), horner(&COS))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// How many representable doubles lie between `a` and `b`.
    fn ulps(a: f64, b: f64) -> u64 {
        let key = |v: f64| {
            let bits = v.to_bits() as i64;
            if bits < 0 {
                i64::MIN - bits
            } else {
                bits
            }
        };
        key(a).abs_diff(key(b))
    }

    #[test]
    fn quarter_turns_are_exact() {
        for k in -12i32..=12 {
            let (s, c) = sin_cos_deg(90.0 * f64::from(k));
            // (0.0 == -0.0: the sign of a zero is not asked for.)
            let expected = [(0.0, 1.0), (1.0, 0.0), (0.0, -1.0), (-1.0, 0.0)];
            assert_eq!(
                (s, c),
                expected[k.rem_euclid(4) as usize],
                "{k} quarter turns"
            );
        }
        assert!(tan_deg(90.0).is_infinite());
        assert_eq!(tan_deg(180.0), 0.0);
    }

    #[test]
    fn agrees_with_the_platform_within_a_few_ulps() {
        let mut worst = 0;
        let mut angle = -720.0;
        while angle <= 720.0 {
            let (s, c) = sin_cos_deg(angle);
            let radians = angle.to_radians();
            // The platform's argument, in radians, is itself rounded: near a zero of
            // the function that is many ulps of the value, so compare absolutely there.
            for (mine, theirs) in [(s, radians.sin()), (c, radians.cos())] {
                assert!((mine - theirs).abs() < 2e-15, "{angle}: {mine} vs {theirs}");
                // Beyond a quarter turn the platform's own rounding of the radians
                // grows with the angle: ulps are counted within it only.
                if theirs.abs() > 0.5 && angle.abs() <= 90.0 {
                    worst = worst.max(ulps(mine, theirs));
                }
            }
            angle += 0.173;
        }
        assert!(worst <= 4, "{worst} ulps");
    }

    #[test]
    fn the_same_angle_a_turn_away_gives_the_same_bytes() {
        for angle in [0.5, 17.25, 33.0, 89.75, 123.5, 271.0] {
            assert_eq!(sin_cos_deg(angle), sin_cos_deg(angle + 360.0));
            assert_eq!(sin_cos_deg(angle), sin_cos_deg(angle - 720.0));
        }
        assert!(sin_cos_deg(f64::NAN).0.is_nan());
        assert!(sin_cos_deg(f64::INFINITY).1.is_nan());
    }
}
