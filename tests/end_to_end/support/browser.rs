//! A headless Chromium for the browser tests: where it is, how it is run, and a small
//! DevTools protocol client to drive a page as a user does.
//!
//! Needs Chromium (`chromium`, or the path in `TESSERA_CHROMIUM`). Without it a test
//! says so and passes, unless `TESSERA_REQUIRE_BROWSER=1` (as in CI), where a missing
//! browser fails it.

use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::time::Duration;

use super::{free_port, poll, Daemon};

/// The browser: `TESSERA_CHROMIUM`, or Chromium where Debian puts it.
pub fn chromium() -> Option<PathBuf> {
    if let Some(path) = std::env::var_os("TESSERA_CHROMIUM") {
        return Some(PathBuf::from(path));
    }
    [
        "/usr/bin/chromium",
        "/usr/bin/chromium-browser",
        "/usr/bin/google-chrome",
    ]
    .iter()
    .map(PathBuf::from)
    .find(|p| p.exists())
}

/// How every test here runs the browser: headless, quiet, nothing fetched from outside.
const BROWSER_FLAGS: [&str; 8] = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
];

/// Loads `url` in a fresh headless browser (at most 60 s), lets the page run for
/// `virtual_ms` of virtual time, and dumps its DOM on stdout.
pub fn dump_dom(browser: &Path, profile: &Path, url: &str, virtual_ms: u32) -> Output {
    Command::new("timeout")
        .arg("60")
        .arg(browser)
        .args(BROWSER_FLAGS)
        .arg(format!("--virtual-time-budget={virtual_ms}"))
        .arg("--dump-dom")
        .arg(format!("--user-data-dir={}", profile.display()))
        .arg(url)
        .output()
        .expect("cannot start the browser")
}

/// The flag that has the browser trust a certificate of the key in the PEM file `key`
/// (a coordinator's `--tls-auto` key): the base64 SHA-256 of its public key, as a user
/// who pinned the farm's fingerprint would accept its certificate, and nothing else.
pub fn trust_key(key: &Path) -> String {
    use base64::Engine;
    use rcgen::PublicKeyData;
    use sha2::Digest;
    let pem = std::fs::read_to_string(key).unwrap_or_else(|e| panic!("{}: {e}", key.display()));
    let pair = rcgen::KeyPair::from_pem(&pem).expect("a PEM key");
    let digest = sha2::Sha256::digest(pair.subject_public_key_info());
    format!(
        "--ignore-certificate-errors-spki-list={}",
        base64::engine::general_purpose::STANDARD.encode(digest)
    )
}

/// `GET PATH` over HTTP/1.1 (the DevTools listener takes nothing older and keeps the
/// connection open: the body is read by its length): the status code and the body.
fn http11_get(addr: &str, path: &str) -> Option<(u16, Vec<u8>)> {
    let mut stream = std::net::TcpStream::connect(addr).ok()?;
    stream.set_read_timeout(Some(Duration::from_secs(5))).ok()?;
    write!(
        stream,
        "GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n"
    )
    .ok()?;
    let mut head = Vec::new();
    let mut byte = [0u8; 1];
    while !head.ends_with(b"\r\n\r\n") {
        stream.read_exact(&mut byte).ok()?;
        head.push(byte[0]);
    }
    let head = String::from_utf8_lossy(&head).to_ascii_lowercase();
    let status = head.split_whitespace().nth(1)?.parse().ok()?;
    let length: usize = head
        .lines()
        .find_map(|l| l.strip_prefix("content-length:"))?
        .trim()
        .parse()
        .ok()?;
    let mut body = vec![0u8; length];
    stream.read_exact(&mut body).ok()?;
    Some((status, body))
}

/// A headless Chromium driven over the DevTools protocol: a WebSocket to its page,
/// spoken by hand (a few dozen lines, text frames only) so that the tests need no
/// client library. Killed when dropped.
pub struct DevTools {
    browser: Daemon,
    socket: std::net::TcpStream,
    next_id: u64,
}

impl DevTools {
    /// Starts the browser on `url` and connects to its page.
    pub fn open(browser: &Path, profile: &Path, url: &str, log: &Path) -> DevTools {
        DevTools::open_with(browser, profile, url, log, &[])
    }

