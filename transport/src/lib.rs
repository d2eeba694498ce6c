//! The byte stream under the protocol: plain TCP, or TLS (rustls) when the farm has a
//! certificate. Above this module every peer sees the same framed stream either way,
//! and the handshake of clients and workers ([`dial`]) is written once.
//!
//! A coordinator's certificate comes from PEM files, or is made here once and kept in
//! its data directory ([`ServerTls::auto`]); peers trust it through a CA file, or by
//! pinning its SHA-256 fingerprint ([`ClientTls::pinned`]), which needs no file at all.
//!
//! The settings that say how to reach a coordinator are read here as well, so that the
//! daemons and the clients read them alike: its address ([`parse_address`]), which TLS
//! to serve or speak ([`ServerTls::from_settings`], [`ClientTls::from_settings`]) and the
//! token of a peer's role ([`load_secret`]).

use std::path::Path;
use std::pin::Pin;
use std::sync::{Arc, Mutex};
use std::task::{Context as TaskContext, Poll};
use std::time::Duration;

use anyhow::{anyhow, Context, Result};
use bytes::Bytes;
use futures_util::{SinkExt, StreamExt};
use protocol::{PeerHandshake, PeerStep, Role, DEFAULT_MAX_FRAME};
use rustls::client::danger::{HandshakeSignatureValid, ServerCertVerified, ServerCertVerifier};
use rustls::crypto::WebPkiSupportedAlgorithms;
use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, PrivateKeyDer, ServerName, UnixTime};
use rustls::{DigitallySignedStruct, SignatureScheme};
use sha2::{Digest, Sha256};
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::TcpStream;
use tokio_util::codec::{Framed, LengthDelimitedCodec};

mod address;
mod secret;

pub use address::{parse_address, AddressError, DEFAULT_ADDRESS, DEFAULT_PORT};
pub use secret::{exposed_token_file, load_secret, SecretError, TokenSource};

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
    /// SHA-256 of the leaf certificate's DER bytes: what peers pin.
    fingerprint: [u8; 32],
}

/// The SHA-256 fingerprint of a certificate: the hash of its DER bytes, which is what
/// `openssl x509 -noout -fingerprint -sha256` shows too (there with colons).
pub fn fingerprint(certificate: &[u8]) -> [u8; 32] {
    Sha256::digest(certificate).into()
}

/// A fingerprint as 64 lowercase hex digits, the form the coordinator prints and
/// `--tls-fingerprint` takes.
pub fn fingerprint_hex(fingerprint: &[u8; 32]) -> String {
    fingerprint.iter().map(|b| format!("{b:02x}")).collect()
}

/// Reads a fingerprint: 64 hex digits, in either case, optionally in pairs separated by
/// colons (as openssl prints them). The error says what is wrong.
pub fn parse_fingerprint(text: &str) -> Result<[u8; 32], String> {
    let digits: String = text.trim().chars().filter(|&c| c != ':').collect();
    if digits.len() != 64 || !digits.chars().all(|c| c.is_ascii_hexdigit()) {
        return Err(format!(
            "not a SHA-256 fingerprint: expected 64 hex digits (as the coordinator prints at \
             startup), got {:?}",
            text.trim()
        ));
    }
    let mut out = [0u8; 32];
    for (i, byte) in out.iter_mut().enumerate() {
        *byte = u8::from_str_radix(&digits[2 * i..2 * i + 2], 16).expect("checked hex digits");
    }
    Ok(out)
}

/// Reads a pin as a peer's settings give it: a fingerprint ([`parse_fingerprint`]), or
/// none when the value is empty, so that a container environment can set the variable
/// to nothing rather than leave it out.
pub fn parse_pin(text: &str) -> Result<Option<[u8; 32]>, String> {
    if text.trim().is_empty() {
        return Ok(None);
    }
    parse_fingerprint(text).map(Some)
}

/// Where [`ServerTls::auto`] keeps the certificate and its key, under the data
/// directory.
pub const AUTO_TLS_DIR: &str = "tls";

impl std::fmt::Debug for ServerTls {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("ServerTls")
    }
}

