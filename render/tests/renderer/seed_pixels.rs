//! Pixels of the seed scene at 600×400, aa 2, derived by hand from the formulas of the
//! scene format, and checked against the renderer.
//!
//! Seed scene: camera at (3, 1.5, -4) looking at the origin; lights at (-7, 10, -10)
//! and (7, 10, 10), both white; sphere 0 at the origin (r 1, green, s 0.3); sphere 1 at
//! (3, 0, 0) (r 1, grey, s 0.6); the checkerboard plane y = -1.

use render::{parse_scene, render_tile, Rect, Tracer, Vec3};

use crate::support::SEED;

fn seed_pixel(x: u32, y: u32) -> [u8; 3] {
    let scene = parse_scene(SEED).unwrap();
    let mut settings = scene.settings;
    settings.aa = 2;
    let tracer = Tracer::new(&scene, settings);
    let tile = render_tile(
        &tracer,
        Rect {
            x,
            y,
            width: 1,
            height: 1,
        },
    )
    .unwrap();
    [tile.rgb[0], tile.rgb[1], tile.rgb[2]]
}

/// Section 2's camera ray for image point (px, py) of the 600×400 frame.
fn camera_ray(px: f64, py: f64) -> Vec3 {
    let p = Vec3::new(3.0, 1.5, -4.0);
    let f = (Vec3::ZERO - p).normalize();
    let r = Vec3::new(0.0, 1.0, 0.0).cross(f).normalize();
    let u = f.cross(r);
    let x = (px - 300.0) / 400.0;
    let y = (200.0 - py) / 400.0;
    (f + r * x + u * y).normalize()
}

#[test]
fn sky_is_black() {
    // Pixel (300, 20): the four sample rays point upwards (d.y ≈ +0.13), above the
    // plane and both spheres, and meet nothing: black.
    for (sx, sy) in [(0.25, 0.25), (0.75, 0.25), (0.25, 0.75), (0.75, 0.75)] {
        assert!(camera_ray(300.0 + sx, 20.0 + sy).y > 0.1);
    }
    assert_eq!(seed_pixel(300, 20), [0, 0, 0]);
}

#[test]
fn lit_white_checker_square() {
    // Pixel (201, 108): all four samples meet the plane y = -1 near (-26.7, -1, 20.6),
    // where floor(x) + floor(z) = -27 + 20 = -7 is odd: white, C = (1, 1, 1). Both lights
    // are far above the spheres' shadows, so each sample is 0.2 + cos₀ + cos₁ (with the
    // normal (0, 1, 0)), about 0.78 < 1: no clipping. Their mean, 0.78659, × 255 = 200.58.
    let lights = [Vec3::new(-7.0, 10.0, -10.0), Vec3::new(7.0, 10.0, 10.0)];
    let mut sum = 0.0;
    for (sy, sx) in [(0.25, 0.25), (0.25, 0.75), (0.75, 0.25), (0.75, 0.75)] {
        let d = camera_ray(201.0 + sx, 108.0 + sy);
        let t = (-1.0 - 1.5) / d.y;
        let p = Vec3::new(3.0, 1.5, -4.0) + d * t;
        assert_eq!(
            (p.x.floor() + p.z.floor()).rem_euclid(2.0),
            1.0,
            "white square"
        );
        let cos: f64 = lights.iter().map(|l| (*l - p).normalize().y).sum();
        sum += 0.2 + cos;
    }
    let mean = sum / 4.0;
    assert!((mean - 0.78659).abs() < 1e-5, "{mean}");
    let expected = (mean * 255.0).round() as u8;
    assert_eq!(expected, 201);
    assert_eq!(seed_pixel(201, 108), [201, 201, 201]);
}

#[test]
fn shadow_of_both_lights_is_ambient_only() {
    // Pixel (300, 282): the samples meet the plane near (0.22, -1, -0.29), just in front
    // of sphere 0's contact point: floor(x) + floor(z) = 0 + (-1) is odd, white. The
    // segments to both lights pass through sphere 0 (after about 0.1 of their 16.4
    // length), so only ambient light remains: 0.2 × 1 × 255 = 51.
    for (sx, sy) in [(0.25, 0.25), (0.75, 0.75)] {
        let d = camera_ray(300.0 + sx, 282.0 + sy);
        let p = Vec3::new(3.0, 1.5, -4.0) + d * ((-1.0 - 1.5) / d.y);
        for light in [Vec3::new(-7.0, 10.0, -10.0), Vec3::new(7.0, 10.0, 10.0)] {
            // Distance from the sphere's centre to the segment p → light is below 1.
            let l = (light - p).normalize();
            let closest = p + l * (Vec3::ZERO - p).dot(l);
            assert!(closest.length() < 1.0);
        }
    }
    assert_eq!(seed_pixel(300, 282), [51, 51, 51]);
}

#[test]
fn specular_highlights() {
    // Pixel (533, 226) on sphere 1 (grey 0.5, s 0.6): light 0 reflects almost exactly
    // towards the camera, R·l ≈ 0.9999, so each sample is about ambient 0.1 + diffuse
    // 0.5 × 0.91 + highlight 0.6 × (R·l)¹⁰ ≈ 0.6 = 1.155 per channel; the sum 3.47 > 3
    // spills into every channel and all clamp to 1: white.
    assert_eq!(seed_pixel(533, 226), [255, 255, 255]);
    // Pixel (262, 172) on sphere 0 (0.5 1 0.5, s 0.3): the highlight 0.3 × (R·l)¹⁰ ≈ 0.3
    // saturates green but not red and blue.
    assert_eq!(seed_pixel(262, 172), [203, 255, 203]);
}
