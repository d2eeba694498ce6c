//! `tessera submit`, `status`, `list`, `cancel`, `pause`, `resume`, `priority`, `events`,
//! `retry`, `requeue`, `delete`, `fetch` and `workers` (with `workers drain|disable|enable`).

use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::{anyhow, Context, Result};
use coordinator::client::{Client, ConnectionLost};
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use protocol::{
    JobId, JobSpec, JobState, JobStatus, Overrides, Sampling, Settings, Verification, WorkerStatus,
};
use render::RenderSettings;
use serde_json::{json, Value};
use transport::{DialError, Endpoint};

use crate::output::{default_output, FramesDir, ImageOutput};
use crate::render_command::sampling_summary;
use crate::sequence_commands::{frames_summary, run_fetch_sequence, wait_sequence, FrameChoice};

/// Reads a scene file for submission.
pub fn read_scene(path: &Path) -> Result<String> {
    std::fs::read_to_string(path)
        .with_context(|| format!("cannot read scene file {}", path.display()))
}

/// What a job is called and who submitted it; `None` takes the default.
#[derive(Clone, Debug, Default)]
pub struct Label {
    /// Default: the scene file's stem.
    pub name: Option<String>,
    /// Default: [`default_submitter`].
    pub submitter: Option<String>,
}

/// `$USER@hostname`: who a job says submitted it unless told. It is the client's
/// claim, not checked by anyone; the coordinator records the address the submission
/// came from beside it.
pub fn default_submitter() -> String {
    let user = ["USER", "USERNAME", "LOGNAME"]
        .iter()
        .find_map(|v| std::env::var(v).ok().filter(|u| !u.is_empty()))
        .unwrap_or_else(|| "unknown".into());
    let host = ["/proc/sys/kernel/hostname", "/etc/hostname"]
        .iter()
        .find_map(|p| {
            std::fs::read_to_string(p)
                .ok()
                .map(|h| h.trim().to_string())
                .filter(|h| !h.is_empty())
        })
        .or_else(|| std::env::var("COMPUTERNAME").ok())
        .unwrap_or_else(|| "localhost".into());
    format!("{user}@{host}")
}

/// Submits; a refused scene's message is prefixed with the file name, exactly as
/// `tessera render` reports it.
pub async fn submit(client: &mut Client, scene_path: &Path, job: JobChoices) -> Result<JobId> {
    let JobChoices {
        overrides,
        priority,
        verification,
        time_limit_ms,
        label,
        frames,
    } = job;
    let scene = read_scene(scene_path)?;
    let name = label.name.unwrap_or_else(|| {
        scene_path
            .file_stem()
            .map_or_else(String::new, |s| s.to_string_lossy().into_owned())
    });
    client
        .submit(JobSpec {
            scene,
            overrides,
            priority,
            verification,
            time_limit_ms,
            name,
            submitter: label.submitter.unwrap_or_else(default_submitter),
            frame: frames.frame,
            frames: frames.frames,
        })
        .await
        .map_err(|e| anyhow!("{}: {e}", scene_path.display()))
}

/// How long a lost coordinator is tried again before following a job gives up.
const RECONNECT_FOR: Duration = Duration::from_secs(300);
/// The pause before the first try to reconnect; it doubles after each failed one...
const FIRST_RETRY: Duration = Duration::from_millis(100);
/// ...up to this.
const LONGEST_RETRY: Duration = Duration::from_secs(2);
/// A coordinator answers a watch within a second even without progress, so a
/// connection silent for this long is lost (a cut network, a stopped coordinator).
const ANSWER_TIMEOUT: Duration = Duration::from_secs(15);
/// A wait whose job made no progress while the coordinator said, for this long, that no
/// worker can take tiles prints that warning (once): a short gap between workers, or
/// workers reconnecting to a restarted coordinator, says nothing.
const NO_WORKER_GRACE: Duration = Duration::from_secs(3);

