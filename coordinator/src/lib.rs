//! Tessera's coordinator: accepts jobs, cuts them into tiles, hands the tiles to
//! workers and stores the assembled images.
//!
//! [`scheduler`] makes every decision as a pure state machine; [`server`] is the daemon
//! that feeds it events from the network and carries out its actions; [`client`] is the
//! library side of the command-line client; [`security`] holds the rules a coordinator's
//! settings must follow before it accepts anyone, and [`keyring`] which token a peer
//! proves as tokens are rotated.

pub mod archive;
pub mod client;
pub mod daemon;
mod db;
pub mod events;
pub mod http;
pub mod json;
pub mod keyring;
mod metrics;
mod preview;
pub mod security;
pub mod server;
mod store;
pub mod studio;
mod tiling;
pub mod webhooks;

pub use crate::daemon::serve;
/// Any PNG to 8-bit RGB, as the farm reads back the frames it stored; also what the
/// benchmarks and the end-to-end tests decode images with.
pub use crate::preview::decode_png;
pub use crate::server::{Config, VerifyConfig};
