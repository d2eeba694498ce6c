//! The programs' images read back and compared pixel by pixel: a PNG or a binary PPM
//! decoded to RGB8, and how two images differ, as numbers for the CSV and in words for
//! the tables. Every case's images are compared here, sphere and mesh alike.

use std::path::Path;

use anyhow::{anyhow, bail, Context, Result};

use crate::scenes::thousands;

/// A decoded RGB8 image.
pub(super) struct Rgb {
    pub(super) width: u32,
    pub(super) height: u32,
    pub(super) bytes: Vec<u8>,
}

/// Reads a PNG, or a binary PPM (P6, maxval 255).
pub(super) fn decode(path: &Path) -> Result<Rgb> {
    let data = std::fs::read(path).with_context(|| format!("cannot read {}", path.display()))?;
    if data.starts_with(b"P6") {
        return decode_ppm(&data).with_context(|| format!("{}: not a P6 PPM", path.display()));
    }
    let image = coordinator::decode_png(&data)
        .with_context(|| format!("cannot decode {}", path.display()))?;
    Ok(Rgb {
        width: image.width,
        height: image.height,
        bytes: image.rgb,
    })
}

pub(super) fn decode_ppm(data: &[u8]) -> Result<Rgb> {
    // Four white-space separated fields (P6, width, height, maxval), then one white
    // space byte, then the pixels.
    let mut fields = Vec::new();
    let mut at = 0;
    while fields.len() < 4 {
        while data.get(at).is_some_and(u8::is_ascii_whitespace) {
            at += 1;
        }
        let start = at;
        while data.get(at).is_some_and(|b| !b.is_ascii_whitespace()) {
            at += 1;
        }
        if start == at {
            bail!("truncated header");
        }
        fields.push(std::str::from_utf8(&data[start..at])?.to_owned());
    }
    let (width, height): (u32, u32) = (fields[1].parse()?, fields[2].parse()?);
    if fields[3] != "255" {
        bail!("maxval {} (expected 255)", fields[3]);
    }
    let bytes = data
        .get(at + 1..at + 1 + width as usize * height as usize * 3)
        .ok_or_else(|| anyhow!("truncated pixels"))?
        .to_vec();
    Ok(Rgb {
        width,
        height,
        bytes,
    })
}

/// How two images differ: kept as numbers, for the CSV, and said in words by
/// `Display` for the tables.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum ImageDiff {
    Sizes {
        a: (u32, u32),
        b: (u32, u32),
    },
    /// Pixels with any channel different, and the largest difference of a channel
    /// (levels of 255).
    Pixels {
        differing: u64,
        max_level: u8,
    },
}

impl ImageDiff {
    /// The differing pixels and the largest channel difference, `None` for images of
    /// different sizes.
    pub(super) fn counts(self) -> Option<(u64, u8)> {
        match self {
            ImageDiff::Sizes { .. } => None,
            ImageDiff::Pixels {
                differing,
                max_level,
            } => Some((differing, max_level)),
        }
    }
}

impl std::fmt::Display for ImageDiff {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match *self {
            ImageDiff::Sizes { a, b } => {
                write!(f, "sizes differ ({}×{} and {}×{})", a.0, a.1, b.0, b.1)
            }
            ImageDiff::Pixels { differing: 0, .. } => f.write_str("identical"),
            ImageDiff::Pixels {
                differing,
                max_level,
            } => write!(
                f,
                "{} {} (up to {max_level} levels)",
                thousands(differing),
                if differing == 1 {
                    "pixel differs"
                } else {
                    "pixels differ"
                }
            ),
        }
    }
}

/// How many pixels differ and by how much.
pub(super) fn difference(a: &Rgb, b: &Rgb) -> ImageDiff {
    if (a.width, a.height) != (b.width, b.height) {
        return ImageDiff::Sizes {
            a: (a.width, a.height),
            b: (b.width, b.height),
        };
    }
    let mut differing = 0u64;
    let mut max_level = 0u8;
    for (p, q) in a.bytes.chunks_exact(3).zip(b.bytes.chunks_exact(3)) {
        if p != q {
            differing += 1;
            for (x, y) in p.iter().zip(q) {
                max_level = max_level.max(x.abs_diff(*y));
            }
        }
    }
    ImageDiff::Pixels {
        differing,
        max_level,
    }
}

/// `identical`, or how many pixels differ and by how much.
pub(super) fn compare(a: &Rgb, b: &Rgb) -> String {
    difference(a, b).to_string()
}
