//! A TCP relay on 127.0.0.1 that stands for a slow link: each direction of each
//! connection is forwarded at most at a given rate (a token bucket, bursts of
//! [`BURST`] bytes), as a remote page's line would carry it. Bytes wait in the
//! kernel's buffers on the way, as they would in a network's queues. Dropping it closes
//! every connection through it.

use std::io::{ErrorKind, Read, Write};
use std::net::{Shutdown, TcpListener, TcpStream};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::thread;
use std::time::{Duration, Instant};

/// How often the accepting thread, and a relay thread blocked on a read, look at the
/// stop flag.
const CHECK: Duration = Duration::from_millis(20);

/// The bucket's size: what may go at once after a quiet spell (a few milliseconds of
/// a 20 Mbit/s link).
pub const BURST: usize = 16 * 1024;

#[derive(Default)]
struct Shared {
    stop: AtomicBool,
    /// Bytes relayed from upstream to the connecting side, over every connection.
    downstream: AtomicU64,
    /// Every socket of the relay, shut down on drop so that blocked threads end.
    sockets: Mutex<Vec<TcpStream>>,
}

/// The relay; dropping it closes every connection through it.
pub struct ThrottleRelay {
    address: String,
    shared: Arc<Shared>,
}

impl ThrottleRelay {
    /// Relays connections to `upstream` (an address on 127.0.0.1) at most at
    /// `bytes_per_second` each way.
    pub fn start(upstream: &str, bytes_per_second: u64) -> ThrottleRelay {
        assert!(bytes_per_second > 0);
        let listener = TcpListener::bind("127.0.0.1:0").expect("cannot bind the relay");
        listener
            .set_nonblocking(true)
            .expect("cannot make the relay nonblocking");
        let address = listener.local_addr().expect("relay address").to_string();
        let shared = Arc::new(Shared::default());
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
                        {
                            let mut sockets = accepting.sockets.lock().expect("sockets");
                            for s in [&down, &up] {
                                let _ = s.set_nodelay(true);
                                let _ = s.set_read_timeout(Some(CHECK));
                                if let Ok(s) = s.try_clone() {
                                    sockets.push(s);
                                }
                            }
                        }
                        let (Ok(down2), Ok(up2)) = (down.try_clone(), up.try_clone()) else {
                            continue;
                        };
                        let to_client = Arc::clone(&accepting);
                        thread::spawn(move || {
                            forward(up2, down2, bytes_per_second, &to_client, true)
                        });
                        let to_server = Arc::clone(&accepting);
                        thread::spawn(move || {
                            forward(down, up, bytes_per_second, &to_server, false)
                        });
                    }
                    Err(e) if e.kind() == ErrorKind::WouldBlock => thread::sleep(CHECK),
                    Err(_) => thread::sleep(CHECK),
                }
            }
        });
        ThrottleRelay { address, shared }
    }

    /// Where a client connects to reach the upstream through the slow link.
    pub fn address(&self) -> &str {
        &self.address
    }

    /// Bytes relayed from upstream to clients so far.
    pub fn downstream_bytes(&self) -> u64 {
        self.shared.downstream.load(Ordering::SeqCst)
    }
}

impl Drop for ThrottleRelay {
    fn drop(&mut self) {
        self.shared.stop.store(true, Ordering::SeqCst);
        for socket in self.shared.sockets.lock().expect("sockets").drain(..) {
            let _ = socket.shutdown(Shutdown::Both);
        }
    }
}

/// Copies `from` to `to` at most at `rate` bytes a second: a chunk is read only once
/// the previous one went, so what the link has not carried waits upstream.
fn forward(mut from: TcpStream, mut to: TcpStream, rate: u64, shared: &Shared, down: bool) {
    let mut buf = vec![0u8; BURST];
    let mut tokens = BURST as f64;
    let mut filled = Instant::now();
    while !shared.stop.load(Ordering::SeqCst) {
        let n = match from.read(&mut buf) {
            Ok(0) => break,
            Ok(n) => n,
            Err(e) if matches!(e.kind(), ErrorKind::WouldBlock | ErrorKind::TimedOut) => continue,
            Err(_) => break,
        };
        loop {
            let now = Instant::now();
            tokens =
                (tokens + now.duration_since(filled).as_secs_f64() * rate as f64).min(BURST as f64);
            filled = now;
            if tokens >= n as f64 {
                break;
            }
            thread::sleep(Duration::from_secs_f64((n as f64 - tokens) / rate as f64));
        }
        tokens -= n as f64;
        if to.write_all(&buf[..n]).is_err() {
            break;
        }
        if down {
            shared.downstream.fetch_add(n as u64, Ordering::SeqCst);
        }
    }
    let _ = to.shutdown(Shutdown::Both);
    let _ = from.shutdown(Shutdown::Both);
}
