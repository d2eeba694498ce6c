//! The client side of the protocol: what `tessera submit`, `status`, `list`, `cancel`,
//! `fetch` and `workers` (and `tessera up`) use to talk to a coordinator.

use anyhow::{anyhow, bail, Context, Result};
use futures_util::{SinkExt, StreamExt};
use protocol::{
    ClientRequest, ClientResponse, JobId, JobSpec, JobStatus, MessageCodec, Role, WorkerStatus,
    DEFAULT_MAX_FRAME,
};
use tokio_util::codec::Framed;

use transport::{self, Endpoint, Stream};

/// An open, handshaken connection to a coordinator.
pub struct Client {
    conn: Framed<Stream, MessageCodec<ClientResponse, ClientRequest>>,
    address: String,
}

impl Client {
    /// Connects and handshakes (over TLS if the endpoint says so), proving the
    /// endpoint's secret if the coordinator asks for it. Errors name the address tried.
    pub async fn connect(endpoint: &Endpoint) -> Result<Client> {
        let raw = transport::dial(endpoint, Role::Client)
            .await
            .map_err(transport::DialError::into_inner)?;
        Ok(Client {
            conn: raw.map_codec(|_| MessageCodec::new(DEFAULT_MAX_FRAME)),
            address: endpoint.address.clone(),
        })
    }

    /// Sends one request and reads its response; a refusal becomes an error carrying
    /// the coordinator's message.
    pub async fn request(&mut self, request: ClientRequest) -> Result<ClientResponse> {
        self.conn
            .send(request)
            .await
            .with_context(|| format!("lost the coordinator at {}", self.address))?;
        match self.conn.next().await {
            Some(Ok(ClientResponse::Error { message })) => Err(anyhow!(message)),
            Some(Ok(response)) => Ok(response),
            Some(Err(e)) => {
                Err(anyhow!(e)).with_context(|| format!("lost the coordinator at {}", self.address))
            }
            None => bail!("the coordinator at {} closed the connection", self.address),
        }
    }

    pub async fn submit(&mut self, spec: JobSpec) -> Result<JobId> {
        match self.request(ClientRequest::Submit(spec)).await? {
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

    pub async fn workers(&mut self) -> Result<Vec<WorkerStatus>> {
        match self.request(ClientRequest::Workers).await? {
            ClientResponse::Workers(workers) => Ok(workers),
            other => Err(unexpected(&other)),
        }
    }

    /// The finished job's PNG, fetched in chunks.
    pub async fn fetch(&mut self, job: JobId) -> Result<Vec<u8>> {
        let mut png = Vec::new();
        loop {
            let offset = png.len() as u64;
            match self.request(ClientRequest::Fetch { job, offset }).await? {
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
