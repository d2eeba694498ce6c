//! The animated preview of a sequence job (`GET /api/jobs/ID/preview.gif`): its frames
//! done one after another from the first, each downscaled, as one looping GIF.
//!
//! The work is bounded: at most [`MAX_FRAMES`] frames (with more done, every k-th, each
//! shown k times as long, so the preview still plays at the scene's speed), each at
//! most [`SIDE`] pixels on its longer side; the frames are decoded, downscaled and
//! encoded one at a time, so only one full-size frame is in memory at once.
//!
//! The png and gif crates directly, with the settings the `image` crate gave them (the
//! bytes are the same, the tests compare them): `image` would bring colour management
//! the farm never uses into every build.

use std::borrow::Borrow;

use anyhow::{Context, Result};

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

/// The most bytes a decoded PNG may take before its conversion to RGB: 512 MiB, the
/// `image` crate's default allocation limit, which this decoder keeps.
const MAX_DECODED_BYTES: usize = 512 * 1024 * 1024;

/// Decodes a stored frame's PNG. Any PNG decodes, to 8-bit RGB as the `image` crate's
/// `load_from_memory(..).into_rgb8()` made it: palettes and depths below 8 expanded, 16
/// bits rounded to 8, grey copied to red, green and blue, alpha dropped.
pub fn decode_png(png: &[u8]) -> Result<render::Image> {
    decode_png_rgb8(png).context("not a PNG image")
}

fn decode_png_rgb8(png: &[u8]) -> Result<render::Image> {
    let mut decoder = png::Decoder::new_with_limits(
        std::io::Cursor::new(png),
        png::Limits {
            bytes: MAX_DECODED_BYTES,
        },
    );
    // Palettes and depths below 8 expand to 8 bits; 16 bits stay, to be rounded below
    // (the png crate's STRIP_16 would truncate them).
    decoder.set_transformations(png::Transformations::EXPAND);
    let mut reader = decoder.read_info()?;
    let (width, height) = reader.info().size();
    let size = reader
        .output_buffer_size()
        .filter(|&size| size <= MAX_DECODED_BYTES)
        .with_context(|| format!("a {width}×{height} image would take more than 512 MiB"))?;
    let mut pixels = vec![0; size];
    reader.next_frame(&mut pixels)?;
    let rgb = match reader.output_color_type() {
        (png::ColorType::Rgb, png::BitDepth::Eight) => pixels,
        (colour, png::BitDepth::Eight) => to_rgb(&pixels, colour, 1, |sample| sample[0])?,
        (colour, png::BitDepth::Sixteen) => to_rgb(&pixels, colour, 2, |sample| {
            // `image`'s rounding of 16 bits to 8: round(v × 255 / 65535).
            ((u32::from(u16::from_be_bytes([sample[0], sample[1]])) + 128) / 257) as u8
        })?,
        (colour, depth) => anyhow::bail!("{colour:?} samples of {depth:?} bits after expansion"),
    };
    Ok(render::Image { width, height, rgb })
}

