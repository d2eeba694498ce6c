//! Images compared as the farm's contract states it: byte for byte.

use std::path::Path;

/// A decoded image: 8-bit RGB, rows top first, three bytes a pixel.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Rgb8(render::Image);

impl Rgb8 {
    /// An image whose pixel (x, y) is `f(x, y)`.
    pub fn from_fn(width: u32, height: u32, f: impl Fn(u32, u32) -> [u8; 3]) -> Self {
        let mut image = render::Image::black(width, height);
        for (i, pixel) in image.rgb.chunks_exact_mut(3).enumerate() {
            let (x, y) = (i as u32 % width, i as u32 / width);
            pixel.copy_from_slice(&f(x, y));
        }
        Self(image)
    }

    pub fn dimensions(&self) -> (u32, u32) {
        (self.0.width, self.0.height)
    }

    /// The pixels' bytes, row by row.
    pub fn as_raw(&self) -> &[u8] {
        &self.0.rgb
    }

    pub fn get_pixel(&self, x: u32, y: u32) -> [u8; 3] {
        self.0.pixel(x, y)
    }

    /// Pixel (x, y)'s three bytes, to change.
    pub fn pixel_mut(&mut self, x: u32, y: u32) -> &mut [u8] {
        let at = (y as usize * self.0.width as usize + x as usize) * 3;
        &mut self.0.rgb[at..at + 3]
    }

    /// Every pixel with its position, in row-major order.
    pub fn enumerate_pixels(&self) -> impl Iterator<Item = (u32, u32, [u8; 3])> + '_ {
        let width = self.0.width;
        self.0.rgb.chunks_exact(3).enumerate().map(move |(i, p)| {
            let (x, y) = (i as u32 % width, i as u32 / width);
            (x, y, [p[0], p[1], p[2]])
        })
    }

    /// Every pixel, in row-major order.
    pub fn pixels(&self) -> impl Iterator<Item = [u8; 3]> + '_ {
        self.enumerate_pixels().map(|(_, _, p)| p)
    }

    /// The `width` × `height` part whose top left corner is (x, y).
    pub fn crop(&self, x: u32, y: u32, width: u32, height: u32) -> Self {
        Self::from_fn(width, height, |cx, cy| self.get_pixel(x + cx, y + cy))
    }
}

/// Any PNG, in 8-bit RGB as the farm reads its stored frames back (palettes and lower
/// depths expanded, 16 bits rounded, grey copied, alpha dropped); `Err` with the
/// decoder's reason when it is not a PNG.
pub fn decode_png(png: &[u8]) -> Result<Rgb8, String> {
    coordinator::decode_png(png)
        .map(Rgb8)
        .map_err(|e| format!("{e:#}"))
}

/// Decodes a PNG file, insisting on the 8-bit RGB the binary writes.
pub fn decode_rgb8(path: &Path) -> Rgb8 {
    let bytes = std::fs::read(path)
        .unwrap_or_else(|e| panic!("{} is not a readable file: {e}", path.display()));
    let header = png::Decoder::new(std::io::Cursor::new(&bytes))
        .read_info()
        .unwrap_or_else(|e| panic!("{} is not a readable PNG: {e}", path.display()))
        .info()
        .clone();
    assert_eq!(
        (header.color_type, header.bit_depth),
        (png::ColorType::Rgb, png::BitDepth::Eight),
        "{} is not 8-bit RGB",
        path.display()
    );
    decode_png(&bytes).unwrap_or_else(|e| panic!("{} is not a readable PNG: {e}", path.display()))
}

/// The two PNG files are the same image (size and every pixel) and the same bytes; on
/// a mismatch, says how many pixels differ and where the first is.
pub fn assert_same_png(actual: &Path, reference: &Path, what: &str) {
    let a_bytes = std::fs::read(actual).unwrap_or_else(|e| panic!("{what}: no image: {e}"));
    let r_bytes = std::fs::read(reference).expect("cannot read the reference image");
    let a = decode_png(&a_bytes).unwrap_or_else(|e| panic!("{what}: not a PNG: {e}"));
    let r = decode_png(&r_bytes).expect("the reference is a PNG");
    assert_eq!(a.dimensions(), r.dimensions(), "{what}: image size");
    if a.as_raw() != r.as_raw() {
        let differing = a.pixels().zip(r.pixels()).filter(|(p, q)| p != q).count();
        let (x, y, _) = a
            .enumerate_pixels()
            .find(|&(x, y, p)| p != r.get_pixel(x, y))
            .expect("some pixel differs");
        let (width, height) = a.dimensions();
        panic!(
            "{what}: {differing} of {} pixels differ from `tessera render`'s, the first at \
             ({x}, {y})",
            width * height
        );
    }
    assert!(
        a_bytes == r_bytes,
        "{what}: same pixels but the PNG files differ ({} vs {} bytes)",
        a_bytes.len(),
        r_bytes.len()
    );
}
