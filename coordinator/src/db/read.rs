//! Reading rows back: jobs, tiles, event logs and disabled machines. Nothing read is
//! trusted: every row is checked here (its checksum, its length, the names and numbers
//! it holds) beside the column order those checks depend on, and one that fails comes
//! back on its own as a [`BadRow`] instead of failing the whole load.

use std::collections::BTreeMap;

use anyhow::{Context, Result};
use protocol::{JobEvent, JobId, JobState, Sampling, Settings, Verification};
use rusqlite::{params, OptionalExtension};

use super::{tile_checksum, BadRow, Db, Label, StoredJob, StoredTile, TileEncoding, Times, Totals};

impl Db {
    /// The largest job id stored.
    pub fn max_job_id(&self) -> Result<JobId> {
        let max: Option<i64> = self
            .conn
            .query_row("SELECT MAX(id) FROM jobs", [], |r| r.get(0))
            .optional()?
            .flatten();
        Ok(max.map_or(0, |m| m.max(0) as JobId))
    }

    /// The machines an operator disabled, by name.
    pub fn load_disabled(&self) -> Result<Vec<String>> {
        let mut statement = self
            .conn
            .prepare("SELECT name FROM disabled_machines ORDER BY name")
            .context("cannot read the disabled machines")?;
        let names = statement
            .query_map([], |r| r.get::<_, String>(0))?
            .collect::<Result<Vec<_>, _>>()
            .context("cannot read the disabled machines")?;
        Ok(names)
    }

    /// The job's events numbered above `after`, oldest first, at most `limit`.
    pub fn load_events(&self, job: JobId, after: u64, limit: usize) -> Result<Vec<JobEvent>> {
        let mut query = self.conn.prepare_cached(
            "SELECT seq, unix_ms, kind, detail FROM events
             WHERE job = ?1 AND seq > ?2 ORDER BY seq LIMIT ?3",
        )?;
        let rows = query
            .query_map(
                params![job as i64, after.min(i64::MAX as u64) as i64, limit as i64],
                |r| {
                    Ok(JobEvent {
                        seq: r.get::<_, i64>(0)?.max(0) as u64,
                        unix_ms: r.get::<_, i64>(1)?.max(0) as u64,
                        kind: r.get(2)?,
                        detail: r.get(3)?,
                    })
                },
            )?
            .collect::<rusqlite::Result<Vec<_>>>()
            .context("cannot read the job's events")?;
        Ok(rows)
    }

    /// Where each job's event log stands, by job: its highest number, and the count
    /// of entries not kept that its `not_kept` marker gives (0 without one).
    pub fn event_positions(&self) -> Result<BTreeMap<JobId, (u64, u64)>> {
        let mut query = self.conn.prepare(
            "SELECT job, MAX(seq),
                    MAX(CASE WHEN kind = 'not_kept' THEN detail ELSE '' END)
             FROM events GROUP BY job",
        )?;
        let rows = query
            .query_map([], |r| {
                let marker: String = r.get(2)?;
                let dropped = marker
                    .split(' ')
                    .next()
                    .and_then(|n| n.parse().ok())
                    .unwrap_or(0);
                Ok((
                    r.get::<_, i64>(0)?.max(0) as JobId,
                    (r.get::<_, i64>(1)?.max(0) as u64, dropped),
                ))
            })?
            .collect::<rusqlite::Result<BTreeMap<_, _>>>()
            .context("cannot read the job event logs")?;
        Ok(rows)
    }

    /// How many tiles of the job are stored. For a job that ended unfinished (cancelled
    /// or failed) this is its progress, kept across restarts: the tiles a retry keeps.
    pub fn count_tiles(&self, job: JobId) -> Result<u32> {
        let count: i64 = self
            .conn
            .query_row(
                "SELECT COUNT(*) FROM tiles WHERE job = ?1",
                params![job as i64],
                |r| r.get(0),
            )
            .context("cannot count the job's stored tiles")?;
        Ok(u32::try_from(count).unwrap_or(u32::MAX))
    }

    /// Every stored job. A row that cannot be read (a damaged database) is returned as
    /// a [`BadRow`] instead of failing the whole load.
    pub fn load_jobs(&self) -> Result<Vec<Result<StoredJob, BadRow>>> {
        let mut query = self
            .conn
            .prepare(&format!("SELECT {JOB_COLUMNS} FROM jobs ORDER BY id"))?;
        let rows = query
            .query_map([], |r| Ok(read_job(r)))?
            .map(|row| row.unwrap_or_else(|e| Err(bad(format!("unreadable job row: {e}")))))
            .collect();
        Ok(rows)
    }

