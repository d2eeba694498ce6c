//! The data directory: one folder per finished job holding its image, its scene and a
//! JSON metadata file, and `last-job-id`, above the highest job id ever issued. Every file is
//! written to a temporary name, synced and renamed, so a crash never leaves a
//! half-written file under its real name; an image is read back and its SHA-256
//! compared before it counts as stored, and compared again whenever it is served.

use std::io::{Read, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};
use std::sync::Arc;

use anyhow::{Context, Result};
use protocol::JobId;
use serde::Serialize;
use sha2::{Digest, Sha256};

/// What is stored beside each image.
#[derive(Clone, Serialize)]
pub struct JobMetadata {
    pub id: JobId,
    pub state: &'static str,
    pub scene_sha256: String,
    /// The frame of the scene rendered, from 1.
    pub frame: u32,
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
    /// When the job was submitted, first handed out, and ended (ms since the Unix epoch).
    pub submitted_unix_ms: u64,
    pub started_unix_ms: u64,
    pub ended_unix_ms: u64,
    /// The SHA-256 of `image.png`, in hex.
    pub image_sha256: String,
}

pub struct Store {
    root: PathBuf,
    /// What `last-job-id` holds (ids up to it may be issued without writing it), and the
    /// highest id issued; `None` until the file is first read.
    ids: std::sync::Mutex<Option<IdWatermark>>,
}

#[derive(Clone, Copy)]
struct IdWatermark {
    recorded: JobId,
    issued: JobId,
}

/// How many ids `last-job-id` reserves at a time: a sequence starts a frame job (a new
/// id) per frame, and two synced writes per id cost more than its frame's database
/// rows. A clean stop gives the unused ones back; after a crash, ids continue above the
/// reserved block.
pub const ID_BLOCK: JobId = 64;

/// Where a job's image is kept: a job of one frame in its own folder
/// (`jobs/ID/image.png`, `job.json`, `scene.json`); a frame job of a sequence in the
/// sequence's folder, as `jobs/SEQ/frame_0007.png` and `frame_0007.json` (named as
/// `tessera render --frames` names them, `count` being the scene's frames), beside the
/// sequence's one `scene.json`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ImagePlace {
    Job(JobId),
    Frame {
        sequence: JobId,
        frame: u32,
        count: u32,
    },
}

impl ImagePlace {
    /// The job whose folder holds the image.
    fn folder(self) -> JobId {
        match self {
            ImagePlace::Job(job) | ImagePlace::Frame { sequence: job, .. } => job,
        }
    }

    fn image_name(self) -> String {
        match self {
            ImagePlace::Job(_) => "image.png".into(),
            ImagePlace::Frame { frame, count, .. } => {
                render::frame_file_name(u64::from(frame), count)
            }
        }
    }

    fn metadata_name(self) -> String {
        match self {
            ImagePlace::Job(_) => "job.json".into(),
            ImagePlace::Frame { .. } => self.image_name().replace(".png", ".json"),
        }
    }
}

impl Store {
    /// Opens (creating if needed) the data directory.
    pub fn open(root: &Path) -> Result<Store> {
        std::fs::create_dir_all(root.join("jobs"))
            .with_context(|| format!("cannot create the data directory {}", root.display()))?;
        Ok(Store {
            root: root.to_path_buf(),
            ids: std::sync::Mutex::new(None),
        })
    }

    /// The highest job id the directory has seen: in `last-job-id` or as a job folder.
    /// Zero for a directory that never held a job.
    pub fn highest_job_id(&self) -> Result<JobId> {
        let mut highest = self.recorded_last_id()?;
        let jobs = self.root.join("jobs");
        for entry in
            std::fs::read_dir(&jobs).with_context(|| format!("cannot read {}", jobs.display()))?
        {
            if let Some(id) = entry?
                .file_name()
                .to_str()
                .and_then(|n| n.parse::<JobId>().ok())
            {
                highest = highest.max(id);
            }
        }
        Ok(highest)
    }

