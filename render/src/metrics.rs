//! How far an image is from a reference, over its 8-bit values: the numbers by which
//! samplers are compared (error against a converged render of the same scene, e.g. a
//! regular grid with `aa` 32).
//!
//! Pure functions of two [`Image`]s of the same size. They are not on the rendering path,
//! so they may use `log10`.

use crate::image::Image;

/// The levels by which a pixel may differ from the reference before it counts as off in
/// [`ImageError::share_off_by_more_than_2`].
pub const OFF_LEVELS: u8 = 2;

/// An image's distance from its reference.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ImageError {
    /// Root mean square difference over every channel of every pixel, in 8-bit levels.
    pub rmse: f64,
    /// Peak signal-to-noise ratio in decibels, 20 · log₁₀(255 / RMSE): higher is better,
    /// `f64::INFINITY` for identical images.
    pub psnr: f64,
    /// The fraction (0 to 1) of pixels with some channel more than 2 levels off: the
    /// visible mistakes, which an average can hide.
    pub share_off_by_more_than_2: f64,
    /// The largest difference of any channel, in levels.
    pub max_difference: u8,
}

/// Compares `image` with `reference`.
///
/// # Panics
///
/// If the two images differ in size: a comparison of different frames means nothing.
pub fn compare(reference: &Image, image: &Image) -> ImageError {
    assert_same_size(reference, image);
    let mse = mse(reference, image);
    let rmse = mse.sqrt();
    let mut off = 0u64;
    let mut max_difference = 0u8;
    for (p, q) in reference.rgb.chunks_exact(3).zip(image.rgb.chunks_exact(3)) {
        let worst = p
            .iter()
            .zip(q)
            .map(|(a, b)| a.abs_diff(*b))
            .max()
            .unwrap_or(0);
        max_difference = max_difference.max(worst);
        if worst > OFF_LEVELS {
            off += 1;
        }
    }
    let pixels = reference.rgb.len() / 3;
    ImageError {
        rmse,
        psnr: psnr_of_mse(mse),
        share_off_by_more_than_2: if pixels == 0 {
            0.0
        } else {
            off as f64 / pixels as f64
        },
        max_difference,
    }
}

/// The root mean square difference over every channel, in levels.
///
/// # Panics
///
/// If the images differ in size.
pub fn rmse(reference: &Image, image: &Image) -> f64 {
    assert_same_size(reference, image);
    mse(reference, image).sqrt()
}

/// The peak signal-to-noise ratio in decibels; `f64::INFINITY` for identical images.
///
/// # Panics
///
/// If the images differ in size.
pub fn psnr(reference: &Image, image: &Image) -> f64 {
    assert_same_size(reference, image);
    psnr_of_mse(mse(reference, image))
}

/// The fraction of pixels with a channel more than `levels` off.
///
/// # Panics
///
/// If the images differ in size.
pub fn share_off(reference: &Image, image: &Image, levels: u8) -> f64 {
    assert_same_size(reference, image);
    let pixels = reference.rgb.len() / 3;
    if pixels == 0 {
        return 0.0;
    }
    let off = reference
        .rgb
        .chunks_exact(3)
        .zip(image.rgb.chunks_exact(3))
        .filter(|(p, q)| p.iter().zip(q.iter()).any(|(a, b)| a.abs_diff(*b) > levels))
        .count();
    off as f64 / pixels as f64
}

fn assert_same_size(reference: &Image, image: &Image) {
    assert!(
        reference.width == image.width && reference.height == image.height,
        "cannot compare a {}x{} image with a {}x{} reference",
        image.width,
        image.height,
        reference.width,
        reference.height
    );
}

/// The mean squared difference per channel (0 for empty images).
fn mse(reference: &Image, image: &Image) -> f64 {
    if reference.rgb.is_empty() {
        return 0.0;
    }
    let sum: u64 = reference
        .rgb
        .iter()
        .zip(&image.rgb)
        .map(|(a, b)| {
            let d = u64::from(a.abs_diff(*b));
            d * d
        })
        .sum();
    sum as f64 / reference.rgb.len() as f64
}

fn psnr_of_mse(mse: f64) -> f64 {
    if mse == 0.0 {
        f64::INFINITY
    } else {
        10.0 * (255.0 * 255.0 / mse).log10()
    }
}
