//! The client side of the protocol: what `tessera submit`, `status`, `list`, `cancel`,
//! `delete`, `fetch` and `workers` (and `tessera up`) use to talk to a coordinator.

use std::time::Duration;

use anyhow::{anyhow, bail, Result};
use futures_util::{SinkExt, StreamExt};
use protocol::{
    ClientRequest, ClientResponse, FrameError, JobEvent, JobId, JobSpec, JobStatus, MessageCodec,
    Role, WorkerStatus, DEFAULT_MAX_FRAME,
};
use tokio_util::codec::Framed;

use transport::{self, DialError, Endpoint, Stream};

mod uploads;

pub use uploads::{LocalFile, UploadProgress};

/// The connection to the coordinator broke (closed, reset, or silent for longer than
/// the answer timeout): the request may be tried again on a new connection. Requests
/// return it inside their `anyhow::Error`; find it with [`ConnectionLost::of`].
#[derive(Debug, thiserror::Error)]
#[error("lost the coordinator at {address}: {reason}")]
pub struct ConnectionLost {
    pub address: String,
    /// What happened, without the address: "connection closed", "no answer for 15 s", ...
    pub reason: String,
}

impl ConnectionLost {
    /// The lost connection behind `error`, if that is what it is.
    pub fn of(error: &anyhow::Error) -> Option<&ConnectionLost> {
        error.downcast_ref()
    }
}

/// An open, handshaken connection to a coordinator.
pub struct Client {
    conn: Framed<Stream, MessageCodec<ClientResponse, ClientRequest>>,
    address: String,
    /// A request whose answer takes longer than this counts as a lost connection.
    answer_timeout: Option<Duration>,
    /// Told how a submission's upload goes ([`Client::on_upload`]).
    upload_progress: Option<Box<dyn FnMut(uploads::UploadProgress) + Send>>,
}

impl Client {
    /// Connects and handshakes (over TLS if the endpoint says so), proving the
    /// endpoint's secret if the coordinator asks for it. Errors name the address tried.
    pub async fn connect(endpoint: &Endpoint) -> Result<Client> {
        Client::dial(endpoint).await.map_err(DialError::into_inner)
    }

    /// [`Client::connect`], telling a coordinator that cannot be reached now (worth
    /// trying again) from one that refuses this client as configured.
    pub async fn dial(endpoint: &Endpoint) -> Result<Client, DialError> {
        let raw = transport::dial(endpoint, Role::Client).await?;
        Ok(Client {
            conn: raw.map_codec(|_| MessageCodec::new(DEFAULT_MAX_FRAME)),
            address: endpoint.address.clone(),
            answer_timeout: None,
            upload_progress: None,
        })
    }

    /// From now on, a request not answered within `timeout` fails with
    /// [`ConnectionLost`] (by default a request waits as long as the connection lasts).
    pub fn set_answer_timeout(&mut self, timeout: Duration) {
        self.answer_timeout = Some(timeout);
    }

    /// Sends one request and reads its response; a refusal becomes an error carrying
    /// the coordinator's message, a broken connection a [`ConnectionLost`].
    pub async fn request(&mut self, request: ClientRequest) -> Result<ClientResponse> {
        let exchange = async {
            self.conn.send(request).await?;
            self.conn.next().await.transpose()
        };
        let answer = match self.answer_timeout {
            Some(limit) => match tokio::time::timeout(limit, exchange).await {
                Ok(answer) => answer,
                Err(_) => return Err(self.lost(format!("no answer for {} s", limit.as_secs_f64()))),
            },
            None => exchange.await,
        };
        match answer {
            // The refusal itself is the error, so that a caller can act on its kind.
            Ok(Some(ClientResponse::Error(refusal))) => Err(anyhow::Error::new(refusal)),
            Ok(Some(response)) => Ok(response),
            Ok(None) => Err(self.lost("connection closed".into())),
            Err(FrameError::Io(e)) => Err(self.lost(e.to_string())),
            Err(e) => Err(anyhow!(e).context(format!(
                "cannot understand the coordinator at {}",
                self.address
            ))),
        }
    }

