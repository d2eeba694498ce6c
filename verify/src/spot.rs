//! Spot checks: a few pixels of a tile result rendered again and compared.
//!
//! The pixels are chosen after the result has arrived, from a seed the worker never
//! sees, so a worker cannot know which of its pixels will be looked at: a result with a
//! share `f` of its pixels wrong passes `n` checked pixels with probability `(1 − f)ⁿ`,
//! and a wholly wrong one never passes. When two results of one tile differ, the
//! coordinator renders the pixels where they differ to tell which one is wrong.

use protocol::TileRect;
use render::{Rect, Tracer};

/// One pixel of a result that is not what the renderer gives.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error("pixel ({x}, {y}) is {got:?}, the renderer gives {expected:?}")]
pub struct WrongPixel {
    pub x: u32,
    pub y: u32,
    pub expected: [u8; 3],
    pub got: [u8; 3],
}

/// The number of pixels checked in a tile when `per_tile` are asked for: no more than
/// one in 128 of its pixels (so that checking costs under 1 % of rendering on any
/// tile), and at least one.
pub fn pixels_to_check(rect: TileRect, per_tile: u32) -> usize {
    let pixels = u64::from(rect.width) * u64::from(rect.height);
    (per_tile as usize).min((pixels / 128).max(1) as usize)
}

/// `count` distinct pixels of the tile (all of them if it has fewer), chosen by
/// `seed`: absolute frame coordinates.
pub fn choose(rect: TileRect, count: usize, seed: u64) -> Vec<(u32, u32)> {
    let pixels = u64::from(rect.width) * u64::from(rect.height);
    let mut state = seed;
    let mut chosen: Vec<u64> = Vec::with_capacity(count);
    while (chosen.len() as u64) < pixels.min(count as u64) {
        let index = splitmix(&mut state) % pixels;
        if !chosen.contains(&index) {
            chosen.push(index);
        }
    }
    chosen
        .into_iter()
        .map(|i| {
            (
                rect.x + (i % u64::from(rect.width)) as u32,
                rect.y + (i / u64::from(rect.width)) as u32,
            )
        })
        .collect()
}

/// SplitMix64: spreads a seed into well-mixed numbers.
fn splitmix(state: &mut u64) -> u64 {
    *state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
    let mut z = *state;
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// The bytes of pixel (`x`, `y`) (frame coordinates) of a tile's RGB8 result.
pub fn pixel_at(rect: TileRect, rgb: &[u8], x: u32, y: u32) -> [u8; 3] {
    let i = ((y - rect.y) as usize * rect.width as usize + (x - rect.x) as usize) * 3;
    [rgb[i], rgb[i + 1], rgb[i + 2]]
}

/// The pixel (`x`, `y`) as the renderer gives it: a one-pixel tile, which has the same
/// bytes as the pixel in any other tiling.
pub fn render_pixel(tracer: &Tracer, x: u32, y: u32) -> [u8; 3] {
    let rect = Rect {
        x,
        y,
        width: 1,
        height: 1,
    };
    match render::render_tile(tracer, rect) {
        Ok(tile) => [tile.rgb[0], tile.rgb[1], tile.rgb[2]],
        // Callers pass pixels of the job's own grid or jittered tiles, which lie inside
        // the frame (adaptive answers are checked by advancing a block again, in
        // `crate::adaptive`).
        Err(e) => unreachable!("a grid or jittered tile's pixel renders alone: {e}"),
    }
}

/// Renders the chosen pixels and compares them with the result's.
pub fn check(
    tracer: &Tracer,
    rect: TileRect,
    rgb: &[u8],
    pixels: &[(u32, u32)],
) -> Result<(), WrongPixel> {
    for &(x, y) in pixels {
        let expected = render_pixel(tracer, x, y);
        let got = pixel_at(rect, rgb, x, y);
        if got != expected {
            return Err(WrongPixel {
                x,
                y,
                expected,
                got,
            });
        }
    }
    Ok(())
}

/// The pixels where two results of a tile differ, in row order.
pub fn differing_pixels(rect: TileRect, a: &[u8], b: &[u8]) -> Vec<(u32, u32)> {
    a.chunks_exact(3)
        .zip(b.chunks_exact(3))
        .enumerate()
        .filter(|(_, (p, q))| p != q)
        .map(|(i, _)| {
            (
                rect.x + (i % rect.width as usize) as u32,
                rect.y + (i / rect.width as usize) as u32,
            )
        })
        .collect()
}

/// Which of two differing results of a tile is wrong.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Arbitration {
    /// Where the first result is wrong, if it is.
    pub first: Option<WrongPixel>,
    /// Where the second result is wrong, if it is.
    pub second: Option<WrongPixel>,
}

