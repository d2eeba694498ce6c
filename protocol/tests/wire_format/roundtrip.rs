//! Round trips and hostile input for the wire format, the framing and the handshake.
//!
//! What is proven, and why it matters:
//! - **Round trip.** Every message type (`ToWorker`, `FromWorker`, `ClientRequest`,
//!   `ClientResponse`, `Hello`, `Welcome`) comes back equal from `wire::encode` then
//!   `wire::decode`, and from `MessageCodec` with several messages back to back fed in
//!   arbitrary chunks: TCP delivers bytes, not frames, so a peer must reassemble the same
//!   messages whatever the segmentation.
//! - **Canonical, self-delimiting encoding.** A strict prefix of a message, or a message
//!   with trailing bytes, is refused; bytes that do decode are exactly the encoding of
//!   what they decode to. So a frame holds one message and only one meaning.
//! - **Hostile input (invariant 6).** A length prefix above the frame limit is refused
//!   from the 4 prefix bytes alone; a truncated frame asks for more bytes instead of
//!   producing a message; garbage in a well-sized frame is an error, never a panic; a
//!   vector or string length claimed far beyond the frame is refused without allocating
//!   it (checked with a tracking allocator).
//! - **Handshake (invariant 7).** `Hello::from_frame` tells a non-Tessera peer
//!   (`BadMagic`) from a Tessera peer of another version (`VersionMismatch`, whose message
//!   names both versions), and accepts this version's own hello for any role.

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::fmt::Debug;

use bytes::BytesMut;
use proptest::prelude::*;
use protocol::{
    wire, AssetAnswer, AssetKey, AssetRef, AssetRequest, CanaryFile, CanaryRender, ClientRequest,
    ClientResponse, FrameError, FrameFailure, FrameProgress, FrameRange, FromWorker, Hello,
    HelloError, JobAssets, JobEvent, JobSpec, JobState, JobStatus, KeyId, KeyStanding, Lacking,
    MessageCodec, Overrides, PeerKey, Refusal, RefusalKind, Role, Sampling, Settings, TileRect,
    ToWorker, Verification, Welcome, WorkerCache, WorkerStatus, DEFAULT_MAX_FRAME, MAGIC,
    MAX_FRAME_LIMIT, PROTOCOL_VERSION,
};
use serde::{de::DeserializeOwned, Serialize};
use tokio_util::codec::{Decoder, Encoder};

use crate::frame;

// ---------------------------------------------------------------------------------------
// A tracking allocator: the largest single allocation made by the current thread, so that
// "refused without allocating what the peer claims" is checked, not assumed.

struct Tracking;

thread_local! {
    static LARGEST: Cell<usize> = const { Cell::new(0) };
}

fn note(size: usize) {
    // `try_with`: the slot may be gone while the thread is being torn down.
    let _ = LARGEST.try_with(|largest| largest.set(largest.get().max(size)));
}

// SAFETY: every method forwards to the system allocator with the same arguments; the
// tracking only reads the sizes, into a thread-local `Cell` that never allocates.
unsafe impl GlobalAlloc for Tracking {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        note(layout.size());
        System.alloc(layout)
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        note(layout.size());
        System.alloc_zeroed(layout)
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        System.dealloc(ptr, layout)
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        note(new_size);
        System.realloc(ptr, layout, new_size)
    }
}

#[global_allocator]
static ALLOCATOR: Tracking = Tracking;

/// Runs `f` and returns its result with the largest single allocation it made.
fn largest_allocation<R>(f: impl FnOnce() -> R) -> (R, usize) {
    LARGEST.with(|largest| largest.set(0));
    let result = f();
    (result, LARGEST.with(Cell::get))
}

/// What serde may reserve up front for a sequence whatever length is claimed
/// (`serde::__private::size_hint::cautious`): 1 MiB.
const SERDE_PREALLOCATION_CAP: usize = 1024 * 1024;

// ---------------------------------------------------------------------------------------
// Strategies.

fn text() -> impl Strategy<Value = String> {
    "(?s:.{0,100})"
}

fn blob() -> impl Strategy<Value = Vec<u8>> {
    prop::collection::vec(any::<u8>(), 0..2000)
}

/// Every `f64` but NaN, so that `PartialEq` can judge the round trip (NaN's bits are
/// checked separately in `nan_rates_keep_their_bits`).
fn rate() -> impl Strategy<Value = f64> {
    use prop::num::f64::*;
    POSITIVE | NEGATIVE | NORMAL | SUBNORMAL | ZERO | INFINITE
}

/// Every sampler, with any target: the encoding must carry out-of-range targets too
/// (refusing them is the coordinator's job).
fn sampling() -> impl Strategy<Value = Sampling> {
    prop_oneof![
        Just(Sampling::Grid),
        Just(Sampling::Jittered),
        any::<u32>().prop_map(|target_milli| Sampling::Adaptive { target_milli }),
    ]
}

prop_compose! {
    fn settings()(width in any::<u32>(), height in any::<u32>(), aa in any::<u32>(),
                  max_depth in any::<u32>(), sampling in sampling()) -> Settings {
        Settings { width, height, aa, max_depth, sampling }
    }
}

prop_compose! {
    fn rect()(x in any::<u32>(), y in any::<u32>(), width in any::<u32>(),
              height in any::<u32>()) -> TileRect {
        TileRect { x, y, width, height }
    }
}

prop_compose! {
    fn overrides()(width in any::<Option<u32>>(), height in any::<Option<u32>>(),
                   aa in any::<Option<u32>>(), max_depth in any::<Option<u32>>(),
                   tile_size in any::<Option<u32>>(),
                   sampling in prop::option::of(sampling())) -> Overrides {
        Overrides { width, height, aa, max_depth, tile_size, sampling }
    }
}

