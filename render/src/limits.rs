//! Bounds on what a scene may ask for, so that a scene file can never make the renderer
//! allocate or compute without bound. Each is checked with a clear error at load time
//! and again when a caller overrides a setting.

/// Largest width or height in pixels (a 16K frame).
pub const MAX_SIDE: u32 = 16_384;
/// Largest `aa`: 64 × 64 = 4096 samples per pixel.
pub const MAX_AA: u32 = 64;
/// Largest reflection depth.
pub const MAX_DEPTH: u32 = 64;
/// Largest mesh file, in bytes: a 20-million-triangle binary STL is about 1 GB.
pub const MAX_MESH_FILE_BYTES: u64 = 2 << 30;
/// Most triangles in one mesh file.
pub const MAX_MESH_TRIANGLES: usize = 20_000_000;
