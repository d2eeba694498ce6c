//! A submission: its scene parsed and its settings checked off the lock, then admitted
//! and answered once its row is written; and a refinement, a new job from a finished
//! adaptive one's stored tile states, checked before it is admitted.

use std::net::IpAddr;
use std::sync::atomic::Ordering;
use std::sync::Arc;

use protocol::scene_hash;
use protocol::{
    AssetAnswer, AssetRef, ClientResponse, JobId, JobSpec, JobState, Refusal, Settings,
    MAX_ASSET_NAME, MAX_JOB_ASSETS,
};
use scheduler::lifecycle;

use super::unknown_job;
use crate::db::Label;
use crate::server::core::Prepared;
use crate::server::persistence::Write;
use crate::server::Shared;
use crate::tiling::{self, MAX_TILE, MIN_TILE};

/// Checks and measures a submission (parsing its scene) without the lock, has the
/// lifecycle admit it, and answers once its row is written.
pub(super) async fn submit(sh: &Arc<Shared>, spec: JobSpec, peer: IpAddr) -> ClientResponse {
    if sh.closing.load(Ordering::SeqCst) {
        return ClientResponse::Error(Refusal::unavailable(
            "the coordinator is shutting down: submit again when it is back",
        ));
    }
    if let Err(refusal) = check_assets(&spec.assets) {
        return ClientResponse::Error(refusal);
    }
    let limits = sh.limits;
    // The scene's files are kept under a provisional owner while the scene is checked,
    // then under the job's id once it is admitted: no collection falls in between.
    let owner = sh.depot.provisional();
    let shared = Arc::clone(sh);
    // What stops a submission before admission: the answer to give, boxed (an answer
    // is large, a prepared job is not).
    let checked = tokio::task::spawn_blocking(move || -> Result<Prepared, Box<ClientResponse>> {
        if let Err(lacking) = shared
            .depot
            .pin(owner, &spec.assets, crate::server::unix_ms())
        {
            let answer = ClientResponse::Assets(AssetAnswer::SubmitLacking { lacking });
            return Err(Box::new(answer));
        }
        let refused = |r: Refusal| Box::new(ClientResponse::Error(r));
        let files = shared.mesh_files(&spec.assets).map_err(|e| {
            refused(Refusal::not_found(format!(
                "a file of the scene cannot be read from the coordinator's store: {e}"
            )))
        })?;
        prepare(spec, &limits, peer, &files).map_err(refused)
    })
    .await;
    let response = match checked {
        Ok(Ok(prepared)) => admit(sh, prepared).await,
        Ok(Err(response)) => *response,
        Err(_) => ClientResponse::Error(Refusal::unavailable(
            "the scene could not be checked: try again",
        )),
    };
    sh.depot.release(owner, crate::server::unix_ms());
    response
}

/// The files a submission names, checked before any is read: how many, their names
/// (one each), none twice.
pub(in crate::server) fn check_assets(assets: &[AssetRef]) -> Result<(), Refusal> {
    if assets.len() > MAX_JOB_ASSETS {
        return Err(Refusal::limit(format!(
            "assets: {} files, more than the {MAX_JOB_ASSETS} a job may name",
            assets.len()
        )));
    }
    let mut names = std::collections::BTreeSet::new();
    for (i, a) in assets.iter().enumerate() {
        if a.name.is_empty() || a.name.len() > MAX_ASSET_NAME || a.name.contains('\0') {
            return Err(Refusal::invalid(format!(
                "assets[{i}]: a file's name must be 1 to {MAX_ASSET_NAME} bytes without NUL"
            )));
        }
        if !names.insert(a.name.as_str()) {
            return Err(Refusal::invalid(format!(
                "assets[{i}]: {:?} is named twice",
                a.name
            )));
        }
    }
    Ok(())
}

