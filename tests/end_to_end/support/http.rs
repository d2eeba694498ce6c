//! Plain HTTP/1.0 to the daemons' HTTP listeners (status page, API, health, metrics):
//! the server closes the connection when done, so an answer is read to its end.

use std::io::{Read, Write};
use std::time::Duration;

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
    let socket: std::net::SocketAddr = addr.parse().ok()?;
    let mut stream = std::net::TcpStream::connect_timeout(&socket, timeout).ok()?;
    stream.set_read_timeout(Some(timeout)).ok()?;
    stream.set_write_timeout(Some(timeout)).ok()?;
    write!(
        stream,
        "GET {path} HTTP/1.0\r\nHost: {addr}\r\n{headers}\r\n"
    )
    .ok()?;
    let mut response = Vec::new();
    stream.read_to_end(&mut response).ok()?;
    let head_end = response.windows(4).position(|w| w == b"\r\n\r\n")?;
    let head = String::from_utf8_lossy(&response[..head_end]).to_ascii_lowercase();
    let status = head.split_whitespace().nth(1)?.parse().ok()?;
    Some(Answer {
        status,
        head,
        body: response[head_end + 4..].to_vec(),
    })
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