/// A connection to a coordinator that is opened again, with backoff, whenever it is
/// lost: what `submit --wait` and `up` follow a job through. Only requests that are
/// safe to repeat (watching, fetching) go through it.
pub struct Session {
    endpoint: Endpoint,
    client: Client,
    /// When the current outage began: the connection was lost and no request has
    /// succeeded since.
    outage: Option<Instant>,
    /// The progress bar shown, so that messages do not tear it.
    bar: ProgressBar,
}

impl Session {
    pub async fn connect(endpoint: &Endpoint) -> Result<Session> {
        let mut client = Client::connect(endpoint).await?;
        client.set_answer_timeout(ANSWER_TIMEOUT);
        Ok(Session {
            endpoint: endpoint.clone(),
            client,
            outage: None,
            bar: ProgressBar::hidden(),
        })
    }

    /// The connection as it is now, for a request that must not be repeated.
    pub fn client(&mut self) -> &mut Client {
        &mut self.client
    }

    /// Makes `call` on the connection; if the connection is lost, says so (once per
    /// outage), reconnects and makes it again, for up to [`RECONNECT_FOR`].
    async fn retrying<T>(
        &mut self,
        mut call: impl AsyncFnMut(&mut Client) -> Result<T>,
    ) -> Result<T> {
        loop {
            let error = match call(&mut self.client).await {
                Ok(value) => {
                    self.outage = None;
                    return Ok(value);
                }
                Err(e) => e,
            };
            let Some(lost) = ConnectionLost::of(&error) else {
                return Err(error);
            };
            let since = match self.outage {
                Some(since) => since,
                None => {
                    let reason = &lost.reason;
                    self.bar
                        .suspend(|| eprintln!("lost the coordinator ({reason}): reconnecting"));
                    *self.outage.insert(Instant::now())
                }
            };
            self.reconnect(since + RECONNECT_FOR).await?;
        }
    }

    /// Dials until the coordinator answers, pausing 100 ms, then twice as long after
    /// each failure up to 2 s; gives up at `deadline`, or at once if the coordinator
    /// answers but refuses this client.
    async fn reconnect(&mut self, deadline: Instant) -> Result<()> {
        let mut pause = FIRST_RETRY;
        loop {
            tokio::time::sleep(pause).await;
            match Client::dial(&self.endpoint).await {
                Ok(mut client) => {
                    client.set_answer_timeout(ANSWER_TIMEOUT);
                    self.client = client;
                    return Ok(());
                }
                Err(DialError::Refused(e)) => return Err(e),
                Err(DialError::Unreachable(e)) if Instant::now() + pause >= deadline => {
                    return Err(e.context(format!(
                        "lost the coordinator at {} and could not reconnect within {} min",
                        self.endpoint.address,
                        RECONNECT_FOR.as_secs() / 60
                    )))
                }
                Err(DialError::Unreachable(_)) => pause = (pause * 2).min(LONGEST_RETRY),
            }
        }
    }

    pub(crate) async fn watch(&mut self, job: JobId, after_tiles: u32) -> Result<JobStatus> {
        self.retrying(async |client: &mut Client| client.watch(job, after_tiles).await)
            .await
    }

    /// A done frame of a sequence, reconnecting if need be.
    pub async fn fetch_frame(&mut self, job: JobId, frame: u32) -> Result<Vec<u8>> {
        self.retrying(async |client: &mut Client| client.fetch_frame(job, frame).await)
            .await
    }

    /// A finished job's image, reconnecting if need be.
    pub async fn fetch(&mut self, job: JobId) -> Result<Vec<u8>> {
        self.retrying(async |client: &mut Client| client.fetch(job).await)
            .await
    }
}

