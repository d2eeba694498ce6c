//! The commands about one job on a coordinator, or all of them: `status`, `list`,
//! `cancel`, `pause`, `resume`, `priority`, `events`, `retry`, `requeue`, `delete` and
//! `fetch`. Each connects, asks and prints the answer: a line for people, or with
//! `--json` an object for scripts.

use std::path::{Path, PathBuf};

use anyhow::Result;
use coordinator::client::Client;
use protocol::{JobId, JobState, JobStatus};
use serde_json::{json, Value};
use transport::Endpoint;

use crate::args::{parse_job_id, parse_priority, parse_tile_number, ClientArgs};
use crate::output::{FramesDir, ImageOutput};
use crate::report::{counted, frames_summary, shown_state, status_json, utc};
use crate::sequences::fetch_frames;

/// The job commands, listed in `tessera --help` between `submit` and `workers`.
#[derive(clap::Subcommand)]
pub enum Command {
    /// Show a job's state and progress.
    Status {
        /// The job's id (as `tessera submit` and `tessera list` show it).
        #[arg(value_parser = parse_job_id)]
        job: JobId,
        #[command(flatten)]
        common: ClientArgs,
    },

    /// List the coordinator's jobs, newest first (as the status page does).
    List {
        #[command(flatten)]
        common: ClientArgs,
    },

    /// Cancel a job: its tiles stop being rendered.
    Cancel {
        /// The job's id (as `tessera submit` and `tessera list` show it).
        #[arg(value_parser = parse_job_id)]
        job: JobId,
        #[command(flatten)]
        common: ClientArgs,
    },

