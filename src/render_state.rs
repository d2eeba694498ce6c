//! Saved adaptive renders: every sample a `tessera render --state FILE` took, so that
//! `tessera refine FILE` can go on to a lower error target or a larger cap without
//! taking them again.
//!
//! The file holds the scene's text (a refine needs nothing else), the settings, the
//! rung reached and each block's levels and sums. Layout: the magic line, a format
//! version, the SHA-256 of the rest, then the zstd-compressed bincode of [`Saved`].
//! The digest is checked before anything is decoded, and the blocks are checked again
//! by the renderer (`Region::new`) before a sample of them is used: a damaged or
//! edited file is refused with one line, never rendered from.

use std::path::Path;

use anyhow::{bail, ensure, Context, Result};
use render::progressive::BlockState;
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use crate::output::FileOutput;

const MAGIC: &[u8] = b"tessera render state\n";
const VERSION: u32 = 1;
/// The largest decompressed state accepted: far above any frame the limits allow at
/// the largest cap, far below what a hostile file could ask to allocate.
const MAX_DECODED: usize = 8 << 30;

/// What a saved render holds.
#[derive(Serialize, Deserialize)]
pub struct Saved {
    pub scene: String,
    pub width: u32,
    pub height: u32,
    pub aa: u32,
    pub max_depth: u32,
    /// The target the saved image was rendered to, in thousandths of a level.
    pub target_milli: u32,
    /// The rung of the saved image.
    pub rung: u32,
    pub blocks: Vec<BlockState>,
}

/// Writes `saved` to `out` atomically.
pub fn save(out: FileOutput, saved: &Saved) -> Result<()> {
    let encoded = bincode::serde::encode_to_vec(saved, bincode::config::standard())
        .context("cannot encode the render state")?;
    let compressed =
        zstd::bulk::compress(&encoded, 3).context("cannot compress the render state")?;
    let mut body = Vec::with_capacity(compressed.len() + 8);
    body.extend_from_slice(&VERSION.to_le_bytes());
    body.extend_from_slice(&(encoded.len() as u64).to_le_bytes());
    body.extend_from_slice(&compressed);
    let mut bytes = Vec::with_capacity(MAGIC.len() + 32 + body.len());
    bytes.extend_from_slice(MAGIC);
    bytes.extend_from_slice(&Sha256::digest(&body));
    bytes.extend_from_slice(&body);
    out.write(&bytes)
}

/// Reads and checks a saved render.
pub fn load(path: &Path) -> Result<Saved> {
    let bytes = std::fs::read(path)
        .with_context(|| format!("cannot read render state {}", path.display()))?;
    decode(&bytes).with_context(|| format!("{}", path.display()))
}

fn decode(bytes: &[u8]) -> Result<Saved> {
    let Some(rest) = bytes.strip_prefix(MAGIC) else {
        bail!("not a render state (saved by `tessera render --state`)");
    };
    ensure!(rest.len() >= 32 + 12, "the render state is truncated");
    let (digest, body) = rest.split_at(32);
    ensure!(
        Sha256::digest(body).as_slice() == digest,
        "the render state is damaged (its checksum does not match)"
    );
    let version = u32::from_le_bytes(body[..4].try_into().expect("4 bytes"));
    ensure!(
        version == VERSION,
        "render state format {version} is not the one this build reads ({VERSION})"
    );
    let size = u64::from_le_bytes(body[4..12].try_into().expect("8 bytes"));
    let size = usize::try_from(size)
        .ok()
        .filter(|&s| s <= MAX_DECODED)
        .context("the render state claims an impossible size")?;
    let encoded =
        zstd::bulk::decompress(&body[12..], size).context("the render state is damaged")?;
    let (saved, used): (Saved, usize) =
        bincode::serde::decode_from_slice(&encoded, bincode::config::standard())
            .context("the render state is damaged")?;
    ensure!(used == encoded.len(), "the render state has trailing bytes");
    Ok(saved)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> Saved {
        Saved {
            scene: "{}".into(),
            width: 8,
            height: 8,
            aa: 4,
            max_depth: 3,
            target_milli: 2000,
            rung: 17,
            blocks: Vec::new(),
        }
    }

    #[test]
    fn a_saved_state_reads_back_and_any_damage_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("r.state");
        save(crate::output::FileOutput::create(&path).unwrap(), &sample()).unwrap();
        let back = load(&path).unwrap();
        assert_eq!((back.rung, back.aa, back.scene.as_str()), (17, 4, "{}"));
        let good = std::fs::read(&path).unwrap();
        for at in [0, MAGIC.len() + 3, good.len() - 1] {
            let mut bad = good.clone();
            bad[at] ^= 0x40;
            let err = decode(&bad).err().expect("damage is noticed").to_string();
            assert!(err.contains("render state"), "{err}");
        }
        assert!(decode(&good[..good.len() - 5]).is_err());
    }
}