    fn last_id_path(&self) -> PathBuf {
        self.root.join("last-job-id")
    }

    fn recorded_last_id(&self) -> Result<JobId> {
        let path = self.last_id_path();
        match std::fs::read_to_string(&path) {
            Ok(text) => text.trim().parse().with_context(|| {
                format!(
                    "{} does not hold a job id ({:?}): write the highest job id ever issued \
                     into it, or remove it (ids then continue above the database's and the \
                     job folders')",
                    path.display(),
                    text.trim()
                )
            }),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(0),
            Err(e) => Err(e).with_context(|| format!("cannot read {}", path.display())),
        }
    }

    /// Records durably that ids up to `id` have been issued, so they are never issued
    /// again, whatever happens to the database: the file is written only when `id` is
    /// beyond it, and then reserves [`ID_BLOCK`] ids.
    pub fn record_last_id(&self, id: JobId) -> Result<()> {
        let mut ids = self.ids.lock().expect("the id watermark's lock");
        let known = match *ids {
            Some(known) => known,
            None => {
                let recorded = self.recorded_last_id().unwrap_or(0);
                IdWatermark {
                    recorded,
                    issued: recorded,
                }
            }
        };
        let mut next = IdWatermark {
            issued: known.issued.max(id),
            ..known
        };
        if known.recorded < id {
            let reserved = id.saturating_add(ID_BLOCK - 1);
            write_atomically(&self.last_id_path(), format!("{reserved}\n").as_bytes())?;
            next.recorded = reserved;
        }
        *ids = Some(next);
        Ok(())
    }

    /// At a clean stop: gives back the reserved ids not issued, so that the next start
    /// continues right after the last id issued.
    pub fn release_reserved_ids(&self) -> Result<()> {
        let mut ids = self.ids.lock().expect("the id watermark's lock");
        if let Some(known) = *ids {
            if known.recorded > known.issued {
                let issued = known.issued;
                write_atomically(&self.last_id_path(), format!("{issued}\n").as_bytes())?;
                *ids = Some(IdWatermark {
                    recorded: issued,
                    issued,
                });
            }
        }
        Ok(())
    }

    fn job_dir(&self, job: JobId) -> PathBuf {
        // Only the coordinator's own numeric ids ever become paths.
        self.root.join("jobs").join(job.to_string())
    }

    fn image_path(&self, place: ImagePlace) -> PathBuf {
        self.job_dir(place.folder()).join(place.image_name())
    }

    /// Checks the stored image of a finished job against its checksum, reading it in
    /// chunks; returns its length.
    pub fn verify_image(&self, place: ImagePlace, sha256: &[u8; 32]) -> Result<u64> {
        let path = self.image_path(place);
        let mut file = std::fs::File::open(&path)
            .with_context(|| format!("cannot read {}", path.display()))?;
        let mut hasher = Sha256::new();
        let mut buf = vec![0u8; 256 * 1024];
        let mut len = 0u64;
        loop {
            let n = file
                .read(&mut buf)
                .with_context(|| format!("cannot read {}", path.display()))?;
            if n == 0 {
                break;
            }
            hasher.update(&buf[..n]);
            len += n as u64;
        }
        let actual: [u8; 32] = hasher.finalize().into();
        anyhow::ensure!(
            &actual == sha256,
            "{} is damaged: its SHA-256 does not match the one recorded",
            path.display()
        );
        Ok(len)
    }

    /// Up to `len` bytes of a finished job's image from `offset`, and the image's size.
    pub fn read_image_chunk(
        &self,
        place: ImagePlace,
        offset: u64,
        len: usize,
    ) -> Result<(u64, Vec<u8>)> {
        let path = self.image_path(place);
        let mut file = std::fs::File::open(&path)
            .with_context(|| format!("cannot read {}", path.display()))?;
        let total = file
            .metadata()
            .with_context(|| format!("cannot read {}", path.display()))?
            .len();
        let start = offset.min(total);
        file.seek(SeekFrom::Start(start))
            .with_context(|| format!("cannot read {}", path.display()))?;
        let mut bytes = Vec::with_capacity(len.min((total - start) as usize));
        file.take(len as u64)
            .read_to_end(&mut bytes)
            .with_context(|| format!("cannot read {}", path.display()))?;
        Ok((total, bytes))
    }

