//! What the render crate's tests share: the seed scene, a deterministic generator,
//! scenes built in code, and frames rendered on a pool of a given size.

use render::{
    parse_scene, render_frame, Frame, Material, Object, RenderSettings, Sampling, Scene, Shape,
    Tracer, Vec3,
};

/// The seed scene, `scenes/seed.json`.
pub const SEED: &str = include_str!("../../../scenes/seed.json");

/// The seed scene, parsed.
pub fn seed() -> Scene {
    parse_scene(SEED).unwrap()
}

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

pub fn v(x: f64, y: f64, z: f64) -> Vec3 {
    Vec3::new(x, y, z)
}

/// A sphere of the colour (0.8, 0.5, 0.3).
pub fn sphere(center: Vec3, radius: f64, material: Material) -> Object {
    Object {
        shape: Shape::Sphere { center, radius },
        color: v(0.8, 0.5, 0.3),
        material,
    }
}

/// The two tracers of a scene: through the hierarchy, and testing every sphere.
pub fn both(scene: &Scene) -> (Tracer, Tracer) {
    let bvh = Tracer::with_bvh(scene, scene.settings, true);
    let brute = Tracer::with_bvh(scene, scene.settings, false);
    assert!(
        bvh.uses_bvh() && !brute.uses_bvh(),
        "the hierarchy is forced on and off"
    );
    (bvh, brute)
}

/// A tracer of `scene` at `width` × `height` with `aa` and `sampling`, the scene's other
/// settings kept.
pub fn tracer(scene: &Scene, width: u32, height: u32, aa: u32, sampling: Sampling) -> Tracer {
    Tracer::new(
        scene,
        RenderSettings {
            width,
            height,
            aa,
            sampling,
            ..scene.settings
        },
    )
}

/// The whole frame in tiles of `tile`, on a pool of `threads` threads.
pub fn frame(tracer: &Tracer, tile: u32, threads: usize) -> Frame {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap();
    pool.install(|| render_frame(tracer, tile, &|_| {}))
}
