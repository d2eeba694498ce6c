//! Golden-image tests: every `scenes/*.json` is rendered by the real binary at the
//! scene's own settings and compared with the committed `tests/golden/<stem>.png`.
//!
//! # Metric
//!
//! A render matches its golden only when it is the same image: the same width and
//! height and, pixel by pixel, the same 8-bit values in every channel. Images are
//! specified bit-exact (a pixel is a deterministic function of the scene, the settings
//! and its coordinates, computed only with operations that round the same on every
//! machine), so any difference, even one level in one channel of one pixel, is a change
//! of the renderer's output, never noise to tolerate. The decoded pixels are compared,
//! not the PNG files: the encoder's compression may change with the `image` crate
//! without any pixel changing.
//!
//! On a mismatch the test reports how many pixels differ, the first differing pixel in
//! row-major order (top row first) with its golden and rendered values, and the largest
//! per-channel difference, which tells a rounding slip (1 level) from a moved edge.
//!
//! # Workflow
//!
//! On a mismatch the render is also written beside the golden as
//! `tests/golden/<stem>.actual.png` (ignored by git) for inspection. After an intended
//! change of the images, re-create the goldens with
//! `TESSERA_BLESS=1 cargo test --release --test end_to_end cli::golden` and review
//! them before committing.

use std::ffi::OsStr;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use tempfile::TempDir;

use crate::support::{all_scenes, decode_rgb8, repo, shared, tessera, Rgb8};

/// Far longer than any committed scene takes even in a debug build; a render this long
/// means the binary hangs.
const TIMEOUT: Duration = Duration::from_secs(300);

/// How a render differs from its golden.
#[derive(Debug, Clone, PartialEq, Eq)]
enum Mismatch {
    Size {
        golden: (u32, u32),
        actual: (u32, u32),
    },
    Pixels {
        /// How many pixels have at least one channel different.
        count: u64,
        total: u64,
        /// The first of them in row-major order: (x, y), golden value, rendered value.
        first: ((u32, u32), [u8; 3], [u8; 3]),
        /// The largest per-channel difference anywhere, in levels of 255.
        max_delta: u8,
    },
}

impl std::fmt::Display for Mismatch {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Mismatch::Size { golden, actual } => {
                write!(f, "size {actual:?} differs from the golden's {golden:?}")
            }
            Mismatch::Pixels {
                count,
                total,
                first: ((x, y), g, a),
                max_delta,
            } => write!(
                f,
                "{count} of {total} pixels differ; the first at (x {x}, y {y}): golden {:?}, \
                 rendered {a:?}; largest channel difference {max_delta} of 255",
                g
            ),
        }
    }
}

/// Compares `actual` with `golden` exactly, as the module doc says.
fn compare(golden: &Rgb8, actual: &Rgb8) -> Result<(), Mismatch> {
    if golden.dimensions() != actual.dimensions() {
        return Err(Mismatch::Size {
            golden: golden.dimensions(),
            actual: actual.dimensions(),
        });
    }
    let mut count = 0u64;
    let mut first = None;
    let mut max_delta = 0u8;
    for ((x, y, g), a) in golden.enumerate_pixels().zip(actual.pixels()) {
        if g == a {
            continue;
        }
        count += 1;
        first.get_or_insert(((x, y), g, a));
        for c in 0..3 {
            max_delta = max_delta.max(g[c].abs_diff(a[c]));
        }
    }
    match first {
        None => Ok(()),
        Some(first) => Err(Mismatch::Pixels {
            count,
            total: u64::from(golden.dimensions().0) * u64::from(golden.dimensions().1),
            first,
            max_delta,
        }),
    }
}

fn golden_dir() -> PathBuf {
    repo().join("tests/golden")
}

/// Renders `scene` at its own settings with the real binary into `out`, failing the test
/// if it errs or runs longer than [`TIMEOUT`].
fn render(scene: &Path, out: &Path) {
    let run = tessera(
        repo(),
        &[
            OsStr::new("render"),
            scene.as_os_str(),
            OsStr::new("-o"),
            out.as_os_str(),
        ],
        TIMEOUT,
    );
    assert!(
        run.status.success(),
        "rendering {} failed ({}):\n{}",
        scene.display(),
        run.status,
        run.stderr
    );
}

fn blessing() -> bool {
    std::env::var_os("TESSERA_BLESS").is_some_and(|v| v == "1")
}

