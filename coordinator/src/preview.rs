//! The animated preview of a sequence job (`GET /api/jobs/ID/preview.gif`): its frames
//! done one after another from the first, each downscaled, as one looping GIF.
//!
//! The work is bounded: at most [`MAX_FRAMES`] frames (with more done, every k-th, each
//! shown k times as long, so the preview still plays at the scene's speed), each at
//! most [`SIDE`] pixels on its longer side; the frames are decoded, downscaled and
//! encoded one at a time, so only one full-size frame is in memory at once.

use std::borrow::Borrow;

use anyhow::{Context, Result};
use image::codecs::gif::{GifEncoder, Repeat};
use image::{Delay, Frame, RgbaImage};

/// The most frames a preview holds.
pub const MAX_FRAMES: u32 = 240;

/// A preview's frames are at most this many pixels on their longer side.
pub const SIDE: u32 = 320;

/// The frame rate of a scene whose animation does not give one.
pub const DEFAULT_FPS: f64 = 24.0;

/// The GIF encoder's colour quantisation speed, 1 (best, slowest) to 30: 10 is the
/// `gif` crate's own suggestion, fast enough for a preview of hundreds of frames.
const QUANTISATION_SPEED: i32 = 10;

/// The frames a preview of `done_prefix` frames done from `first` shows, and the step
/// between them: all of them up to [`MAX_FRAMES`], else every k-th from the first, k
/// the smallest step that keeps them within [`MAX_FRAMES`].
pub fn frames_shown(first: u32, done_prefix: u32) -> (Vec<u32>, u32) {
    let step = done_prefix.div_ceil(MAX_FRAMES).max(1);
    let frames = (0..done_prefix)
        .step_by(step as usize)
        .map(|i| first + i)
        .collect();
    (frames, step)
}

/// How long each shown frame stays, in hundredths of a second (the GIF's unit): `step`
/// frames of the scene at `fps` frames per second. At least 2: browsers play a shorter
/// delay as a tenth of a second.
pub fn delay_cs(fps: f64, step: u32) -> u16 {
    let fps = if fps.is_finite() && fps > 0.0 {
        fps
    } else {
        DEFAULT_FPS
    };
    (100.0 * f64::from(step) / fps)
        .round()
        .clamp(2.0, f64::from(u16::MAX)) as u16
}

/// Decodes a stored frame's PNG.
pub fn decode_png(png: &[u8]) -> Result<render::Image> {
    let decoded = image::load_from_memory_with_format(png, image::ImageFormat::Png)
        .context("not a PNG image")?
        .into_rgb8();
    Ok(render::Image {
        width: decoded.width(),
        height: decoded.height(),
        rgb: decoded.into_raw(),
    })
}

/// A nearest-pixel copy of `image` whose longer side is at most `side`, its aspect
/// kept.
pub fn downscale(image: &render::Image, side: u32) -> render::Image {
    let longer = image.width.max(image.height);
    if longer <= side {
        return image.clone();
    }
    let w = (u64::from(image.width) * u64::from(side) / u64::from(longer)).max(1) as u32;
    let h = (u64::from(image.height) * u64::from(side) / u64::from(longer)).max(1) as u32;
    let mut out = render::Image::black(w, h);
    for y in 0..h {
        let sy = (u64::from(y) * u64::from(image.height) / u64::from(h)) as u32;
        for x in 0..w {
            let sx = (u64::from(x) * u64::from(image.width) / u64::from(w)) as u32;
            let i = (y as usize * w as usize + x as usize) * 3;
            out.rgb[i..i + 3].copy_from_slice(&image.pixel(sx, sy));
        }
    }
    out
}

/// Encodes `frames` (RGB images of one size, taken one at a time) as a GIF that loops
/// forever, each frame shown `delay_cs` hundredths of a second. The first error of
/// `frames` stops it.
pub fn encode_gif<I: Borrow<render::Image>>(
    frames: impl IntoIterator<Item = Result<I>>,
    delay_cs: u16,
) -> Result<Vec<u8>> {
    let mut out = Vec::new();
    {
        let mut encoder = GifEncoder::new_with_speed(&mut out, QUANTISATION_SPEED);
        encoder.set_repeat(Repeat::Infinite)?;
        let delay = Delay::from_numer_denom_ms(u32::from(delay_cs) * 10, 1);
        let mut size = None;
        for frame in frames {
            let frame = frame?;
            let frame: &render::Image = frame.borrow();
            let this = (frame.width, frame.height);
            anyhow::ensure!(
                *size.get_or_insert(this) == this,
                "a frame of {}×{} among frames of {}×{}",
                this.0,
                this.1,
                size.map_or(0, |s| s.0),
                size.map_or(0, |s| s.1)
            );
            let rgba: Vec<u8> = frame
                .rgb
                .chunks_exact(3)
                .flat_map(|p| [p[0], p[1], p[2], 255])
                .collect();
            let buffer = RgbaImage::from_raw(frame.width, frame.height, rgba)
                .context("a frame's pixels do not fill its size")?;
            encoder.encode_frame(Frame::from_parts(buffer, 0, 0, delay))?;
        }
        anyhow::ensure!(size.is_some(), "no frame to encode");
        // Dropping the encoder writes the GIF's trailer.
    }
    Ok(out)
}

