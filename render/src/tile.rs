//! Tiles: any rectangle of the frame, rendered on its own with the same bytes it has in
//! a full-frame render, and whole frames assembled from tiles rendered in parallel.

use rayon::prelude::*;

use crate::image::{Image, TileImage};
use crate::rect::{tiles, Rect, TileError};
use crate::sampling::{PixelResult, PixelSampler};
use crate::settings::Sampling;
use crate::tracer::Tracer;

/// Default tile side for whole-frame renders: small enough to balance two to dozens of
/// threads on a 600 × 400 frame, large enough that scheduling costs nothing.
pub const DEFAULT_TILE_SIZE: u32 = 32;

/// Renders one tile with the tracer's settings and sampling. Each pixel depends only on
/// the scene, the settings and its coordinates, so the bytes equal those of the same
/// pixels in any other tiling.
pub fn render_tile(tracer: &Tracer, rect: Rect) -> Result<TileImage, TileError> {
    rect.check_inside(tracer.settings())?;
    let mut rgb = Vec::with_capacity(rect.pixel_count() as usize * 3);
    let mut rays = 0;
    let mut samples = 0;
    let mut error_sq_sum = 0.0;
    let mut sampler = PixelSampler::new(tracer);
    let mut add = |pixel: PixelResult| {
        rgb.extend_from_slice(&pixel.rgb);
        samples += u64::from(pixel.samples);
        error_sq_sum += pixel.error_sq;
    };
    let columns = rect.x..rect.x + rect.width;
    match tracer.settings().sampling {
        Sampling::Grid => {
            for j in rect.y..rect.y + rect.height {
                sampler.render_grid_row(j, columns.clone(), &mut rays, &mut add);
            }
        }
        Sampling::Jittered => {
            for j in rect.y..rect.y + rect.height {
                for i in columns.clone() {
                    add(sampler.render_jittered(i, j, &mut rays));
                }
            }
        }
        Sampling::Adaptive { .. } => return Err(TileError::Adaptive(rect)),
    }
    Ok(TileImage {
        rect,
        rgb,
        rays,
        samples,
        error_sq_sum,
    })
}

/// A rendered frame, what it cost and how wrong it may be.
#[derive(Clone, Debug)]
pub struct Frame {
    pub image: Image,
    pub rays: u64,
    /// Camera samples taken over the whole frame.
    pub samples: u64,
    /// The sum of the tiles' [`TileImage::error_sq_sum`].
    pub error_sq_sum: f64,
}

impl Frame {
    /// Mean camera samples per pixel.
    pub fn samples_per_pixel(&self) -> f64 {
        self.samples as f64 / self.image.pixel_count().max(1) as f64
    }

    /// The renderer's own estimate of the frame's error, in 8-bit levels: the root mean
    /// square over its pixels of each pixel's estimated error. NaN when it is unknown:
    /// with one sample per pixel the spread of the samples cannot be measured (the
    /// unbiased variance of one value is 0/0).
    pub fn estimated_error(&self) -> f64 {
        estimated_error(self.samples, self.error_sq_sum, self.image.pixel_count())
    }
}

/// The RMS estimated error (levels) of `pixels` pixels that took `samples` samples and
/// whose squared estimates sum to `error_sq_sum`; NaN when unknown (no pixel, or one
/// sample per pixel: every sampler takes at least 4 per pixel when `aa` ≥ 2).
pub fn estimated_error(samples: u64, error_sq_sum: f64, pixels: u64) -> f64 {
    if pixels == 0 || samples <= pixels {
        return f64::NAN;
    }
    (error_sq_sum / pixels as f64).sqrt()
}

/// Renders the whole frame as tiles on the current rayon pool, calling `on_tile` with
/// the pixel count of each finished tile (for progress display). The image is the same
/// whatever the tile size and the number of threads.
///
/// With adaptive sampling the frame is walked down the threshold ladder to its target
/// ([`crate::adaptive::render_to_target`]); `tile_size` does not matter then, and
/// `on_tile` hears of the whole frame at the end.
pub fn render_frame(tracer: &Tracer, tile_size: u32, on_tile: &(dyn Fn(u64) + Sync)) -> Frame {
    let settings = *tracer.settings();
    if let Some(target) = settings.sampling.target_error() {
        let (_, frame) = crate::adaptive::render_to_target(tracer, None, target, &mut |_, _| true);
        on_tile(settings.pixel_count());
        return Frame {
            image: frame.image,
            rays: frame.totals.rays,
            samples: frame.totals.samples,
            error_sq_sum: frame.totals.error_sq_levels(),
        };
    }
    let done: Vec<TileImage> = tiles(&settings, tile_size)
        .into_par_iter()
        .map(|rect| {
            let tile = render_tile(tracer, rect).expect("tiles() cuts inside the frame");
            on_tile(rect.pixel_count());
            tile
        })
        .collect();
    let mut image = Image::black(settings.width, settings.height);
    let mut rays = 0;
    let mut samples = 0;
    let mut error_sq_sum = 0.0;
    for tile in &done {
        image.put_tile(tile);
        rays += tile.rays;
        samples += tile.samples;
        error_sq_sum += tile.error_sq_sum;
    }
    Frame {
        image,
        rays,
        samples,
        error_sq_sum,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::image::tests::check_png;
    use crate::settings::RenderSettings;

    /// Small frames of the seed scene, as the farm renders them, encode as the `image`
    /// crate's encoder did (`image`'s tests check made-up images the same way): the
    /// digests are of its output.
    #[test]
    fn rendered_frames_are_encoded_as_the_image_crate_does() {
        let scene = crate::parse_scene(include_str!("../../scenes/seed.json")).unwrap();
        for (width, height, digest) in [
            (
                64,
                48,
                "0e9e3ef0aa712f67c84da2b8da362801a1084da241093b7747c7f409b649c368",
            ),
            (
                131,
                77,
                "549cef6393af24b48f0e4ceacfd12c0bb8710e32a8abaefb601b539e79a849b4",
            ),
        ] {
            let settings = RenderSettings {
                width,
                height,
                ..Default::default()
            };
            let tracer = Tracer::new(&scene, settings);
            check_png(&render_frame(&tracer, 16, &|_| {}).image, digest);
        }
    }
}