/// Follows a job until it ends, with a progress bar on a terminal, and returns its
/// final status. A job that fails or is cancelled is an error.
pub async fn wait(session: &mut Session, job: JobId) -> Result<JobStatus> {
    let bar = if std::io::stderr().is_terminal() {
        ProgressBar::with_draw_target(None, ProgressDrawTarget::stderr())
    } else {
        ProgressBar::hidden()
    };
    session.bar = bar.clone();
    bar.set_style(
        ProgressStyle::with_template(
            "{spinner} [{elapsed_precise}] {wide_bar} {pos}/{len} tiles {msg}",
        )
        .expect("the template is valid"),
    );
    let mut seen = 0;
    // Since when the coordinator has said, answer after answer without progress, that
    // no worker can take tiles.
    let mut stuck_since: Option<Instant> = None;
    let mut warned = false;
    let status = loop {
        let status = match session.watch(job, seen).await {
            Ok(status) => status,
            Err(e) => {
                bar.abandon();
                session.bar = ProgressBar::hidden();
                return Err(e);
            }
        };
        if status.tiles_done != seen || status.warning.is_none() {
            stuck_since = None;
        } else {
            let since = *stuck_since.get_or_insert_with(Instant::now);
            if let Some(warning) = status.warning.as_ref().filter(|_| !warned) {
                if since.elapsed() >= NO_WORKER_GRACE {
                    bar.suspend(|| eprintln!("warning: job {job}: {warning}"));
                    warned = true;
                }
            }
        }
        seen = status.tiles_done;
        bar.set_length(u64::from(status.tiles_total));
        bar.set_position(u64::from(status.tiles_done));
        let rate = status.rays as f64 / (status.elapsed_ms.max(1) as f64 / 1000.0) / 1e6;
        let eta = status.eta_ms.map_or(String::new(), |ms| {
            format!(", {:.1} s left", ms as f64 / 1000.0)
        });
        bar.set_message(format!("{rate:.1} M rays/s{eta}"));
        if status.state.is_final() {
            break status;
        }
    };
    bar.finish_and_clear();
    session.bar = ProgressBar::hidden();
    done_or_why(job, status)
}

/// A final status as the answer to waiting: done, or an error saying how it ended.
pub fn done_or_why(job: JobId, status: JobStatus) -> Result<JobStatus> {
    match status.state {
        JobState::Done => Ok(status),
        JobState::Failed => Err(anyhow!(
            "job {job} failed: {}",
            status.error.as_deref().unwrap_or("no reason given")
        )),
        other => Err(anyhow!("job {job} is {}", other.as_str())),
    }
}

/// Fetches a finished job's image and writes it.
pub async fn fetch_to(client: &mut Client, job: JobId, output: ImageOutput) -> Result<usize> {
    let png = client.fetch(job).await?;
    output.write(&png)?;
    Ok(png.len())
}

/// Waits for `job` to end and downloads its image to `output`; an error names the job.
async fn wait_and_fetch(
    session: &mut Session,
    job: JobId,
    output: ImageOutput,
) -> Result<JobStatus> {
    async {
        let status = wait(session, job).await?;
        fetch_through(session, job, output).await?;
        Ok(status)
    }
    .await
    .map_err(|e| naming_job(job, e))
}

/// Fetches a finished job's image through a session, reconnecting if need be, and
/// writes it; a file that cannot be written (it was checked before the job, but a disk
/// fills and directories go) is reported with how to fetch the image again.
pub async fn fetch_through(
    session: &mut Session,
    job: JobId,
    output: ImageOutput,
) -> Result<usize> {
    let png = session.fetch(job).await?;
    let path = output.path().to_path_buf();
    output.write(&png).map_err(|e| {
        anyhow!(
            "job {job} is done, but {e:#}: `tessera fetch {job} -o {}` recovers it",
            path.display()
        )
    })?;
    Ok(png.len())
}

/// `error` with the job's id in front, unless it names the job already: whatever ends
/// the wait for a submitted job, the user learns its id.
fn naming_job(job: JobId, error: anyhow::Error) -> anyhow::Error {
    let text = format!("{error:#}");
    let name = format!("job {job}");
    let named = text
        .match_indices(&name)
        .any(|(at, _)| !text[at + name.len()..].starts_with(|c: char| c.is_ascii_digit()));
    if named {
        error
    } else {
        error.context(name)
    }
}

