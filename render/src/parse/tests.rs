use super::*;

const SEED: &str = include_str!("../../../scenes/seed.json");

fn error_of(text: &str) -> String {
    parse_scene(text).unwrap_err().to_string()
}

/// A minimal valid scene with one object replaced.
fn with_object(object: &str) -> String {
    format!(r#"{{"lights": [], "objects": [{object}]}}"#)
}

#[test]
fn the_seed_scene_loads_with_its_values_and_the_defaults() {
    let s = parse_scene(SEED).unwrap();
    assert_eq!(s.lights.len(), 2);
    assert_eq!(s.lights[1].position, Vec3::new(7.0, 10.0, 10.0));
    assert_eq!(s.objects.len(), 3);
    assert_eq!(
        s.objects[0].shape,
        Shape::Sphere {
            center: Vec3::ZERO,
            radius: 1.0
        }
    );
    assert_eq!(s.objects[1].material, Material::Reflective(0.6));
    assert_eq!(s.objects[2].material, Material::Checker);
    assert_eq!(
        s.objects[2].shape,
        Shape::Plane {
            normal: Vec3::new(0.0, 1.0, 0.0),
            distance: -1.0
        }
    );
    assert_eq!(s.camera, CameraSpec::default());
    assert_eq!(s.settings, RenderSettings::default());
    assert_eq!(s.ambient, 0.2);
}

#[test]
fn vectors_and_colours_may_be_arrays_and_planes_plane() {
    let s = parse_scene(
        r#"{"lights": [{"position": [1, 2, 3], "color": [1, 0.5, 0]}],
                "objects": [{"type": "plane", "normal": [0, 2, 0], "distance": 1,
                             "color": [1, 1, 1, 0]}],
                "camera": {"look_at": "0 0 1"},
                "image": {"width": 32, "aa": 3},
                "ambient": 0.5}"#,
    )
    .unwrap();
    assert_eq!(s.lights[0].color, Vec3::new(1.0, 0.5, 0.0));
    assert_eq!(s.objects[0].material, Material::Matte);
    assert_eq!(s.camera.position, CameraSpec::default().position);
    assert_eq!(s.camera.look_at, Vec3::new(0.0, 0.0, 1.0));
    assert_eq!(
        (s.settings.width, s.settings.height, s.settings.aa),
        (32, 400, 3)
    );
    assert_eq!(s.ambient, 0.5);
}

