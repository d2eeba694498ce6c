//! Checking what workers return: the canary a worker renders when it joins, spot
//! checks of every tile result, and the tracers they need, all off the state lock.
//!
//! The decisions (hold a result for confirmation, accept it, quarantine a machine) are
//! the scheduler's and the core's; this module only renders and compares.

use std::collections::VecDeque;
use std::sync::{Arc, Mutex};

use protocol::{CanaryRender, SceneHash, Settings, TileRect};
use render::adaptive::Footprints;
use render::Tracer;
use verify::spot::{self, WrongPixel};

/// How results are checked, for every job.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct VerifyConfig {
    /// Pixels of each tile result rendered again by the coordinator (at most one in
    /// 128 of the tile's pixels; 0 turns spot checks off). An adaptive answer's pixels
    /// depend on its whole block, so a block is checked instead: one block of an answer
    /// of B blocks, with probability min(1, B × `spot_pixels` / 1600), which costs
    /// about `spot_pixels` / 16 % of the rendering (1 % by default).
    pub spot_pixels: u32,
    /// Share of the tiles of a job in sampled verification whose result is held until
    /// another machine returns the same bytes (0 turns audits off).
    pub audit_share: f64,
}

impl Default for VerifyConfig {
    fn default() -> Self {
        VerifyConfig {
            spot_pixels: 16,
            audit_share: 0.01,
        }
    }
}

/// Tracers kept for spot checks: the jobs running at once, give or take.
const TRACERS_KEPT: usize = 16;

/// Recently used tracers by scene, frame and settings, oldest first.
type Tracers = VecDeque<((SceneHash, u32, Settings), Arc<Tracer>)>;

/// The adaptive footprints of recent tracers (by the tracer's address, which the cache
/// of tracers keeps alive), oldest first.
type FootprintsKept = VecDeque<(Arc<Tracer>, Arc<Footprints>)>;

/// The canary's reference render and the tracers of recent jobs.
pub struct Verifier {
    pub config: VerifyConfig,
    pub canary: Canary,
    tracers: Mutex<Tracers>,
    footprints: Mutex<FootprintsKept>,
}

/// The canary as this coordinator renders it.
pub struct Canary {
    pub renders: Vec<CanaryRender>,
    pub images: Vec<Vec<u8>>,
}

impl Verifier {
    /// Renders the canary (a few milliseconds): call it off the async threads.
    pub fn new(config: VerifyConfig) -> Result<Verifier, String> {
        let renders = verify::canary::renders();
        let images =
            verify::canary::render(verify::canary::SCENE, &verify::canary::files(), &renders)?;
        Ok(Verifier {
            config,
            canary: Canary { renders, images },
            tracers: Mutex::new(VecDeque::new()),
            footprints: Mutex::new(VecDeque::new()),
        })
    }

    /// The tracer for a job's frame of its scene (from 1), read with the files it names
    /// (`files`), and settings, built on first use (parsing, computing the frame and building the hierarchy: call it off the
    /// state lock). The frame is the job's, so a result rendered from another frame
    /// fails its checks.
    pub fn tracer(
        &self,
        hash: SceneHash,
        frame: u32,
        settings: Settings,
        scene: &str,
        files: impl FnOnce() -> Result<render::MeshFiles, String>,
    ) -> Result<Arc<Tracer>, String> {
        let key = (hash, frame, settings);
        if let Some((_, t)) = self.cache().iter().find(|(k, _)| *k == key) {
            return Ok(Arc::clone(t));
        }
        // The scene's files are read (and checked) only when the tracer is built.
        let parsed = render::parse_animated_with(scene, &files()?)
            .map_err(|e| e.to_string())?
            .frame(u64::from(frame))
            .map_err(|e| e.to_string())?;
        let tracer = Arc::new(verify::tracer(&parsed, &settings)?);
        let mut cache = self.cache();
        if !cache.iter().any(|(k, _)| *k == key) {
            if cache.len() >= TRACERS_KEPT {
                cache.pop_front();
            }
            cache.push_back((key, Arc::clone(&tracer)));
        }
        Ok(tracer)
    }

    /// The adaptive footprints of a tracer's frame, computed on first use (off the
    /// lock) and kept while its tracer is.
    pub fn footprints(&self, tracer: &Tracer) -> Arc<Footprints> {
        let kept = || self.footprints.lock().unwrap_or_else(|e| e.into_inner());
        if let Some((_, f)) = kept().iter().find(|(t, _)| std::ptr::eq(&**t, tracer)) {
            return Arc::clone(f);
        }
        let f = verify::adaptive::footprints(tracer);
        let owner = self
            .cache()
            .iter()
            .find(|(_, t)| std::ptr::eq(&**t, tracer))
            .map(|(_, t)| Arc::clone(t));
        if let Some(owner) = owner {
            let mut kept = kept();
            if kept.len() >= TRACERS_KEPT {
                kept.pop_front();
            }
            kept.push_back((owner, Arc::clone(&f)));
        }
        f
    }

    /// Whether one block of an adaptive answer of `blocks` blocks is checked.
    pub fn adaptive_check(&self, blocks: usize) -> bool {
        let share = (blocks as f64 * f64::from(self.config.spot_pixels) / 1600.0).min(1.0);
        let draw = (random_u64() >> 11) as f64 / (1u64 << 53) as f64;
        share > 0.0 && draw < share
    }

    fn cache(&self) -> std::sync::MutexGuard<'_, Tracers> {
        self.tracers.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Renders a few pixels of the result, chosen now from fresh randomness, and
    /// compares them with the result's.
    pub fn spot_check(
        &self,
        tracer: &Tracer,
        rect: TileRect,
        rgb: &[u8],
    ) -> Result<(), WrongPixel> {
        let count = match self.config.spot_pixels {
            0 => 0,
            n => spot::pixels_to_check(rect, n),
        };
        let pixels = spot::choose(rect, count, random_u64());
        spot::check(tracer, rect, rgb, &pixels)
    }

    /// Whether this result is audited: held until another machine confirms it.
    pub fn audit(&self) -> bool {
        let share = self.config.audit_share;
        let draw = (random_u64() >> 11) as f64 / (1u64 << 53) as f64;
        share > 0.0 && draw < share
    }
}

/// 64 bits from the operating system: what is checked must not be predictable by the
/// worker that rendered it.
pub(super) fn random_u64() -> u64 {
    let mut bytes = [0u8; 8];
    // Without randomness the choice falls back to the clock, still unknown to a worker.
    if getrandom::fill(&mut bytes).is_err() {
        let nanos = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos() as u64);
        return nanos;
    }
    u64::from_le_bytes(bytes)
}
