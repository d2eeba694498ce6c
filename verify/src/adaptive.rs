//! Adaptive tiles on the farm: advancing a tile's blocks down the threshold ladder from
//! a state the coordinator kept, the state's encoding on the wire, and the checks of a
//! worker's answer.
//!
//! A block's state after rung k is a pure function of the scene, the settings, its
//! coordinates and k, whichever earlier rungs it stopped at on the way (see
//! `render::adaptive`). So a pass that advances a tile from its previous state gives
//! the bytes a whole-frame walk gives, on any worker, and the coordinator can check one
//! block of an answer by advancing that block alone from the same previous state.

use std::sync::Arc;

use protocol::TileRect;
use render::adaptive::{sample_cap, BlockState, Footprints, Region, RungTotals, BLOCK};
use render::Tracer;

/// The largest side of an adaptive tile. A tile's state holds about 80 bytes per pixel
/// (each pixel's sums, and its colour at every level): at 256 × 256 pixels, even
/// incompressible, the previous state and the answer stay far below the default frame
/// limit of 16 MiB.
pub const MAX_TILE: u32 = 256;

/// The level tile states are compressed at: the fastest.
const ZSTD_LEVEL: i32 = 1;

/// Why a tile cannot be an adaptive tile of its job: one line naming the rule.
pub fn check_tile_side(side: u32) -> Result<(), String> {
    if side.is_multiple_of(BLOCK) && side <= MAX_TILE {
        Ok(())
    } else {
        Err(format!(
            "adaptive sampling needs tiles cut on its {BLOCK}-pixel blocks: a multiple of \
             {BLOCK} up to {MAX_TILE}, got {side}"
        ))
    }
}

/// Blocks in a block-aligned tile.
fn blocks_in(rect: TileRect) -> u64 {
    u64::from(rect.width.div_ceil(BLOCK)) * u64::from(rect.height.div_ceil(BLOCK))
}

/// The most levels a block may hold with `aa`: from its first count up to the cap.
fn max_levels(aa: u32) -> u64 {
    let cap = sample_cap(aa);
    // A first level of 1 (a cap of 1, 2) or 4 samples, then doublings up to the cap.
    u64::from(cap.trailing_zeros()) + 1
}

/// The most bytes the encoded state of a tile can take: what its compressed state may
/// decompress to, so that a small frame cannot expand into a large allocation.
pub fn state_bound(rect: TileRect, aa: u32) -> usize {
    let pixels = u64::from(rect.width) * u64::from(rect.height);
    let blocks = blocks_in(rect);
    let levels = max_levels(aa);
    // In the wire's fixed-width integers: the Vec's length; per block its rectangle
    // (four u32) and the lengths of its levels and sums; per level its count (u32),
    // spread, contrast and rounding (f64), rays (u64), its pixels' length and bytes;
    // per pixel its two sums of three f64.
    let bytes = 8 + blocks * (16 + 8 + 8) + levels * (blocks * 44 + pixels * 3) + pixels * 48;
    usize::try_from(bytes).unwrap_or(usize::MAX)
}

/// The state of a tile's blocks as it crosses the network: encoded like a message,
/// then one zstd frame.
pub fn encode_state(blocks: &[BlockState]) -> Vec<u8> {
    let raw = protocol::wire::encode(&blocks);
    zstd::bulk::compress(&raw, ZSTD_LEVEL).unwrap_or_else(|_| {
        // Only when zstd cannot allocate its context: a frame stored as it is.
        zstd::stream::encode_all(&raw[..], 0).expect("zstd compresses in memory")
    })
}

/// The encoded (uncompressed) bytes of a compressed state, within the tile's bound.
pub fn decompress_state(bytes: &[u8], rect: TileRect, aa: u32) -> Result<Vec<u8>, String> {
    zstd::bulk::decompress(bytes, state_bound(rect, aa))
        .map_err(|e| format!("its block state does not decompress within its bound: {e}"))
}

/// A state from its encoded (uncompressed) bytes.
pub fn decode_state(raw: &[u8]) -> Result<Vec<BlockState>, String> {
    protocol::wire::decode::<Vec<BlockState>>(raw)
        .map_err(|e| format!("its block state is unreadable: {}", e.detail()))
}

/// A compressed state, decoded.
pub fn unpack_state(bytes: &[u8], rect: TileRect, aa: u32) -> Result<Vec<BlockState>, String> {
    decode_state(&decompress_state(bytes, rect, aa)?)
}