    /// [`DevTools::open`] with more command-line flags for the browser (such as
    /// [`trust_key`]'s).
    pub fn open_with(
        browser: &Path,
        profile: &Path,
        url: &str,
        log: &Path,
        flags: &[String],
    ) -> DevTools {
        let port = free_port();
        let child = Command::new(browser)
            .args(BROWSER_FLAGS)
            .args(flags)
            .args([
                "--remote-debugging-address=127.0.0.1",
                "--window-size=1400,1000",
            ])
            .arg(format!("--remote-debugging-port={port}"))
            .arg(format!("--user-data-dir={}", profile.display()))
            .arg(url)
            .stdin(std::process::Stdio::null())
            .stdout(std::process::Stdio::null())
            .stderr(std::fs::File::create(log).unwrap())
            .spawn()
            .expect("cannot start the browser");
        let browser = Daemon {
            name: "chromium".into(),
            child,
            log: Some(log.to_path_buf()),
        };
        let devtools = format!("127.0.0.1:{port}");
        let target = poll("the browser's page", Duration::from_secs(30), || {
            let (code, body) = http11_get(&devtools, "/json/list")?;
            let targets: serde_json::Value = serde_json::from_slice(&body).ok()?;
            (code == 200).then_some(())?;
            targets.as_array()?.iter().find_map(|t| {
                (t["type"] == "page")
                    .then(|| t["webSocketDebuggerUrl"].as_str().map(str::to_owned))
                    .flatten()
            })
        });
        let path = target
            .strip_prefix(&format!("ws://{devtools}"))
            .unwrap_or_else(|| panic!("a page target elsewhere: {target}"))
            .to_owned();
        let mut socket = std::net::TcpStream::connect(&devtools).unwrap();
        socket
            .set_read_timeout(Some(Duration::from_secs(20)))
            .unwrap();
        write!(
            socket,
            "GET {path} HTTP/1.1\r\nHost: {devtools}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n\
             Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n\r\n"
        )
        .unwrap();
        let mut head = Vec::new();
        let mut byte = [0u8; 1];
        while !head.ends_with(b"\r\n\r\n") {
            socket
                .read_exact(&mut byte)
                .expect("no WebSocket handshake");
            head.push(byte[0]);
        }
        let head = String::from_utf8_lossy(&head);
        assert!(
            head.starts_with("HTTP/1.1 101"),
            "WebSocket refused: {head}"
        );
        DevTools {
            browser,
            socket,
            next_id: 1,
        }
    }

    fn send_frame(&mut self, text: &str) {
        let payload = text.as_bytes();
        let mut frame = vec![0x81u8];
        let mask = [0x5a, 0x17, 0xc3, 0x2e];
        match payload.len() {
            n if n < 126 => frame.push(0x80 | n as u8),
            n if n < 65536 => {
                frame.push(0x80 | 126);
                frame.extend((n as u16).to_be_bytes());
            }
            n => {
                frame.push(0x80 | 127);
                frame.extend((n as u64).to_be_bytes());
            }
        }
        frame.extend(mask);
        frame.extend(payload.iter().enumerate().map(|(i, b)| b ^ mask[i % 4]));
        self.socket.write_all(&frame).unwrap();
    }

    /// The next whole text message.
    fn read_message(&mut self) -> String {
        let mut message = Vec::new();
        loop {
            let mut head = [0u8; 2];
            self.socket
                .read_exact(&mut head)
                .expect("the browser went silent");
            let len = match head[1] & 0x7f {
                126 => {
                    let mut n = [0u8; 2];
                    self.socket.read_exact(&mut n).unwrap();
                    u64::from(u16::from_be_bytes(n))
                }
                127 => {
                    let mut n = [0u8; 8];
                    self.socket.read_exact(&mut n).unwrap();
                    u64::from_be_bytes(n)
                }
                n => u64::from(n),
            };
            let mut payload = vec![0u8; len as usize];
            self.socket.read_exact(&mut payload).unwrap();
            match head[0] & 0x0f {
                0x0 | 0x1 => message.extend(payload),
                0x8 => panic!("the browser closed the DevTools connection"),
                _ => continue,
            }
            if head[0] & 0x80 != 0 {
                return String::from_utf8(message).expect("DevTools speaks UTF-8");
            }
        }
    }

    /// Calls a DevTools method and returns its result.
    pub fn call(&mut self, method: &str, params: serde_json::Value) -> serde_json::Value {
        let answer = self.answer(method, params);
        assert!(answer["error"].is_null(), "{method}: {answer}");
        answer["result"].clone()
    }

    /// Calls a DevTools method and returns the whole answer, result or error.
    fn answer(&mut self, method: &str, params: serde_json::Value) -> serde_json::Value {
        let id = self.next_id;
        self.next_id += 1;
        let request = serde_json::json!({ "id": id, "method": method, "params": params });
        self.send_frame(&request.to_string());
        loop {
            let answer: serde_json::Value = serde_json::from_str(&self.read_message()).unwrap();
            if answer["id"] == id {
                return answer;
            }
        }
    }