impl ServerTls {
    /// The TLS a coordinator's settings ask for: the PEM files `pem` (certificate chain,
    /// private key) if given, else with `auto` the certificate kept under the data
    /// directory `data` ([`ServerTls::auto`] in [`AUTO_TLS_DIR`]), else none: plain TCP.
    pub fn from_settings(
        pem: Option<(&Path, &Path)>,
        auto: bool,
        data: &Path,
    ) -> Result<Option<ServerTls>> {
        match pem {
            Some((cert, key)) => ServerTls::from_pem_files(cert, key).map(Some),
            None if auto => ServerTls::auto(&data.join(AUTO_TLS_DIR)).map(Some),
            None => Ok(None),
        }
    }

    /// Reads a PEM certificate chain (leaf first) and a PEM private key.
    pub fn from_pem_files(cert: &Path, key: &Path) -> Result<ServerTls> {
        let chain = read_certificates(cert)?;
        let chain_leaf = chain[0].clone();
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
            fingerprint: fingerprint(chain_leaf.as_ref()),
        })
    }

    /// The coordinator's own certificate, made on first use and kept in `dir`
    /// (`cert.pem` and `key.pem`, both mode 0600, in a directory of mode 0700), so that
    /// its fingerprint stays the same across restarts and peers pinned to it keep
    /// working. A farm needs no CA, no openssl and no file copied to the peers: they
    /// pin the fingerprint printed at startup.
    pub fn auto(dir: &Path) -> Result<ServerTls> {
        let cert = dir.join("cert.pem");
        let key = dir.join("key.pem");
        match (cert.exists(), key.exists()) {
            (true, true) => {}
            (true, false) => anyhow::bail!(
                "{} exists without its key {}: restore the key, or remove the certificate to \
                 make a new one (its fingerprint changes: pin the new one on every peer)",
                cert.display(),
                key.display()
            ),
            // Nothing yet, or a key whose certificate was never written (a start cut
            // short while making them): make both.
            _ => generate_certificate(dir, &cert, &key)?,
        }
        ServerTls::from_pem_files(&cert, &key)
    }

    /// The SHA-256 fingerprint of the certificate served: what peers pin with
    /// `--tls-fingerprint`.
    pub fn fingerprint(&self) -> [u8; 32] {
        self.fingerprint
    }

    /// Completes the server side of a TLS handshake.
    pub async fn accept(&self, tcp: TcpStream) -> std::io::Result<Stream> {
        Ok(Box::new(Closing(self.acceptor.accept(tcp).await?)))
    }
}

/// Makes a self-signed certificate (ECDSA P-256) and its key, and writes them to
/// `cert` and `key` in `dir` through temporary files renamed into place, key first:
/// a certificate on disk always has its key beside it.
fn generate_certificate(dir: &Path, cert: &Path, key: &Path) -> Result<()> {
    create_private_dir(dir)?;
    let mut names = vec!["localhost".to_string(), "127.0.0.1".into(), "::1".into()];
    if let Some(host) = std::fs::read_to_string("/etc/hostname")
        .ok()
        .map(|h| h.trim().to_string())
        .filter(|h| !h.is_empty() && h != "localhost")
    {
        names.push(host);
    }
    let key_pair = rcgen::KeyPair::generate().context("cannot make a TLS key")?;
    let mut params = rcgen::CertificateParams::new(names)
        .or_else(|_| rcgen::CertificateParams::new(vec!["localhost".to_string()]))
        .context("cannot make a TLS certificate")?;
    params.distinguished_name = rcgen::DistinguishedName::new();
    params
        .distinguished_name
        .push(rcgen::DnType::CommonName, "tessera coordinator");
    let certificate = params
        .self_signed(&key_pair)
        .context("cannot make a TLS certificate")?;
    write_private(key, key_pair.serialize_pem().as_bytes())?;
    write_private(cert, certificate.pem().as_bytes())?;
    Ok(())
}

fn create_private_dir(dir: &Path) -> Result<()> {
    let mut builder = std::fs::DirBuilder::new();
    builder.recursive(true);
    #[cfg(unix)]
    std::os::unix::fs::DirBuilderExt::mode(&mut builder, 0o700);
    builder
        .create(dir)
        .with_context(|| format!("cannot create {}", dir.display()))
}

