//! `tessera render` on one machine: the command's contract (images, summaries, one-line
//! refusals), scenes with mesh files, animated scenes and their frames, the committed
//! golden images of every example scene, adaptive renders saved and refined, and the
//! scheduler's simulator.

mod animation;
mod blender;
mod golden;
mod meshes;
mod refine;
mod render;
mod simulate;
