//! The first frame of every connection: who is speaking, and in which version.
//!
//! Its layout is fixed for all versions so that a peer of another version can always be
//! told what is wrong: 4 magic bytes, a u16 version (little-endian), then the role.

use serde::{Deserialize, Serialize};

use crate::wire;

/// The first four bytes of every `Hello`: "TSRA".
pub const MAGIC: [u8; 4] = *b"TSRA";

/// Bumped whenever any message changes shape.
pub const PROTOCOL_VERSION: u16 = 3;

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
    /// `build` names the worker's renderer build (version, target, profile): shown in
    /// listings and logs, and named when its canary render does not match.
    Worker {
        name: String,
        threads: u32,
        build: String,
    },
}

/// The coordinator's answer to a `Hello` (and to an [`AuthProof`]).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Welcome {
    /// The connection is open for the role's messages.
    Accepted { version: u16 },
    /// The connection is refused and will be closed; `reason` says why.
    Refused { reason: String },
    /// The coordinator requires the shared secret: answer with an [`AuthProof`] for
    /// this fresh nonce. The secret itself never crosses the network.
    Challenge { nonce: [u8; 32] },
}

/// The peer's answer to a [`Welcome::Challenge`]: HMAC-SHA256, keyed with the shared
/// secret, of [`AUTH_CONTEXT`] followed by the nonce.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct AuthProof {
    pub mac: [u8; 32],
}

/// Bound into every proof, so that a MAC made for anything else never passes.
pub const AUTH_CONTEXT: &[u8] = b"tessera-auth-v1";

/// The proof of knowing `secret` for `nonce`.
pub fn prove(secret: &[u8], nonce: &[u8; 32]) -> AuthProof {
    use hmac::{KeyInit, Mac};
    let mut mac =
        hmac::Hmac::<sha2::Sha256>::new_from_slice(secret).expect("HMAC takes keys of any length");
    mac.update(AUTH_CONTEXT);
    mac.update(nonce);
    AuthProof {
        mac: mac.finalize().into_bytes().into(),
    }
}

/// Checks a proof in constant time.
pub fn verify(secret: &[u8], nonce: &[u8; 32], proof: &AuthProof) -> bool {
    use hmac::{KeyInit, Mac};
    let mut mac =
        hmac::Hmac::<sha2::Sha256>::new_from_slice(secret).expect("HMAC takes keys of any length");
    mac.update(AUTH_CONTEXT);
    mac.update(nonce);
    mac.verify_slice(&proof.mac).is_ok()
}

/// The peer side of the handshake, without I/O: say what to send, read what comes back.
pub struct PeerHandshake {
    secret: Option<Vec<u8>>,
    proved: bool,
}

/// What the peer does next.
#[derive(Debug, PartialEq, Eq)]
pub enum PeerStep {
    /// Send this frame body and read the next `Welcome`.
    Send(Vec<u8>),
    /// The connection is open.
    Accepted,
}

/// Why a peer's handshake failed.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum PeerHandshakeError {
    #[error("refused: {0}")]
    Refused(String),
    #[error("a token is required: give --token-file FILE or set TESSERA_TOKEN")]
    TokenRequired,
    #[error("does not answer like a Tessera coordinator: {0}")]
    NotACoordinator(String),
}

impl PeerHandshake {
    /// A handshake that proves `secret` if the coordinator asks for it.
    pub fn new(secret: Option<Vec<u8>>) -> Self {
        PeerHandshake {
            secret,
            proved: false,
        }
    }

    /// Reads one `Welcome` frame.
    pub fn on_frame(&mut self, frame: &[u8]) -> Result<PeerStep, PeerHandshakeError> {
        match wire::decode::<Welcome>(frame) {
            Ok(Welcome::Accepted { .. }) => Ok(PeerStep::Accepted),
            Ok(Welcome::Refused { reason }) => Err(PeerHandshakeError::Refused(reason)),
            Ok(Welcome::Challenge { nonce }) if !self.proved => match &self.secret {
                Some(secret) => {
                    self.proved = true;
                    Ok(PeerStep::Send(wire::encode(&prove(secret, &nonce))))
                }
                None => Err(PeerHandshakeError::TokenRequired),
            },
            Ok(Welcome::Challenge { .. }) => Err(PeerHandshakeError::NotACoordinator(
                "a second challenge".into(),
            )),
            Err(e) => Err(PeerHandshakeError::NotACoordinator(e.to_string())),
        }
    }
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
        wire::decode(frame).map_err(|e| HelloError::Malformed(e.detail().to_string()))
    }

    /// The frame body of this hello.
    pub fn to_frame(&self) -> Vec<u8> {
        wire::encode(self)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_proof_passes_only_with_the_same_secret_and_nonce() {
        let nonce = [7u8; 32];
        let proof = prove(b"s3cret", &nonce);
        assert!(verify(b"s3cret", &nonce, &proof));
        assert!(!verify(b"s3cre", &nonce, &proof));
        assert!(!verify(b"s3cret", &[8u8; 32], &proof));
    }

    #[test]
    fn the_peer_answers_a_challenge_once_and_needs_a_secret() {
        let challenge = wire::encode(&Welcome::Challenge { nonce: [1; 32] });
        let accepted = wire::encode(&Welcome::Accepted {
            version: PROTOCOL_VERSION,
        });
        let mut peer = PeerHandshake::new(Some(b"k".to_vec()));
        let PeerStep::Send(frame) = peer.on_frame(&challenge).unwrap() else {
            panic!("expected a proof");
        };
        let proof: AuthProof = wire::decode(&frame).unwrap();
        assert!(verify(b"k", &[1; 32], &proof));
        assert!(peer.on_frame(&challenge).is_err(), "a second challenge");
        assert_eq!(peer.on_frame(&accepted).unwrap(), PeerStep::Accepted);

        let mut anonymous = PeerHandshake::new(None);
        assert_eq!(
            anonymous.on_frame(&challenge).unwrap_err(),
            PeerHandshakeError::TokenRequired
        );
        let refused = wire::encode(&Welcome::Refused {
            reason: "no".into(),
        });
        assert_eq!(
            anonymous.on_frame(&refused).unwrap_err(),
            PeerHandshakeError::Refused("no".into())
        );
    }
}
