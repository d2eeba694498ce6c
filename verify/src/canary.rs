//! The canary: a small fixed scene every worker renders when it joins, before any tile.
//!
//! It exercises every path of the renderer a job can take (spheres, planes, the
//! checkerboard, mirrors, shadows from two lights, recursion, each sampler) in about a
//! millisecond of work. A worker whose bytes differ from the coordinator's own render
//! would change images in ways spot checks catch only by chance, so it is refused with
//! both builds named; builds that render identically work together whatever their
//! versions.

use protocol::{CanaryRender, Sampling, Settings, TileRect};

/// The canary scene's text.
pub const SCENE: &str = include_str!("canary.json");

/// The canary's renders: the whole 40 × 30 frame with each sampler, and one tile off
/// the frame's corner with adaptive sampling (whose border pixels are shared with the
/// neighbouring tiles).
pub fn renders() -> Vec<CanaryRender> {
    let settings = |aa, sampling| Settings {
        width: 40,
        height: 30,
        aa,
        max_depth: 6,
        sampling,
    };
    let frame = TileRect {
        x: 0,
        y: 0,
        width: 40,
        height: 30,
    };
    let adaptive = Sampling::Adaptive { target_milli: 500 };
    vec![
        CanaryRender {
            settings: settings(3, Sampling::Grid),
            rect: frame,
        },
        CanaryRender {
            settings: settings(3, Sampling::Jittered),
            rect: frame,
        },
        CanaryRender {
            settings: settings(4, adaptive),
            rect: frame,
        },
        CanaryRender {
            settings: settings(4, adaptive),
            rect: TileRect {
                x: 13,
                y: 7,
                width: 11,
                height: 9,
            },
        },
    ]
}

/// Renders the canary as a worker is asked to: one RGB8 buffer per render.
pub fn render(scene: &str, renders: &[CanaryRender]) -> Result<Vec<Vec<u8>>, String> {
    let scene = render::parse_scene(scene).map_err(|e| format!("the canary scene: {e}"))?;
    renders
        .iter()
        .map(|r| {
            let tracer = crate::tracer(&scene, &r.settings)?;
            render::render_tile(&tracer, crate::render_rect(r.rect))
                .map(|tile| tile.rgb)
                .map_err(|e| e.to_string())
        })
        .collect()
}

/// Where a worker's canary differs from the coordinator's.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum Mismatch {
    #[error("it answered {got} renders instead of {expected}")]
    Count { expected: usize, got: usize },
    #[error("render {index} ({sampler} sampling) has {got} bytes instead of {expected}")]
    Length {
        index: usize,
        sampler: &'static str,
        expected: usize,
        got: usize,
    },
    #[error(
        "render {index} ({sampler} sampling) differs at pixel ({x}, {y}): {got:?} instead of {expected:?}"
    )]
    Pixel {
        index: usize,
        sampler: &'static str,
        x: u32,
        y: u32,
        expected: [u8; 3],
        got: [u8; 3],
    },
}

/// Compares a worker's canary with the coordinator's, naming the first difference.
pub fn compare(
    renders: &[CanaryRender],
    expected: &[Vec<u8>],
    got: &[Vec<u8>],
) -> Result<(), Mismatch> {
    if expected.len() != got.len() {
        return Err(Mismatch::Count {
            expected: expected.len(),
            got: got.len(),
        });
    }
    for (index, ((render, ours), theirs)) in renders.iter().zip(expected).zip(got).enumerate() {
        let sampler = render.settings.sampling.name();
        if ours.len() != theirs.len() {
            return Err(Mismatch::Length {
                index,
                sampler,
                expected: ours.len(),
                got: theirs.len(),
            });
        }
        if let Some((x, y)) = crate::spot::differing_pixels(render.rect, ours, theirs)
            .into_iter()
            .next()
        {
            return Err(Mismatch::Pixel {
                index,
                sampler,
                x,
                y,
                expected: crate::spot::pixel_at(render.rect, ours, x, y),
                got: crate::spot::pixel_at(render.rect, theirs, x, y),
            });
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_canary_renders_and_matches_itself() {
        let renders = renders();
        let ours = render(SCENE, &renders).expect("the canary renders");
        assert_eq!(ours.len(), renders.len());
        assert_eq!(compare(&renders, &ours, &ours), Ok(()));
        // Not a blank image: the scene shows something in every render.
        for image in &ours {
            assert!(image.iter().any(|&b| b > 40) && image.iter().any(|&b| b < 200));
        }
    }

    #[test]
    fn one_changed_byte_is_named() {
        let renders = renders();
        let ours = render(SCENE, &renders).unwrap();
        let mut theirs = ours.clone();
        theirs[2][3 * 41 + 1] ^= 1;
        let err = compare(&renders, &ours, &theirs).unwrap_err();
        assert!(matches!(
            err,
            Mismatch::Pixel {
                index: 2,
                sampler: "adaptive",
                x: 1,
                y: 1,
                ..
            }
        ));
        theirs.pop();
        assert!(matches!(
            compare(&renders, &ours, &theirs),
            Err(Mismatch::Count { .. })
        ));
    }

    #[test]
    fn the_tile_equals_the_same_pixels_of_the_frame() {
        let renders = renders();
        let ours = render(SCENE, &renders).unwrap();
        let (frame, tile) = (&ours[2], &ours[3]);
        let r = renders[3].rect;
        for y in r.y..r.y + r.height {
            for x in r.x..r.x + r.width {
                assert_eq!(
                    crate::spot::pixel_at(r, tile, x, y),
                    crate::spot::pixel_at(renders[2].rect, frame, x, y)
                );
            }
        }
    }
}
