//! The coordinator's Prometheus metrics (all named `tessera_…`).
//!
//! Events the daemon sees one by one (a tile accepted, its latency) are counted as
//! they happen; what is a state (jobs by state, workers connected) or is already
//! counted by the scheduler (leases expired, tiles requeued) is read at each scrape,
//! so the two can never disagree.

use std::collections::VecDeque;
use std::sync::atomic::AtomicU64;
use std::sync::Mutex;
use std::time::{Duration, Instant};

use prometheus_client::encoding::EncodeLabelSet;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::metrics::histogram::{exponential_buckets, Histogram};
use prometheus_client::registry::Registry;
use protocol::JobState;

use scheduler::Counters;

/// Rays per second are averaged over this window.
const RATE_WINDOW: Duration = Duration::from_secs(10);

/// The state of the farm at a scrape.
pub struct Snapshot {
    /// Jobs known to the coordinator, by state.
    pub jobs: Vec<(JobState, i64)>,
    pub workers: i64,
    pub tiles_in_flight: i64,
    pub scheduler: Counters,
    /// Whether storage can write (a gauge of 1 or 0).
    pub storage_available: bool,
    /// The work waiting in each pool, and its workers.
    pub pools: Vec<PoolFigures>,
}

/// One pool's figures at a scrape: what an autoscaler scales its workers on.
#[derive(Clone, Debug, PartialEq)]
pub struct PoolFigures {
    /// The pool's name: the tags its jobs require, sorted, joined with `,` (empty: the
    /// jobs any worker may take).
    pub pool: String,
    /// Tiles of its active jobs (not paused) not yet done.
    pub waiting_tiles: u64,
    /// Their estimated rendering time on one thread, in seconds.
    pub waiting_cpu_seconds: f64,
    /// Connected workers ready for work that have every tag of the pool.
    pub workers: u64,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct PoolLabel {
    pool: String,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct StateLabel {
    state: String,
}

pub struct Metrics {
    registry: Registry,
    jobs: Family<StateLabel, Gauge>,
    workers: Gauge,
    tiles_in_flight: Gauge,
    tiles_rendered: Counter,
    rays: Counter,
    tile_latency: Histogram,
    leases_expired: Counter,
    tiles_reassigned: Counter,
    workers_dropped: Counter,
    workers_unresponsive: Counter,
    rays_per_second: Gauge<f64, AtomicU64>,
    storage_available: Gauge,
    storage_outages: Counter,
    results_rejected: Counter,
    results_confirmed: Counter,
    workers_quarantined: Counter,
    workers_refused: Counter,
    canaries_interrupted: Counter,
    assets: AssetMetrics,
    /// Per webhook URL (docs/operations.md, "Webhooks").
    pub webhooks: WebhookMetrics,
    /// What the scheduler's counters were at the last scrape.
    synced: Mutex<Counters>,
    /// (time, rays so far), oldest first, over the last [`RATE_WINDOW`].
    rate: Mutex<VecDeque<(Instant, u64)>>,
    pools: PoolMetrics,
}

impl Default for Metrics {
    fn default() -> Self {
        Metrics::new()
    }
}

impl Metrics {
    pub fn new() -> Self {
        let mut registry = Registry::with_prefix("tessera");
        let jobs = Family::<StateLabel, Gauge>::default();
        registry.register(
            "jobs",
            "Jobs known to the coordinator, by state",
            jobs.clone(),
        );
        let workers = Gauge::default();
        registry.register("workers_connected", "Workers connected", workers.clone());
        let tiles_in_flight = Gauge::default();
        registry.register(
            "tiles_in_flight",
            "Tiles handed to workers and not yet returned",
            tiles_in_flight.clone(),
        );
        let tiles_rendered = Counter::default();
        registry.register(
            "tiles_rendered",
            "Tiles rendered and accepted (first results only)",
            tiles_rendered.clone(),
        );
        let rays = Counter::default();
        registry.register("rays", "Rays traced for accepted tiles", rays.clone());
        // 1 ms to about 65 s.
        let tile_latency = Histogram::new(exponential_buckets(0.001, 2.0, 17));
        registry.register(
            "tile_latency_seconds",
            "Time from handing a tile to a worker to receiving its result",
            tile_latency.clone(),
        );
        let leases_expired = Counter::default();
        registry.register(
            "leases_expired",
            "Tile leases that ran out before the tile came back",
            leases_expired.clone(),
        );
        let tiles_reassigned = Counter::default();
        registry.register(
            "tiles_reassigned",
            "Tiles put back in the queue to be rendered by another worker (lease expired, \
             worker lost, tile failed)",
            tiles_reassigned.clone(),
        );
        let workers_dropped = Counter::default();
        registry.register(
            "workers_dropped",
            "Workers dropped for missing their heartbeats",
            workers_dropped.clone(),
        );
        let workers_unresponsive = Counter::default();
        registry.register(
            "workers_unresponsive",
            "Times a worker was marked unresponsive: its leases ran out and it returned no \
             result for longer than its progress allowance (it still sent heartbeats)",
            workers_unresponsive.clone(),
        );
        let rays_per_second = Gauge::<f64, AtomicU64>::default();
        registry.register(
            "rays_per_second",
            "Rays per second over the last 10 seconds",
            rays_per_second.clone(),
        );
        let storage_available = Gauge::default();
        registry.register(
            "storage_available",
            "1 while the data directory can be written, 0 while it cannot (full, read-only \
             or stalled): no new tiles are handed out then",
            storage_available.clone(),
        );
        let storage_outages = Counter::default();
        registry.register(
            "storage_outages",
            "Times the data directory stopped being writable",
            storage_outages.clone(),
        );
        let results_rejected = Counter::default();
        registry.register(
            "results_rejected",
            "Tile results found wrong (by a spot check, or against another machine's) and \
             thrown away",
            results_rejected.clone(),
        );
        let results_confirmed = Counter::default();
        registry.register(
            "results_confirmed",
            "Tile results accepted because another machine returned the same bytes",
            results_confirmed.clone(),
        );
        let workers_quarantined = Counter::default();
        registry.register(
            "workers_quarantined",
            "Machines quarantined for returning wrong pixels",
            workers_quarantined.clone(),
        );
        let workers_refused = Counter::default();
        registry.register(
            "workers_refused",
            "Workers refused because their canary render differs from the coordinator's",
            workers_refused.clone(),
        );
        let canaries_interrupted = Counter::default();
        registry.register(
            "worker_canaries_interrupted",
            "Worker connections lost during their canary (a connection error, closed or \
             silent): not refusals, the worker reconnects",
            canaries_interrupted.clone(),
        );
        let assets = AssetMetrics::register(&mut registry);
        let webhooks = WebhookMetrics::register(&mut registry);
        let pools = PoolMetrics::register(&mut registry);
        Metrics {
            pools,
            registry,
            assets,
            webhooks,
            canaries_interrupted,
            results_rejected,
            results_confirmed,
            workers_quarantined,
            workers_refused,
            storage_available,
            storage_outages,
            jobs,
            workers,
            tiles_in_flight,
            tiles_rendered,
            rays,
            tile_latency,
            leases_expired,
            tiles_reassigned,
            workers_dropped,
            workers_unresponsive,
            rays_per_second,
            synced: Mutex::new(Counters::default()),
            rate: Mutex::new(VecDeque::new()),
        }
    }

    /// Counts an accepted tile that took `latency` from assignment to result.
    pub fn tile_accepted(&self, rays: u64, latency: Option<Duration>) {
        self.tiles_rendered.inc();
        self.rays.inc_by(rays);
        if let Some(latency) = latency {
            self.tile_latency.observe(latency.as_secs_f64());
        }
    }

    /// Counts a tile result found wrong.
    pub fn result_rejected(&self) {
        self.results_rejected.inc();
    }

    /// Counts a result confirmed by another machine's identical one.
    pub fn result_confirmed(&self) {
        self.results_confirmed.inc();
    }

    /// Counts bytes of scene files received from clients.
    pub fn asset_bytes_received(&self, bytes: u64) {
        self.assets.received.inc_by(bytes);
    }

    /// Counts bytes of scene files sent to workers.
    pub fn asset_bytes_sent(&self, bytes: u64) {
        self.assets.sent.inc_by(bytes);
    }

    /// The store of scene files as it stands.
    pub fn asset_store(&self, stats: &assets::StoreStats) {
        self.assets.files.set(stats.files as i64);
        self.assets.bytes.set(stats.bytes as i64);
        self.assets.partial_bytes.set(stats.partial_bytes as i64);
    }

    /// Counts a machine quarantined.
    pub fn worker_quarantined(&self) {
        self.workers_quarantined.inc();
    }

    /// Counts a worker connection lost during its canary.
    pub fn canary_interrupted(&self) {
        self.canaries_interrupted.inc();
    }

    /// Counts a worker refused at its canary.
    pub fn worker_refused(&self) {
        self.workers_refused.inc();
    }

    /// Counts an outage of storage (it just became unavailable).
    pub fn storage_outage(&self) {
        self.storage_outages.inc();
    }

    /// Takes a sample of the ray count for the rate (called every half second).
    pub fn sample_rate(&self, now: Instant) {
        let mut rate = self.rate.lock().expect("rate lock");
        rate.push_back((now, self.rays.get()));
        while rate
            .front()
            .is_some_and(|(t, _)| now.duration_since(*t) > RATE_WINDOW)
        {
            rate.pop_front();
        }
        if let (Some(&(t0, r0)), Some(&(t1, r1))) = (rate.front(), rate.back()) {
            let seconds = t1.duration_since(t0).as_secs_f64();
            let per_second = if seconds > 0.0 {
                (r1 - r0) as f64 / seconds
            } else {
                0.0
            };
            self.rays_per_second.set(per_second);
        }
    }

    /// The metrics in `format`, with the state of `snapshot`.
    pub fn render(&self, snapshot: &Snapshot, format: Exposition) -> String {
        for (state, n) in &snapshot.jobs {
            self.jobs
                .get_or_create(&StateLabel {
                    state: state.as_str().to_owned(),
                })
                .set(*n);
        }
        self.workers.set(snapshot.workers);
        self.storage_available
            .set(i64::from(snapshot.storage_available));
        self.tiles_in_flight.set(snapshot.tiles_in_flight);
        self.pools.set(&snapshot.pools);
        {
            let mut synced = self.synced.lock().expect("metrics lock");
            let now = snapshot.scheduler;
            self.leases_expired
                .inc_by(now.leases_expired.saturating_sub(synced.leases_expired));
            self.tiles_reassigned
                .inc_by(now.tiles_requeued.saturating_sub(synced.tiles_requeued));
            self.workers_dropped
                .inc_by(now.workers_dropped.saturating_sub(synced.workers_dropped));
            self.workers_unresponsive.inc_by(
                now.workers_unresponsive
                    .saturating_sub(synced.workers_unresponsive),
            );
            *synced = now;
        }
        let mut out = String::new();
        prometheus_client::encoding::text::encode(&mut out, &self.registry)
            .expect("writing to a String cannot fail");
        match format {
            Exposition::OpenMetrics => out,
            Exposition::Prometheus => openmetrics_to_prometheus(&out),
        }
    }
}

/// The two text formats a scrape can ask for. The registry encodes OpenMetrics; the
/// Prometheus text format (0.0.4) is what `promtool check metrics`, older scrapers and
/// a plain `curl` expect, so it is also the answer when the request does not say.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Exposition {
    /// `text/plain; version=0.0.4`.
    Prometheus,
    /// `application/openmetrics-text; version=1.0.0`.
    OpenMetrics,
}

impl Exposition {
    /// The format an `Accept` header asks for: OpenMetrics when it names
    /// `application/openmetrics-text` (version 1.0.0 or none given) at least as
    /// strongly as anything the text format matches (`text/plain`, `text/*`, `*/*`);
    /// the text format otherwise, and when there is no header.
    pub fn negotiate(accept: Option<&str>) -> Exposition {
        let Some(accept) = accept else {
            return Exposition::Prometheus;
        };
        let mut openmetrics: f32 = 0.0;
        let mut text: f32 = 0.0;
        for range in accept.split(',') {
            let mut parts = range.split(';').map(str::trim);
            let media = parts.next().unwrap_or("").to_ascii_lowercase();
            let mut quality = 1.0_f32;
            let mut version = None;
            for param in parts {
                let Some((key, value)) = param.split_once('=') else {
                    continue;
                };
                let value = value.trim().trim_matches('"');
                match key.trim().to_ascii_lowercase().as_str() {
                    "q" => quality = value.parse().unwrap_or(0.0_f32).clamp(0.0, 1.0),
                    "version" => version = Some(value.to_owned()),
                    _ => {}
                }
            }
            match media.as_str() {
                "application/openmetrics-text"
                    if version.as_deref().is_none_or(|v| v == "1.0.0") =>
                {
                    openmetrics = openmetrics.max(quality);
                }
                "text/plain" | "text/*" | "*/*" => text = text.max(quality),
                _ => {}
            }
        }
        if openmetrics > 0.0 && openmetrics >= text {
            Exposition::OpenMetrics
        } else {
            Exposition::Prometheus
        }
    }

