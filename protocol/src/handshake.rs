//! The first frame of every connection: who is speaking, and in which version.
//!
//! Its layout is fixed for all versions so that a peer of another version can always be
//! told what is wrong: 4 magic bytes, a u16 version (little-endian), then the role.

use serde::{Deserialize, Serialize};

use crate::wire;

/// The first four bytes of every `Hello`: "TSRA".
pub const MAGIC: [u8; 4] = *b"TSRA";

/// Bumped whenever any message changes shape.
pub const PROTOCOL_VERSION: u16 = 14;

/// The peer's first frame.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Hello {
    pub magic: [u8; 4],
    pub version: u16,
    pub role: Role,
    /// Fresh random bytes of the peer, so that the coordinator's proof (in
    /// [`Welcome::Challenge`]) is made for this connection and cannot be replayed from
    /// an earlier one. A peer without a secret checks nothing and may send zeros.
    pub nonce: [u8; 32],
    /// Which secret the peer holds ([`KeyId::of`] it), if it holds one. The coordinator
    /// proves its secret first, so it must know which one to prove: while a rotated
    /// token's overlap window is open it holds two per role.
    pub key: Option<KeyId>,
}

/// A short name for a secret that reveals nothing of it: the first 4 bytes of
/// SHA-256 over a fixed label and the secret. Peers send it in their [`Hello`] so that
/// the coordinator knows which of its secrets to prove; logs and listings show it (as 8
/// hex digits) to say which secret a peer used, and operators compare it between
/// machines without copying tokens around.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct KeyId(pub [u8; 4]);

/// The label hashed before the secret, so that a key id is no plain SHA-256 of the
/// token that could be looked up elsewhere.
const KEY_ID_LABEL: &[u8] = b"tessera key id v1\0";

impl KeyId {
    /// The key id of `secret`.
    pub fn of(secret: &[u8]) -> KeyId {
        use sha2::{Digest, Sha256};
        let digest = Sha256::new()
            .chain_update(KEY_ID_LABEL)
            .chain_update(secret)
            .finalize();
        KeyId([digest[0], digest[1], digest[2], digest[3]])
    }
}

impl std::fmt::Display for KeyId {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        for b in self.0 {
            write!(f, "{b:02x}")?;
        }
        Ok(())
    }
}

/// What the peer is.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Role {
    /// Submits jobs and asks about them.
    Client,
    /// Renders tiles with `threads` threads; `name` identifies it in listings and logs.
    /// `build` names the worker's renderer build (version, target, profile): shown in
    /// listings and logs, and named when its canary render does not match. `tags`
    /// name the pools it belongs to ([`check_tags`](crate::check_tags)): a job that
    /// requires tags goes only to workers that have them all.
    Worker {
        name: String,
        threads: u32,
        build: String,
        tags: Vec<String>,
    },
}

/// The two kinds of peer, each with its own secret: a client's token cannot join as a
/// worker, and a worker's token cannot submit jobs.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum AuthRole {
    Client,
    Worker,
}

impl AuthRole {
    /// "client" or "worker", as messages name the role.
    pub fn name(self) -> &'static str {
        match self {
            AuthRole::Client => "client",
            AuthRole::Worker => "worker",
        }
    }
}

impl std::fmt::Display for AuthRole {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl Role {
    /// Which secret this role proves.
    pub fn auth_role(&self) -> AuthRole {
        match self {
            Role::Client => AuthRole::Client,
            Role::Worker { .. } => AuthRole::Worker,
        }
    }
}

/// The coordinator's answer to a `Hello` (and to an [`AuthProof`]).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Welcome {
    /// The connection is open for the role's messages.
    Accepted { version: u16 },
    /// The connection is refused and will be closed; `reason` says why.
    Refused { reason: String },
    /// The coordinator requires the role's secret. It proves first that it knows it
    /// (`proof`, see [`coordinator_proof`]) over the peer's nonce and its own fresh
    /// `nonce`; the peer checks that proof, then answers with an [`AuthProof`]. Neither
    /// secret ever crosses the network.
    Challenge { nonce: [u8; 32], proof: [u8; 32] },
}

/// The peer's answer to a [`Welcome::Challenge`] whose proof it accepted: see
/// [`peer_proof`].
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct AuthProof {
    pub mac: [u8; 32],
}

