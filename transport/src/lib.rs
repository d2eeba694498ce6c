//! The byte stream under the protocol: plain TCP, or TLS (rustls) when the farm has a
//! certificate. Above this module every peer sees the same framed stream either way,
//! and the handshake of clients and workers ([`dial`]) is written once.

use std::path::Path;
use std::sync::Arc;
use std::time::Duration;

use anyhow::{anyhow, Context, Result};
use bytes::Bytes;
use futures_util::{SinkExt, StreamExt};
use protocol::{Hello, PeerHandshake, PeerStep, Role, DEFAULT_MAX_FRAME};
use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, PrivateKeyDer, ServerName};
use tokio::io::{AsyncRead, AsyncWrite};
use tokio::net::TcpStream;
use tokio_util::codec::{Framed, LengthDelimitedCodec};

/// Anything the protocol can run over.
pub trait Io: AsyncRead + AsyncWrite + Unpin + Send {}
impl<T: AsyncRead + AsyncWrite + Unpin + Send> Io for T {}

/// A connection, plain or encrypted.
pub type Stream = Box<dyn Io>;

/// The first byte of every TLS connection (a handshake record).
pub const TLS_HANDSHAKE_RECORD: u8 = 0x16;

fn crypto() -> Arc<rustls::crypto::CryptoProvider> {
    Arc::new(rustls::crypto::ring::default_provider())
}

/// The coordinator's side of TLS: its certificate chain and private key.
#[derive(Clone)]
pub struct ServerTls {
    acceptor: tokio_rustls::TlsAcceptor,
}

impl std::fmt::Debug for ServerTls {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("ServerTls")
    }
}

impl ServerTls {
    /// Reads a PEM certificate chain (leaf first) and a PEM private key.
    pub fn from_pem_files(cert: &Path, key: &Path) -> Result<ServerTls> {
        let chain = read_certificates(cert)?;
        let key = PrivateKeyDer::from_pem_file(key)
            .map_err(|e| anyhow!("cannot read a private key from {}: {e}", key.display()))?;
        let config = rustls::ServerConfig::builder_with_provider(crypto())
            .with_safe_default_protocol_versions()
            .context("TLS setup")?
            .with_no_client_auth()
            .with_single_cert(chain, key)
            .with_context(|| {
                format!(
                    "the key in the TLS key file does not suit the certificate in {}",
                    cert.display()
                )
            })?;
        Ok(ServerTls {
            acceptor: tokio_rustls::TlsAcceptor::from(Arc::new(config)),
        })
    }

    /// Completes the server side of a TLS handshake.
    pub async fn accept(&self, tcp: TcpStream) -> std::io::Result<Stream> {
        Ok(Box::new(self.acceptor.accept(tcp).await?))
    }
}

/// A client's or worker's side of TLS: which certificates it trusts, and the name the
/// coordinator's certificate must carry.
#[derive(Clone)]
pub struct ClientTls {
    connector: tokio_rustls::TlsConnector,
    server_name: Option<ServerName<'static>>,
}

impl std::fmt::Debug for ClientTls {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ClientTls")
            .field("server_name", &self.server_name)
            .finish_non_exhaustive()
    }
}

impl ClientTls {
    /// Trusts the certificates of the PEM file `ca` (a CA, or the coordinator's own
    /// self-signed certificate). `server_name` overrides the name checked against the
    /// coordinator's certificate, which is otherwise the host of the address dialled.
    pub fn from_ca_file(ca: &Path, server_name: Option<&str>) -> Result<ClientTls> {
        let mut roots = rustls::RootCertStore::empty();
        for certificate in read_certificates(ca)? {
            roots
                .add(certificate)
                .with_context(|| format!("unusable certificate in {}", ca.display()))?;
        }
        let config = rustls::ClientConfig::builder_with_provider(crypto())
            .with_safe_default_protocol_versions()
            .context("TLS setup")?
            .with_root_certificates(roots)
            .with_no_client_auth();
        let server_name = server_name
            .map(|name| {
                ServerName::try_from(name.to_string())
                    .map_err(|_| anyhow!("{name:?} is not a valid TLS server name"))
            })
            .transpose()?;
        Ok(ClientTls {
            connector: tokio_rustls::TlsConnector::from(Arc::new(config)),
            server_name,
        })
    }

    async fn connect(&self, address: &str, tcp: TcpStream) -> Result<Stream, DialError> {
        let name = match &self.server_name {
            Some(name) => name.clone(),
            None => host_name(address).map_err(DialError::Refused)?,
        };
        match self.connector.connect(name, tcp).await {
            Ok(stream) => Ok(Box::new(stream)),
            // rustls reports certificate and protocol errors as invalid data: retrying
            // cannot help.
            Err(e) if e.kind() == std::io::ErrorKind::InvalidData => Err(DialError::Refused(
                anyhow!("TLS handshake with the coordinator at {address} failed: {e}"),
            )),
            Err(e) => Err(DialError::Unreachable(anyhow!(
                "TLS handshake with the coordinator at {address} failed: {e} (does the \
                 coordinator use TLS?)"
            ))),
        }
    }
}

