//! Why a scene or a setting was refused.

use thiserror::Error;

/// A scene that cannot be rendered, with the place that is wrong.
///
/// Displays as a single line meant for the user, e.g.
/// `objects[2].radius: must be > 0, got -1`.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
pub enum SceneError {
    /// The text is not JSON at all.
    #[error("not valid JSON: {message} at line {line}, column {column}")]
    Syntax {
        message: String,
        line: usize,
        column: usize,
    },
    /// The JSON is well formed but some value is missing, unknown, of the wrong type or
    /// out of range. `path` names it the way a user would find it in the file:
    /// `objects[2].radius`, `image.width`, `lights`.
    #[error("{path}: {message}")]
    Invalid { path: String, message: String },
}

impl SceneError {
    pub(crate) fn invalid(path: impl Into<String>, message: impl Into<String>) -> Self {
        SceneError::Invalid {
            path: path.into(),
            message: message.into(),
        }
    }
}