/// Who proves to whom: the first bytes of every MAC, one label per direction and role,
/// so that no proof can pass for another direction or for the other role. All four are
/// 30 ASCII bytes long, so none is a prefix of another.
pub fn auth_label(by_coordinator: bool, role: AuthRole) -> &'static [u8] {
    match (by_coordinator, role) {
        (true, AuthRole::Worker) => b"tessera-v3 coordinator->worker",
        (true, AuthRole::Client) => b"tessera-v3 coordinator->client",
        (false, AuthRole::Worker) => b"tessera-v3 worker->coordinator",
        (false, AuthRole::Client) => b"tessera-v3 client->coordinator",
    }
}

/// HMAC-SHA256 keyed with `secret` over `label ‖ peer_nonce ‖ coordinator_nonce`.
fn mac(
    secret: &[u8],
    label: &[u8],
    peer_nonce: &[u8; 32],
    coordinator_nonce: &[u8; 32],
) -> hmac::Hmac<sha2::Sha256> {
    use hmac::{KeyInit, Mac};
    let mut mac =
        hmac::Hmac::<sha2::Sha256>::new_from_slice(secret).expect("HMAC takes keys of any length");
    mac.update(label);
    mac.update(peer_nonce);
    mac.update(coordinator_nonce);
    mac
}

/// The coordinator's proof of knowing `role`'s secret, for this pair of nonces.
pub fn coordinator_proof(
    secret: &[u8],
    role: AuthRole,
    peer_nonce: &[u8; 32],
    coordinator_nonce: &[u8; 32],
) -> [u8; 32] {
    use hmac::Mac;
    mac(
        secret,
        auth_label(true, role),
        peer_nonce,
        coordinator_nonce,
    )
    .finalize()
    .into_bytes()
    .into()
}

/// The peer's proof of knowing `role`'s secret, for this pair of nonces.
pub fn peer_proof(
    secret: &[u8],
    role: AuthRole,
    peer_nonce: &[u8; 32],
    coordinator_nonce: &[u8; 32],
) -> AuthProof {
    use hmac::Mac;
    AuthProof {
        mac: mac(
            secret,
            auth_label(false, role),
            peer_nonce,
            coordinator_nonce,
        )
        .finalize()
        .into_bytes()
        .into(),
    }
}

/// Checks a MAC in constant time.
fn verify_mac(
    secret: &[u8],
    label: &[u8],
    peer_nonce: &[u8; 32],
    coordinator_nonce: &[u8; 32],
    claimed: &[u8; 32],
) -> bool {
    use hmac::Mac;
    mac(secret, label, peer_nonce, coordinator_nonce)
        .verify_slice(claimed)
        .is_ok()
}

/// The peer side of the handshake, without I/O: the `Hello` to send, then what to do
/// with each `Welcome` that comes back.
pub struct PeerHandshake {
    role: Role,
    secret: Option<Vec<u8>>,
    nonce: [u8; 32],
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

/// Why a peer's handshake failed. Each text is one line, meant to follow "the
/// coordinator at ADDR: ".
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum PeerHandshakeError {
    #[error("refused: {0}")]
    Refused(String),
    #[error(
        "a token is required: it asks {role}s for the farm's {role} token (give --token-file \
         FILE or set TESSERA_TOKEN)"
    )]
    TokenRequired { role: AuthRole },
    /// It accepted without proving that it knows the secret this peer holds.
    #[error(
        "authentication failed: it accepted this {role} without proving that it knows the \
         {role} token, so it is not the farm's coordinator (or it runs without a {role} \
         token); refusing it"
    )]
    Unproven { role: AuthRole },
    /// Its proof does not match the secret this peer holds. The peer cannot tell an
    /// impostor from a token of the wrong role or farm: both look the same from here.
    #[error(
        "authentication failed: it does not prove that it knows this {role} token (it is not \
         the farm's coordinator, or this is not the farm's {role} token: another role's, \
         another farm's, or mistyped); refusing it"
    )]
    WrongProof { role: AuthRole },
    #[error("does not answer like a Tessera coordinator: {0}")]
    NotACoordinator(String),
}

impl PeerHandshake {
    /// A handshake as `role`, proving `secret` (and requiring the coordinator to prove
    /// it) if there is one. `nonce` must be fresh random bytes for every connection.
    pub fn new(role: Role, secret: Option<Vec<u8>>, nonce: [u8; 32]) -> Self {
        PeerHandshake {
            role,
            secret,
            nonce,
            proved: false,
        }
    }

    /// The first frame body to send: it names the secret held by its key id.
    pub fn hello(&self) -> Vec<u8> {
        Hello {
            key: self.secret.as_deref().map(KeyId::of),
            ..Hello::with_nonce(self.role.clone(), self.nonce)
        }
        .to_frame()
    }

