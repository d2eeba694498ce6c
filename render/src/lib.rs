//! Tessera's ray tracer: the seed scene format's Whitted-style renderer.
//!
//! Pure computation: a scene's text goes in ([`parse_scene`]; an animated scene's frames
//! through [`parse_animated`] and [`AnimatedScene::frame`]), tiles or whole frames
//! come out ([`render_tile`], [`render_frame`]), and every pixel is a deterministic
//! function of the scene, the settings and its coordinates. No I/O, no network, no async,
//! so the same code serves `tessera render`, the workers of the farm and the tests.
//!
//! Pixels are sampled on the scene format's regular grid by default, or jittered, or
//! adaptively ([`Sampling`]); every tile reports the samples it took and its estimated
//! error, and [`metrics`] measures an image's real error against a reference.
//!
//! # Layering
//!
//! The modules depend on each other one way only, lowest first (a module uses only
//! those on lines above its own, and its tests follow the same order):
//!
//! - [`vec3`](Vec3), [`trig`], [`simd`], [`limits`], `error`: numbers, angles, lanes,
//!   limits and the scene error;
//! - [`transform`], `bounds` → `hierarchy`: affine maps, and the bounding volume
//!   hierarchy over boxes that meshes and section 8's shapes share;
//! - [`mesh`]: mesh files (from a directory or sent with a scene, each read recorded),
//!   their readers, and the geometry every object showing a file shares, with the
//!   hierarchy built over it once, and kept across scenes by a [`GeometryCache`];
//! - `settings` → `scene` → [`animation`]: what a render may override, the scene
//!   model, and frames as functions of the frame number;
//! - `parse` → `write`: scene files read, and written back;
//! - `camera`, `geometry` → `bvh`, `shapes` → `tracer` → `footprint`: rays, their
//!   intersections, and what a pixel sees;
//! - `rect` → `image` → [`metrics`]: a frame's rectangles and pixels;
//! - [`sampling`] → [`adaptive`] → `tile`: the samplers, adaptive sampling over the
//!   whole frame, and tiles and frames rendered with either.

pub mod adaptive;
pub mod animation;
mod bounds;
mod bvh;
mod camera;
mod error;
mod footprint;
mod geometry;
mod hierarchy;
mod image;
pub mod limits;
pub mod mesh;
pub mod metrics;
mod parse;
mod rect;
pub mod sampling;
mod scene;
mod settings;
mod shapes;
pub mod simd;
#[cfg(test)]
mod test_rng;
mod tile;
mod tracer;
pub mod transform;
pub mod trig;
mod vec3;
mod write;

pub use crate::animation::{
    frame_file_name, AnimatedScene, Animation, FrameOutOfRange, MAX_FRAMES,
};
pub use crate::error::SceneError;
pub use crate::image::{Image, TileImage};
pub use crate::mesh::{buffer_name, CacheStats, FileRead, GeometryCache, MeshFile, MeshFiles};
pub use crate::parse::{
    parse_animated, parse_animated_with, parse_scene, parse_scene_with, validate_settings,
    MAX_TRACKS,
};
pub use crate::rect::{tiles, Rect, TileError};
pub use crate::sampling::sample_offsets;
pub use crate::scene::{CameraSpec, Light, Material, MeshObject, Object, Scene, Shape};
pub use crate::settings::{
    InvalidTarget, RenderSettings, Sampler, Sampling, SamplingChoiceError, MAX_TARGET_MILLI,
    MIN_TARGET_MILLI,
};
pub use crate::tile::{estimated_error, render_frame, render_tile, Frame, DEFAULT_TILE_SIZE};
pub use crate::tracer::{Hit, Tracer};
pub use crate::vec3::Vec3;
pub use crate::write::Unwritable;

/// This renderer's build: version, target and profile (and the packager's stamp from
/// `TESSERA_BUILD` at compile time, if any). Workers announce it; the canary render,
/// not this name, decides whether two builds agree.
pub fn build_identity() -> String {
    let profile = if cfg!(debug_assertions) {
        "debug"
    } else {
        "release"
    };
    let stamp = option_env!("TESSERA_BUILD").map_or(String::new(), |s| format!(", {s}"));
    format!(
        "tessera {} ({}-{}, {profile}{stamp})",
        env!("CARGO_PKG_VERSION"),
        std::env::consts::ARCH,
        std::env::consts::OS
    )
}
