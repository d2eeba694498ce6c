//! The one place that knows the encoding: bincode 2 with fixed-width little-endian
//! integers and a decode limit, so that a length or a vector size claimed by a peer is
//! checked against what the frame can hold before anything is allocated.

use bincode::config::{self, Configuration, Fixint, Limit, LittleEndian};
use serde::{de::DeserializeOwned, Serialize};

use crate::codec::MAX_FRAME_LIMIT;

/// The encoding of every message. Integers are fixed width (u32 = 4 bytes, u64 = 8),
/// little-endian; lengths of strings, byte vectors and sequences are u64; enum variants
/// are a u32 index; `Option` is one byte 0 or 1 followed by the value.
fn configuration() -> Configuration<LittleEndian, Fixint, Limit<MAX_FRAME_LIMIT>> {
    config::standard()
        .with_little_endian()
        .with_fixed_int_encoding()
        .with_limit::<MAX_FRAME_LIMIT>()
}

/// A message that could not be decoded.
#[derive(Debug, thiserror::Error)]
#[error("malformed message: {0}")]
pub struct DecodeError(String);

/// Encodes one message.
pub fn encode<T: Serialize>(message: &T) -> Vec<u8> {
    bincode::serde::encode_to_vec(message, configuration())
        .expect("in-memory encoding of a well-formed message cannot fail")
}

/// Decodes one message that must fill `bytes` exactly.
pub fn decode<T: DeserializeOwned>(bytes: &[u8]) -> Result<T, DecodeError> {
    let (message, used) = bincode::serde::decode_from_slice(bytes, configuration())
        .map_err(|e| DecodeError(e.to_string()))?;
    if used != bytes.len() {
        return Err(DecodeError(format!(
            "{} trailing bytes after the message",
            bytes.len() - used
        )));
    }
    Ok(message)
}