/// Has the lifecycle admit a prepared job (or a sequence), and answers once its row is
/// written.
pub(in crate::server) async fn admit(sh: &Arc<Shared>, prepared: Prepared) -> ClientResponse {
    let (reply, answer) = tokio::sync::oneshot::channel();
    let assets = prepared.assets.clone();
    if prepared.frames.is_some() {
        let stored = match sh.lock().admit_sequence(prepared, reply) {
            Ok(stored) => stored,
            Err(message) => return ClientResponse::Error(message),
        };
        let id = stored.id;
        keep_files(sh, id, &assets);
        let shared = Arc::clone(sh);
        sh.persistence.write(Write::InsertJob {
            job: Box::new(stored),
            then: Box::new(move |result| {
                shared.lock().sequence_stored(&shared, id, result);
            }),
        });
    } else {
        let mut core = sh.lock();
        let stored = match core.admit(prepared, reply) {
            Ok(stored) => stored,
            Err(message) => return ClientResponse::Error(message),
        };
        let id = stored.id;
        keep_files(sh, id, &assets);
        let write = core.insert_write(sh, stored);
        // A studio view's pass is not stored: `store` discards the write.
        core.store(sh, id, write);
    }
    answer.await.unwrap_or_else(|_| {
        ClientResponse::Error(Refusal::unavailable(
            "the coordinator stopped before storing the job: submit again",
        ))
    })
}

/// Keeps the files of a job just admitted for as long as the job is kept (they were
/// pinned for its check: they are in the store).
fn keep_files(sh: &Shared, job: JobId, assets: &[AssetRef]) {
    if !assets.is_empty() && sh.depot.pin(job, assets, crate::server::unix_ms()).is_err() {
        tracing::error!(
            job,
            "the scene's files left the store while it was admitted"
        );
    }
}

/// A new job from a finished adaptive one, its tiles starting from the old job's
/// final states: the old job's scene (read back and checked against its hash), size,
/// tiling, depth, priority and verification, with the new target, cap and time limit.
/// The states are read from disk and checked (their checksum, then each as a state of
/// its tile for the new job, as a worker's answer would be) before the job is
/// admitted: a missing or damaged state refuses the refinement, never gives a wrong
/// image.
pub(super) async fn refine(
    sh: &Arc<Shared>,
    job: JobId,
    target_milli: u32,
    aa: Option<u32>,
    time_limit_ms: Option<u64>,
    peer: IpAddr,
) -> Result<ClientResponse, Refusal> {
    if sh.closing.load(Ordering::SeqCst) {
        return Err(Refusal::unavailable(
            "the coordinator is shutting down: refine again when it is back",
        ));
    }
    let (old, tile_size, priority, verification, hash, name, submitter, frame, assets, require) = {
        let core = sh.lock();
        let Some(status) = core.status(job) else {
            return Ok(unknown_job(job));
        };
        if status.state != JobState::Done {
            return Err(Refusal::state(format!(
                "it is {}: only a job that is done can be refined",
                status.state.as_str()
            )));
        }
        if status.settings.sampling.target_error().is_none() {
            return Err(Refusal::invalid(format!(
                "it was rendered with {} sampling: only adaptive jobs keep their tile states",
                status.settings.sampling.name()
            )));
        }
        let record = core
            .jobs
            .get(&job)
            .ok_or_else(|| Refusal::unknown_job(job))?;
        (
            status.settings,
            record.tile_size,
            record.priority,
            record.verification,
            record.hash,
            status.name.clone(),
            status.submitter.clone(),
            status.frame,
            record.assets.to_vec(),
            // A refinement renders in the pool the job did.
            record.require.clone(),
        )
    };
    let aa = aa.unwrap_or(old.aa);
    if aa < old.aa {
        return Err(Refusal::invalid(format!(
            "aa {aa} is below the job's {}: a refinement can only add samples",
            old.aa
        )));
    }
    let shared = Arc::clone(sh);
    let limits = sh.limits;
    let prepared = tokio::task::spawn_blocking(move || -> Result<Prepared, Refusal> {
        let store = &shared.store;
        let scene = store
            .read_scene(job)
            .map_err(|e| Refusal::internal(format!("{e:#}")))?;
        if scene_hash(&scene, &assets) != hash {
            return Err(Refusal::internal(format!(
                "the stored scene of job {job} does not match the job's scene hash"
            )));
        }
        let states = store
            .read_states(job)
            .map_err(|e| Refusal::internal(format!("{e:#}")))?;
        let spec = JobSpec {
            scene,
            overrides: protocol::Overrides {
                width: Some(old.width),
                height: Some(old.height),
                aa: Some(aa),
                max_depth: Some(old.max_depth),
                tile_size: Some(tile_size),
                sampling: Some(protocol::Sampling::Adaptive { target_milli }),
            },
            priority,
            verification,
            time_limit_ms,
            name: refined_name(&name),
            submitter,
            frame,
            frames: None,
            assets,
            // A refinement is a job of its own, waiting for nothing.
            after: Vec::new(),
            require,
        };
        let files = shared
            .mesh_files(&spec.assets)
            .map_err(|e| Refusal::not_found(format!("the scene's files: {e}")))?;
        let mut prepared = prepare(spec, &limits, peer, &files)?;
        if states.tile_size != tile_size
            || states.aa != old.aa
            || states.states.len() != prepared.tiles.len()
        {
            return Err(Refusal::invalid(format!(
                "its stored tile states are for another tiling ({} tiles of {} px at aa {}, \
                 not {} of {tile_size} px at aa {})",
                states.states.len(),
                states.tile_size,
                states.aa,
                prepared.tiles.len(),
                old.aa
            )));
        }
        let verifier = &shared.verifier;
        let tracer = verifier
            .tracer(
                prepared.hash,
                prepared.frame,
                prepared.settings,
                &prepared.scene,
                || Ok(files.clone()),
            )
            .map_err(Refusal::invalid)?;
        let footprints = verifier.footprints(&tracer);
        for (t, (state, &rect)) in states.states.iter().zip(&prepared.tiles).enumerate() {
            verify::adaptive::unpack_state(state, rect, prepared.settings.aa)
                .and_then(|blocks| {
                    verify::adaptive::region(
                        &tracer,
                        std::sync::Arc::clone(&footprints),
                        rect,
                        blocks,
                    )
                    .map(drop)
                })
                .map_err(|e| {
                    Refusal::internal(format!("the stored state of tile {t} is not valid: {e}"))
                })?;
        }
        prepared.start = Some(states);
        Ok(prepared)
    })
    .await
    .map_err(|_| Refusal::unavailable("the stored states could not be checked: try again"))??;
    Ok(admit(sh, prepared).await)
}