/// The 8-bit RGB of `pixels`, of `colour` with samples `sample_bytes` wide that `eight`
/// turns into 8 bits.
fn to_rgb(
    pixels: &[u8],
    colour: png::ColorType,
    sample_bytes: usize,
    eight: impl Fn(&[u8]) -> u8,
) -> Result<Vec<u8>> {
    let channels = match colour {
        png::ColorType::Grayscale => 1,
        png::ColorType::GrayscaleAlpha => 2,
        png::ColorType::Rgb => 3,
        png::ColorType::Rgba => 4,
        png::ColorType::Indexed => anyhow::bail!("a palette left after expansion"),
    };
    let pixel_bytes = channels * sample_bytes;
    let mut rgb = Vec::with_capacity(pixels.len() / pixel_bytes * 3);
    for pixel in pixels.chunks_exact(pixel_bytes) {
        let sample = |channel: usize| eight(&pixel[channel * sample_bytes..]);
        if channels < 3 {
            let grey = sample(0);
            rgb.extend([grey; 3]);
        } else {
            rgb.extend([sample(0), sample(1), sample(2)]);
        }
    }
    Ok(rgb)
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
///
/// The bytes are those the `image` crate's `GifEncoder` wrote at this speed: no global
/// palette, the looping extension before the first frame, each frame quantised from
/// opaque RGBA by `gif::Frame::from_rgba_speed` and disposed to the background.
pub fn encode_gif<I: Borrow<render::Image>>(
    frames: impl IntoIterator<Item = Result<I>>,
    delay_cs: u16,
) -> Result<Vec<u8>> {
    let mut encoder: Option<gif::Encoder<Vec<u8>>> = None;
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
        let (Ok(width), Ok(height)) = (u16::try_from(frame.width), u16::try_from(frame.height))
        else {
            anyhow::bail!(
                "a frame of {}×{} is larger than a GIF holds",
                frame.width,
                frame.height
            );
        };
        anyhow::ensure!(
            frame.rgb.len() == usize::from(width) * usize::from(height) * 3,
            "a frame's pixels do not fill its size"
        );
        let mut rgba: Vec<u8> = frame
            .rgb
            .chunks_exact(3)
            .flat_map(|p| [p[0], p[1], p[2], 255])
            .collect();
        let mut gif_frame =
            gif::Frame::from_rgba_speed(width, height, &mut rgba, QUANTISATION_SPEED);
        gif_frame.delay = delay_cs;
        gif_frame.dispose = gif::DisposalMethod::Background;
        let encoder = match &mut encoder {
            Some(encoder) => encoder,
            None => {
                let mut new = gif::Encoder::new(Vec::new(), width, height, &[])?;
                new.set_repeat(gif::Repeat::Infinite)?;
                encoder.insert(new)
            }
        };
        encoder.write_frame(&gif_frame)?;
    }
    let encoder = encoder.context("no frame to encode")?;
    // Writes the GIF's trailer.
    Ok(encoder.into_inner()?)
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

/// The frames of a GIF, for the tests: each as the `gif` crate decodes it, in RGBA,
/// which is the whole picture for the GIFs [`encode_gif`] writes (every frame covers
/// the screen from its corner; another GIF is refused).
#[cfg(test)]
pub fn decode_gif(gif: &[u8]) -> Result<Vec<DecodedFrame>> {
    let mut options = gif::DecodeOptions::new();
    options.set_color_output(gif::ColorOutput::RGBA);
    let mut decoder = options.read_info(gif)?;
    let screen = (decoder.width(), decoder.height());
    let mut frames = Vec::new();
    while let Some(frame) = decoder.read_next_frame()? {
        anyhow::ensure!(
            (frame.left, frame.top, frame.width, frame.height) == (0, 0, screen.0, screen.1),
            "a frame that does not cover the screen"
        );
        frames.push(DecodedFrame {
            width: u32::from(frame.width),
            height: u32::from(frame.height),
            delay_cs: u32::from(frame.delay),
            rgba: frame.buffer.to_vec(),
        });
    }
    Ok(frames)
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

    /// The SHA-256 of `bytes`, in hexadecimal.
    fn sha256_hex(bytes: &[u8]) -> String {
        use sha2::Digest;
        sha2::Sha256::digest(bytes)
            .iter()
            .map(|b| format!("{b:02x}"))
            .collect()
    }

    /// A pseudo-random byte stream (xorshift), the same on every run.
    fn noise(seed: u32) -> impl FnMut() -> u8 {
        let mut state = seed | 1;
        move || {
            state ^= state << 13;
            state ^= state >> 17;
            state ^= state << 5;
            (state >> 11) as u8
        }
    }

    fn from_fn(width: u32, height: u32, f: impl Fn(u32, u32) -> [u8; 3]) -> render::Image {
        let mut image = render::Image::black(width, height);
        for y in 0..height {
            for x in 0..width {
                let i = (y as usize * width as usize + x as usize) * 3;
                image.rgb[i..i + 3].copy_from_slice(&f(x, y));
            }
        }
        image
    }

    /// Frames of the seed scene orbited, as a sequence's preview shows them.
    fn rendered(frames: usize, width: u32, height: u32) -> Vec<render::Image> {
        let scene =
            render::parse_scene(include_str!("../../scenes/seed.json")).expect("the seed scene");
        let settings = render::RenderSettings {
            width,
            height,
            ..Default::default()
        };
        (0..frames)
            .map(|i| {
                let mut scene = scene.clone();
                scene.camera.position.x += i as f64 * 0.3;
                let tracer = render::Tracer::new(&scene, settings);
                render::render_frame(&tracer, 16, &|_| {}).image
            })
            .collect()
    }

    #[test]
    fn gif_bytes_are_those_of_the_image_crate() {
        let mut byte = noise(7);
        let mut noisy = render::Image::black(41, 29);
        noisy.rgb.iter_mut().for_each(|b| *b = byte());
        let gradient = |shift: u32| {
            from_fn(37, 23, move |x, y| {
                [(x * 7 + shift) as u8, (y * 11) as u8, (x * y + shift) as u8]
            })
        };
        // Each with the SHA-256 of what `image` 0.25's GIF encoder wrote for it, as the
        // preview used it (quantisation speed 10, repeating forever, the delay given).
        let cases: Vec<(Vec<render::Image>, u16, &str)> = vec![
            (
                vec![filled(1, 1, [200, 100, 50])],
                4,
                "d1927ae66da8040bbbb26c2da43ba8c23a440b5e1b9a4312c79784e9f5cbb8ab",
            ),
            (
                [[255, 0, 0], [0, 255, 0], [0, 0, 255]]
                    .iter()
                    .map(|&c| filled(32, 18, c))
                    .collect(),
                delay_cs(24.0, 1),
                "14fd81a4391622016dcb03245b5767966c571b1cf3ef3f994cb6afba556abddc",
            ),
            // Under 256 colours: an exact palette; over: NeuQuant.
            (
                vec![from_fn(16, 15, |x, y| [x as u8 * 16, y as u8 * 17, 9])],
                2,
                "160a4347373133abd6ba4374b2ad37c868a16cb9be51d3ba86a9effbe351c59f",
            ),
            (
                vec![gradient(0), gradient(40), gradient(80)],
                13,
                "d964416a6e8a1783b24c2b600e805a070dba25243fc9d2f7cbdabb809178788e",
            ),
            (
                vec![noisy.clone(), noisy],
                u16::MAX,
                "17f0d9dbc978c9fe533be1939babbeac818b25b476da119b3b82d23c2f978a61",
            ),
            (
                rendered(3, 80, 53),
                delay_cs(30.0, 2),
                "623bf255d063155cbbd85de67781a17e00a4331367763eea867d06128468b2ae",
            ),
            (
                vec![downscale(&rendered(1, 331, 97)[0], 64)],
                10,
                "e8d8135b4dc195f26102e998c782a28043a69386ec288d5bf9c239f53d46c66b",
            ),
        ];
        for (frames, delay, digest) in &cases {
            let gif = encode_gif(frames.iter().map(Ok), *delay).unwrap();
            let (width, height) = (frames[0].width, frames[0].height);
            assert_eq!(
                sha256_hex(&gif),
                *digest,
                "{} frames of {width}×{height}",
                frames.len()
            );
            let decoded = decode_gif(&gif).unwrap();
            assert_eq!(decoded.len(), frames.len());
            assert!(decoded.iter().all(|f| f.delay_cs == u32::from(*delay)));
            assert!(decoded
                .iter()
                .all(|f| (f.width, f.height) == (width, height)));
        }
    }

    /// A PNG of the png crate's `colour` and `depth` with `pixels` as they are stored.
    fn png_of(
        (width, height): (u32, u32),
        colour: png::ColorType,
        depth: png::BitDepth,
        chunks: &dyn Fn(&mut png::Encoder<&mut Vec<u8>>),
        pixels: &[u8],
    ) -> Vec<u8> {
        let mut out = Vec::new();
        let mut encoder = png::Encoder::new(&mut out, width, height);
        encoder.set_color(colour);
        encoder.set_depth(depth);
        chunks(&mut encoder);
        let mut writer = encoder.write_header().unwrap();
        writer.write_image_data(pixels).unwrap();
        writer.finish().unwrap();
        out
    }

    #[test]
    fn pngs_of_every_colour_type_and_depth_decode_as_the_image_crate_decoded() {
        use png::{BitDepth as D, ColorType as C};
        let mut byte = noise(11);
        let mut random = |len: usize| (0..len).map(|_| byte()).collect::<Vec<u8>>();
        let none: &dyn Fn(&mut png::Encoder<&mut Vec<u8>>) = &|_| {};
        let mut pngs = Vec::new();
        // Every colour type at every depth it allows, at an odd size (rows of a partial
        // byte at depths below 8).
        let (w, h) = (13, 7);
        for (colour, depths, channels) in [
            (
                C::Grayscale,
                &[D::One, D::Two, D::Four, D::Eight, D::Sixteen][..],
                1,
            ),
            (C::GrayscaleAlpha, &[D::Eight, D::Sixteen][..], 2),
            (C::Rgb, &[D::Eight, D::Sixteen][..], 3),
            (C::Rgba, &[D::Eight, D::Sixteen][..], 4),
        ] {
            for &depth in depths {
                let row = (w as usize * channels * depth as usize).div_ceil(8);
                pngs.push(png_of(
                    (w, h),
                    colour,
                    depth,
                    none,
                    &random(row * h as usize),
                ));
            }
        }
        // Palettes, with and without transparency, and transparent colours.
        for depth in [D::One, D::Two, D::Four, D::Eight] {
            let row = (w as usize * depth as usize).div_ceil(8);
            let entries = 1usize << (depth as usize).min(8);
            let palette = random(entries * 3);
            let pixels = random(row * h as usize);
            let trns = random(entries / 2);
            let plain = |e: &mut png::Encoder<&mut Vec<u8>>| e.set_palette(palette.clone());
            pngs.push(png_of((w, h), C::Indexed, depth, &plain, &pixels));
            let transparent = |e: &mut png::Encoder<&mut Vec<u8>>| {
                e.set_palette(palette.clone());
                e.set_trns(trns.clone());
            };
            pngs.push(png_of((w, h), C::Indexed, depth, &transparent, &pixels));
        }
        let grey_key = |e: &mut png::Encoder<&mut Vec<u8>>| e.set_trns(vec![0, 7]);
        let grey = random(w as usize * h as usize);
        pngs.push(png_of((w, h), C::Grayscale, D::Eight, &grey_key, &grey));
        let rgb_key = |e: &mut png::Encoder<&mut Vec<u8>>| e.set_trns(vec![0, 1, 0, 2, 0, 3]);
        let rgb = random(w as usize * h as usize * 3);
        pngs.push(png_of((w, h), C::Rgb, D::Eight, &rgb_key, &rgb));
        // Colour space chunks, which neither applies.
        let srgb = |e: &mut png::Encoder<&mut Vec<u8>>| {
            e.set_source_srgb(png::SrgbRenderingIntent::Perceptual);
            e.set_source_gamma(png::ScaledFloat::new(1.0 / 2.2));
        };
        pngs.push(png_of((w, h), C::Rgb, D::Eight, &srgb, &rgb));
        // Every grey value, at 8 and 16 bits: the rounding to 8 bits.
        let all8: Vec<u8> = (0..=255).collect();
        pngs.push(png_of((16, 16), C::Grayscale, D::Eight, none, &all8));
        let all16: Vec<u8> = (0..=u16::MAX).flat_map(u16::to_be_bytes).collect();
        pngs.push(png_of((256, 256), C::Grayscale, D::Sixteen, none, &all16));
        pngs.push(png_of(
            (85, 257),
            C::Rgb,
            D::Sixteen,
            none,
            &all16[..85 * 257 * 6],
        ));
        // An animated PNG: its first frame.
        let mut apng = Vec::new();
        {
            let mut encoder = png::Encoder::new(&mut apng, 5, 4);
            encoder.set_color(C::Rgb);
            encoder.set_animated(2, 0).unwrap();
            let mut writer = encoder.write_header().unwrap();
            writer.write_image_data(&random(60)).unwrap();
            writer.write_image_data(&random(60)).unwrap();
            writer.finish().unwrap();
        }
        pngs.push(apng);
        // What the farm stores.
        pngs.push(rendered(1, 61, 37)[0].to_png());
        pngs.push(filled(1, 1, [1, 2, 3]).to_png());

        // What `image` 0.25's `load_from_memory(..).into_rgb8()` gave for each: its size
        // and the SHA-256 of its pixels.
        let theirs = [
            (
                13,
                7,
                "b0a71fd83e4fdc89f09bee3b0e4df099cd6c61faa37ced11c4a5e396a8d9f94f",
            ),
            (
                13,
                7,
                "bb53347331ee8b294924e218f5f9881abc976c7e7c9ff2ff51f1028070303344",
            ),
            (
                13,
                7,
                "fbceb8d21c1d7646c9daf63bf107ab009844014aed3b15b6c5f3107acc1eeac1",
            ),
            (
                13,
                7,
                "d1fe2af6f4f93df2c95cba21170d3ed066d6087299dc16d0e34b58aede905cfa",
            ),
            (
                13,
                7,
                "5df66b0f19ba0d0d8a706488fd66198d407f0c54e7abd1c27b2ca11958962ad6",
            ),
            (
                13,
                7,
                "a9415fba98f309a3c64127c81d78c05af9930ac2d19b98511b952f5d9e45c982",
            ),
            (
                13,
                7,
                "f73a65c077c0b2d97974dc01ba94d09bc08954a248cf022810c82c67198820f0",
            ),
            (
                13,
                7,
                "af849fae12d4992b3e74dec1423d84bf411c20ae00eae67f46d7388e0253a844",
            ),
            (
                13,
                7,
                "d8958dfa1a75f85c6554e776741a8740224db5ab098c1a1569633040d1370115",
            ),
            (
                13,
                7,
                "9faccba4d91c22190920e84132b5163da2775cbd10baef75bda1bc5a9e83dc08",
            ),
            (
                13,
                7,
                "ec6f290a86161412428ff92c18bad2949502bc04f9184b9ff25316da85a89612",
            ),
            (
                13,
                7,
                "796fa94f92156cb5e56319dfe68e7b7534a9354dd3687df694c2569273804a7e",
            ),
            (
                13,
                7,
                "796fa94f92156cb5e56319dfe68e7b7534a9354dd3687df694c2569273804a7e",
            ),
            (
                13,
                7,
                "b6ac9b35e61acfa17eada2caffdcbc9f2cf578591a3dc99f763d9c81d798b83b",
            ),
            (
                13,
                7,
                "b6ac9b35e61acfa17eada2caffdcbc9f2cf578591a3dc99f763d9c81d798b83b",
            ),
            (
                13,
                7,
                "32163da38f1330cb2793f245151795aaa68a4013e4a5ef9e0b722e6eda39ac5a",
            ),
            (
                13,
                7,
                "32163da38f1330cb2793f245151795aaa68a4013e4a5ef9e0b722e6eda39ac5a",
            ),
            (
                13,
                7,
                "77e3229ce4af45b3295665c472c2ffca41be24c3b81d338818602ef897c9ea79",
            ),
            (
                13,
                7,
                "77e3229ce4af45b3295665c472c2ffca41be24c3b81d338818602ef897c9ea79",
            ),
            (
                13,
                7,
                "684b4f082af779547b2d37de562bb392b6164aca2112fdfceabf37f6cf809ad1",
            ),
            (
                13,
                7,
                "674b4e083e6ea595940136abbc6c9e5113473383d77341d569c6f794bb95aa52",
            ),
            (
                13,
                7,
                "674b4e083e6ea595940136abbc6c9e5113473383d77341d569c6f794bb95aa52",
            ),
            (
                16,
                16,
                "72432263dbfe17abc40ed269f24c7a344e077e3671007dfc8a2f3851f8193dc2",
            ),
            (
                256,
                256,
                "ff972ca078809fc54fb6af18b581bc19a7744814ad32ab29fefad1c55c4637d6",
            ),
            (
                85,
                257,
                "f638907d21c3d151dd508cd2a2b5becf0826e26522d12a3b301360df239a47a2",
            ),
            (
                5,
                4,
                "be94067945359c166b3e72b2097e8bbd8e4e6d164f0af69ece66bec5c148387f",
            ),
            (
                61,
                37,
                "dcd0ed4ef28a35762c00779e4ecfeb58a87a9706be753a5c4504f9b857f38924",
            ),
            (
                1,
                1,
                "039058c6f2c0cb492c533b0a4d14ef77cc0f78abccced5287d84a1a2011cfb81",
            ),
        ];
        assert_eq!(pngs.len(), theirs.len());
        for (i, (png, (width, height, digest))) in pngs.iter().zip(theirs).enumerate() {
            let ours = decode_png(png).unwrap_or_else(|e| panic!("PNG {i}: {e:#}"));
            assert_eq!((ours.width, ours.height), (width, height), "PNG {i}");
            assert_eq!(sha256_hex(&ours.rgb), digest, "PNG {i}: other pixels");
        }
    }

    #[test]
    fn what_is_not_a_png_is_refused_as_before() {
        let good = filled(9, 4, [1, 2, 3]).to_png();
        let mut bad_crc = good.clone();
        bad_crc[20] ^= 1; // in IHDR
        let mut bad_data = good.clone();
        let idat = good.windows(4).position(|w| w == b"IDAT").unwrap();
        bad_data[idat + 6] ^= 0x55;
        // Each refused by `image` 0.25's decoder too, which this one replaced.
        let cases: [&[u8]; 6] = [
            b"",
            b"not a png",
            b"GIF89a",
            &good[..8],
            &good[..good.len() / 2],
            &bad_crc,
        ];
        for (i, bytes) in cases.iter().enumerate() {
            let error = decode_png(bytes).expect_err(&format!("case {i}"));
            assert_eq!(error.to_string(), "not a PNG image", "case {i}");
        }
        // A damaged image stream: refused, as `image` 0.25 refused it.
        assert!(decode_png(&bad_data).is_err());
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
