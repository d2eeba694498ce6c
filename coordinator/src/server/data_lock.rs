//! One coordinator per data directory.
//!
//! Two coordinators on one directory would both issue job ids from the same database
//! and overwrite each other's images. The first to start holds an exclusive advisory
//! lock on `DATA/coordinator.lock` (`flock` on Unix) for as long as it runs, and writes
//! its process id and address into the file; a second is refused at start with that
//! address. The operating system drops the lock when its holder exits, however it
//! exits, so the file left behind by a killed coordinator never blocks a restart.

use std::fs::{File, OpenOptions, TryLockError};
use std::io::{Read, Seek, SeekFrom, Write};
use std::net::SocketAddr;
use std::path::{Path, PathBuf};

use tracing::warn;

/// The lock file's name in the data directory.
pub const LOCK_FILE: &str = "coordinator.lock";

/// Why the data directory could not be taken.
#[derive(Debug, thiserror::Error)]
pub enum LockError {
    #[error(
        "the data directory {dir} is in use by another coordinator ({holder}): stop it, or \
         give this one another --data"
    )]
    InUse { dir: PathBuf, holder: String },
    #[error("cannot open the lock file {path}: {source}")]
    Open {
        path: PathBuf,
        source: std::io::Error,
    },
}

/// The exclusive hold on a data directory, released when dropped (or when the process
/// ends).
#[derive(Debug)]
pub struct DataLock {
    /// `None` where the file system cannot lock (the start was not refused for it).
    file: Option<File>,
}

impl DataLock {
    /// Takes the data directory `data` (which must exist), or says who holds it.
    pub fn acquire(data: &Path) -> Result<DataLock, LockError> {
        let path = data.join(LOCK_FILE);
        let open = || {
            OpenOptions::new()
                .read(true)
                .write(true)
                .create(true)
                .truncate(false)
                .open(&path)
        };
        let mut file = open().map_err(|source| LockError::Open {
            path: path.clone(),
            source,
        })?;
        match file.try_lock() {
            Ok(()) => {}
            Err(TryLockError::WouldBlock) => {
                let mut text = String::new();
                let _ = file.read_to_string(&mut text);
                return Err(LockError::InUse {
                    dir: data.to_path_buf(),
                    holder: describe_holder(&text),
                });
            }
            Err(TryLockError::Error(e)) => {
                // A file system without locks (some network ones): the start goes on,
                // unguarded, rather than not at all.
                warn!(path = %path.display(), error = %e,
                    "cannot lock the data directory: nothing stops a second coordinator \
                     from using it");
                return Ok(DataLock { file: None });
            }
        }
        let mut lock = DataLock { file: Some(file) };
        lock.write(&format!("pid {}\n", std::process::id()));
        Ok(lock)
    }

    /// Records the address the coordinator listens on, for a second one to name.
    pub fn record_address(&mut self, addr: SocketAddr) {
        self.write(&format!("pid {}\naddress {addr}\n", std::process::id()));
    }

    /// Replaces the file's text; a failure only loses the description of the holder.
    fn write(&mut self, text: &str) {
        if let Some(file) = &mut self.file {
            let written = file
                .set_len(0)
                .and_then(|()| file.seek(SeekFrom::Start(0)))
                .and_then(|_| file.write_all(text.as_bytes()));
            if let Err(e) = written {
                warn!(error = %e, "cannot write the data directory's lock file");
            }
        }
    }
}

/// "pid 123, listening on 127.0.0.1:7878" from the lock file's text.
fn describe_holder(text: &str) -> String {
    let field = |name: &str| {
        text.lines()
            .find_map(|l| l.strip_prefix(name).map(|v| v.trim().to_owned()))
            .filter(|v| !v.is_empty())
    };
    match (field("pid "), field("address ")) {
        (Some(pid), Some(addr)) => format!("pid {pid}, listening on {addr}"),
        (Some(pid), None) => format!("pid {pid}, still starting"),
        (None, Some(addr)) => format!("listening on {addr}"),
        (None, None) => "it has not said which".to_owned(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_second_hold_is_refused_with_the_holders_address_and_a_released_one_is_not() {
        let dir = tempfile::tempdir().unwrap();
        let mut first = DataLock::acquire(dir.path()).unwrap();
        first.record_address("127.0.0.1:7878".parse().unwrap());
        let refused = DataLock::acquire(dir.path()).unwrap_err().to_string();
        assert!(
            refused.contains("in use by another coordinator")
                && refused.contains(&format!("pid {}", std::process::id()))
                && refused.contains("listening on 127.0.0.1:7878")
                && refused.contains(&dir.path().display().to_string()),
            "{refused}"
        );
        drop(first);
        // The file stays behind, as after a killed coordinator: it blocks nothing.
        assert!(dir.path().join(LOCK_FILE).exists());
        let _again = DataLock::acquire(dir.path()).unwrap();
    }

    #[test]
    fn the_holder_is_described_from_what_it_wrote() {
        assert_eq!(
            describe_holder("pid 9\naddress 10.0.0.1:7878\n"),
            "pid 9, listening on 10.0.0.1:7878"
        );
        assert_eq!(describe_holder("pid 9\n"), "pid 9, still starting");
        assert_eq!(describe_holder(""), "it has not said which");
    }
}
