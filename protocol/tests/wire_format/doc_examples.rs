//! The worked examples of `docs/protocol.md` (section 3) are exactly what the encoder
//! produces: every `text` block there, read as hex bytes, equals the frame of the
//! message it describes, in order. A change of any message's shape fails here until
//! the documentation shows the new bytes.

use protocol::{
    wire, AuthRole, ClientRequest, ClientResponse, FromWorker, Hello, JobAssets, JobSpec, JobState,
    JobStatus, KeyId, Overrides, Role, Sampling, Settings, TileRect, ToWorker, Verification,
    Welcome, MAGIC, PROTOCOL_VERSION,
};
use serde::Serialize;

use crate::frame;

const DOC: &str = include_str!("../../../docs/protocol.md");
const SCENE: &str = r#"{"lights": [], "objects": []}"#;

/// The job of the examples: 34 × 17 pixels, adaptive sampling with a 4 × 4 budget and a
/// target of one level.
const SETTINGS: Settings = Settings {
    width: 34,
    height: 17,
    aa: 4,
    max_depth: 10,
    sampling: Sampling::Adaptive { target_milli: 1000 },
};

fn scene_hash() -> [u8; 32] {
    use sha2::{Digest, Sha256};
    Sha256::digest(SCENE.as_bytes()).into()
}

/// The coordinator's nonce in the authentication examples: 00, 01, … 1f.
fn nonce() -> [u8; 32] {
    std::array::from_fn(|i| i as u8)
}

/// The peer's nonce in the examples' hellos: 20, 21, … 3f.
fn peer_nonce() -> [u8; 32] {
    std::array::from_fn(|i| 0x20 + i as u8)
}

/// The secret of the authentication examples: a client token file holding `s3cret`.
const SECRET: &[u8] = b"s3cret";

/// A message as a frame: big-endian length, then the body.
fn message_frame<T: Serialize>(message: &T) -> Vec<u8> {
    frame(&wire::encode(message)).to_vec()
}

/// The examples, in the order the document gives them.
fn examples() -> Vec<(&'static str, Vec<u8>)> {
    vec![
        (
            "worker Hello",
            message_frame(&Hello {
                magic: MAGIC,
                version: PROTOCOL_VERSION,
                role: Role::Worker {
                    name: "w1".into(),
                    threads: 4,
                    build: "b".into(),
                    tags: vec!["gpu".into()],
                },
                nonce: peer_nonce(),
                key: None,
            }),
        ),
        (
            "client Hello",
            message_frame(&Hello {
                key: Some(KeyId::of(SECRET)),
                ..Hello::with_nonce(Role::Client, peer_nonce())
            }),
        ),
        (
            "Welcome::Accepted",
            message_frame(&Welcome::Accepted {
                version: PROTOCOL_VERSION,
            }),
        ),
        (
            "Submit",
            message_frame(&ClientRequest::Submit(JobSpec {
                scene: SCENE.into(),
                overrides: Overrides {
                    width: Some(34),
                    height: Some(17),
                    aa: Some(4),
                    max_depth: None,
                    tile_size: Some(16),
                    sampling: Some(Sampling::Adaptive { target_milli: 1000 }),
                },
                priority: -1,
                verification: Verification::Sampled,
                time_limit_ms: None,
                name: "n".into(),
                submitter: "u@h".into(),
                frame: 1,
                frames: None,
                assets: Vec::new(),
                after: Vec::new(),
                require: vec!["gpu".into()],
            })),
        ),
        ("Status", message_frame(&ClientRequest::Status { job: 7 })),
        (
            "Job",
            message_frame(&ClientResponse::Job(JobStatus {
                id: 7,
                state: JobState::Running,
                settings: SETTINGS,
                priority: -1,
                tiles_done: 5,
                tiles_total: 6,
                rays: 2304,
                elapsed_ms: 20,
                eta_ms: None,
                error: None,
                samples: 2304,
                estimated_error: Some(0.0),
                time_limit_ms: None,
                stopped_on_time_limit: false,
                paused: false,
                warning: None,
                name: "n".into(),
                submitter: "u@h".into(),
                submitted_from: "::1".into(),
                submitted_unix_ms: 1_000,
                queued_ms: Some(3),
                frame: 1,
                frames: None,
                sequence: None,
                assets: JobAssets {
                    files: 2,
                    bytes: 5_000,
                },
                after: Vec::new(),
                waiting_for: Vec::new(),
                require: vec!["gpu".into()],
            })),
        ),
        (
            "Scene",
            message_frame(&ToWorker::Scene {
                hash: scene_hash(),
                scene: SCENE.into(),
                assets: Vec::new(),
            }),
        ),
        (
            "Advance",
            message_frame(&ToWorker::Advance {
                job: 7,
                tile: 5,
                scene: scene_hash(),
                frame: 1,
                settings: SETTINGS,
                rect: TileRect {
                    x: 32,
                    y: 16,
                    width: 2,
                    height: 1,
                },
                pass: 0,
                rung: 0,
                previous: None,
            }),
        ),
        (
            "Render",
            message_frame(&ToWorker::Render {
                job: 8,
                tile: 5,
                scene: scene_hash(),
                frame: 1,
                settings: Settings {
                    sampling: Sampling::Jittered,
                    ..SETTINGS
                },
                rect: TileRect {
                    x: 32,
                    y: 16,
                    width: 2,
                    height: 1,
                },
            }),
        ),
        (
            "TileDone",
            message_frame(&FromWorker::TileDone {
                job: 8,
                tile: 5,
                rgb: vec![0xff, 0x80, 0x00, 0x10, 0x20, 0x30],
                rays: 48,
                render_us: 15,
                samples: 32,
                error_sq_sum: 2.25,
            }),
        ),
        (
            "Welcome::Challenge",
            message_frame(&Welcome::Challenge {
                nonce: nonce(),
                proof: protocol::coordinator_proof(
                    SECRET,
                    AuthRole::Client,
                    &peer_nonce(),
                    &nonce(),
                ),
            }),
        ),
        (
            "AuthProof",
            message_frame(&protocol::peer_proof(
                SECRET,
                AuthRole::Client,
                &peer_nonce(),
                &nonce(),
            )),
        ),
    ]
}

