//! The samplers: the grid keeps the scene format's bytes, jittered and adaptive tiles
//! are the same in any tiling, adaptive sampling spends samples where the colours
//! disagree, the error estimate falls with more samples, and the image metrics give
//! known values on hand-made images.

use proptest::prelude::*;
use render::adaptive::{sample_cap, BlockState, Level, Region, BLOCK, LAST_RUNG};
use render::{
    metrics, parse_scene, render_tile, sample_offsets, validate_settings, Image, Rect,
    RenderSettings, Sampling, TileError, Tracer,
};

use crate::support::{frame, seed, tracer, SEED};

/// Every scene of `scenes/`, by name.
const SCENES: [(&str, &str); 5] = [
    ("seed", SEED),
    (
        "reflections",
        include_str!("../../../scenes/reflections.json"),
    ),
    ("tilted", include_str!("../../../scenes/tilted.json")),
    ("lights", include_str!("../../../scenes/lights.json")),
    (
        "hall-of-mirrors",
        include_str!("../../../scenes/hall-of-mirrors.json"),
    ),
];

fn adaptive(levels: f64) -> Sampling {
    Sampling::adaptive(levels).unwrap()
}

/// One pixel as a 1 × 1 tile: its samples and its estimated error (levels).
fn pixel_cost(tracer: &Tracer, x: u32, y: u32) -> (u64, f64) {
    let tile = render_tile(
        tracer,
        Rect {
            x,
            y,
            width: 1,
            height: 1,
        },
    )
    .unwrap();
    (tile.samples, tile.error_sq_sum.sqrt())
}

// ---------------------------------------------------------------------------------
// The grid.
// ---------------------------------------------------------------------------------

#[test]
fn the_grid_gives_the_bytes_and_rays_of_tracer_pixel_on_every_scene() {
    for (name, text) in SCENES {
        let scene = parse_scene(text).unwrap();
        for aa in [1, 2, 3] {
            let t = tracer(&scene, 48, 32, aa, Sampling::Grid);
            let mut expected = Image::black(48, 32);
            let mut rays = 0;
            for y in 0..32 {
                for x in 0..48 {
                    let rgb = t.pixel(x, y, &mut rays);
                    expected.put_rect(
                        Rect {
                            x,
                            y,
                            width: 1,
                            height: 1,
                        },
                        &rgb,
                    );
                }
            }
            let f = frame(&t, 7, 2);
            assert!(
                f.image == expected,
                "{name}, aa {aa}: the grid's bytes changed"
            );
            assert_eq!(f.rays, rays, "{name}, aa {aa}: rays");
            assert_eq!(f.samples, 48 * 32 * u64::from(aa * aa), "{name}, aa {aa}");
            if aa == 1 {
                assert_eq!(f.error_sq_sum, 0.0);
                assert!(f.estimated_error().is_nan(), "one sample: no estimate");
            } else {
                assert!(
                    f.estimated_error() > 0.0,
                    "{name}, aa {aa}: edges are noisy"
                );
            }
        }
    }
}

#[test]
fn the_default_sampling_is_the_grid() {
    assert_eq!(RenderSettings::default().sampling, Sampling::Grid);
    assert_eq!(seed().settings.sampling, Sampling::Grid);
}

// ---------------------------------------------------------------------------------
// Determinism: any tiling, any thread count.
// ---------------------------------------------------------------------------------