    /// The job's stored tiles whose checksum matches, their pixels decoded;
    /// `tile_bytes` gives the size of each tile's pixels (`None`: the job has no such
    /// tile), so that a compressed row expands to that size at most. The other rows are
    /// returned as [`BadRow`]s with their tile number (when readable), to be deleted and
    /// rendered again.
    pub fn load_tiles(
        &self,
        job: JobId,
        tile_bytes: impl Fn(u32) -> Option<usize>,
    ) -> Result<Vec<Result<StoredTile, BadRow>>> {
        let mut query = self.conn.prepare(
            "SELECT tile, rgb, rays, worker, samples, error_sq_sum, sha256, done_ms, encoding
             FROM tiles WHERE job = ?1 ORDER BY tile",
        )?;
        let rows = query
            .query_map(params![job as i64], |r| Ok(read_tile(r, &tile_bytes)))?
            .map(|row| row.unwrap_or_else(|e| Err(bad(format!("unreadable tile row: {e}")))))
            .collect();
        Ok(rows)
    }
}

/// The columns [`read_job`] reads, in its order.
pub(super) const JOB_COLUMNS: &str =
    "id, scene, hash, width, height, aa, max_depth, tile_size, priority,
    state, error, sampler, target_milli, total_rays, total_samples, total_error_sq_sum,
    total_error_pixels, submitted_ms, started_ms, ended_ms, image_sha256, verification,
    time_limit_ms, stopped_on_time_limit, paused, name, submitter, submitted_from, frame,
    last_frame, sequence, retried_ms, assets, after_jobs, required_tags";

fn bad(what: String) -> BadRow {
    BadRow { what, tile: None }
}

fn bad_tile(tile: i64, what: String) -> BadRow {
    BadRow {
        what,
        tile: Some(tile),
    }
}

pub(super) fn read_job(r: &rusqlite::Row<'_>) -> Result<StoredJob, BadRow> {
    let id: i64 = r.get(0).map_err(|e| bad(format!("job id: {e}")))?;
    let field = |e: rusqlite::Error| bad(format!("job {id}: {e}"));
    let hash: Vec<u8> = r.get(2).map_err(field)?;
    let state: String = r.get(9).map_err(field)?;
    let sampler: String = r.get(11).map_err(field)?;
    let totals = match (
        r.get::<_, Option<i64>>(13).map_err(field)?,
        r.get::<_, Option<i64>>(14).map_err(field)?,
        r.get::<_, Option<f64>>(15).map_err(field)?,
        r.get::<_, Option<i64>>(16).map_err(field)?,
    ) {
        (Some(rays), Some(samples), Some(error_sq_sum), Some(error_pixels)) => Some(Totals {
            rays: rays.max(0) as u64,
            samples: samples.max(0) as u64,
            error_sq_sum,
            error_pixels: error_pixels.max(0) as u64,
        }),
        _ => None,
    };
    let time = |i: usize| -> Result<Option<u64>, BadRow> {
        Ok(r.get::<_, Option<i64>>(i)
            .map_err(field)?
            .map(|t| t.max(0) as u64))
    };
    let image_sha256 = match r.get::<_, Option<Vec<u8>>>(20).map_err(field)? {
        None => None,
        Some(h) => Some(
            <[u8; 32]>::try_from(h.as_slice())
                .map_err(|_| bad(format!("job {id}: an image checksum of {} bytes", h.len())))?,
        ),
    };
    let verification: String = r.get(21).map_err(field)?;
    let verification = match verification.as_str() {
        "sampled" => Verification::Sampled,
        "full" => Verification::Full,
        other => return Err(bad(format!("job {id}: unknown verification {other:?}"))),
    };
    let time_limit_ms = time(22)?;
    let stopped_on_time_limit = r.get::<_, i64>(23).map_err(field)? != 0;
    let paused = r.get::<_, i64>(24).map_err(field)? != 0;
    let label = Label {
        name: r.get(25).map_err(field)?,
        submitter: r.get(26).map_err(field)?,
        submitted_from: r.get(27).map_err(field)?,
    };
    let frame: u32 = r.get(28).map_err(field)?;
    if frame == 0 {
        return Err(bad(format!(
            "job {id}: frame 0 (frames are numbered from 1)"
        )));
    }
    let last_frame: Option<u32> = r.get(29).map_err(field)?;
    if last_frame.is_some_and(|last| last < frame) {
        return Err(bad(format!(
            "job {id}: a sequence whose last frame comes before its first"
        )));
    }
    let sequence = r
        .get::<_, Option<i64>>(30)
        .map_err(field)?
        .map(|s| JobId::try_from(s).map_err(|_| bad(format!("job {id}: sequence {s}"))))
        .transpose()?;
    let assets: String = r.get(32).map_err(field)?;
    let assets = serde_json::from_str(&assets)
        .map_err(|e| bad(format!("job {id}: unreadable scene files: {e}")))?;
    let after: String = r.get(33).map_err(field)?;
    let after: Vec<JobId> = serde_json::from_str(&after)
        .map_err(|e| bad(format!("job {id}: unreadable dependencies: {e}")))?;
    let require: String = r.get(34).map_err(field)?;
    let require: Vec<String> = serde_json::from_str(&require)
        .map_err(|e| bad(format!("job {id}: unreadable required tags: {e}")))?;
    // Checked as a submission's are: a row edited by hand cannot put a tag in that
    // listings and metrics could not show.
    let require =
        protocol::check_tags(&require).map_err(|e| bad(format!("job {id}: required tags: {e}")))?;
    Ok(StoredJob {
        after,
        require,
        assets,
        frame,
        last_frame,
        sequence,
        paused,
        label,
        verification,
        time_limit_ms,
        stopped_on_time_limit,
        id: JobId::try_from(id).map_err(|_| bad(format!("job id {id}")))?,
        scene: r.get(1).map_err(field)?,
        hash: hash
            .try_into()
            .map_err(|_| bad(format!("job {id}: a scene hash that is not 32 bytes")))?,
        settings: Settings {
            width: r.get(3).map_err(field)?,
            height: r.get(4).map_err(field)?,
            aa: r.get(5).map_err(field)?,
            max_depth: r.get(6).map_err(field)?,
            sampling: parse_sampling(&sampler, r.get(12).map_err(field)?)
                .ok_or_else(|| bad(format!("job {id}: unknown sampler {sampler:?}")))?,
        },
        tile_size: r.get(7).map_err(field)?,
        priority: r.get(8).map_err(field)?,
        state: parse_state(&state)
            .ok_or_else(|| bad(format!("job {id}: unknown state {state:?}")))?,
        error: r.get(10).map_err(field)?,
        totals,
        times: Times {
            submitted: time(17)?,
            started: time(18)?,
            ended: time(19)?,
            retried: time(31)?,
        },
        image_sha256,
    })
}