/// The frame's footprints for a tracer (computed once per job and shared by its tiles).
pub fn footprints(tracer: &Tracer) -> Arc<Footprints> {
    Region::footprints(tracer)
}

/// A tile advanced to a rung.
pub struct Advanced {
    /// Its pixels at the rung, RGB8, rows top to bottom.
    pub rgb: Vec<u8>,
    pub blocks: Vec<BlockState>,
    /// Rays traced by this advance.
    pub rays: u64,
    /// Samples of its pixels at the rung.
    pub samples: u64,
}

/// Rays traced for blocks so far.
fn rays_of(blocks: &[BlockState]) -> u64 {
    blocks
        .iter()
        .filter_map(|b| b.levels.last())
        .map(|l| l.rays)
        .sum()
}

/// Advances the blocks of `rect` to `rung` from `previous` (or from nothing).
pub fn advance(
    tracer: &Tracer,
    footprints: Arc<Footprints>,
    rect: TileRect,
    previous: Option<Vec<BlockState>>,
    rung: u32,
) -> Result<Advanced, String> {
    let before = previous.as_deref().map_or(0, rays_of);
    let mut region = region_from(tracer, Arc::clone(&footprints), rect, previous)?;
    region.advance_to(rung);
    let aa = tracer.settings().aa;
    let rgb = pixels(&region, &footprints, aa, rect, rung).expect("advanced to the rung");
    let samples = region.totals(rung).expect("advanced to the rung").samples;
    let blocks = region.into_blocks();
    let rays = rays_of(&blocks).saturating_sub(before);
    Ok(Advanced {
        rgb,
        blocks,
        rays,
        samples,
    })
}

/// A region of a tile's blocks, checked: the right rectangles, levels that double from
/// the first count this job's `aa` gives, finite numbers. A state that could only be
/// continued by rendering anew (another first count) is refused too: it is not what
/// any worker of this job returns.
pub fn region<'t>(
    tracer: &'t Tracer,
    footprints: Arc<Footprints>,
    rect: TileRect,
    blocks: Vec<BlockState>,
) -> Result<Region<'t>, String> {
    let base = render::adaptive::BASE_SAMPLES.min(sample_cap(tracer.settings().aa));
    if blocks
        .iter()
        .any(|b| b.levels.first().is_some_and(|l| l.count != base))
    {
        return Err(format!("its blocks do not start at {base} samples"));
    }
    Region::new(tracer, footprints, crate::render_rect(rect), Some(blocks))
        .map_err(|e| e.to_string())
}

/// A region of `rect` from a state received (checked like [`region`]) or from nothing.
pub fn region_from<'t>(
    tracer: &'t Tracer,
    footprints: Arc<Footprints>,
    rect: TileRect,
    blocks: Option<Vec<BlockState>>,
) -> Result<Region<'t>, String> {
    match blocks {
        Some(blocks) => region(tracer, footprints, rect, blocks),
        None => Region::new(tracer, footprints, crate::render_rect(rect), None)
            .map_err(|e| e.to_string()),
    }
}

/// The tile's pixels at `rung`, if every block has been rendered that far. `footprints`
/// and `aa` are the job's (the region's own).
pub fn pixels(
    region: &Region,
    footprints: &Footprints,
    aa: u32,
    rect: TileRect,
    rung: u32,
) -> Option<Vec<u8>> {
    let cap = sample_cap(aa);
    let mut rgb = vec![0; rect.width as usize * rect.height as usize * 3];
    for block in region.blocks() {
        let r = block.rect;
        let min = footprints.min_samples(r.x / BLOCK, r.y / BLOCK);
        let level = &block.levels[block.level_at(rung, cap, min)?];
        let row = r.width as usize * 3;
        for j in 0..r.height as usize {
            let at = ((r.y - rect.y) as usize + j) * rect.width as usize + (r.x - rect.x) as usize;
            rgb[at * 3..at * 3 + row].copy_from_slice(&level.rgb[j * row..(j + 1) * row]);
        }
    }
    Some(rgb)
}

