//! The one place that knows the encoding: bincode 2 with fixed-width little-endian
//! integers and a decode limit, so that a length or a vector size claimed by a peer is
//! checked against what the frame can hold before anything is allocated.

use bincode::config::{self, Configuration, Fixint, LittleEndian, NoLimit};
use serde::{de::DeserializeOwned, Serialize};

/// No configuration may raise the frame limit above this (64 MiB); it is also the
/// decoder's allocation limit. Kept here, below the framing that caps frames with it.
pub const MAX_FRAME_LIMIT: usize = 64 * 1024 * 1024;

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

/// A message that could not be decoded: which message, and what is wrong with it in
/// one line (never the decoder's debug output).
#[derive(Debug, thiserror::Error)]
#[error("unreadable {message}: {detail}")]
pub struct DecodeError {
    message: &'static str,
    detail: String,
}

impl DecodeError {
    fn new<T>(detail: String) -> Self {
        let name = std::any::type_name::<T>();
        let name = name.split('<').next().unwrap_or(name);
        DecodeError {
            message: name.rsplit("::").next().unwrap_or(name),
            detail,
        }
    }

    /// What is wrong, without the name of the message.
    pub fn detail(&self) -> &str {
        &self.detail
    }
}

/// One line saying what is wrong with the bytes, for the peer that sent them.
fn describe(e: &bincode::error::DecodeError) -> String {
    use bincode::error::DecodeError as E;
    match e {
        E::UnexpectedEnd { .. } => "the frame ends in the middle of a field".into(),
        E::LimitExceeded | E::OutsideUsizeRange(_) => {
            "a length claims more bytes than the frame holds".into()
        }
        E::Utf8 { .. } => "a string is not valid UTF-8".into(),
        E::InvalidBooleanValue(v) => format!("a bool is {v}, not 0 or 1"),
        E::UnexpectedVariant {
            type_name, found, ..
        } if type_name.starts_with("Option") => format!("an Option tag is {found}, not 0 or 1"),
        E::UnexpectedVariant { found, .. } => format!("unknown variant {found}"),
        E::OtherString(text) => unknown_variant(text).unwrap_or_else(|| text.clone()),
        E::Other(text) => (*text).into(),
        _ => "not a valid encoding".into(),
    }
}

/// Serde's "invalid value: integer `9`, expected variant index 0 <= i < 8" as
/// "unknown variant 9 (variants go from 0 to 8)".
fn unknown_variant(text: &str) -> Option<String> {
    let rest = text.strip_prefix("invalid value: integer `")?;
    let (found, rest) = rest.split_once('`')?;
    let count: u64 = rest
        .strip_prefix(", expected variant index 0 <= i < ")?
        .parse()
        .ok()?;
    Some(format!(
        "unknown variant {found} (variants go from 0 to {})",
        count.checked_sub(1)?
    ))
}

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
    let (message, used) = decoded.map_err(|e| DecodeError::new::<T>(describe(&e)))?;
    if used != bytes.len() {
        let extra = bytes.len() - used;
        return Err(DecodeError::new::<T>(format!(
            "{extra} byte{} after the end of the message",
            if extra == 1 { "" } else { "s" }
        )));
    }
    Ok(message)
}