fn sampler() -> impl Strategy<Value = Sampling> {
    prop_oneof![
        Just(Sampling::Jittered),
        Just(adaptive(0.5)),
        Just(adaptive(2.0)),
        Just(adaptive(8.0)),
    ]
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(24))]

    /// Random tile sizes and thread counts give byte-identical frames, and spend the
    /// same samples.
    #[test]
    fn jittered_and_adaptive_frames_are_the_same_in_any_tiling(
        tile in 1u32..80,
        threads in 1usize..5,
        aa in 1u32..5,
        sampling in sampler(),
    ) {
        let t = tracer(&seed(), 90, 60, aa, sampling);
        let reference = frame(&t, 90, 1);
        let tiled = frame(&t, tile, threads);
        prop_assert!(tiled.image == reference.image);
        prop_assert_eq!(tiled.samples, reference.samples);
        prop_assert_eq!(tiled.rays, reference.rays);
        let (a, b) = (tiled.estimated_error(), reference.estimated_error());
        prop_assert!(
            (a.is_nan() && b.is_nan()) || (a - b).abs() <= 1e-9 * b.abs(),
            "estimates {} and {}", a, b
        );
    }

    /// Any rectangle rendered alone equals the same pixels of the full frame. (Adaptive
    /// tiles are regions of blocks: the same property is tested in
    /// `render::adaptive`.)
    #[test]
    fn a_jittered_tile_equals_its_pixels_in_the_full_frame(
        x in 0u32..80, y in 0u32..60, w in 1u32..40, h in 1u32..40,
    ) {
        let t = tracer(&seed(), 80, 60, 4, Sampling::Jittered);
        let full = frame(&t, 16, 2).image;
        let rect = Rect { x, y, width: w.min(80 - x), height: h.min(60 - y) };
        let tile = render_tile(&t, rect).unwrap();
        for row in 0..rect.height {
            for col in 0..rect.width {
                let i = ((row * rect.width + col) * 3) as usize;
                prop_assert_eq!(&tile.rgb[i..i + 3], &full.pixel(x + col, y + row)[..]);
            }
        }
    }
}

#[test]
fn samplers_really_differ_from_the_grid() {
    let scene = seed();
    let grid = frame(&tracer(&scene, 90, 60, 4, Sampling::Grid), 32, 2).image;
    let jittered = frame(&tracer(&scene, 90, 60, 4, Sampling::Jittered), 32, 2).image;
    let adaptive = frame(&tracer(&scene, 90, 60, 4, adaptive(1.0)), 32, 2).image;
    assert!(jittered != grid);
    assert!(adaptive != grid);
    // ...but they render the same picture, closer to a converged one than one sample
    // per pixel is.
    let converged = frame(&tracer(&scene, 90, 60, 16, Sampling::Grid), 32, 2).image;
    let one_sample = frame(&tracer(&scene, 90, 60, 1, Sampling::Grid), 32, 2).image;
    let far = metrics::rmse(&converged, &one_sample);
    for (name, image) in [
        ("grid", &grid),
        ("jittered", &jittered),
        ("adaptive", &adaptive),
    ] {
        let rmse = metrics::rmse(&converged, image);
        assert!(rmse < 0.75 * far, "{name}: RMSE {rmse}, one sample {far}");
    }
}

// ---------------------------------------------------------------------------------
// Where the samples go.
// ---------------------------------------------------------------------------------

#[test]
fn jittered_points_stay_inside_their_strata_and_differ_between_pixels() {
    // The jittered pattern is the first n² points of the pixel's Owen-scrambled Sobol
    // sequence: for n a power of two, a (0, 2m, 2)-net with one point in each of the
    // n × n cells; for any n, n² distinct points inside the pixel.
    for n in [1, 2, 3, 4, 5, 8, 64] {
        for (i, j) in [
            (0, 0),
            (1, 0),
            (0, 1),
            (599, 399),
            (16383, 16383),
            (77, 123),
        ] {
            let points = sample_offsets(Sampling::Jittered, n, i, j, n * n);
            assert_eq!(points.len() as u32, n * n);
            assert!(points
                .iter()
                .all(|&(x, y)| (0.0..1.0).contains(&x) && (0.0..1.0).contains(&y)));
            let nf = f64::from(n);
            let mut cells: Vec<(u32, u32)> = points
                .iter()
                .map(|&(x, y)| ((x * nf) as u32, (y * nf) as u32))
                .collect();
            cells.sort();
            cells.dedup();
            if n.is_power_of_two() {
                assert_eq!(cells.len() as u32, n * n, "n {n}, pixel ({i}, {j})");
            }
            assert_eq!(points, sample_offsets(Sampling::Jittered, n, i, j, n * n));
        }
    }
    // Not the grid's centres, and not the same pattern in neighbouring pixels.
    let p = sample_offsets(Sampling::Jittered, 4, 10, 10, 16);
    assert_ne!(p, sample_offsets(Sampling::Grid, 4, 10, 10, 16));
    assert_ne!(p, sample_offsets(Sampling::Jittered, 4, 11, 10, 16));
    assert_ne!(p, sample_offsets(Sampling::Jittered, 4, 10, 11, 16));
}