    /// The `Content-Type` of an answer in this format.
    pub fn content_type(self) -> &'static str {
        match self {
            Exposition::Prometheus => "text/plain; version=0.0.4; charset=utf-8",
            Exposition::OpenMetrics => "application/openmetrics-text; version=1.0.0; charset=utf-8",
        }
    }
}

/// The registry's OpenMetrics exposition in the Prometheus text format. The two differ,
/// for the metric types this registry holds (counters, gauges, histograms), only in
/// that a counter's `HELP` and `TYPE` name its samples' `_total` name, and that the
/// text format has no `UNIT` lines and no `# EOF`; samples are written alike.
fn openmetrics_to_prometheus(openmetrics: &str) -> String {
    let counters: std::collections::HashSet<&str> = openmetrics
        .lines()
        .filter_map(|line| line.strip_prefix("# TYPE "))
        .filter_map(|rest| rest.strip_suffix(" counter"))
        .collect();
    let mut out = String::with_capacity(openmetrics.len());
    for line in openmetrics.lines() {
        if line == "# EOF" || line.starts_with("# UNIT ") {
            continue;
        }
        let descriptor = ["# HELP ", "# TYPE "]
            .into_iter()
            .find_map(|prefix| Some((prefix, line.strip_prefix(prefix)?)));
        match descriptor {
            Some((prefix, rest)) => {
                let (name, tail) = rest.split_once(' ').unwrap_or((rest, ""));
                let suffix = if counters.contains(name) {
                    "_total"
                } else {
                    ""
                };
                out.push_str(&format!("{prefix}{name}{suffix} {tail}"));
            }
            None => out.push_str(line),
        }
        out.push('\n');
    }
    out
}

