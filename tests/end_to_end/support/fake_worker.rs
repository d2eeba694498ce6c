//! A worker written in the test, on the real protocol: it connects with
//! `transport::dial` (no token, plain TCP on 127.0.0.1), or from another loopback
//! address with the same handshake done here ([`FakeWorker::start_from`]), renders the canary, its tiles
//! and its adaptive passes honestly with the `verify` and `render` crates, exactly as
//! a real worker does, and then lies as it is told: every pixel wrong, one byte of
//! some tiles (for an adaptive pass: one sum of each block of its state), one pixel
//! of every output (the canary included), as a worker with a different renderer would,
//! or frame 1 of an animated scene whatever the frame asked for.
//!
//! It runs on a thread of its own with a small tokio runtime, answers pings and sends
//! a heartbeat every second, and records what it was sent. Dropping it closes its
//! connection and joins its thread.

use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::{self, JoinHandle};
use std::time::{Duration, Instant};

use protocol::{
    CanaryFile, CanaryRender, FromWorker, Role, SceneHash, Settings, TileRect, ToWorker,
};
use tokio::io::{AsyncReadExt, AsyncWriteExt};

/// How the fake worker departs from an honest one.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Lie {
    /// Returns what it renders.
    Honest,
    /// Every pixel of every tile pure red (255, 0, 0).
    Red,
    /// One byte changed in every `n`th tile, starting with the first.
    OneByteEvery(u64),
    /// A renderer that differs: one pixel of every output changed, the canary's
    /// renders included.
    Perturbed,
    /// Renders frame 1 of the scene whatever frame it is asked for (what a worker
    /// that ignored the frame would return), honestly otherwise.
    FrameOne,
    /// Reports the first tile of this frame failed (`TileFailed`), as a worker that
    /// cannot render it would; honest with everything else.
    FailFrame(u32),
    /// Renders its first `n` tiles honestly, then keeps every further tile without
    /// answering (its heartbeats go on): a job stalls with exactly `n` of its tiles.
    SilentAfter(u64),
    /// Closes its connection when the canary comes, as a worker that gave up on a
    /// paused coordinator does (its connection was queued unanswered past its connect
    /// limit): a lost connection, not a wrong renderer.
    HangsUpAtCanary,
}

/// What the fake worker saw and did, shared with its thread.
#[derive(Default)]
struct State {
    stop: AtomicBool,
    /// Handshake accepted.
    connected: AtomicBool,
    /// The connection ended (closed by the coordinator, or an error).
    closed: AtomicBool,
    canaries: AtomicU64,
    /// `Render` and `Advance` messages received.
    tiles_assigned: AtomicU64,
    /// `TileDone` and `Advanced` sent.
    tiles_returned: AtomicU64,
    /// `TileDone` and `Advanced` sent.with pixels changed from the honest render.
    tiles_lied: AtomicU64,
    refusal: Mutex<Option<String>>,
    /// The name the coordinator said it joined under (`ToWorker::Joined`).
    joined_as: Mutex<Option<String>>,
    /// How the connection ended or failed, if it did.
    error: Mutex<Option<String>>,
}

/// A running fake worker; dropping it disconnects it.
pub struct FakeWorker {
    state: Arc<State>,
    thread: Option<JoinHandle<()>>,
}

impl FakeWorker {
    /// Connects to the coordinator at `addr` as worker `name` (one thread) announcing
    /// renderer build `build`, and serves it on a thread of its own.
    pub fn start(addr: &str, name: &str, build: &str, lie: Lie) -> FakeWorker {
        FakeWorker::start_from(None, addr, name, build, lie)
    }

    /// As [`FakeWorker::start`], connecting from the local address `source` (another
    /// loopback address such as 127.0.0.2 is another host to the coordinator).
    pub fn start_from(
        source: Option<std::net::IpAddr>,
        addr: &str,
        name: &str,
        build: &str,
        lie: Lie,
    ) -> FakeWorker {
        let state = Arc::new(State::default());
        let (addr, name, build) = (addr.to_owned(), name.to_owned(), build.to_owned());
        let shared = Arc::clone(&state);
        let thread = thread::Builder::new()
            .name(format!("fake worker {name}"))
            .spawn(move || {
                let runtime = tokio::runtime::Builder::new_current_thread()
                    .enable_all()
                    .build()
                    .expect("cannot start the fake worker's runtime");
                let outcome = runtime.block_on(serve(source, &addr, name, build, lie, &shared));
                if let Err(e) = outcome {
                    *shared.error.lock().expect("error slot") = Some(e);
                }
                shared.closed.store(true, Ordering::SeqCst);
            })
            .expect("cannot start the fake worker's thread");
        FakeWorker {
            state,
            thread: Some(thread),
        }
    }

    pub fn connected(&self) -> bool {
        self.state.connected.load(Ordering::SeqCst)
    }

