//! Recording: new jobs, finished tiles and event log entries, a job's start, controls,
//! end and retry, disabled machines, and deletions. Each is one statement or one
//! transaction, made to last as the [`Durability`](super::Durability) last set says.

use anyhow::{Context, Result};
use protocol::{JobId, JobState, Sampling};
use rusqlite::{params, OptionalExtension};

use super::read::{read_job, JOB_COLUMNS};
use super::{
    tile_checksum, Db, EventWrite, ReopenError, StoredJob, TileEncoding, TileWrite, Times, Totals,
};
use crate::events::{Announcement, FarmEvent, Retention};

impl Db {
    /// Stores a new job durably.
    pub fn insert_job(&self, job: &StoredJob) -> Result<()> {
        self.conn
            .execute(
                "INSERT INTO jobs (id, scene, hash, width, height, aa, max_depth, tile_size,
                                   priority, state, error, sampler, target_milli, submitted_ms,
                                   verification, time_limit_ms, name, submitter, submitted_from,
                                   frame, last_frame, sequence, assets, after_jobs,
                                   required_tags)
                 VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11, ?12, ?13, ?14, ?15, ?16,
                         ?17, ?18, ?19, ?20, ?21, ?22, ?23, ?24, ?25)",
                params![
                    job.id as i64,
                    job.scene,
                    &job.hash[..],
                    job.settings.width,
                    job.settings.height,
                    job.settings.aa,
                    job.settings.max_depth,
                    job.tile_size,
                    job.priority,
                    job.state.as_str(),
                    job.error,
                    job.settings.sampling.name(),
                    target_milli(job.settings.sampling),
                    job.times.submitted.map(|t| t as i64),
                    job.verification.name(),
                    job.time_limit_ms.map(|t| t.min(i64::MAX as u64) as i64),
                    job.label.name,
                    job.label.submitter,
                    job.label.submitted_from,
                    job.frame,
                    job.last_frame,
                    job.sequence.map(|s| s as i64),
                    serde_json::to_string(&job.assets).context("cannot write the scene files")?,
                    serde_json::to_string(&job.after)
                        .context("cannot write the job's dependencies")?,
                    serde_json::to_string(&job.require)
                        .context("cannot write the tags the job requires")?,
                ],
            )
            .context("cannot store the job")?;
        Ok(())
    }

    /// [`Db::save_batch`] without farm events, as the tests record tiles and logs.
    #[cfg(test)]
    pub fn save_results(&mut self, tiles: &[TileWrite], events: &[EventWrite]) -> Result<()> {
        self.save_batch(tiles, events, &[], Retention::default(), 0)
            .map(drop)
    }

    /// Records finished tiles (with their checksums), event log entries and the farm's
    /// events announced meanwhile, all in one transaction, and trims the farm's events
    /// to `retention` (at `now_ms`) in it too. A log entry replaces one of the same job
    /// and number (how the marker of events not kept is updated; and a write retried
    /// after a failure changes nothing). Returns the farm's events as recorded, with
    /// their ids, once committed.
    pub fn save_batch(
        &mut self,
        tiles: &[TileWrite],
        events: &[EventWrite],
        announced: &[Announcement],
        retention: Retention,
        now_ms: u64,
    ) -> Result<Vec<FarmEvent>> {
        let tx = self.conn.transaction()?;
        insert_events(&tx, events)?;
        let recorded = super::farm_events::insert(&tx, announced, retention, now_ms)?;
        {
            let mut insert = tx.prepare_cached(
                "INSERT OR IGNORE INTO tiles (job, tile, rgb, rays, worker, samples, error_sq_sum,
                                              sha256, done_ms, encoding)
                 VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10)",
            )?;
            for t in tiles {
                insert.execute(params![
                    t.job as i64,
                    t.tile,
                    t.zstd,
                    t.rays as i64,
                    t.worker,
                    t.samples as i64,
                    t.error_sq_sum,
                    &tile_checksum(&t.zstd)[..],
                    t.done_ms as i64,
                    TileEncoding::Zstd.name(),
                ])?;
            }
        }
        tx.commit().context("cannot record finished tiles")?;
        Ok(recorded)
    }

    /// Records when the job's first tile was handed out.
    pub fn set_started(&self, job: JobId, started_ms: u64) -> Result<()> {
        self.conn
            .execute(
                "UPDATE jobs SET state = 'running', started_ms = ?2 WHERE id = ?1",
                params![job as i64, started_ms as i64],
            )
            .context("cannot record that the job started")?;
        Ok(())
    }

    /// Records that the job ended on its time limit (shown by its status after a
    /// restart).
    pub fn set_stopped_on_time_limit(&self, job: JobId) -> Result<()> {
        self.conn
            .execute(
                "UPDATE jobs SET stopped_on_time_limit = 1 WHERE id = ?1",
                params![job as i64],
            )
            .context("cannot record the job's end")?;
        Ok(())
    }

    /// Puts a failed or cancelled job back in the queue (unpaused, its end and error
    /// forgotten, retried at `now`) and returns it as stored; `None` if there is no such
    /// job. A job in another state is returned unchanged.
    pub fn reopen_job(&self, job: JobId, now: u64) -> Result<Option<StoredJob>, ReopenError> {
        self.conn
            .execute(
                "UPDATE jobs SET state = 'queued', error = NULL, ended_ms = NULL, paused = 0,
                                 total_rays = NULL, total_samples = NULL,
                                 total_error_sq_sum = NULL, total_error_pixels = NULL,
                                 retried_ms = ?2
                 WHERE id = ?1 AND state IN ('failed', 'cancelled')",
                params![job as i64, now as i64],
            )
            .context("cannot put the job back in the queue")
            .map_err(ReopenError::Storage)?;
        let found = self
            .conn
            .prepare(&format!("SELECT {JOB_COLUMNS} FROM jobs WHERE id = ?1"))
            .and_then(|mut query| {
                query
                    .query_row(params![job as i64], |r| Ok(read_job(r)))
                    .optional()
            })
            .map_err(|e| ReopenError::Storage(e.into()))?;
        match found {
            None => Ok(None),
            Some(Ok(stored)) => Ok(Some(stored)),
            Some(Err(bad)) => Err(ReopenError::BadRow(bad.what)),
        }
    }

    /// A sequence job runs again (a frame of it was requeued): its end and totals are
    /// forgotten until it ends anew.
    pub fn set_running_again(&self, job: JobId) -> Result<()> {
        self.conn
            .execute(
                "UPDATE jobs SET state = 'running', error = NULL, ended_ms = NULL,
                                 total_rays = NULL, total_samples = NULL,
                                 total_error_sq_sum = NULL, total_error_pixels = NULL
                 WHERE id = ?1",
                params![job as i64],
            )
            .context("cannot record that the sequence runs again")?;
        Ok(())
    }

    /// Records what an operator set of a running job: whether it is paused, and its
    /// priority.
    pub fn set_controls(&self, job: JobId, paused: bool, priority: i32) -> Result<()> {
        self.conn
            .execute(
                "UPDATE jobs SET paused = ?2, priority = ?3 WHERE id = ?1",
                params![job as i64, i64::from(paused), priority],
            )
            .context("cannot record the job's pause and priority")?;
        Ok(())
    }

    /// Records that an operator disabled (or enabled again) a machine, by name: it
    /// stays disabled across restarts until enabled.
    pub fn set_disabled(&self, machine: &str, disabled: bool) -> Result<()> {
        let sql = if disabled {
            "INSERT OR IGNORE INTO disabled_machines (name) VALUES (?1)"
        } else {
            "DELETE FROM disabled_machines WHERE name = ?1"
        };
        self.conn
            .execute(sql, params![machine])
            .context("cannot record the disabled machine")?;
        Ok(())
    }

    /// Records a job's end: its final state, totals, times and image checksum. A done
    /// job's tiles are no longer needed (its image is stored and verified): they are
    /// deleted, and the space they took given back. A failed or cancelled job keeps
    /// them until it is deleted, for a retry to render only the others.
    pub fn set_ended(
        &mut self,
        job: JobId,
        state: JobState,
        error: Option<&str>,
        totals: Totals,
        times: Times,
        image_sha256: Option<[u8; 32]>,
    ) -> Result<()> {
        let tx = self.conn.transaction()?;
        tx.execute(
            "UPDATE jobs SET state = ?2, error = ?3, total_rays = ?4, total_samples = ?5,
                             total_error_sq_sum = ?6, total_error_pixels = ?7,
                             started_ms = ?8, ended_ms = ?9, image_sha256 = ?10,
                             scene = CASE WHEN sequence IS NULL THEN scene ELSE '' END
             WHERE id = ?1",
            params![
                job as i64,
                state.as_str(),
                error,
                totals.rays as i64,
                totals.samples as i64,
                totals.error_sq_sum,
                totals.error_pixels as i64,
                times.started.map(|t| t as i64),
                times.ended.map(|t| t as i64),
                image_sha256.as_ref().map(|h| &h[..]),
            ],
        )?;
        // A failed or cancelled job keeps its tiles until it is deleted: a retry
        // renders only the others.
        if state == JobState::Done {
            tx.execute("DELETE FROM tiles WHERE job = ?1", params![job as i64])?;
        }
        tx.commit().context("cannot record the job's end")?;
        self.give_back_space();
        Ok(())
    }

    /// Deletes a job, its tiles and its event log.
    pub fn delete_job(&mut self, job: JobId) -> Result<()> {
        let tx = self.conn.transaction()?;
        tx.execute("DELETE FROM events WHERE job = ?1", params![job as i64])?;
        tx.execute("DELETE FROM tiles WHERE job = ?1", params![job as i64])?;
        tx.execute("DELETE FROM jobs WHERE id = ?1", params![job as i64])?;
        tx.commit().context("cannot delete the job")?;
        self.give_back_space();
        Ok(())
    }

    /// Deletes stored tiles whose results were revoked (their worker was caught
    /// returning wrong pixels): they are rendered again.
    pub fn delete_tiles(&mut self, job: JobId, tiles: &[u32]) -> Result<()> {
        let tx = self.conn.transaction()?;
        for &tile in tiles {
            tx.execute(
                "DELETE FROM tiles WHERE job = ?1 AND tile = ?2",
                params![job as i64, tile],
            )?;
        }
        tx.commit().context("cannot delete revoked tiles")?;
        Ok(())
    }

    /// Deletes one stored tile (found damaged at startup).
    pub fn delete_tile(&self, job: JobId, tile: i64) -> Result<()> {
        self.conn
            .execute(
                "DELETE FROM tiles WHERE job = ?1 AND tile = ?2",
                params![job as i64, tile],
            )
            .context("cannot delete a damaged tile")?;
        Ok(())
    }
}

/// Inserts event log entries in `tx` (see [`Db::save_batch`]).
fn insert_events(tx: &rusqlite::Transaction<'_>, events: &[EventWrite]) -> Result<()> {
    if events.is_empty() {
        return Ok(());
    }
    let mut insert = tx.prepare_cached(
        "INSERT OR REPLACE INTO events (job, seq, unix_ms, kind, detail)
         VALUES (?1, ?2, ?3, ?4, ?5)",
    )?;
    for e in events {
        insert.execute(params![
            e.job as i64,
            e.event.seq as i64,
            e.event.unix_ms as i64,
            e.event.kind,
            e.event.detail,
        ])?;
    }
    Ok(())
}

fn target_milli(sampling: Sampling) -> u32 {
    match sampling {
        Sampling::Adaptive { target_milli } => target_milli,
        Sampling::Grid | Sampling::Jittered => 0,
    }
}
