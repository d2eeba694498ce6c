//! A TCP relay that stands for a long network path: it forwards a byte stream both ways
//! unchanged, holding every chunk for a fixed one-way delay (and, if asked, for the time
//! a link of a given bandwidth takes to carry it), and counts the protocol's frames as
//! they pass. The latency suite puts one in front of each worker.
//!
//! Each direction is two threads: one reads chunks as they arrive and stamps them, the
//! other writes each chunk when its time has come, in order. Threads sleep with the
//! kernel's precision (tens of microseconds), so the relay adds no latency of its own
//! to speak of; [`self_test`] measures it.

use std::collections::BTreeMap;
use std::io::{self, Read, Write};
use std::net::{Shutdown, SocketAddr, TcpListener, TcpStream};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{mpsc, Arc, Mutex};
use std::thread;
use std::time::{Duration, Instant};

/// What the relay does to the bytes it carries, in each direction alike.
#[derive(Clone, Copy, Debug)]
pub struct Link {
    /// Half the round-trip time.
    pub one_way: Duration,
    /// Bytes per second; `None` carries chunks as fast as they come.
    pub bandwidth: Option<f64>,
}

/// Which way bytes travel.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Direction {
    /// Worker to coordinator.
    Up,
    /// Coordinator to worker.
    Down,
}

/// Frames and bytes (the 4-byte length prefix included) of one kind of message.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Count {
    pub frames: u64,
    pub bytes: u64,
}

/// What crossed a relay.
#[derive(Clone, Debug, Default)]
pub struct Traffic {
    /// Bytes forwarded worker to coordinator: exactly what the TCP stream carried.
    pub up_bytes: u64,
    /// Bytes forwarded coordinator to worker.
    pub down_bytes: u64,
    /// Frames and bytes by direction and kind of message.
    pub kinds: BTreeMap<(Direction, &'static str), Count>,
    /// Sum of the render times the tile results report (`render_us`).
    pub render_us: u64,
}

impl Traffic {
    /// What was added since `earlier`, a snapshot of the same relays.
    pub fn since(&self, earlier: &Traffic) -> Traffic {
        let mut kinds = BTreeMap::new();
        for (key, now) in &self.kinds {
            let before = earlier.kinds.get(key).copied().unwrap_or_default();
            let d = Count {
                frames: now.frames - before.frames,
                bytes: now.bytes - before.bytes,
            };
            if d.frames > 0 {
                kinds.insert(*key, d);
            }
        }
        Traffic {
            up_bytes: self.up_bytes - earlier.up_bytes,
            down_bytes: self.down_bytes - earlier.down_bytes,
            kinds,
            render_us: self.render_us - earlier.render_us,
        }
    }

    /// Adds another relay's traffic to this one.
    pub fn add(&mut self, other: &Traffic) {
        self.up_bytes += other.up_bytes;
        self.down_bytes += other.down_bytes;
        self.render_us += other.render_us;
        for (key, c) in &other.kinds {
            let e = self.kinds.entry(*key).or_default();
            e.frames += c.frames;
            e.bytes += c.bytes;
        }
    }

