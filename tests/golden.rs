//! Golden-image tests: every `scenes/*.json` is rendered by the real binary at the
//! scene's own settings and compared with the committed `tests/golden/<stem>.png`.
//!
//! # Metric
//!
//! A render matches its golden when all of these hold:
//!
//! 1. identical width and height;
//! 2. at most [`MAX_OFF_FRACTION`] (0.05 %) of the pixels have any channel differing by
//!    more than [`TOLERANCE`] (1 level of 255). These are the ties of silhouette and
//!    shadow edges, where a sample lands on a boundary and a different but equally valid
//!    floating-point evaluation flips it; every other pixel is within 1 level per
//!    channel, which absorbs rounding of `v * 255` at exactly .5;
//! 3. PSNR over all channels of all pixels >= [`MIN_PSNR_DB`] (50 dB, i.e. a mean
//!    squared error of at most 0.65 level²), so that even within tolerance the image
//!    cannot drift as a whole, and the edge ties of rule 2 stay small: on the seed's
//!    600x400 frame the error budget is, for example, 120 pixels 36 levels off in every
//!    channel, or about 7 pixels flipped between black and white. Identical images have
//!    an infinite PSNR.
//!
//! A uniform change of brightness (a wrong ambient or diffuse factor) breaks rule 2 over
//! most of the frame; a tile written a few pixels off moves the edges inside it by up to
//! 255 levels, which breaks rule 3 even when few pixels change; see
//! [`metric_rejects_plausible_regressions`].
//!
//! # Workflow
//!
//! On a mismatch the test prints the numbers and writes the render beside the golden as
//! `tests/golden/<stem>.actual.png` (ignored by git) for inspection. After an intended
//! change of the images, re-create the goldens with
//! `TESSERA_BLESS=1 cargo test --release --test golden` and review them before
//! committing.

mod common;

use std::ffi::OsStr;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use image::RgbImage;
use tempfile::TempDir;

/// Largest per-channel difference, in levels of 255, that a pixel may have and still
/// count as equal.
const TOLERANCE: u8 = 1;
/// Largest fraction of pixels allowed beyond [`TOLERANCE`], as parts per 10 000
/// (5 = 0.05 %), so the check is exact integer arithmetic.
const MAX_OFF_PER_10K: u64 = 5;
/// [`MAX_OFF_PER_10K`] as a fraction, for messages.
const MAX_OFF_FRACTION: f64 = MAX_OFF_PER_10K as f64 / 10_000.0;
/// Lowest acceptable peak signal-to-noise ratio over all channels.
const MIN_PSNR_DB: f64 = 50.0;

/// Far longer than any committed scene takes even in a debug build; a render this long
/// means the binary hangs.
const TIMEOUT: Duration = Duration::from_secs(300);

/// How far a render is from its golden.
#[derive(Debug, Clone, Copy)]
struct Difference {
    pixels: u64,
    /// Pixels with a channel off by more than [`TOLERANCE`].
    off_pixels: u64,
    /// Largest per-channel difference anywhere.
    max_delta: u8,
    /// Infinite when the images are identical.
    psnr_db: f64,
}

impl Difference {
    fn off_fraction(&self) -> f64 {
        self.off_pixels as f64 / self.pixels as f64
    }
}

impl std::fmt::Display for Difference {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} of {} pixels ({:.4} %, limit {:.2} %) differ by more than {TOLERANCE} level; \
             max difference {} levels; PSNR {:.2} dB (limit {MIN_PSNR_DB} dB)",
            self.off_pixels,
            self.pixels,
            self.off_fraction() * 100.0,
            MAX_OFF_FRACTION * 100.0,
            self.max_delta,
            self.psnr_db,
        )
    }
}

/// Measures `actual` against `golden` and applies the metric of the module doc.
/// `Err` says why they do not match.
fn compare(golden: &RgbImage, actual: &RgbImage) -> Result<Difference, String> {
    if golden.dimensions() != actual.dimensions() {
        return Err(format!(
            "size {:?} differs from the golden's {:?}",
            actual.dimensions(),
            golden.dimensions()
        ));
    }
    let mut off_pixels = 0u64;
    let mut max_delta = 0u8;
    let mut squared_error = 0u64;
    for (g, a) in golden.pixels().zip(actual.pixels()) {
        let deltas = [0, 1, 2].map(|c| g.0[c].abs_diff(a.0[c]));
        let worst = deltas.into_iter().max().unwrap_or(0);
        max_delta = max_delta.max(worst);
        if worst > TOLERANCE {
            off_pixels += 1;
        }
        squared_error += deltas
            .iter()
            .map(|&d| u64::from(d) * u64::from(d))
            .sum::<u64>();
    }
    let pixels = u64::from(golden.width()) * u64::from(golden.height());
    let mse = squared_error as f64 / (pixels * 3) as f64;
    let psnr_db = if squared_error == 0 {
        f64::INFINITY
    } else {
        10.0 * (255.0 * 255.0 / mse).log10()
    };
    let diff = Difference {
        pixels,
        off_pixels,
        max_delta,
        psnr_db,
    };
    if off_pixels * 10_000 > pixels * MAX_OFF_PER_10K || psnr_db < MIN_PSNR_DB {
        Err(diff.to_string())
    } else {
        Ok(diff)
    }
}

fn repo() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

fn golden_dir() -> PathBuf {
    repo().join("tests/golden")
}