    /// Reads one `Welcome` frame.
    pub fn on_frame(&mut self, frame: &[u8]) -> Result<PeerStep, PeerHandshakeError> {
        let role = self.role.auth_role();
        match wire::decode::<Welcome>(frame) {
            Ok(Welcome::Accepted { .. }) if self.secret.is_some() && !self.proved => {
                Err(PeerHandshakeError::Unproven { role })
            }
            Ok(Welcome::Accepted { .. }) => Ok(PeerStep::Accepted),
            Ok(Welcome::Refused { reason }) => Err(PeerHandshakeError::Refused(reason)),
            Ok(Welcome::Challenge { .. }) if self.proved => Err(
                PeerHandshakeError::NotACoordinator("a second challenge".into()),
            ),
            Ok(Welcome::Challenge { nonce, proof }) => {
                let Some(secret) = &self.secret else {
                    return Err(PeerHandshakeError::TokenRequired { role });
                };
                let label = auth_label(true, role);
                if !verify_mac(secret, label, &self.nonce, &nonce, &proof) {
                    return Err(PeerHandshakeError::WrongProof { role });
                }
                self.proved = true;
                Ok(PeerStep::Send(wire::encode(&peer_proof(
                    secret,
                    role,
                    &self.nonce,
                    &nonce,
                ))))
            }
            Err(e) => Err(PeerHandshakeError::NotACoordinator(e.to_string())),
        }
    }
}

/// The coordinator side of authentication, without I/O: the challenge for a peer's
/// `Hello`, then the check of its answer.
pub struct CoordinatorChallenge {
    role: AuthRole,
    secret: Vec<u8>,
    peer_nonce: [u8; 32],
    nonce: [u8; 32],
}

/// Why a peer's answer to a challenge is refused.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("authentication failed: the proof does not match this coordinator's {role} token")]
pub struct AuthFailure {
    pub role: AuthRole,
}

impl CoordinatorChallenge {
    /// A challenge for `hello`'s role, proving `secret` (that role's); `nonce` must be
    /// fresh random bytes.
    pub fn new(hello: &Hello, secret: &[u8], nonce: [u8; 32]) -> Self {
        CoordinatorChallenge {
            role: hello.role.auth_role(),
            secret: secret.to_vec(),
            peer_nonce: hello.nonce,
            nonce,
        }
    }

    /// The `Welcome::Challenge` to send.
    pub fn welcome(&self) -> Welcome {
        Welcome::Challenge {
            nonce: self.nonce,
            proof: coordinator_proof(&self.secret, self.role, &self.peer_nonce, &self.nonce),
        }
    }