    /// Pause a queued or running job: no new tiles of it go out until it is resumed.
    #[command(
        long_about = "Pause a queued or running job: no new tiles of it are handed out \
            (tiles already out may finish, and count) until `tessera resume`. The pause \
            survives a restart of the coordinator. Pausing a paused job changes nothing; \
            pausing a job that has ended is an error.",
        after_help = "Example:\n  tessera pause 7"
    )]
    Pause {
        /// The job's id (as `tessera submit` and `tessera list` show it).
        #[arg(value_parser = parse_job_id)]
        job: JobId,
        #[command(flatten)]
        common: ClientArgs,
    },

    /// Resume a paused job: its tiles are handed out again.
    #[command(after_help = "Example:\n  tessera resume 7")]
    Resume {
        /// The job's id (as `tessera submit` and `tessera list` show it).
        #[arg(value_parser = parse_job_id)]
        job: JobId,
        #[command(flatten)]
        common: ClientArgs,
    },

    /// Change a queued or running job's priority: higher runs first.
    #[command(
        long_about = "Change a queued or running job's priority (as `tessera submit \
            --priority` sets it): higher runs first, and the next tiles handed out follow \
            the new order. Tiles already out finish where they are. Kept across a restart \
            of the coordinator.",
        after_help = "Example:\n  tessera priority 7 10\n  tessera priority 7 -5"
    )]
    Priority {
        /// The job's id (as `tessera submit` and `tessera list` show it).
        #[arg(value_parser = parse_job_id)]
        job: JobId,
        /// The new priority: higher runs first.
        #[arg(allow_negative_numbers = true, value_parser = parse_priority)]
        priority: i32,
        #[command(flatten)]
        common: ClientArgs,
    },

    /// Show a job's event log: what happened to it, one line per event.
    #[command(
        long_about = "Show a job's event log, one line per event (time in UTC, event, \
            details): its submission (name, submitter, address), its first tile out, \
            each tile handed out and done (by which worker, in how long), failed or \
            taken back, quarantines affecting it, operators' pauses, priorities, \
            cancels, retries and requeues (with their address), adaptive passes, and \
            its end. Kept on the coordinator's disk with the job (at most 10,000 \
            events, then one saying how many more were not kept, and the end).",
        after_help = "Example:\n  tessera events 7\n  tessera events 7 --json"
    )]
    Events {
        /// The job's id (as `tessera submit` and `tessera list` show it).
        #[arg(value_parser = parse_job_id)]
        job: JobId,
        #[command(flatten)]
        common: ClientArgs,
    },

    /// Put a failed or cancelled job back in the queue under the same id.
    #[command(
        long_about = "Put a failed or cancelled job back in the queue under the same id: \
            the tiles it has stored count, the others are rendered, and its image is the \
            same as if it had never stopped. A job that is done, queued or running \
            cannot be retried.",
        after_help = "Example:\n  tessera retry 7"
    )]
    Retry {
        /// The job's id (as `tessera submit` and `tessera list` show it).
        #[arg(value_parser = parse_job_id)]
        job: JobId,
        /// For a sequence: render frame K again, alone (done, failed or cancelled).
        /// Without it, a sequence's failed and cancelled frames are rendered again.
        #[arg(long, value_name = "K", value_parser = clap::value_parser!(u32).range(1..))]
        frame: Option<u32>,
        #[command(flatten)]
        common: ClientArgs,
    },

    /// Render tiles of a queued or running job again (a machine is suspected).
    #[command(
        long_about = "Render the named tiles of a queued or running job again, wherever \
            they are: waiting, out on a worker (its result no longer counts), or done \
            (its result is dropped). For a machine an operator suspects; the events of \
            the job (`tessera events`) say which worker rendered each tile. A job that \
            has ended cannot be requeued: its image is final (submit it again instead).",
        after_help = "Example:\n  tessera requeue 7 3 4 12"
    )]
    Requeue {
        /// The job's id (as `tessera submit` and `tessera list` show it).
        #[arg(value_parser = parse_job_id)]
        job: JobId,
        /// The tiles' numbers (from 0, as the job's events name them).
        #[arg(required = true, num_args = 1.., value_parser = parse_tile_number)]
        tiles: Vec<u32>,
        #[command(flatten)]
        common: ClientArgs,
    },

    /// Delete an ended job (done, failed or cancelled) and its image from the coordinator.
    #[command(
        long_about = "Delete an ended job (done, failed or cancelled) from the coordinator: \
            its image, scene and records are removed from its disk and `tessera status` \
            no longer knows it. A queued or running job must be cancelled first. Its id \
            is never given to another job.",
        after_help = "Example:\n  tessera delete 7"
    )]
    Delete {
        /// The job's id (as `tessera submit` and `tessera list` show it).
        #[arg(value_parser = parse_job_id)]
        job: JobId,
        #[command(flatten)]
        common: ClientArgs,
    },

    /// Download a finished job's image.
    Fetch {
        /// The job's id (as `tessera submit` and `tessera list` show it).
        #[arg(value_parser = parse_job_id)]
        job: JobId,
        /// Where to write the PNG [default: job-JOB.png]; for a sequence, the directory
        /// its done frames go into, as frame_0001.png, ... [default: job-JOB/].
        #[arg(short, long, value_name = "OUT.png|DIR")]
        output: Option<PathBuf>,
        #[command(flatten)]
        common: ClientArgs,
    },
}

impl Command {
    /// Asks the coordinator of the command's `--coordinator` (and its TLS and token).
    pub fn run(self) -> Result<()> {
        super::block_on(async move {
            match self {
                Command::Status { job, common } => {
                    run_status(&common.target()?, job, common.json).await
                }
                Command::List { common } => run_list(&common.target()?, common.json).await,
                Command::Cancel { job, common } => {
                    run_cancel(&common.target()?, job, common.json).await
                }
                Command::Pause { job, common } => {
                    run_pause(&common.target()?, job, true, common.json).await
                }
                Command::Resume { job, common } => {
                    run_pause(&common.target()?, job, false, common.json).await
                }
                Command::Priority {
                    job,
                    priority,
                    common,
                } => run_priority(&common.target()?, job, priority, common.json).await,
                Command::Events { job, common } => {
                    run_events(&common.target()?, job, common.json).await
                }
                Command::Retry { job, frame, common } => {
                    run_retry(&common.target()?, job, frame, common.json).await
                }
                Command::Requeue { job, tiles, common } => {
                    run_requeue(&common.target()?, job, tiles, common.json).await
                }
                Command::Delete { job, common } => {
                    run_delete(&common.target()?, job, common.json).await
                }
                Command::Fetch {
                    job,
                    output,
                    common,
                } => run_fetch(&common.target()?, job, output, common.json).await,
            }
        })
    }
}

