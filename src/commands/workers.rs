//! `tessera workers`: the workers connected to a coordinator, with their throughput;
//! and `tessera workers drain|disable|enable WORKER`.

use anyhow::Result;
use coordinator::client::Client;
use protocol::{ClientRequest, WorkerCache};
use serde_json::Value;
use transport::Endpoint;

use crate::args::ClientArgs;
use crate::report::{bytes, counted};
use coordinator::json::worker_json;

/// List the workers connected to the coordinator, with their throughput; or drain,
/// disable or enable one.
///
/// A worker's M rays/s is its rate while rendering: the rays of its results of the
/// last minute over the time it spent rendering them (idle time left out), 0 once it
/// has returned nothing for a minute.
#[derive(clap::Args)]
#[command(
    args_conflicts_with_subcommands = true,
    after_help = "Examples:\n  \
        tessera workers                      lists them (id, name, state)\n  \
        tessera workers drain render-07      finishes its tiles, then it exits\n  \
        tessera workers disable render-07    no new tiles, even after a restart\n  \
        tessera workers enable render-07"
)]
pub struct Args {
    #[command(subcommand)]
    action: Option<WorkerAction>,
    #[command(flatten)]
    common: ClientArgs,
}

/// `tessera workers drain|disable|enable WORKER`.
#[derive(clap::Subcommand)]
enum WorkerAction {
    /// The worker finishes the tiles it holds, then exits (status 0) without
    /// reconnecting, as on SIGTERM on its machine.
    Drain {
        /// A worker's id or name, as `tessera workers` shows them (names are unique
        /// among connected workers).
        worker: String,
        #[command(flatten)]
        common: ClientArgs,
    },
    /// The worker's machine gets no new tiles (those it holds finish); it stays
    /// connected. Kept by machine name and stored: it holds across reconnects and
    /// coordinator restarts until `tessera workers enable`.
    Disable {
        /// A worker's id or name, as `tessera workers` shows them.
        worker: String,
        #[command(flatten)]
        common: ClientArgs,
    },
    /// The disabled machine takes tiles again.
    Enable {
        /// A connected worker's id or name, or the name of a disabled machine.
        worker: String,
        #[command(flatten)]
        common: ClientArgs,
    },
}

pub fn run(args: Args) -> Result<()> {
    super::block_on(async move {
        match args.action {
            None => list(&args.common.target()?, args.common.json).await,
            Some(action) => control(action).await,
        }
    })
}

async fn list(coordinator: &Endpoint, json_out: bool) -> Result<()> {
    let workers = Client::connect(coordinator).await?.workers().await?;
    if json_out {
        println!(
            "{}",
            Value::Array(workers.iter().map(worker_json).collect())
        );
    } else if workers.is_empty() {
        println!("no workers");
    } else {
        for w in &workers {
            let rtt = w.rtt_us.map_or(String::new(), |us| {
                format!(", rtt {:.1} ms", us as f64 / 1000.0)
            });
            let mut state = w
                .quarantined
                .as_ref()
                .map_or(String::new(), |why| format!(", QUARANTINED: {why}"));
            if w.disabled {
                state.push_str(", DISABLED");
            }
            if w.draining {
                state.push_str(", DRAINING");
            }
            if w.unresponsive {
                state.push_str(", UNRESPONSIVE");
            }
            // Which worker token it proved: after a rotation, "previous" marks the
            // workers whose token file is still to be replaced.
            let key = w.key.map_or(String::new(), |k| format!(", key {k}"));
            let cache = w.cache.as_ref().map_or(String::new(), cache_summary);
            let tags = if w.tags.is_empty() {
                String::new()
            } else {
                format!(", tags {}", w.tags.join(", "))
            };
            println!(
                "worker {} {} on {}: {}, {}/{} tiles in flight, {} done, {:.1} M rays/s{rtt}{cache}, build {}{key}{tags}{state}",
                w.id,
                w.name,
                w.host,
                counted(w.threads, "thread"),
                w.tiles_in_flight,
                w.credit,
                counted(w.tiles_done, "tile"),
                w.rays_per_second / 1e6,
                w.build,
            );
        }
    }
    Ok(())
}

/// Drains, disables or enables a worker; answers once the change is made (stored, for
/// a disable or an enable), saying which worker it acted on.
async fn control(action: WorkerAction) -> Result<()> {
    let (request, key, done, common) = match action {
        WorkerAction::Drain { worker, common } => (
            ClientRequest::DrainWorker {
                worker: worker.clone(),
            },
            worker,
            "draining: it finishes the tiles it holds, then exits".to_string(),
            common,
        ),
        WorkerAction::Disable { worker, common } => (
            ClientRequest::DisableWorker {
                worker: worker.clone(),
            },
            worker.clone(),
            format!(
                "disabled: its machine gets no new tiles until `tessera workers enable {worker}`"
            ),
            common,
        ),
        WorkerAction::Enable { worker, common } => (
            ClientRequest::EnableWorker {
                worker: worker.clone(),
            },
            worker,
            "enabled: it takes tiles again".into(),
            common,
        ),
    };
    // The one worker acted on (none when enabling a machine not connected).
    let workers = Client::connect(&common.target()?)
        .await?
        .control_worker(request)
        .await?;
    if common.json {
        println!(
            "{}",
            Value::Array(workers.iter().map(worker_json).collect())
        );
    } else {
        match workers.first() {
            Some(w) => println!("worker {} (id {}, host {}) {done}", w.name, w.id, w.host),
            None => println!("machine {key} {done}"),
        }
    }
    Ok(())
}

/// A worker's files in its listing line: `, cache 12 files 1.2 GB of 10.00 GB, 3.1 M
/// triangles built, fetching 1 file (12.0 of 33.7 MB)`, and what is wrong with its
/// disk cache, if anything.
fn cache_summary(c: &WorkerCache) -> String {
    let mut line = if c.capacity > 0 {
        format!(
            ", cache {} {} of {}",
            counted(c.files, "file"),
            bytes(c.bytes),
            bytes(c.capacity)
        )
    } else {
        ", no disk cache".to_string()
    };
    if c.geometry_triangles > 0 {
        line.push_str(&format!(
            ", {:.1} M triangles built",
            c.geometry_triangles as f64 / 1e6
        ));
    }
    if c.fetching > 0 {
        line.push_str(&format!(
            ", fetching {} ({} of {})",
            counted(c.fetching, "file"),
            bytes(c.fetching_received),
            bytes(c.fetching_total)
        ));
    }
    if let Some(problem) = &c.problem {
        line.push_str(&format!(" ({problem})"));
    }
    line
}
