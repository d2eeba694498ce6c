//! Following a job on a coordinator: a connection that is opened again whenever it is
//! lost, waiting for the job with a progress bar, and fetching its image.

use std::io::IsTerminal;
use std::time::{Duration, Instant};

use anyhow::{anyhow, Result};
use coordinator::client::{Client, ConnectionLost};
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use protocol::{JobId, JobState, JobStatus};
use transport::{DialError, Endpoint};

use crate::output::ImageOutput;

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

    /// The job's status once it has progressed past `after_tiles` or ended
    /// ([`Client::watch`]), reconnecting if need be.
    pub async fn watch(&mut self, job: JobId, after_tiles: u32) -> Result<JobStatus> {
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

/// Waits for `job` to end and downloads its image to `output`; an error names the job.
pub async fn wait_and_fetch(
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
async fn fetch_through(session: &mut Session, job: JobId, output: ImageOutput) -> Result<()> {
    let png = session.fetch(job).await?;
    let path = output.path().to_path_buf();
    output.write(&png).map_err(|e| {
        anyhow!(
            "job {job} is done, but {e:#}: `tessera fetch {job} -o {}` recovers it",
            path.display()
        )
    })
}

/// `error` with the job's id in front, unless it names the job already: whatever ends
/// the wait for a submitted job, the user learns its id.
pub fn naming_job(job: JobId, error: anyhow::Error) -> anyhow::Error {
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

#[cfg(test)]
mod tests {
    use super::*;

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
