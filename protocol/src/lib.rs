//! Tessera's wire protocol, shared by the coordinator, its workers and its clients.
//!
//! A connection carries frames: a 4-byte big-endian length, then one message encoded
//! with bincode (fixed-width little-endian integers, see [`wire`]). The first frame
//! each way is the handshake ([`Hello`], [`Welcome`]); after it, a client sends
//! [`ClientRequest`]s and reads [`ClientResponse`]s, and a worker reads [`ToWorker`]
//! and sends [`FromWorker`] messages. `docs/protocol.md` describes every byte.
//!
//! This crate holds formats and limits only: no sockets, no policy. It does not know
//! the renderer either: a scene travels as its JSON text plus a content hash.

mod assets;
mod codec;
mod handshake;
mod messages;
mod settings;
mod tags;
pub mod wire;

pub use crate::assets::*;
pub use crate::codec::{frame_codec, FrameError, MessageCodec, DEFAULT_MAX_FRAME};
pub use crate::handshake::{
    auth_label, coordinator_proof, peer_proof, AuthFailure, AuthProof, AuthRole,
    CoordinatorChallenge, Hello, HelloError, KeyId, PeerHandshake, PeerHandshakeError, PeerStep,
    Role, Welcome, MAGIC, PROTOCOL_VERSION,
};
pub use crate::messages::*;
pub use crate::settings::*;
pub use crate::tags::{check_tag, check_tags, pool_name, qualifies, MAX_TAGS, MAX_TAG_BYTES};
pub use crate::wire::MAX_FRAME_LIMIT;