/// Writes `bytes` to `path` with mode 0600 (readable by the coordinator's user only),
/// through a temporary file renamed into place.
fn write_private(path: &Path, bytes: &[u8]) -> Result<()> {
    use std::io::Write;
    let temporary = path.with_extension("pem.tmp");
    let mut options = std::fs::OpenOptions::new();
    options.write(true).create(true).truncate(true);
    #[cfg(unix)]
    std::os::unix::fs::OpenOptionsExt::mode(&mut options, 0o600);
    let write = || -> std::io::Result<()> {
        let mut file = options.open(&temporary)?;
        file.write_all(bytes)?;
        file.sync_all()?;
        std::fs::rename(&temporary, path)
    };
    write().with_context(|| format!("cannot write {}", path.display()))
}

/// Accepts exactly one end-entity certificate, named by its SHA-256 fingerprint, and
/// nothing else: no CA, no name, no validity period is consulted, since the pin says
/// everything there is to trust. The handshake's signatures are still checked with the
/// crypto provider, so only the holder of that certificate's private key gets through.
#[derive(Debug)]
struct PinnedCertificate {
    fingerprint: [u8; 32],
    algorithms: WebPkiSupportedAlgorithms,
}

/// A certificate that is not the pinned one, with both fingerprints.
#[derive(Debug)]
struct PinMismatch {
    pinned: [u8; 32],
    presented: [u8; 32],
}

impl std::fmt::Display for PinMismatch {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "the coordinator presented the certificate with SHA-256 fingerprint {}, but \
             --tls-fingerprint expects {}",
            fingerprint_hex(&self.presented),
            fingerprint_hex(&self.pinned)
        )
    }
}

impl std::error::Error for PinMismatch {}

