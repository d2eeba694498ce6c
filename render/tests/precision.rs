//! What single precision would cost. The tracer computes in f64 throughout; before
//! anyone moves a part of it to f32 for speed (twice the SIMD lanes), this measures the
//! error f32 brings on the hard cases of `numerics.rs`, with the tracer's own
//! intersection method (the cancellation-free quadratic) computed once in f32 and once
//! in f64 against the exact answer. docs/numerics.md records the figures; run with
//! `cargo test --release -p render --test precision -- --nocapture`.

use std::ops::{Add, Div, Mul, Neg, Sub};

/// The arithmetic the sphere test needs, in either precision.
trait Real:
    Copy
    + PartialOrd
    + Add<Output = Self>
    + Sub<Output = Self>
    + Mul<Output = Self>
    + Div<Output = Self>
    + Neg<Output = Self>
{
    fn of(x: f64) -> Self;
    fn to_f64(self) -> f64;
    fn sqrt(self) -> Self;
}

impl Real for f32 {
    fn of(x: f64) -> Self {
        x as f32
    }
    fn to_f64(self) -> f64 {
        f64::from(self)
    }
    fn sqrt(self) -> Self {
        f32::sqrt(self)
    }
}

impl Real for f64 {
    fn of(x: f64) -> Self {
        x
    }
    fn to_f64(self) -> f64 {
        self
    }
    fn sqrt(self) -> Self {
        f64::sqrt(self)
    }
}

type V<T> = [T; 3];

fn v<T: Real>(p: [f64; 3]) -> V<T> {
    [T::of(p[0]), T::of(p[1]), T::of(p[2])]
}