/// The first rung after `rung` at which some block of the region doubles, if any: a
/// tile with no block doubling at a pass's rung need not be sent in that pass.
pub fn next_work(region: &Region, rung: u32) -> Option<u32> {
    let last = render::adaptive::LAST_RUNG;
    if rung >= last || region.totals(last).is_some() {
        return None;
    }
    // Work at rung r means some block has not reached r; that holds from some rung on.
    let (mut lo, mut hi) = (rung, last);
    while hi - lo > 1 {
        let mid = lo + (hi - lo) / 2;
        if region.totals(mid).is_some() {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    Some(hi)
}

/// The region's totals at each rung of `rungs` (all reached).
pub fn totals(region: &Region, rungs: std::ops::RangeInclusive<u32>) -> Option<Vec<RungTotals>> {
    rungs.map(|k| region.totals(k)).collect()
}

/// A block of an answer that is not what the renderer gives.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("block ({x}, {y}) at rung {rung} is not what the renderer gives: {what}")]
pub struct WrongBlock {
    pub x: u32,
    pub y: u32,
    pub rung: u32,
    pub what: &'static str,
}

/// Block `index` of the tile advanced to `rung` here, from its previous state.
fn reference_block(
    tracer: &Tracer,
    footprints: &Arc<Footprints>,
    previous: Option<&[BlockState]>,
    rect: render::Rect,
    index: usize,
    rung: u32,
) -> Option<BlockState> {
    let before = match previous {
        Some(p) => Some(vec![p.get(index)?.clone()]),
        None => None,
    };
    let mut region = Region::new(tracer, Arc::clone(footprints), rect, before).ok()?;
    region.advance_to(rung);
    region.into_blocks().pop()
}

/// Whether two block states are the same bits (their numbers included).
fn same(a: &BlockState, b: &BlockState) -> bool {
    protocol::wire::encode(a) == protocol::wire::encode(b)
}

/// Checks block `seed` mod blocks of an answer (`blocks`, checked by [`region`]) by
/// advancing it here from its previous state: its levels and sums must be the same
/// bits. What it costs is the rendering of that one block.
pub fn check_block(
    tracer: &Tracer,
    footprints: &Arc<Footprints>,
    previous: Option<&[BlockState]>,
    blocks: &[BlockState],
    rung: u32,
    seed: u64,
) -> Result<(), WrongBlock> {
    if blocks.is_empty() {
        return Ok(());
    }
    let index = (seed % blocks.len() as u64) as usize;
    let got = &blocks[index];
    let r = got.rect;
    let wrong = |what| WrongBlock {
        x: r.x,
        y: r.y,
        rung,
        what,
    };
    match reference_block(tracer, footprints, previous, r, index, rung) {
        Some(expected) if same(&expected, got) => Ok(()),
        Some(_) => Err(wrong("its samples differ")),
        None => Err(wrong("it cannot be rendered from the previous state")),
    }
}

/// Which of two differing answers for a tile is wrong: up to
/// [`crate::spot::ARBITRATION_PIXELS`] of the blocks where they differ are advanced
/// here (rarely needed: only when a liar is about).
pub fn arbitrate(
    tracer: &Tracer,
    footprints: &Arc<Footprints>,
    previous: Option<&[BlockState]>,
    first: &[BlockState],
    second: &[BlockState],
    rung: u32,
) -> (Option<WrongBlock>, Option<WrongBlock>) {
    let mut verdict = (None, None);
    let differing = first
        .iter()
        .zip(second)
        .enumerate()
        .filter(|(_, (a, b))| !same(a, b))
        .take(crate::spot::ARBITRATION_PIXELS);
    for (index, (a, b)) in differing {
        let r = a.rect;
        let expected = reference_block(tracer, footprints, previous, r, index, rung);
        for (got, slot) in [(a, &mut verdict.0), (b, &mut verdict.1)] {
            if slot.is_none() && expected.as_ref().is_none_or(|e| !same(e, got)) {
                *slot = Some(WrongBlock {
                    x: got.rect.x,
                    y: got.rect.y,
                    rung,
                    what: "its samples differ from another machine's and from the renderer's",
                });
            }
        }
        if verdict.0.is_some() && verdict.1.is_some() {
            break;
        }
    }
    verdict
}

#[cfg(test)]
mod tests {
    use super::*;
    use protocol::{Sampling, Settings};

    fn tracer(aa: u32) -> Tracer {
        let scene = crate::canary::parse(crate::canary::SCENE, &crate::canary::files()).unwrap();
        let settings = Settings {
            width: 40,
            height: 30,
            aa,
            max_depth: 4,
            sampling: Sampling::Adaptive { target_milli: 500 },
        };
        crate::tracer(&scene, &settings).unwrap()
    }

    const TILE: TileRect = TileRect {
        x: 16,
        y: 24,
        width: 24,
        height: 6,
    };

    #[test]
    fn passes_through_the_wire_give_the_blocks_of_one_advance() {
        let t = tracer(8);
        let fp = footprints(&t);
        let direct = advance(&t, Arc::clone(&fp), TILE, None, 150).unwrap();
        let first = advance(&t, Arc::clone(&fp), TILE, None, 60).unwrap();
        let packed = encode_state(&first.blocks);
        let raw = decompress_state(&packed, TILE, 8).unwrap();
        assert!(raw.len() <= state_bound(TILE, 8));
        let back = decode_state(&raw).unwrap();
        let second = advance(&t, Arc::clone(&fp), TILE, Some(back.clone()), 150).unwrap();
        assert_eq!(second.rgb, direct.rgb);
        assert_eq!(
            protocol::wire::encode(&second.blocks),
            protocol::wire::encode(&direct.blocks)
        );
        assert_eq!(first.rays + second.rays, direct.rays);
        assert_eq!(second.samples, direct.samples);
        // The one-block check passes on every block, and fails on a changed sum.
        for seed in 0..6 {
            assert_eq!(
                check_block(&t, &fp, Some(&back), &second.blocks, 150, seed),
                Ok(())
            );
        }
        let mut lie = second.blocks.clone();
        lie[2].sums[5][1][0] += 1e-9;
        assert!(check_block(&t, &fp, Some(&back), &lie, 150, 2).is_err());
        let (a, b) = arbitrate(&t, &fp, Some(&back), &second.blocks, &lie, 150);
        assert_eq!((a, b.map(|w| (w.x, w.y))), (None, Some((32, 24))));
    }

    #[test]
    fn a_finished_state_fits_its_bound_exactly_at_one_level() {
        // aa 1: one level per block, the bound is the size itself; above, every block
        // at its cap still fits.
        for aa in [1, 2, 3, 4] {
            let t = tracer(aa);
            let fp = footprints(&t);
            let done =
                advance(&t, Arc::clone(&fp), TILE, None, render::adaptive::LAST_RUNG).unwrap();
            let raw = protocol::wire::encode(&done.blocks);
            let bound = state_bound(TILE, aa);
            assert!(raw.len() <= bound, "aa {aa}: {} > {bound}", raw.len());
            if aa == 1 {
                assert_eq!(raw.len(), bound);
            }
            let packed = encode_state(&done.blocks);
            assert_eq!(decompress_state(&packed, TILE, aa).unwrap(), raw);
        }
    }

    #[test]
    fn a_tile_without_work_at_a_rung_traces_nothing_there() {
        let t = tracer(16);
        let fp = footprints(&t);
        let done = advance(&t, Arc::clone(&fp), TILE, None, 10).unwrap();
        let region = region(&t, Arc::clone(&fp), TILE, done.blocks.clone()).unwrap();
        let next = next_work(&region, 10).expect("aa 16 leaves work");
        assert!(next > 11, "{next}");
        let idle = advance(
            &t,
            Arc::clone(&fp),
            TILE,
            Some(done.blocks.clone()),
            next - 1,
        )
        .unwrap();
        assert_eq!(idle.rays, 0);
        let busy = advance(&t, Arc::clone(&fp), TILE, Some(done.blocks), next).unwrap();
        assert!(busy.rays > 0);
    }

    #[test]
    fn states_past_their_bound_or_damaged_are_refused() {
        let t = tracer(4);
        let fp = footprints(&t);
        let done = advance(&t, Arc::clone(&fp), TILE, None, 80).unwrap();
        let packed = encode_state(&done.blocks);
        let small = TileRect {
            width: 8,
            height: 6,
            ..TILE
        };
        assert!(decompress_state(&packed, small, 4).is_err());
        assert!(unpack_state(&packed[..packed.len() / 2], TILE, 4).is_err());
        let mut other = done.blocks.clone();
        other.swap(0, 1);
        assert!(region(&t, fp, TILE, other).is_err());
        assert!(check_tile_side(24).is_ok());
        assert_eq!(
            check_tile_side(20).unwrap_err(),
            "adaptive sampling needs tiles cut on its 8-pixel blocks: a multiple of 8 up to 256, got 20"
        );
    }
}
