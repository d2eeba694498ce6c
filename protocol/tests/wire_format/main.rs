//! The protocol crate's tests: every message type round trips through the encoder, the
//! framing and the handshake, hostile input is refused without harm, and the worked
//! examples of `docs/protocol.md` are exactly the encoder's bytes.

mod doc_examples;
mod roundtrip;

use bytes::{BufMut, BytesMut};

/// A frame around `body`, as the length-delimited codec writes it.
pub fn frame(body: &[u8]) -> BytesMut {
    let mut bytes = BytesMut::with_capacity(4 + body.len());
    bytes.put_u32(u32::try_from(body.len()).expect("test frames are small"));
    bytes.put_slice(body);
    bytes
}
