//! The one place that knows the encoding: bincode 2 with fixed-width little-endian
//! integers and a decode limit, so that a length or a vector size claimed by a peer is
//! checked against what the frame can hold before anything is allocated.

use bincode::config::{self, Configuration, Fixint, LittleEndian, NoLimit};
use serde::{de::DeserializeOwned, Serialize};

use crate::codec::MAX_FRAME_LIMIT;

/// The encoding of every message. Integers are fixed width (u32 = 4 bytes, u64 = 8),
/// little-endian; lengths of strings, byte vectors and sequences are u64; enum variants
/// are a u32 index; `Option` is one byte 0 or 1 followed by the value.
fn encoding() -> Configuration<LittleEndian, Fixint, NoLimit> {
    config::standard()
        .with_little_endian()
        .with_fixed_int_encoding()
}

/// Decodes with an allocation limit of `LIMIT` bytes: a length claimed beyond it is
/// refused before anything is allocated.
fn decode_within<T: DeserializeOwned, const LIMIT: usize>(
    bytes: &[u8],
) -> Result<(T, usize), bincode::error::DecodeError> {
    bincode::serde::decode_from_slice(bytes, encoding().with_limit::<LIMIT>())
}

/// A message that could not be decoded.
#[derive(Debug, thiserror::Error)]
#[error("malformed message: {0}")]
pub struct DecodeError(String);

/// Encodes one message.
pub fn encode<T: Serialize>(message: &T) -> Vec<u8> {
    bincode::serde::encode_to_vec(message, encoding())
        .expect("in-memory encoding of a well-formed message cannot fail")
}

/// Decodes one message that must fill `bytes` exactly.
///
/// The allocation limit follows the frame's own size (the smallest of 4 KiB, 64 KiB,
/// 1 MiB, 16 MiB and 64 MiB that holds it), so a peer's claimed lengths can make the
/// decoder allocate at most 16 times what it actually sent.
pub fn decode<T: DeserializeOwned>(bytes: &[u8]) -> Result<T, DecodeError> {
    const KIB: usize = 1024;
    let decoded = match bytes.len() {
        n if n <= 4 * KIB => decode_within::<T, { 4 * KIB }>(bytes),
        n if n <= 64 * KIB => decode_within::<T, { 64 * KIB }>(bytes),
        n if n <= 1024 * KIB => decode_within::<T, { 1024 * KIB }>(bytes),
        n if n <= 16 * 1024 * KIB => decode_within::<T, { 16 * 1024 * KIB }>(bytes),
        _ => decode_within::<T, MAX_FRAME_LIMIT>(bytes),
    };
    let (message, used) = decoded.map_err(|e| DecodeError(e.to_string()))?;
    if used != bytes.len() {
        return Err(DecodeError(format!(
            "{} trailing bytes after the message",
            bytes.len() - used
        )));
    }
    Ok(message)
}