async fn run_status(coordinator: &Endpoint, job: JobId, json_out: bool) -> Result<()> {
    let status = Client::connect(coordinator).await?.status(job).await?;
    if json_out {
        println!("{}", status_json(&status));
    } else {
        if let Some(warning) = &status.warning {
            eprintln!("warning: {warning}");
        }
        println!("{}", status_line(&status));
    }
    Ok(())
}

/// `tessera list`: with `--json`, an array of jobs; the farm's warning (no worker can
/// take tiles) is in each active job's `warning` field, and on stderr once otherwise.
async fn run_list(coordinator: &Endpoint, json_out: bool) -> Result<()> {
    let mut jobs = Client::connect(coordinator).await?.list().await?;
    newest_first(&mut jobs);
    if json_out {
        println!("{}", Value::Array(jobs.iter().map(status_json).collect()));
    } else if jobs.is_empty() {
        println!("no jobs");
    } else {
        if let Some(warning) = jobs.iter().find_map(|s| s.warning.as_ref()) {
            eprintln!("warning: {warning}");
        }
        print!("{}", list_table(&jobs));
    }
    Ok(())
}

/// `tessera list`'s order, table and JSON alike: newest first, as the status page
/// shows jobs, so that what was just submitted is at the top (ids grow with each
/// submission).
fn newest_first(jobs: &mut [JobStatus]) {
    jobs.sort_by_key(|job| std::cmp::Reverse(job.id));
}

/// `tessera list`'s table: one row per job, columns aligned (`tessera status JOB`
/// gives the rest of a job's figures).
fn list_table(jobs: &[JobStatus]) -> String {
    let seconds = |ms: u64| format!("{:.1} s", ms as f64 / 1000.0);
    let mut rows = vec![[
        "ID",
        "STATE",
        "TILES",
        "FRAMES",
        "PRIORITY",
        "NAME",
        "SUBMITTER",
        "FROM",
        "SUBMITTED (UTC)",
        "QUEUED",
        "ELAPSED",
    ]
    .map(String::from)];
    for s in jobs {
        rows.push([
            s.id.to_string(),
            shown_state(s).to_string(),
            format!("{}/{}", s.tiles_done, s.tiles_total),
            s.frames.as_ref().map_or_else(
                || s.frame.to_string(),
                |f| format!("{}/{}", f.done, f.last - f.first + 1),
            ),
            s.priority.to_string(),
            if s.name.is_empty() {
                "-".into()
            } else {
                s.name.clone()
            },
            s.submitter.clone(),
            s.submitted_from.clone(),
            utc(s.submitted_unix_ms),
            s.queued_ms.map_or_else(|| "-".into(), seconds),
            seconds(s.elapsed_ms),
        ]);
    }
    let mut widths = [0usize; 11];
    for row in &rows {
        for (w, cell) in widths.iter_mut().zip(row) {
            *w = (*w).max(cell.chars().count());
        }
    }
    let mut out = String::new();
    for row in &rows {
        let cells: Vec<String> = row
            .iter()
            .zip(widths)
            .map(|(cell, w)| format!("{cell:<w$}"))
            .collect();
        out.push_str(cells.join("  ").trim_end());
        out.push('\n');
    }
    out
}

/// `tessera cancel`: a job already cancelled is no error (what was asked is so); one
/// that ended otherwise is, saying how it ended.
async fn run_cancel(coordinator: &Endpoint, job: JobId, json_out: bool) -> Result<()> {
    let mut client = Client::connect(coordinator).await?;
    let already = match client.cancel(job).await {
        Ok(()) => false,
        Err(refused) => match client.status(job).await {
            Ok(s) if s.state == JobState::Cancelled => true,
            Ok(s) if s.state.is_final() => anyhow::bail!(
                "job {job} is already {}: there is nothing to cancel (`tessera delete {job}` \
                 removes it)",
                s.state.as_str()
            ),
            _ => return Err(refused),
        },
    };
    if json_out {
        println!(
            "{}",
            json!({ "id": job, "state": "cancelled", "already_cancelled": already })
        );
    } else if already {
        println!("job {job} was already cancelled");
    } else {
        println!("job {job} cancelled");
    }
    Ok(())
}