prop_compose! {
    fn job_spec()(scene in text(), overrides in overrides(), priority in any::<i32>(),
                  full in any::<bool>(), time_limit_ms in any::<Option<u64>>(),
                  name in text(), frame in any::<u32>(),
                  frames in prop::option::of(frame_range()),
                  assets in prop::collection::vec(asset_ref(), 0..3),
                  after in prop::collection::vec(any::<u64>(), 0..4),
                  require in prop::collection::vec(text(), 0..3))
                 -> JobSpec {
        let verification = if full { Verification::Full } else { Verification::Sampled };
        JobSpec {
            scene, overrides, priority, verification, time_limit_ms,
            name: name.clone(), submitter: name, frame, frames, assets, after, require,
        }
    }
}

fn asset_key() -> impl Strategy<Value = AssetKey> {
    (any::<[u8; 32]>(), any::<u64>()).prop_map(|(sha256, size)| AssetKey { sha256, size })
}

fn asset_ref() -> impl Strategy<Value = AssetRef> {
    (text(), asset_key()).prop_map(|(name, key)| AssetRef { name, key })
}

fn asset_request() -> impl Strategy<Value = AssetRequest> {
    prop_oneof![
        prop::collection::vec(asset_key(), 0..4).prop_map(|keys| AssetRequest::Lacking { keys }),
        (asset_key(), any::<u64>(), blob()).prop_map(|(key, offset, bytes)| AssetRequest::Upload {
            key,
            offset,
            bytes
        }),
    ]
}

fn asset_answer() -> impl Strategy<Value = AssetAnswer> {
    prop_oneof![
        prop::collection::vec(
            (asset_key(), any::<u64>()).prop_map(|(key, received)| Lacking { key, received }),
            0..4
        )
        .prop_map(|lacking| AssetAnswer::Lacking { lacking }),
        (asset_key(), any::<u64>(), any::<bool>()).prop_map(|(key, received, complete)| {
            AssetAnswer::Received {
                key,
                received,
                complete,
            }
        }),
        prop::collection::vec(asset_key(), 0..4)
            .prop_map(|lacking| AssetAnswer::SubmitLacking { lacking }),
    ]
}

prop_compose! {
    fn frame_range()(first in any::<u32>(), last in any::<u32>()) -> FrameRange {
        FrameRange { first, last }
    }
}

prop_compose! {
    fn frame_progress()(
        first in any::<u32>(), last in any::<u32>(), scene_frames in any::<u32>(),
        done in any::<u32>(),
        active in any::<u32>(), pending in any::<u32>(), cancelled in any::<u32>(),
        done_prefix in any::<u32>(), failed in any::<u32>(),
        failures in prop::collection::vec(
            (any::<u32>(), any::<u64>(), text())
                .prop_map(|(frame, job, error)| FrameFailure { frame, job, error }),
            0..3,
        ),
    ) -> FrameProgress {
        FrameProgress {
            first, last, scene_frames, done, active, pending, cancelled, done_prefix, failed,
            failures,
        }
    }
}

fn job_state() -> impl Strategy<Value = JobState> {
    prop_oneof![
        Just(JobState::Queued),
        Just(JobState::Running),
        Just(JobState::Done),
        Just(JobState::Failed),
        Just(JobState::Cancelled),
        Just(JobState::Waiting),
    ]
}

prop_compose! {
    fn job_status()(
        id in any::<u64>(), state in job_state(), settings in settings(),
        priority in any::<i32>(), tiles_done in any::<u32>(), tiles_total in any::<u32>(),
        rays in any::<u64>(), elapsed_ms in any::<u64>(), eta_ms in any::<Option<u64>>(),
        error in prop::option::of(text()), samples in any::<u64>(),
        estimated_error in prop::option::of(rate()),
        time_limit_ms in any::<Option<u64>>(), stopped_on_time_limit in any::<bool>(),
        paused in any::<bool>(), warning in prop::option::of(text()),
        name in text(), submitter in text(),
        submitted_from in text(), submitted_unix_ms in any::<u64>(),
        queued_ms in any::<Option<u64>>(), frame in any::<u32>(),
        frames in prop::option::of(frame_progress()), sequence in any::<Option<u64>>(),
        asset_files in any::<u32>(), asset_bytes in any::<u64>(),
        after in prop::collection::vec(any::<u64>(), 0..4),
        waiting_for in prop::collection::vec(any::<u64>(), 0..4),
        require in prop::collection::vec(text(), 0..3),
    ) -> JobStatus {
        JobStatus {
            id, state, settings, priority, tiles_done, tiles_total, rays, elapsed_ms,
            eta_ms, error, samples, estimated_error, time_limit_ms, stopped_on_time_limit,
            paused, warning, name, submitter, submitted_from, submitted_unix_ms, queued_ms,
            frame, frames, sequence,
            assets: JobAssets { files: asset_files, bytes: asset_bytes }, after, waiting_for,
            require,
        }
    }
}

prop_compose! {
    fn worker_status()(
        id in any::<u64>(), name in text(), threads in any::<u32>(),
        tiles_in_flight in any::<u32>(), tiles_done in any::<u64>(), rays in any::<u64>(),
        connected_ms in any::<u64>(), rays_per_second in rate(), build in text(),
        quarantined in prop::option::of(text()), rtt_us in any::<Option<u64>>(),
        credit in any::<u32>(), draining in any::<bool>(), disabled in any::<bool>(),
        unresponsive in any::<bool>(),
        key in prop::option::of((any::<[u8; 4]>(), any::<bool>())), host in text(),
        cache in prop::option::of(worker_cache()), tags in prop::collection::vec(text(), 0..3),
    ) -> WorkerStatus {
        let key = key.map(|(id, current)| PeerKey {
            id: KeyId(id),
            standing: if current { KeyStanding::Current } else { KeyStanding::Previous },
        });
        WorkerStatus {
            id, name, threads, tiles_in_flight, tiles_done, rays, connected_ms,
            rays_per_second, build, quarantined, rtt_us, credit, draining, disabled,
            unresponsive, key, host, cache, tags,
        }
    }
}

