//! How a frame is cut into tiles when the client does not say.

use protocol::{Settings, TileRect};

/// Smallest and largest tile sides a job may ask for. The upper bound keeps a tile's
/// result (side² × 3 bytes) far below the frame limit.
pub const MIN_TILE: u32 = 8;
pub const MAX_TILE: u32 = 512;

/// A tile side giving each tile about 64 K samples (a few milliseconds of work on one
/// core for the seed scene: long enough that the per-tile overhead vanishes, short
/// enough to balance), reduced until the frame has at least 64 tiles so that several
/// workers all have work.
///
/// Samples are counted by the budget, `aa` × `aa` per pixel, whatever the sampler: an
/// adaptive job usually spends less, but where it spends the budget (on edges) a tile
/// sized for fewer samples would be a straggler.
///
/// The side is always a multiple of 8, so that every tile is cut on the 8 × 8 blocks
/// adaptive sampling works in (its tiles must be; the others do not mind).
pub fn default_tile_size(settings: &Settings) -> u32 {
    let blocks = |side: u32| (side / 8 * 8).clamp(16, 256);
    let mut side = blocks(256 / settings.aa.max(1));
    while side > 16 && tile_count(settings, side) < 64 {
        side = blocks(side / 2);
    }
    side
}

/// The tile side of a sequence job's frames: about 64 K samples a tile as for any job,
/// reduced only until a frame has 8 tiles. A sequence keeps the workers busy with its
/// next frame while a frame's last tiles finish, so its frames need not be cut as
/// finely as a lone frame: fewer, larger tiles cost the farm less per frame (each
/// tile is a message, a check, a compression and a row written). A large frame is
/// still cut into many tiles (1920 × 1080 at aa 2: 135).
pub fn sequence_tile_size(settings: &Settings) -> u32 {
    let blocks = |side: u32| (side / 8 * 8).clamp(16, 256);
    let mut side = blocks(256 / settings.aa.max(1));
    while side > 16 && tile_count(settings, side) < 8 {
        side = blocks(side / 2);
    }
    side
}

pub fn tile_count(settings: &Settings, side: u32) -> u32 {
    settings.width.div_ceil(side) * settings.height.div_ceil(side)
}

/// The tiles of a frame, row by row from the top left: the renderer's own cut, so that
/// tile `i` means the same rectangle everywhere.
pub fn cut(settings: &Settings, side: u32) -> Vec<TileRect> {
    render::tiles(&verify::render_settings(settings), side)
        .into_iter()
        .map(|r| TileRect {
            x: r.x,
            y: r.y,
            width: r.width,
            height: r.height,
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use protocol::Sampling;

    #[test]
    fn default_tiles_are_cut_on_blocks() {
        for aa in 1..=64 {
            for (width, height) in [(600, 400), (40, 30), (1920, 1080), (8192, 8192)] {
                let s = Settings {
                    width,
                    height,
                    aa,
                    max_depth: 5,
                    sampling: Sampling::Adaptive { target_milli: 1000 },
                };
                for side in [default_tile_size(&s), sequence_tile_size(&s)] {
                    assert!(
                        side.is_multiple_of(8) && (16..=256).contains(&side),
                        "{aa}: {side}"
                    );
                    assert!(verify::adaptive::check_tile_side(side).is_ok());
                }
            }
        }
    }
}
