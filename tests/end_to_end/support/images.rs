//! Images compared as the farm's contract states it: byte for byte.

use std::path::Path;

use image::{ColorType, RgbImage};

/// Decodes a PNG, insisting on the 8-bit RGB the binary writes.
pub fn decode_rgb8(path: &Path) -> RgbImage {
    let img = image::open(path)
        .unwrap_or_else(|e| panic!("{} is not a readable PNG: {e}", path.display()));
    assert_eq!(
        img.color(),
        ColorType::Rgb8,
        "{} is not 8-bit RGB",
        path.display()
    );
    img.into_rgb8()
}

/// The two PNG files are the same image (size and every pixel) and the same bytes; on
/// a mismatch, says how many pixels differ and where the first is.
pub fn assert_same_png(actual: &Path, reference: &Path, what: &str) {
    let a_bytes = std::fs::read(actual).unwrap_or_else(|e| panic!("{what}: no image: {e}"));
    let r_bytes = std::fs::read(reference).expect("cannot read the reference image");
    let a = image::load_from_memory(&a_bytes)
        .unwrap_or_else(|e| panic!("{what}: not a PNG: {e}"))
        .to_rgb8();
    let r = image::load_from_memory(&r_bytes)
        .expect("the reference is a PNG")
        .to_rgb8();
    assert_eq!(a.dimensions(), r.dimensions(), "{what}: image size");
    if a.as_raw() != r.as_raw() {
        let differing = a.pixels().zip(r.pixels()).filter(|(p, q)| p != q).count();
        let (x, y, _) = a
            .enumerate_pixels()
            .find(|&(x, y, p)| p != r.get_pixel(x, y))
            .expect("some pixel differs");
        panic!(
            "{what}: {differing} of {} pixels differ from `tessera render`'s, the first at \
             ({x}, {y})",
            a.width() * a.height()
        );
    }
    assert!(
        a_bytes == r_bytes,
        "{what}: same pixels but the PNG files differ ({} vs {} bytes)",
        a_bytes.len(),
        r_bytes.len()
    );
}