/// Parses and checks a job: the settings it will render with, its tiles and what the
/// lifecycle needs to admit it.
pub(in crate::server) fn prepare(
    spec: JobSpec,
    limits: &lifecycle::Limits,
    client: IpAddr,
    files: &render::MeshFiles,
) -> Result<Prepared, Refusal> {
    limits.check_scene_bytes(spec.scene.len())?;
    let require = protocol::check_tags(&spec.require)
        .map_err(|e| Refusal::invalid(format!("require: {e}")))?;
    // The frame is checked with the scene: a frame it does not have is refused in the
    // loader's one line ("frame 122 is beyond the scene's 121 frames"). Image settings
    // are not animated, so the base scene's are every frame's.
    let animated = render::parse_animated_with(&spec.scene, files)
        .map_err(|e| Refusal::invalid(e.to_string()))?;
    let frames = animated.frame_count();
    let out_of_range = |frame: u32| render::FrameOutOfRange {
        frame: u64::from(frame),
        frames,
        animated: animated.animation.is_some(),
    };
    if spec.frame == 0 || spec.frame > frames {
        return Err(Refusal::invalid(out_of_range(spec.frame).to_string()));
    }
    if let Some(range) = spec.frames {
        if !spec.after.is_empty() {
            return Err(Refusal::invalid(
                "after: a sequence job cannot wait for other jobs; submit its frames' \
                 dependencies as single jobs, or submit the sequence once they are done",
            ));
        }
        if spec.frame != 1 {
            return Err(Refusal::invalid(
                "frames: a sequence job names its range, not a frame",
            ));
        }
        if range.first == 0 || range.first > range.last {
            return Err(Refusal::invalid(format!(
                "frames: {}-{} is not a range of frames (from 1, first to last)",
                range.first, range.last
            )));
        }
        if range.last > frames {
            return Err(Refusal::invalid(out_of_range(range.last).to_string()));
        }
    }
    let scene = animated.base;
    let o = spec.overrides;
    let mut s = scene.settings;
    s.width = o.width.unwrap_or(s.width);
    s.height = o.height.unwrap_or(s.height);
    s.aa = o.aa.unwrap_or(s.aa);
    s.max_depth = o.max_depth.unwrap_or(s.max_depth);
    s.sampling = o.sampling.map_or(s.sampling, verify::render_sampling);
    render::validate_settings(&s, "").map_err(|e| Refusal::invalid(format!("overrides: {e}")))?;
    let settings = Settings {
        width: s.width,
        height: s.height,
        aa: s.aa,
        max_depth: s.max_depth,
        sampling: o.sampling.unwrap_or_default(),
    };
    if let Some(limit) = spec.time_limit_ms {
        if settings.sampling.target_error().is_none() {
            return Err(Refusal::invalid(format!(
                "time_limit: only adaptive jobs stop on a time limit, not {} sampling",
                settings.sampling.name()
            )));
        }
        if limit == 0 {
            return Err(Refusal::invalid("time_limit: must be more than 0 ms"));
        }
    }
    let tile_size = match o.tile_size {
        Some(t) if !(MIN_TILE..=MAX_TILE).contains(&t) => {
            return Err(Refusal::invalid(format!(
                "overrides: tile: must be between {MIN_TILE} and {MAX_TILE}, got {t}"
            )))
        }
        Some(t) => t,
        None if spec.frames.is_some() => tiling::sequence_tile_size(&settings),
        None => tiling::default_tile_size(&settings),
    };
    if settings.sampling.target_error().is_some() {
        verify::adaptive::check_tile_side(tile_size)
            .map_err(|e| Refusal::invalid(format!("overrides: tile: {e}")))?;
    }
    let hash = scene_hash(&spec.scene, &spec.assets);
    let request = lifecycle::Request {
        client: Some(client),
        scene_bytes: spec.scene.len(),
        objects: scene.objects.len(),
        width: s.width,
        height: s.height,
        aa: s.aa,
    };
    // Checked here too (the lifecycle checks again when it admits the job), so that
    // the tiles of a huge image are never cut.
    limits.check(&request)?;
    let tiles = tiling::cut(&settings, tile_size);
    Ok(Prepared {
        interactive: false,
        owner: None,
        scene: spec.scene,
        hash,
        frame: spec.frame,
        settings,
        tile_size,
        tiles,
        priority: spec.priority,
        verification: spec.verification,
        request,
        time_limit_ms: spec.time_limit_ms,
        start: None,
        label: Label {
            name: one_line(&spec.name, MAX_LABEL),
            submitter: one_line(&spec.submitter, MAX_LABEL),
            submitted_from: client.to_string(),
        },
        sequence: None,
        frames: spec.frames,
        frame_count: frames,
        assets: spec.assets,
        after: spec.after,
        require,
    })
}