#[test]
fn errors_name_the_place_and_the_problem() {
    let sphere = |radius: &str| {
        with_object(&format!(
            r#"{{"type": "sphere", "center": "0 0 0", "radius": {radius}, "color": "1 1 1 0"}}"#
        ))
    };
    assert_eq!(
        error_of(&sphere("-1")),
        "objects[0].radius: must be > 0, got -1"
    );
    assert_eq!(
        error_of(&sphere("0")),
        "objects[0].radius: must be > 0, got 0"
    );
    assert_eq!(
        error_of(&sphere("\"big\"")),
        "objects[0].radius: expected a number, got a string"
    );
    assert_eq!(
        error_of(&with_object(
            r#"{"type": "sphere", "center": "0 0 0", "radius": 1, "color": "1 1 1 1.5"}"#
        )),
        "objects[0].color: special (4th number) must be 0, in (0, 1] or 2, got 1.5"
    );
    assert_eq!(
        error_of(&with_object(r#"{"type": "cube"}"#)),
        "objects[0].type: unknown object type \"cube\" (expected \"sphere\", \"plane\", \"triangle\", \"box\" or \"mesh\")"
    );
    assert_eq!(
        error_of(&with_object(
            r#"{"type": "plan", "normal": "0 0 0", "distance": 1, "color": "1 1 1 0"}"#
        )),
        "objects[0].normal: must be a non-zero vector of finite length"
    );
    assert_eq!(
        error_of(&with_object(
            r#"{"type": "sphere", "center": "0 0 inf", "radius": 1, "color": "1 1 1 0"}"#
        )),
        "objects[0].center: must be a finite number, got inf"
    );
    assert_eq!(
        error_of(&with_object(
            r#"{"type": "sphere", "center": "0 0", "radius": 1, "color": "1 1 1 0"}"#
        )),
        "objects[0].center: expected 3 numbers, got 2"
    );
    assert_eq!(
        error_of(&with_object(r#"{"type": "sphere", "centre": "0 0 0"}"#)),
        "objects[0].centre: unknown key (expected one of: type, center, radius, color)"
    );
    assert_eq!(
        error_of(r#"{"lights": []}"#),
        "scene: missing key \"objects\""
    );
    assert_eq!(
        error_of(r#"{"lights": [], "objects": [], "image": {"width": 0}}"#),
        "image.width: must be between 1 and 16384, got 0"
    );
    assert_eq!(
        error_of(r#"{"lights": [], "objects": [], "camera": {"position": "0 5 0"}}"#),
        "camera: the viewing direction (look_at - position) is parallel to the world up axis (0 1 0)"
    );
    assert_eq!(
        error_of("{\"lights\": [],\n \"objects\": [}"),
        "not valid JSON: expected value at line 2, column 14"
    );
}

/// Reads `text` both ways and checks they agree: the same result from
/// `parse_scene` as from the reference, and, whenever the fast reading gives a
/// scene, the reference's scene to the bit (`Debug` tells -0 from 0). Returns the
/// fast reading's answer.
fn agree(text: &str) -> Option<Scene> {
    let reference = parse_reference(text);
    let fast = fast::parse(text);
    if let Some(scene) = &fast {
        match &reference {
            Ok(r) => assert_eq!(format!("{scene:?}"), format!("{r:?}"), "{text}"),
            Err(e) => {
                panic!("the fast reading accepts what the reference refuses ({e}): {text}")
            }
        }
    }
    assert_eq!(
        format!("{:?}", parse_scene(text)),
        format!("{reference:?}"),
        "{text}"
    );
    fast
}

const SCENES: &[&str] = &[
    SEED,
    include_str!("../../../scenes/hall-of-mirrors.json"),
    include_str!("../../../scenes/lights.json"),
    include_str!("../../../scenes/reflections.json"),
    include_str!("../../../scenes/tilted.json"),
];

#[test]
fn the_example_scenes_are_read_the_fast_way_and_agree() {
    for text in SCENES {
        assert!(agree(text).is_some(), "{text}");
    }
}

/// `n` spheres written the way the many-spheres benchmark writes them, after a plane.
fn many_spheres(n: usize, bad: &[(usize, &str)]) -> String {
    let mut objects = vec![
        r#"{"type":"plane","normal":[0,1,0],"distance":-1.0,"color":[0.6,0.6,0.6,0]}"#.to_string(),
    ];
    for i in 0..n {
        let x = i as f64 * 0.37 - 8.0;
        let r = 0.06 + (i % 7) as f64 * 0.01;
        let special = if i % 5 == 0 { "0.5" } else { "0.0" };
        objects.push(format!(
            r#"{{"type":"sphere","center":[{x},{},{}],"radius":{r},"color":[0.3,{},0.9,{special}]}}"#,
            -1.0 + r,
            i as f64 * 1e-3,
            (i % 10) as f64 / 10.0,
        ));
    }
    for &(i, object) in bad {
        objects[i] = object.to_string();
    }
    format!(
        r#"{{"camera":{{"position":[0,5,-9],"look_at":[0,-1,6]}},"image":{{"width":600,"height":400,"aa":1}},"lights":[{{"position":[-6,10,-4],"color":[0.8,0.8,0.8]}}],"objects":[{}]}}"#,
        objects.join(",")
    )
}

#[test]
fn many_objects_are_read_the_fast_way_in_parallel_and_agree() {
    let text = many_spheres(20_000, &[]);
    let scene = agree(&text).expect("the fast reading takes it");
    assert_eq!(scene.objects.len(), 20_001);
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(3)
        .build()
        .unwrap();
    let parallel = pool.install(|| fast::parse(&text)).unwrap();
    let one = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap();
    let sequential = one.install(|| fast::parse(&text)).unwrap();
    assert_eq!(format!("{parallel:?}"), format!("{scene:?}"));
    assert_eq!(format!("{sequential:?}"), format!("{scene:?}"));
}

/// The pieces read in parallel are cut at guesses; guesses past the end of the
/// objects array (here in a long lights array after it) are dropped.
#[test]
fn guessed_cuts_past_the_objects_array_change_nothing() {
    let light = r#"{"position": [1, 2, 3], "color": [1, 1, 1]}"#;
    let lights = vec![light; 40_000].join(",");
    let sphere = r#"{"type": "sphere", "center": [0, 0, 0], "radius": 1, "color": [1, 1, 1, 0]}"#;
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(4)
        .build()
        .unwrap();
    for spheres in [1, 10, 20_000] {
        let objects = vec![sphere; spheres].join(", ");
        let text = format!(r#"{{"objects": [{objects}], "lights": [{lights}], "ambient": 0.5}}"#);
        let scene = pool
            .install(|| agree(&text))
            .expect("the fast reading takes it");
        assert_eq!((scene.objects.len(), scene.lights.len()), (spheres, 40_000));
    }
}

#[test]
fn every_spelling_the_format_allows_is_read_the_fast_way() {
    let text = r#"{
            "ambient": 0,
            "image": {"max_depth": 0, "height": 10, "width": 20, "aa": 2},
            "camera": {"look_at": [1, 2, 3.5]},
            "lights": [{"color": "1 1 1", "position": " 1\t2\n3 "},
                       {"position": [-1, -2e0, 3E-1], "color": [1, 0.5, 0, 7]}],
            "objects": [
                {"type": "sphere", "center": "0 0 0", "radius": 1, "color": "1 1 1 0"},
                {"color": [0.25, 0, 1e-3, 1], "radius": 18446744073709551616,
                 "center": [-0, -9223372036854775809, 1.7976931348623157e308], "type": "sphere"},
                {"type": "plan", "normal": "+1 .5 -0", "distance": -1, "color": "1 1 1 2"},
                {"type": "plane", "normal": [0, 1, 0], "distance": 0.0, "color": [0, 0, 0, 0.5]},
                {"type": "sphere", "center": "1 2 3", "radius": 2.5e-1, "color": "0 0 0 1"},
                {"type": "sphere", "center": "1e-320 0 0", "radius": 1e-200, "color": "0 0 0 0"}
            ]
        }"#;
    let scene = agree(text).expect("the fast reading takes it");
    assert_eq!(scene.objects.len(), 6);
    assert_eq!(scene.lights[1].position, Vec3::new(-1.0, -2.0, 0.3));
    assert_eq!(scene.objects[2].material, Material::Checker);
    assert_eq!(
        scene.objects[4].shape,
        Shape::Sphere {
            center: Vec3::new(1.0, 2.0, 3.0),
            radius: 0.25
        }
    );
}

/// Scenes the fast reading leaves to the reference, and the reference's words for
/// them: unchanged by the fast reading.
#[test]
fn what_the_fast_reading_refuses_is_worded_as_before() {
    let sphere = r#"{"type": "sphere", "center": "0 0 0", "radius": 1, "color": "1 1 1 0"}"#;
    let bad_radius = r#"{"type": "sphere", "center": "0 0 0", "radius": -1, "color": "1 1 1 0"}"#;
    let bad_color = r#"{"type": "sphere", "center": "0 0 0", "radius": 1, "color": "1 1 1 3"}"#;
    let objects = |list: &[&str]| format!(r#"{{"lights": [], "objects": [{}]}}"#, list.join(", "));
    let cases: Vec<(String, &str)> = vec![
        (
            objects(&[bad_radius, sphere, sphere]),
            "objects[0].radius: must be > 0, got -1",
        ),
        (
            objects(&[sphere, bad_radius, sphere]),
            "objects[1].radius: must be > 0, got -1",
        ),
        (
            objects(&[sphere, sphere, bad_radius]),
            "objects[2].radius: must be > 0, got -1",
        ),
        (
            objects(&[sphere, bad_color, bad_radius]),
            "objects[1].color: special (4th number) must be 0, in (0, 1] or 2, got 3",
        ),
        // A syntax error wins over any earlier invalid value.
        (
            format!(r#"{{"lights": [], "objects": [{bad_radius}, {{"type": }}]}}"#),
            "not valid JSON: expected value at line 1, column 110",
        ),
        // Numbers too large for an f64 are a syntax error, even inside an object.
        (
            objects(&[sphere, r#"{"type": "sphere", "radius": 1e999}"#]),
            "not valid JSON: number out of range at line 1, column 133",
        ),
        // Lights come before objects, objects before camera, image and ambient.
        (
            format!(r#"{{"ambient": -1, "objects": [{bad_radius}], "lights": [{{}}]}}"#),
            "lights[0]: missing key \"position\"",
        ),
        (
            format!(r#"{{"ambient": -1, "lights": [], "objects": [{bad_radius}]}}"#),
            "objects[0].radius: must be > 0, got -1",
        ),
        (
            format!(r#"{{"ambient": -1, "lights": [], "objects": [{sphere}], "camera": 5}}"#),
            "camera: expected an object, got a number",
        ),
        (
            format!(r#"{{"ambient": -1, "lights": [], "objects": [{sphere}]}}"#),
            "ambient: must be >= 0, got -1",
        ),
        // `null` is a value, not an absent key.
        (
            format!(r#"{{"lights": [], "objects": [{sphere}], "image": null}}"#),
            "image: expected an object, got null",
        ),
        (
            objects(&[
                r#"{"type": "sphere", "center": "0 0 0", "radius": null, "color": "1 1 1 0"}"#,
            ]),
            "objects[0].radius: expected a number, got null",
        ),
        // Unknown keys are named in sorted order, before missing keys and values.
        (
            r#"{"zeta": 1, "lights": 2, "alpha": 3}"#.to_string(),
            "alpha: unknown key (expected one of: lights, objects, camera, image, ambient, animation)",
        ),
        (
            objects(&[r#"{"type": "sphere", "radius": -1, "shiny": 1, "normal": 2}"#]),
            "objects[0].normal: unknown key (expected one of: type, center, radius, color)",
        ),
        (
            objects(&[r#"{"radius": 1}"#]),
            "objects[0]: missing key \"type\"",
        ),
        (
            objects(&[sphere, "[]"]),
            "objects[1]: expected an object, got an array",
        ),
        (
            objects(&[
                r#"{"type": "sphere", "center": [0, "0", 0], "radius": 1, "color": "1 1 1 0"}"#,
            ]),
            "objects[0].center: expected 3 numbers, found a string in the array",
        ),
        (
            objects(&[
                r#"{"type": "sphere", "center": "0 0 1e400", "radius": 1, "color": "1 1 1 0"}"#,
            ]),
            "objects[0].center: must be a finite number, got inf",
        ),
        (
            objects(&[
                r#"{"type": "sphere", "center": [0, 0, 0, 0, 0], "radius": 1, "color": "1 1 1 0"}"#,
            ]),
            "objects[0].center: expected 3 numbers, got 5",
        ),
        (
            objects(&[
                r#"{"type": "sph\u0065re", "center": "0 0 0", "radius": 1, "color": "1 1 1"}"#,
            ]),
            "objects[0].color: expected 4 numbers (r g b special), got 3",
        ),
        (
            r#"{"lights": [], "objects": {}}"#.to_string(),
            "objects: expected an array, got an object",
        ),
        ("[]".to_string(), "scene: expected an object, got an array"),
        (
            format!("{} x", objects(&[sphere])),
            "not valid JSON: trailing characters at line 1, column 101",
        ),
    ];
    for (text, message) in &cases {
        assert!(fast::parse(text).is_none(), "{text}");
        assert_eq!(&error_of(text), message, "{text}");
        agree(text);
    }
    // The same, far into a large scene.
    let text = many_spheres(5000, &[(3000, bad_radius), (4000, bad_color)]);
    assert_eq!(error_of(&text), "objects[3000].radius: must be > 0, got -1");
    let text = many_spheres(5000, &[(5000, bad_color)]);
    assert_eq!(
        error_of(&text),
        "objects[5000].color: special (4th number) must be 0, in (0, 1] or 2, got 3"
    );
}

/// The fast reading leaves an animated scene to the reference, and agrees with it on
/// the same scene without its animation.
#[test]
fn the_fast_reading_leaves_animations_to_the_reference() {
    let still = SEED.trim_end().strip_suffix('}').unwrap();
    let animated = format!(
        r#"{still}, "animation": {{"frames": 10, "tracks": [{{"target": "objects[0].radius",
                "keys": [{{"frame": 1, "value": 0.5}}, {{"frame": 10, "value": 2}}]}}]}}}}"#
    );
    assert!(fast::parse(&animated).is_none());
    assert!(fast::parse(SEED).is_some());
    agree(&animated);
    agree(SEED);
    // The static part of the animated scene is the seed, read the fast way.
    let a = parse_animated(&animated).unwrap();
    assert_eq!(a.base, fast::parse(SEED).unwrap());
    assert_eq!(parse_animated(SEED).unwrap().animation, None);
    // Without a frame, the animated scene is its frame 1.
    let first = parse_scene(&animated).unwrap();
    assert_eq!(first, a.frame(1).unwrap());
    assert_eq!(
        first.objects[0].shape,
        Shape::Sphere {
            center: Vec3::ZERO,
            radius: 0.5
        }
    );
    // An error in the static part is the static reading's error, animation or not.
    let broken = animated.replacen("\"radius\": 1.0", "\"radius\": -1", 1);
    assert_eq!(error_of(&broken), "objects[0].radius: must be > 0, got -1");
}

/// Scenes the reference accepts but the fast reading leaves to it: same scene.
#[test]
fn what_the_fast_reading_refuses_may_still_be_a_scene() {
    let cases = [
        // A repeated key: the last one counts.
        r#"{"lights": [], "objects": [{"type": "sphere", "center": "0 0 0", "radius": -1,
                "radius": 2, "color": "1 1 1 0"}]}"#,
        r#"{"lights": [{}], "lights": [], "objects": []}"#,
        // Escapes are left to the reference.
        r#"{"lights": [], "objects": [{"type": "sph\u0065re", "c\u0065nter": "\u0031 2 3",
                "radius": 1, "color": "0 0 0 1"}]}"#,
    ];
    for text in cases {
        assert!(fast::parse(text).is_none(), "{text}");
        assert!(parse_scene(text).is_ok(), "{text}");
        agree(text);
    }
    let s = parse_scene(cases[0]).unwrap();
    assert_eq!(
        s.objects[0].shape,
        Shape::Sphere {
            center: Vec3::ZERO,
            radius: 2.0
        }
    );
}

mod differential {
    use super::{agree, fast};
    use proptest::prelude::*;

    fn strings(list: &[&'static str]) -> impl Strategy<Value = String> + Clone {
        prop::sample::select(list.to_vec()).prop_map(str::to_string)
    }

    /// A JSON number: always a number when `clean`, sometimes something else
    /// otherwise. Both kinds include the spellings serde_json reads its own way
    /// (exponents, more than 19 digits, -0).
    fn number(clean: bool, positive: bool) -> BoxedStrategy<String> {
        let odd = strings(&[
            "1e2",
            "1E-2",
            "2.5e+1",
            "0.5",
            "18446744073709551616",
            "12345678901234567890.123",
            "0.00000000000000000000123",
            "1.0000000000000000000001",
        ]);
        let good = if positive {
            prop_oneof![
                4 => (1i32..20).prop_map(|x| x.to_string()),
                4 => (1e-3f64..1e3).prop_map(|x| format!("{x}")),
                1 => odd,
            ]
            .boxed()
        } else {
            prop_oneof![
                4 => (-20i32..20).prop_map(|x| x.to_string()),
                4 => (-1e3f64..1e3).prop_map(|x| format!("{x}")),
                1 => (-1e100f64..1e100).prop_map(|x| format!("{x:e}")),
                1 => strings(&["-0", "-0.0", "-9223372036854775809", "-1e-999"]),
                1 => odd,
            ]
            .boxed()
        };
        if clean {
            return good;
        }
        prop_oneof![
            6 => good,
            1 => strings(&["-1", "0", "1e999", "01", "1.", "\"1\"", "null", "true", "[1]", "{}"]),
        ]
        .boxed()
    }

    fn word(clean: bool) -> BoxedStrategy<String> {
        let good = prop_oneof![
            4 => (-20i32..20).prop_map(|x| x.to_string()),
            4 => (-1e3f64..1e3).prop_map(|x| format!("{x}")),
            1 => strings(&["+.5", "1e3", "-0", "5.", "1234567890123456789012345"]),
        ];
        if clean {
            return good.boxed();
        }
        prop_oneof![
            6 => good,
            1 => strings(&["inf", "NaN", "1e400", "x", "\\u0031", "-"]),
        ]
        .boxed()
    }

    /// A list of numbers, `n` of them when `clean`.
    fn numbers(n: usize, clean: bool) -> BoxedStrategy<String> {
        let count = if clean {
            Just(n).boxed()
        } else {
            prop_oneof![4 => Just(n), 1 => 0..6usize].boxed()
        };
        // White space in an array may be any JSON white space; in a string, a tab or
        // a line break would be a control character.
        (count, any::<bool>(), strings(&["", " ", "  "]))
            .prop_flat_map(move |(count, as_array, pad)| {
                if as_array {
                    let pad = if pad.len() == 2 {
                        "\t\n".to_string()
                    } else {
                        pad
                    };
                    prop::collection::vec(number(clean, false), count)
                        .prop_map(move |v| format!("[{pad}{}{pad}]", v.join(", ")))
                        .boxed()
                } else {
                    prop::collection::vec(word(clean), count)
                        .prop_map(move |v| format!("\"{pad}{}{pad}\"", v.join(" ")))
                        .boxed()
                }
            })
            .boxed()
    }

    fn color(clean: bool) -> BoxedStrategy<String> {
        let channel = if clean {
            strings(&["0", "0.5", "1", "1.5", "0.0", "2e-1"]).boxed()
        } else {
            strings(&["0", "0.5", "1", "-1", "-0", "1e999"]).boxed()
        };
        let special = if clean {
            strings(&["0", "0.5", "1", "2", "0.0", "-0", "2e0"]).boxed()
        } else {
            strings(&["0", "0.5", "1.5", "3", "-1"]).boxed()
        };
        let written = (prop::collection::vec(channel, 3), special, any::<bool>()).prop_map(
            |(rgb, s, as_array)| {
                if as_array {
                    format!("[{}, {s}]", rgb.join(", "))
                } else {
                    format!("\"{} {s}\"", rgb.join(" "))
                }
            },
        );
        if clean {
            written.boxed()
        } else {
            prop_oneof![3 => written, 1 => numbers(4, false)].boxed()
        }
    }

    /// An object with its fields in any order; when not `clean`, sometimes with one
    /// too many, one missing, one repeated, one key spelled with an escape or a value
    /// of the wrong kind.
    fn object(clean: bool) -> BoxedStrategy<String> {
        let kind = if clean {
            strings(&["\"sphere\"", "\"plan\"", "\"plane\""]).boxed()
        } else {
            strings(&[
                "\"sphere\"",
                "\"plan\"",
                "\"sph\\u0065re\"",
                "\"cube\"",
                "1",
                "null",
            ])
            .boxed()
        };
        (
            kind,
            numbers(3, clean),
            (number(clean, true), number(clean, false)),
            color(clean),
            any::<prop::sample::Index>(),
            0u8..if clean { 1 } else { 6 },
            any::<prop::sample::Index>(),
        )
            .prop_map(
                |(kind, vector, (positive, scalar), color, at, change, other)| {
                    let sphere = kind.contains("sph");
                    let (v, s, scalar) = if sphere {
                        ("center", "radius", positive)
                    } else {
                        ("normal", "distance", scalar)
                    };
                    let mut fields = vec![
                        ("type".to_string(), kind.to_string()),
                        (v.to_string(), vector),
                        (s.to_string(), scalar),
                        ("color".to_string(), color),
                    ];
                    let i = at.index(fields.len());
                    let j = other.index(fields.len());
                    fields.swap(i, j);
                    match change {
                        1 => {
                            fields.remove(i);
                        }
                        2 => {
                            let f = fields[j].clone();
                            fields.insert(i, f);
                        }
                        3 => fields.insert(i, ("shiny".to_string(), "1".to_string())),
                        4 => fields.insert(
                            i,
                            (
                                if sphere { "normal" } else { "center" }.to_string(),
                                "\"0 1 0\"".to_string(),
                            ),
                        ),
                        5 => fields[i].0 = fields[i].0.replacen('e', "\\u0065", 1),
                        _ => {}
                    }
                    let body: Vec<String> = fields
                        .iter()
                        .map(|(k, v)| format!("\"{k}\": {v}"))
                        .collect();
                    format!("{{{}}}", body.join(", "))
                },
            )
            .boxed()
    }

    /// A scene: half of them valid, the others with a few surprises.
    fn scene() -> impl Strategy<Value = String> {
        any::<bool>().prop_flat_map(|clean| {
            let light = (numbers(3, clean), numbers(3, clean))
                .prop_map(|(p, c)| format!(r#"{{"position": {p}, "color": {c}}}"#));
            let object = if clean {
                object(true)
            } else {
                prop_oneof![4 => object(true), 1 => object(false)].boxed()
            };
            let optional = if clean {
                strings(&[
                    "",
                    r#", "camera": {"position": "0 1 -5", "look_at": [0, 0, 0]}"#,
                    r#", "image": {"width": 10, "height": 5, "max_depth": 0}"#,
                    r#", "image": {"width": 10, "aa": 2}"#,
                    r#", "ambient": 0.5"#,
                ])
                .boxed()
            } else {
                strings(&[
                    "",
                    r#", "camera": null"#,
                    r#", "ambient": -0.5"#,
                    r#", "image": {"width": 10, "height": 1e1}"#,
                    r#", "ambient": 1e999"#,
                    r#", "objects": []"#,
                    r#", "extra": []"#,
                    " x",
                ])
                .boxed()
            };
            (
                prop::collection::vec(light, 0..3),
                prop::collection::vec(object, 0..8),
                optional,
                any::<bool>(),
            )
                .prop_map(|(lights, objects, optional, objects_first)| {
                    let lights = format!(r#""lights": [{}]"#, lights.join(", "));
                    let objects = format!(r#""objects": [{}]"#, objects.join(",\n "));
                    let (a, b) = if objects_first {
                        (objects, lights)
                    } else {
                        (lights, objects)
                    };
                    match optional.strip_prefix(' ') {
                        Some(after) => format!("{{{a}, {b}}} {after}"),
                        None => format!("{{{a}, {b}{optional}}}"),
                    }
                })
        })
    }
    proptest! {
        #![proptest_config(ProptestConfig::with_cases(3000))]

        #[test]
        fn the_fast_reading_agrees_with_the_reference(text in scene()) {
            agree(&text);
        }

        /// A generated scene with an animation put first: the fast reading leaves it
        /// to the reference, which accepts it exactly when it accepts the scene
        /// without it, with that scene as its static part.
        #[test]
        fn an_animation_changes_nothing_else(text in scene()) {
            let animated = format!(
                r#"{{"animation": {{"frames": 3, "tracks": [{{"target": "camera.position",
                        "keys": [{{"frame": 1, "value": "0 1 -5"}}, {{"frame": 3, "value": [1, 1, -5]}}]}}]}}, {}"#,
                &text[1..]
            );
            prop_assert!(fast::parse(&animated).is_none());
            agree(&animated);
            let still = crate::parse_scene(&text);
            let moving = crate::parse_animated(&animated);
            prop_assert_eq!(still.is_ok(), moving.is_ok(), "{}", animated);
            if let (Ok(still), Ok(moving)) = (still, moving) {
                prop_assert_eq!(format!("{:?}", moving.base), format!("{still:?}"));
                let last = moving.frame(3).unwrap();
                prop_assert_eq!(last.camera.position, crate::Vec3::new(1.0, 1.0, -5.0));
            }
        }

        #[test]
        fn numbers_are_read_as_serde_json_reads_them(
            token in r"-?(0|[0-9]{0,22})(\.[0-9]{0,22})?([eE][+-]?[0-9]{1,3})?[.0-9]?",
            end in prop_oneof![Just(""), Just(","), Just("]"), Just(" ")],
        ) {
            let text = format!("{token}{end}");
            let mut cursor = fast::Cursor { text: &text, pos: 0 };
            let fast = cursor.number();
            let reference = serde_json::from_str::<f64>(&token).ok();
            prop_assert_eq!(fast.map(f64::to_bits), reference.map(f64::to_bits), "{}", token);
            if fast.is_some() {
                prop_assert_eq!(cursor.pos, token.len());
            }
        }
    }

    /// The generated scenes exercise both readings: many are taken by the fast one,
    /// many are left to the reference.
    #[test]
    fn the_generated_scenes_go_both_ways() {
        use proptest::strategy::ValueTree;
        use proptest::test_runner::TestRunner;
        let mut runner = TestRunner::deterministic();
        let strategy = scene();
        let total = 1000;
        let fast = (0..total)
            .filter(|_| {
                let text = strategy.new_tree(&mut runner).unwrap().current();
                super::fast::parse(&text).is_some()
            })
            .count();
        assert!(
            fast > total / 5 && fast < total * 4 / 5,
            "{fast} of {total}"
        );
    }
}

#[test]
fn overrides_are_checked_against_the_limits() {
    let ok = RenderSettings::default();
    assert!(validate_settings(&ok, "").is_ok());
    let too_wide = RenderSettings {
        width: MAX_SIDE + 1,
        ..ok
    };
    assert_eq!(
        validate_settings(&too_wide, "").unwrap_err().to_string(),
        format!(
            "width: must be between 1 and {MAX_SIDE}, got {}",
            MAX_SIDE + 1
        )
    );
    let no_aa = RenderSettings { aa: 0, ..ok };
    assert!(validate_settings(&no_aa, "image")
        .unwrap_err()
        .to_string()
        .starts_with("image.aa:"));
}