/// The figures autoscalers scale worker pools on, per pool: a scrape shows the pools
/// of that moment only (a pool whose last job ended disappears, so a query should add
/// `or vector(0)`).
struct PoolMetrics {
    waiting_tiles: Family<PoolLabel, Gauge>,
    waiting_cpu_seconds: Family<PoolLabel, Gauge<f64, AtomicU64>>,
    workers: Family<PoolLabel, Gauge>,
}

impl PoolMetrics {
    fn register(registry: &mut Registry) -> PoolMetrics {
        let pools = PoolMetrics {
            waiting_tiles: Family::default(),
            waiting_cpu_seconds: Family::default(),
            workers: Family::default(),
        };
        registry.register(
            "pool_waiting_tiles",
            "Tiles not yet done of the active jobs (not paused) of the pool: the tags they \
             require, sorted and joined with commas (empty: any worker)",
            pools.waiting_tiles.clone(),
        );
        registry.register(
            "pool_waiting_cpu_seconds",
            "Estimated rendering seconds on one thread of those tiles (docs/operations.md, \
             Autoscaling)",
            pools.waiting_cpu_seconds.clone(),
        );
        registry.register(
            "pool_workers",
            "Connected workers ready for work that have every tag of the pool",
            pools.workers.clone(),
        );
        pools
    }

