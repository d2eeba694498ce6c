//! A file's identity: the SHA-256 of its bytes and their count.
//!
//! The size travels with the hash so that a receiver can refuse a file over its limits,
//! and reserve room for it, before a single byte arrives, and so that a truncated copy
//! is told apart from the real one by its length alone.

use std::fmt;

use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

/// A file's identity: its SHA-256 and its length in bytes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
pub struct AssetId {
    pub sha256: [u8; 32],
    pub size: u64,
}

impl AssetId {
    /// The identity of `bytes`.
    pub fn of(bytes: &[u8]) -> AssetId {
        AssetId {
            sha256: Sha256::digest(bytes).into(),
            size: bytes.len() as u64,
        }
    }

    /// The hash in lowercase hexadecimal, 64 characters: the file's name on disk.
    pub fn hex(&self) -> String {
        to_hex(&self.sha256)
    }

    /// The identity named by 64 hexadecimal characters (either case) and a size; `None`
    /// for anything else.
    pub fn from_hex(hex: &str, size: u64) -> Option<AssetId> {
        Some(AssetId {
            sha256: parse_hex32(hex)?,
            size,
        })
    }
}

impl fmt::Display for AssetId {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "sha256:{} ({} bytes)", self.hex(), self.size)
    }
}

/// `bytes` in lowercase hexadecimal.
pub(crate) fn to_hex(bytes: &[u8]) -> String {
    const DIGITS: &[u8; 16] = b"0123456789abcdef";
    let mut out = String::with_capacity(bytes.len() * 2);
    for b in bytes {
        out.push(DIGITS[usize::from(b >> 4)] as char);
        out.push(DIGITS[usize::from(b & 0xf)] as char);
    }
    out
}

/// The 32 bytes written as exactly 64 hexadecimal characters.
pub(crate) fn parse_hex32(hex: &str) -> Option<[u8; 32]> {
    let digits = hex.as_bytes();
    if digits.len() != 64 {
        return None;
    }
    let mut out = [0u8; 32];
    for (byte, pair) in out.iter_mut().zip(digits.chunks_exact(2)) {
        *byte = (nibble(pair[0])? << 4) | nibble(pair[1])?;
    }
    Some(out)
}

fn nibble(c: u8) -> Option<u8> {
    match c {
        b'0'..=b'9' => Some(c - b'0'),
        b'a'..=b'f' => Some(c - b'a' + 10),
        b'A'..=b'F' => Some(c - b'A' + 10),
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hex_round_trips_and_is_lowercase() {
        let id = AssetId::of(b"abc");
        assert_eq!(
            id.hex(),
            "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad"
        );
        assert_eq!(AssetId::from_hex(&id.hex(), 3), Some(id));
        assert_eq!(AssetId::from_hex(&id.hex().to_uppercase(), 3), Some(id));
        assert_eq!(AssetId::from_hex(&id.hex()[1..], 3), None);
        assert_eq!(AssetId::from_hex(&format!("{}g", &id.hex()[1..]), 3), None);
        assert_eq!(id.to_string(), format!("sha256:{} (3 bytes)", id.hex()));
    }
}
