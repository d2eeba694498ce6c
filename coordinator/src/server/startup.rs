//! Opening the data directory: nothing on disk is trusted without a check.
//!
//! - A directory that has held jobs (a `last-job-id` file or job folders) must still
//!   have its database: a missing, empty or unreadable `tessera.db` stops the start
//!   with a message that names the file and what to do (restore it, or
//!   `--reset-database`, which sets the bad file aside and starts a new one). A silent
//!   empty start would lose the queue and reuse job ids.
//! - Job ids continue above every id ever issued: the database's, the job folders' and
//!   `last-job-id`'s, whichever is highest.
//! - A row that cannot be read, a scene whose hash does not match, a tile whose pixels
//!   fail their checksum or do not fit its rectangle: each is reported in one log line
//!   and dropped (a dropped tile is rendered again; a job whose scene is damaged
//!   fails, saying so). Nothing here panics on what it reads.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use protocol::{JobId, JobState};
use tracing::{info, warn};

use crate::db::{Db, StoredJob, StoredTile, Times, Totals};
use crate::store::Store;
use crate::tiling;

/// The data directory, checked, with the jobs to take back.
pub struct Opened {
    pub db: Db,
    pub db_path: PathBuf,
    pub store: Store,
    /// Above every id ever issued.
    pub next_id: JobId,
    pub jobs: Vec<RestoredJob>,
    /// Machines an operator disabled: they stay so across restarts.
    pub disabled: Vec<String>,
}

/// A stored job and, if it is unfinished, its valid tiles.
pub struct RestoredJob {
    pub job: StoredJob,
    pub tiles: Vec<StoredTile>,
    /// Its event log: the number of its last entry (0: none), and how many entries
    /// its marker says were not kept.
    pub last_event: (u64, u64),
    /// How many tiles a cancelled or failed job has stored: its progress when it
    /// ended, shown again after a restart (and what a retry keeps). 0 for the others,
    /// whose progress is `tiles` (unfinished) or all of them (done).
    pub stored_tiles: u32,
}

pub fn open(data: &Path, reset: bool) -> Result<Opened> {
    let store = Store::open(data)?;
    let highest = store.highest_job_id()?;
    let db_path = data.join("tessera.db");
    let advice = |problem: &str| {
        format!(
            "the job database {} {problem}, but {} has held jobs (ids up to {highest}): \
             restore it, or start with --reset-database to begin a new one (unfinished jobs \
             are lost; new ids continue after {highest})",
            db_path.display(),
            data.display()
        )
    };
    let problem = match std::fs::metadata(&db_path) {
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            (highest > 0).then(|| "is missing".to_owned())
        }
        Err(e) => Some(format!("cannot be read ({e})")),
        Ok(m) if m.len() == 0 => (highest > 0).then(|| "is empty".to_owned()),
        Ok(_) => None,
    };
    let fresh = std::fs::metadata(&db_path).map_or(true, |m| m.len() == 0);
    let opened = match problem {
        Some(problem) => Err(advice(&problem)),
        None => Db::open(&db_path, fresh)
            .and_then(|db| db.load_jobs().map(|rows| (db, rows)))
            .map_err(|e| advice(&format!("is not a readable job database ({e:#})"))),
    };
    let (mut db, rows) = match opened {
        Ok(opened) => opened,
        Err(message) if !reset => bail!(message),
        Err(message) => {
            warn!(error = %message, "--reset-database: starting a new job database");
            set_aside(&db_path)?;
            let db = Db::open(&db_path, true)?;
            (db, Vec::new())
        }
    };
    let mut jobs = Vec::new();
    let mut highest = highest;
    // A log that cannot be read only costs its numbering: it starts again at 1 (and
    // its new entries replace the old ones).
    let positions = db.event_positions().unwrap_or_else(|e| {
        warn!(error = %format!("{e:#}"), "cannot read the job event logs");
        Default::default()
    });
    for row in rows {
        match row {
            Ok(job) => {
                highest = highest.max(job.id);
                let last_event = positions.get(&job.id).copied().unwrap_or((0, 0));
                if let Some(mut job) = check_job(&mut db, job)? {
                    job.last_event = last_event;
                    jobs.push(job);
                }
            }
            Err(bad) => warn!(error = %bad.what, "skipping a damaged job row"),
        }
    }
    highest = highest.max(db.max_job_id().unwrap_or(0));
    let disabled = db.load_disabled()?;
    if highest > 0 {
        store
            .record_last_id(highest)
            .context("cannot record the highest job id")?;
    }
    Ok(Opened {
        db,
        db_path,
        store,
        next_id: highest
            .checked_add(1)
            .context("every job id has been issued: this data directory can take no more jobs")?,
        jobs,
        disabled,
    })
}

/// Moves a bad database (and its journal files) aside rather than deleting it.
fn set_aside(db_path: &Path) -> Result<()> {
    let stamp = super::unix_ms();
    for suffix in ["", "-wal", "-shm"] {
        let path = PathBuf::from(format!("{}{suffix}", db_path.display()));
        if path.exists() {
            let aside = PathBuf::from(format!("{}.damaged-{stamp}", path.display()));
            std::fs::rename(&path, &aside).with_context(|| {
                format!(
                    "cannot move {} aside to {}",
                    path.display(),
                    aside.display()
                )
            })?;
            info!(from = %path.display(), to = %aside.display(), "set the old database aside");
        }
    }
    Ok(())
}