    /// Whether its connection has ended.
    pub fn closed(&self) -> bool {
        self.state.closed.load(Ordering::SeqCst)
    }

    pub fn canaries(&self) -> u64 {
        self.state.canaries.load(Ordering::SeqCst)
    }

    pub fn tiles_assigned(&self) -> u64 {
        self.state.tiles_assigned.load(Ordering::SeqCst)
    }

    pub fn tiles_returned(&self) -> u64 {
        self.state.tiles_returned.load(Ordering::SeqCst)
    }

    pub fn tiles_lied(&self) -> u64 {
        self.state.tiles_lied.load(Ordering::SeqCst)
    }

    /// The reason of the `Refuse` it was sent, if any.
    pub fn refusal(&self) -> Option<String> {
        self.state.refusal.lock().expect("refusal slot").clone()
    }

    /// The name the coordinator said it joined under, once it joined.
    pub fn joined_as(&self) -> Option<String> {
        self.state.joined_as.lock().expect("name slot").clone()
    }

    /// How its connection ended, if it ended with an error.
    pub fn error(&self) -> Option<String> {
        self.state.error.lock().expect("error slot").clone()
    }

    /// Waits until its connection has ended, at most `timeout`.
    pub fn wait_closed(&self, timeout: Duration) -> bool {
        let deadline = Instant::now() + timeout;
        while !self.closed() {
            if Instant::now() >= deadline {
                return false;
            }
            thread::sleep(Duration::from_millis(10));
        }
        true
    }
}