#[test]
fn adaptive_points_put_each_group_of_four_in_the_four_quadrants() {
    for (i, j) in [(0, 0), (1, 0), (300, 20), (599, 399)] {
        let points = sample_offsets(adaptive(1.0), 8, i, j, 64);
        for group in points.chunks(4) {
            let mut quadrants: Vec<(u32, u32)> = group
                .iter()
                .map(|&(x, y)| ((x * 2.0) as u32, (y * 2.0) as u32))
                .collect();
            quadrants.sort();
            assert_eq!(
                quadrants,
                [(0, 0), (0, 1), (1, 0), (1, 1)],
                "pixel ({i}, {j})"
            );
        }
        assert!(points
            .iter()
            .all(|&(x, y)| (0.0..1.0).contains(&x) && (0.0..1.0).contains(&y)));
    }
    // A per-pixel scramble: neighbours do not share their points.
    assert_ne!(
        sample_offsets(adaptive(1.0), 8, 0, 0, 4),
        sample_offsets(adaptive(1.0), 8, 1, 0, 4)
    );
}

/// The seed at 600 × 400: the top rows around the middle see only sky (black, every
/// sample the same).
const SKY: Rect = Rect {
    x: 280,
    y: 0,
    width: 40,
    height: 10,
};

/// The blocks of `rect` advanced to `rung`, and each one's level there.
fn blocks_at(t: &Tracer, rect: Rect, rung: u32) -> Vec<(BlockState, Level)> {
    let footprints = Region::footprints(t);
    let mut region = Region::new(t, footprints.clone(), rect, None).unwrap();
    region.advance_to(rung);
    let cap = sample_cap(t.settings().aa);
    region
        .blocks()
        .iter()
        .map(|b| {
            let min = footprints.min_samples(b.rect.x / BLOCK, b.rect.y / BLOCK);
            let l = b.level_at(rung, cap, min).unwrap();
            (b.clone(), b.levels[l].clone())
        })
        .collect()
}

#[test]
fn adaptive_sampling_spends_only_the_first_level_on_a_flat_region() {
    let scene = seed();
    let sky = Rect { height: 16, ..SKY };
    for rung in [0, 200, LAST_RUNG] {
        let t = tracer(&scene, 600, 400, 8, adaptive(1.0));
        for (_, level) in blocks_at(&t, sky, rung) {
            assert_eq!(level.count, 4, "rung {rung}");
            assert_eq!(level.spread, 0.0);
            assert!(level.rgb.iter().all(|&c| c == 0), "the sky is black");
        }
    }
    // With a cap below the first level, the cap.
    let t = tracer(&scene, 600, 400, 1, adaptive(0.001));
    for (_, level) in blocks_at(&t, sky, LAST_RUNG) {
        assert_eq!(level.count, 1);
        assert!(level.spread.is_nan(), "one sample: no estimate");
    }
    // A single tile of an adaptive frame is not rendered on its own.
    let t = tracer(&scene, 600, 400, 8, adaptive(1.0));
    assert!(matches!(render_tile(&t, SKY), Err(TileError::Adaptive(_))));
}

