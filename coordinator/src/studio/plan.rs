//! How an interactive view is rendered: a coarse picture first, then the full
//! resolution, then the full quality, each pass painted over the last on the page.
//!
//! Every pass is an ordinary job of the farm (the same tiles, verification and
//! determinism), so the last pass's picture is, byte for byte, what `tessera render`
//! gives for the view's scene and settings. The earlier passes exist only to put a
//! picture on screen fast: the coarse pass has about as many pixels as a thumbnail, so
//! it is back within a round trip or two of the edit.

use protocol::{Sampling, Settings};

use super::views::Millis;

/// The coarse pass has at most this many pixels: 240 × 135 for a 960 × 540 view, a few
/// milliseconds of rendering for a simple scene.
pub const COARSE_PIXELS: u64 = 32_768;

/// Tile side of every pass: small, so that the first tiles come back at once, every
/// worker gets some, and each tile pushed to a page is small.
pub const PREVIEW_TILE: u32 = 64;

/// One pass of a view.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Pass {
    /// Its place in the plan, from 0.
    pub index: u32,
    /// The pass renders 1 / `scale` of the view's width and height: a pixel of it
    /// covers `scale` × `scale` pixels of the view.
    pub scale: u32,
    pub settings: Settings,
    pub tile_size: u32,
    /// Whether this pass gives the view's final picture.
    pub last: bool,
}

impl Pass {
    /// What the pass is, in a few words, for the page.
    pub fn description(&self) -> String {
        let s = &self.settings;
        let quality = match s.sampling {
            Sampling::Adaptive { target_milli } => format!(
                "adaptive to {} levels, cap aa {}",
                f64::from(target_milli) / 1000.0,
                s.aa
            ),
            sampling if s.aa > 1 => format!("aa {} {}", s.aa, sampling.name()),
            _ => "1 sample per pixel".to_owned(),
        };
        format!("{} × {}, {quality}", s.width, s.height)
    }
}

/// The passes of a view with final settings `full`: a coarse one when the view is
/// larger than [`COARSE_PIXELS`], one sample per pixel at full size when the final
/// pass takes more, then the final pass.
pub fn passes(full: Settings) -> Vec<Pass> {
    let mut plan = Vec::with_capacity(3);
    let pixels =
        |scale: u32| u64::from(full.width.div_ceil(scale)) * u64::from(full.height.div_ceil(scale));
    let mut scale = 1;
    while pixels(scale) > COARSE_PIXELS {
        scale *= 2;
    }
    let preview = |scale: u32| Settings {
        width: full.width.div_ceil(scale),
        height: full.height.div_ceil(scale),
        aa: 1,
        max_depth: full.max_depth,
        sampling: Sampling::Grid,
    };
    if scale > 1 {
        plan.push((scale, preview(scale), PREVIEW_TILE));
    }
    let one_sample = full.aa == 1 && full.sampling == Sampling::Grid;
    if !one_sample {
        plan.push((1, preview(1), PREVIEW_TILE));
    }
    // The final pass in the same small tiles: the first of them come back as fast, and
    // every tile pushed to a page is at most 12 KiB of pixels, which bounds a page's
    // backlog in bytes.
    plan.push((1, full, PREVIEW_TILE));
    let count = plan.len();
    plan.into_iter()
        .enumerate()
        .map(|(i, (scale, settings, tile_size))| Pass {
            index: i as u32,
            scale,
            settings,
            tile_size,
            last: i + 1 == count,
        })
        .collect()
}

/// An edit that comes less than this after the view's previous one is part of a
/// drag: its passes after the first are sent to the page only once it has lasted this
/// long ([`hold_until`]).
pub const SETTLE_MS: Millis = 150;

/// Until when the passes after the first of an edit made at `edited_at` are held back
/// from the page, the view's previous edit having been made at `previous`.
///
/// While the camera moves, each edit is replaced by the next within a frame or two:
/// its coarse pass shows it, and its full-resolution passes (about 30 times the coarse
/// pass's pixels for a 960 × 540 view) would reach a page on an ordinary link only
/// after the next edit made them useless, queued in the network ahead of that edit's
/// tiles. An edit after a pause is not held: it is the one whose picture is wanted.
/// The last edit of a drag waits [`SETTLE_MS`] at most, less than its final pass takes
/// to render.
pub fn hold_until(edited_at: Millis, previous: Option<Millis>) -> Millis {
    match previous {
        Some(previous) if edited_at.saturating_sub(previous) < SETTLE_MS => edited_at + SETTLE_MS,
        _ => edited_at,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_the_edits_of_a_drag_are_held() {
        assert_eq!(hold_until(1_000, None), 1_000);
        assert_eq!(hold_until(1_000, Some(1_000 - SETTLE_MS)), 1_000);
        assert_eq!(hold_until(1_000, Some(900)), 1_000 + SETTLE_MS);
        assert_eq!(hold_until(1_000, Some(1_000)), 1_000 + SETTLE_MS);
    }

    fn settings(width: u32, height: u32, aa: u32, sampling: Sampling) -> Settings {
        Settings {
            width,
            height,
            aa,
            max_depth: 10,
            sampling,
        }
    }

    #[test]
    fn a_large_view_goes_coarse_then_full_size_then_full_quality() {
        let full = settings(960, 540, 2, Sampling::Grid);
        let plan = passes(full);
        let sizes: Vec<_> = plan
            .iter()
            .map(|p| {
                (
                    p.scale,
                    p.settings.width,
                    p.settings.height,
                    p.settings.aa,
                    p.last,
                )
            })
            .collect();
        assert_eq!(
            sizes,
            [
                (4, 240, 135, 1, false),
                (1, 960, 540, 1, false),
                (1, 960, 540, 2, true)
            ]
        );
        assert_eq!(plan[2].settings, full, "the last pass is the view itself");
        assert!(plan.iter().all(|p| p.tile_size == PREVIEW_TILE));
        assert_eq!(plan[0].description(), "240 × 135, 1 sample per pixel");
        assert_eq!(plan[2].description(), "960 × 540, aa 2 grid");
    }

    #[test]
    fn passes_that_would_repeat_are_left_out() {
        // One sample per pixel: the full-size preview would be the final pass.
        let plan = passes(settings(960, 540, 1, Sampling::Grid));
        assert_eq!(plan.len(), 2);
        // Small enough to need no coarse pass.
        let plan = passes(settings(160, 120, 3, Sampling::Jittered));
        assert_eq!(plan.iter().map(|p| p.scale).collect::<Vec<_>>(), [1, 1]);
        let plan = passes(settings(160, 120, 1, Sampling::Grid));
        assert_eq!(plan.len(), 1);
        assert!(plan[0].last);
    }

    #[test]
    fn the_coarse_pass_covers_the_frame_whatever_its_size() {
        for (w, h) in [
            (961, 541),
            (16384, 16384),
            (16384, 1),
            (1, 16384),
            (181, 181),
        ] {
            let plan = passes(settings(w, h, 4, Sampling::Adaptive { target_milli: 500 }));
            let first = &plan[0];
            let px = u64::from(first.settings.width) * u64::from(first.settings.height);
            assert!(px <= COARSE_PIXELS, "{w}x{h}: {px} pixels");
            assert!(first.settings.width * first.scale >= w, "{w}x{h}");
            assert!(first.settings.height * first.scale >= h, "{w}x{h}");
            assert!(first.settings.width >= 1 && first.settings.height >= 1);
            assert!(plan.last().unwrap().last);
            assert_eq!(plan.iter().filter(|p| p.last).count(), 1);
        }
    }
}