prop_compose! {
    fn worker_cache()(
        files in any::<u64>(), bytes in any::<u64>(), capacity in any::<u64>(),
        fetching in any::<u32>(), fetching_received in any::<u64>(),
        fetching_total in any::<u64>(), fetched_bytes in any::<u64>(),
        geometry_triangles in any::<u64>(), problem in prop::option::of(text()),
    ) -> WorkerCache {
        WorkerCache {
            files, bytes, capacity, fetching, fetching_received, fetching_total,
            fetched_bytes, geometry_triangles, problem,
        }
    }
}

fn to_worker() -> impl Strategy<Value = ToWorker> {
    prop_oneof![
        (
            any::<[u8; 32]>(),
            text(),
            prop::collection::vec(asset_ref(), 0..3)
        )
            .prop_map(|(hash, scene, assets)| ToWorker::Scene {
                hash,
                scene,
                assets
            }),
        (asset_key(), any::<u64>(), blob()).prop_map(|(key, offset, bytes)| ToWorker::AssetChunk {
            key,
            offset,
            bytes
        }),
        (asset_key(), text()).prop_map(|(key, reason)| ToWorker::AssetUnavailable { key, reason }),
        (
            any::<u64>(),
            any::<u32>(),
            any::<[u8; 32]>(),
            any::<u32>(),
            settings(),
            rect()
        )
            .prop_map(
                |(job, tile, scene, frame, settings, rect)| ToWorker::Render {
                    job,
                    tile,
                    scene,
                    frame,
                    settings,
                    rect
                }
            ),
        any::<u64>().prop_map(|job| ToWorker::Cancel { job }),
        any::<[u8; 32]>().prop_map(|hash| ToWorker::ForgetScene { hash }),
        Just(ToWorker::Heartbeat),
        (
            text(),
            prop::collection::vec(
                (text(), prop::collection::vec(any::<u8>(), 0..64))
                    .prop_map(|(name, bytes)| CanaryFile { name, bytes }),
                0..3
            ),
            prop::collection::vec(
                (settings(), rect()).prop_map(|(settings, rect)| CanaryRender { settings, rect }),
                0..5
            )
        )
            .prop_map(|(scene, files, renders)| ToWorker::Canary {
                scene,
                files,
                renders
            }),
        text().prop_map(|reason| ToWorker::Refuse { reason }),
        any::<u64>().prop_map(|token| ToWorker::Ping { token }),
        (
            (any::<u64>(), any::<u32>(), any::<[u8; 32]>(), any::<u32>()),
            settings(),
            rect(),
            (any::<u32>(), any::<u32>(), prop::option::of(blob()))
        )
            .prop_map(
                |((job, tile, scene, frame), settings, rect, (pass, rung, previous))| {
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
                    }
                }
            ),
        Just(ToWorker::Drain),
        text().prop_map(|name| ToWorker::Joined { name }),
    ]
}

fn from_worker() -> impl Strategy<Value = FromWorker> {
    prop_oneof![
        (
            any::<u64>(),
            any::<u32>(),
            blob(),
            any::<u64>(),
            any::<u64>(),
            any::<u64>(),
            rate()
        )
            .prop_map(|(job, tile, rgb, rays, render_us, samples, error_sq_sum)| {
                FromWorker::TileDone {
                    job,
                    tile,
                    rgb,
                    rays,
                    render_us,
                    samples,
                    error_sq_sum,
                }
            }),
        (any::<u64>(), any::<u32>(), text())
            .prop_map(|(job, tile, message)| { FromWorker::TileFailed { job, tile, message } }),
        Just(FromWorker::Draining),
        Just(FromWorker::Heartbeat),
        (asset_key(), any::<u64>())
            .prop_map(|(key, offset)| FromWorker::FetchAsset { key, offset }),
        worker_cache().prop_map(FromWorker::Cache),
        prop_oneof![
            prop::collection::vec(blob(), 0..4).prop_map(Ok),
            text().prop_map(Err),
        ]
        .prop_map(|images| FromWorker::CanaryDone { images }),
        any::<u64>().prop_map(|token| FromWorker::Pong { token }),
        (
            any::<u64>(),
            any::<u32>(),
            blob(),
            any::<u64>(),
            any::<u64>(),
            any::<u64>(),
            rate()
        )
            .prop_map(
                |(job, tile, zstd, rays, render_us, samples, error_sq_sum)| {
                    FromWorker::TileDoneZstd {
                        job,
                        tile,
                        zstd,
                        rays,
                        render_us,
                        samples,
                        error_sq_sum,
                    }
                }
            ),
        (
            (any::<u64>(), any::<u32>(), any::<u32>(), any::<u32>()),
            blob(),
            blob(),
            (any::<u64>(), any::<u64>())
        )
            .prop_map(
                |((job, tile, pass, rung), zstd, state, (rays, render_us))| FromWorker::Advanced {
                    job,
                    tile,
                    pass,
                    rung,
                    zstd,
                    state,
                    rays,
                    render_us
                }
            ),
    ]
}

fn client_request() -> impl Strategy<Value = ClientRequest> {
    prop_oneof![
        job_spec().prop_map(ClientRequest::Submit),
        any::<u64>().prop_map(|job| ClientRequest::Status { job }),
        Just(ClientRequest::List),
        any::<u64>().prop_map(|job| ClientRequest::Cancel { job }),
        (any::<u64>(), any::<u64>()).prop_map(|(job, offset)| ClientRequest::Fetch { job, offset }),
        Just(ClientRequest::Workers),
        (
            any::<u64>(),
            any::<u32>(),
            any::<Option<u32>>(),
            any::<Option<u64>>()
        )
            .prop_map(
                |(job, target_milli, aa, time_limit_ms)| ClientRequest::Refine {
                    job,
                    target_milli,
                    aa,
                    time_limit_ms,
                }
            ),
        (any::<u64>(), any::<u32>())
            .prop_map(|(job, after_tiles)| ClientRequest::Watch { job, after_tiles }),
        any::<u64>().prop_map(|job| ClientRequest::Pause { job }),
        any::<u64>().prop_map(|job| ClientRequest::Resume { job }),
        (any::<u64>(), any::<i32>())
            .prop_map(|(job, priority)| ClientRequest::SetPriority { job, priority }),
        text().prop_map(|worker| ClientRequest::DrainWorker { worker }),
        text().prop_map(|worker| ClientRequest::DisableWorker { worker }),
        text().prop_map(|worker| ClientRequest::EnableWorker { worker }),
        (any::<u64>(), any::<u64>()).prop_map(|(job, after)| ClientRequest::Events { job, after }),
        any::<u64>().prop_map(|job| ClientRequest::Retry { job }),
        (any::<u64>(), prop::collection::vec(any::<u32>(), 0..5))
            .prop_map(|(job, tiles)| ClientRequest::Requeue { job, tiles }),
        (any::<u64>(), any::<u32>(), any::<u64>())
            .prop_map(|(job, frame, offset)| ClientRequest::FetchFrame { job, frame, offset }),
        (any::<u64>(), any::<u32>())
            .prop_map(|(job, frame)| ClientRequest::RequeueFrame { job, frame }),
        asset_request().prop_map(ClientRequest::Assets),
    ]
}