/// The bytes of each ```text block of the worked examples: on each line, the hex
/// pairs before the first double space (the rest is the comment).
fn documented() -> Vec<Vec<u8>> {
    let start = DOC
        .find("### Worked examples")
        .expect("docs/protocol.md has worked examples");
    let end = start + DOC[start..].find("\n## 4.").expect("section 4 follows");
    let mut blocks = Vec::new();
    let mut current: Option<Vec<u8>> = None;
    for line in DOC[start..end].lines() {
        match (line.trim(), current.as_mut()) {
            ("```text", None) => current = Some(Vec::new()),
            ("```", Some(_)) => blocks.push(current.take().expect("in a block")),
            (_, Some(bytes)) => {
                let hex = line.split("  ").next().unwrap_or("");
                for pair in hex.split_whitespace() {
                    let byte = u8::from_str_radix(pair, 16)
                        .unwrap_or_else(|_| panic!("not a hex byte: {pair:?} in {line:?}"));
                    bytes.push(byte);
                }
            }
            _ => {}
        }
    }
    blocks
}

fn hex(bytes: &[u8]) -> String {
    bytes
        .chunks(8)
        .map(|c| {
            c.iter()
                .map(|b| format!("{b:02x}"))
                .collect::<Vec<_>>()
                .join(" ")
        })
        .collect::<Vec<_>>()
        .join("\n")
}

#[test]
fn the_worked_examples_are_the_encoders_bytes() {
    let documented = documented();
    let examples = examples();
    assert_eq!(documented.len(), examples.len(), "one block per example");
    for ((name, actual), doc) in examples.iter().zip(&documented) {
        assert!(
            actual == doc,
            "{name}: the document shows\n{}\nthe encoder gives\n{}",
            hex(doc),
            hex(actual)
        );
    }
}

#[test]
fn the_client_hello_of_the_checklist_is_the_encoders() {
    // The checklist shows the bytes before the nonce, which is the peer's own, and
    // the key that follows it: none (00), for a client without a token.
    let bytes = message_frame(&Hello::new(Role::Client));
    assert_eq!(bytes.last(), Some(&0), "no key");
    let spaced = bytes[..bytes.len() - 33]
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect::<Vec<_>>()
        .join(" ");
    assert!(
        DOC.contains(&format!("`{spaced}`")),
        "the checklist should show `{spaced}`"
    );
}

#[test]
fn the_labels_of_section_4_are_the_codes() {
    for by_coordinator in [true, false] {
        for role in [AuthRole::Client, AuthRole::Worker] {
            let label = std::str::from_utf8(protocol::auth_label(by_coordinator, role)).unwrap();
            assert!(
                DOC.contains(&format!("`{label}`")),
                "docs/protocol.md should name the label `{label}`"
            );
        }
    }
}