    fn set(&self, figures: &[PoolFigures]) {
        self.waiting_tiles.clear();
        self.waiting_cpu_seconds.clear();
        self.workers.clear();
        for f in figures {
            let label = PoolLabel {
                pool: f.pool.clone(),
            };
            self.waiting_tiles
                .get_or_create(&label)
                .set(i64::try_from(f.waiting_tiles).unwrap_or(i64::MAX));
            self.waiting_cpu_seconds
                .get_or_create(&label)
                .set(f.waiting_cpu_seconds);
            self.workers
                .get_or_create(&label)
                .set(i64::try_from(f.workers).unwrap_or(i64::MAX));
        }
    }
}

/// The label of a webhook's series: its URL without user information and query.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct WebhookLabel {
    pub webhook: String,
}

/// What the webhooks did, per webhook: counted as it happens by each webhook's task.
pub struct WebhookMetrics {
    pub delivered: Family<WebhookLabel, Counter>,
    pub failed_attempts: Family<WebhookLabel, Counter>,
    pub given_up: Family<WebhookLabel, Counter>,
    pub dropped: Family<WebhookLabel, Counter>,
    pub queue_depth: Family<WebhookLabel, Gauge>,
}

impl WebhookMetrics {
    fn register(registry: &mut Registry) -> WebhookMetrics {
        let m = WebhookMetrics {
            delivered: Family::default(),
            failed_attempts: Family::default(),
            given_up: Family::default(),
            dropped: Family::default(),
            queue_depth: Family::default(),
        };
        registry.register(
            "webhook_delivered",
            "Job ends delivered to a webhook (answered 2xx)",
            m.delivered.clone(),
        );
        registry.register(
            "webhook_failed_attempts",
            "Posts to a webhook that failed (another status, no answer, refused, TLS), \
             retried or given up",
            m.failed_attempts.clone(),
        );
        registry.register(
            "webhook_given_up",
            "Job ends a webhook gave up on after its attempts or their maximum age",
            m.given_up.clone(),
        );
        registry.register(
            "webhook_dropped",
            "Job ends not delivered to a webhook because its queue was full (the oldest \
             waiting is dropped) or the event retention deleted them first (counted by \
             event id, of any kind)",
            m.dropped.clone(),
        );
        registry.register(
            "webhook_queue_depth",
            "Job ends waiting for a webhook, the one being posted included",
            m.queue_depth.clone(),
        );
        m
    }
}