fn client_response() -> impl Strategy<Value = ClientResponse> {
    prop_oneof![
        any::<u64>().prop_map(|job| ClientResponse::Submitted { job }),
        job_status().prop_map(ClientResponse::Job),
        prop::collection::vec(job_status(), 0..5).prop_map(ClientResponse::Jobs),
        any::<u64>().prop_map(|job| ClientResponse::Cancelled { job }),
        (any::<u64>(), any::<u64>(), any::<u64>(), blob()).prop_map(
            |(job, total, offset, bytes)| ClientResponse::ImageChunk {
                job,
                total,
                offset,
                bytes
            }
        ),
        prop::collection::vec(worker_status(), 0..5).prop_map(ClientResponse::Workers),
        (
            prop_oneof![
                Just(RefusalKind::Invalid),
                Just(RefusalKind::NotFound),
                Just(RefusalKind::State),
                Just(RefusalKind::Limit),
                Just(RefusalKind::Unavailable),
                Just(RefusalKind::Internal),
            ],
            text()
        )
            .prop_map(|(kind, message)| ClientResponse::Error(Refusal::new(kind, message))),
        (
            any::<u64>(),
            prop::collection::vec((any::<u64>(), any::<u64>(), text(), text()), 0..4)
        )
            .prop_map(|(job, events)| ClientResponse::Events {
                job,
                events: events
                    .into_iter()
                    .map(|(seq, unix_ms, kind, detail)| JobEvent {
                        seq,
                        unix_ms,
                        kind,
                        detail
                    })
                    .collect(),
            }),
        asset_answer().prop_map(ClientResponse::Assets),
    ]
}

fn role() -> impl Strategy<Value = Role> {
    prop_oneof![
        Just(Role::Client),
        (
            text(),
            any::<u32>(),
            text(),
            prop::collection::vec(text(), 0..3)
        )
            .prop_map(|(name, threads, build, tags)| {
                Role::Worker {
                    name,
                    threads,
                    build,
                    tags,
                }
            }),
    ]
}

prop_compose! {
    /// Any hello, also with a foreign magic or version: the encoding must carry them too.
    fn hello()(
        magic in any::<[u8; 4]>(),
        version in any::<u16>(),
        role in role(),
        nonce in any::<[u8; 32]>(),
        key in prop::option::of(any::<[u8; 4]>()),
    ) -> Hello {
        Hello { magic, version, role, nonce, key: key.map(KeyId) }
    }
}

fn welcome() -> impl Strategy<Value = Welcome> {
    prop_oneof![
        any::<u16>().prop_map(|version| Welcome::Accepted { version }),
        text().prop_map(|reason| Welcome::Refused { reason }),
        (any::<[u8; 32]>(), any::<[u8; 32]>())
            .prop_map(|(nonce, proof)| Welcome::Challenge { nonce, proof }),
    ]
}

// ---------------------------------------------------------------------------------------
// Checks shared by every message type.

fn codec<T>() -> MessageCodec<T, T> {
    MessageCodec::new(DEFAULT_MAX_FRAME)
}

/// `wire` alone: the encoding decodes to the message and is self-delimiting.
fn check_wire<T>(message: &T) -> Result<(), TestCaseError>
where
    T: Serialize + DeserializeOwned + PartialEq + Debug,
{
    let bytes = wire::encode(message);
    let back: T = wire::decode(&bytes).map_err(|e| TestCaseError::fail(e.to_string()))?;
    prop_assert_eq!(&back, message);
    // Fixed-width integers: decoding is the exact inverse, bit for bit.
    prop_assert_eq!(wire::encode(&back), bytes.clone());
    for cut in [0, bytes.len() / 2, bytes.len() - 1] {
        prop_assert!(
            wire::decode::<T>(&bytes[..cut]).is_err(),
            "a {}-byte prefix of a {}-byte message decoded",
            cut,
            bytes.len()
        );
    }
    let mut longer = bytes.clone();
    longer.push(0);
    prop_assert!(
        wire::decode::<T>(&longer).is_err(),
        "trailing byte accepted"
    );
    Ok(())
}

/// `MessageCodec`: the messages back to back, fed in chunks of the given sizes (cycled),
/// decode to the same messages in order and leave nothing behind.
fn check_stream<T>(messages: &[T], chunks: &[usize]) -> Result<(), TestCaseError>
where
    T: Serialize + DeserializeOwned + PartialEq + Debug + Clone,
{
    let mut codec = codec::<T>();
    let mut stream = BytesMut::new();
    for message in messages {
        codec
            .encode(message.clone(), &mut stream)
            .map_err(|e| TestCaseError::fail(e.to_string()))?;
    }
    let expected_len: usize = messages.iter().map(|m| 4 + wire::encode(m).len()).sum();
    prop_assert_eq!(stream.len(), expected_len);

    let mut received = BytesMut::new();
    let mut decoded = Vec::new();
    let mut sizes = chunks.iter().cycle();
    let mut rest = &stream[..];
    while !rest.is_empty() {
        let size = (*sizes.next().expect("at least one chunk size")).min(rest.len());
        received.extend_from_slice(&rest[..size]);
        rest = &rest[size..];
        while let Some(message) = codec
            .decode(&mut received)
            .map_err(|e| TestCaseError::fail(e.to_string()))?
        {
            decoded.push(message);
        }
    }
    prop_assert_eq!(decoded.as_slice(), messages);
    prop_assert!(received.is_empty(), "{} bytes left over", received.len());
    Ok(())
}

