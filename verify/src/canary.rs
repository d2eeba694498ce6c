//! The canary: a small fixed scene every worker renders when it joins, before any tile.
//!
//! It exercises every path of the renderer a job can take (spheres, planes, the
//! checkerboard, mirrors, shadows from two lights, recursion, each sampler, and the
//! shapes of section 8: a mesh read from a file, instanced twice with flat and smooth
//! shading under transforms whose sines and cosines every machine must compute alike, a
//! box and a triangle) in a few milliseconds of work. A worker whose bytes differ from the coordinator's own render
//! would change images in ways spot checks catch only by chance, so it is refused with
//! both builds named; builds that render identically work together whatever their
//! versions.

use std::collections::BTreeMap;
use std::sync::Arc;

use protocol::{CanaryFile, CanaryRender, Sampling, Settings, TileRect};

/// The canary scene's text.
pub const SCENE: &str = include_str!("canary.json");

/// The mesh file the canary scene names: an icosahedron subdivided once (80 faces).
/// It travels inside the canary message, not by hash: a worker renders the canary
/// before it may fetch anything.
const MESH: (&str, &[u8]) = ("canary.obj", include_bytes!("canary.obj"));

/// The files the canary scene names, as the canary message carries them.
pub fn files() -> Vec<CanaryFile> {
    vec![CanaryFile {
        name: MESH.0.to_string(),
        bytes: MESH.1.to_vec(),
    }]
}

/// Parses a canary scene with its files.
pub fn parse(scene: &str, files: &[CanaryFile]) -> Result<render::Scene, String> {
    let bound: BTreeMap<String, Arc<[u8]>> = files
        .iter()
        .map(|f| (f.name.clone(), Arc::from(f.bytes.as_slice())))
        .collect();
    render::parse_scene_with(scene, &render::MeshFiles::bound(bound))
        .map_err(|e| format!("the canary scene: {e}"))
}

/// The canary's renders: the whole 40 × 30 frame with each sampler, and one
/// block-aligned tile inside it with adaptive sampling, walked down the ladder in passes
/// whose block states cross the wire encoding as the farm's passes do.
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
                x: 8,
                y: 8,
                width: 24,
                height: 16,
            },
        },
    ]
}

/// Renders the canary as a worker is asked to: one RGB8 buffer per render.
pub fn render(
    scene: &str,
    files: &[CanaryFile],
    renders: &[CanaryRender],
) -> Result<Vec<Vec<u8>>, String> {
    let scene = parse(scene, files)?;
    renders
        .iter()
        .map(|r| {
            let tracer = crate::tracer(&scene, &r.settings)?;
            match r.settings.sampling.target_error() {
                Some(target) => walk(&tracer, r.rect, target),
                None => render::render_tile(&tracer, crate::render_rect(r.rect))
                    .map(|tile| tile.rgb)
                    .map_err(|e| e.to_string()),
            }
        })
        .collect()
}

/// Rungs per pass of the canary's adaptive walk.
const RUNGS_PER_PASS: u32 = 24;

/// An adaptive render of `rect` as the farm makes it: rung after rung until the
/// region's own estimate meets `target`, in passes of [`RUNGS_PER_PASS`] rungs between
/// which the blocks' state is encoded, compressed and read back (the whole frame gives
/// exactly what `render::adaptive::render_to_target` gives).
fn walk(tracer: &render::Tracer, rect: TileRect, target: f64) -> Result<Vec<u8>, String> {
    use render::adaptive::meets;
    let footprints = crate::adaptive::footprints(tracer);
    let aa = tracer.settings().aa;
    let mut state = None;
    let mut k = 0;
    loop {
        let pass_end = k + RUNGS_PER_PASS;
        let mut region =
            crate::adaptive::region_from(tracer, std::sync::Arc::clone(&footprints), rect, state)?;
        loop {
            region.advance_to(k);
            let totals = region.totals(k).ok_or("a rung not reached")?;
            if meets(&totals, k, target) {
                return crate::adaptive::pixels(&region, &footprints, aa, rect, k)
                    .ok_or_else(|| "a rung not reached".to_string());
            }
            if k + 1 == pass_end {
                break;
            }
            k += 1;
        }
        k += 1;
        let packed = crate::adaptive::encode_state(region.blocks());
        state = Some(crate::adaptive::unpack_state(&packed, rect, aa)?);
    }
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
        let ours = render(SCENE, &files(), &renders).expect("the canary renders");
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
        let ours = render(SCENE, &files(), &renders).unwrap();
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
    fn the_mesh_shows_in_every_render() {
        // A renderer that read the mesh wrong (one vertex moved, here) would be caught
        // by each of the canary's renders, not only by chance.
        let renders = renders();
        let ours = render(SCENE, &files(), &renders).unwrap();
        let mut moved = files();
        let text = String::from_utf8(moved[0].bytes.clone()).unwrap();
        let first = text.lines().find(|l| l.starts_with("v ")).unwrap();
        moved[0].bytes = text
            .replacen(first, "v -0.425731 0.950651 0.000000", 1)
            .into_bytes();
        let theirs = render(SCENE, &moved, &renders).unwrap();
        for (index, (a, b)) in ours.iter().zip(&theirs).enumerate() {
            assert_ne!(a, b, "render {index} does not show the mesh");
        }
        // And without its file the canary is not rendered at all.
        let err = render(SCENE, &[], &renders).unwrap_err();
        assert!(err.contains("canary.obj"), "{err}");
    }

    #[test]
    fn the_adaptive_frame_in_passes_is_the_local_walk() {
        let renders = renders();
        let ours = render(SCENE, &files(), &renders).unwrap();
        let scene = parse(SCENE, &files()).unwrap();
        let tracer = crate::tracer(&scene, &renders[2].settings).unwrap();
        let target = renders[2].settings.sampling.target_error().unwrap();
        let (_, frame) =
            render::adaptive::render_to_target(&tracer, None, target, &mut |_, _| true);
        assert!(
            frame.rung > RUNGS_PER_PASS,
            "several passes: rung {}",
            frame.rung
        );
        assert_eq!(ours[2], frame.image.rgb);
    }
}
