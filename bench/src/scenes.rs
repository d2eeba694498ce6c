//! The scenes the benchmarks render, made in code so that their size can vary (the
//! object count of the many-spheres scene) and every run renders exactly the same ones.

use serde_json::{json, Value};

/// A benchmark scene: a name for tables and files, and its JSON text.
pub struct BenchScene {
    pub name: &'static str,
    pub what: String,
    pub json: String,
}

/// The seed's own scene, as shipped in `scenes/seed.json`.
pub fn seed() -> BenchScene {
    BenchScene {
        name: "seed",
        what: "the seed scene: two spheres over a checkerboard, large smooth areas".into(),
        json: include_str!("../../scenes/seed.json").to_owned(),
    }
}

/// A small integer hash mixed to a number in [0, 1): fixed positions, no RNG state.
fn unit(i: u64, salt: u64) -> f64 {
    let mut z = i
        .wrapping_mul(0x9E37_79B9_7F4A_7C15)
        .wrapping_add(salt.wrapping_mul(0xD1B5_4A32_D192_ED03));
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^= z >> 31;
    (z >> 11) as f64 / (1u64 << 53) as f64
}

/// `count` small spheres scattered over a 16 × 16 patch of a plane, seen from above at
/// an angle; one in five is reflective. The patch and the radius stay the same whatever
/// the count, so the frame's cost is what grows with it.
pub fn spheres(count: usize) -> BenchScene {
    let objects: Vec<Value> = std::iter::once(json!({
        "type": "plane", "normal": [0, 1, 0], "distance": -1.0,
        "color": [0.6, 0.6, 0.6, 0]
    }))
    .chain((0..count as u64).map(|i| {
        let x = -8.0 + 16.0 * unit(i, 1);
        let z = -2.0 + 16.0 * unit(i, 2);
        let r = 0.06 + 0.06 * unit(i, 3);
        let special = if i % 5 == 0 { 0.5 } else { 0.0 };
        json!({
            "type": "sphere", "center": [x, -1.0 + r, z], "radius": r,
            "color": [0.3 + 0.7 * unit(i, 4), 0.3 + 0.7 * unit(i, 5), 0.3 + 0.7 * unit(i, 6), special]
        })
    }))
    .collect();
    let scene = json!({
        "camera": { "position": [0, 5, -9], "look_at": [0, -1, 6] },
        "image": { "width": 600, "height": 400, "aa": 1 },
        "lights": [
            { "position": [-6, 10, -4], "color": [0.8, 0.8, 0.8] },
            { "position": [8, 6, 12], "color": [0.4, 0.4, 0.5] }
        ],
        "objects": objects
    });
    BenchScene {
        name: "spheres",
        what: format!(
            "{} small spheres over a plane, a fifth of them mirrors",
            thousands(count as u64)
        ),
        json: scene.to_string(),
    }
}

/// A checkerboard seen from just above, out to the horizon: squares shrink below a
/// pixel, the hardest case for a regular grid (aliasing, moiré).
pub fn checker_horizon() -> BenchScene {
    let scene = json!({
        "camera": { "position": [0, 0.4, -4], "look_at": [2, 0.1, 10] },
        "image": { "width": 600, "height": 400, "aa": 1 },
        "lights": [ { "position": [3, 20, 5], "color": [1, 1, 1] } ],
        "objects": [
            { "type": "plane", "normal": [0, 1, 0], "distance": -0.5, "color": [0, 0, 0, 2] },
            { "type": "sphere", "center": [0.5, 0.3, 2], "radius": 0.8, "color": [0.9, 0.9, 0.9, 0.8] }
        ]
    });
    BenchScene {
        name: "checker-horizon",
        what: "a checkerboard out to the horizon: detail finer than a pixel everywhere far away"
            .into(),
        json: scene.to_string(),
    }
}

/// Rows of tiny spheres (thinner than a pixel at this size) strung like wires in front
/// of a lit wall: features a single sample per pixel misses.
pub fn thin_features() -> BenchScene {
    let mut objects = vec![
        json!({ "type": "plane", "normal": [0, 0, -1], "distance": -6.0, "color": [0.9, 0.85, 0.7, 0] }),
        json!({ "type": "plane", "normal": [0, 1, 0], "distance": -3.0, "color": [0.4, 0.4, 0.4, 0] }),
    ];
    for wire in 0..6u64 {
        let y = -2.5 + f64::from(wire as u32) * 0.9;
        let tilt = (unit(wire, 7) - 0.5) * 0.6;
        let radius = 0.008 + 0.004 * f64::from(wire as u32);
        for k in 0..160u64 {
            let x = -8.0 + 16.0 * (k as f64 / 159.0);
            objects.push(json!({
                "type": "sphere", "center": [x, y + tilt * x / 8.0, 2.0], "radius": radius,
                "color": [0.1, 0.1, 0.15, 0]
            }));
        }
    }
    let scene = json!({
        "camera": { "position": [0, 0, -6], "look_at": [0, 0, 2] },
        "image": { "width": 600, "height": 400, "aa": 1 },
        "lights": [ { "position": [0, 6, -8], "color": [1, 1, 1] } ],
        "objects": objects
    });
    BenchScene {
        name: "thin-features",
        what: "960 spheres a fraction of a pixel wide, strung in wires in front of a wall".into(),
        json: scene.to_string(),
    }
}

/// The scenes of `tessera-bench`'s speed-against-error table.
pub fn error_suite() -> Vec<BenchScene> {
    vec![seed(), spheres(1000), checker_horizon(), thin_features()]
}

/// The seed scene's objects lit by `count` equal white lights on a circle above them,
/// together as bright as the seed's two: what each light adds to a frame's cost.
pub fn lights(count: usize) -> BenchScene {
    let lights: Vec<Value> = (0..count)
        .map(|i| {
            let angle = std::f64::consts::TAU * i as f64 / count as f64;
            let c = 2.0 / count as f64;
            json!({
                "position": [10.0 * angle.cos(), 10.0, 10.0 * angle.sin()],
                "color": [c, c, c]
            })
        })
        .collect();
    let seed: Value = serde_json::from_str(&seed().json).expect("scenes/seed.json is valid JSON");
    let scene = json!({
        "image": { "width": 600, "height": 400, "aa": 1 },
        "lights": lights,
        "objects": seed["objects"].clone()
    });
    BenchScene {
        name: "lights",
        what: format!("the seed scene's objects under {count} lights"),
        json: scene.to_string(),
    }
}

/// `scenes/hall-of-mirrors.json`: two facing mirrors, reflections up to the depth limit.
pub fn hall_of_mirrors() -> BenchScene {
    BenchScene {
        name: "hall-of-mirrors",
        what: "two facing mirrors (reflectance 0.9) around two spheres: deep reflections".into(),
        json: include_str!("../../scenes/hall-of-mirrors.json").to_owned(),
    }
}

/// 1000000 as "1,000,000".
pub fn thousands(n: u64) -> String {
    let digits = n.to_string();
    let mut out = String::new();
    for (i, d) in digits.chars().enumerate() {
        if i > 0 && (digits.len() - i).is_multiple_of(3) {
            out.push(',');
        }
        out.push(d);
    }
    out
}