/// A complete frame of arbitrary bytes gives a message or an error, never a panic and
/// never "need more bytes"; whatever it accepts is exactly that message's encoding.
fn check_garbage<T>(body: &[u8]) -> Result<(), TestCaseError>
where
    T: Serialize + DeserializeOwned + Debug,
{
    let mut bytes = frame(body);
    match codec::<T>().decode(&mut bytes) {
        Ok(Some(message)) => prop_assert_eq!(wire::encode(&message), body),
        Ok(None) => prop_assert!(false, "a complete frame was taken for a partial one"),
        Err(FrameError::Decode(_)) => {}
        Err(e) => prop_assert!(false, "a well-sized frame gave a framing error: {}", e),
    }
    Ok(())
}

fn chunk_sizes() -> impl Strategy<Value = Vec<usize>> {
    prop_oneof![
        Just(vec![1]),
        prop::collection::vec(1usize..64, 1..16),
        prop::collection::vec(1usize..4096, 1..8),
    ]
}

/// A valid encoding with one byte changed, cut short or extended.
fn mutated<T: Debug + Serialize>(
    messages: impl Strategy<Value = T>,
) -> impl Strategy<Value = Vec<u8>> {
    (messages, any::<prop::sample::Index>(), any::<u8>(), 0..3u8).prop_map(
        |(message, at, byte, how)| {
            let mut bytes = wire::encode(&message);
            let i = at.index(bytes.len());
            match how {
                0 => bytes[i] ^= byte | 1,
                1 => bytes.truncate(i),
                _ => bytes.insert(i, byte),
            }
            bytes
        },
    )
}

// ---------------------------------------------------------------------------------------
// Properties.

fn config() -> ProptestConfig {
    ProptestConfig {
        cases: 512,
        // Keep the tree clean: a failure prints its minimal case, which is enough.
        failure_persistence: None,
        ..ProptestConfig::default()
    }
}

proptest! {
    #![proptest_config(config())]

    #[test]
    fn to_worker_round_trips(
        messages in prop::collection::vec(to_worker(), 1..6),
        chunks in chunk_sizes(),
    ) {
        for message in &messages {
            check_wire(message)?;
        }
        check_stream(&messages, &chunks)?;
    }

    #[test]
    fn from_worker_round_trips(
        messages in prop::collection::vec(from_worker(), 1..6),
        chunks in chunk_sizes(),
    ) {
        for message in &messages {
            check_wire(message)?;
        }
        check_stream(&messages, &chunks)?;
    }

    #[test]
    fn client_request_round_trips(
        messages in prop::collection::vec(client_request(), 1..6),
        chunks in chunk_sizes(),
    ) {
        for message in &messages {
            check_wire(message)?;
        }
        check_stream(&messages, &chunks)?;
    }

    #[test]
    fn client_response_round_trips(
        messages in prop::collection::vec(client_response(), 1..6),
        chunks in chunk_sizes(),
    ) {
        for message in &messages {
            check_wire(message)?;
        }
        check_stream(&messages, &chunks)?;
    }

    #[test]
    fn handshake_messages_round_trip(
        hellos in prop::collection::vec(hello(), 1..4),
        welcomes in prop::collection::vec(welcome(), 1..4),
        chunks in chunk_sizes(),
    ) {
        for message in &hellos {
            check_wire(message)?;
        }
        for message in &welcomes {
            check_wire(message)?;
        }
        check_stream(&hellos, &chunks)?;
        check_stream(&welcomes, &chunks)?;
    }

    #[test]
    fn a_truncated_frame_waits_for_the_rest(
        message in from_worker(),
        cut in any::<prop::sample::Index>(),
    ) {
        let mut codec = codec::<FromWorker>();
        let mut whole = BytesMut::new();
        codec.encode(message.clone(), &mut whole).unwrap();
        let cut = cut.index(whole.len()); // 0 ..= len - 1: always short of a frame
        let mut received = BytesMut::from(&whole[..cut]);
        prop_assert!(matches!(codec.decode(&mut received), Ok(None)));
        received.extend_from_slice(&whole[cut..]);
        prop_assert_eq!(codec.decode(&mut received).unwrap(), Some(message));
        prop_assert!(received.is_empty());
    }

    #[test]
    fn garbage_in_a_well_sized_frame_is_an_error_not_a_panic(
        body in prop::collection::vec(any::<u8>(), 0..256),
    ) {
        check_garbage::<ToWorker>(&body)?;
        check_garbage::<FromWorker>(&body)?;
        check_garbage::<ClientRequest>(&body)?;
        check_garbage::<ClientResponse>(&body)?;
        check_garbage::<Hello>(&body)?;
        check_garbage::<Welcome>(&body)?;
    }

    #[test]
    fn damaged_messages_are_errors_not_panics(
        to_worker in mutated(to_worker()),
        from_worker in mutated(from_worker()),
        request in mutated(client_request()),
        response in mutated(client_response()),
    ) {
        check_garbage::<ToWorker>(&to_worker)?;
        check_garbage::<FromWorker>(&from_worker)?;
        check_garbage::<ClientRequest>(&request)?;
        check_garbage::<ClientResponse>(&response)?;
    }

    #[test]
    fn hello_accepts_this_version_for_any_role(role in role(), nonce in any::<[u8; 32]>()) {
        let hello = Hello::with_nonce(role, nonce);
        let frame = hello.to_frame();
        // The fixed prefix every version keeps: magic, then the version little-endian.
        prop_assert_eq!(&frame[..4], &MAGIC[..]);
        prop_assert_eq!(&frame[4..6], &PROTOCOL_VERSION.to_le_bytes()[..]);
        prop_assert_eq!(Hello::from_frame(&frame), Ok(hello));
    }

    #[test]
    fn hello_refuses_a_wrong_magic(
        magic in any::<[u8; 4]>().prop_filter("not ours", |m| *m != MAGIC),
        rest in prop::collection::vec(any::<u8>(), 0..64),
    ) {
        let mut frame = magic.to_vec();
        frame.extend_from_slice(&rest);
        prop_assert_eq!(Hello::from_frame(&frame), Err(HelloError::BadMagic));
    }

    #[test]
    fn hello_names_both_versions_on_a_mismatch(
        theirs in any::<u16>().prop_filter("another version", |v| *v != PROTOCOL_VERSION),
        role in role(),
    ) {
        let frame = Hello { magic: MAGIC, version: theirs, role, nonce: [0; 32], key: None }.to_frame();
        let error = Hello::from_frame(&frame).unwrap_err();
        prop_assert_eq!(&error, &HelloError::VersionMismatch { ours: PROTOCOL_VERSION, theirs });
        let text = error.to_string();
        prop_assert!(text.contains(&format!("version {PROTOCOL_VERSION}")), "{}", text);
        prop_assert!(text.contains(&format!("version {theirs}")), "{}", text);
    }

    #[test]
    fn hello_diagnoses_the_version_whatever_follows_it(
        theirs in any::<u16>().prop_filter("another version", |v| *v != PROTOCOL_VERSION),
        rest in prop::collection::vec(any::<u8>(), 0..64),
    ) {
        // Another version's hello may continue in any shape.
        let mut frame = MAGIC.to_vec();
        frame.extend_from_slice(&theirs.to_le_bytes());
        frame.extend_from_slice(&rest);
        prop_assert_eq!(
            Hello::from_frame(&frame),
            Err(HelloError::VersionMismatch { ours: PROTOCOL_VERSION, theirs })
        );
    }
}