    /// One kind's count (zero when none passed).
    pub fn kind(&self, direction: Direction, kind: &str) -> Count {
        self.kinds
            .iter()
            .find(|((d, k), _)| *d == direction && *k == kind)
            .map(|(_, c)| *c)
            .unwrap_or_default()
    }
}

/// The first frame each way: the worker's `Hello`, the coordinator's `Welcome`.
pub const HANDSHAKE: &str = "handshake";
/// A frame whose variant index is not one of those below.
pub const OTHER: &str = "other";
/// `FromWorker` kinds by variant index (docs/protocol.md §5).
pub const UP_KINDS: [&str; 7] = [
    "tile results",
    "tile failures",
    "draining",
    "heartbeats",
    "canary results",
    "pongs",
    "compressed tile results",
];
/// `ToWorker` kinds by variant index.
pub const DOWN_KINDS: [&str; 8] = [
    "scenes",
    "render assignments",
    "cancels",
    "scene releases",
    "heartbeats",
    "canaries",
    "refusals",
    "pings",
];

/// Cuts one direction's byte stream into frames (4-byte big-endian length, then the
/// body) and counts them by their enum variant index, the body's first 4 bytes. Only the
/// variant index and, for a tile result, its `render_us` are read: the counts do not
/// depend on the rest of the message's layout.
struct FrameMeter {
    direction: Direction,
    buf: Vec<u8>,
    frames: u64,
}

impl FrameMeter {
    fn feed(&mut self, bytes: &[u8], traffic: &Mutex<Traffic>) {
        self.buf.extend_from_slice(bytes);
        let mut seen: Vec<(&'static str, u64, u64)> = Vec::new();
        let mut pos = 0;
        while self.buf.len() - pos >= 4 {
            let len =
                u32::from_be_bytes(self.buf[pos..pos + 4].try_into().expect("4 bytes")) as usize;
            if self.buf.len() - pos - 4 < len {
                break;
            }
            let body = &self.buf[pos + 4..pos + 4 + len];
            let (kind, render_us) = self.classify(body);
            seen.push((kind, 4 + len as u64, render_us));
            self.frames += 1;
            pos += 4 + len;
        }
        self.buf.drain(..pos);
        let mut t = traffic.lock().unwrap_or_else(|e| e.into_inner());
        match self.direction {
            Direction::Up => t.up_bytes += bytes.len() as u64,
            Direction::Down => t.down_bytes += bytes.len() as u64,
        }
        for (kind, bytes, render_us) in seen {
            let c = t.kinds.entry((self.direction, kind)).or_default();
            c.frames += 1;
            c.bytes += bytes;
            t.render_us += render_us;
        }
    }

    fn classify(&self, body: &[u8]) -> (&'static str, u64) {
        if self.frames == 0 {
            return (HANDSHAKE, 0);
        }
        let Some(index) = body
            .get(..4)
            .map(|b| u32::from_le_bytes(b.try_into().expect("4 bytes")) as usize)
        else {
            return (OTHER, 0);
        };
        let kinds: &[&'static str] = match self.direction {
            Direction::Up => &UP_KINDS,
            Direction::Down => &DOWN_KINDS,
        };
        let kind = kinds.get(index).copied().unwrap_or(OTHER);
        // TileDone and TileDoneZstd: variant u32, job u64, tile u32, pixels (u64
        // length, bytes), rays u64, render_us u64, ...
        let render_us = if self.direction == Direction::Up && (index == 0 || index == 6) {
            let read_u64 = |at: usize| {
                body.get(at..at + 8)
                    .map(|b| u64::from_le_bytes(b.try_into().expect("8 bytes")))
            };
            read_u64(16)
                .and_then(|rgb| usize::try_from(rgb).ok())
                .and_then(|rgb| read_u64(24 + rgb + 8))
                .unwrap_or(0)
        } else {
            0
        };
        (kind, render_us)
    }
}

/// A listening relay: each connection accepted is forwarded to `target` through the
/// link. Dropping it stops accepting; connections end when their peers close them.
pub struct Relay {
    address: SocketAddr,
    traffic: Arc<Mutex<Traffic>>,
    stop: Arc<AtomicBool>,
}

impl Relay {
    /// Listens on an ephemeral loopback port.
    pub fn start(target: SocketAddr, link: Link) -> io::Result<Relay> {
        let listener = TcpListener::bind("127.0.0.1:0")?;
        let address = listener.local_addr()?;
        let traffic = Arc::new(Mutex::new(Traffic::default()));
        let stop = Arc::new(AtomicBool::new(false));
        let (t, s) = (traffic.clone(), stop.clone());
        thread::Builder::new()
            .name("relay-accept".into())
            .spawn(move || {
                for client in listener.incoming() {
                    if s.load(Ordering::SeqCst) {
                        break;
                    }
                    let Ok(client) = client else { continue };
                    let t = t.clone();
                    let _ = thread::Builder::new()
                        .name("relay-connect".into())
                        .spawn(move || {
                            if let Err(e) = connect(client, target, link, t) {
                                eprintln!("relay: cannot reach {target}: {e}");
                            }
                        });
                }
            })?;
        Ok(Relay {
            address,
            traffic,
            stop,
        })
    }

    pub fn address(&self) -> SocketAddr {
        self.address
    }

