//! Jobs on a farm of real `tessera` processes on 127.0.0.1: started by hand or by
//! `tessera up`, refined, frames and sequences of animated scenes, triangles, boxes and
//! meshes (whose files travel by content), pools of tagged workers; what the farm gives is byte for byte what
//! `tessera render` gives.

mod assets;
mod dependencies;
mod frames;
mod jobs;
mod local_farm;
mod pools;
mod refine;
mod sequences;
mod shapes;