// ---------------------------------------------------------------------------------------
// Unit tests: the frame limit, hostile lengths, the handshake's edge cases.

fn is_framing_error(result: Result<Option<FromWorker>, FrameError>) -> bool {
    matches!(result, Err(FrameError::Io(ref e)) if e.kind() == std::io::ErrorKind::InvalidData)
}

#[test]
fn an_oversized_length_prefix_is_refused_before_the_body() {
    let mut codec = MessageCodec::<FromWorker, FromWorker>::new(1024);
    let mut prefix = BytesMut::from(&[0xFF, 0xFF, 0xFF, 0xFF][..]);
    assert!(is_framing_error(codec.decode(&mut prefix)));

    let mut codec = MessageCodec::<FromWorker, FromWorker>::new(1024);
    let mut prefix = BytesMut::from(&1025u32.to_be_bytes()[..]);
    assert!(is_framing_error(codec.decode(&mut prefix)));

    // Exactly the maximum is a frame like any other: it waits for its body.
    let mut codec = MessageCodec::<FromWorker, FromWorker>::new(1024);
    let mut prefix = BytesMut::from(&1024u32.to_be_bytes()[..]);
    assert!(matches!(codec.decode(&mut prefix), Ok(None)));
}

#[test]
fn the_default_limit_and_the_hard_cap_hold() {
    let mut codec = codec::<FromWorker>();
    let mut prefix = BytesMut::from(&(DEFAULT_MAX_FRAME as u32 + 1).to_be_bytes()[..]);
    assert!(is_framing_error(codec.decode(&mut prefix)));

    // No configuration raises the limit past MAX_FRAME_LIMIT.
    let mut codec = MessageCodec::<FromWorker, FromWorker>::new(usize::MAX);
    let mut prefix = BytesMut::from(&(MAX_FRAME_LIMIT as u32 + 1).to_be_bytes()[..]);
    assert!(is_framing_error(codec.decode(&mut prefix)));
}

#[test]
fn the_encoder_refuses_a_message_the_peer_would_refuse() {
    let mut codec = MessageCodec::<ToWorker, ToWorker>::new(100);
    let mut out = BytesMut::new();
    let scene = ToWorker::Scene {
        hash: [0; 32],
        scene: "x".repeat(200),
        assets: Vec::new(),
    };
    assert!(codec.encode(scene, &mut out).is_err());
}

#[test]
fn an_empty_buffer_needs_more_bytes() {
    assert!(matches!(
        codec::<FromWorker>().decode(&mut BytesMut::new()),
        Ok(None)
    ));
}

/// `FromWorker::TileDone { job: 7, tile: 3, rgb: <claimed length> }` followed by a few
/// bytes: fixed-width little-endian fields, u32 variant index, u64 lengths.
fn tile_done_claiming(rgb_len: u64) -> Vec<u8> {
    let mut bytes = Vec::new();
    bytes.extend_from_slice(&0u32.to_le_bytes()); // variant TileDone
    bytes.extend_from_slice(&7u64.to_le_bytes()); // job
    bytes.extend_from_slice(&3u32.to_le_bytes()); // tile
    bytes.extend_from_slice(&rgb_len.to_le_bytes()); // rgb's length
    bytes.extend_from_slice(&[1, 2, 3, 4, 5, 6]);
    bytes
}

/// `FromWorker::TileFailed { job: 7, tile: 3, message: <claimed length> }` and a few
/// bytes.
fn tile_failed_claiming(message_len: u64) -> Vec<u8> {
    let mut bytes = Vec::new();
    bytes.extend_from_slice(&1u32.to_le_bytes()); // variant TileFailed
    bytes.extend_from_slice(&7u64.to_le_bytes()); // job
    bytes.extend_from_slice(&3u32.to_le_bytes()); // tile
    bytes.extend_from_slice(&message_len.to_le_bytes()); // message's length
    bytes.extend_from_slice(b"oops");
    bytes
}

