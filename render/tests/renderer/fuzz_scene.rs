//! Property-based fuzzing of scene loading: whatever the text, `parse_scene` returns a
//! scene or one line saying what is wrong and where. It never panics, and a scene it
//! accepts renders without panicking.
//!
//! Inputs are the seed scene mutated (bytes flipped, inserted, deleted, spans
//! duplicated), structured JSON with random values in the scene's keys, and raw bytes.
//! Any input found to crash is kept in `REGRESSIONS` below.

use proptest::prelude::*;
use render::{parse_scene, render_tile, Rect, RenderSettings, Tracer};

use crate::support::SEED;

/// Inputs that once crashed or misbehaved; each must load or fail cleanly.
const REGRESSIONS: &[&str] = &[
    // A key with a line break made a two-line error (found by this fuzzer).
    "{\"lights\": [], \"objects\": [{\"type\": \"sphere\", \"ce\\nter\": \"0 0 0\"}]}",
    // The same inside an object type and a vector word.
    "{\"lights\": [], \"objects\": [{\"type\": \"sph\\nere\"}]}",
    "{\"lights\": [{\"position\": \"1 2 x\\u0007\", \"color\": \"1 1 1\"}], \"objects\": []}",
    // A camera that looks straight down, nearly: the right axis underflows.
    r#"{"lights": [], "objects": [], "camera": {"position": "0 1 0", "look_at": "1e-300 0 0"}}"#,
    // Numbers Rust's parser accepts but a scene must not contain.
    r#"{"lights": [{"position": "inf 0 0", "color": "1 1 1"}], "objects": []}"#,
    r#"{"lights": [], "objects": [{"type": "sphere", "center": "NaN 0 0", "radius": 1, "color": "1 1 1 0"}]}"#,
    // A radius so small its square underflows.
    r#"{"lights": [], "objects": [{"type": "sphere", "center": "0 0 0", "radius": 1e-200, "color": "1 1 1 0"}]}"#,
    // A normal whose length overflows.
    r#"{"lights": [], "objects": [{"type": "plane", "normal": "1e200 1e200 0", "distance": 0, "color": "1 1 1 0"}]}"#,
];

/// Loads, and renders a few pixels of anything that loads, at a tiny size.
fn check(text: &str) {
    match parse_scene(text) {
        Ok(scene) => {
            let settings = RenderSettings {
                width: 4,
                height: 3,
                aa: 1,
                max_depth: scene.settings.max_depth.min(4),
                ..scene.settings
            };
            let tracer = Tracer::new(&scene, settings);
            let tile = render_tile(
                &tracer,
                Rect {
                    x: 0,
                    y: 0,
                    width: 4,
                    height: 3,
                },
            )
            .unwrap();
            assert_eq!(tile.rgb.len(), 36);
        }
        Err(e) => {
            let message = e.to_string();
            assert!(
                !message.is_empty() && !message.contains('\n'),
                "{message:?}"
            );
        }
    }
}

#[test]
fn regressions_load_or_fail_cleanly() {
    for text in REGRESSIONS {
        check(text);
    }
}

fn mutated_seed() -> impl Strategy<Value = String> {
    let bytes = SEED.as_bytes().to_vec();
    let len = bytes.len();
    prop::collection::vec((0..len, any::<u8>(), 0u8..4), 1..8).prop_map(move |edits| {
        let mut b = bytes.clone();
        for (at, byte, kind) in edits {
            let at = at.min(b.len().saturating_sub(1));
            match kind {
                0 => b[at] = byte,
                1 => b.insert(at, byte),
                2 => {
                    b.remove(at);
                }
                _ => {
                    let end = (at + 16).min(b.len());
                    let span = b[at..end].to_vec();
                    b.splice(at..at, span);
                }
            }
        }
        String::from_utf8_lossy(&b).into_owned()
    })
}

fn number() -> impl Strategy<Value = String> {
    prop_oneof![
        any::<f64>().prop_map(|x| format!("{x}")),
        (-10i32..10).prop_map(|x| x.to_string()),
        Just("1e308".to_string()),
        Just("-0".to_string()),
        Just("\"x\"".to_string()),
        Just("null".to_string()),
        Just("[1, 2]".to_string()),
    ]
}

fn vector() -> impl Strategy<Value = String> {
    prop_oneof![
        (number(), number(), number()).prop_map(|(a, b, c)| format!("[{a}, {b}, {c}]")),
        (any::<f32>(), any::<f32>(), any::<f32>())
            .prop_map(|(a, b, c)| format!("\" {a} {b} {c} \"")),
        "[ -~]{0,12}".prop_map(|s| format!("{s:?}")),
    ]
}

fn structured() -> impl Strategy<Value = String> {
    let object = prop_oneof![
        (vector(), number(), vector()).prop_map(|(c, r, col)| format!(
            r#"{{"type": "sphere", "center": {c}, "radius": {r}, "color": {col}}}"#
        )),
        (vector(), number(), vector()).prop_map(|(n, d, col)| format!(
            r#"{{"type": "plan", "normal": {n}, "distance": {d}, "color": {col}}}"#
        )),
    ];
    (
        prop::collection::vec(object, 0..4),
        prop::collection::vec((vector(), vector()), 0..3),
        (vector(), vector()),
        (0u32..5, 0u32..5, 0u32..4, number()),
    )
        .prop_map(|(objects, lights, (pos, at), (w, h, aa, ambient))| {
            let lights: Vec<String> = lights
                .into_iter()
                .map(|(p, c)| format!(r#"{{"position": {p}, "color": {c}}}"#))
                .collect();
            format!(
                r#"{{"lights": [{}], "objects": [{}], "camera": {{"position": {pos}, "look_at": {at}}},
                    "image": {{"width": {w}, "height": {h}, "aa": {aa}}}, "ambient": {ambient}}}"#,
                lights.join(", "),
                objects.join(", ")
            )
        })
}

/// 2000 cases per property in CI; set `TESSERA_FUZZ_CASES` for a long run.
fn cases() -> u32 {
    std::env::var("TESSERA_FUZZ_CASES")
        .ok()
        .and_then(|n| n.parse().ok())
        .unwrap_or(2000)
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(cases()))]

    #[test]
    fn mutated_seed_scenes_load_or_fail_cleanly(text in mutated_seed()) {
        check(&text);
    }

    #[test]
    fn structured_scenes_load_or_fail_cleanly(text in structured()) {
        check(&text);
    }

    #[test]
    fn raw_bytes_load_or_fail_cleanly(bytes in prop::collection::vec(any::<u8>(), 0..256)) {
        check(&String::from_utf8_lossy(&bytes));
    }
}
