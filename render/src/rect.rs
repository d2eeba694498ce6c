//! The rectangles of a frame that tiles cover: one checked against the frame, and a
//! frame cut into them.
//!
//! Plain geometry of pixels, below everything that renders them (a tile, a region of
//! adaptive sampling's blocks) and the image they are put into.

use thiserror::Error;

use crate::settings::RenderSettings;

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
    /// its tiles are advanced as regions of blocks ([`crate::adaptive::Region`]).
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
