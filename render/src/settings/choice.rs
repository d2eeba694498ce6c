//! Which sampling a user's choices add up to: a sampler's name, an error target and a
//! time limit, as `tessera render`, `submit` and `up` take them. Checked before
//! anything is rendered or sent, so that a combination that means nothing is one line
//! saying so rather than a render that ignores part of what was asked.

use thiserror::Error;

use super::{InvalidTarget, Sampling, MIN_TARGET_MILLI};

/// A sampler by its name alone; [`Sampling::choose`] adds the target it needs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Sampler {
    Grid,
    Jittered,
    Adaptive,
}

/// A combination of sampler, error target and time limit that asks for nothing
/// Tessera can render. The messages name the command line's flags, which is where the
/// choices are made.
#[derive(Debug, Clone, Copy, PartialEq, Error)]
pub enum SamplingChoiceError {
    /// The target is out of range.
    #[error("--target-error: {0}")]
    Target(InvalidTarget),
    /// Adaptive sampling without a target has no reason to stop.
    #[error(
        "--sampler adaptive needs --target-error LEVELS (the error each pixel should reach, \
         in 8-bit levels, for example 1)"
    )]
    NoTarget,
    /// Only adaptive sampling aims for an error: a target with another sampler named.
    #[error("--target-error applies only to --sampler adaptive")]
    TargetWithoutAdaptive,
    /// Only adaptive sampling can stop early.
    #[error("--time-limit applies only to --sampler adaptive")]
    TimeLimitWithoutAdaptive,
}

impl Sampling {
    /// The sampling that `sampler`, `target_error` (in 8-bit levels) and a time limit
    /// (`time_limited`) ask for; `None` when nothing is asked, which is the grid (a
    /// scene file never chooses a sampler).
    ///
    /// Adaptive sampling needs a target, and only it takes one. A target alone asks
    /// for adaptive sampling, as a time limit does (the two flags that only adaptive
    /// sampling takes each imply it). A time limit asks for adaptive sampling: alone,
    /// or with `--sampler adaptive` and no target, to the smallest target there is, so
    /// that the time decides; with a target and no sampler named, to that target or
    /// the limit, whichever comes first. A target or a time limit with a sampler named
    /// in any other way is refused.
    pub fn choose(
        sampler: Option<Sampler>,
        target_error: Option<f64>,
        time_limited: bool,
    ) -> Result<Option<Sampling>, SamplingChoiceError> {
        if time_limited {
            return match (sampler, target_error) {
                (None | Some(Sampler::Adaptive), None) => Ok(Some(Sampling::Adaptive {
                    target_milli: MIN_TARGET_MILLI,
                })),
                (None, Some(_)) => Sampling::choose(Some(Sampler::Adaptive), target_error, false),
                (Some(_), _) => Err(SamplingChoiceError::TimeLimitWithoutAdaptive),
            };
        }
        match (sampler, target_error) {
            (None | Some(Sampler::Adaptive), Some(levels)) => Sampling::adaptive(levels)
                .map(Some)
                .map_err(SamplingChoiceError::Target),
            (Some(Sampler::Adaptive), None) => Err(SamplingChoiceError::NoTarget),
            (_, Some(_)) => Err(SamplingChoiceError::TargetWithoutAdaptive),
            (Some(Sampler::Grid), None) => Ok(Some(Sampling::Grid)),
            (Some(Sampler::Jittered), None) => Ok(Some(Sampling::Jittered)),
            (None, None) => Ok(None),
        }
    }

    /// Whether this is what a time limit alone asks for ([`Sampling::choose`]):
    /// adaptive sampling to the smallest target there is, so that the time, not a
    /// target, decides where it stops. Reports say so rather than show the target.
    pub fn time_decides(self) -> bool {
        self == Sampling::Adaptive {
            target_milli: MIN_TARGET_MILLI,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use Sampler::{Adaptive, Grid, Jittered};

    fn adaptive(target_milli: u32) -> Option<Sampling> {
        Some(Sampling::Adaptive { target_milli })
    }

    #[test]
    fn a_sampler_alone_is_itself_and_adaptive_needs_a_target() {
        assert_eq!(Sampling::choose(None, None, false), Ok(None));
        assert_eq!(
            Sampling::choose(Some(Grid), None, false),
            Ok(Some(Sampling::Grid))
        );
        assert_eq!(
            Sampling::choose(Some(Jittered), None, false),
            Ok(Some(Sampling::Jittered))
        );
        assert_eq!(
            Sampling::choose(Some(Adaptive), Some(0.5), false),
            Ok(adaptive(500))
        );
        assert_eq!(
            Sampling::choose(Some(Adaptive), None, false),
            Err(SamplingChoiceError::NoTarget)
        );
    }

    #[test]
    fn a_target_is_for_adaptive_sampling_only_and_in_range() {
        // A target alone implies adaptive sampling.
        assert_eq!(Sampling::choose(None, Some(1.0), false), Ok(adaptive(1000)));
        for sampler in [Some(Grid), Some(Jittered)] {
            assert_eq!(
                Sampling::choose(sampler, Some(1.0), false),
                Err(SamplingChoiceError::TargetWithoutAdaptive)
            );
        }
        assert_eq!(
            Sampling::choose(Some(Adaptive), Some(0.0), false)
                .unwrap_err()
                .to_string(),
            "--target-error: must be a number of 8-bit levels from 0.001 to 255, got 0"
        );
    }

    #[test]
    fn a_time_limit_asks_for_adaptive_sampling() {
        assert_eq!(
            Sampling::choose(None, None, true),
            Ok(adaptive(MIN_TARGET_MILLI))
        );
        assert_eq!(
            Sampling::choose(Some(Adaptive), None, true),
            Ok(adaptive(MIN_TARGET_MILLI))
        );
        assert_eq!(Sampling::choose(None, Some(2.0), true), Ok(adaptive(2000)));
        assert_eq!(
            Sampling::choose(None, Some(-1.0), true),
            Err(SamplingChoiceError::Target(InvalidTarget(-1.0)))
        );
        let alone = Sampling::choose(None, None, true).unwrap().unwrap();
        assert!(alone.time_decides());
        assert!(!Sampling::adaptive(2.0).unwrap().time_decides());
        assert!(!Sampling::Grid.time_decides());
        for sampler in [Grid, Jittered] {
            assert_eq!(
                Sampling::choose(Some(sampler), None, true)
                    .unwrap_err()
                    .to_string(),
                "--time-limit applies only to --sampler adaptive"
            );
        }
    }
}