    fn lost(&self, reason: String) -> anyhow::Error {
        ConnectionLost {
            address: self.address.clone(),
            reason,
        }
        .into()
    }

    pub async fn submit(&mut self, spec: JobSpec) -> Result<JobId> {
        match self.request(ClientRequest::Submit(spec)).await? {
            ClientResponse::Submitted { job } => Ok(job),
            other => Err(unexpected(&other)),
        }
    }

    /// A new job refining a finished adaptive one: its id.
    pub async fn refine(
        &mut self,
        job: JobId,
        target_milli: u32,
        aa: Option<u32>,
        time_limit_ms: Option<u64>,
    ) -> Result<JobId> {
        let request = ClientRequest::Refine {
            job,
            target_milli,
            aa,
            time_limit_ms,
        };
        match self.request(request).await? {
            ClientResponse::Submitted { job } => Ok(job),
            other => Err(unexpected(&other)),
        }
    }

    pub async fn status(&mut self, job: JobId) -> Result<JobStatus> {
        match self.request(ClientRequest::Status { job }).await? {
            ClientResponse::Job(status) => Ok(status),
            other => Err(unexpected(&other)),
        }
    }

    /// The job's status once it has progressed past `after_tiles` or ended (see
    /// [`ClientRequest::Watch`]).
    pub async fn watch(&mut self, job: JobId, after_tiles: u32) -> Result<JobStatus> {
        match self
            .request(ClientRequest::Watch { job, after_tiles })
            .await?
        {
            ClientResponse::Job(status) => Ok(status),
            other => Err(unexpected(&other)),
        }
    }

    pub async fn list(&mut self) -> Result<Vec<JobStatus>> {
        match self.request(ClientRequest::List).await? {
            ClientResponse::Jobs(jobs) => Ok(jobs),
            other => Err(unexpected(&other)),
        }
    }

    pub async fn cancel(&mut self, job: JobId) -> Result<()> {
        match self.request(ClientRequest::Cancel { job }).await? {
            ClientResponse::Cancelled { .. } => Ok(()),
            other => Err(unexpected(&other)),
        }
    }

    /// Pauses a queued or running job (see [`ClientRequest::Pause`]): its status once
    /// the pause is stored.
    pub async fn pause(&mut self, job: JobId) -> Result<JobStatus> {
        match self.request(ClientRequest::Pause { job }).await? {
            ClientResponse::Job(status) if status.id == job => Ok(status),
            other => Err(unexpected(&other)),
        }
    }

    /// Makes a paused job schedulable again: its status once stored.
    pub async fn resume(&mut self, job: JobId) -> Result<JobStatus> {
        match self.request(ClientRequest::Resume { job }).await? {
            ClientResponse::Job(status) if status.id == job => Ok(status),
            other => Err(unexpected(&other)),
        }
    }

    /// Gives a queued or running job a new priority: its status once stored.
    pub async fn set_priority(&mut self, job: JobId, priority: i32) -> Result<JobStatus> {
        match self
            .request(ClientRequest::SetPriority { job, priority })
            .await?
        {
            ClientResponse::Job(status) if status.id == job => Ok(status),
            other => Err(unexpected(&other)),
        }
    }

    /// A page of the job's event log after entry `after` (see
    /// [`ClientRequest::Events`]).
    pub async fn events(&mut self, job: JobId, after: u64) -> Result<Vec<JobEvent>> {
        match self.request(ClientRequest::Events { job, after }).await? {
            ClientResponse::Events { job: j, events } if j == job => Ok(events),
            other => Err(unexpected(&other)),
        }
    }