/// The host part of `host:port` (IPv6 addresses in brackets), as a TLS server name.
fn host_name(address: &str) -> Result<ServerName<'static>> {
    let host = address
        .rsplit_once(':')
        .map_or(address, |(host, _port)| host)
        .trim_start_matches('[')
        .trim_end_matches(']');
    ServerName::try_from(host.to_string())
        .map_err(|_| anyhow!("{host:?} is not a name a TLS certificate can carry"))
}

fn read_certificates(path: &Path) -> Result<Vec<CertificateDer<'static>>> {
    let chain = CertificateDer::pem_file_iter(path)
        .and_then(|certificates| certificates.collect::<Result<Vec<_>, _>>())
        .map_err(|e| anyhow!("cannot read certificates from {}: {e}", path.display()))?;
    anyhow::ensure!(!chain.is_empty(), "no certificate in {}", path.display());
    Ok(chain)
}

/// How to reach a coordinator: its address, whether to speak TLS to it, and the secret
/// to prove if it asks for one.
#[derive(Clone, Debug)]
pub struct Endpoint {
    pub address: String,
    pub tls: Option<ClientTls>,
    pub secret: Option<Vec<u8>>,
}

impl Endpoint {
    /// Plain TCP, no secret: a local farm.
    pub fn plain(address: impl Into<String>) -> Endpoint {
        Endpoint {
            address: address.into(),
            tls: None,
            secret: None,
        }
    }
}

/// Why a connection could not be set up.
#[derive(Debug)]
pub enum DialError {
    /// Not reachable now (refused, reset, closed): worth trying again later.
    Unreachable(anyhow::Error),
    /// Reached, but it will not work as configured (wrong token, version, certificate):
    /// trying again cannot help.
    Refused(anyhow::Error),
}

impl DialError {
    pub fn into_inner(self) -> anyhow::Error {
        match self {
            DialError::Unreachable(e) | DialError::Refused(e) => e,
        }
    }
}

/// A handshaken connection, ready for the role's message codec.
pub type Handshaken = Framed<Stream, LengthDelimitedCodec>;

/// How long connecting, TLS and the handshake may take together before the
/// coordinator counts as unreachable.
pub const DIAL_TIMEOUT: Duration = Duration::from_secs(10);

/// Connects, sets up TLS if configured, says hello as `role` and answers the
/// coordinator's challenge until it accepts or refuses, all within [`DIAL_TIMEOUT`].
pub async fn dial(endpoint: &Endpoint, role: Role) -> Result<Handshaken, DialError> {
    tokio::time::timeout(DIAL_TIMEOUT, dial_now(endpoint, role))
        .await
        .unwrap_or_else(|_| {
            Err(DialError::Unreachable(anyhow!(
                "no answer from the coordinator at {} within {} s",
                endpoint.address,
                DIAL_TIMEOUT.as_secs()
            )))
        })
}

async fn dial_now(endpoint: &Endpoint, role: Role) -> Result<Handshaken, DialError> {
    let address = &endpoint.address;
    let unreachable = |e: anyhow::Error| DialError::Unreachable(e);
    let talk = |e: std::io::Error| {
        DialError::Unreachable(
            anyhow::Error::from(e).context(format!("cannot talk to the coordinator at {address}")),
        )
    };
    let tcp = TcpStream::connect(address)
        .await
        .with_context(|| format!("cannot reach the coordinator at {address}"))
        .map_err(unreachable)?;
    tcp.set_nodelay(true).map_err(talk)?;
    let stream: Stream = match &endpoint.tls {
        Some(tls) => tls.connect(address, tcp).await?,
        None => Box::new(tcp),
    };
    let mut raw = Framed::new(stream, protocol::frame_codec(DEFAULT_MAX_FRAME));
    raw.send(Bytes::from(Hello::new(role).to_frame()))
        .await
        .map_err(talk)?;
    let mut handshake = PeerHandshake::new(endpoint.secret.clone());
    loop {
        let reply = raw
            .next()
            .await
            .ok_or_else(|| {
                unreachable(anyhow!(
                    "the coordinator at {address} closed the connection{}",
                    if endpoint.tls.is_none() {
                        " (does it require TLS?)"
                    } else {
                        ""
                    }
                ))
            })?
            .map_err(talk)?;
        match handshake.on_frame(&reply) {
            Ok(PeerStep::Accepted) => return Ok(raw),
            Ok(PeerStep::Send(proof)) => raw.send(Bytes::from(proof)).await.map_err(talk)?,
            Err(e) => {
                return Err(DialError::Refused(anyhow!(
                    "the coordinator at {address}: {e}"
                )))
            }
        }
    }
}
