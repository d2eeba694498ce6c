//! Who may call which HTTP route: the decision, apart from the I/O that serves it.
//!
//! Every route of the coordinator's HTTP side has one [`Access`], set in the route
//! table (`super::routes`), and a request passes [`decide`] before its handler runs.
//! On a farm with a client secret, everything but health and the pages' own HTML and
//! script needs that secret: the jobs, their images, frames, previews and events, the
//! workers' names and addresses, the studio and the controls. A request proves it in
//! one of two ways:
//!
//! - `Authorization: Bearer SECRET`, for scripts and `curl`;
//! - a session cookie, for the pages: a browser cannot put a header on an `<img>`, an
//!   `EventSource` or a download, and a secret in a URL ends up in histories and
//!   logs. The login form posts the secret once ([`Access::Login`]); the answer sets
//!   an `HttpOnly`, `SameSite=Strict` cookie (`Secure` over TLS) that the browser then
//!   sends with every request of the page, and that no script can read.
//!
//! The cookie is not a copy of the secret: it is an expiry time and the HMAC-SHA256 of
//! it under the secret ([`Session`]). The coordinator keeps no session table, so a
//! restart logs no one out, and a session made with a secret ends when that secret
//! stops being accepted (a rotation's overlap window closes), as connections proved
//! with it do.

use std::net::IpAddr;

use axum::http::StatusCode;
use hmac::{KeyInit, Mac};
use sha2::{Digest, Sha256};

/// Who may call a route.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Access {
    /// Anyone: health and readiness, for supervisors and load balancers.
    Open,
    /// Anyone: a page's own HTML and script, which hold nothing of the farm's (what
    /// they show comes from [`Access::Read`] routes once logged in).
    Page,
    /// Anyone may try a secret: the login form's post, and logging out. JSON from
    /// the page's own origin only, as the controls.
    Login,
    /// The metrics: the scrape token (`--metrics-token-file`), or the client secret.
    Scrape,
    /// What the farm holds: the client secret.
    Read,
    /// What changes the farm: the client secret, as JSON from the page's own origin.
    Control,
    /// What adds a file to the farm's store (a studio page's mesh): a control's rules,
    /// but as raw bytes (`Content-Type: application/octet-stream`, which a cross-site
    /// form cannot send either without the browser asking first).
    Upload,
}

impl Access {
    /// The name the documentation and the route test use.
    pub fn as_str(self) -> &'static str {
        match self {
            Access::Open => "open",
            Access::Page => "page",
            Access::Login => "login",
            Access::Scrape => "scrape",
            Access::Read => "read",
            Access::Control => "control",
            Access::Upload => "upload",
        }
    }
}

/// The secrets a request may prove, as the coordinator holds them now.
#[derive(Clone, Copy, Debug, Default)]
pub struct Secrets<'a> {
    /// The client secrets accepted now (the current one, and within a rotation's
    /// overlap window the previous one); `None` on a farm without a client secret.
    pub client: Option<&'a [Vec<u8>]>,
    /// The scrape token, if the coordinator has one.
    pub scrape: Option<&'a [u8]>,
}

/// What a request shows of itself.
#[derive(Clone, Copy, Debug)]
pub struct Asking<'a> {
    pub peer: IpAddr,
    /// The `Authorization` header, if any.
    pub authorization: Option<&'a str>,
    /// The session cookie's value, if the request carries one ([`session_cookie`]).
    pub session: Option<&'a str>,
    /// The `Content-Type` header, if any.
    pub content_type: Option<&'a str>,
    /// The `Origin` header, if any (browsers send it with every cross-site POST).
    pub origin: Option<&'a str>,
    /// The `Host` header, if any.
    pub host: Option<&'a str>,
    /// Seconds since the Unix epoch, for the session's expiry.
    pub now: u64,
}

/// Why a request is refused: its HTTP status and one line saying why.
pub type Refused = (StatusCode, String);