#[test]
fn the_hand_made_layout_matches_the_encoder() {
    // The crafted messages below are only meaningful if the layout is the real one.
    let real = FromWorker::TileDone {
        job: 7,
        tile: 3,
        rgb: vec![1, 2, 3, 4, 5, 6],
        rays: 0,
        render_us: 0,
        samples: 0,
        error_sq_sum: 0.0,
    };
    let mut crafted = tile_done_claiming(6);
    crafted.extend_from_slice(&[0; 32]); // rays, render_us, samples, error_sq_sum
    assert_eq!(wire::encode(&real), crafted);
    let real = FromWorker::TileFailed {
        job: 7,
        tile: 3,
        message: "oops".into(),
    };
    assert_eq!(wire::encode(&real), tile_failed_claiming(4));
}

#[test]
fn a_tile_names_its_frame_after_the_scene_hash() {
    // Version 8: `Render` and `Advance` carry the frame of the scene, a u32 right after
    // the scene's hash, and it comes back as sent.
    let settings = Settings {
        width: 64,
        height: 48,
        aa: 2,
        max_depth: 5,
        sampling: Sampling::Grid,
    };
    let rect = TileRect {
        x: 16,
        y: 0,
        width: 16,
        height: 16,
    };
    let render = ToWorker::Render {
        job: 3,
        tile: 1,
        scene: [9; 32],
        frame: 17,
        settings,
        rect,
    };
    let advance = ToWorker::Advance {
        job: 3,
        tile: 1,
        scene: [9; 32],
        frame: 120,
        settings,
        rect,
        pass: 0,
        rung: 0,
        previous: None,
    };
    for (message, frame) in [(render, 17u32), (advance, 120)] {
        let bytes = wire::encode(&message);
        // variant (4), job (8), tile (4), scene (32), then the frame.
        assert_eq!(bytes[48..52], frame.to_le_bytes(), "{message:?}");
        let back: ToWorker = wire::decode(&bytes).unwrap();
        assert_eq!(back, message);
    }
    let spec = JobSpec {
        scene: "{}".into(),
        overrides: Overrides::default(),
        priority: 0,
        verification: Verification::Sampled,
        time_limit_ms: None,
        name: String::new(),
        submitter: String::new(),
        frame: 17,
        frames: None,
        assets: Vec::new(),
        after: Vec::new(),
        require: Vec::new(),
    };
    let bytes = wire::encode(&ClientRequest::Submit(spec.clone()));
    // The frame, the range (`None`: one byte 0), then the files, the jobs it waits for
    // and the requirements (none: a length of 8 zero bytes each) are the JobSpec's
    // last fields.
    let end = bytes.len() - 24;
    assert_eq!(bytes[end - 5..end - 1], 17u32.to_le_bytes());
    assert_eq!(bytes[end - 1], 0);
    assert_eq!(bytes[end..], [0; 24]);
    let back: ClientRequest = wire::decode(&bytes).unwrap();
    assert_eq!(back, ClientRequest::Submit(spec));
}

#[test]
fn a_huge_claimed_vector_is_refused_without_allocating_it() {
    for claimed in [1u64 << 40, u64::MAX, MAX_FRAME_LIMIT as u64 + 1] {
        let body = tile_done_claiming(claimed);
        let (result, largest) = largest_allocation(|| wire::decode::<FromWorker>(&body));
        assert!(result.is_err(), "claimed {claimed}");
        assert!(
            largest <= SERDE_PREALLOCATION_CAP,
            "claimed {claimed}: allocated {largest} bytes for a {}-byte message",
            body.len()
        );

        // Through the codec too, in a frame of the right size.
        let mut bytes = frame(&body);
        let (result, largest) = largest_allocation(|| codec::<FromWorker>().decode(&mut bytes));
        assert!(matches!(result, Err(FrameError::Decode(_))));
        assert!(largest <= SERDE_PREALLOCATION_CAP);
    }
}

#[test]
fn a_huge_claimed_string_is_refused_without_allocating_it() {
    for claimed in [1u64 << 40, u64::MAX, MAX_FRAME_LIMIT as u64 + 1] {
        let body = tile_failed_claiming(claimed);
        let (result, largest) = largest_allocation(|| wire::decode::<FromWorker>(&body));
        assert!(result.is_err(), "claimed {claimed}");
        assert!(
            largest <= SERDE_PREALLOCATION_CAP,
            "allocated {largest} bytes"
        );
    }
}

/// A string claimed longer than its frame (but within the 64 MiB frame limit) is
/// refused without being allocated: bincode's `String` decoding reserves
/// `vec![0; claimed]` once the claim passes the configured limit, so `wire` sets the
/// limit from the frame's own length, not from `MAX_FRAME_LIMIT`.
#[test]
fn a_string_claimed_longer_than_its_frame_is_refused_without_allocating_it() {
    let claimed = 48 * 1024 * 1024;
    let body = tile_failed_claiming(claimed);
    let (result, largest) = largest_allocation(|| wire::decode::<FromWorker>(&body));
    assert!(result.is_err());
    assert!(
        largest <= SERDE_PREALLOCATION_CAP,
        "a {}-byte message made the decoder allocate {largest} bytes",
        body.len()
    );
}

/// Decodes one complete frame around `body`.
fn decode_framed<T: DeserializeOwned>(body: &[u8]) -> Result<Option<T>, FrameError> {
    MessageCodec::<T, T>::new(DEFAULT_MAX_FRAME).decode(&mut frame(body))
}

#[test]
fn hand_made_garbage_is_an_error() {
    let unknown_variant = 99u32.to_le_bytes();
    assert!(matches!(
        decode_framed::<FromWorker>(&unknown_variant),
        Err(FrameError::Decode(_))
    ));

    let huge_variant = u32::MAX.to_le_bytes();
    assert!(matches!(
        decode_framed::<ToWorker>(&huge_variant),
        Err(FrameError::Decode(_))
    ));

    let mut bad_utf8 = tile_failed_claiming(2);
    bad_utf8.truncate(bad_utf8.len() - 4);
    bad_utf8.extend_from_slice(&[0xC3, 0x28]);
    assert!(matches!(
        decode_framed::<FromWorker>(&bad_utf8),
        Err(FrameError::Decode(_))
    ));

    let mut bad_option = 1u32.to_le_bytes().to_vec(); // ClientResponse::Job
    bad_option.extend_from_slice(&[0; 8 + 4]); // id, state
    bad_option.extend_from_slice(&[0; 20 + 4 + 4 + 4 + 8 + 8]); // settings .. elapsed_ms
    bad_option.push(2); // eta_ms: neither None (0) nor Some (1)
    assert!(matches!(
        decode_framed::<ClientResponse>(&bad_option),
        Err(FrameError::Decode(_))
    ));
}