/// A frame of a decoded GIF, for the tests.
#[cfg(test)]
pub struct DecodedFrame {
    pub width: u32,
    pub height: u32,
    /// In hundredths of a second.
    pub delay_cs: u32,
    pub rgba: Vec<u8>,
}

/// The frames of a GIF, for the tests.
#[cfg(test)]
pub fn decode_gif(gif: &[u8]) -> Result<Vec<DecodedFrame>> {
    use image::AnimationDecoder;
    let decoder = image::codecs::gif::GifDecoder::new(std::io::Cursor::new(gif))?;
    decoder
        .into_frames()
        .map(|frame| {
            let frame = frame?;
            let (numer, denom) = frame.delay().numer_denom_ms();
            let buffer = frame.into_buffer();
            Ok(DecodedFrame {
                width: buffer.width(),
                height: buffer.height(),
                delay_cs: numer / denom.max(1) / 10,
                rgba: buffer.into_raw(),
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn filled(width: u32, height: u32, rgb: [u8; 3]) -> render::Image {
        render::Image {
            width,
            height,
            rgb: rgb.repeat(width as usize * height as usize),
        }
    }

    #[test]
    fn frames_encode_as_a_looping_gif_of_their_size_and_delay() {
        let colours = [[255, 0, 0], [0, 255, 0], [0, 0, 255]];
        let frames = colours.iter().map(|&c| Ok(filled(32, 18, c)));
        let gif = encode_gif(frames, delay_cs(24.0, 1)).unwrap();
        assert!(gif.starts_with(b"GIF89a"));
        // NETSCAPE2.0 with a repeat count of 0: loops forever.
        let netscape = gif.windows(11).position(|w| w == b"NETSCAPE2.0");
        let at = netscape.expect("the looping extension");
        assert_eq!(&gif[at + 11..at + 15], &[3, 1, 0, 0]);
        let decoded = decode_gif(&gif).unwrap();
        assert_eq!(decoded.len(), 3);
        for (frame, colour) in decoded.iter().zip(colours) {
            assert_eq!((frame.width, frame.height), (32, 18));
            assert_eq!(
                frame.delay_cs, 4,
                "24 fps is 4 hundredths of a second a frame"
            );
            // A single colour survives quantisation exactly.
            assert_eq!(&frame.rgba[..4], &[colour[0], colour[1], colour[2], 255]);
        }
    }

    #[test]
    fn frames_of_another_size_or_none_are_refused() {
        let frames = [Ok(filled(4, 4, [1, 2, 3])), Ok(filled(5, 4, [1, 2, 3]))];
        assert!(encode_gif(frames, 4).is_err());
        assert!(encode_gif(std::iter::empty::<Result<render::Image>>(), 4).is_err());
        let failing = [Ok(filled(4, 4, [0; 3])), Err(anyhow::anyhow!("damaged"))];
        let error = encode_gif(failing, 4).unwrap_err();
        assert_eq!(error.to_string(), "damaged");
    }

    #[test]
    fn at_most_max_frames_are_shown_every_kth_from_the_first() {
        assert_eq!(frames_shown(1, 3), (vec![1, 2, 3], 1));
        assert_eq!(frames_shown(5, 0), (vec![], 1));
        let (all, step) = frames_shown(1, MAX_FRAMES);
        assert_eq!((all.len() as u32, step), (MAX_FRAMES, 1));
        let (some, step) = frames_shown(10, MAX_FRAMES + 1);
        assert_eq!(step, 2);
        assert_eq!(some.len() as u32, MAX_FRAMES / 2 + 1);
        assert_eq!((some[0], some[1]), (10, 12));
        let (many, step) = frames_shown(1, 10_000);
        assert_eq!(step, 42);
        assert!(many.len() as u32 <= MAX_FRAMES);
        assert_eq!(*many.last().unwrap(), 1 + 42 * (many.len() as u32 - 1));
    }

    #[test]
    fn delays_follow_the_frame_rate_and_the_step() {
        assert_eq!(delay_cs(24.0, 1), 4);
        assert_eq!(delay_cs(10.0, 1), 10);
        assert_eq!(delay_cs(24.0, 3), 13);
        // Faster than browsers play: 2 hundredths.
        assert_eq!(delay_cs(120.0, 1), 2);
        assert_eq!(delay_cs(0.0, 1), 4);
        assert_eq!(delay_cs(f64::NAN, 2), 8);
    }

    #[test]
    fn a_png_decodes_to_its_pixels() {
        let image = filled(7, 3, [9, 8, 7]);
        assert_eq!(decode_png(&image.to_png()).unwrap(), image);
        assert!(decode_png(b"not a png").is_err());
    }

    #[test]
    fn previews_keep_the_aspect_and_sample_the_image() {
        let mut image = render::Image::black(4000, 1000);
        image.rgb[..3].copy_from_slice(&[9, 8, 7]);
        let small = downscale(&image, 1024);
        assert_eq!((small.width, small.height), (1024, 256));
        assert_eq!(small.pixel(0, 0), [9, 8, 7]);
        assert_eq!(small.pixel(1, 0), [0, 0, 0]);
        let tiny = render::Image::black(10, 20);
        assert_eq!(downscale(&tiny, 1024), tiny);
        let tall = downscale(&render::Image::black(480, 1920), SIDE);
        assert_eq!((tall.width, tall.height), (80, 320));
    }
}