    /// A finished job's whole image, checked against its checksum (when it has one):
    /// the very bytes returned are the ones hashed, so an image rewritten meanwhile (a
    /// frame rendered again) is never served unchecked.
    pub fn read_verified_image(
        &self,
        place: ImagePlace,
        sha256: Option<&[u8; 32]>,
    ) -> Result<Vec<u8>> {
        let path = self.image_path(place);
        let bytes =
            std::fs::read(&path).with_context(|| format!("cannot read {}", path.display()))?;
        if let Some(sha256) = sha256 {
            let actual: [u8; 32] = Sha256::digest(&bytes).into();
            anyhow::ensure!(
                &actual == sha256,
                "{} is damaged: its SHA-256 does not match the one recorded",
                path.display()
            );
        }
        Ok(bytes)
    }

    /// A finished job's scene, as stored beside its image.
    pub fn read_scene(&self, job: JobId) -> Result<String> {
        let path = self.job_dir(job).join("scene.json");
        std::fs::read_to_string(&path).with_context(|| format!("cannot read {}", path.display()))
    }

    fn states_path(&self, job: JobId) -> PathBuf {
        self.job_dir(job).join(STATES_FILE)
    }

    /// The final block states of a finished adaptive job, checked against the checksum
    /// they were written with. Whether they are states of the job's tiles is for the
    /// caller to check (it needs the renderer).
    pub fn read_states(&self, job: JobId) -> Result<TileStates> {
        let path = self.states_path(job);
        let bytes = match std::fs::read(&path) {
            Ok(bytes) => bytes,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => anyhow::bail!(
                "{} is missing: the job's tile states were not kept",
                path.display()
            ),
            Err(e) => return Err(e).with_context(|| format!("cannot read {}", path.display())),
        };
        TileStates::decode(&bytes)
            .map_err(|e| anyhow::anyhow!("{} is damaged: {e}", path.display()))
    }

    /// Stores a finished job: scene, image, an adaptive job's final tile states, then
    /// metadata (the metadata's presence means the job is complete). The image is read
    /// back and compared with `png`'s checksum before this returns.
    pub fn save(
        &self,
        place: ImagePlace,
        meta: &JobMetadata,
        scene: &str,
        png: &[u8],
        states: Option<&TileStates>,
    ) -> Result<[u8; 32]> {
        let dir = self.job_dir(place.folder());
        std::fs::create_dir_all(&dir)
            .with_context(|| format!("cannot create {}", dir.display()))?;
        let scene_path = dir.join("scene.json");
        // A sequence keeps one copy of its scene, written with its first frame.
        // The scene and the image are renamed into place unsynced: the metadata's
        // rename, last, syncs the folder, which makes all three durable at once.
        if matches!(place, ImagePlace::Job(_)) || !scene_path.exists() {
            replace_file(&scene_path, scene.as_bytes())?;
        }
        if let Some(states) = states {
            write_atomically(&self.states_path(meta.id), &states.encode())?;
        }
        replace_file(&self.image_path(place), png)?;
        let sha: [u8; 32] = Sha256::digest(png).into();
        self.verify_image(place, &sha)?;
        let meta = JobMetadata {
            image_sha256: sha.iter().map(|b| format!("{b:02x}")).collect(),
            ..meta.clone()
        };
        let json = serde_json::to_vec_pretty(&meta).expect("metadata serialises");
        write_atomically(&dir.join(place.metadata_name()), &json)?;
        Ok(sha)
    }