#[test]
fn adaptive_sampling_spends_more_on_edges_and_the_whole_budget_for_a_tiny_target() {
    let scene = seed();
    let (w, h) = (240, 160);
    let full = Rect {
        x: 0,
        y: 0,
        width: w,
        height: h,
    };
    // Edges: pixels whose converged colour differs from their centre sample's, i.e.
    // pixels partly covered by two surfaces.
    let centre = frame(&tracer(&scene, w, h, 1, Sampling::Grid), 32, 2).image;
    let converged = frame(&tracer(&scene, w, h, 16, Sampling::Grid), 32, 2).image;
    let loose_tracer = tracer(&scene, w, h, 8, adaptive(3.0));
    let loose_frame = frame(&loose_tracer, 32, 2);
    let rung = (0..=LAST_RUNG)
        .find(|&k| {
            let region = blocks_at(&loose_tracer, full, k);
            let samples: u64 = region
                .iter()
                .map(|(b, l)| u64::from(l.count) * b.rect.pixel_count())
                .sum();
            samples == loose_frame.samples
        })
        .expect("the frame stands at some rung");
    let loose = blocks_at(&loose_tracer, full, rung);
    let tiny = blocks_at(&tracer(&scene, w, h, 8, adaptive(0.001)), full, LAST_RUNG);
    let (mut edge_samples, mut edges, mut flat_samples, mut flats) = (0u64, 0, 0u64, 0);
    for ((block, level), (_, tiny_level)) in loose.iter().zip(&tiny) {
        assert!([4, 8, 16, 32, 64].contains(&level.count));
        if level.spread > 0.0 {
            // A block whose samples disagree takes the whole budget at a tiny target,
            // unless they come to agree exactly at some level before.
            assert!(
                tiny_level.count == 64 || tiny_level.spread == 0.0,
                "{:?}: {} samples",
                block.rect,
                tiny_level.count
            );
        }
        let r = block.rect;
        for y in r.y..r.y + r.height {
            for x in r.x..r.x + r.width {
                let off = centre
                    .pixel(x, y)
                    .iter()
                    .zip(converged.pixel(x, y))
                    .any(|(a, b)| a.abs_diff(b) > 32);
                if off {
                    edges += 1;
                    edge_samples += u64::from(level.count);
                } else {
                    flats += 1;
                    flat_samples += u64::from(level.count);
                }
            }
        }
    }
    assert!(edges > 50, "the seed has edges ({edges} found)");
    let edge_mean = edge_samples as f64 / f64::from(edges);
    let flat_mean = flat_samples as f64 / f64::from(flats);
    assert!(
        edge_mean > 2.0 * flat_mean,
        "edges take {edge_mean:.1} samples per pixel, the rest {flat_mean:.1}"
    );
    assert!(
        flat_mean < 24.0,
        "the rest takes {flat_mean:.1} samples per pixel"
    );
}

// ---------------------------------------------------------------------------------
// The error estimate.
// ---------------------------------------------------------------------------------

#[test]
fn the_error_estimate_falls_with_more_samples() {
    let scene = seed();
    for sampling in [Sampling::Grid, Sampling::Jittered] {
        let estimates: Vec<f64> = [2, 4, 8]
            .iter()
            .map(|&aa| frame(&tracer(&scene, 90, 60, aa, sampling), 32, 2).estimated_error())
            .collect();
        assert!(
            estimates[0] > estimates[1] && estimates[1] > estimates[2],
            "{sampling}: {estimates:?}"
        );
    }
    // Adaptive: a lower target, or a larger budget, gives a lower estimate.
    let estimate = |aa, target| {
        let f = frame(&tracer(&scene, 90, 60, aa, adaptive(target)), 32, 2);
        (f.estimated_error(), f.samples)
    };
    let (loose, loose_samples) = estimate(8, 16.0);
    let (tight, tight_samples) = estimate(8, 0.5);
    assert!(tight < loose && tight_samples > loose_samples);
    assert!(estimate(16, 0.5).0 < tight);
}

#[test]
fn the_error_estimate_is_the_standard_error_of_the_pixel_mean() {
    // The sky: every sample equal, so no error at all, for every sampler.
    let scene = seed();
    for sampling in [Sampling::Grid, Sampling::Jittered] {
        let t = tracer(&scene, 600, 400, 4, sampling);
        assert_eq!(
            render_tile(&t, SKY).unwrap().error_sq_sum,
            0.0,
            "{sampling}"
        );
    }
    let sphere = parse_scene(
        r#"{"lights": [],
            "objects": [{"type": "sphere", "center": "0 0 0", "radius": 1,
                         "color": "1 1 1 0"}],
            "camera": {"position": "0 0 -5", "look_at": "0 0 0"},
            "image": {"width": 2, "height": 2},
            "ambient": 1}"#,
    )
    .unwrap();
    // A white sphere (ambient 1, no lights) seen from 5 units away covers the inner
    // corner of each pixel of a 2 × 2 image. With the grid at aa 2 a sample is white (1)
    // or black (0); with w white samples of 4 the unbiased variance is w(4 − w)/12 and
    // the error 255 · √(s²/4) levels.
    let t = tracer(&sphere, 2, 2, 2, Sampling::Grid);
    let mut rays = 0;
    for (x, y) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
        let (samples, error) = pixel_cost(&t, x, y);
        assert_eq!(samples, 4);
        let rgb = t.pixel(x, y, &mut rays);
        let white = (f64::from(rgb[0]) / 255.0 * 4.0).round();
        let expected = 255.0 * (white * (4.0 - white) / 12.0 / 4.0).sqrt();
        assert!(
            (error - expected).abs() < 1e-9,
            "({x}, {y}): {white} white samples, error {error}, expected {expected}"
        );
    }
}