    /// Checks the peer's answer: exactly an [`AuthProof`] whose MAC matches, compared
    /// in constant time.
    pub fn check(&self, frame: &[u8]) -> Result<(), AuthFailure> {
        let failure = AuthFailure { role: self.role };
        let proof = wire::decode::<AuthProof>(frame).map_err(|_| failure.clone())?;
        let label = auth_label(false, self.role);
        if verify_mac(
            &self.secret,
            label,
            &self.peer_nonce,
            &self.nonce,
            &proof.mac,
        ) {
            Ok(())
        } else {
            Err(failure)
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
    /// This version's hello for `role`, with an all-zero nonce: for a peer without a
    /// secret, which checks no proof.
    pub fn new(role: Role) -> Self {
        Hello::with_nonce(role, [0; 32])
    }

    /// This version's hello for `role`, with the peer's fresh `nonce` and no key id
    /// (see [`PeerHandshake::hello`] for a peer with a secret).
    pub fn with_nonce(role: Role, nonce: [u8; 32]) -> Self {
        Hello {
            magic: MAGIC,
            version: PROTOCOL_VERSION,
            role,
            nonce,
            key: None,
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

    const PEER_NONCE: [u8; 32] = [1; 32];
    const COORDINATOR_NONCE: [u8; 32] = [2; 32];

    fn worker() -> Role {
        Role::Worker {
            name: "w".into(),
            threads: 1,
            build: "b".into(),
            tags: Vec::new(),
        }
    }

    fn accepted() -> Vec<u8> {
        wire::encode(&Welcome::Accepted {
            version: PROTOCOL_VERSION,
        })
    }

    /// The coordinator's side for `peer`'s hello, proving `secret`.
    fn challenger(peer: &PeerHandshake, secret: &[u8]) -> CoordinatorChallenge {
        let hello = Hello::from_frame(&peer.hello()).unwrap();
        CoordinatorChallenge::new(&hello, secret, COORDINATOR_NONCE)
    }

    #[test]
    fn both_sides_prove_the_secret_and_the_connection_opens() {
        for role in [Role::Client, worker()] {
            let mut peer = PeerHandshake::new(role.clone(), Some(b"k".to_vec()), PEER_NONCE);
            let hello = Hello::from_frame(&peer.hello()).unwrap();
            assert_eq!(
                hello.nonce, PEER_NONCE,
                "the hello carries the peer's nonce"
            );
            assert_eq!(hello.role, role);
            let coordinator = challenger(&peer, b"k");
            let PeerStep::Send(answer) = peer
                .on_frame(&wire::encode(&coordinator.welcome()))
                .unwrap()
            else {
                panic!("expected the peer's proof");
            };
            assert_eq!(coordinator.check(&answer), Ok(()));
            assert_eq!(peer.on_frame(&accepted()).unwrap(), PeerStep::Accepted);
        }
    }

    #[test]
    fn a_peer_refuses_a_coordinator_that_does_not_prove_the_secret() {
        // Accepted without any challenge.
        let mut peer = PeerHandshake::new(worker(), Some(b"k".to_vec()), PEER_NONCE);
        assert_eq!(
            peer.on_frame(&accepted()).unwrap_err(),
            PeerHandshakeError::Unproven {
                role: AuthRole::Worker
            }
        );
        // A challenge whose proof is made with another secret, or garbage.
        let mut peer = PeerHandshake::new(worker(), Some(b"k".to_vec()), PEER_NONCE);
        let impostor = challenger(&peer, b"not k");
        assert_eq!(
            peer.on_frame(&wire::encode(&impostor.welcome()))
                .unwrap_err(),
            PeerHandshakeError::WrongProof {
                role: AuthRole::Worker
            }
        );
        let mut peer = PeerHandshake::new(Role::Client, Some(b"k".to_vec()), PEER_NONCE);
        let garbage = Welcome::Challenge {
            nonce: COORDINATOR_NONCE,
            proof: [0; 32],
        };
        assert!(matches!(
            peer.on_frame(&wire::encode(&garbage)),
            Err(PeerHandshakeError::WrongProof { .. })
        ));
        // After a refused challenge the peer never accepts either.
        assert!(peer.on_frame(&accepted()).is_err());
    }

    #[test]
    fn a_proof_for_another_role_direction_or_nonce_never_passes() {
        let secret = b"shared by mistake";
        // The coordinator's proof for a client does not pass for a worker.
        let mut as_worker = PeerHandshake::new(worker(), Some(secret.to_vec()), PEER_NONCE);
        let client_proof =
            coordinator_proof(secret, AuthRole::Client, &PEER_NONCE, &COORDINATOR_NONCE);
        let replay = Welcome::Challenge {
            nonce: COORDINATOR_NONCE,
            proof: client_proof,
        };
        assert!(matches!(
            as_worker.on_frame(&wire::encode(&replay)),
            Err(PeerHandshakeError::WrongProof { .. })
        ));
        // A peer's own proof reflected back as the coordinator's does not pass.
        let mut peer = PeerHandshake::new(worker(), Some(secret.to_vec()), PEER_NONCE);
        let reflected = peer_proof(secret, AuthRole::Worker, &PEER_NONCE, &COORDINATOR_NONCE);
        let reflection = Welcome::Challenge {
            nonce: COORDINATOR_NONCE,
            proof: reflected.mac,
        };
        assert!(peer.on_frame(&wire::encode(&reflection)).is_err());
        // The coordinator's proof does not pass as a peer's, nor a client's as a worker's.
        let worker_hello = Hello::with_nonce(worker(), PEER_NONCE);
        let coordinator = CoordinatorChallenge::new(&worker_hello, secret, COORDINATOR_NONCE);
        let Welcome::Challenge { proof, .. } = coordinator.welcome() else {
            panic!("a challenge");
        };
        let failure = AuthFailure {
            role: AuthRole::Worker,
        };
        assert_eq!(
            coordinator.check(&wire::encode(&AuthProof { mac: proof })),
            Err(failure.clone())
        );
        let as_client = peer_proof(secret, AuthRole::Client, &PEER_NONCE, &COORDINATOR_NONCE);
        assert_eq!(
            coordinator.check(&wire::encode(&as_client)),
            Err(failure.clone())
        );
        // A proof for another coordinator nonce or another peer nonce fails too.
        let stale = peer_proof(secret, AuthRole::Worker, &PEER_NONCE, &[9; 32]);
        assert_eq!(
            coordinator.check(&wire::encode(&stale)),
            Err(failure.clone())
        );
        let other_peer = peer_proof(secret, AuthRole::Worker, &[9; 32], &COORDINATOR_NONCE);
        assert_eq!(
            coordinator.check(&wire::encode(&other_peer)),
            Err(failure.clone())
        );
        // Not an AuthProof at all.
        assert_eq!(coordinator.check(b"short"), Err(failure));
        assert_eq!(
            coordinator.check(&wire::encode(&peer_proof(
                secret,
                AuthRole::Worker,
                &PEER_NONCE,
                &COORDINATOR_NONCE
            ))),
            Ok(())
        );
    }

    #[test]
    fn the_peer_answers_one_challenge_and_needs_a_secret() {
        let mut peer = PeerHandshake::new(Role::Client, Some(b"k".to_vec()), PEER_NONCE);
        let coordinator = challenger(&peer, b"k");
        let challenge = wire::encode(&coordinator.welcome());
        assert!(matches!(peer.on_frame(&challenge), Ok(PeerStep::Send(_))));
        assert_eq!(
            peer.on_frame(&challenge).unwrap_err(),
            PeerHandshakeError::NotACoordinator("a second challenge".into())
        );

        let mut anonymous = PeerHandshake::new(worker(), None, PEER_NONCE);
        assert_eq!(
            anonymous.on_frame(&challenge).unwrap_err(),
            PeerHandshakeError::TokenRequired {
                role: AuthRole::Worker
            }
        );
        // Without a secret, a coordinator without one is fine.
        let mut open = PeerHandshake::new(Role::Client, None, PEER_NONCE);
        assert_eq!(open.on_frame(&accepted()).unwrap(), PeerStep::Accepted);
        let refused = wire::encode(&Welcome::Refused {
            reason: "no".into(),
        });
        assert_eq!(
            anonymous.on_frame(&refused).unwrap_err(),
            PeerHandshakeError::Refused("no".into())
        );
        assert!(matches!(
            anonymous.on_frame(b"\x07\x00\x00\x00"),
            Err(PeerHandshakeError::NotACoordinator(_))
        ));
    }

    #[test]
    fn a_key_id_names_a_secret_without_being_a_plain_hash_of_it() {
        // The example of docs/protocol.md.
        assert_eq!(KeyId::of(b"s3cret"), KeyId([0x97, 0x22, 0x1d, 0xf8]));
        assert_eq!(KeyId::of(b"s3cret").to_string(), "97221df8");
        assert_ne!(KeyId::of(b"s3cret"), KeyId::of(b"s3cret "));
        use sha2::{Digest, Sha256};
        assert_ne!(KeyId::of(b"s3cret").0, Sha256::digest(b"s3cret")[..4]);
        // A peer names its secret's key id in its hello; without one, none.
        let peer = PeerHandshake::new(worker(), Some(b"k".to_vec()), PEER_NONCE);
        let hello = Hello::from_frame(&peer.hello()).unwrap();
        assert_eq!(hello.key, Some(KeyId::of(b"k")));
        let anonymous = PeerHandshake::new(Role::Client, None, PEER_NONCE);
        assert_eq!(Hello::from_frame(&anonymous.hello()).unwrap().key, None);
    }

    #[test]
    fn a_hello_of_the_previous_version_is_refused_naming_both() {
        let mut frame = Hello::new(Role::Client).to_frame();
        frame[4..6].copy_from_slice(&13u16.to_le_bytes());
        let error = Hello::from_frame(&frame).unwrap_err();
        assert_eq!(
            error.to_string(),
            "protocol version mismatch: this coordinator speaks version 14, the peer speaks \
             version 13"
        );
    }

    #[test]
    fn the_labels_are_distinct_and_equally_long() {
        let labels: Vec<&[u8]> = [true, false]
            .into_iter()
            .flat_map(|c| [AuthRole::Client, AuthRole::Worker].map(|r| auth_label(c, r)))
            .collect();
        for (i, a) in labels.iter().enumerate() {
            assert_eq!(a.len(), 30, "{}", String::from_utf8_lossy(a));
            for b in &labels[i + 1..] {
                assert_ne!(a, b);
            }
        }
    }

    #[test]
    fn failures_are_one_line_naming_the_role() {
        for error in [
            PeerHandshakeError::TokenRequired {
                role: AuthRole::Client,
            },
            PeerHandshakeError::Unproven {
                role: AuthRole::Client,
            },
            PeerHandshakeError::WrongProof {
                role: AuthRole::Client,
            },
        ] {
            let text = error.to_string();
            assert!(
                !text.contains('\n') && text.contains("client token"),
                "{text}"
            );
        }
        assert_eq!(
            AuthFailure {
                role: AuthRole::Worker
            }
            .to_string(),
            "authentication failed: the proof does not match this coordinator's worker token"
        );
    }
}