/// Whether a request may call a route of this `access`.
///
/// - [`Access::Open`] and [`Access::Page`]: always.
/// - [`Access::Login`] and [`Access::Control`] must be JSON (`Content-Type:
///   application/json`), [`Access::Upload`] raw bytes (`application/octet-stream`),
///   neither of which a cross-site form can send without the browser asking first
///   (nothing here answers that question), and an `Origin`, when sent, must name the
///   host the request was sent to.
/// - With a client secret, [`Access::Read`], [`Access::Control`] and [`Access::Upload`]
///   need it (a bearer token or a session), compared in constant time: none is 401, a
///   wrong one 403. [`Access::Scrape`] takes the scrape token as well.
/// - Without one, reading is open (such a farm listens on loopback unless its
///   operator said `--insecure`), and only a loopback peer may use the controls and
///   uploads.
pub fn decide(access: Access, secrets: Secrets<'_>, asking: &Asking<'_>) -> Result<(), Refused> {
    match access {
        Access::Open | Access::Page => return Ok(()),
        Access::Login => return same_site(asking, "application/json"),
        Access::Control => same_site(asking, "application/json")?,
        Access::Upload => same_site(asking, "application/octet-stream")?,
        Access::Scrape | Access::Read => {}
    }
    let Some(client) = secrets.client else {
        return match access {
            Access::Control | Access::Upload if !asking.peer.is_loopback() => Err((
                StatusCode::FORBIDDEN,
                "without a client secret only this machine may use the controls: give the \
                 coordinator a client token to use them from elsewhere"
                    .into(),
            )),
            _ => Ok(()),
        };
    };
    let bearer = asking
        .authorization
        .map(|v| v.strip_prefix("Bearer ").map(str::trim));
    let session_valid = asking
        .session
        .is_some_and(|cookie| Session::verify(cookie, client, asking.now));
    let bearer_valid = |token: &str| {
        let scrape = access == Access::Scrape
            && secrets
                .scrape
                .is_some_and(|s| same_secret(token.as_bytes(), s));
        // Every secret is compared, so that the time taken does not tell which.
        let client = client
            .iter()
            .fold(false, |any, s| same_secret(token.as_bytes(), s) | any);
        scrape | client
    };
    match bearer {
        Some(Some(token)) if bearer_valid(token) => Ok(()),
        Some(Some(_)) => Err((StatusCode::FORBIDDEN, "wrong client token".into())),
        _ if session_valid => Ok(()),
        _ if asking.session.is_some() => Err((
            StatusCode::UNAUTHORIZED,
            "the session has expired or its secret was replaced: log in again".into(),
        )),
        _ => Err((
            StatusCode::UNAUTHORIZED,
            match access {
                Access::Scrape => {
                    "this farm has secrets: send the scrape token (or the client token) as \
                     Authorization: Bearer TOKEN"
                }
                _ => {
                    "this farm has a client secret: log in on the page, or send it as \
                     Authorization: Bearer TOKEN"
                }
            }
            .into(),
        )),
    }
}

/// A control or a login must be JSON (an upload raw bytes, `kind`) from the page's own
/// origin.
fn same_site(asking: &Asking<'_>, kind: &str) -> Result<(), Refused> {
    let right = asking.content_type.is_some_and(|t| {
        t.split(';')
            .next()
            .is_some_and(|m| m.trim().eq_ignore_ascii_case(kind))
    });
    if !right {
        let what = if kind == "application/json" {
            "controls"
        } else {
            "uploads"
        };
        return Err((
            StatusCode::UNSUPPORTED_MEDIA_TYPE,
            format!("{what} take Content-Type: {kind}"),
        ));
    }
    if let Some(origin) = asking.origin {
        let origin_host = origin
            .split_once("://")
            .map_or(origin, |(_, rest)| rest)
            .trim_end_matches('/');
        if asking.host != Some(origin_host) {
            return Err((
                StatusCode::FORBIDDEN,
                format!("a control from another site ({origin}) is refused"),
            ));
        }
    }
    Ok(())
}

/// Compares two secrets in time independent of where they differ (and of their
/// lengths): their SHA-256 digests, every byte looked at.
pub fn same_secret(given: &[u8], secret: &[u8]) -> bool {
    let (a, b) = (Sha256::digest(given), Sha256::digest(secret));
    a.iter()
        .zip(b.iter())
        .fold(0u8, |acc, (x, y)| acc | (x ^ y))
        == 0
}

/// How long a login lasts: a working day, after which the page asks again.
pub const SESSION_SECONDS: u64 = 12 * 60 * 60;