// ---------------------------------------------------------------------------------
// Settings.
// ---------------------------------------------------------------------------------

#[test]
fn adaptive_targets_are_validated() {
    for bad in [0.0, -1.0, f64::NAN, f64::INFINITY, 1e-4, 256.0] {
        let e = Sampling::adaptive(bad).unwrap_err().to_string();
        assert!(e.contains("0.001 to 255"), "{e}");
    }
    let zero = RenderSettings {
        sampling: Sampling::Adaptive { target_milli: 0 },
        ..RenderSettings::default()
    };
    assert_eq!(
        validate_settings(&zero, "").unwrap_err().to_string(),
        "target_error: must be between 0.001 and 255 levels, got 0"
    );
    assert!(validate_settings(
        &RenderSettings {
            sampling: adaptive(0.001),
            ..RenderSettings::default()
        },
        ""
    )
    .is_ok());
    assert_eq!(adaptive(1.0).to_string(), "adaptive (target 1 levels)");
    assert_eq!(adaptive(0.25).target_error(), Some(0.25));
    assert_eq!(Sampling::Jittered.target_error(), None);
}

// ---------------------------------------------------------------------------------
// Metrics.
// ---------------------------------------------------------------------------------

fn image(width: u32, height: u32, rgb: &[u8]) -> Image {
    Image {
        width,
        height,
        rgb: rgb.to_vec(),
    }
}

#[test]
fn identical_images_have_no_error() {
    let a = image(2, 1, &[0, 10, 20, 255, 128, 7]);
    let e = metrics::compare(&a, &a);
    assert_eq!(e.rmse, 0.0);
    assert_eq!(e.psnr, f64::INFINITY);
    assert_eq!(e.share_off_by_more_than_2, 0.0);
    assert_eq!(e.max_difference, 0);
}

#[test]
fn known_differences_give_known_errors() {
    // Every channel 5 levels off: RMSE 5, PSNR 20·log10(255/5) = 20·log10(51).
    let a = image(2, 2, &[100; 12]);
    let b = image(2, 2, &[105; 12]);
    let e = metrics::compare(&a, &b);
    assert_eq!(e.rmse, 5.0);
    assert!((e.psnr - 20.0 * 51f64.log10()).abs() < 1e-12);
    assert_eq!(e.share_off_by_more_than_2, 1.0);
    assert_eq!(e.max_difference, 5);
    assert_eq!(metrics::compare(&b, &a), e, "symmetric");

    // One channel of one pixel 3 off, another pixel 2 off: MSE (9 + 4)/12; only the
    // first pixel is more than 2 levels off.
    let a = image(2, 2, &[0; 12]);
    let b = image(2, 2, &[3, 0, 0, 0, 2, 0, 0, 0, 0, 0, 0, 0]);
    let e = metrics::compare(&a, &b);
    assert!((e.rmse - (13.0f64 / 12.0).sqrt()).abs() < 1e-15);
    assert!((e.psnr - 10.0 * (255.0 * 255.0 * 12.0 / 13.0f64).log10()).abs() < 1e-12);
    assert_eq!(e.share_off_by_more_than_2, 0.25);
    assert_eq!(e.max_difference, 3);
    assert_eq!(metrics::rmse(&a, &b), e.rmse);
    assert_eq!(metrics::psnr(&a, &b), e.psnr);
    assert_eq!(metrics::share_off(&a, &b, 1), 0.5);

    // Black against white: the worst case, PSNR 0.
    let e = metrics::compare(&image(1, 1, &[0, 0, 0]), &image(1, 1, &[255, 255, 255]));
    assert_eq!((e.rmse, e.psnr, e.max_difference), (255.0, 0.0, 255));
}

#[test]
#[should_panic(expected = "cannot compare a 1x2 image with a 2x1 reference")]
fn images_of_different_sizes_are_not_compared() {
    metrics::compare(&image(2, 1, &[0; 6]), &image(1, 2, &[0; 6]));
}
