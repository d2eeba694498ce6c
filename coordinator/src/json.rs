//! The JSON objects of a job's status and a worker's, as `tessera ... --json` prints
//! them and the HTTP API (`/api/v1`) answers them: built here once, so that a script
//! reading either reads the same fields.

use protocol::{FrameProgress, JobStatus, WorkerStatus};
use serde_json::{json, Value};

/// The state shown for a job: its lifecycle state, or "paused".
pub fn shown_state(s: &JobStatus) -> &'static str {
    if s.paused && !s.state.is_final() {
        "paused"
    } else {
        s.state.as_str()
    }
}

/// A job's status as the `--json` output of the job commands gives it.
pub fn status_json(s: &JobStatus) -> Value {
    json!({
        "id": s.id,
        "state": shown_state(s),
        "paused": s.paused,
        "frame": s.frame,
        "width": s.settings.width,
        "height": s.settings.height,
        "aa": s.settings.aa,
        "max_depth": s.settings.max_depth,
        "priority": s.priority,
        "tiles_done": s.tiles_done,
        "tiles_total": s.tiles_total,
        "rays": s.rays,
        "elapsed_ms": s.elapsed_ms,
        "eta_ms": s.eta_ms,
        "error": s.error,
        "sampler": s.settings.sampling.name(),
        "target_error": s.settings.sampling.target_error(),
        "samples": s.samples,
        // The mean over the whole image (a sequence's per pixel of a frame), once done.
        "samples_per_pixel": s.samples_per_pixel(),
        "estimated_error": s.estimated_error,
        "time_limit_ms": s.time_limit_ms,
        "stopped_on_time_limit": s.stopped_on_time_limit,
        "warning": s.warning,
        "name": s.name,
        "submitter": s.submitter,
        "submitted_from": s.submitted_from,
        "submitted_unix_ms": s.submitted_unix_ms,
        "queued_ms": s.queued_ms,
        "sequence": s.sequence,
        "frames": s.frames.as_ref().map(frames_json),
        "assets": { "files": s.assets.files, "bytes": s.assets.bytes },
        "after": s.after,
        "waiting_for": s.waiting_for,
        "require": s.require,
    })
}

/// A sequence's frames as JSON.
fn frames_json(f: &FrameProgress) -> Value {
    let failures: Vec<Value> = f
        .failures
        .iter()
        .map(|x| json!({ "frame": x.frame, "job": x.job, "error": x.error }))
        .collect();
    json!({
        "first": f.first,
        "last": f.last,
        "done": f.done,
        "active": f.active,
        "pending": f.pending,
        "cancelled": f.cancelled,
        "failed": f.failed,
        "done_prefix": f.done_prefix,
        "failures": failures,
    })
}

/// A worker as `tessera workers --json` lists it.
pub fn worker_json(w: &WorkerStatus) -> Value {
    json!({
        "id": w.id,
        "name": w.name,
        "threads": w.threads,
        "tiles_in_flight": w.tiles_in_flight,
        "tiles_done": w.tiles_done,
        "rays": w.rays,
        "connected_ms": w.connected_ms,
        "rays_per_second": w.rays_per_second,
        "build": w.build,
        "quarantined": w.quarantined,
        "rtt_us": w.rtt_us,
        "credit": w.credit,
        "draining": w.draining,
        "disabled": w.disabled,
        "unresponsive": w.unresponsive,
        "key": w.key.map(|k| json!({ "id": k.id.to_string(), "standing": k.standing.as_str() })),
        "host": w.host,
        "cache": w.cache.as_ref().map(|c| json!({
            "files": c.files,
            "bytes": c.bytes,
            "capacity": c.capacity,
            "fetching": c.fetching,
            "fetching_received": c.fetching_received,
            "fetching_total": c.fetching_total,
            "fetched_bytes": c.fetched_bytes,
            "geometry_triangles": c.geometry_triangles,
            "problem": c.problem,
        })),
        "tags": w.tags,
    })
}
