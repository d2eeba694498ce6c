//! A TCP relay on 127.0.0.1 that can cut the link: while cut it reads and forwards
//! nothing in either direction and closes nothing, like a pulled cable or a dead
//! switch. Data in flight waits in the kernel's buffers and flows again when the link
//! is restored; connections closed during the cut are closed when it ends.

use std::io::{ErrorKind, Read, Write};
use std::net::{Shutdown, TcpListener, TcpStream};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::thread;
use std::time::Duration;

/// How often a blocked relay thread looks at the cut and stop flags.
const CHECK: Duration = Duration::from_millis(20);

#[derive(Default)]
struct Flags {
    cut: AtomicBool,
    stop: AtomicBool,
    /// Every byte relayed from the connecting side to the upstream side.
    upstream_bytes: Mutex<Vec<u8>>,
}

impl Flags {
    fn stopped(&self) -> bool {
        self.stop.load(Ordering::SeqCst)
    }

    /// Waits while the link is cut; false if the relay is stopping.
    fn wait_link(&self) -> bool {
        while self.cut.load(Ordering::SeqCst) {
            if self.stopped() {
                return false;
            }
            thread::sleep(CHECK);
        }
        !self.stopped()
    }
}

/// The relay; dropping it closes every connection through it.
pub struct CutProxy {
    address: String,
    flags: Arc<Flags>,
}

impl CutProxy {
    /// Relays connections to `upstream` (an address on 127.0.0.1).
    pub fn start(upstream: &str) -> CutProxy {
        let listener = TcpListener::bind("127.0.0.1:0").expect("cannot bind the proxy");
        listener
            .set_nonblocking(true)
            .expect("cannot make the proxy nonblocking");
        let address = listener.local_addr().expect("proxy address").to_string();
        let flags = Arc::new(Flags::default());
        let upstream = upstream.to_owned();
        let accepting = Arc::clone(&flags);
        thread::spawn(move || {
            while !accepting.stopped() {
                match listener.accept() {
                    Ok((downstream, _)) => {
                        downstream.set_nonblocking(false).expect("blocking socket");
                        let Ok(up) = TcpStream::connect(&upstream) else {
                            continue;
                        };
                        relay(downstream, up, &accepting);
                    }
                    Err(e) if e.kind() == ErrorKind::WouldBlock => thread::sleep(CHECK),
                    Err(_) => thread::sleep(CHECK),
                }
            }
        });
        CutProxy { address, flags }
    }

    /// Where peers connect to reach the upstream through the relay.
    pub fn address(&self) -> &str {
        &self.address
    }

    /// Stops all traffic, silently.
    pub fn cut(&self) {
        self.flags.cut.store(true, Ordering::SeqCst);
    }

    /// Lets traffic (and any close held during the cut) through again.
    pub fn restore(&self) {
        self.flags.cut.store(false, Ordering::SeqCst);
    }

    /// The bytes peers have sent upstream so far, as relayed.
    pub fn upstream_bytes(&self) -> Vec<u8> {
        self.flags.upstream_bytes.lock().expect("capture").clone()
    }
}

impl Drop for CutProxy {
    fn drop(&mut self) {
        self.flags.stop.store(true, Ordering::SeqCst);
    }
}

/// Starts the two directions of one connection.
fn relay(downstream: TcpStream, upstream: TcpStream, flags: &Arc<Flags>) {
    let pairs = [
        (downstream.try_clone(), upstream.try_clone(), true),
        (upstream.try_clone(), downstream.try_clone(), false),
    ];
    for (from, to, capture) in pairs {
        let (Ok(from), Ok(to)) = (from, to) else {
            return;
        };
        let flags = Arc::clone(flags);
        thread::spawn(move || pump(from, to, &flags, capture));
    }
}

/// Copies `from` to `to` while the link is up.
fn pump(mut from: TcpStream, mut to: TcpStream, flags: &Flags, capture: bool) {
    from.set_read_timeout(Some(CHECK)).expect("read timeout");
    let mut buf = vec![0u8; 64 * 1024];
    loop {
        if !flags.wait_link() {
            break;
        }
        match from.read(&mut buf) {
            Ok(0) => {
                // Closed on this side: pass the close on once the link is up.
                if flags.wait_link() {
                    let _ = to.shutdown(Shutdown::Write);
                }
                return;
            }
            Ok(n) => {
                if capture {
                    flags
                        .upstream_bytes
                        .lock()
                        .expect("capture")
                        .extend_from_slice(&buf[..n]);
                }
                if !flags.wait_link() || to.write_all(&buf[..n]).is_err() {
                    break;
                }
            }
            Err(e) if matches!(e.kind(), ErrorKind::WouldBlock | ErrorKind::TimedOut) => {}
            Err(_) => {
                flags.wait_link();
                break;
            }
        }
    }
    let _ = to.shutdown(Shutdown::Both);
    let _ = from.shutdown(Shutdown::Both);
}