#[test]
fn scenes_match_their_golden_images() {
    let _turn = shared();
    // Every scene, so a new one is covered (and asks for its golden) without touching
    // this file.
    let scenes = all_scenes();
    assert!(!scenes.is_empty(), "no scenes/*.json found");
    let work = TempDir::new().expect("cannot create a temporary directory");
    let bless = blessing();
    let mut failures = Vec::new();

    for scene in &scenes {
        let stem = scene
            .file_stem()
            .expect("a .json file has a stem")
            .to_string_lossy();
        let rendered = work.path().join(format!("{stem}.png"));
        let started = Instant::now();
        render(scene, &rendered);
        let took = started.elapsed();
        let golden_path = golden_dir().join(format!("{stem}.png"));
        let actual_path = golden_dir().join(format!("{stem}.actual.png"));

        if bless {
            std::fs::create_dir_all(golden_dir()).expect("cannot create tests/golden");
            // Through a rename, so an interrupted bless never leaves a truncated golden.
            let tmp = tempfile::Builder::new()
                .suffix(".png.tmp")
                .tempfile_in(golden_dir())
                .expect("cannot create a file in tests/golden");
            std::fs::copy(&rendered, tmp.path()).expect("cannot write the golden");
            tmp.persist(&golden_path).expect("cannot write the golden");
            let _ = std::fs::remove_file(&actual_path);
            println!("{stem}: blessed {} ({took:.2?})", golden_path.display());
            continue;
        }

        let actual = decode_rgb8(&rendered);
        let verdict = if golden_path.exists() {
            compare(&decode_rgb8(&golden_path), &actual).map_err(|m| m.to_string())
        } else {
            Err(format!(
                "no golden image {}: run `TESSERA_BLESS=1 cargo test --release --test \
                 end_to_end cli::golden` to create it, then review it",
                golden_path.display()
            ))
        };
        match verdict {
            Ok(()) => {
                // A stale failure image from an earlier run would only mislead.
                let _ = std::fs::remove_file(&actual_path);
                println!("{stem}: identical ({took:.2?})");
            }
            Err(why) => {
                std::fs::copy(&rendered, &actual_path).expect("cannot write the actual image");
                failures.push(format!(
                    "{stem}: {why}\n    render written to {}",
                    actual_path.display()
                ));
            }
        }
    }
    assert!(
        failures.is_empty(),
        "{} of {} scenes do not match their golden image:\n{}",
        failures.len(),
        scenes.len(),
        failures.join("\n")
    );
}

/// A small image with some structure, so that the comparison is tested without
/// rendering (and while blessing rewrites the goldens).
fn pattern() -> Rgb8 {
    Rgb8::from_fn(64, 48, |x, y| {
        [(x * 4) as u8, (y * 5) as u8, ((x ^ y) * 3) as u8]
    })
}

/// The comparison accepts only the same image and reports where it differs: one level
/// in one channel of one pixel is a mismatch, located and counted.
#[test]
fn one_level_in_one_pixel_is_a_mismatch() {
    let _turn = shared();
    let golden = pattern();
    assert_eq!(compare(&golden, &golden.clone()), Ok(()));

    for (x, y, channel, up) in [(0, 0, 0, true), (17, 29, 1, false), (63, 47, 2, true)] {
        let mut actual = golden.clone();
        let before = golden.get_pixel(x, y);
        let v = &mut actual.pixel_mut(x, y)[channel];
        *v = if up {
            v.wrapping_add(1)
        } else {
            v.wrapping_sub(1)
        };
        let after = actual.get_pixel(x, y);
        assert_eq!(
            compare(&golden, &actual),
            Err(Mismatch::Pixels {
                count: 1,
                total: 64 * 48,
                first: ((x, y), before, after),
                max_delta: 1,
            }),
            "one level at ({x}, {y}) in channel {channel}"
        );
    }

    // Several pixels: all are counted, the first in row-major order is reported.
    let mut actual = golden.clone();
    for (x, y) in [(40, 30), (5, 31), (60, 2)] {
        actual.pixel_mut(x, y)[0] ^= 0x80;
    }
    let Err(Mismatch::Pixels {
        count,
        first,
        max_delta,
        ..
    }) = compare(&golden, &actual)
    else {
        panic!("three changed pixels must be a mismatch");
    };
    assert_eq!((count, first.0, max_delta), (3, (60, 2), 128));

    // A different size is never a match, even when the common part is the same.
    let cropped = golden.crop(0, 0, 63, 48);
    assert_eq!(
        compare(&golden, &cropped),
        Err(Mismatch::Size {
            golden: (64, 48),
            actual: (63, 48),
        })
    );
}
