//! Tiles: any rectangle of the frame, rendered on its own with the same bytes it has in
//! a full-frame render, and whole frames assembled from tiles rendered in parallel.

use rayon::prelude::*;
use thiserror::Error;

use crate::image::Image;
use crate::scene::RenderSettings;
use crate::tracer::Tracer;

/// Default tile side for whole-frame renders: small enough to balance two to dozens of
/// threads on a 600 × 400 frame, large enough that scheduling costs nothing.
pub const DEFAULT_TILE_SIZE: u32 = 32;

/// A rectangle of pixels: columns `x .. x + width`, rows `y .. y + height`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct Rect {
    pub x: u32,
    pub y: u32,
    pub width: u32,
    pub height: u32,
}

/// A tile that does not lie inside the frame.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
#[error("tile {rect:?} does not lie inside the {frame_width}x{frame_height} frame")]
pub struct TileError {
    pub rect: Rect,
    pub frame_width: u32,
    pub frame_height: u32,
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
            Err(TileError {
                rect: *self,
                frame_width: settings.width,
                frame_height: settings.height,
            })
        }
    }
}

/// The pixels of one tile, RGB8, rows top to bottom.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct TileImage {
    pub rect: Rect,
    pub rgb: Vec<u8>,
    /// Rays traced for this tile (camera, reflection and shadow rays).
    pub rays: u64,
}

/// Renders one tile. Each pixel depends only on the scene, the settings and its
/// coordinates, so the bytes equal those of the same pixels in any other tiling.
pub fn render_tile(tracer: &Tracer, rect: Rect) -> Result<TileImage, TileError> {
    rect.check_inside(tracer.settings())?;
    let mut rgb = Vec::with_capacity(rect.pixel_count() as usize * 3);
    let mut rays = 0;
    for j in rect.y..rect.y + rect.height {
        for i in rect.x..rect.x + rect.width {
            rgb.extend_from_slice(&tracer.pixel(i, j, &mut rays));
        }
    }
    Ok(TileImage { rect, rgb, rays })
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

/// A rendered frame and what it cost.
#[derive(Clone, Debug)]
pub struct Frame {
    pub image: Image,
    pub rays: u64,
}

/// Renders the whole frame as tiles on the current rayon pool, calling `on_tile` with
/// the pixel count of each finished tile (for progress display). The image is the same
/// whatever the tile size and the number of threads.
pub fn render_frame(tracer: &Tracer, tile_size: u32, on_tile: &(dyn Fn(u64) + Sync)) -> Frame {
    let settings = *tracer.settings();
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
    for tile in &done {
        image.put_tile(tile);
        rays += tile.rays;
    }
    Frame { image, rays }
}
