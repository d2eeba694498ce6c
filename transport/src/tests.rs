//! Fingerprints and pins, the TLS a coordinator serves and a peer speaks as their settings
//! choose, and the stream under the protocol: told apart by its first bytes, closed with
//! or without TLS's close_notify, and a pinned certificate accepted or refused.

use super::*;

#[test]
fn fingerprints_read_in_hex_with_or_without_colons() {
    let bytes: [u8; 32] = std::array::from_fn(|i| (i * 7) as u8);
    let hex = fingerprint_hex(&bytes);
    assert_eq!(hex.len(), 64);
    assert_eq!(parse_fingerprint(&hex), Ok(bytes));
    assert_eq!(parse_fingerprint(&hex.to_uppercase()), Ok(bytes));
    let colons = hex
        .as_bytes()
        .chunks(2)
        .map(|c| std::str::from_utf8(c).unwrap())
        .collect::<Vec<_>>()
        .join(":");
    assert_eq!(parse_fingerprint(&format!(" {colons}\n")), Ok(bytes));
    assert!(parse_fingerprint(&hex[..62]).is_err());
    assert!(parse_fingerprint(&format!("{}zz", &hex[..62]))
        .unwrap_err()
        .contains("64 hex digits"));
}

#[test]
fn an_empty_pin_is_none() {
    let hex = "ab".repeat(32);
    assert_eq!(parse_pin(&hex), Ok(Some([0xab; 32])));
    assert_eq!(parse_pin(""), Ok(None));
    assert_eq!(parse_pin("  "), Ok(None));
    assert!(parse_pin("abc").unwrap_err().contains("64 hex digits"));
}

#[test]
fn a_coordinator_serves_the_tls_its_settings_choose() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    assert!(ServerTls::from_settings(None, false, &data)
        .unwrap()
        .is_none());
    assert!(!data.exists(), "plain TCP makes no certificate");
    let auto = ServerTls::from_settings(None, true, &data)
        .unwrap()
        .expect("--tls-auto serves TLS");
    let kept = data.join(AUTO_TLS_DIR);
    assert_eq!(
        ServerTls::auto(&kept).unwrap().fingerprint(),
        auto.fingerprint()
    );
    // Files given win over the automatic certificate.
    let other = dir.path().join("other");
    let files = ServerTls::auto(&other).unwrap();
    let (cert, key) = (other.join("cert.pem"), other.join("key.pem"));
    let chosen = ServerTls::from_settings(Some((&cert, &key)), true, &data)
        .unwrap()
        .expect("files serve TLS");
    assert_eq!(chosen.fingerprint(), files.fingerprint());
    assert_ne!(chosen.fingerprint(), auto.fingerprint());
}

#[test]
fn a_peer_speaks_the_tls_its_settings_choose() {
    let dir = tempfile::tempdir().unwrap();
    assert!(ClientTls::from_settings(None, None, None)
        .unwrap()
        .is_none());
    let pinned = ClientTls::from_settings(None, None, Some([7; 32]))
        .unwrap()
        .expect("a pin speaks TLS");
    assert!(pinned.server_name.is_none());
    ServerTls::auto(dir.path()).unwrap();
    let ca = dir.path().join("cert.pem");
    let trusted = ClientTls::from_settings(Some(&ca), Some("farm.example"), Some([7; 32]))
        .unwrap()
        .expect("a CA file speaks TLS");
    assert_eq!(
        trusted.server_name,
        Some(ServerName::try_from("farm.example").unwrap())
    );
    let missing = dir.path().join("missing.pem");
    assert!(ClientTls::from_settings(Some(&missing), None, None).is_err());
}