impl ServerCertVerifier for PinnedCertificate {
    fn verify_server_cert(
        &self,
        end_entity: &CertificateDer<'_>,
        _intermediates: &[CertificateDer<'_>],
        _server_name: &ServerName<'_>,
        _ocsp_response: &[u8],
        _now: UnixTime,
    ) -> Result<ServerCertVerified, rustls::Error> {
        let presented = fingerprint(end_entity.as_ref());
        if presented == self.fingerprint {
            Ok(ServerCertVerified::assertion())
        } else {
            Err(rustls::Error::InvalidCertificate(
                rustls::CertificateError::Other(rustls::OtherError(Arc::new(PinMismatch {
                    pinned: self.fingerprint,
                    presented,
                }))),
            ))
        }
    }

    fn verify_tls12_signature(
        &self,
        message: &[u8],
        cert: &CertificateDer<'_>,
        dss: &DigitallySignedStruct,
    ) -> Result<HandshakeSignatureValid, rustls::Error> {
        rustls::crypto::verify_tls12_signature(message, cert, dss, &self.algorithms)
    }

    fn verify_tls13_signature(
        &self,
        message: &[u8],
        cert: &CertificateDer<'_>,
        dss: &DigitallySignedStruct,
    ) -> Result<HandshakeSignatureValid, rustls::Error> {
        rustls::crypto::verify_tls13_signature(message, cert, dss, &self.algorithms)
    }

    fn supported_verify_schemes(&self) -> Vec<SignatureScheme> {
        self.algorithms.supported_schemes()
    }
}

/// The pin mismatch inside a failed TLS handshake, if that is why it failed.
fn pin_mismatch(error: &std::io::Error) -> Option<&PinMismatch> {
    let rustls::Error::InvalidCertificate(rustls::CertificateError::Other(other)) =
        error.get_ref()?.downcast_ref::<rustls::Error>()?
    else {
        return None;
    };
    other.0.downcast_ref::<PinMismatch>()
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
    /// The TLS a peer's settings ask for: trust in the certificates of the CA file `ca`
    /// (checked against `server_name`, if given), else in the certificate pinned by its
    /// fingerprint `pin`, else none: plain TCP. A CA file wins over a pin.
    pub fn from_settings(
        ca: Option<&Path>,
        server_name: Option<&str>,
        pin: Option<[u8; 32]>,
    ) -> Result<Option<ClientTls>> {
        match (ca, pin) {
            (Some(ca), _) => ClientTls::from_ca_file(ca, server_name).map(Some),
            (None, Some(pin)) => ClientTls::pinned(pin).map(Some),
            (None, None) => Ok(None),
        }
    }

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

    /// Trusts exactly the certificate whose SHA-256 fingerprint is `fingerprint` (see
    /// [`parse_fingerprint`]), whatever names it carries and whoever signed it.
    pub fn pinned(fingerprint: [u8; 32]) -> Result<ClientTls> {
        let provider = crypto();
        let verifier = PinnedCertificate {
            fingerprint,
            algorithms: provider.signature_verification_algorithms,
        };
        let config = rustls::ClientConfig::builder_with_provider(provider)
            .with_safe_default_protocol_versions()
            .context("TLS setup")?
            .dangerous()
            .with_custom_certificate_verifier(Arc::new(verifier))
            .with_no_client_auth();
        Ok(ClientTls {
            connector: tokio_rustls::TlsConnector::from(Arc::new(config)),
            server_name: None,
        })
    }

    async fn connect(&self, address: &str, tcp: TcpStream) -> Result<Stream, DialError> {
        let name = match &self.server_name {
            Some(name) => name.clone(),
            None => host_name(address).map_err(DialError::Refused)?,
        };
        let first = Arc::new(Mutex::new(Vec::new()));
        let tcp = Recorded {
            io: tcp,
            first: Arc::clone(&first),
            full: false,
        };
        let connected = self.connector.connect(name, tcp).await;
        // What answered the hello, when it was not TLS: the likely mistake, by name.
        if connected.is_err() {
            let first = first.lock().unwrap_or_else(|e| e.into_inner());
            match answered(&first) {
                Answered::Http => return Err(DialError::Refused(http_port(address))),
                Answered::Plain => {
                    return Err(DialError::Refused(anyhow!(
                        "{address} does not speak TLS: is it the coordinator's HTTP port, or a \
                         coordinator started without TLS?"
                    )))
                }
                Answered::Nothing | Answered::Tls => {}
            }
        }
        match connected {
            Ok(stream) => Ok(Box::new(Closing(stream))),
            Err(e) if pin_mismatch(&e).is_some() => Err(DialError::Refused(anyhow!(
                "TLS with the coordinator at {address}: {}; refusing it (not the farm's \
                 coordinator, or its certificate was replaced)",
                pin_mismatch(&e).expect("checked")
            ))),
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

/// A TLS stream that ends as TLS should on both sides. Dropped, it sends `close_notify`
/// (one try that does not wait: a socket that cannot take it now is closed without);
/// and a peer that closed without one, between frames, is taken as gone, like a plain
/// TCP peer that closed, instead of an error every client command made the coordinator
/// log. The framing above still reports a frame cut short (bytes left at the end).
struct Closing<T: AsyncWrite + Unpin>(T);

/// Whether a read error is a peer closing the connection without `close_notify`.
fn unannounced_close(error: &std::io::Error) -> bool {
    error.kind() == std::io::ErrorKind::UnexpectedEof
}

impl<T: AsyncRead + AsyncWrite + Unpin> AsyncRead for Closing<T> {
    fn poll_read(
        self: Pin<&mut Self>,
        cx: &mut TaskContext<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<std::io::Result<()>> {
        match Pin::new(&mut self.get_mut().0).poll_read(cx, buf) {
            Poll::Ready(Err(e)) if unannounced_close(&e) => Poll::Ready(Ok(())),
            other => other,
        }
    }
}

impl<T: AsyncWrite + Unpin> AsyncWrite for Closing<T> {
    fn poll_write(
        self: Pin<&mut Self>,
        cx: &mut TaskContext<'_>,
        buf: &[u8],
    ) -> Poll<std::io::Result<usize>> {
        Pin::new(&mut self.get_mut().0).poll_write(cx, buf)
    }

    fn poll_write_vectored(
        self: Pin<&mut Self>,
        cx: &mut TaskContext<'_>,
        bufs: &[std::io::IoSlice<'_>],
    ) -> Poll<std::io::Result<usize>> {
        Pin::new(&mut self.get_mut().0).poll_write_vectored(cx, bufs)
    }

    fn is_write_vectored(&self) -> bool {
        self.0.is_write_vectored()
    }

    fn poll_flush(self: Pin<&mut Self>, cx: &mut TaskContext<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.get_mut().0).poll_flush(cx)
    }

    fn poll_shutdown(self: Pin<&mut Self>, cx: &mut TaskContext<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.get_mut().0).poll_shutdown(cx)
    }
}

impl<T: AsyncWrite + Unpin> Drop for Closing<T> {
    fn drop(&mut self) {
        // A stream already shut down sends nothing more.
        let mut cx = TaskContext::from_waker(std::task::Waker::noop());
        let _ = Pin::new(&mut self.0).poll_shutdown(&mut cx);
    }
}

/// How many of the first bytes read back are kept to tell what answered a TLS hello.
const FIRST_BYTES: usize = 8;

/// A connection that keeps the first bytes it reads ([`FIRST_BYTES`]) where the
/// dialler can read them after a failed TLS handshake, which consumed them.
struct Recorded<T> {
    io: T,
    first: Arc<Mutex<Vec<u8>>>,
    /// All the bytes wanted are kept: reads go straight through.
    full: bool,
}

impl<T: AsyncRead + Unpin> AsyncRead for Recorded<T> {
    fn poll_read(
        self: Pin<&mut Self>,
        cx: &mut TaskContext<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<std::io::Result<()>> {
        let this = self.get_mut();
        let before = buf.filled().len();
        let poll = Pin::new(&mut this.io).poll_read(cx, buf);
        if !this.full && matches!(poll, Poll::Ready(Ok(()))) {
            let mut first = this.first.lock().unwrap_or_else(|e| e.into_inner());
            let room = FIRST_BYTES.saturating_sub(first.len());
            first.extend(buf.filled()[before..].iter().take(room));
            this.full = first.len() >= FIRST_BYTES;
        }
        poll
    }
}

impl<T: AsyncWrite + Unpin> AsyncWrite for Recorded<T> {
    fn poll_write(
        self: Pin<&mut Self>,
        cx: &mut TaskContext<'_>,
        buf: &[u8],
    ) -> Poll<std::io::Result<usize>> {
        Pin::new(&mut self.get_mut().io).poll_write(cx, buf)
    }

    fn poll_write_vectored(
        self: Pin<&mut Self>,
        cx: &mut TaskContext<'_>,
        bufs: &[std::io::IoSlice<'_>],
    ) -> Poll<std::io::Result<usize>> {
        Pin::new(&mut self.get_mut().io).poll_write_vectored(cx, bufs)
    }

    fn is_write_vectored(&self) -> bool {
        self.io.is_write_vectored()
    }

    fn poll_flush(self: Pin<&mut Self>, cx: &mut TaskContext<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.get_mut().io).poll_flush(cx)
    }

    fn poll_shutdown(self: Pin<&mut Self>, cx: &mut TaskContext<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.get_mut().io).poll_shutdown(cx)
    }
}

/// What a peer answered, told by the first bytes read from it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Answered {
    /// Nothing yet (it closed, or said nothing).
    Nothing,
    /// A TLS record: a content type TLS knows (20 to 24), then version 3.
    Tls,
    /// An HTTP status line: an HTTP server, such as the coordinator's HTTP port (in
    /// clear, or behind the TLS it serves with the coordinator's certificate, which
    /// then answers the protocol's first frame with an HTTP error).
    Http,
    /// Anything else in clear: to a TLS hello, a coordinator without TLS answers with a
    /// protocol frame (its refusal of a frame that long).
    Plain,
}

/// What answered, from the first bytes read (as many as came, at least one for a
/// verdict): what names the likely mistake when a TLS handshake or the protocol's
/// handshake fails on them.
pub fn answered(first: &[u8]) -> Answered {
    match first {
        [] => Answered::Nothing,
        [b'H', b'T', b'T', b'P', ..] => Answered::Http,
        [0x14..=0x18] | [0x14..=0x18, 0x03, ..] => Answered::Tls,
        _ => Answered::Plain,
    }
}

/// The error for a peer that found the coordinator's HTTP port where it expected the
/// protocol's.
fn http_port(address: &str) -> anyhow::Error {
    anyhow!(
        "{address} answered in HTTP: this looks like the coordinator's HTTP port (--http); \
         give the port it listens on for workers and clients (--listen, 7878 by default)"
    )
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

/// How to reach a coordinator: its address, whether to speak TLS to it, and where the
/// secret of this peer's role (a worker's or a client's token) comes from: the
/// coordinator must prove it knows it before the peer proves it in turn.
#[derive(Clone, Debug)]
pub struct Endpoint {
    pub address: String,
    pub tls: Option<ClientTls>,
    /// Read at every [`dial`], so that a rotated token file is picked up.
    pub secret: TokenSource,
}

impl Endpoint {
    /// Plain TCP, no secret: a local farm.
    pub fn plain(address: impl Into<String>) -> Endpoint {
        Endpoint {
            address: address.into(),
            tls: None,
            secret: TokenSource::None,
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

/// No connection to the coordinator's address at all (refused, no route, no such
/// host): a type of its own, so that a command can add how its address is chosen.
#[derive(Debug, thiserror::Error)]
#[error("cannot reach the coordinator at {address}")]
pub struct CannotReach {
    pub address: String,
    #[source]
    pub source: std::io::Error,
}

/// A handshaken connection, ready for the role's message codec.
pub type Handshaken = Framed<Stream, LengthDelimitedCodec>;

/// How long connecting, TLS and the handshake may take together before the
/// coordinator counts as unreachable.
pub const DIAL_TIMEOUT: Duration = Duration::from_secs(10);

/// Reads the endpoint's token as its source holds it now, then [`dial_with`] it. A
/// token that cannot be read (a file being rewritten, say) counts as a coordinator
/// not reachable now: trying again later may help.
pub async fn dial(endpoint: &Endpoint, role: Role) -> Result<Handshaken, DialError> {
    let secret = endpoint
        .secret
        .load()
        .map_err(|e| DialError::Unreachable(e.into()))?;
    dial_with(endpoint, role, secret).await
}

/// Connects, sets up TLS if configured, says hello as `role` with a fresh nonce and the
/// key id of `secret`, checks the coordinator's proof of the secret (a peer with a
/// secret refuses a coordinator that does not prove it) and answers its challenge until
/// it accepts or refuses, all within [`DIAL_TIMEOUT`].
pub async fn dial_with(
    endpoint: &Endpoint,
    role: Role,
    secret: Option<Vec<u8>>,
) -> Result<Handshaken, DialError> {
    tokio::time::timeout(DIAL_TIMEOUT, dial_now(endpoint, role, secret))
        .await
        .unwrap_or_else(|_| {
            Err(DialError::Unreachable(anyhow!(
                "no answer from the coordinator at {} within {} s",
                endpoint.address,
                DIAL_TIMEOUT.as_secs()
            )))
        })
}

async fn dial_now(
    endpoint: &Endpoint,
    role: Role,
    secret: Option<Vec<u8>>,
) -> Result<Handshaken, DialError> {
    let address = &endpoint.address;
    let unreachable = |e: anyhow::Error| DialError::Unreachable(e);
    let talk = |e: std::io::Error| {
        DialError::Unreachable(
            anyhow::Error::from(e).context(format!("cannot talk to the coordinator at {address}")),
        )
    };
    let tcp = TcpStream::connect(address).await.map_err(|source| {
        unreachable(anyhow::Error::new(CannotReach {
            address: address.clone(),
            source,
        }))
    })?;
    tcp.set_nodelay(true).map_err(talk)?;
    let stream: Stream = match &endpoint.tls {
        Some(tls) => tls.connect(address, tcp).await?,
        None => Box::new(tcp),
    };
    let mut raw = Framed::new(stream, protocol::frame_codec(DEFAULT_MAX_FRAME));
    let mut nonce = [0u8; 32];
    getrandom::fill(&mut nonce)
        .map_err(|e| DialError::Unreachable(anyhow!("no randomness for a nonce: {e}")))?;
    let mut handshake = PeerHandshake::new(role, secret, nonce);
    raw.send(Bytes::from(handshake.hello()))
        .await
        .map_err(talk)?;
    loop {
        let reply = raw.next().await;
        // An HTTP server answers the hello with a status line, whose first bytes read as
        // an absurd frame length: the coordinator's HTTP port, most likely, in clear or
        // over the TLS it serves when the coordinator has TLS (these are the bytes after
        // TLS, then).
        if answered(raw.read_buffer()) == Answered::Http {
            return Err(DialError::Refused(http_port(address)));
        }
        let reply = reply
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

#[cfg(test)]
mod tests;