/// A page's session: the cookie `EXPIRY.MAC`, EXPIRY in seconds since the Unix epoch
/// and MAC the hex HMAC-SHA256 of `tessera session EXPIRY` keyed with the client
/// secret it was made with.
pub struct Session;

impl Session {
    /// A new session's cookie value, made with `secret`, ending `SESSION_SECONDS`
    /// after `now`.
    pub fn issue(secret: &[u8], now: u64) -> String {
        let expiry = now.saturating_add(SESSION_SECONDS);
        let mac: String = Self::mac(secret, expiry)
            .finalize()
            .into_bytes()
            .iter()
            .map(|b| format!("{b:02x}"))
            .collect();
        format!("{expiry}.{mac}")
    }

    /// Whether `cookie` is a session made with one of `secrets` that has not ended by
    /// `now`. The MAC is checked in constant time.
    pub fn verify(cookie: &str, secrets: &[Vec<u8>], now: u64) -> bool {
        let Some((expiry, mac)) = cookie.split_once('.') else {
            return false;
        };
        let Ok(expiry) = expiry.parse::<u64>() else {
            return false;
        };
        let Some(mac) = unhex(mac) else {
            return false;
        };
        if now >= expiry || expiry > now.saturating_add(SESSION_SECONDS) {
            return false;
        }
        secrets.iter().fold(false, |any, secret| {
            Self::mac(secret, expiry).verify_slice(&mac).is_ok() | any
        })
    }

    fn mac(secret: &[u8], expiry: u64) -> hmac::Hmac<Sha256> {
        let mut mac =
            hmac::Hmac::<Sha256>::new_from_slice(secret).expect("HMAC takes keys of any length");
        mac.update(format!("tessera session {expiry}").as_bytes());
        mac
    }
}

fn unhex(text: &str) -> Option<Vec<u8>> {
    if !text.len().is_multiple_of(2) || !text.is_ascii() {
        return None;
    }
    (0..text.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(&text[i..i + 2], 16).ok())
        .collect()
}

/// The session cookie's name for a page reached at `host` (the `Host` header): one
/// per port, since browsers share cookies between the ports of a host, and two
/// coordinators on one machine must not log each other out.
pub fn cookie_name(host: Option<&str>) -> String {
    let port = host
        .and_then(|h| h.rsplit_once(':'))
        .map(|(_, port)| port)
        .filter(|p| !p.is_empty() && p.bytes().all(|b| b.is_ascii_digit()));
    match port {
        Some(port) => format!("tessera_session_{port}"),
        None => "tessera_session".into(),
    }
}

/// The value of cookie `name` in a `Cookie` header, if there.
pub fn session_cookie<'a>(cookies: &'a str, name: &str) -> Option<&'a str> {
    cookies.split(';').find_map(|pair| {
        let (key, value) = pair.trim().split_once('=')?;
        (key == name).then_some(value)
    })
}

/// The `Set-Cookie` value that stores `value` (an empty value with a past expiry logs
/// out): `HttpOnly` so that no script reads it, `SameSite=Strict` so that no other
/// site's page sends it, `Secure` when the page came over TLS.
pub fn set_cookie(name: &str, value: Option<&str>, secure: bool) -> String {
    let (value, age) = match value {
        Some(value) => (value, SESSION_SECONDS),
        None => ("", 0),
    };
    let secure = if secure { "; Secure" } else { "" };
    format!("{name}={value}; Path=/; Max-Age={age}; HttpOnly; SameSite=Strict{secure}")
}

#[cfg(test)]
mod tests {
    use super::*;

    const LOOPBACK: IpAddr = IpAddr::V4(std::net::Ipv4Addr::LOCALHOST);
    const REMOTE: IpAddr = IpAddr::V4(std::net::Ipv4Addr::new(192, 0, 2, 7));
    const NOW: u64 = 1_800_000_000;