/// The store of the files scenes name: what it holds, and what crosses the network.
struct AssetMetrics {
    files: Gauge,
    bytes: Gauge,
    partial_bytes: Gauge,
    received: Counter,
    sent: Counter,
}

impl AssetMetrics {
    fn register(registry: &mut Registry) -> AssetMetrics {
        let m = AssetMetrics {
            files: Gauge::default(),
            bytes: Gauge::default(),
            partial_bytes: Gauge::default(),
            received: Counter::default(),
            sent: Counter::default(),
        };
        registry.register(
            "asset_files",
            "Scene files (meshes, buffers) stored, each once",
            m.files.clone(),
        );
        registry.register(
            "asset_bytes",
            "Bytes of the scene files stored",
            m.bytes.clone(),
        );
        registry.register(
            "asset_upload_bytes",
            "Bytes of uploads of scene files not yet complete",
            m.partial_bytes.clone(),
        );
        registry.register(
            "asset_received_bytes",
            "Bytes of scene files received from clients",
            m.received.clone(),
        );
        registry.register(
            "asset_sent_bytes",
            "Bytes of scene files sent to workers",
            m.sent.clone(),
        );
        m
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_exposition_names_every_metric_and_follows_the_scheduler() {
        let m = Metrics::new();
        m.tile_accepted(1000, Some(Duration::from_millis(20)));
        let mut snapshot = Snapshot {
            jobs: vec![(JobState::Running, 1), (JobState::Done, 2)],
            workers: 3,
            tiles_in_flight: 4,
            scheduler: Counters {
                leases_expired: 5,
                tiles_requeued: 6,
                workers_dropped: 7,
                workers_unresponsive: 9,
            },
            storage_available: true,
            pools: vec![
                PoolFigures {
                    pool: String::new(),
                    waiting_tiles: 0,
                    waiting_cpu_seconds: 0.0,
                    workers: 3,
                },
                PoolFigures {
                    pool: "gpu,ssd".into(),
                    waiting_tiles: 12,
                    waiting_cpu_seconds: 7.5,
                    workers: 1,
                },
            ],
        };
        m.storage_outage();
        let text = m.render(&snapshot, Exposition::OpenMetrics);
        for line in [
            "tessera_jobs{state=\"running\"} 1",
            "tessera_jobs{state=\"done\"} 2",
            "tessera_workers_connected 3",
            "tessera_tiles_in_flight 4",
            "tessera_tiles_rendered_total 1",
            "tessera_rays_total 1000",
            "tessera_tile_latency_seconds_count 1",
            "tessera_leases_expired_total 5",
            "tessera_tiles_reassigned_total 6",
            "tessera_workers_dropped_total 7",
            "tessera_workers_unresponsive_total 9",
            "tessera_storage_available 1",
            "tessera_storage_outages_total 1",
            "tessera_pool_waiting_tiles{pool=\"\"} 0",
            "tessera_pool_waiting_tiles{pool=\"gpu,ssd\"} 12",
            "tessera_pool_waiting_cpu_seconds{pool=\"gpu,ssd\"} 7.5",
            "tessera_pool_workers{pool=\"\"} 3",
            "tessera_pool_workers{pool=\"gpu,ssd\"} 1",
        ] {
            assert!(text.lines().any(|l| l == line), "{line} missing in\n{text}");
        }
        // Counters follow the scheduler's totals, not add them up again; a pool gone
        // from the farm is gone from the scrape.
        snapshot.pools.truncate(1);
        snapshot.scheduler.leases_expired = 8;
        snapshot.storage_available = false;
        let text = m.render(&snapshot, Exposition::OpenMetrics);
        assert!(text.contains("tessera_storage_available 0\n"), "{text}");
        assert!(!text.contains("gpu,ssd"), "{text}");
        assert!(text.contains("tessera_leases_expired_total 8\n"), "{text}");
        assert!(
            text.contains("tessera_tiles_reassigned_total 6\n"),
            "{text}"
        );
    }

    #[test]
    fn the_text_format_names_counters_by_their_samples_and_has_no_eof() {
        let m = Metrics::new();
        m.tile_accepted(1000, Some(Duration::from_millis(20)));
        let snapshot = Snapshot {
            jobs: vec![(JobState::Running, 1)],
            workers: 1,
            tiles_in_flight: 0,
            scheduler: Counters::default(),
            storage_available: true,
            pools: Vec::new(),
        };
        let openmetrics = m.render(&snapshot, Exposition::OpenMetrics);
        assert!(openmetrics.ends_with("# EOF\n"), "{openmetrics}");
        assert!(openmetrics.contains("# TYPE tessera_rays counter\n"));
        let text = m.render(&snapshot, Exposition::Prometheus);
        for line in [
            "# HELP tessera_rays_total Rays traced for accepted tiles.",
            "# TYPE tessera_rays_total counter",
            "tessera_rays_total 1000",
            "# TYPE tessera_workers_connected gauge",
            "# TYPE tessera_tile_latency_seconds histogram",
            "tessera_tile_latency_seconds_count 1",
        ] {
            assert!(text.lines().any(|l| l == line), "{line} missing in\n{text}");
        }
        assert!(
            !text.contains("# EOF") && !text.contains("# UNIT"),
            "{text}"
        );
        // Every sample line is the same in both.
        let samples = |t: &str| -> Vec<String> {
            t.lines()
                .filter(|l| !l.starts_with('#'))
                .map(str::to_owned)
                .collect()
        };
        assert_eq!(samples(&text), samples(&openmetrics));
    }

    #[test]
    fn scrapes_get_the_format_they_ask_for() {
        use Exposition::{OpenMetrics, Prometheus};
        for (accept, want) in [
            (None, Prometheus),
            (Some("*/*"), Prometheus),
            (Some("text/plain"), Prometheus),
            (Some("text/plain;version=0.0.4"), Prometheus),
            (Some("application/openmetrics-text"), OpenMetrics),
            // What Prometheus 2 sends: OpenMetrics first.
            (
                Some(
                    "application/openmetrics-text;version=1.0.0,application/openmetrics-text;\
                     version=0.0.1;q=0.75,text/plain;version=0.0.4;q=0.5,*/*;q=0.1",
                ),
                OpenMetrics,
            ),
            // The text format preferred.
            (
                Some("text/plain;version=0.0.4;q=0.9, application/openmetrics-text;q=0.3"),
                Prometheus,
            ),
            // A version this exposition is not.
            (
                Some("application/openmetrics-text; version=0.0.1"),
                Prometheus,
            ),
            (Some("application/openmetrics-text; q=0"), Prometheus),
            (Some("image/png"), Prometheus),
            // Garbage is the default, never an error.
            (Some("application/openmetrics-text;q=NaN"), Prometheus),
            (Some("application/openmetrics-text;q=-5"), Prometheus),
            (Some(",,,;;;=="), Prometheus),
            (Some("q=abc"), Prometheus),
        ] {
            assert_eq!(Exposition::negotiate(accept), want, "{accept:?}");
        }
    }

    #[test]
    fn rays_per_second_come_from_the_window() {
        let m = Metrics::new();
        let t0 = Instant::now();
        m.sample_rate(t0);
        m.tile_accepted(5000, None);
        m.sample_rate(t0 + Duration::from_secs(2));
        assert_eq!(m.rays_per_second.get(), 2500.0);
    }
}
