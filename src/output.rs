//! Writing result files so that a failure never leaves a partial one behind.

use std::io::Write;
use std::path::{Path, PathBuf};

use anyhow::{anyhow, bail, Context, Result};

/// `scenes/seed.json` renders to `./seed.png`.
pub fn default_output(scene: &Path) -> PathBuf {
    let stem = scene
        .file_stem()
        .map_or_else(|| "render".into(), |s| s.to_string_lossy().into_owned());
    PathBuf::from(format!("{stem}.png"))
}

/// An image still to be written: checked before any rendering, so that a render is
/// never thrown away for a file name that cannot be written.
///
/// Tessera writes PNG only: a name with another extension (`out.jpg`) is refused, not
/// silently given PNG bytes.
pub struct ImageOutput(FileOutput);

impl ImageOutput {
    /// Checks that `path` names a PNG file that can be written, by creating (and
    /// removing) a temporary file beside it, as the image will be written.
    pub fn create(path: &Path) -> Result<ImageOutput> {
        let png = path
            .extension()
            .is_some_and(|e| e.eq_ignore_ascii_case("png"));
        if !png {
            bail!(
                "{}: tessera writes PNG images only: give a file name ending in .png",
                path.display()
            );
        }
        Ok(ImageOutput(FileOutput::create(path)?))
    }

    pub fn path(&self) -> &Path {
        &self.0.path
    }

    /// Writes the image and renames it into place.
    pub fn write(self, png: &[u8]) -> Result<()> {
        self.0.write(png)
    }
}

/// A directory for the frames of a sequence (`tessera render --frames`, `tessera fetch`
/// of a sequence job, `tessera submit --frames --wait`, `tessera up --frames`): checked
/// and created before anything is rendered; each frame is written whole, atomically,
/// under the name `tessera render --frames` gives it (`frame_0007.png`).
pub struct FramesDir {
    dir: PathBuf,
}

impl FramesDir {
    pub fn create(dir: &Path) -> Result<FramesDir> {
        if dir
            .extension()
            .is_some_and(|e| e.eq_ignore_ascii_case("png"))
        {
            bail!(
                "{}: a sequence is written one file per frame into a directory: give -o DIR/",
                dir.display()
            );
        }
        if dir.exists() && !dir.is_dir() {
            bail!(
                "{}: a sequence is written one file per frame into a directory, and this is a \
                 file",
                dir.display()
            );
        }
        std::fs::create_dir_all(dir)
            .with_context(|| format!("cannot create the directory {}", dir.display()))?;
        Ok(FramesDir { dir: dir.into() })
    }

    pub fn path(&self) -> &Path {
        &self.dir
    }

    /// Where frame `k` of a scene of `count` frames goes.
    pub fn frame_path(&self, k: u64, count: u32) -> PathBuf {
        self.dir.join(render::frame_file_name(k, count))
    }

    /// The output of frame `k`, checked.
    pub fn frame(&self, k: u64, count: u32) -> Result<ImageOutput> {
        ImageOutput::create(&self.frame_path(k, count))
    }
}

/// Where a farm job's result goes (`tessera submit --wait`, `tessera up`): a job's
/// image, or a sequence's frames into a directory as they are done.
pub enum JobOutput {
    Image(ImageOutput),
    Frames(FramesDir),
}

impl JobOutput {
    /// Checks the output of a job of `scene` before the farm spends anything on it:
    /// `output`, or by default the scene's file name with .png for an image, without
    /// .json for the directory of a `sequence`'s frames.
    pub fn create(sequence: bool, output: Option<PathBuf>, scene: &Path) -> Result<JobOutput> {
        Ok(if sequence {
            JobOutput::Frames(FramesDir::create(
                &output.unwrap_or_else(|| default_output(scene).with_extension("")),
            )?)
        } else {
            JobOutput::Image(ImageOutput::create(
                &output.unwrap_or_else(|| default_output(scene)),
            )?)
        })
    }

    pub fn path(&self) -> &Path {
        match self {
            JobOutput::Image(image) => image.path(),
            JobOutput::Frames(dir) => dir.path(),
        }
    }
}