    /// Removes a job's stored files: a job's folder (a sequence's, with its frames),
    /// or a frame's image and metadata.
    pub fn delete(&self, place: ImagePlace) -> Result<()> {
        if let ImagePlace::Frame { .. } = place {
            let dir = self.job_dir(place.folder());
            for name in [place.image_name(), place.metadata_name()] {
                let path = dir.join(name);
                match std::fs::remove_file(&path) {
                    Ok(()) => {}
                    Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
                    Err(e) => {
                        return Err(e).with_context(|| format!("cannot delete {}", path.display()))
                    }
                }
            }
            return Ok(());
        }
        let dir = self.job_dir(place.folder());
        match std::fs::remove_dir_all(&dir) {
            Ok(()) => Ok(()),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(()),
            Err(e) => Err(e).with_context(|| format!("cannot delete {}", dir.display())),
        }
    }

    /// Writes and removes a small file: succeeds only when the directory can be
    /// written, which is how the daemon learns that storage is usable again.
    pub fn probe(&self) -> Result<()> {
        let path = self.root.join(".probe");
        write_atomically(&path, &[0u8; 4096])?;
        std::fs::remove_file(&path).with_context(|| format!("cannot remove {}", path.display()))
    }
}

/// The file beside a finished adaptive job's image holding its tiles' final states.
pub const STATES_FILE: &str = "states.bin";

/// The magic that opens a states file, with its format's version.
const STATES_MAGIC: &[u8; 8] = b"TSTATES1";

/// A finished adaptive job's tiles' final block states (each compressed as a worker
/// sends it) and the rung of the ladder they reached: what a refinement starts from.
///
/// On disk: the magic, the rung, aa and tile side (u32 little-endian), the number of
/// tiles (u32), then each state as a u64 length and its bytes, and last the SHA-256 of
/// everything before it, so that a flipped bit anywhere is found before use.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct TileStates {
    pub rung: u32,
    pub aa: u32,
    pub tile_size: u32,
    pub states: Vec<Arc<Vec<u8>>>,
}

impl TileStates {
    pub fn encode(&self) -> Vec<u8> {
        let mut out = Vec::new();
        out.extend_from_slice(STATES_MAGIC);
        for n in [self.rung, self.aa, self.tile_size, self.states.len() as u32] {
            out.extend_from_slice(&n.to_le_bytes());
        }
        for s in &self.states {
            out.extend_from_slice(&(s.len() as u64).to_le_bytes());
            out.extend_from_slice(s);
        }
        let sha: [u8; 32] = Sha256::digest(&out).into();
        out.extend_from_slice(&sha);
        out
    }

    pub fn decode(bytes: &[u8]) -> std::result::Result<TileStates, String> {
        let body_len = bytes
            .len()
            .checked_sub(32)
            .ok_or("shorter than its checksum")?;
        let (body, sha) = bytes.split_at(body_len);
        if Sha256::digest(body).as_slice() != sha {
            return Err("its SHA-256 does not match its contents".into());
        }
        let rest = body
            .strip_prefix(STATES_MAGIC.as_slice())
            .ok_or("not a states file")?;
        let mut at = 0usize;
        let mut take = |n: usize| -> std::result::Result<&[u8], String> {
            let end = at
                .checked_add(n)
                .filter(|&e| e <= rest.len())
                .ok_or("truncated")?;
            let slice = &rest[at..end];
            at = end;
            Ok(slice)
        };
        let mut u32_at = || -> std::result::Result<u32, String> {
            Ok(u32::from_le_bytes(take(4)?.try_into().expect("4 bytes")))
        };
        let (rung, aa, tile_size, count) = (u32_at()?, u32_at()?, u32_at()?, u32_at()?);
        let mut states = Vec::new();
        for _ in 0..count {
            let len = u64::from_le_bytes(take(8)?.try_into().expect("8 bytes"));
            let len = usize::try_from(len).map_err(|_| "truncated")?;
            states.push(Arc::new(take(len)?.to_vec()));
        }
        if at != rest.len() {
            return Err("bytes after its last state".into());
        }
        Ok(TileStates {
            rung,
            aa,
            tile_size,
            states,
        })
    }
}