fn dot<T: Real>(a: V<T>, b: V<T>) -> T {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn sub<T: Real>(a: V<T>, b: V<T>) -> V<T> {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn normalize<T: Real>(a: V<T>) -> V<T> {
    let n = dot(a, a).sqrt();
    [a[0] / n, a[1] / n, a[2] / n]
}

/// The tracer's sphere test (render/src/geometry.rs), in precision `T`: the nearest
/// positive root, or `None`. The scene's numbers are rounded to `T` first, as a
/// tracer in `T` would have to.
fn sphere_hit<T: Real>(
    origin: [f64; 3],
    dir: [f64; 3],
    center: [f64; 3],
    radius: f64,
) -> Option<f64> {
    let (o, d, c, r) = (
        v::<T>(origin),
        normalize(v::<T>(dir)),
        v::<T>(center),
        T::of(radius),
    );
    let f = sub(o, c);
    let b = dot(f, d);
    let cc = dot(f, f) - r * r;
    let zero = T::of(0.0);
    if cc > zero && b >= zero {
        return None;
    }
    let along = [f[0] - b * d[0], f[1] - b * d[1], f[2] - b * d[2]];
    let disc = r * r - dot(along, along);
    if disc < zero {
        return None;
    }
    let q = if b > zero {
        -b - disc.sqrt()
    } else {
        -b + disc.sqrt()
    };
    let (t0, t1) = (cc / q, q);
    let (near, far) = if t0 < t1 { (t0, t1) } else { (t1, t0) };
    [near, far]
        .into_iter()
        .find(|t| *t > zero)
        .map(Real::to_f64)
}

/// Rays from 1e3 away aimed within 1e-5 · r of the rim of a sphere of radius 1e-3,
/// half just inside, half just outside: how many each precision classifies wrongly.
fn rim_of_a_tiny_far_sphere<T: Real>() -> (usize, usize) {
    let (r, distance) = (1e-3, 1e3);
    let origin = [0.0, 0.0, -distance];
    let mut wrong = 0;
    let mut probes = 0;
    for i in 0..100 {
        for inside in [true, false] {
            let delta = r * 1e-5 * (f64::from(i) + 1.0) / 100.0;
            let aim = if inside { r - delta } else { r + delta };
            // The exact distance from the centre to the line through origin and
            // (aim, 0, 0) is aim · D / sqrt(aim² + D²): below r exactly when inside.
            let hit = sphere_hit::<T>(origin, [aim, 0.0, distance], [0.0; 3], r).is_some();
            wrong += usize::from(hit != inside);
            probes += 1;
        }
    }
    (wrong, probes)
}

/// A sphere of radius 0.25 around (1e5, 1e5, 1e5) seen from 10 away, with rays over
/// its disc: the largest error of the shading normal, in 8-bit levels of a diffuse term
/// lit by a white light of intensity 1 (the normal's error times 255), and the rays
/// that miss although they meet the sphere.
fn sphere_far_from_the_origin<T: Real>() -> (f64, usize, usize) {
    let c = [1e5, 1e5, 1e5];
    let radius = 0.25;
    let origin = [c[0] + 0.0625, c[1] - 0.03125, c[2] - 10.0];
    let mut worst = 0.0f64;
    let mut lost = 0;
    let mut probes = 0;
    for i in 0..40 {
        for j in 0..40 {
            let target = [
                c[0] + radius * (-0.9 + 1.8 * f64::from(i) / 39.0),
                c[1] + radius * (-0.9 + 1.8 * f64::from(j) / 39.0),
                c[2],
            ];
            let dir = normalize::<f64>(sub(target, origin));
            let Some(exact) = sphere_hit::<f64>(origin, dir, c, radius) else {
                continue;
            };
            probes += 1;
            let exact_normal =
                sub([0, 1, 2].map(|k| origin[k] + exact * dir[k]), c).map(|x| x / radius);
            match sphere_hit::<T>(origin, dir, c, radius) {
                None => lost += 1,
                Some(t) => {
                    // The hit point as a T tracer would hold it, and its normal.
                    let p: V<T> = [0, 1, 2].map(|k| T::of(origin[k]) + T::of(t) * T::of(dir[k]));
                    let n = sub(p, v::<T>(c)).map(|x| x.to_f64() / radius);
                    let err = (0..3)
                        .map(|k| (n[k] - exact_normal[k]).abs())
                        .fold(0.0, f64::max);
                    worst = worst.max(err * 255.0);
                }
            }
        }
    }
    (worst, lost, probes)
}

/// A sphere of radius 1e-3 resting on a plane at height 1e5: whether a point of the
/// ground 2e-3 from the contact lies in the sphere's shadow under a light straight
/// above, decided by a shadow ray from the ground point (the sphere is not under the
/// point, so the exact answer is "lit"), and the same for a point 5e-4 from the
/// contact, which is under the sphere ("shadowed"). Counts wrong decisions over 100
/// positions along x near 1e5.
fn contact_shadow_at_large_coordinates<T: Real>() -> (usize, usize) {
    let mut wrong = 0;
    let mut probes = 0;
    let r = 1e-3;
    for i in 0..100 {
        let x = 1e5 + f64::from(i) * 0.37;
        let center = [x, 1e5 + r, 0.0];
        for (offset, shadowed) in [(2e-3, false), (5e-4, true)] {
            let ground = [x + offset, 1e5, 0.0];
            let blocked = sphere_hit::<T>(ground, [0.0, 1.0, 0.0], center, r).is_some();
            wrong += usize::from(blocked != shadowed);
            probes += 1;
        }
    }
    (wrong, probes)
}

#[test]
fn single_precision_costs_what_docs_numerics_says() {
    let (rim32, rim_probes) = rim_of_a_tiny_far_sphere::<f32>();
    let (rim64, _) = rim_of_a_tiny_far_sphere::<f64>();
    let (normal32, lost32, far_probes) = sphere_far_from_the_origin::<f32>();
    let (normal64, lost64, _) = sphere_far_from_the_origin::<f64>();
    let (contact32, contact_probes) = contact_shadow_at_large_coordinates::<f32>();
    let (contact64, _) = contact_shadow_at_large_coordinates::<f64>();
    println!("| case | probes | f32 | f64 |");
    println!("| --- | ---: | ---: | ---: |");
    println!(
        "| rim of a 1e-3 sphere seen from 1e3: wrong hit/miss | {rim_probes} | {rim32} | {rim64} |"
    );
    println!(
        "| sphere of radius 0.25 at 1e5: largest shading error (8-bit levels) | {far_probes} | {normal32:.1} | {normal64:.2e} |"
    );
    println!("| sphere of radius 0.25 at 1e5: hits lost | {far_probes} | {lost32} | {lost64} |");
    println!(
        "| 1e-3 sphere resting on ground at 1e5: wrong shadow decisions | {contact_probes} | {contact32} | {contact64} |"
    );

    // f64 gets every case right, to far below one 8-bit level.
    assert_eq!((rim64, lost64, contact64), (0, 0, 0));
    assert!(normal64 < 1e-3, "f64 shading error {normal64} levels");
    // f32 does not: at coordinates of 1e5 its spacing (2⁻⁷ ≈ 0.008) exceeds a 1e-3
    // sphere and turns the normals of a sphere of radius 0.25 by whole levels.
    assert!(normal32 > 1.0, "f32 shading error only {normal32} levels");
    assert!(contact32 > 0, "f32 decided every contact shadow right");
}