/// The one-line summary of a finished job: size, samples spent, estimated error, tiles,
/// time.
pub fn summary(output: &Path, status: &JobStatus) -> String {
    // The time rendering took: the queue's wait is not the farm's speed.
    let queued = status.queued_ms.unwrap_or(0).min(status.elapsed_ms);
    let secs = (status.elapsed_ms - queued) as f64 / 1000.0;
    let wait = if queued > 0 {
        format!(" after {:.1} s in the queue", queued as f64 / 1000.0)
    } else {
        String::new()
    };
    // As `tessera render` says it: whether the time limit, not the target, ended it.
    let target_given = status.settings.sampling
        != (Sampling::Adaptive {
            target_milli: render::MIN_TARGET_MILLI,
        });
    let note = match (status.stopped_on_time_limit, target_given) {
        (false, _) => "",
        (true, true) => "; stopped by the time limit before the target",
        (true, false) => "; as far as the time limit allowed",
    };
    format!(
        "{}: {}x{}, {}{note}, {} tiles, rendered in {:.3} s{wait}, {:.1} M rays/s",
        output.display(),
        status.settings.width,
        status.settings.height,
        sampling_summary(
            &render_settings(&status.settings),
            status.samples,
            status.estimated_error
        ),
        status.tiles_total,
        secs,
        status.rays as f64 / secs.max(1e-9) / 1e6
    )
}

/// The renderer's view of a job's settings, for the summary.
fn render_settings(s: &Settings) -> RenderSettings {
    RenderSettings {
        width: s.width,
        height: s.height,
        aa: s.aa,
        max_depth: s.max_depth,
        sampling: match s.sampling {
            Sampling::Grid => render::Sampling::Grid,
            Sampling::Jittered => render::Sampling::Jittered,
            Sampling::Adaptive { target_milli } => render::Sampling::Adaptive { target_milli },
        },
    }
}

/// What a submission chooses besides its scene.
pub struct JobChoices {
    pub overrides: Overrides,
    pub priority: i32,
    pub verification: Verification,
    /// Milliseconds of rendering an adaptive job may take, if limited.
    pub time_limit_ms: Option<u64>,
    pub label: Label,
    /// The frame of the scene, from 1, or a sequence of frames.
    pub frames: FrameChoice,
}

/// Where `tessera submit --wait` writes what it waits for: a job's image, or a
/// sequence's frames into a directory as they are done.
enum WaitOutput {
    Image(ImageOutput),
    Frames(FramesDir),
}

impl WaitOutput {
    fn path(&self) -> &Path {
        match self {
            WaitOutput::Image(o) => o.path(),
            WaitOutput::Frames(d) => d.path(),
        }
    }
}

/// `tessera submit`. With `--wait`, a job's image is written to `-o` [default: the
/// scene's file name with .png]; a sequence's frames into the directory `-o` [default:
/// the scene's file name without .json] as they are done.
pub async fn run_submit(
    coordinator: &Endpoint,
    scene: &Path,
    job: JobChoices,
    wait_for_it: bool,
    output: Option<PathBuf>,
    json_out: bool,
) -> Result<()> {
    // The output is checked before the farm spends anything on it.
    let output = match (wait_for_it, job.frames.frames.is_some()) {
        (false, _) => None,
        (true, false) => Some(WaitOutput::Image(ImageOutput::create(
            &output.unwrap_or_else(|| default_output(scene)),
        )?)),
        (true, true) => Some(WaitOutput::Frames(FramesDir::create(
            &output.unwrap_or_else(|| default_output(scene).with_extension("")),
        )?)),
    };
    let mut session = Session::connect(coordinator).await?;
    let job = submit(session.client(), scene, job).await?;
    let Some(output) = output else {
        print_submitted(job, json_out);
        return Ok(());
    };
    eprintln!("submitted job {job}");
    let output_path = output.path().to_path_buf();
    let status = match output {
        WaitOutput::Image(image) => wait_and_fetch(&mut session, job, image).await?,
        WaitOutput::Frames(dir) => wait_sequence(&mut session, job, Some(&dir))
            .await
            .map_err(|e| naming_job(job, e))?,
    };
    if json_out {
        let mut v = status_json(&status);
        v["output"] = json!(output_path.display().to_string());
        println!("{v}");
    } else if status.frames.is_some() {
        eprintln!("{}", sequence_summary(&output_path, &status));
    } else {
        eprintln!("{}", summary(&output_path, &status));
    }
    Ok(())
}