/// Writes `bytes` to `path` durably: through a synced temporary file renamed into
/// place, then the folder synced.
fn write_atomically(path: &Path, bytes: &[u8]) -> Result<()> {
    replace_file(path, bytes)?;
    // The rename itself is durable only once the folder is synced.
    let dir = path.parent().expect("stored files live in a folder");
    std::fs::File::open(dir)
        .and_then(|d| d.sync_all())
        .with_context(|| format!("cannot sync {}", dir.display()))?;
    Ok(())
}

/// Writes `bytes` to a synced temporary file and renames it to `path`: a crash leaves
/// the old file or the new one, never a part. The rename is durable once the folder is
/// synced (by the caller).
fn replace_file(path: &Path, bytes: &[u8]) -> Result<()> {
    let dir = path.parent().expect("stored files live in a folder");
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_states_file_reads_back_and_any_flipped_byte_is_found() {
        let states = TileStates {
            rung: 93,
            aa: 8,
            tile_size: 32,
            states: vec![Arc::new(vec![1, 2, 3]), Arc::new(Vec::new())],
        };
        let bytes = states.encode();
        assert_eq!(TileStates::decode(&bytes), Ok(states));
        for i in 0..bytes.len() {
            let mut bad = bytes.clone();
            bad[i] ^= 0x10;
            assert!(TileStates::decode(&bad).is_err(), "byte {i}");
        }
        assert!(TileStates::decode(&bytes[..bytes.len() - 1]).is_err());
    }

    #[test]
    fn ids_are_reserved_in_blocks_and_the_unused_given_back_at_a_clean_stop() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("last-job-id");
        let read = || std::fs::read_to_string(&file).unwrap();
        let store = Store::open(dir.path()).unwrap();
        store.record_last_id(5).unwrap();
        assert_eq!(read(), format!("{}\n", 5 + ID_BLOCK - 1));
        // Ids inside the block are not written again (the file is not even read).
        std::fs::write(&file, "garbage").unwrap();
        store.record_last_id(6).unwrap();
        store.record_last_id(5 + ID_BLOCK - 1).unwrap();
        assert_eq!(read(), "garbage");
        // Beyond it: a new block.
        store.record_last_id(5 + ID_BLOCK).unwrap();
        assert_eq!(read(), format!("{}\n", 5 + 2 * ID_BLOCK - 1));
        // A crash keeps the block: the next start continues above it.
        let crashed = Store::open(dir.path()).unwrap();
        assert_eq!(crashed.highest_job_id().unwrap(), 5 + 2 * ID_BLOCK - 1);
        // A clean stop gives back what was not issued.
        store.release_reserved_ids().unwrap();
        assert_eq!(read(), format!("{}\n", 5 + ID_BLOCK));
        let restarted = Store::open(dir.path()).unwrap();
        assert_eq!(restarted.highest_job_id().unwrap(), 5 + ID_BLOCK);
        // Nothing issued by a store: nothing written.
        restarted.release_reserved_ids().unwrap();
        assert_eq!(read(), format!("{}\n", 5 + ID_BLOCK));
    }

    #[test]
    fn a_verified_image_is_served_only_when_its_checksum_matches() {
        let dir = tempfile::tempdir().unwrap();
        let store = Store::open(dir.path()).unwrap();
        let place = ImagePlace::Frame {
            sequence: 4,
            frame: 2,
            count: 10,
        };
        let path = store.image_path(place);
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        std::fs::write(&path, b"frame two").unwrap();
        assert!(path.ends_with("jobs/4/frame_0002.png"));
        let sha: [u8; 32] = Sha256::digest(b"frame two").into();
        assert_eq!(
            store.read_verified_image(place, Some(&sha)).unwrap(),
            b"frame two"
        );
        assert_eq!(
            store.read_verified_image(place, None).unwrap(),
            b"frame two"
        );
        std::fs::write(&path, b"frame 2wo").unwrap();
        let error = store.read_verified_image(place, Some(&sha)).unwrap_err();
        assert!(error.to_string().contains("is damaged"), "{error}");
        assert!(store.read_verified_image(ImagePlace::Job(9), None).is_err());
    }
}