    /// A snapshot of the counts so far.
    pub fn traffic(&self) -> Traffic {
        self.traffic
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .clone()
    }
}

impl Drop for Relay {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        // Wakes the accepting thread, which then sees the flag.
        let _ = TcpStream::connect(self.address);
    }
}

fn connect(
    client: TcpStream,
    target: SocketAddr,
    link: Link,
    traffic: Arc<Mutex<Traffic>>,
) -> io::Result<()> {
    let server = TcpStream::connect(target)?;
    client.set_nodelay(true)?;
    server.set_nodelay(true)?;
    pump(
        client.try_clone()?,
        server.try_clone()?,
        Direction::Up,
        link,
        traffic.clone(),
    )?;
    pump(server, client, Direction::Down, link, traffic)
}

/// Forwards `from` to `to` through the link, on two threads.
fn pump(
    mut from: TcpStream,
    mut to: TcpStream,
    direction: Direction,
    link: Link,
    traffic: Arc<Mutex<Traffic>>,
) -> io::Result<()> {
    let (tx, rx) = mpsc::channel::<(Instant, Vec<u8>)>();
    let from_writer = from.try_clone()?;
    thread::Builder::new()
        .name("relay-read".into())
        .spawn(move || {
            let mut meter = FrameMeter {
                direction,
                buf: Vec::new(),
                frames: 0,
            };
            let mut buf = vec![0u8; 256 * 1024];
            loop {
                match from.read(&mut buf) {
                    Ok(0) | Err(_) => break,
                    Ok(n) => {
                        let arrived = Instant::now();
                        if tx.send((arrived, buf[..n].to_vec())).is_err() {
                            break;
                        }
                        meter.feed(&buf[..n], &traffic);
                    }
                }
            }
            // Dropping `tx` tells the writer that the stream has ended.
        })?;
    thread::Builder::new()
        .name("relay-write".into())
        .spawn(move || {
            let mut link_free = Instant::now();
            for (arrived, chunk) in rx {
                let mut due = arrived;
                if let Some(bandwidth) = link.bandwidth {
                    let start = due.max(link_free);
                    link_free = start + Duration::from_secs_f64(chunk.len() as f64 / bandwidth);
                    due = link_free;
                }
                due += link.one_way;
                let now = Instant::now();
                if due > now {
                    thread::sleep(due - now);
                }
                if to.write_all(&chunk).is_err() {
                    let _ = from_writer.shutdown(Shutdown::Both);
                    return;
                }
            }
            let _ = to.shutdown(Shutdown::Write);
        })?;
    Ok(())
}

/// The relay's own cost and accuracy: median round trip of small messages to an echo
/// server directly, through a relay without delay, and through one set to `rtt`.
pub struct SelfTest {
    pub direct_us: f64,
    pub relayed_us: f64,
    pub rtt: Duration,
    pub delayed_us: f64,
}

/// Measures [`SelfTest`] with `trips` round trips each (a tenth of them for the delayed
/// relay, at least 5).
pub fn self_test(trips: usize, rtt: Duration) -> io::Result<SelfTest> {
    let echo = TcpListener::bind("127.0.0.1:0")?;
    let echo_address = echo.local_addr()?;
    thread::Builder::new()
        .name("relay-echo".into())
        .spawn(move || {
            for stream in echo.incoming() {
                let Ok(mut stream) = stream else { continue };
                let _ = stream.set_nodelay(true);
                thread::spawn(move || {
                    let mut buf = [0u8; 64];
                    while let Ok(n) = stream.read(&mut buf) {
                        if n == 0 || stream.write_all(&buf[..n]).is_err() {
                            break;
                        }
                    }
                });
            }
        })?;
    let median_rtt = |address: SocketAddr, trips: usize| -> io::Result<f64> {
        let mut s = TcpStream::connect(address)?;
        s.set_nodelay(true)?;
        let mut times = Vec::with_capacity(trips);
        let mut buf = [0u8; 64];
        for i in 0..trips + 2 {
            let started = Instant::now();
            s.write_all(&buf)?;
            s.read_exact(&mut buf)?;
            if i >= 2 {
                times.push(started.elapsed().as_secs_f64() * 1e6);
            }
        }
        times.sort_by(f64::total_cmp);
        Ok(times[times.len() / 2])
    };
    let direct_us = median_rtt(echo_address, trips)?;
    let plain = Relay::start(
        echo_address,
        Link {
            one_way: Duration::ZERO,
            bandwidth: None,
        },
    )?;
    let relayed_us = median_rtt(plain.address(), trips)?;
    let delayed = Relay::start(
        echo_address,
        Link {
            one_way: rtt / 2,
            bandwidth: None,
        },
    )?;
    let delayed_us = median_rtt(delayed.address(), (trips / 10).max(5))?;
    // The echo server's thread stays parked in `accept`; it holds nothing.
    Ok(SelfTest {
        direct_us,
        relayed_us,
        rtt,
        delayed_us,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(body: &[u8]) -> Vec<u8> {
        let mut f = (body.len() as u32).to_be_bytes().to_vec();
        f.extend_from_slice(body);
        f
    }

    #[test]
    fn frames_are_counted_by_kind_across_chunk_boundaries() {
        let traffic = Mutex::new(Traffic::default());
        let mut meter = FrameMeter {
            direction: Direction::Up,
            buf: Vec::new(),
            frames: 0,
        };
        let mut stream = frame(b"hello");
        // TileDone with 6 bytes of pixels and render_us = 1234.
        let mut done = 0u32.to_le_bytes().to_vec();
        done.extend_from_slice(&7u64.to_le_bytes());
        done.extend_from_slice(&3u32.to_le_bytes());
        done.extend_from_slice(&6u64.to_le_bytes());
        done.extend_from_slice(&[1, 2, 3, 4, 5, 6]);
        done.extend_from_slice(&99u64.to_le_bytes());
        done.extend_from_slice(&1234u64.to_le_bytes());
        done.extend_from_slice(&[0; 16]);
        stream.extend(frame(&done));
        stream.extend(frame(&3u32.to_le_bytes()));
        for chunk in stream.chunks(5) {
            meter.feed(chunk, &traffic);
        }
        let t = traffic.into_inner().unwrap();
        assert_eq!(t.up_bytes, stream.len() as u64);
        assert_eq!(t.kind(Direction::Up, HANDSHAKE).frames, 1);
        assert_eq!(
            t.kind(Direction::Up, "tile results"),
            Count {
                frames: 1,
                bytes: 4 + done.len() as u64
            }
        );
        assert_eq!(t.kind(Direction::Up, "heartbeats").bytes, 8);
        assert_eq!(t.render_us, 1234);
    }
}