fn read_tile(
    r: &rusqlite::Row<'_>,
    tile_bytes: impl Fn(u32) -> Option<usize>,
) -> Result<StoredTile, BadRow> {
    let tile: i64 = r.get(0).map_err(|e| bad(format!("tile number: {e}")))?;
    let field = |e: rusqlite::Error| bad_tile(tile, format!("tile {tile}: {e}"));
    let stored: Vec<u8> = r.get(1).map_err(field)?;
    let sha: Option<Vec<u8>> = r.get(6).map_err(field)?;
    // Tiles recorded by an earlier version carry no checksum; their length is still
    // checked against the tile's rectangle by the caller.
    if let Some(sha) = sha {
        if sha.as_slice() != tile_checksum(&stored) {
            return Err(bad_tile(
                tile,
                format!("tile {tile}: its pixels do not match their checksum"),
            ));
        }
    }
    let tile_number =
        u32::try_from(tile).map_err(|_| bad_tile(tile, format!("tile number {tile}")))?;
    let encoding: String = r.get(8).map_err(field)?;
    let rgb = match TileEncoding::parse(&encoding) {
        Some(TileEncoding::Raw) => stored,
        Some(TileEncoding::Zstd) => {
            let Some(capacity) = tile_bytes(tile_number) else {
                return Err(bad_tile(
                    tile,
                    format!("tile {tile}: the job has no such tile"),
                ));
            };
            zstd::bulk::decompress(&stored, capacity).map_err(|e| {
                bad_tile(
                    tile,
                    format!("tile {tile}: its compressed pixels do not decompress: {e}"),
                )
            })?
        }
        None => {
            return Err(bad_tile(
                tile,
                format!("tile {tile}: unknown pixel encoding {encoding:?}"),
            ))
        }
    };
    Ok(StoredTile {
        tile: tile_number,
        rgb,
        rays: r.get::<_, i64>(2).map_err(field)?.max(0) as u64,
        worker: r.get(3).map_err(field)?,
        samples: r
            .get::<_, Option<i64>>(4)
            .map_err(field)?
            .map(|n| n.max(0) as u64),
        error_sq_sum: r.get(5).map_err(field)?,
        done_ms: r
            .get::<_, Option<i64>>(7)
            .map_err(field)?
            .map(|t| t.max(0) as u64),
    })
}

fn parse_sampling(name: &str, target_milli: u32) -> Option<Sampling> {
    match name {
        "grid" => Some(Sampling::Grid),
        "jittered" => Some(Sampling::Jittered),
        "adaptive" => Some(Sampling::Adaptive { target_milli }),
        _ => None,
    }
}

fn parse_state(name: &str) -> Option<JobState> {
    match name {
        "queued" => Some(JobState::Queued),
        "running" => Some(JobState::Running),
        "done" => Some(JobState::Done),
        "failed" => Some(JobState::Failed),
        "cancelled" => Some(JobState::Cancelled),
        _ => None,
    }
}
