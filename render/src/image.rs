//! The frame buffer and its PNG encoding (section 6: 8-bit RGB, top row first).

use crate::tile::{Rect, TileImage};

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

    /// Encodes the image as PNG.
    pub fn to_png(&self) -> Vec<u8> {
        use image::ImageEncoder;
        let mut out = Vec::new();
        image::codecs::png::PngEncoder::new(&mut out)
            .write_image(
                &self.rgb,
                self.width,
                self.height,
                image::ExtendedColorType::Rgb8,
            )
            .expect("encoding an in-memory RGB8 buffer of the right size cannot fail");
        out
    }
}