/// What `tessera submit` without `--wait` prints: the job's id.
fn print_submitted(job: JobId, json_out: bool) {
    if json_out {
        println!("{}", json!({ "id": job, "state": "queued" }));
    } else {
        println!("{job}");
    }
}

/// The one-line summary of a finished sequence.
pub fn sequence_summary(dir: &Path, status: &JobStatus) -> String {
    let frames = status.frames.as_ref().map_or(0, |f| f.done);
    let queued = status.queued_ms.unwrap_or(0).min(status.elapsed_ms);
    let secs = (status.elapsed_ms - queued) as f64 / 1000.0;
    format!(
        "{}: {frames} frames of {}x{}, {}, rendered in {:.3} s ({:.2} frames/s), {:.1} M rays/s",
        dir.display(),
        status.settings.width,
        status.settings.height,
        sampling_summary(
            &render_settings(&status.settings),
            status.samples / u64::from(frames.max(1)),
            status.estimated_error
        ),
        secs,
        f64::from(frames) / secs.max(1e-9),
        status.rays as f64 / secs.max(1e-9) / 1e6
    )
}

/// What a refinement of a farm job asks for.
pub struct Refinement {
    /// The new target; `None`: the old job's.
    pub target_milli: Option<u32>,
    pub aa: Option<u32>,
    pub time_limit_ms: Option<u64>,
}

/// `tessera refine JOB`: a new job going on from a finished adaptive job's samples;
/// prints its id, or with `wait`, follows it and writes its image.
pub async fn run_refine(
    coordinator: &Endpoint,
    old: JobId,
    refinement: Refinement,
    wait_for_it: bool,
    output: Option<PathBuf>,
    json_out: bool,
) -> Result<()> {
    // A file named is checked before the farm spends anything on it.
    let checked = match (wait_for_it, &output) {
        (true, Some(path)) => Some(ImageOutput::create(path)?),
        _ => None,
    };
    let mut session = Session::connect(coordinator).await?;
    let target_milli = match refinement.target_milli {
        Some(t) => t,
        None => match session.client().status(old).await?.settings.sampling {
            Sampling::Adaptive { target_milli } => target_milli,
            other => anyhow::bail!(
                "cannot refine job {old}: it was rendered with {} sampling: only adaptive \
                 jobs keep their tile states",
                other.name()
            ),
        },
    };
    let job = session
        .client()
        .refine(old, target_milli, refinement.aa, refinement.time_limit_ms)
        .await?;
    if !wait_for_it {
        if json_out {
            println!(
                "{}",
                json!({ "id": job, "state": "queued", "refines": old })
            );
        } else {
            println!("{job}");
        }
        return Ok(());
    }
    eprintln!("refining job {old} as job {job}");
    let output = match checked {
        Some(output) => output,
        None => ImageOutput::create(&PathBuf::from(format!("job-{job}.png")))
            .map_err(|e| naming_job(job, e))?,
    };
    let output_path = output.path().to_path_buf();
    let status = wait_and_fetch(&mut session, job, output).await?;
    if json_out {
        let mut v = status_json(&status);
        v["output"] = json!(output_path.display().to_string());
        v["refines"] = json!(old);
        println!("{v}");
    } else {
        eprintln!("{}", summary(&output_path, &status));
    }
    Ok(())
}