/// The most characters of a job's name or submitter kept: listings stay readable and
/// a client cannot make the coordinator store much through them.
const MAX_LABEL: usize = 200;

/// `text` on one line (control characters become spaces), at most `max` characters.
fn one_line(text: &str, max: usize) -> String {
    text.chars()
        .map(|c| if c.is_control() { ' ' } else { c })
        .take(max)
        .collect::<String>()
        .trim()
        .to_owned()
}

/// The name of a refined job: `seed (refined)`, then `seed (refined 2)`, `seed (refined
/// 3)`... rather than a suffix stacked at every refine.
fn refined_name(name: &str) -> String {
    let count = |inner: &str| -> Option<u32> {
        match inner.strip_prefix("refined") {
            Some("") => Some(1),
            Some(n) => n.strip_prefix(' ')?.parse().ok().filter(|&n| n >= 2),
            None => None,
        }
    };
    let stem = name.strip_suffix(')').and_then(|rest| {
        let open = rest.rfind(" (")?;
        count(&rest[open + 2..]).map(|n| (&rest[..open], n))
    });
    match stem {
        Some((base, n)) => format!("{base} (refined {})", n + 1),
        None => format!("{name} (refined)"),
    }
}

#[cfg(test)]
mod refined_name_tests {
    use super::*;

    #[test]
    fn a_refined_name_counts_its_refines() {
        assert_eq!(refined_name("seed"), "seed (refined)");
        assert_eq!(refined_name("seed (refined)"), "seed (refined 2)");
        assert_eq!(refined_name("seed (refined 2)"), "seed (refined 3)");
        assert_eq!(refined_name("seed (refined 9)"), "seed (refined 10)");
        assert_eq!(refined_name("a (b)"), "a (b) (refined)");
        assert_eq!(refined_name("x (refined 1)"), "x (refined 1) (refined)");
        assert_eq!(refined_name("(refined)"), "(refined) (refined)");
    }
}
