//! The protocol's framing spoken by hand over a raw connection, for tests that play a
//! peer (a hostile one, an impostor, one of another version): each frame is its length
//! as four big-endian bytes, then its body.

use std::io::{Read, Write};
use std::net::TcpStream;

/// Frames these tests read are far smaller than this; a larger length is a failure.
const LARGEST_FRAME: usize = 1 << 20;

/// `body` with its length prefix.
pub fn frame(body: &[u8]) -> Vec<u8> {
    let len = u32::try_from(body.len()).expect("small frame");
    let mut frame = len.to_be_bytes().to_vec();
    frame.extend_from_slice(body);
    frame
}

/// Sends one frame.
pub fn send_frame(stream: &mut TcpStream, body: &[u8]) {
    stream.write_all(&frame(body)).expect("cannot send a frame");
}

/// Reads one frame from the peer at the other end (`what` names the exchange).
pub fn read_frame(stream: &mut TcpStream, what: &str) -> Vec<u8> {
    next_frame(stream, what).unwrap_or_else(|e| panic!("{what}: {e}"))
}

/// Reads one frame, or `None` once the connection has ended (or failed) before a whole
/// frame.
pub fn read_frame_until_closed(stream: &mut TcpStream, what: &str) -> Option<Vec<u8>> {
    next_frame(stream, what).ok()
}

fn next_frame(stream: &mut TcpStream, what: &str) -> Result<Vec<u8>, String> {
    let mut len = [0; 4];
    stream
        .read_exact(&mut len)
        .map_err(|e| format!("no frame from the peer: {e}"))?;
    let len = u32::from_be_bytes(len) as usize;
    assert!(len < LARGEST_FRAME, "{what}: a frame of {len} bytes");
    let mut body = vec![0; len];
    stream
        .read_exact(&mut body)
        .map_err(|e| format!("truncated frame: {e}"))?;
    Ok(body)
}
