//! HTTP/1.0 to the daemons' HTTP listeners (status page, API, health, metrics), plain
//! or over TLS: the server closes the connection when done, so an answer is read to
//! its end.

use std::io::{Read, Write};
use std::path::Path;
use std::sync::Arc;
use std::time::Duration;

/// How to reach an HTTP listener: its address, and over TLS the trust to check its
/// certificate with.
#[derive(Clone)]
pub struct Site {
    pub addr: String,
    pub tls: Option<Arc<rustls::ClientConfig>>,
}

impl Site {
    /// Plain HTTP at `addr`.
    pub fn plain(addr: &str) -> Site {
        Site {
            addr: addr.to_owned(),
            tls: None,
        }
    }

    /// HTTPS at `addr`, trusting only the certificate in the PEM file `cert` (a
    /// coordinator's `--tls-auto` one names 127.0.0.1).
    pub fn https(addr: &str, cert: &Path) -> Site {
        use rustls::pki_types::pem::PemObject;
        let mut roots = rustls::RootCertStore::empty();
        for certificate in rustls::pki_types::CertificateDer::pem_file_iter(cert)
            .unwrap_or_else(|e| panic!("{}: {e}", cert.display()))
        {
            roots.add(certificate.unwrap()).unwrap();
        }
        let config = rustls::ClientConfig::builder_with_provider(Arc::new(
            rustls::crypto::ring::default_provider(),
        ))
        .with_safe_default_protocol_versions()
        .unwrap()
        .with_root_certificates(roots)
        .with_no_client_auth();
        Site {
            addr: addr.to_owned(),
            tls: Some(Arc::new(config)),
        }
    }

    /// `METHOD PATH` with `headers` and `body`, at most `timeout` to connect and for each
    /// read: the answer, or `None` if nothing answers (or TLS fails).
    pub fn request(
        &self,
        method: &str,
        path: &str,
        headers: &[(&str, &str)],
        body: &[u8],
        timeout: Duration,
    ) -> Option<Answer> {
        let socket: std::net::SocketAddr = self.addr.parse().ok()?;
        let tcp = std::net::TcpStream::connect_timeout(&socket, timeout).ok()?;
        tcp.set_read_timeout(Some(timeout)).ok()?;
        tcp.set_write_timeout(Some(timeout)).ok()?;
        let mut request = format!("{method} {path} HTTP/1.0\r\nHost: {}\r\n", self.addr);
        if !body.is_empty() || method == "POST" {
            request.push_str(&format!("Content-Length: {}\r\n", body.len()));
        }
        for (name, value) in headers {
            request.push_str(&format!("{name}: {value}\r\n"));
        }
        request.push_str("\r\n");
        let mut request = request.into_bytes();
        request.extend_from_slice(body);
        let response = match &self.tls {
            None => exchange(tcp, &request)?,
            Some(config) => {
                let name = rustls::pki_types::ServerName::from(socket.ip());
                let connection = rustls::ClientConnection::new(Arc::clone(config), name).ok()?;
                exchange(rustls::StreamOwned::new(connection, tcp), &request)?
            }
        };
        let head_end = response.windows(4).position(|w| w == b"\r\n\r\n")?;
        let head = String::from_utf8_lossy(&response[..head_end]).to_ascii_lowercase();
        let status = head.split_whitespace().nth(1)?.parse().ok()?;
        Some(Answer {
            status,
            head,
            body: response[head_end + 4..].to_vec(),
        })
    }
}

/// Sends `request` and reads the answer to its end (a TLS peer that closes without
/// close_notify still gives what it sent).
fn exchange(mut stream: impl Read + Write, request: &[u8]) -> Option<Vec<u8>> {
    stream.write_all(request).ok()?;
    stream.flush().ok()?;
    let mut response = Vec::new();
    match stream.read_to_end(&mut response) {
        Ok(_) => Some(response),
        Err(e) if e.kind() == std::io::ErrorKind::UnexpectedEof && !response.is_empty() => {
            Some(response)
        }
        Err(_) => None,
    }
}

impl Site {
    /// `METHOD PATH` of the API (`/api/v1`) with the client token `token` and `body`:
    /// raw bytes for a `PUT` (an upload), JSON otherwise. Panics if nothing answers.
    pub fn api(&self, token: &str, method: &str, path: &str, body: &[u8]) -> Answer {
        let auth = format!("Bearer {token}");
        let kind = if method == "PUT" {
            "application/octet-stream"
        } else {
            "application/json"
        };
        let headers = [("Authorization", auth.as_str()), ("Content-Type", kind)];
        self.request(method, path, &headers, body, Duration::from_secs(30))
            .unwrap_or_else(|| panic!("no answer to {method} {path}"))
    }
}