#[test]
fn nan_rates_keep_their_bits() {
    let status = WorkerStatus {
        id: 1,
        name: "w".into(),
        threads: 2,
        tiles_in_flight: 0,
        tiles_done: 0,
        rays: 0,
        connected_ms: 0,
        rays_per_second: f64::from_bits(0x7FF8_0000_0000_0123),
        build: String::new(),
        quarantined: None,
        rtt_us: None,
        credit: 2,
        draining: false,
        disabled: false,
        unresponsive: false,
        key: None,
        host: "127.0.0.1".into(),
        cache: None,
        tags: Vec::new(),
    };
    let bytes = wire::encode(&ClientResponse::Workers(vec![status]));
    let ClientResponse::Workers(back) = wire::decode(&bytes).unwrap() else {
        panic!("wrong variant");
    };
    assert_eq!(back[0].rays_per_second.to_bits(), 0x7FF8_0000_0000_0123);
}

#[test]
fn short_or_foreign_first_frames_are_not_tessera_peers() {
    for frame in [
        &b""[..],
        b"TSR",
        b"TSRA",
        b"TSRA\x01",
        b"GET / HTTP/1.1\r\n",
    ] {
        assert_eq!(
            Hello::from_frame(frame),
            Err(HelloError::BadMagic),
            "{frame:?}"
        );
    }
}

#[test]
fn a_hello_of_this_version_with_a_damaged_body_is_malformed() {
    let mut frame = Hello::new(Role::Client).to_frame();
    frame.push(0); // trailing byte
    assert!(matches!(
        Hello::from_frame(&frame),
        Err(HelloError::Malformed(_))
    ));
    let mut frame = MAGIC.to_vec();
    frame.extend_from_slice(&PROTOCOL_VERSION.to_le_bytes());
    frame.extend_from_slice(&7u32.to_le_bytes()); // no such role
    assert!(matches!(
        Hello::from_frame(&frame),
        Err(HelloError::Malformed(_))
    ));
}

// ---------------------------------------------------------------------------------------
// The texts of decoding errors: one line a peer can read, never debug output.

fn decode_error<T: DeserializeOwned + Debug>(bytes: &[u8]) -> String {
    wire::decode::<T>(bytes).unwrap_err().to_string()
}

#[test]
fn decoding_errors_name_the_message_and_the_problem_in_one_line() {
    assert_eq!(
        decode_error::<ClientRequest>(&21u32.to_le_bytes()),
        "unreadable ClientRequest: unknown variant 21 (variants go from 0 to 20)"
    );
    let mut status = wire::encode(&ClientRequest::Status { job: 1 });
    assert_eq!(
        decode_error::<ClientRequest>(&status[..6]),
        "unreadable ClientRequest: the frame ends in the middle of a field"
    );
    status.push(0);
    assert_eq!(
        decode_error::<ClientRequest>(&status),
        "unreadable ClientRequest: 1 byte after the end of the message"
    );
    let submit = |overrides| {
        wire::encode(&ClientRequest::Submit(JobSpec {
            scene: "x".into(),
            overrides,
            priority: 0,
            verification: Verification::Sampled,
            time_limit_ms: None,
            name: String::new(),
            submitter: String::new(),
            frame: 1,
            frames: None,
            assets: Vec::new(),
            after: Vec::new(),
            require: Vec::new(),
        }))
    };
    let mut tagged = submit(Overrides::default());
    tagged[13] = 2; // overrides.width's Option tag
    assert_eq!(
        decode_error::<ClientRequest>(&tagged),
        "unreadable ClientRequest: an Option tag is 2, not 0 or 1"
    );
    let mut nested = submit(Overrides {
        sampling: Some(Sampling::Grid),
        ..Default::default()
    });
    // The Sampling variant, before the priority, verification, time limit, the name
    // and submitter (two empty strings: their lengths), the frame, the range, the
    // files, the jobs it waits for and the requirements (none: their lengths).
    let at = nested.len() - 13 - 16 - 4 - 1 - 8 - 8 - 8;
    nested[at] = 7;
    assert_eq!(
        decode_error::<ClientRequest>(&nested),
        "unreadable ClientRequest: unknown variant 7 (variants go from 0 to 2)"
    );
    let scene = wire::encode(&ToWorker::Scene {
        hash: [0; 32],
        scene: "ab".into(),
        assets: Vec::new(),
    });
    let mut bad_utf8 = scene.clone();
    // The scene's last byte, before the files' length (8 bytes).
    let last = bad_utf8.len() - 9;
    bad_utf8[last] = 0xff;
    assert_eq!(
        decode_error::<ToWorker>(&bad_utf8),
        "unreadable ToWorker: a string is not valid UTF-8"
    );
    let mut long = scene;
    long[40] = 0xff; // the string's length: 2 + 2^32
    assert_eq!(
        decode_error::<ToWorker>(&long),
        "unreadable ToWorker: a length claims more bytes than the frame holds"
    );
    let mut hello = Hello::new(Role::Client).to_frame();
    hello[6] = 7;
    assert_eq!(
        Hello::from_frame(&hello).unwrap_err().to_string(),
        "malformed hello: unknown variant 7 (variants go from 0 to 1)"
    );
    let mut codec = MessageCodec::<FromWorker, FromWorker>::new(1024);
    let mut prefix = BytesMut::from(&1025u32.to_be_bytes()[..]);
    assert_eq!(
        codec.decode(&mut prefix).unwrap_err().to_string(),
        "a frame of 1025 bytes is too long"
    );
}
