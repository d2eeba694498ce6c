//! Tiles: any rectangle of the frame, rendered on its own with the same bytes it has in
//! a full-frame render, and whole frames assembled from tiles rendered in parallel.

use rayon::prelude::*;
use thiserror::Error;

use crate::image::Image;
use crate::sampling::{PixelResult, PixelSampler, Sampling};
use crate::scene::RenderSettings;
use crate::tracer::Tracer;

/// Default tile side for whole-frame renders: small enough to balance two to dozens of
/// threads on a 600 × 400 frame, large enough that scheduling costs nothing.
pub const DEFAULT_TILE_SIZE: u32 = 32;

/// A rectangle of pixels: columns `x .. x + width`, rows `y .. y + height`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
pub struct Rect {
    pub x: u32,
    pub y: u32,
    pub width: u32,
    pub height: u32,
}

/// A tile that cannot be rendered on its own.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
pub enum TileError {
    /// The tile does not lie inside the frame.
    #[error("tile {rect:?} does not lie inside the {frame_width}x{frame_height} frame")]
    Outside {
        rect: Rect,
        frame_width: u32,
        frame_height: u32,
    },
    /// Adaptive sampling decides over the whole frame which rung each block stops at:
    /// its tiles are advanced as regions of blocks ([`crate::progressive::Region`]).
    #[error("tile {0:?}: adaptive sampling renders regions of blocks, not single tiles")]
    Adaptive(Rect),
}

impl Rect {
    pub fn pixel_count(&self) -> u64 {
        u64::from(self.width) * u64::from(self.height)
    }

    /// Checks that the tile is non-empty and inside a frame of the given settings.
    pub fn check_inside(&self, settings: &RenderSettings) -> Result<(), TileError> {
        let fits = |start: u32, len: u32, side: u32| {
            len > 0 && start.checked_add(len).is_some_and(|end| end <= side)
        };
        if fits(self.x, self.width, settings.width) && fits(self.y, self.height, settings.height) {
            Ok(())
        } else {
            Err(TileError::Outside {
                rect: *self,
                frame_width: settings.width,
                frame_height: settings.height,
            })
        }
    }
}

/// The pixels of one tile, RGB8, rows top to bottom, and what they cost.
#[derive(Clone, Debug, PartialEq)]
pub struct TileImage {
    pub rect: Rect,
    pub rgb: Vec<u8>,
    /// Rays traced for this tile (camera, reflection and shadow rays).
    pub rays: u64,
    /// Camera samples taken: pixels × `aa`² for the grid and jittered samplers, what
    /// the pixels needed for adaptive sampling.
    pub samples: u64,
    /// The sum over the tile's pixels of the square of each pixel's estimated error, in
    /// 8-bit levels squared (see [`crate::sampling`]). A sum, so that tiles combine into
    /// a frame's or a job's RMS estimate by addition. Pixels of one sample have no
    /// estimate and add 0.
    pub error_sq_sum: f64,
}

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

/// Cuts a frame into tiles of at most `size` × `size`, row by row from the top left.
pub fn tiles(settings: &RenderSettings, size: u32) -> Vec<Rect> {
    let size = size.max(1);
    let mut out = Vec::new();
    for y in (0..settings.height).step_by(size as usize) {
        for x in (0..settings.width).step_by(size as usize) {
            out.push(Rect {
                x,
                y,
                width: size.min(settings.width - x),
                height: size.min(settings.height - y),
            });
        }
    }
    out
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
/// ([`crate::progressive::render_to_target`]); `tile_size` does not matter then, and
/// `on_tile` hears of the whole frame at the end.
pub fn render_frame(tracer: &Tracer, tile_size: u32, on_tile: &(dyn Fn(u64) + Sync)) -> Frame {
    let settings = *tracer.settings();
    if let Some(target) = settings.sampling.target_error() {
        let (_, frame) =
            crate::progressive::render_to_target(tracer, None, target, &mut |_, _| true);
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