/// What an HTTP server answered.
pub struct Answer {
    pub status: u16,
    /// The status line and the headers, lowercased.
    pub head: String,
    pub body: Vec<u8>,
}

/// The value of header `name` (lowercase) in an answer's `head`, if present.
pub fn header<'a>(head: &'a str, name: &str) -> Option<&'a str> {
    head.lines()
        .find_map(|l| l.strip_prefix(name)?.strip_prefix(':'))
        .map(str::trim)
}

/// `GET PATH` with extra header lines (each ending in `\r\n`) from the HTTP listener at
/// `addr`, with `timeout` on connecting, sending and each read. `None` if nothing
/// answers.
pub fn http_request(addr: &str, path: &str, headers: &str, timeout: Duration) -> Option<Answer> {
    let headers: Vec<(&str, &str)> = headers
        .split("\r\n")
        .filter_map(|line| line.split_once(':'))
        .map(|(name, value)| (name, value.trim()))
        .collect();
    Site::plain(addr).request("GET", path, &headers, b"", timeout)
}

/// [`http_get_within`] 10 s.
pub fn http_get(addr: &str, path: &str) -> Option<(u16, Vec<u8>)> {
    http_get_within(addr, path, Duration::from_secs(10))
}

/// `GET PATH` from the HTTP listener at `addr`, at most `timeout` to connect and for
/// each read: the status code and the body. `None` if nothing answers.
pub fn http_get_within(addr: &str, path: &str, timeout: Duration) -> Option<(u16, Vec<u8>)> {
    http_request(addr, path, "", timeout).map(|answer| (answer.status, answer.body))
}

/// `GET PATH`, which must answer 200 with text (at most 10 s): the text.
pub fn http_get_text(addr: &str, path: &str) -> String {
    let (status, body) =
        http_get(addr, path).unwrap_or_else(|| panic!("no answer to GET {path} from {addr}"));
    assert_eq!(
        status,
        200,
        "GET {path}: {}",
        String::from_utf8_lossy(&body)
    );
    String::from_utf8(body).unwrap_or_else(|e| panic!("GET {path}: not text: {e}"))
}

/// `POST PATH` with `headers` and `body` over HTTP/1.0: the status code and the body.
pub fn http_post(addr: &str, path: &str, headers: &[(&str, &str)], body: &str) -> (u16, String) {
    let mut stream = std::net::TcpStream::connect(addr).unwrap();
    stream
        .set_read_timeout(Some(Duration::from_secs(20)))
        .unwrap();
    let mut request = format!(
        "POST {path} HTTP/1.0\r\nHost: {addr}\r\nContent-Length: {}\r\n",
        body.len()
    );
    for (name, value) in headers {
        request.push_str(&format!("{name}: {value}\r\n"));
    }
    request.push_str("\r\n");
    request.push_str(body);
    stream.write_all(request.as_bytes()).unwrap();
    let mut response = Vec::new();
    stream.read_to_end(&mut response).unwrap();
    let text = String::from_utf8_lossy(&response).into_owned();
    let (head, body) = text.split_once("\r\n\r\n").expect("an HTTP answer");
    let code = head.split_whitespace().nth(1).unwrap().parse().unwrap();
    (code, body.to_owned())
}

/// The message of a refusal's body, `{"error": MESSAGE}`, which is one line.
pub fn json_error(body: &[u8]) -> String {
    let json: serde_json::Value = serde_json::from_slice(body).expect("a JSON refusal");
    let message = json["error"].as_str().expect("an error field").to_owned();
    assert!(!message.contains('\n'), "{message:?}");
    message
}

/// The value of the sample `NAME VALUE` in a Prometheus exposition (`NAME` with its
/// labels, if it has any), if present; a value that is not a number fails the test.
pub fn metric_value(exposition: &str, name: &str) -> Option<f64> {
    exposition
        .lines()
        .find_map(|line| line.strip_prefix(name)?.strip_prefix(' '))
        .map(|value| {
            value
                .trim()
                .parse()
                .unwrap_or_else(|e| panic!("{name} {value:?} is not a number: {e}"))
        })
}