impl Drop for FakeWorker {
    fn drop(&mut self) {
        self.state.stop.store(true, Ordering::SeqCst);
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

/// One connection, until the coordinator closes it or the fake is dropped.
async fn serve(
    source: Option<std::net::IpAddr>,
    addr: &str,
    name: String,
    build: String,
    lie: Lie,
    state: &State,
) -> Result<(), String> {
    let role = Role::Worker {
        name,
        threads: 1,
        build,
        tags: Vec::new(),
    };
    let (io, early) = match source {
        None => {
            let raw = transport::dial(&transport::Endpoint::plain(addr), role)
                .await
                .map_err(|e| format!("cannot connect: {:#}", e.into_inner()))?;
            // Frames by hand (4-byte big-endian length, then bincode), starting with
            // whatever the handshake's framing already read.
            let parts = raw.into_parts();
            (parts.io, parts.read_buf.to_vec())
        }
        Some(source) => dial_from(source, addr, role).await?,
    };
    state.connected.store(true, Ordering::SeqCst);
    let (mut reader, mut writer) = tokio::io::split(io);
    let (frames_tx, mut frames) = tokio::sync::mpsc::unbounded_channel::<Result<Vec<u8>, String>>();
    tokio::spawn(async move {
        let mut buf = early;
        let mut chunk = vec![0u8; 64 * 1024];
        loop {
            while buf.len() >= 4 {
                let len = u32::from_be_bytes([buf[0], buf[1], buf[2], buf[3]]) as usize;
                if buf.len() < 4 + len {
                    break;
                }
                let body = buf[4..4 + len].to_vec();
                buf.drain(..4 + len);
                if frames_tx.send(Ok(body)).is_err() {
                    return;
                }
            }
            match reader.read(&mut chunk).await {
                Ok(0) => {
                    let _ = frames_tx.send(Err("the coordinator closed the connection".into()));
                    return;
                }
                Ok(n) => buf.extend_from_slice(&chunk[..n]),
                Err(e) => {
                    let _ = frames_tx.send(Err(format!("cannot read: {e}")));
                    return;
                }
            }
        }
    });
    let mut scenes: HashMap<SceneHash, render::AnimatedScene> = HashMap::new();
    let mut heartbeat = tokio::time::interval(Duration::from_secs(1));
    let mut check_stop = tokio::time::interval(Duration::from_millis(20));
    loop {
        if state.stop.load(Ordering::SeqCst) {
            let _ = writer.shutdown().await;
            return Ok(());
        }
        let frame = tokio::select! {
            frame = frames.recv() => frame,
            _ = heartbeat.tick() => {
                send(&mut writer, &FromWorker::Heartbeat).await?;
                continue;
            }
            _ = check_stop.tick() => continue,
        };
        let body = match frame {
            Some(Ok(body)) => body,
            Some(Err(end)) => {
                // A refused worker's connection is closed after the refusal: expected.
                let refused = state.refusal.lock().expect("refusal slot").is_some();
                return if refused { Ok(()) } else { Err(end) };
            }
            None => return Err("the reader stopped".into()),
        };
        let message: ToWorker = protocol::wire::decode(&body)
            .map_err(|e| format!("unreadable message from the coordinator: {e}"))?;
        let answer = match message {
            ToWorker::Canary { .. } if lie == Lie::HangsUpAtCanary => {
                let _ = writer.shutdown().await;
                return Ok(());
            }
            ToWorker::Canary {
                scene,
                files,
                renders,
            } => {
                state.canaries.fetch_add(1, Ordering::SeqCst);
                let images = render_canary(&scene, &files, &renders).map(|mut images| {
                    if lie == Lie::Perturbed {
                        for image in &mut images {
                            perturb(image, 0);
                        }
                    }
                    images
                });
                Some(FromWorker::CanaryDone { images })
            }
            // The fake worker's scenes name no file.
            ToWorker::Scene { hash, scene, .. } => {
                let parsed = render::parse_animated(&scene)
                    .map_err(|e| format!("the coordinator sent a bad scene: {e}"))?;
                scenes.insert(hash, parsed);
                None
            }
            ToWorker::ForgetScene { hash } => {
                scenes.remove(&hash);
                None
            }
            ToWorker::Ping { token } => Some(FromWorker::Pong { token }),
            ToWorker::Refuse { reason } => {
                *state.refusal.lock().expect("refusal slot") = Some(reason);
                None
            }
            // The fake worker is stopped by its test, never drained.
            ToWorker::Joined { name } => {
                *state.joined_as.lock().expect("name slot") = Some(name);
                None
            }
            ToWorker::Heartbeat
            | ToWorker::Cancel { .. }
            | ToWorker::Drain
            | ToWorker::AssetChunk { .. }
            | ToWorker::AssetUnavailable { .. } => None,
            ToWorker::Advance {
                job,
                tile,
                scene,
                frame,
                settings,
                rect,
                pass,
                rung,
                previous,
            } => {
                let nth = state.tiles_assigned.fetch_add(1, Ordering::SeqCst);
                let scene = scenes
                    .get(&scene)
                    .ok_or_else(|| format!("tile {tile} of job {job} before its scene"))?;
                let started = Instant::now();
                let scene = frame_of(scene, frame, lie)?;
                let tracer = verify::tracer(&scene, &settings)?;
                let previous = previous
                    .map(|p| verify::adaptive::unpack_state(&p, rect, settings.aa))
                    .transpose()?;
                let footprints = verify::adaptive::footprints(&tracer);
                let mut advanced =
                    verify::adaptive::advance(&tracer, footprints, rect, previous, rung)?;
                let lied = match lie {
                    Lie::Honest
                    | Lie::FailFrame(_)
                    | Lie::HangsUpAtCanary
                    | Lie::SilentAfter(_) => false,
                    Lie::FrameOne => frame != 1,
                    Lie::Red => {
                        for pixel in advanced.rgb.chunks_exact_mut(3) {
                            pixel.copy_from_slice(&[255, 0, 0]);
                        }
                        true
                    }
                    Lie::OneByteEvery(n) if !nth.is_multiple_of(n) => false,
                    Lie::OneByteEvery(_) | Lie::Perturbed => {
                        // Pixels that agree with the state, a state a hair off: what
                        // only advancing a block again can tell.
                        for block in &mut advanced.blocks {
                            block.sums[0][0][0] += 1.0 / 1024.0;
                        }
                        true
                    }
                };
                state.tiles_returned.fetch_add(1, Ordering::SeqCst);
                if lied {
                    state.tiles_lied.fetch_add(1, Ordering::SeqCst);
                }
                Some(FromWorker::Advanced {
                    job,
                    tile,
                    pass,
                    rung,
                    zstd: zstd::bulk::compress(&advanced.rgb, 1)
                        .map_err(|e| format!("cannot compress: {e}"))?,
                    state: verify::adaptive::encode_state(&advanced.blocks),
                    rays: advanced.rays,
                    render_us: started.elapsed().as_micros() as u64,
                })
            }
            ToWorker::Render {
                job,
                tile,
                scene,
                frame,
                settings,
                rect,
            } => {
                let nth = state.tiles_assigned.fetch_add(1, Ordering::SeqCst);
                let scene = scenes
                    .get(&scene)
                    .ok_or_else(|| format!("tile {tile} of job {job} before its scene"))?;
                if lie == Lie::FailFrame(frame) && tile == 0 {
                    send(
                        &mut writer,
                        &FromWorker::TileFailed {
                            job,
                            tile,
                            message: format!("this machine cannot render frame {frame}"),
                        },
                    )
                    .await?;
                    continue;
                }
                if matches!(lie, Lie::SilentAfter(n) if nth >= n) {
                    continue;
                }
                let started = Instant::now();
                let scene = frame_of(scene, frame, lie)?;
                let mut image = render_tile(&scene, &settings, rect)?;
                let lied = match lie {
                    Lie::Honest
                    | Lie::FailFrame(_)
                    | Lie::HangsUpAtCanary
                    | Lie::SilentAfter(_) => false,
                    Lie::FrameOne => frame != 1,
                    Lie::Red => {
                        for pixel in image.rgb.chunks_exact_mut(3) {
                            pixel.copy_from_slice(&[255, 0, 0]);
                        }
                        true
                    }
                    Lie::OneByteEvery(n) if nth.is_multiple_of(n) => {
                        perturb(&mut image.rgb, nth as usize);
                        true
                    }
                    Lie::OneByteEvery(_) => false,
                    Lie::Perturbed => {
                        perturb(&mut image.rgb, nth as usize);
                        true
                    }
                };
                state.tiles_returned.fetch_add(1, Ordering::SeqCst);
                if lied {
                    state.tiles_lied.fetch_add(1, Ordering::SeqCst);
                }
                Some(FromWorker::TileDone {
                    job,
                    tile,
                    rgb: image.rgb,
                    rays: image.rays,
                    render_us: started.elapsed().as_micros() as u64,
                    samples: image.samples,
                    error_sq_sum: image.error_sq_sum,
                })
            }
        };
        if let Some(answer) = answer {
            send(&mut writer, &answer).await?;
        }
    }
}

/// Connects to `addr` from the local address `source` and handshakes as `role` (no
/// token, plain TCP), as `transport::dial` does: the connection and what was read
/// past the coordinator's `Accepted`.
async fn dial_from(
    source: std::net::IpAddr,
    addr: &str,
    role: Role,
) -> Result<(transport::Stream, Vec<u8>), String> {
    let socket = tokio::net::TcpSocket::new_v4().map_err(|e| format!("no socket: {e}"))?;
    socket
        .bind((source, 0).into())
        .map_err(|e| format!("cannot bind {source}: {e}"))?;
    let to = addr.parse().map_err(|e| format!("{addr}: {e}"))?;
    let mut tcp = socket
        .connect(to)
        .await
        .map_err(|e| format!("cannot connect from {source}: {e}"))?;
    let mut handshake = protocol::PeerHandshake::new(role, None, [7; 32]);
    tcp.write_all(&super::wire::frame(&handshake.hello()))
        .await
        .map_err(|e| format!("cannot send: {e}"))?;
    let mut buf = Vec::new();
    let mut chunk = [0u8; 4096];
    loop {
        while buf.len() >= 4 {
            let len = u32::from_be_bytes([buf[0], buf[1], buf[2], buf[3]]) as usize;
            if buf.len() < 4 + len {
                break;
            }
            let body: Vec<u8> = buf.drain(..4 + len).skip(4).collect();
            match handshake.on_frame(&body) {
                Ok(protocol::PeerStep::Accepted) => return Ok((Box::new(tcp), buf)),
                Ok(protocol::PeerStep::Send(proof)) => tcp
                    .write_all(&super::wire::frame(&proof))
                    .await
                    .map_err(|e| format!("cannot send: {e}"))?,
                Err(e) => return Err(format!("refused: {e}")),
            }
        }
        match tcp.read(&mut chunk).await {
            Ok(0) => return Err("the coordinator closed the connection".into()),
            Ok(n) => buf.extend_from_slice(&chunk[..n]),
            Err(e) => return Err(format!("cannot read: {e}")),
        }
    }
}

async fn send(
    writer: &mut (impl tokio::io::AsyncWrite + Unpin),
    message: &FromWorker,
) -> Result<(), String> {
    writer
        .write_all(&super::wire::frame(&protocol::wire::encode(message)))
        .await
        .map_err(|e| format!("cannot send: {e}"))
}

/// Changes one byte of the pixels (chosen by `seed`), so that it always differs.
fn perturb(rgb: &mut [u8], seed: usize) {
    let at = (seed.wrapping_mul(7919) + rgb.len() / 2) % rgb.len();
    rgb[at] ^= 0x01;
}

/// The frame of the scene to render: the one asked for, or frame 1 for
/// [`Lie::FrameOne`].
fn frame_of(scene: &render::AnimatedScene, frame: u32, lie: Lie) -> Result<render::Scene, String> {
    let frame = if lie == Lie::FrameOne { 1 } else { frame };
    scene.frame(u64::from(frame)).map_err(|e| e.to_string())
}

/// Renders one rectangle honestly, as a real worker does.
fn render_tile(
    scene: &render::Scene,
    settings: &Settings,
    rect: TileRect,
) -> Result<render::TileImage, String> {
    let tracer = verify::tracer(scene, settings)?;
    render::render_tile(&tracer, verify::render_rect(rect)).map_err(|e| e.to_string())
}

/// Renders the canary as a real worker does: one RGB8 buffer per render.
fn render_canary(
    scene: &str,
    files: &[CanaryFile],
    renders: &[CanaryRender],
) -> Result<Vec<Vec<u8>>, String> {
    verify::canary::render(scene, files, renders)
}