#[cfg(unix)]
#[test]
fn the_automatic_certificate_is_private_and_kept_across_restarts() {
    use std::os::unix::fs::PermissionsExt;
    let dir = tempfile::tempdir().unwrap();
    let tls = dir.path().join("data").join(AUTO_TLS_DIR);
    let first = ServerTls::auto(&tls).unwrap();
    for name in ["cert.pem", "key.pem"] {
        let mode = std::fs::metadata(tls.join(name))
            .unwrap()
            .permissions()
            .mode();
        assert_eq!(mode & 0o777, 0o600, "{name}");
    }
    let mode = std::fs::metadata(&tls).unwrap().permissions().mode();
    assert_eq!(mode & 0o777, 0o700);
    let again = ServerTls::auto(&tls).unwrap();
    assert_eq!(first.fingerprint(), again.fingerprint());
    let pem = std::fs::read(tls.join("cert.pem")).unwrap();
    let der = CertificateDer::from_pem_slice(&pem).unwrap();
    assert_eq!(fingerprint(der.as_ref()), first.fingerprint());
    // A certificate without its key is not silently replaced.
    std::fs::remove_file(tls.join("key.pem")).unwrap();
    assert!(ServerTls::auto(&tls).is_err());
}

#[test]
fn the_first_bytes_read_tell_tls_from_http_and_from_plain_protocol() {
    assert_eq!(answered(b""), Answered::Nothing);
    // A TLS alert or handshake record, whole or its first byte only.
    assert_eq!(answered(&[0x15, 0x03, 0x03, 0x00, 0x02]), Answered::Tls);
    assert_eq!(answered(&[0x16]), Answered::Tls);
    // The HTTP port's answer, in clear or read after TLS.
    assert_eq!(answered(b"HTTP/1.1 400 Bad Request\r\n"), Answered::Http);
    assert_eq!(answered(b"HTTP/1.0 400"), Answered::Http);
    // A coordinator without TLS refusing a TLS hello: a frame in clear.
    assert_eq!(answered(&[0, 0, 0, 0x4c, 1, 0]), Answered::Plain);
    assert_eq!(answered(b"SSH-2.0-OpenSSH"), Answered::Plain);
    assert_eq!(answered(&[0x16, 0x00]), Answered::Plain);
}

/// A peer pinned to `pin` dialling a server that, once it read what the peer sent
/// first (after TLS with `tls`), answers `answer` and closes: the peer's error.
async fn dial_answered(tls: Option<ServerTls>, pin: [u8; 32], answer: &'static [u8]) -> String {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let address = listener.local_addr().unwrap().to_string();
    let serving = tokio::spawn(async move {
        let (tcp, _) = listener.accept().await.unwrap();
        let mut stream: Stream = match tls {
            Some(tls) => tls.accept(tcp).await.unwrap(),
            None => Box::new(tcp),
        };
        let mut first = [0u8; 4];
        let _ = stream.read_exact(&mut first).await;
        let _ = stream.write_all(answer).await;
        let _ = stream.shutdown().await;
    });
    let endpoint = Endpoint {
        tls: Some(ClientTls::pinned(pin).unwrap()),
        ..Endpoint::plain(address.clone())
    };
    let result = dial_with(&endpoint, Role::Client, None).await;
    serving.abort();
    match result {
        Err(DialError::Refused(e)) => {
            let text = format!("{e:#}");
            assert!(text.starts_with(&address), "{text}");
            text
        }
        Err(DialError::Unreachable(e)) => panic!("taken for unreachable: {e:#}"),
        Ok(_) => panic!("the handshake succeeded"),
    }
}

#[tokio::test]
async fn a_pinned_peer_names_the_http_port_or_a_coordinator_without_tls() {
    const HTTP: &[u8] = b"HTTP/1.1 400 Bad Request\r\ncontent-length: 0\r\n\r\n";
    let dir = tempfile::tempdir().unwrap();
    let server = ServerTls::auto(dir.path()).unwrap();
    let pin = server.fingerprint();
    let http_port = "answered in HTTP: this looks like the coordinator's HTTP port";
    // The HTTP port in clear.
    let error = dial_answered(None, pin, HTTP).await;
    assert!(error.contains(http_port), "{error}");
    // The HTTP port serving TLS with the coordinator's certificate.
    let error = dial_answered(Some(server), pin, HTTP).await;
    assert!(error.contains(http_port), "{error}");
    // A coordinator without TLS, refusing the TLS hello as a frame too long.
    let error = dial_answered(None, pin, &[0, 0, 0, 2, 1, 0]).await;
    assert!(
        error.ends_with(
            "does not speak TLS: is it the coordinator's HTTP port, or a coordinator \
             started without TLS?"
        ),
        "{error}"
    );
}

