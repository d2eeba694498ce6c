//! The frame buffer, the tiles put into it, and its PNG encoding (section 6: 8-bit RGB,
//! top row first).
//!
//! Below the samplers and the tile renderer, which all fill images; it knows only the
//! rectangles pixels come in ([`crate::rect`]).

use crate::rect::Rect;

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

/// An 8-bit RGB image, rows top to bottom.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Image {
    pub width: u32,
    pub height: u32,
    pub rgb: Vec<u8>,
}

impl Image {
    pub fn black(width: u32, height: u32) -> Self {
        Image {
            width,
            height,
            rgb: vec![0; width as usize * height as usize * 3],
        }
    }

    /// Copies a tile's pixels into place. The tile must lie inside the image.
    pub fn put_tile(&mut self, tile: &TileImage) {
        self.put_rect(tile.rect, &tile.rgb);
    }

    /// Copies the RGB8 pixels of rectangle `r` (rows top to bottom, `r.width × r.height
    /// × 3` bytes) into place. The rectangle must lie inside the image.
    pub fn put_rect(&mut self, r: Rect, rgb: &[u8]) {
        let row_bytes = r.width as usize * 3;
        for (row, src) in rgb.chunks_exact(row_bytes).enumerate() {
            let start = ((r.y as usize + row) * self.width as usize + r.x as usize) * 3;
            self.rgb[start..start + row_bytes].copy_from_slice(src);
        }
    }

    pub fn pixel_count(&self) -> u64 {
        u64::from(self.width) * u64::from(self.height)
    }

    /// The RGB value at column `x`, row `y`.
    pub fn pixel(&self, x: u32, y: u32) -> [u8; 3] {
        let i = (y as usize * self.width as usize + x as usize) * 3;
        [self.rgb[i], self.rgb[i + 1], self.rgb[i + 2]]
    }

    /// Encodes the image as PNG: 8-bit RGB, no ancillary chunk, fast deflate and the
    /// adaptive filter, byte for byte what the `image` crate's default `PngEncoder` wrote
    /// (stored frames and golden files are compared as bytes).
    ///
    /// The png crate directly: `image` would bring colour management the farm never uses
    /// into every build.
    ///
    /// # Panics
    ///
    /// If `rgb` does not hold `width × height` pixels or a side is 0: an `Image` so
    /// broken is a bug of its maker, and writing to memory has no other way to fail.
    pub fn to_png(&self) -> Vec<u8> {
        let mut out = Vec::new();
        write_png(&mut out, self).unwrap_or_else(|e| {
            panic!(
                "encoding a {}×{} image of {} bytes as PNG: {e}",
                self.width,
                self.height,
                self.rgb.len()
            )
        });
        out
    }
}

/// Writes `image` as PNG with the settings of `image` 0.25's `PngEncoder::new`: its
/// default `CompressionType::Fast` is `png::Compression::Fast`, its default
/// `FilterType::Adaptive` is set after the compression (which picks a filter of its own),
/// and nothing but the size, colour type and depth goes into the header's `Info`.
fn write_png(out: &mut Vec<u8>, image: &Image) -> Result<(), png::EncodingError> {
    let mut encoder =
        png::Encoder::with_info(out, png::Info::with_size(image.width, image.height))?;
    encoder.set_color(png::ColorType::Rgb);
    encoder.set_depth(png::BitDepth::Eight);
    encoder.set_compression(png::Compression::Fast);
    encoder.set_filter(png::Filter::Adaptive);
    let mut writer = encoder.write_header()?;
    writer.write_image_data(&image.rgb)?;
    writer.finish()
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// The SHA-256 of `bytes`, in hexadecimal.
    pub(crate) fn sha256_hex(bytes: &[u8]) -> String {
        use sha2::Digest;
        sha2::Sha256::digest(bytes)
            .iter()
            .map(|b| format!("{b:02x}"))
            .collect()
    }

    fn from_fn(width: u32, height: u32, f: impl Fn(u32, u32) -> [u8; 3]) -> Image {
        let mut image = Image::black(width, height);
        for y in 0..height {
            for x in 0..width {
                let i = (y as usize * width as usize + x as usize) * 3;
                image.rgb[i..i + 3].copy_from_slice(&f(x, y));
            }
        }
        image
    }

    /// `image.to_png()` is byte for byte what the encoder it replaced wrote (the `image`
    /// crate's default PNG encoder, 0.25, whose output's SHA-256 is `digest`), and
    /// decodes to the image.
    pub(crate) fn check_png(image: &Image, digest: &str) {
        let png = image.to_png();
        assert_eq!(
            sha256_hex(&png),
            digest,
            "{}×{} image",
            image.width,
            image.height
        );
        let decoder = png::Decoder::new(std::io::Cursor::new(&png));
        let mut reader = decoder.read_info().unwrap();
        assert_eq!(reader.info().size(), (image.width, image.height));
        assert_eq!(
            reader.output_color_type(),
            (png::ColorType::Rgb, png::BitDepth::Eight)
        );
        let mut rgb = vec![0; reader.output_buffer_size().unwrap()];
        reader.next_frame(&mut rgb).unwrap();
        assert_eq!(rgb, image.rgb);
    }

    #[test]
    fn png_bytes_are_those_of_the_image_crate() {
        // A pseudo-random noise that neither filter nor deflate can do much with.
        let mut state = 0x2545_f491_u32;
        let mut noise = Image::black(97, 61);
        for byte in &mut noise.rgb {
            state ^= state << 13;
            state ^= state >> 17;
            state ^= state << 5;
            *byte = state as u8;
        }
        // Each with the SHA-256 of what `image` 0.25's PNG encoder wrote for it.
        let images = [
            (
                Image::black(1, 1),
                "4d44c07cf62f61efdc4fe0ea126031bc958585f934e0ef8c1c7d2baca829aeae",
            ),
            (
                from_fn(1, 1, |_, _| [255, 128, 7]),
                "5800ebf9696633587bc1e646e40977dac18a1f767afecc839fa1d6c2db93c14a",
            ),
            (
                Image::black(600, 400),
                "3a59bd56a68239a9455fdf9d1d1defad9eef68924c3307199d8fb510eff2c002",
            ),
            (
                from_fn(3, 5, |x, y| [x as u8 * 80, y as u8 * 50, 200]),
                "55ff9c9c6e79f6276100b5f81e101665a1c4ae3398f90d1cd00b2e75fe5edd0c",
            ),
            (
                from_fn(1, 257, |_, y| [y as u8, 0, 255 - y as u8]),
                "f75a2ec44088210425f024793afa6867a46e857df69779c2ebad83a40f94e558",
            ),
            (
                from_fn(257, 1, |x, _| [x as u8; 3]),
                "ef600c6fa45b601b87191d4484ce6439196ae0447a34564beb13b2a8deb00fad",
            ),
            // A smooth gradient with a sharp edge, like a sky over a floor.
            (
                from_fn(333, 211, |x, y| {
                    if y > 120 {
                        [(x / 3) as u8, 90, 40]
                    } else {
                        [(x * 255 / 332) as u8, (y * 255 / 120) as u8, 180]
                    }
                }),
                "f5a139be016dfef94426c025c6a3e3c61d9fb5d5bc57ca5fb0d8c9c1fa7030d6",
            ),
            (
                noise,
                "2ff916d4aaf3b23df13626818791174f1c8bbbdcda4fc91b54a5b174ae983b6f",
            ),
        ];
        for (image, digest) in &images {
            check_png(image, digest);
        }
    }
}