/// Checks a stored job and loads the tiles of an unfinished one; a job that cannot be
/// rendered any more is recorded as failed.
pub(super) fn check_job(db: &mut Db, job: StoredJob) -> Result<Option<RestoredJob>> {
    let id = job.id;
    let s = &job.settings;
    let sane = s.width > 0
        && s.height > 0
        && s.aa > 0
        && (tiling::MIN_TILE..=tiling::MAX_TILE).contains(&job.tile_size)
        && u64::from(s.width) * u64::from(s.height) <= 1 << 30;
    if !sane {
        warn!(job = id, "skipping a job row with impossible settings");
        return Ok(None);
    }
    if job.state.is_final() {
        // Only a figure: a count that cannot be read shows no progress rather than
        // stopping the start.
        let stored_tiles = if matches!(job.state, JobState::Cancelled | JobState::Failed) {
            db.count_tiles(id).unwrap_or_else(|e| {
                warn!(job = id, error = %format!("{e:#}"), "cannot count the job's stored tiles");
                0
            })
        } else {
            0
        };
        return Ok(Some(RestoredJob {
            job,
            tiles: Vec::new(),
            last_event: (0, 0),
            stored_tiles,
        }));
    }
    // A scene that names files is known by its text and its files together (the hash
    // the job was accepted under and its workers check).
    let hash = protocol::scene_hash(&job.scene, &job.assets);
    let damaged = if hash != job.hash {
        Some("its stored scene does not match its hash".to_owned())
    } else if !job.assets.is_empty() {
        // Its files are in the store, not at hand here: parsed without them the scene
        // would be refused for naming them. The hash above proves the text and the
        // files' identities are those accepted; the store checks each file's bytes when
        // it is read, and a file gone makes the job's tiles fail with its name.
        None
    } else {
        match render::parse_animated(&job.scene) {
            Err(e) => Some(format!("its stored scene no longer parses: {e}")),
            Ok(scene) => scene
                .frame(u64::from(job.frame))
                .err()
                .map(|e| format!("its stored scene lacks its frame: {e}")),
        }
    };
    if let Some(reason) = damaged {
        let message = format!("job {id} cannot be resumed: {reason}");
        warn!(job = id, error = %message, "failing a damaged job");
        let times = Times {
            ended: Some(super::unix_ms()),
            ..job.times
        };
        db.set_ended(
            id,
            JobState::Failed,
            Some(&message),
            Totals::default(),
            times,
            None,
        )?;
        return Ok(Some(RestoredJob {
            job: StoredJob {
                state: JobState::Failed,
                error: Some(message),
                times,
                ..job
            },
            tiles: Vec::new(),
            last_event: (0, 0),
            stored_tiles: 0,
        }));
    }
    let rects = tiling::cut(&job.settings, job.tile_size);
    let mut tiles = Vec::new();
    let tile_bytes = |t: u32| {
        rects
            .get(t as usize)
            .map(|r| r.width as usize * r.height as usize * 3)
    };
    for row in db.load_tiles(id, tile_bytes)? {
        let (number, why) = match row {
            Ok(t) => match rects.get(t.tile as usize) {
                Some(r) if t.rgb.len() == r.width as usize * r.height as usize * 3 => {
                    tiles.push(t);
                    continue;
                }
                Some(_) => (
                    Some(i64::from(t.tile)),
                    format!(
                        "tile {}: {} bytes of pixels for its rectangle",
                        t.tile,
                        t.rgb.len()
                    ),
                ),
                None => (
                    Some(i64::from(t.tile)),
                    format!("tile {}: the job has {} tiles", t.tile, rects.len()),
                ),
            },
            Err(bad) => (bad.tile, bad.what),
        };
        warn!(job = id, error = %why, "dropping a damaged stored tile: it is rendered again");
        if let Some(number) = number {
            db.delete_tile(id, number)?;
        }
    }
    Ok(Some(RestoredJob {
        job,
        tiles,
        last_event: (0, 0),
        stored_tiles: 0,
    }))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_damaged_id_watermark_stops_the_start_and_says_what_to_do() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("last-job-id"), "garbage\n").unwrap();
        let error = format!("{:#}", open(dir.path(), false).err().unwrap());
        assert!(
            error.contains("last-job-id does not hold a job id"),
            "{error}"
        );
        assert!(error.contains("remove it"), "{error}");
    }

    /// A job whose scene names files is known by its text and its files: restored,
    /// not failed as damaged (its hash is not its text's alone, and its scene does not
    /// parse without its files).
    #[test]
    fn a_job_whose_scene_names_files_is_restored() {
        let dir = tempfile::tempdir().unwrap();
        let mut db = Db::open(&dir.path().join("jobs.db"), true).unwrap();
        let mut job = crate::db::tests::job(5, protocol::Sampling::Grid);
        job.scene = r#"{"camera": {"position": "0 0 -5", "look_at": "0 0 0"},
            "objects": [{"type": "mesh", "file": "cube.obj", "color": "1 1 1 0"}]}"#
            .into();
        job.assets = vec![protocol::AssetRef {
            name: "cube.obj".into(),
            key: protocol::AssetKey {
                sha256: [3; 32],
                size: 120,
            },
        }];
        job.hash = protocol::scene_hash(&job.scene, &job.assets);
        db.insert_job(&job).unwrap();
        let restored = check_job(&mut db, job).unwrap().unwrap();
        assert_eq!(
            restored.job.state,
            JobState::Queued,
            "{:?}",
            restored.job.error
        );
    }

    #[test]
    fn ids_continue_above_the_watermark_and_cannot_overflow() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("last-job-id"), "41\n").unwrap();
        let opened = open(dir.path(), true).unwrap();
        assert_eq!(opened.next_id, 42);
        drop(opened);
        std::fs::write(dir.path().join("last-job-id"), format!("{}\n", u64::MAX)).unwrap();
        let error = format!("{:#}", open(dir.path(), true).err().unwrap());
        assert!(error.contains("every job id has been issued"), "{error}");
    }
}