/// A TLS connection between `server` and a peer pinned to it: the server's side as
/// rustls gives it (without [`Closing`]), and the peer's as [`dial`] gives it.
async fn tls_pair(server: &ServerTls) -> (tokio_rustls::server::TlsStream<TcpStream>, Stream) {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let address = listener.local_addr().unwrap().to_string();
    let acceptor = server.acceptor.clone();
    let accepting = tokio::spawn(async move {
        let (tcp, _) = listener.accept().await.unwrap();
        acceptor.accept(tcp).await.unwrap()
    });
    let client = ClientTls::pinned(server.fingerprint()).unwrap();
    let tcp = TcpStream::connect(&address).await.unwrap();
    let Ok(peer) = client.connect(&address, tcp).await else {
        panic!("no TLS");
    };
    (accepting.await.unwrap(), peer)
}

#[tokio::test]
async fn tls_ends_with_close_notify_and_a_close_without_it_between_frames_is_no_error() {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let dir = tempfile::tempdir().unwrap();
    let server = ServerTls::auto(dir.path()).unwrap();

    // Dropped, a peer's stream says close_notify: the other side reads a clean end.
    let (mut theirs, ours) = tls_pair(&server).await;
    drop(ours);
    let mut rest = Vec::new();
    theirs.read_to_end(&mut rest).await.expect("a clean end");
    assert!(rest.is_empty());

    // A peer gone without close_notify after a whole frame: the frame, then the end.
    let (mut theirs, ours) = tls_pair(&server).await;
    let mut framed = Framed::new(ours, LengthDelimitedCodec::new());
    theirs.write_all(&[0, 0, 0, 2, 7, 7]).await.unwrap();
    theirs.flush().await.unwrap();
    drop(theirs.into_inner().0);
    assert_eq!(&framed.next().await.unwrap().unwrap()[..], &[7, 7]);
    assert!(framed.next().await.is_none(), "not a clean end");

    // Gone in the middle of a frame: an error still.
    let (mut theirs, ours) = tls_pair(&server).await;
    let mut framed = Framed::new(ours, LengthDelimitedCodec::new());
    theirs.write_all(&[0, 0, 0, 9, 7]).await.unwrap();
    theirs.flush().await.unwrap();
    drop(theirs.into_inner().0);
    assert!(
        matches!(framed.next().await, Some(Err(_))),
        "a truncated frame taken for an end"
    );
}

/// A TLS handshake between `server` and a peer using `client`: what the peer got.
async fn handshake(server: &ServerTls, client: &ClientTls) -> Result<(), DialError> {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let address = listener.local_addr().unwrap().to_string();
    let server = server.clone();
    let accepting = tokio::spawn(async move {
        let (tcp, _) = listener.accept().await.unwrap();
        let _ = server.accept(tcp).await;
    });
    let tcp = TcpStream::connect(&address).await.unwrap();
    let result = client.connect(&address, tcp).await.map(|_| ());
    accepting.abort();
    result
}

#[tokio::test]
async fn a_pinned_peer_accepts_exactly_the_pinned_certificate() {
    let dir = tempfile::tempdir().unwrap();
    let server = ServerTls::auto(&dir.path().join("a")).unwrap();
    let other = ServerTls::auto(&dir.path().join("b")).unwrap();
    assert_ne!(server.fingerprint(), other.fingerprint());
    let pinned = ClientTls::pinned(server.fingerprint()).unwrap();
    assert!(handshake(&server, &pinned).await.is_ok());
    let Err(DialError::Refused(error)) = handshake(&other, &pinned).await else {
        panic!("another certificate must be refused for good");
    };
    let text = error.to_string();
    assert!(!text.contains('\n'), "{text}");
    assert!(
        text.contains(&fingerprint_hex(&server.fingerprint()))
            && text.contains(&fingerprint_hex(&other.fingerprint())),
        "{text}"
    );
}