/// `tessera pause` and `tessera resume`: a job already paused (or not paused) is no
/// error; one that has ended is.
async fn run_pause(coordinator: &Endpoint, job: JobId, pause: bool, json_out: bool) -> Result<()> {
    let mut client = Client::connect(coordinator).await?;
    let status = if pause {
        client.pause(job).await?
    } else {
        client.resume(job).await?
    };
    if json_out {
        println!("{}", status_json(&status));
    } else if pause {
        println!(
            "job {job} paused: no new tiles go out ({} of {} done; tiles already out may \
             finish); `tessera resume {job}` goes on",
            status.tiles_done, status.tiles_total
        );
    } else {
        println!("job {job} resumed: it is {}", shown_state(&status));
    }
    Ok(())
}

/// `tessera priority JOB N`.
async fn run_priority(
    coordinator: &Endpoint,
    job: JobId,
    priority: i32,
    json_out: bool,
) -> Result<()> {
    let status = Client::connect(coordinator)
        .await?
        .set_priority(job, priority)
        .await?;
    if json_out {
        println!("{}", status_json(&status));
    } else {
        println!(
            "job {job} now has priority {}: its next tiles go out by it",
            status.priority
        );
    }
    Ok(())
}

/// `tessera events JOB`: the job's event log, one line per entry (every page of it).
async fn run_events(coordinator: &Endpoint, job: JobId, json_out: bool) -> Result<()> {
    let mut client = Client::connect(coordinator).await?;
    let mut after = 0;
    let mut all = Vec::new();
    loop {
        let page = client.events(job, after).await?;
        let last = page.len() < protocol::EVENTS_PER_PAGE;
        if let Some(e) = page.last() {
            after = e.seq;
        }
        all.extend(page);
        if last {
            break;
        }
    }
    if json_out {
        let events: Vec<Value> = all.iter().map(coordinator::client::event_json).collect();
        println!("{}", Value::Array(events));
    } else if all.is_empty() {
        println!("no events recorded for job {job}");
    } else {
        for e in &all {
            println!(
                "{}.{:03} {:<16} {}",
                utc(e.unix_ms),
                e.unix_ms % 1000,
                e.kind,
                e.detail
            );
        }
    }
    Ok(())
}

/// `tessera retry JOB`.
async fn run_retry(
    coordinator: &Endpoint,
    job: JobId,
    frame: Option<u32>,
    json_out: bool,
) -> Result<()> {
    let mut client = Client::connect(coordinator).await?;
    let status = match frame {
        Some(k) => client.requeue_frame(job, k).await?,
        None => client.retry(job).await?,
    };
    if json_out {
        println!("{}", status_json(&status));
    } else if let Some(f) = &status.frames {
        let again = match frame {
            Some(k) => format!("frame {k} is"),
            None => "its failed and cancelled frames are".into(),
        };
        println!(
            "job {job}: {again} back in the queue ({})",
            frames_summary(f)
        );
    } else {
        println!(
            "job {job} is back in the queue: {} of {} tiles kept, the others are rendered",
            status.tiles_done, status.tiles_total
        );
    }
    Ok(())
}

/// `tessera requeue JOB TILE...`.
async fn run_requeue(
    coordinator: &Endpoint,
    job: JobId,
    tiles: Vec<u32>,
    json_out: bool,
) -> Result<()> {
    let count = tiles.len();
    let status = Client::connect(coordinator)
        .await?
        .requeue(job, tiles)
        .await?;
    if json_out {
        println!("{}", status_json(&status));
    } else {
        println!(
            "job {job}: {count} tile{} to be rendered again ({} of {} done)",
            if count == 1 { "" } else { "s" },
            status.tiles_done,
            status.tiles_total
        );
    }
    Ok(())
}

async fn run_delete(coordinator: &Endpoint, job: JobId, json_out: bool) -> Result<()> {
    Client::connect(coordinator).await?.delete(job).await?;
    if json_out {
        println!("{}", json!({ "id": job, "state": "deleted" }));
    } else {
        println!("job {job} deleted");
    }
    Ok(())
}