/// How many of the differing pixels are rendered to decide, at most.
pub const ARBITRATION_PIXELS: usize = 8;

/// Renders up to [`ARBITRATION_PIXELS`] of the pixels where `first` and `second`
/// differ: at each, at least one of them is wrong. Finding every result wrong
/// somewhere is what matters, so it stops early only once both are.
pub fn arbitrate(tracer: &Tracer, rect: TileRect, first: &[u8], second: &[u8]) -> Arbitration {
    let mut verdict = Arbitration {
        first: None,
        second: None,
    };
    for (x, y) in differing_pixels(rect, first, second)
        .into_iter()
        .take(ARBITRATION_PIXELS)
    {
        let expected = render_pixel(tracer, x, y);
        for (rgb, slot) in [(first, &mut verdict.first), (second, &mut verdict.second)] {
            let got = pixel_at(rect, rgb, x, y);
            if got != expected && slot.is_none() {
                *slot = Some(WrongPixel {
                    x,
                    y,
                    expected,
                    got,
                });
            }
        }
        if verdict.first.is_some() && verdict.second.is_some() {
            break;
        }
    }
    verdict
}

#[cfg(test)]
mod tests {
    use super::*;
    use protocol::{Sampling, Settings};

    fn tracer() -> (Tracer, TileRect) {
        let scene = crate::canary::parse(crate::canary::SCENE, &crate::canary::files()).unwrap();
        let settings = Settings {
            width: 40,
            height: 30,
            aa: 2,
            max_depth: 4,
            sampling: Sampling::Jittered,
        };
        let rect = TileRect {
            x: 8,
            y: 4,
            width: 16,
            height: 16,
        };
        (crate::tracer(&scene, &settings).unwrap(), rect)
    }

    #[test]
    fn choices_are_distinct_inside_the_tile_and_follow_the_seed() {
        let rect = TileRect {
            x: 10,
            y: 20,
            width: 5,
            height: 3,
        };
        let a = choose(rect, 8, 1);
        assert_eq!(a.len(), 8);
        let mut sorted = a.clone();
        sorted.sort_unstable();
        sorted.dedup();
        assert_eq!(sorted.len(), 8);
        assert!(a
            .iter()
            .all(|&(x, y)| (10..15).contains(&x) && (20..23).contains(&y)));
        assert_eq!(a, choose(rect, 8, 1));
        assert_ne!(a, choose(rect, 8, 2));
        assert_eq!(
            choose(rect, 100, 3).len(),
            15,
            "never more than the tile has"
        );
        assert_eq!(pixels_to_check(rect, 8), 1);
    }

    #[test]
    fn a_right_result_passes_and_a_changed_byte_is_found_when_looked_at() {
        let (tracer, rect) = tracer();
        let right = render::render_tile(&tracer, crate::render_rect(rect))
            .unwrap()
            .rgb;
        let all = choose(rect, 256, 9);
        assert_eq!(check(&tracer, rect, &right, &all), Ok(()));
        let mut wrong = right.clone();
        wrong[3 * 17 + 2] = wrong[3 * 17 + 2].wrapping_add(1); // pixel (9, 5)
        let err = check(&tracer, rect, &wrong, &all).unwrap_err();
        assert_eq!((err.x, err.y), (9, 5));
        let verdict = arbitrate(&tracer, rect, &right, &wrong);
        assert_eq!(verdict.first, None);
        assert_eq!(verdict.second.map(|w| (w.x, w.y)), Some((9, 5)));
        let verdict = arbitrate(&tracer, rect, &wrong, &right);
        assert!(verdict.first.is_some() && verdict.second.is_none());
    }
}
