//! The data directory: one folder per finished job holding its image, its scene and a
//! JSON metadata file. Every file is written to a temporary name and renamed, so a
//! crash never leaves a half-written file under its real name.

use std::io::Write;
use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use protocol::JobId;
use serde::Serialize;

/// What is stored beside each image.
#[derive(Serialize)]
pub struct JobMetadata {
    pub id: JobId,
    pub state: &'static str,
    pub scene_sha256: String,
    pub width: u32,
    pub height: u32,
    pub aa: u32,
    pub max_depth: u32,
    pub tile_size: u32,
    pub tiles: u32,
    pub priority: i32,
    pub wall_time_ms: u64,
    pub rays: u64,
    pub rays_per_second: f64,
    /// Tiles rendered by each worker, by worker name.
    pub tiles_per_worker: std::collections::BTreeMap<String, u64>,
    /// `grid`, `jittered` or `adaptive`.
    pub sampler: &'static str,
    /// The adaptive target in 8-bit levels (absent for the other samplers).
    pub target_error: Option<f64>,
    /// Camera samples taken, in total and per pixel on average.
    pub samples: u64,
    pub samples_per_pixel: f64,
    /// The renderer's RMS error estimate in 8-bit levels (absent with one sample per
    /// pixel).
    pub estimated_error: Option<f64>,
}

pub struct Store {
    root: PathBuf,
}

impl Store {
    /// Opens (creating if needed) the data directory.
    pub fn open(root: &Path) -> Result<Store> {
        std::fs::create_dir_all(root.join("jobs"))
            .with_context(|| format!("cannot create the data directory {}", root.display()))?;
        Ok(Store {
            root: root.to_path_buf(),
        })
    }

    /// The first job id not used by a job already in the directory, so ids stay
    /// unique across restarts.
    pub fn next_job_id(&self) -> Result<JobId> {
        let mut next = 1;
        for entry in std::fs::read_dir(self.root.join("jobs"))? {
            if let Some(id) = entry?
                .file_name()
                .to_str()
                .and_then(|n| n.parse::<JobId>().ok())
            {
                next = next.max(id + 1);
            }
        }
        Ok(next)
    }

    fn job_dir(&self, job: JobId) -> PathBuf {
        // Only the coordinator's own numeric ids ever become paths.
        self.root.join("jobs").join(job.to_string())
    }

    /// The stored image of a finished job.
    pub fn read_image(&self, job: JobId) -> Result<Vec<u8>> {
        let path = self.job_dir(job).join("image.png");
        std::fs::read(&path).with_context(|| format!("cannot read {}", path.display()))
    }

    /// Stores a finished job: scene, image, then metadata (the metadata's presence
    /// means the job is complete).
    pub fn save(&self, meta: &JobMetadata, scene: &str, png: &[u8]) -> Result<()> {
        let dir = self.job_dir(meta.id);
        std::fs::create_dir_all(&dir)
            .with_context(|| format!("cannot create {}", dir.display()))?;
        write_atomically(&dir.join("scene.json"), scene.as_bytes())?;
        write_atomically(&dir.join("image.png"), png)?;
        let json = serde_json::to_vec_pretty(meta).expect("metadata serialises");
        write_atomically(&dir.join("job.json"), &json)?;
        Ok(())
    }
}

fn write_atomically(path: &Path, bytes: &[u8]) -> Result<()> {
    let dir = path.parent().expect("stored files live in a job folder");
    let mut tmp = tempfile::NamedTempFile::new_in(dir)
        .with_context(|| format!("cannot write {}", path.display()))?;
    tmp.write_all(bytes)
        .and_then(|()| tmp.as_file().sync_all())
        .with_context(|| format!("cannot write {}", path.display()))?;
    tmp.persist(path)
        .map_err(|e| e.error)
        .with_context(|| format!("cannot write {}", path.display()))?;
    Ok(())
}
