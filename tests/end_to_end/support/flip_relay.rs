//! A TCP relay on 127.0.0.1 between a worker and its coordinator that corrupts some
//! tile results on the way: of the frames the worker sends, every `every`th tile result
//! (`FromWorker::TileDone`, variant 0, or `TileDoneZstd`, variant 6, whose bodies start
//! with that index as four little-endian bytes), the first included, has one byte of
//! its pixels (raw or compressed) flipped, near the end of the frame (the pixels are
//! followed by four 8-byte fields). Everything else passes unchanged, the
//! handshake included. Or ([`FlipRelay::start_flipping_files`]) it corrupts instead
//! the first few chunks of scene files the coordinator sends (`ToWorker::AssetChunk`,
//! variant 11: the last byte of the chunk's bytes). Dropping it closes every
//! connection through it.

use std::io::{ErrorKind, Read, Write};
use std::net::{Shutdown, TcpListener, TcpStream};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::thread;
use std::time::Duration;

/// How often the accepting thread looks at the stop flag.
const CHECK: Duration = Duration::from_millis(20);

/// Bytes after a `TileDone`'s pixels: rays, render_us, samples, error_sq_sum.
const AFTER_PIXELS: usize = 32;

#[derive(Default)]
struct Shared {
    stop: AtomicBool,
    /// `TileDone` frames relayed, and how many of them were corrupted.
    tile_frames: AtomicU64,
    flipped: AtomicU64,
    /// File chunks still to corrupt, and those corrupted.
    file_flips_left: AtomicU64,
    files_flipped: AtomicU64,
    /// Every socket of the relay, shut down on drop so that blocked threads end.
    sockets: Mutex<Vec<TcpStream>>,
}

/// The relay; dropping it closes every connection through it.
pub struct FlipRelay {
    address: String,
    shared: Arc<Shared>,
}

impl FlipRelay {
    /// Relays connections to `upstream` (an address on 127.0.0.1), corrupting every
    /// `every`th tile result.
    pub fn start(upstream: &str, every: u64) -> FlipRelay {
        assert!(every >= 1);
        FlipRelay::relay(upstream, Some(every), 0)
    }

    /// Relays connections to `upstream`, corrupting the first `chunks` chunks of scene
    /// files sent to the worker, and no tile result.
    pub fn start_flipping_files(upstream: &str, chunks: u64) -> FlipRelay {
        FlipRelay::relay(upstream, None, chunks)
    }

    fn relay(upstream: &str, every: Option<u64>, file_chunks: u64) -> FlipRelay {
        let listener = TcpListener::bind("127.0.0.1:0").expect("cannot bind the relay");
        listener
            .set_nonblocking(true)
            .expect("cannot make the relay nonblocking");
        let address = listener.local_addr().expect("relay address").to_string();
        let shared = Arc::new(Shared {
            file_flips_left: AtomicU64::new(file_chunks),
            ..Shared::default()
        });
        let upstream = upstream.to_owned();
        let accepting = Arc::clone(&shared);
        thread::spawn(move || {
            while !accepting.stop.load(Ordering::SeqCst) {
                match listener.accept() {
                    Ok((down, _)) => {
                        down.set_nonblocking(false).expect("blocking socket");
                        let Ok(up) = TcpStream::connect(&upstream) else {
                            continue;
                        };
                        let _ = up.set_nodelay(true);
                        let _ = down.set_nodelay(true);
                        {
                            let mut sockets = accepting.sockets.lock().expect("sockets");
                            for s in [&down, &up] {
                                if let Ok(s) = s.try_clone() {
                                    sockets.push(s);
                                }
                            }
                        }
                        let (Ok(down2), Ok(up2)) = (down.try_clone(), up.try_clone()) else {
                            continue;
                        };
                        let to_worker = Arc::clone(&accepting);
                        if file_chunks > 0 {
                            thread::spawn(move || to_worker_frames(up2, down2, &to_worker));
                        } else {
                            thread::spawn(move || copy(up2, down2, &to_worker));
                        }
                        let from_worker = Arc::clone(&accepting);
                        thread::spawn(move || frames(down, up, every, &from_worker));
                    }
                    Err(e) if e.kind() == ErrorKind::WouldBlock => thread::sleep(CHECK),
                    Err(_) => thread::sleep(CHECK),
                }
            }
        });
        FlipRelay { address, shared }
    }

