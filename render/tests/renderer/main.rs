//! The render crate's tests, through its public interface: exact answers on hard
//! numerical cases and hand-derived pixels, the hierarchy that changes speed and never
//! answers, tiles and samplers that give the same bytes in any tiling, the adaptive
//! sampler's error knob, the portable code path, scene loading under fuzzing, meshes of
//! every format compared byte for byte, the same from files bound in memory, geometry
//! shared across scenes, and hostile mesh files.

mod bound_files;
mod bvh;
mod calibration;
mod fuzz_scene;
mod hierarchy_precision;
mod hostile_meshes;
mod mesh_mutations;
mod mesh_support;
mod meshes;
mod numerics;
mod portable;
mod sampling;
mod seed_pixels;
mod support;
mod tiles;
