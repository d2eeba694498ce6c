//! Tile invariance: a frame cut into tiles of any size, rendered on any number of
//! threads, or one tile rendered on its own, gives the same bytes.

use proptest::prelude::*;
use render::{render_tile, Image, Rect, Sampling, Tracer};

use crate::support::{frame, seed, tracer};

/// The reference: every pixel rendered as its own 1×1 tile, on this thread.
fn pixel_by_pixel(tracer: &Tracer) -> Image {
    let s = tracer.settings();
    let mut image = Image::black(s.width, s.height);
    for y in 0..s.height {
        for x in 0..s.width {
            let rect = Rect {
                x,
                y,
                width: 1,
                height: 1,
            };
            image.put_tile(&render_tile(tracer, rect).unwrap());
        }
    }
    image
}

#[test]
fn frames_equal_pixel_by_pixel_rendering() {
    let t = tracer(&seed(), 96, 64, 2, Sampling::Grid);
    let reference = pixel_by_pixel(&t);
    for (tile, threads) in [(1, 1), (7, 2), (32, 3), (1000, 1), (16, 8)] {
        assert!(
            frame(&t, tile, threads).image == reference,
            "tile {tile}, {threads} threads"
        );
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(24))]

    /// Random tile sizes and thread counts give byte-identical frames.
    #[test]
    fn any_tiling_and_thread_count_gives_the_same_image(
        tile in 1u32..80,
        threads in 1usize..6,
        aa in 1u32..4,
    ) {
        let t = tracer(&seed(), 90, 60, aa, Sampling::Grid);
        let reference = frame(&t, 90, 1).image;
        prop_assert!(frame(&t, tile, threads).image == reference);
    }

    /// Any rectangle rendered alone equals the same pixels of the full frame.
    #[test]
    fn a_tile_equals_its_pixels_in_the_full_frame(
        x in 0u32..120, y in 0u32..80, w in 1u32..60, h in 1u32..60,
    ) {
        let t = tracer(&seed(), 120, 80, 2, Sampling::Grid);
        let full = frame(&t, 16, 2).image;
        let rect = Rect { x, y, width: w.min(120 - x), height: h.min(80 - y) };
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
fn tiles_outside_the_frame_are_refused() {
    let t = tracer(&seed(), 40, 30, 1, Sampling::Grid);
    for rect in [
        Rect {
            x: 0,
            y: 0,
            width: 0,
            height: 1,
        },
        Rect {
            x: 39,
            y: 0,
            width: 2,
            height: 1,
        },
        Rect {
            x: 0,
            y: 30,
            width: 1,
            height: 1,
        },
        Rect {
            x: u32::MAX,
            y: 0,
            width: 2,
            height: 1,
        },
    ] {
        assert!(render_tile(&t, rect).is_err(), "{rect:?}");
    }
}