/// A file still to be written (an image, a render's saved samples), through a temporary
/// file beside it renamed into place: checked before the work that makes its bytes.
///
/// The temporary file exists only while the bytes are written: one kept open through a
/// long render would stay behind when the render is interrupted (Ctrl-C ends the
/// process without running destructors).
pub struct FileOutput {
    path: PathBuf,
}

impl FileOutput {
    /// Checks that `path` can be written, the way [`FileOutput::write`] will write it.
    pub fn create(path: &Path) -> Result<FileOutput> {
        drop(temporary_beside(path)?);
        Ok(FileOutput { path: path.into() })
    }

    /// Writes `bytes` to a temporary file beside the path, synced, then renamed into
    /// place: a reader sees the old file or the whole new one, never part of it.
    pub fn write(self, bytes: &[u8]) -> Result<()> {
        let cannot = || format!("cannot write {}", self.path.display());
        let mut tmp = temporary_beside(&self.path)?;
        tmp.write_all(bytes)
            .and_then(|()| tmp.as_file().sync_all())
            .with_context(cannot)?;
        tmp.persist(&self.path)
            .map_err(|e| e.error)
            .with_context(cannot)?;
        Ok(())
    }
}

/// A new temporary file in the directory of `path`, removed if dropped.
fn temporary_beside(path: &Path) -> Result<tempfile::NamedTempFile> {
    if path.is_dir() {
        bail!("cannot write {}: it is a directory", path.display());
    }
    let dir = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    let mut builder = tempfile::Builder::new();
    builder.prefix(".tessera-").suffix(".tmp");
    // A temporary file is private (0600); the image is an ordinary file, readable as
    // the user's umask allows.
    #[cfg(unix)]
    builder.permissions(std::os::unix::fs::PermissionsExt::from_mode(0o666));
    // Said of the image's own name: the temporary one, which the error of `tempfile`
    // ends with (` at path "…"`), means nothing to the user.
    builder.tempfile_in(dir).map_err(|e| {
        let text = e.to_string();
        let reason = text.split(" at path \"").next().unwrap_or_default();
        anyhow!("cannot write {}: {reason}", path.display())
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_image_output_is_checked_before_anything_is_written() {
        let dir = tempfile::tempdir().unwrap();
        let jpg = ImageOutput::create(&dir.path().join("out.jpg"))
            .err()
            .unwrap();
        assert!(format!("{jpg:#}").contains("PNG images only"), "{jpg:#}");
        let missing = dir.path().join("nonexistent/x.png");
        let e = ImageOutput::create(&missing).err().unwrap();
        assert!(
            format!("{e:#}").starts_with(&format!("cannot write {}", missing.display()))
                && !format!("{e:#}").contains(".tessera-"),
            "{e:#}"
        );
        let e = ImageOutput::create(dir.path()).err().unwrap();
        assert!(format!("{e:#}").contains("PNG images only"), "{e:#}");
        let sub = dir.path().join("d.png");
        std::fs::create_dir(&sub).unwrap();
        let e = ImageOutput::create(&sub).err().unwrap();
        assert!(format!("{e:#}").contains("is a directory"), "{e:#}");

        let out = dir.path().join("OUT.PNG");
        let pending = ImageOutput::create(&out).unwrap();
        assert!(!out.exists());
        pending.write(b"png").unwrap();
        assert_eq!(std::fs::read(&out).unwrap(), b"png");
        // Dropped unwritten: nothing left behind.
        drop(ImageOutput::create(&dir.path().join("never.png")).unwrap());
        let left: Vec<_> = std::fs::read_dir(dir.path()).unwrap().collect();
        assert_eq!(left.len(), 2, "{left:?}");
    }

    #[test]
    fn frame_files_have_at_least_four_digits() {
        assert_eq!(render::frame_file_name(7, 1), "frame_0007.png");
        assert_eq!(render::frame_file_name(120, 121), "frame_0120.png");
        assert_eq!(render::frame_file_name(9999, 9999), "frame_9999.png");
        assert_eq!(render::frame_file_name(7, 10_000), "frame_00007.png");
        assert_eq!(
            render::frame_file_name(100_000, 100_000),
            "frame_100000.png"
        );
    }
}