    /// Puts a failed or cancelled job back in the queue: its status once stored.
    pub async fn retry(&mut self, job: JobId) -> Result<JobStatus> {
        match self.request(ClientRequest::Retry { job }).await? {
            ClientResponse::Job(status) if status.id == job => Ok(status),
            other => Err(unexpected(&other)),
        }
    }

    /// Has tiles of a queued or running job rendered again: its status once stored.
    pub async fn requeue(&mut self, job: JobId, tiles: Vec<u32>) -> Result<JobStatus> {
        match self.request(ClientRequest::Requeue { job, tiles }).await? {
            ClientResponse::Job(status) if status.id == job => Ok(status),
            other => Err(unexpected(&other)),
        }
    }

    /// Removes an ended job from the coordinator (see [`ClientRequest::Delete`]).
    pub async fn delete(&mut self, job: JobId) -> Result<()> {
        match self.request(ClientRequest::Delete { job }).await? {
            ClientResponse::Deleted { job: deleted } if deleted == job => Ok(()),
            other => Err(unexpected(&other)),
        }
    }

    /// Drains, disables or enables a worker (see [`ClientRequest::DrainWorker`]): the
    /// worker acted on (none for a machine enabled while not connected), once the
    /// change is made (and, for a disable or enable, stored).
    pub async fn control_worker(&mut self, request: ClientRequest) -> Result<Vec<WorkerStatus>> {
        match self.request(request).await? {
            ClientResponse::Workers(workers) => Ok(workers),
            other => Err(unexpected(&other)),
        }
    }

    pub async fn workers(&mut self) -> Result<Vec<WorkerStatus>> {
        match self.request(ClientRequest::Workers).await? {
            ClientResponse::Workers(workers) => Ok(workers),
            other => Err(unexpected(&other)),
        }
    }

    /// Renders a done, failed or cancelled frame of a sequence again, alone: the
    /// sequence's status once it is queued.
    pub async fn requeue_frame(&mut self, job: JobId, frame: u32) -> Result<JobStatus> {
        match self
            .request(ClientRequest::RequeueFrame { job, frame })
            .await?
        {
            ClientResponse::Job(status) if status.id == job => Ok(status),
            other => Err(unexpected(&other)),
        }
    }

    /// The finished job's PNG, fetched in chunks.
    pub async fn fetch(&mut self, job: JobId) -> Result<Vec<u8>> {
        self.fetch_chunks(|offset| ClientRequest::Fetch { job, offset })
            .await
    }

    /// A done frame's PNG of a sequence job, fetched in chunks.
    pub async fn fetch_frame(&mut self, job: JobId, frame: u32) -> Result<Vec<u8>> {
        self.fetch_chunks(|offset| ClientRequest::FetchFrame { job, frame, offset })
            .await
    }

    async fn fetch_chunks(&mut self, ask: impl Fn(u64) -> ClientRequest) -> Result<Vec<u8>> {
        let mut png = Vec::new();
        loop {
            let offset = png.len() as u64;
            match self.request(ask(offset)).await? {
                ClientResponse::ImageChunk {
                    total,
                    offset: at,
                    bytes,
                    ..
                } if at == offset => {
                    png.extend_from_slice(&bytes);
                    if png.len() as u64 >= total {
                        return Ok(png);
                    }
                    if bytes.is_empty() {
                        bail!("the coordinator sent an empty chunk at {offset} of {total}");
                    }
                }
                other => return Err(unexpected(&other)),
            }
        }
    }
}

fn unexpected(response: &ClientResponse) -> anyhow::Error {
    anyhow!("unexpected answer from the coordinator: {response:?}")
}

/// A job's event as JSON, one shape wherever it is shown (`tessera events --json` and
/// the status page's `/api/jobs/ID/events`).
pub fn event_json(e: &protocol::JobEvent) -> serde_json::Value {
    serde_json::json!({ "seq": e.seq, "unix_ms": e.unix_ms, "event": e.kind, "detail": e.detail })
}
