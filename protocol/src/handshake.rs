//! The first frame of every connection: who is speaking, and in which version.
//!
//! Its layout is fixed for all versions so that a peer of another version can always be
//! told what is wrong: 4 magic bytes, a u16 version (little-endian), then the role.

use serde::{Deserialize, Serialize};

use crate::wire;

/// The first four bytes of every `Hello`: "TSRA".
pub const MAGIC: [u8; 4] = *b"TSRA";

/// Bumped whenever any message changes shape.
pub const PROTOCOL_VERSION: u16 = 1;

/// The peer's first frame.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Hello {
    pub magic: [u8; 4],
    pub version: u16,
    pub role: Role,
}

/// What the peer is.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Role {
    /// Submits jobs and asks about them.
    Client,
    /// Renders tiles with `threads` threads; `name` identifies it in listings and logs.
    Worker { name: String, threads: u32 },
}

/// The coordinator's answer to a `Hello`.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Welcome {
    /// The connection is open for the role's messages.
    Accepted { version: u16 },
    /// The connection is refused and will be closed; `reason` says why.
    Refused { reason: String },
}

/// Why a first frame is not an acceptable `Hello`.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum HelloError {
    #[error("not a Tessera peer (the first frame does not start with the magic bytes \"TSRA\")")]
    BadMagic,
    #[error("protocol version mismatch: this coordinator speaks version {ours}, the peer speaks version {theirs}")]
    VersionMismatch { ours: u16, theirs: u16 },
    #[error("malformed hello: {0}")]
    Malformed(String),
}

impl Hello {
    /// This version's hello for `role`.
    pub fn new(role: Role) -> Self {
        Hello {
            magic: MAGIC,
            version: PROTOCOL_VERSION,
            role,
        }
    }

    /// Reads a first frame, diagnosing a wrong magic or version from the fixed prefix
    /// before trying to read the rest (whose shape may differ in another version).
    pub fn from_frame(frame: &[u8]) -> Result<Hello, HelloError> {
        if frame.len() < 6 || frame[..4] != MAGIC {
            return Err(HelloError::BadMagic);
        }
        let theirs = u16::from_le_bytes([frame[4], frame[5]]);
        if theirs != PROTOCOL_VERSION {
            return Err(HelloError::VersionMismatch {
                ours: PROTOCOL_VERSION,
                theirs,
            });
        }
        wire::decode(frame).map_err(|e| HelloError::Malformed(e.to_string()))
    }

    /// The frame body of this hello.
    pub fn to_frame(&self) -> Vec<u8> {
        wire::encode(self)
    }
}