    fn asking(peer: IpAddr, authorization: Option<&str>) -> Asking<'_> {
        Asking {
            peer,
            authorization,
            session: None,
            content_type: Some("application/json"),
            origin: None,
            host: Some("farm:8080"),
            now: NOW,
        }
    }

    fn code(r: Result<(), Refused>) -> Option<StatusCode> {
        r.err().map(|(code, _)| code)
    }

    fn client(secrets: &[Vec<u8>]) -> Secrets<'_> {
        Secrets {
            client: Some(secrets),
            scrape: None,
        }
    }

    #[test]
    fn without_a_secret_reading_is_open_and_only_loopback_may_control() {
        let none = Secrets::default();
        for peer in [LOOPBACK, REMOTE] {
            for access in [Access::Open, Access::Page, Access::Read, Access::Scrape] {
                assert_eq!(code(decide(access, none, &asking(peer, None))), None);
            }
        }
        assert_eq!(
            code(decide(Access::Control, none, &asking(LOOPBACK, None))),
            None
        );
        assert_eq!(
            code(decide(Access::Control, none, &asking(REMOTE, None))),
            Some(StatusCode::FORBIDDEN)
        );
        let v6 = IpAddr::V6(std::net::Ipv6Addr::LOCALHOST);
        assert_eq!(code(decide(Access::Control, none, &asking(v6, None))), None);
        let upload = |peer| Asking {
            content_type: Some("application/octet-stream"),
            ..asking(peer, None)
        };
        assert_eq!(code(decide(Access::Upload, none, &upload(LOOPBACK))), None);
        assert_eq!(
            code(decide(Access::Upload, none, &upload(REMOTE))),
            Some(StatusCode::FORBIDDEN)
        );
    }

    #[test]
    fn an_upload_is_raw_bytes_from_the_page_with_the_secret_as_a_control_is() {
        let secrets = [b"s3cret".to_vec()];
        let upload = |auth, content_type, origin| Asking {
            content_type: Some(content_type),
            origin,
            ..asking(REMOTE, auth)
        };
        let bytes = "application/octet-stream";
        let decide = |a: &Asking<'_>| code(decide(Access::Upload, client(&secrets), a));
        assert_eq!(decide(&upload(Some("Bearer s3cret"), bytes, None)), None);
        assert_eq!(
            decide(&upload(None, bytes, None)),
            Some(StatusCode::UNAUTHORIZED)
        );
        // A form (or JSON) is not an upload; another site's page is refused.
        for other in [
            "multipart/form-data; boundary=x",
            "text/plain",
            "application/json",
        ] {
            assert_eq!(
                decide(&upload(Some("Bearer s3cret"), other, None)),
                Some(StatusCode::UNSUPPORTED_MEDIA_TYPE),
                "{other}"
            );
        }
        assert_eq!(
            decide(&upload(
                Some("Bearer s3cret"),
                bytes,
                Some("http://evil.example")
            )),
            Some(StatusCode::FORBIDDEN)
        );
    }

    #[test]
    fn with_a_secret_the_token_decides_wherever_the_peer_is() {
        let secrets = [b"s3cret".to_vec(), b"previous".to_vec()];
        for access in [Access::Read, Access::Control, Access::Scrape] {
            for peer in [LOOPBACK, REMOTE] {
                let decide = |auth| code(decide(access, client(&secrets), &asking(peer, auth)));
                // Within a rotation's window, the previous secret passes too.
                assert_eq!(decide(Some("Bearer previous")), None);
                assert_eq!(decide(Some("Bearer s3cret")), None);
                assert_eq!(decide(None), Some(StatusCode::UNAUTHORIZED));
                assert_eq!(decide(Some("Bearer wrong")), Some(StatusCode::FORBIDDEN));
                assert_eq!(decide(Some("Basic s3cret")), Some(StatusCode::UNAUTHORIZED));
            }
        }
        // Health and the pages stay open.
        for access in [Access::Open, Access::Page, Access::Login] {
            assert_eq!(
                code(decide(access, client(&secrets), &asking(REMOTE, None))),
                None
            );
        }
    }

    #[test]
    fn the_scrape_token_opens_the_metrics_and_nothing_else() {
        let secrets = [b"client".to_vec()];
        let both = Secrets {
            client: Some(&secrets),
            scrape: Some(b"scrape"),
        };
        let scrape = asking(REMOTE, Some("Bearer scrape"));
        assert_eq!(code(decide(Access::Scrape, both, &scrape)), None);
        assert_eq!(
            code(decide(Access::Read, both, &scrape)),
            Some(StatusCode::FORBIDDEN)
        );
        let client = asking(REMOTE, Some("Bearer client"));
        assert_eq!(code(decide(Access::Scrape, both, &client)), None);
    }

    #[test]
    fn a_session_proves_the_secret_until_it_ends_or_the_secret_goes() {
        let secrets = [b"s3cret".to_vec()];
        let cookie = Session::issue(b"s3cret", NOW);
        let with = |cookie: &str, now: u64, secrets: &[Vec<u8>]| {
            let asking = Asking {
                session: Some(cookie),
                now,
                ..asking(REMOTE, None)
            };
            code(decide(Access::Control, client(secrets), &asking))
        };
        assert_eq!(with(&cookie, NOW, &secrets), None);
        assert_eq!(with(&cookie, NOW + SESSION_SECONDS - 1, &secrets), None);
        assert_eq!(
            with(&cookie, NOW + SESSION_SECONDS, &secrets),
            Some(StatusCode::UNAUTHORIZED)
        );
        // Another secret (after a rotation's window) ends it.
        assert_eq!(
            with(&cookie, NOW, &[b"new".to_vec()]),
            Some(StatusCode::UNAUTHORIZED)
        );
        // A forged or stretched expiry fails the MAC.
        let (expiry, mac) = cookie.split_once('.').unwrap();
        let later = format!("{}.{mac}", expiry.parse::<u64>().unwrap() - 1);
        assert_eq!(with(&later, NOW, &secrets), Some(StatusCode::UNAUTHORIZED));
        for junk in ["", ".", "x.y", "1.zz", &format!("{expiry}.")] {
            assert_eq!(with(junk, NOW, &secrets), Some(StatusCode::UNAUTHORIZED));
        }
        // A cookie from before a clock jump of more than a session is refused.
        let far = Session::issue(b"s3cret", NOW + 10 * SESSION_SECONDS);
        assert_eq!(with(&far, NOW, &secrets), Some(StatusCode::UNAUTHORIZED));
    }

    #[test]
    fn cross_site_requests_are_refused() {
        let form = Asking {
            content_type: Some("application/x-www-form-urlencoded"),
            ..asking(LOOPBACK, None)
        };
        let none = Secrets::default();
        for access in [Access::Control, Access::Login] {
            assert_eq!(
                code(decide(access, none, &form)),
                Some(StatusCode::UNSUPPORTED_MEDIA_TYPE)
            );
            let other = Asking {
                origin: Some("http://evil.example"),
                ..asking(LOOPBACK, None)
            };
            assert_eq!(
                code(decide(access, none, &other)),
                Some(StatusCode::FORBIDDEN)
            );
            let same = Asking {
                origin: Some("https://farm:8080"),
                content_type: Some("application/json; charset=utf-8"),
                ..asking(LOOPBACK, None)
            };
            assert_eq!(code(decide(access, none, &same)), None);
        }
    }

    #[test]
    fn cookies_are_named_per_port_and_found_among_others() {
        assert_eq!(cookie_name(Some("render-1:9090")), "tessera_session_9090");
        assert_eq!(cookie_name(Some("[::1]:80")), "tessera_session_80");
        assert_eq!(cookie_name(Some("render-1")), "tessera_session");
        assert_eq!(cookie_name(None), "tessera_session");
        let header = "a=1; tessera_session_9090=123.ab; tessera_session_9091=x";
        assert_eq!(
            session_cookie(header, "tessera_session_9090"),
            Some("123.ab")
        );
        assert_eq!(session_cookie(header, "tessera_session"), None);
        let set = set_cookie("tessera_session_9090", Some("1.ab"), true);
        assert!(set.contains("HttpOnly") && set.contains("SameSite=Strict"));
        assert!(set.ends_with("; Secure"));
        assert!(!set_cookie("n", None, false).contains("Secure"));
        assert!(set_cookie("n", None, false).contains("Max-Age=0"));
    }

    #[test]
    fn secrets_compare_equal_only_when_equal() {
        assert!(same_secret(b"abc", b"abc"));
        assert!(!same_secret(b"abc", b"abd"));
        assert!(!same_secret(b"abc", b"abcd"));
        assert!(!same_secret(b"", b"abc"));
    }
}