async fn run_fetch(
    coordinator: &Endpoint,
    job: JobId,
    output: Option<PathBuf>,
    json_out: bool,
) -> Result<()> {
    let mut client = Client::connect(coordinator).await?;
    let status = client.status(job).await?;
    if status.frames.is_some() {
        return run_fetch_sequence(&mut client, &status, output.as_deref(), json_out).await;
    }
    let output =
        ImageOutput::create(&output.unwrap_or_else(|| PathBuf::from(format!("job-{job}.png"))))?;
    let path = output.path().to_path_buf();
    let bytes = fetch_to(&mut client, job, output).await?;
    if json_out {
        println!(
            "{}",
            json!({ "id": job, "output": path.display().to_string(), "bytes": bytes })
        );
    } else {
        println!("{}", path.display());
    }
    Ok(())
}

fn status_line(s: &JobStatus) -> String {
    // Frame 1 (every job of a scene without animation) goes without saying.
    let frame = match (&s.frames, s.frame) {
        (Some(f), _) => format!("{}, ", frames_summary(f)),
        (None, 1) => String::new(),
        (None, k) => format!("frame {k}, "),
    };
    let mut line = format!(
        "job {}: {}, {frame}{}/{} tiles, {}x{} aa {} {}{}, {}, {:.1} s",
        s.id,
        shown_state(s),
        s.tiles_done,
        s.tiles_total,
        s.settings.width,
        s.settings.height,
        s.settings.aa,
        s.settings.sampling.name(),
        crate::report::assets_summary(&s.assets),
        counted(s.samples, "sample"),
        s.elapsed_ms as f64 / 1000.0
    );
    if !s.waiting_for.is_empty() {
        let on: Vec<String> = s.waiting_for.iter().map(|j| format!("job {j}")).collect();
        line.push_str(&format!(" (waiting for {} to be done)", on.join(", ")));
    } else if !s.after.is_empty() && !s.state.is_final() {
        let on: Vec<String> = s.after.iter().map(|j| j.to_string()).collect();
        line.push_str(&format!(" (after jobs {}, done)", on.join(", ")));
    }
    if let Some(q) = s.queued_ms {
        line.push_str(&format!(" ({:.1} s of it in the queue)", q as f64 / 1000.0));
    }
    if let Some(e) = s.estimated_error {
        line.push_str(&format!(", estimated error {e:.3} levels"));
    }
    if let Some(eta) = s.eta_ms {
        line.push_str(&format!(", about {:.1} s left", eta as f64 / 1000.0));
    }
    if !s.require.is_empty() {
        line.push_str(&format!(", requires {}", s.require.join(", ")));
    }
    line.push_str(&format!(
        "; {:?} by {} from {}, submitted {} UTC",
        s.name,
        s.submitter,
        s.submitted_from,
        utc(s.submitted_unix_ms)
    ));
    if let Some(e) = &s.error {
        line.push_str(&format!(": {e}"));
    }
    line
}

/// Fetches a finished job's image and writes it.
async fn fetch_to(client: &mut Client, job: JobId, output: ImageOutput) -> Result<usize> {
    let png = client.fetch(job).await?;
    output.write(&png)?;
    Ok(png.len())
}

/// `tessera fetch` of a sequence: its done frames into `dir` [default: `job-N/`].
async fn run_fetch_sequence(
    client: &mut Client,
    status: &JobStatus,
    dir: Option<&Path>,
    json_out: bool,
) -> Result<()> {
    let job = status.id;
    let frames = status.frames.as_ref().expect("a sequence");
    let default = format!("job-{job}");
    let dir = FramesDir::create(dir.unwrap_or(Path::new(&default)))?;
    let written = fetch_frames(client, job, frames, &dir).await?;
    let total = frames.last - frames.first + 1;
    if json_out {
        println!(
            "{}",
            json!({ "id": job, "output": dir.path().display().to_string(), "frames": written, "of": total })
        );
    } else {
        println!(
            "{}: {written} of {total} frames{}",
            dir.path().display(),
            if written < total {
                " (the others are not done)"
            } else {
                ""
            }
        );
    }
    Ok(())
}