    /// Where the worker connects to reach the coordinator through the relay.
    pub fn address(&self) -> &str {
        &self.address
    }

    /// `TileDone` frames relayed so far.
    pub fn tile_frames(&self) -> u64 {
        self.shared.tile_frames.load(Ordering::SeqCst)
    }

    /// `TileDone` frames corrupted so far.
    pub fn flipped(&self) -> u64 {
        self.shared.flipped.load(Ordering::SeqCst)
    }

    /// File chunks corrupted so far.
    pub fn files_flipped(&self) -> u64 {
        self.shared.files_flipped.load(Ordering::SeqCst)
    }
}

impl Drop for FlipRelay {
    fn drop(&mut self) {
        self.shared.stop.store(true, Ordering::SeqCst);
        for socket in self.shared.sockets.lock().expect("sockets").drain(..) {
            let _ = socket.shutdown(Shutdown::Both);
        }
    }
}

/// Coordinator to worker: bytes as they come.
fn copy(mut from: TcpStream, mut to: TcpStream, shared: &Shared) {
    let mut buf = vec![0u8; 64 * 1024];
    while !shared.stop.load(Ordering::SeqCst) {
        match from.read(&mut buf) {
            Ok(0) | Err(_) => break,
            Ok(n) => {
                if to.write_all(&buf[..n]).is_err() {
                    break;
                }
            }
        }
    }
    let _ = to.shutdown(Shutdown::Both);
    let _ = from.shutdown(Shutdown::Both);
}

/// Coordinator to worker: frame by frame, corrupting the first file chunks.
fn to_worker_frames(from: TcpStream, to: TcpStream, shared: &Shared) {
    relay_frames(from, to, shared, |body| {
        // A file chunk: variant 11, the key (40 bytes), the offset (8), the bytes'
        // length (8), then at least one byte.
        let len = body.len();
        let chunk = len > 4 + 40 + 8 + 8 && body[..4] == [11, 0, 0, 0];
        if chunk
            && shared
                .file_flips_left
                .fetch_update(Ordering::SeqCst, Ordering::SeqCst, |n| n.checked_sub(1))
                .is_ok()
        {
            body[len - 1] ^= 0xff;
            shared.files_flipped.fetch_add(1, Ordering::SeqCst);
        }
    });
}

/// Worker to coordinator: frame by frame, corrupting every `every`th tile result
/// (none without `every`).
fn frames(from: TcpStream, to: TcpStream, every: Option<u64>, shared: &Shared) {
    relay_frames(from, to, shared, |body| {
        // A tile result: variant 0 or 6, job, tile, the pixels' length, pixels (raw or
        // compressed), 32 more bytes.
        let len = body.len();
        let tile_done = len > 4 + 8 + 4 + 8 + AFTER_PIXELS
            && (body[..4] == [0, 0, 0, 0] || body[..4] == [6, 0, 0, 0]);
        if tile_done {
            let nth = shared.tile_frames.fetch_add(1, Ordering::SeqCst);
            if every.is_some_and(|every| nth.is_multiple_of(every)) {
                let at = len - AFTER_PIXELS - 7;
                body[at] ^= 0xff;
                shared.flipped.fetch_add(1, Ordering::SeqCst);
            }
        }
    });
}

/// Relays frames one by one, each body passed to `edit` on its way.
fn relay_frames(
    mut from: TcpStream,
    mut to: TcpStream,
    shared: &Shared,
    mut edit: impl FnMut(&mut Vec<u8>),
) {
    loop {
        if shared.stop.load(Ordering::SeqCst) {
            break;
        }
        let mut prefix = [0u8; 4];
        if from.read_exact(&mut prefix).is_err() {
            break;
        }
        let len = u32::from_be_bytes(prefix) as usize;
        let mut body = vec![0u8; len];
        if from.read_exact(&mut body).is_err() {
            break;
        }
        edit(&mut body);
        if to.write_all(&prefix).is_err() || to.write_all(&body).is_err() {
            break;
        }
    }
    let _ = to.shutdown(Shutdown::Both);
    let _ = from.shutdown(Shutdown::Both);
}
