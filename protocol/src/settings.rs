//! What an image is rendered with: a job's settings, its sampler, its tiles' rectangles
//! and what a client may override of a scene's own settings.

use serde::{Deserialize, Serialize};

/// Image settings of a job, after the client's overrides were applied to the scene's.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct Settings {
    pub width: u32,
    pub height: u32,
    /// The sample budget: at most `aa` × `aa` samples per pixel.
    pub aa: u32,
    pub max_depth: u32,
    /// Where the samples of each pixel go. Part of the settings, so that every worker
    /// renders a job's tiles the same way.
    pub sampling: Sampling,
}

/// How the samples of a pixel are placed (the renderer's `Sampling`, on the wire).
/// Every choice is deterministic: a pixel's value depends only on the scene, the
/// settings and its coordinates, so a job's image is the same in any tiling.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum Sampling {
    /// `aa` × `aa` samples on the centred regular grid: the reference.
    #[default]
    Grid,
    /// `aa` × `aa` strata, one sample at a hashed offset inside each.
    Jittered,
    /// Samples where the image needs them, to an image-wide error target: 8 × 8 blocks
    /// of pixels double their samples (from 4, up to the largest power of two not above
    /// `aa` × `aa`) down a fixed ladder of thresholds until the frame's estimated error
    /// is at most the target. `target_milli` is the target in thousandths of an 8-bit
    /// level (1000 = one level), 1 ..= 255,000. The farm renders such a job in passes
    /// of [`ToWorker::Advance`], not with [`ToWorker::Render`].
    Adaptive { target_milli: u32 },
}

impl Sampling {
    /// The lowercase name used on the command line, in listings and in JSON output.
    pub fn name(self) -> &'static str {
        match self {
            Sampling::Grid => "grid",
            Sampling::Jittered => "jittered",
            Sampling::Adaptive { .. } => "adaptive",
        }
    }

    /// The adaptive target in 8-bit levels; `None` for the other samplers.
    pub fn target_error(self) -> Option<f64> {
        match self {
            Sampling::Adaptive { target_milli } => Some(f64::from(target_milli) / 1000.0),
            _ => None,
        }
    }
}

/// A rectangle of the frame: columns `x .. x + width`, rows `y .. y + height`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct TileRect {
    pub x: u32,
    pub y: u32,
    pub width: u32,
    pub height: u32,
}

/// What a client may change of a scene's own settings, and how the job is cut.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Overrides {
    pub width: Option<u32>,
    pub height: Option<u32>,
    pub aa: Option<u32>,
    pub max_depth: Option<u32>,
    /// Side of the square tiles, in pixels.
    pub tile_size: Option<u32>,
    /// How pixels are sampled; `None` is the regular grid (a scene file never says).
    pub sampling: Option<Sampling>,
}
