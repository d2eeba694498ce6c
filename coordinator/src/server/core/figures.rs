//! The figures the coordinator reports of its jobs and workers, as functions of what
//! it has seen (time passed in): how they are estimated is decided here, and tested.

use crate::db::Totals;

/// The image's estimated error in 8-bit levels: the root mean square of the per-pixel
/// estimates, once every pixel of the image has one (`pixels` of them), `None` before,
/// and always with one sample per pixel (`aa` 1: no spread to measure).
///
/// Not over the tiles in so far: those are whichever part of the image came first
/// (often a smooth sky), and read far better than the image will (0.003 levels at 6 of
/// 300 tiles, 1.309 at the end). An adaptive job's totals hold the whole frame's
/// estimate after each pass, so it has one from its first pass on.
pub fn image_error(aa: u32, totals: &Totals, pixels: u64) -> Option<f64> {
    (aa >= 2 && pixels > 0 && totals.error_pixels >= pixels)
        .then(|| (totals.error_sq_sum / totals.error_pixels as f64).sqrt())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn totals(error_sq_sum: f64, error_pixels: u64) -> Totals {
        Totals {
            error_sq_sum,
            error_pixels,
            ..Totals::default()
        }
    }

    #[test]
    fn the_error_is_reported_once_it_covers_the_whole_image() {
        let pixels = 300 * 256;
        // 6 tiles of sky in: no estimate yet, not one that reads too good.
        assert_eq!(
            image_error(2, &totals(0.0001 * 6.0 * 256.0, 6 * 256), pixels),
            None
        );
        assert_eq!(image_error(2, &totals(0.0, 0), pixels), None);
        let whole = image_error(2, &totals(1.309 * 1.309 * pixels as f64, pixels), pixels);
        assert!((whole.unwrap() - 1.309).abs() < 1e-9, "{whole:?}");
        // One sample per pixel: nothing to measure, even with every pixel in.
        assert_eq!(image_error(1, &totals(1.0, pixels), pixels), None);
    }
}
