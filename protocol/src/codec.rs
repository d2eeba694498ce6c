//! Framing: a length prefix (tokio-util's `LengthDelimitedCodec`, 4 bytes big-endian)
//! and one bincode message per frame. A frame longer than the configured maximum is
//! refused from its length prefix alone, before its body is read.

use std::marker::PhantomData;

use bytes::{Bytes, BytesMut};
use serde::{de::DeserializeOwned, Serialize};
use tokio_util::codec::{Decoder, Encoder, LengthDelimitedCodec, LengthDelimitedCodecError};

use crate::wire::{self, DecodeError, MAX_FRAME_LIMIT};

/// The default largest frame: room for the largest scene a job may carry
/// (`limits::MAX_SCENE_BYTES`, 8 MiB) with margin for its envelope.
pub const DEFAULT_MAX_FRAME: usize = 16 * 1024 * 1024;

/// Why a frame could not be read or written.
#[derive(Debug, thiserror::Error)]
pub enum FrameError {
    /// The connection failed, or a frame's length prefix is above the limit (an error
    /// of kind `InvalidData` then, whose text says so).
    #[error("{}", io_text(.0))]
    Io(#[from] std::io::Error),
    #[error(transparent)]
    Decode(#[from] DecodeError),
}

/// Encodes `Out` messages and decodes `In` messages, one per length-prefixed frame.
pub struct MessageCodec<In, Out> {
    frames: LengthDelimitedCodec,
    _messages: PhantomData<fn(Out) -> In>,
}

impl<In, Out> MessageCodec<In, Out> {
    /// A codec refusing frames longer than `max_frame` bytes (capped at
    /// [`MAX_FRAME_LIMIT`]).
    pub fn new(max_frame: usize) -> Self {
        MessageCodec {
            frames: frame_codec(max_frame),
            _messages: PhantomData,
        }
    }
}

/// The framing alone (4-byte big-endian length, at most `max_frame` bytes, capped at
/// [`MAX_FRAME_LIMIT`]), for the handshake frames read before the message codec.
pub fn frame_codec(max_frame: usize) -> LengthDelimitedCodec {
    LengthDelimitedCodec::builder()
        .length_field_length(4)
        .max_frame_length(max_frame.min(MAX_FRAME_LIMIT))
        .new_codec()
}

/// A length prefix above the frame limit.
#[derive(Debug, thiserror::Error)]
#[error("a frame of {length} bytes is too long")]
struct FrameTooLong {
    length: u64,
}

fn io_text(e: &std::io::Error) -> String {
    match e
        .get_ref()
        .and_then(|inner| inner.downcast_ref::<FrameTooLong>())
    {
        Some(too_long) => too_long.to_string(),
        None => format!("connection error: {e}"),
    }
}

impl<In: DeserializeOwned, Out> Decoder for MessageCodec<In, Out> {
    type Item = In;
    type Error = FrameError;

    fn decode(&mut self, src: &mut BytesMut) -> Result<Option<In>, FrameError> {
        let frame = match self.frames.decode(src) {
            Ok(frame) => frame,
            // Refused from its prefix, which is still at the head of `src`.
            Err(e)
                if src.len() >= 4
                    && e.get_ref()
                        .is_some_and(|inner| inner.is::<LengthDelimitedCodecError>()) =>
            {
                let length = u64::from(u32::from_be_bytes([src[0], src[1], src[2], src[3]]));
                return Err(FrameError::Io(std::io::Error::new(
                    std::io::ErrorKind::InvalidData,
                    FrameTooLong { length },
                )));
            }
            Err(e) => return Err(e.into()),
        };
        match frame {
            Some(frame) => Ok(Some(wire::decode(&frame)?)),
            None => Ok(None),
        }
    }
}

impl<In, Out: Serialize> Encoder<Out> for MessageCodec<In, Out> {
    type Error = FrameError;

    fn encode(&mut self, item: Out, dst: &mut BytesMut) -> Result<(), FrameError> {
        self.frames
            .encode(Bytes::from(wire::encode(&item)), dst)
            .map_err(FrameError::Io)
    }
}
