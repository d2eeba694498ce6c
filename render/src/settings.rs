//! What a render may be asked to do besides the scene: image size, antialiasing,
//! reflection depth, and where the samples of a pixel go.
//!
//! Plain values, below the scene model that holds them and the samplers that follow
//! them, so that the scene, the camera and the command line can name a sampling without
//! depending on how it is carried out (that is [`crate::sampling`] and
//! [`crate::adaptive`]).

use std::fmt;

use thiserror::Error;

mod choice;

pub use choice::{Sampler, SamplingChoiceError};

/// Image size, antialiasing, reflection depth and sampling: everything a render may
/// override.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct RenderSettings {
    pub width: u32,
    pub height: u32,
    /// `aa` = n gives n × n samples per pixel: exactly with the grid and jittered
    /// samplers, at most with adaptive sampling.
    pub aa: u32,
    /// Reflection rays are traced only while the depth is below this.
    pub max_depth: u32,
    /// Where the samples of a pixel go. A scene file never sets it: it is the grid
    /// unless the caller asks otherwise.
    pub sampling: Sampling,
}

impl Default for RenderSettings {
    /// The seed's measurement settings (600 × 400, one sample, depth 10, grid).
    fn default() -> Self {
        RenderSettings {
            width: 600,
            height: 400,
            aa: 1,
            max_depth: 10,
            sampling: Sampling::Grid,
        }
    }
}

impl RenderSettings {
    /// Samples per pixel: the grid's and jittered sampling's count, adaptive sampling's
    /// budget.
    pub fn samples_per_pixel(&self) -> u64 {
        u64::from(self.aa) * u64::from(self.aa)
    }

    pub fn pixel_count(&self) -> u64 {
        u64::from(self.width) * u64::from(self.height)
    }
}

/// How the samples of a pixel are placed. The budget is the settings' `aa` = n for all
/// of them: at most n × n samples per pixel.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum Sampling {
    /// n × n samples at ((a + ½)/n, (b + ½)/n): the scene format's reference pattern,
    /// byte for byte.
    #[default]
    Grid,
    /// n × n strata, one sample in each at a deterministic pseudo-random offset: the
    /// grid's cost, without its regular aliasing on edges.
    Jittered,
    /// Samples to an error target for the whole image: blocks of pixels double their
    /// samples where that removes the most error per ray, until the frame's estimated
    /// RMS error is at most the target, at most the largest power of two ≤ n × n per
    /// pixel ([`crate::adaptive`]).
    ///
    /// `target_milli` is the target error in thousandths of an 8-bit level (1000 is one
    /// level), an integer so that settings stay `Eq` and `Hash` and cross the network
    /// exactly. Build it with [`Sampling::adaptive`], which checks the range.
    Adaptive { target_milli: u32 },
}

/// The smallest adaptive target, in thousandths of a level.
pub const MIN_TARGET_MILLI: u32 = 1;
/// The largest adaptive target, in thousandths of a level: 255 levels, the whole range
/// of a channel (any larger target would stop after the first pass anyway).
pub const MAX_TARGET_MILLI: u32 = 255_000;

/// An adaptive target that is not a number of levels Tessera can aim for. Its message
/// says what is wrong; the caller names where the value came from
/// (`--target-error: must be ...`).
#[derive(Debug, Clone, Copy, PartialEq, Error)]
#[error("must be a number of 8-bit levels from 0.001 to 255, got {0}")]
pub struct InvalidTarget(pub f64);

impl Sampling {
    /// Adaptive sampling aiming for an image RMS error of `levels` (8-bit
    /// levels, rounded to the nearest thousandth). Refuses a target that is not finite,
    /// not above 0, or outside 0.001 ..= 255 once rounded.
    pub fn adaptive(levels: f64) -> Result<Sampling, InvalidTarget> {
        if !levels.is_finite() || levels <= 0.0 {
            return Err(InvalidTarget(levels));
        }
        let milli = (levels * 1000.0).round();
        if milli < f64::from(MIN_TARGET_MILLI) || milli > f64::from(MAX_TARGET_MILLI) {
            return Err(InvalidTarget(levels));
        }
        Ok(Sampling::Adaptive {
            target_milli: milli as u32,
        })
    }

    /// The adaptive target in 8-bit levels; `None` for the grid and jittered samplers.
    pub fn target_error(self) -> Option<f64> {
        match self {
            Sampling::Adaptive { target_milli } => Some(f64::from(target_milli) / 1000.0),
            _ => None,
        }
    }

    /// The lowercase name used on the command line and in reports.
    pub fn name(self) -> &'static str {
        match self {
            Sampling::Grid => "grid",
            Sampling::Jittered => "jittered",
            Sampling::Adaptive { .. } => "adaptive",
        }
    }
}

impl fmt::Display for Sampling {
    /// `grid`, `jittered`, or `adaptive (target 0.5 levels)`.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.target_error() {
            Some(t) => write!(f, "{} (target {t} levels)", self.name()),
            None => f.write_str(self.name()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn targets_are_checked_and_kept_in_thousandths() {
        assert_eq!(
            Sampling::adaptive(1.0),
            Ok(Sampling::Adaptive { target_milli: 1000 })
        );
        assert_eq!(Sampling::adaptive(0.25).unwrap().target_error(), Some(0.25));
        for bad in [0.0, -1.0, f64::NAN, f64::INFINITY, 0.0004, 255.1] {
            assert!(Sampling::adaptive(bad).is_err(), "{bad}");
        }
        assert_eq!(
            InvalidTarget(-1.0).to_string(),
            "must be a number of 8-bit levels from 0.001 to 255, got -1"
        );
    }
}
