//! A peer's secret (the token of its role) as an operator hands it over: a file, or an
//! environment variable holding the token itself. Files keep secrets out of process
//! listings and shell histories; the variable suits container platforms that inject
//! secrets that way.
//!
//! A peer keeps where its token comes from ([`TokenSource`]), not the token, and reads
//! it again at every connection: a token file replaced during a rotation is picked up
//! at the next reconnection, without a restart.

use std::path::{Path, PathBuf};

use thiserror::Error;

/// A token that cannot be used: its file is unreadable, or it is empty, which would
/// otherwise turn authentication off without a word.
#[derive(Debug, Error)]
pub enum SecretError {
    #[error("cannot read the token file {}: {error}", path.display())]
    Unreadable {
        path: PathBuf,
        error: std::io::Error,
    },
    /// `source_name` says where the empty token came from: the file, or the variable.
    #[error("the token is empty ({source_name})")]
    Empty { source_name: String },
}

/// The token in `file`, else in the environment variable `variable` (the token itself,
/// not a path), else none. Whitespace at both ends is trimmed (a file's final newline,
/// a pasted space); the rest is used as bytes.
pub fn load_secret(file: Option<&Path>, variable: &str) -> Result<Option<Vec<u8>>, SecretError> {
    let (secret, source_name) = match file {
        Some(path) => (
            std::fs::read_to_string(path).map_err(|error| SecretError::Unreadable {
                path: path.to_owned(),
                error,
            })?,
            format!("the token file {}", path.display()),
        ),
        None => match std::env::var(variable) {
            Ok(token) => (token, variable.to_owned()),
            Err(_) => return Ok(None),
        },
    };
    let secret = secret.trim();
    if secret.is_empty() {
        return Err(SecretError::Empty { source_name });
    }
    Ok(Some(secret.as_bytes().to_vec()))
}

/// The warning a token file deserves when users other than its owner may read or
/// write it (a secret left at the usual 0644), naming the file and the fix; `None`
/// when it is private, or its mode cannot be read (the read itself reports that).
pub fn exposed_token_file(path: &Path) -> Option<String> {
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        let mode = std::fs::metadata(path).ok()?.permissions().mode();
        exposure_warning(path, mode)
    }
    #[cfg(not(unix))]
    {
        let _ = path;
        None
    }
}

/// [`exposed_token_file`] for a file of permission bits `mode`.
#[cfg_attr(not(unix), expect(dead_code, reason = "only Unix has permission bits"))]
fn exposure_warning(path: &Path, mode: u32) -> Option<String> {
    (mode & 0o077 != 0).then(|| {
        format!(
            "the token file {path} is open to other users (mode {mode:04o}): `chmod 600 \
             {path}` keeps it to its owner",
            path = path.display(),
            mode = mode & 0o7777
        )
    })
}

/// Where a peer's token comes from, read at every connection ([`TokenSource::load`]).
#[derive(Clone, Default)]
pub enum TokenSource {
    /// No token: the peer proves nothing.
    #[default]
    None,
    /// The token itself, from an environment variable: a running process's
    /// environment does not change, so it is read once.
    Token(Vec<u8>),
    /// A token file, read again at every connection.
    File(PathBuf),
}

impl TokenSource {
    /// The token in `file`, else in the environment variable `variable`, else none,
    /// as [`load_secret`] reads them; the file is read once now, so that a bad one is
    /// reported at start, and again at every connection.
    pub fn from_settings(file: Option<&Path>, variable: &str) -> Result<TokenSource, SecretError> {
        let secret = load_secret(file, variable)?;
        Ok(match (file, secret) {
            (Some(path), _) => TokenSource::File(path.to_owned()),
            (None, Some(token)) => TokenSource::Token(token),
            (None, None) => TokenSource::None,
        })
    }

    /// The token as its source holds it now.
    pub fn load(&self) -> Result<Option<Vec<u8>>, SecretError> {
        match self {
            TokenSource::None => Ok(None),
            TokenSource::Token(token) => Ok(Some(token.clone())),
            TokenSource::File(path) => load_secret(Some(path), ""),
        }
    }
}

/// Never shows the token itself.
impl std::fmt::Debug for TokenSource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            TokenSource::None => f.write_str("None"),
            TokenSource::Token(_) => f.write_str("Token(..)"),
            TokenSource::File(path) => f.debug_tuple("File").field(path).finish(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_token_file_open_to_others_is_warned_about() {
        let path = Path::new("/etc/tessera/token");
        assert_eq!(exposure_warning(path, 0o100600), None);
        assert_eq!(exposure_warning(path, 0o100400), None);
        assert_eq!(
            exposure_warning(path, 0o100644).as_deref(),
            Some(
                "the token file /etc/tessera/token is open to other users (mode 0644): \
                 `chmod 600 /etc/tessera/token` keeps it to its owner"
            )
        );
        assert!(exposure_warning(path, 0o100640).is_some());
        assert!(exposure_warning(path, 0o100602).is_some());
    }

    #[test]
    fn a_token_file_is_read_again_at_every_load() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("token");
        std::fs::write(&path, "first\n").unwrap();
        let source = TokenSource::from_settings(Some(&path), UNSET).unwrap();
        assert_eq!(source.load().unwrap(), Some(b"first".to_vec()));
        std::fs::write(&path, "second\n").unwrap();
        assert_eq!(source.load().unwrap(), Some(b"second".to_vec()));
        assert_eq!(format!("{source:?}"), format!("File({path:?})"));
        // A file emptied (or being rewritten) is an error at that load, not a token.
        std::fs::write(&path, "").unwrap();
        assert!(source.load().is_err());
        // A bad file is refused at once.
        assert!(TokenSource::from_settings(Some(&dir.path().join("none")), UNSET).is_err());
        let fixed = TokenSource::Token(b"s3cret".to_vec());
        assert_eq!(fixed.load().unwrap(), Some(b"s3cret".to_vec()));
        assert_eq!(format!("{fixed:?}"), "Token(..)");
        assert_eq!(
            TokenSource::from_settings(None, UNSET)
                .unwrap()
                .load()
                .unwrap(),
            None
        );
    }

    /// A variable no other test sets, so that tests running in parallel cannot race.
    const UNSET: &str = "TESSERA_TRANSPORT_TEST_TOKEN_NEVER_SET";

    #[test]
    fn a_token_file_is_read_and_trimmed() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("token");
        std::fs::write(&path, "  s3cret\n").unwrap();
        assert_eq!(
            load_secret(Some(&path), UNSET).unwrap(),
            Some(b"s3cret".to_vec())
        );
    }

    #[test]
    fn no_file_and_no_variable_is_no_secret() {
        assert_eq!(load_secret(None, UNSET).unwrap(), None);
    }

    #[test]
    fn an_unreadable_or_empty_token_is_refused_with_its_source() {
        let dir = tempfile::tempdir().unwrap();
        let missing = dir.path().join("missing");
        let error = load_secret(Some(&missing), UNSET).unwrap_err().to_string();
        assert!(
            error.starts_with(&format!(
                "cannot read the token file {}: ",
                missing.display()
            )),
            "{error}"
        );
        let blank = dir.path().join("blank");
        std::fs::write(&blank, " \n\t\n").unwrap();
        assert_eq!(
            load_secret(Some(&blank), UNSET).unwrap_err().to_string(),
            format!("the token is empty (the token file {})", blank.display())
        );
    }
}