pub async fn run_status(coordinator: &Endpoint, job: JobId, json_out: bool) -> Result<()> {
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
pub async fn run_list(coordinator: &Endpoint, json_out: bool) -> Result<()> {
    let jobs = Client::connect(coordinator).await?.list().await?;
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
pub async fn run_cancel(coordinator: &Endpoint, job: JobId, json_out: bool) -> Result<()> {
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
pub async fn run_pause(
    coordinator: &Endpoint,
    job: JobId,
    pause: bool,
    json_out: bool,
) -> Result<()> {
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
pub async fn run_priority(
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
pub async fn run_events(coordinator: &Endpoint, job: JobId, json_out: bool) -> Result<()> {
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
pub async fn run_retry(
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
pub async fn run_requeue(
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

pub async fn run_delete(coordinator: &Endpoint, job: JobId, json_out: bool) -> Result<()> {
    Client::connect(coordinator).await?.delete(job).await?;
    if json_out {
        println!("{}", json!({ "id": job, "state": "deleted" }));
    } else {
        println!("job {job} deleted");
    }
    Ok(())
}

pub async fn run_fetch(
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

/// What `tessera workers drain|disable|enable` asks.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum WorkerControl {
    Drain,
    Disable,
    Enable,
}

/// `tessera workers drain|disable|enable WORKER`: answers once the change is made
/// (stored, for a disable or enable).
pub async fn run_worker_control(
    coordinator: &Endpoint,
    control: WorkerControl,
    worker: &str,
    json_out: bool,
) -> Result<()> {
    let request = match control {
        WorkerControl::Drain => protocol::ClientRequest::DrainWorker {
            worker: worker.to_string(),
        },
        WorkerControl::Disable => protocol::ClientRequest::DisableWorker {
            worker: worker.to_string(),
        },
        WorkerControl::Enable => protocol::ClientRequest::EnableWorker {
            worker: worker.to_string(),
        },
    };
    let workers = Client::connect(coordinator)
        .await?
        .control_worker(request)
        .await?;
    if json_out {
        println!(
            "{}",
            Value::Array(workers.iter().map(worker_json).collect())
        );
    } else {
        println!(
            "{}",
            match control {
                WorkerControl::Drain =>
                    format!("worker {worker} draining: it finishes the tiles it holds, then exits"),
                WorkerControl::Disable => format!(
                    "worker {worker} disabled: its machine gets no new tiles until \
                     `tessera workers enable {worker}`"
                ),
                WorkerControl::Enable => format!("worker {worker} enabled: it takes tiles again"),
            }
        );
    }
    Ok(())
}

pub async fn run_workers(coordinator: &Endpoint, json_out: bool) -> Result<()> {
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
            println!(
                "worker {} {}: {} threads, {}/{} tiles in flight, {} tiles done, {:.1} M rays/s{rtt}, build {}{state}",
                w.id,
                w.name,
                w.threads,
                w.tiles_in_flight,
                w.credit,
                w.tiles_done,
                w.rays_per_second / 1e6,
                w.build,
            );
        }
    }
    Ok(())
}

/// The state shown for a job: its lifecycle state, or "paused".
fn shown_state(s: &JobStatus) -> &'static str {
    if s.paused && !s.state.is_final() {
        "paused"
    } else {
        s.state.as_str()
    }
}

fn status_line(s: &JobStatus) -> String {
    // Frame 1 (every job of a scene without animation) goes without saying.
    let frame = match (&s.frames, s.frame) {
        (Some(f), _) => format!("{}, ", frames_summary(f)),
        (None, 1) => String::new(),
        (None, k) => format!("frame {k}, "),
    };
    let mut line = format!(
        "job {}: {}, {frame}{}/{} tiles, {}x{} aa {} {}, {} samples, {:.1} s",
        s.id,
        shown_state(s),
        s.tiles_done,
        s.tiles_total,
        s.settings.width,
        s.settings.height,
        s.settings.aa,
        s.settings.sampling.name(),
        s.samples,
        s.elapsed_ms as f64 / 1000.0
    );
    if let Some(q) = s.queued_ms {
        line.push_str(&format!(" ({:.1} s of it in the queue)", q as f64 / 1000.0));
    }
    if let Some(e) = s.estimated_error {
        line.push_str(&format!(", estimated error {e:.3} levels"));
    }
    if let Some(eta) = s.eta_ms {
        line.push_str(&format!(", about {:.1} s left", eta as f64 / 1000.0));
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

fn status_json(s: &JobStatus) -> Value {
    json!({
        "id": s.id,
        "state": shown_state(s),
        "paused": s.paused,
        "frame": s.frame,
        "width": s.settings.width,
        "height": s.settings.height,
        "aa": s.settings.aa,
        "max_depth": s.settings.max_depth,
        "priority": s.priority,
        "tiles_done": s.tiles_done,
        "tiles_total": s.tiles_total,
        "rays": s.rays,
        "elapsed_ms": s.elapsed_ms,
        "eta_ms": s.eta_ms,
        "error": s.error,
        "sampler": s.settings.sampling.name(),
        "target_error": s.settings.sampling.target_error(),
        "samples": s.samples,
        // The mean over the whole image, known once every tile is in.
        // A sequence's samples are its frames': per pixel of a frame.
        "samples_per_pixel": (s.state == JobState::Done).then(|| {
            let frames = s.frames.as_ref().map_or(1, |f| u64::from(f.last - f.first + 1));
            s.samples as f64
                / (u64::from(s.settings.width) * u64::from(s.settings.height) * frames) as f64
        }),
        "estimated_error": s.estimated_error,
        "time_limit_ms": s.time_limit_ms,
        "stopped_on_time_limit": s.stopped_on_time_limit,
        "warning": s.warning,
        "name": s.name,
        "submitter": s.submitter,
        "submitted_from": s.submitted_from,
        "submitted_unix_ms": s.submitted_unix_ms,
        "queued_ms": s.queued_ms,
        "sequence": s.sequence,
        "frames": s.frames.as_ref().map(frames_json),
    })
}

/// A sequence's frames as JSON.
fn frames_json(f: &protocol::FrameProgress) -> Value {
    let failures: Vec<Value> = f
        .failures
        .iter()
        .map(|x| json!({ "frame": x.frame, "job": x.job, "error": x.error }))
        .collect();
    json!({
        "first": f.first,
        "last": f.last,
        "done": f.done,
        "active": f.active,
        "pending": f.pending,
        "cancelled": f.cancelled,
        "failed": f.failed,
        "done_prefix": f.done_prefix,
        "failures": failures,
    })
}

/// A Unix time in milliseconds as `YYYY-MM-DD HH:MM:SS` UTC (the civil calendar from
/// days since the epoch; no time zone database needed).
pub fn utc(unix_ms: u64) -> String {
    let secs = unix_ms / 1000;
    let (days, rest) = ((secs / 86_400) as i64, secs % 86_400);
    // Howard Hinnant's days-to-civil algorithm.
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = doy - (153 * mp + 2) / 5 + 1;
    let month = if mp < 10 { mp + 3 } else { mp - 9 };
    let year = yoe + era * 400 + i64::from(month <= 2);
    format!(
        "{year:04}-{month:02}-{day:02} {:02}:{:02}:{:02}",
        rest / 3600,
        rest % 3600 / 60,
        rest % 60
    )
}

fn worker_json(w: &WorkerStatus) -> Value {
    json!({
        "id": w.id,
        "name": w.name,
        "threads": w.threads,
        "tiles_in_flight": w.tiles_in_flight,
        "tiles_done": w.tiles_done,
        "rays": w.rays,
        "connected_ms": w.connected_ms,
        "rays_per_second": w.rays_per_second,
        "build": w.build,
        "quarantined": w.quarantined,
        "rtt_us": w.rtt_us,
        "credit": w.credit,
        "draining": w.draining,
        "disabled": w.disabled,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn utc_times_are_the_calendar() {
        assert_eq!(utc(0), "1970-01-01 00:00:00");
        assert_eq!(utc(951_782_400_000), "2000-02-29 00:00:00");
        assert_eq!(utc(1_795_000_000_123), "2026-11-18 11:06:40");
    }

    #[test]
    fn an_error_that_ends_a_wait_names_the_job() {
        let named = |job, text: &str| format!("{:#}", naming_job(job, anyhow!(text.to_owned())));
        assert_eq!(named(7, "job 7 failed: boom"), "job 7 failed: boom");
        assert_eq!(
            named(7, "no job 70 on this coordinator"),
            "job 7: no job 70 on this coordinator"
        );
        assert_eq!(
            named(7, "the image is damaged"),
            "job 7: the image is damaged"
        );
        assert_eq!(
            named(12, "lost the coordinator: no job 12"),
            "lost the coordinator: no job 12"
        );
    }
}