/// Every `scenes/*.json`, sorted by name, so a new scene is covered (and asks for its
/// golden) without touching this file.
fn scenes() -> Vec<PathBuf> {
    let mut scenes: Vec<PathBuf> = std::fs::read_dir(repo().join("scenes"))
        .expect("cannot list scenes/")
        .map(|e| e.expect("cannot read an entry of scenes/").path())
        .filter(|p| p.extension().is_some_and(|e| e == "json"))
        .collect();
    scenes.sort();
    scenes
}

/// Renders `scene` at its own settings with the real binary into `out`, failing the test
/// if it errs or runs longer than [`TIMEOUT`].
fn render(scene: &Path, out: &Path) {
    let run = common::tessera(
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

fn decode(path: &Path) -> RgbImage {
    image::open(path)
        .unwrap_or_else(|e| panic!("cannot decode {}: {e}", path.display()))
        .into_rgb8()
}

fn blessing() -> bool {
    std::env::var_os("TESSERA_BLESS").is_some_and(|v| v == "1")
}

#[test]
fn scenes_match_their_golden_images() {
    let scenes = scenes();
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

        let actual = decode(&rendered);
        let verdict = if golden_path.exists() {
            compare(&decode(&golden_path), &actual)
        } else {
            Err(format!(
                "no golden image {}: run `TESSERA_BLESS=1 cargo test --release --test golden` \
                 to create it, then review it",
                golden_path.display()
            ))
        };
        match verdict {
            Ok(diff) => {
                // A stale failure image from an earlier run would only mislead.
                let _ = std::fs::remove_file(&actual_path);
                println!("{stem}: ok ({took:.2?}): {diff}");
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

/// The seed's golden, the image the metric tests perturb. While blessing, the goldens
/// are being rewritten by a concurrent test, so a fresh render of the seed stands in.
fn seed_golden() -> RgbImage {
    if blessing() {
        let work = TempDir::new().expect("cannot create a temporary directory");
        let out = work.path().join("seed.png");
        render(&repo().join("scenes/seed.json"), &out);
        return decode(&out);
    }
    let path = golden_dir().join("seed.png");
    assert!(
        path.exists(),
        "{} is missing: run `TESSERA_BLESS=1 cargo test --release --test golden`",
        path.display()
    );
    decode(&path)
}

/// The metric must not be so tight that a conforming renderer fails it: identical
/// images, scattered 1-level rounding differences and a few edge pixels are accepted.
#[test]
fn metric_accepts_rounding_and_edge_ties() {
    let golden = seed_golden();
    let same = compare(&golden, &golden).expect("an image matches itself");
    assert!(same.psnr_db.is_infinite() && same.off_pixels == 0 && same.max_delta == 0);

    let mut nearly = golden.clone();
    // One channel in four off by a level: rounding differences.
    for (i, p) in nearly.pixels_mut().enumerate() {
        let c = i % 4;
        if c < 3 {
            p.0[c] = if p.0[c] == 255 { 254 } else { p.0[c] + 1 };
        }
    }
    // Half the allowed number of pixels 20 levels off: ties on silhouette and shadow
    // edges, where one sample of several lands on the other side.
    let (w, h) = nearly.dimensions();
    let ties = (u64::from(w) * u64::from(h) * MAX_OFF_PER_10K / 10_000 / 2) as u32;
    for k in 0..ties {
        let p = nearly.get_pixel_mut((k * 37) % w, (k * 53) % h);
        p.0 = p.0.map(|v| if v >= 128 { v - 20 } else { v + 20 });
    }
    let diff = compare(&golden, &nearly).unwrap_or_else(|why| panic!("rejected: {why}"));
    assert!(diff.off_pixels > 0 && diff.psnr_db.is_finite());
}

/// The metric catches what plausible bugs would do to the seed image.
#[test]
fn metric_rejects_plausible_regressions() {
    let golden = seed_golden();

    // A wrong ambient or diffuse factor: every channel scaled by 0.9.
    let mut dimmer = golden.clone();
    for p in dimmer.pixels_mut() {
        p.0 = p.0.map(|v| (f64::from(v) * 0.9).round() as u8);
    }
    let why = compare(&golden, &dimmer).expect_err("a 10 % darker image must be rejected");
    println!("scaled by 0.9: {why}");

    // A tile written 4 pixels off: the busiest 20x20 block (the checkerboard, typically)
    // holds the content of the block 4 pixels to its left. The busiest is chosen so
    // that the shift changes something whatever the scene looks like.
    let (w, h) = golden.dimensions();
    let busiest = (0..h / 20)
        .flat_map(|ty| (1..w / 20).map(move |tx| (tx * 20, ty * 20)))
        .max_by_key(|&(x0, y0)| {
            let mut change = 0u64;
            for y in y0..y0 + 20 {
                for x in x0..x0 + 20 {
                    let (a, b) = (golden.get_pixel(x, y), golden.get_pixel(x - 4, y));
                    change += (0..3)
                        .map(|c| u64::from(a.0[c].abs_diff(b.0[c])))
                        .sum::<u64>();
                }
            }
            change
        })
        .expect("the seed image has at least two tiles across");
    let (x0, y0) = busiest;
    let mut shifted = golden.clone();
    for y in y0..y0 + 20 {
        for x in x0..x0 + 20 {
            shifted.put_pixel(x, y, *golden.get_pixel(x - 4, y));
        }
    }
    let why = compare(&golden, &shifted).expect_err("a misplaced 20x20 tile must be rejected");
    println!("20x20 block at ({x0}, {y0}) shifted by 4 px: {why}");

    // A wrong size is never a match.
    let cropped = image::imageops::crop_imm(&golden, 0, 0, w - 1, h).to_image();
    compare(&golden, &cropped).expect_err("a different size must be rejected");
}