    /// Evaluates `expression` in the page: its value. `null` if the page navigated
    /// while it was evaluated (a form sent, a reload, the first load ending): the
    /// document it ran in is gone, and a poll asks the new one again.
    pub fn eval(&mut self, expression: &str) -> serde_json::Value {
        let answer = self.answer(
            "Runtime.evaluate",
            serde_json::json!({ "expression": expression, "returnByValue": true }),
        );
        let error = &answer["error"];
        if error["message"] == "Inspected target navigated or closed" {
            return serde_json::Value::Null;
        }
        assert!(error.is_null(), "Runtime.evaluate: {answer}");
        answer["result"]["result"]["value"].clone()
    }

    /// Clicks the element `selector` as a user does: a mouse press and release at its
    /// centre. False if it is not on the page.
    pub fn click(&mut self, selector: &str) -> bool {
        let expression = format!(
            "(() => {{ const e = document.querySelector({selector:?}); if (!e) return null; \
             e.scrollIntoView(); const r = e.getBoundingClientRect(); \
             return [r.x + r.width / 2, r.y + r.height / 2]; }})()"
        );
        let at = self.eval(&expression);
        let (Some(x), Some(y)) = (at[0].as_f64(), at[1].as_f64()) else {
            return false;
        };
        for kind in ["mousePressed", "mouseReleased"] {
            self.call(
                "Input.dispatchMouseEvent",
                serde_json::json!({ "type": kind, "x": x, "y": y, "button": "left", "clickCount": 1 }),
            );
        }
        true
    }

    /// Lays the page out as in a window of `width` × `height` CSS pixels.
    pub fn set_viewport(&mut self, width: u32, height: u32) {
        self.call(
            "Emulation.setDeviceMetricsOverride",
            serde_json::json!({ "width": width, "height": height, "deviceScaleFactor": 1, "mobile": false }),
        );
    }

    /// Writes what the page shows now to `path`, as PNG, and a copy under the same name
    /// in `TESSERA_SCREENSHOT_DIR` if set: how the docs' pictures of the pages are
    /// taken.
    pub fn screenshot(&mut self, path: &Path) {
        let shot = self.call(
            "Page.captureScreenshot",
            serde_json::json!({ "format": "png" }),
        );
        let png = base64(shot["data"].as_str().expect("a screenshot"));
        std::fs::write(path, png)
            .unwrap_or_else(|e| panic!("cannot write {}: {e}", path.display()));
        if let (Some(keep), Some(name)) =
            (std::env::var_os("TESSERA_SCREENSHOT_DIR"), path.file_name())
        {
            std::fs::copy(path, Path::new(&keep).join(name))
                .unwrap_or_else(|e| panic!("cannot keep {}: {e}", path.display()));
        }
    }
}

impl Drop for DevTools {
    fn drop(&mut self) {
        self.browser.kill9();
    }
}

/// Standard base64, as the studio's stream carries a tile's PNG and DevTools a
/// screenshot.
pub fn base64(text: &str) -> Vec<u8> {
    let value = |c: u8| -> u32 {
        match c {
            b'A'..=b'Z' => u32::from(c - b'A'),
            b'a'..=b'z' => u32::from(c - b'a') + 26,
            b'0'..=b'9' => u32::from(c - b'0') + 52,
            b'+' => 62,
            b'/' => 63,
            _ => panic!("{c:?} is not base64"),
        }
    };
    let text = text.trim_end_matches('=').as_bytes();
    let mut out = Vec::with_capacity(text.len() * 3 / 4);
    for chunk in text.chunks(4) {
        let bits = chunk
            .iter()
            .enumerate()
            .fold(0u32, |acc, (i, &c)| acc | value(c) << (18 - 6 * i));
        out.extend_from_slice(&bits.to_be_bytes()[1..chunk.len()]);
    }
    out
}

/// Chromium, or `None` (the test then passes, saying it skipped) when there is none and
/// `TESSERA_REQUIRE_BROWSER` is not 1; with it set (CI), a missing browser fails.
pub fn browser_or_skip() -> Option<PathBuf> {
    let browser = chromium();
    if browser.is_none() {
        assert!(
            std::env::var("TESSERA_REQUIRE_BROWSER").as_deref() != Ok("1"),
            "TESSERA_REQUIRE_BROWSER=1 but no Chromium found (install chromium or set TESSERA_CHROMIUM)"
        );
        eprintln!("skipped: no Chromium on this machine (set TESSERA_CHROMIUM)");
    }
    browser
}
