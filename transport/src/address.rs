//! A coordinator's address as its peers are given it: a host and a port, checked when
//! it is given, so that a forgotten port is one line saying so rather than a failure to
//! connect later.

use thiserror::Error;

/// The port a coordinator listens on for workers and clients unless told otherwise.
pub const DEFAULT_PORT: u16 = 7878;

/// The address a coordinator listens on, and its peers dial, unless told otherwise.
pub const DEFAULT_ADDRESS: &str = "127.0.0.1:7878";

/// An address that lacks a host or a port, or whose port is not a port. Each message
/// shows the form that would work, with the default port.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
pub enum AddressError {
    #[error("an IPv6 address needs its closing `]`")]
    UnclosedBracket,
    #[error("an IPv6 address goes in brackets with its port: [{text}]:{DEFAULT_PORT}")]
    UnbracketedIpv6 { text: String },
    #[error("no host: give HOST:PORT, for example 127.0.0.1:{DEFAULT_PORT}")]
    NoHost,
    #[error(
        "no port: give HOST:PORT, for example {host}:{DEFAULT_PORT} ({DEFAULT_PORT} is the \
         coordinator's default port)"
    )]
    NoPort { host: String },
    #[error("{port:?} is not a port number: give HOST:PORT, for example {host}:{DEFAULT_PORT}")]
    BadPort { host: String, port: String },
}

/// Checks that `text` is `HOST:PORT` (an IPv6 host in brackets, `[::1]:7878`) with a
/// port from 1 to 65535, and returns it trimmed. The host is not resolved: names are
/// looked up when the peer dials, and again when it reconnects.
pub fn parse_address(text: &str) -> Result<String, AddressError> {
    let text = text.trim();
    let (host, port) = if let Some(rest) = text.strip_prefix('[') {
        match rest.split_once(']') {
            Some((host, tail)) => (format!("[{host}]"), tail.strip_prefix(':')),
            None => return Err(AddressError::UnclosedBracket),
        }
    } else {
        match text.split_once(':') {
            None => (text.to_owned(), None),
            Some((host, port)) if !port.contains(':') => (host.to_owned(), Some(port)),
            Some(_) => {
                return Err(AddressError::UnbracketedIpv6 {
                    text: text.to_owned(),
                })
            }
        }
    };
    if host.is_empty() {
        return Err(AddressError::NoHost);
    }
    match port {
        None => Err(AddressError::NoPort { host }),
        Some(p) if p.parse::<u16>().is_ok_and(|p| p > 0) => Ok(text.to_owned()),
        Some(p) => Err(AddressError::BadPort {
            host,
            port: p.to_owned(),
        }),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_default_address_has_the_default_port() {
        assert_eq!(
            DEFAULT_ADDRESS.rsplit_once(':').map(|(_, port)| port),
            Some(DEFAULT_PORT.to_string().as_str())
        );
        assert_eq!(
            parse_address(DEFAULT_ADDRESS).as_deref(),
            Ok(DEFAULT_ADDRESS)
        );
    }

    #[test]
    fn an_address_is_a_host_and_a_port() {
        assert_eq!(
            parse_address(" farm.example:9000 ").as_deref(),
            Ok("farm.example:9000")
        );
        assert_eq!(parse_address("[::1]:7878").as_deref(), Ok("[::1]:7878"));
        assert_eq!(
            parse_address("10.0.0.1:65535").as_deref(),
            Ok("10.0.0.1:65535")
        );
    }

    #[test]
    fn a_bad_address_says_what_would_work() {
        let error = |text: &str| parse_address(text).unwrap_err().to_string();
        assert_eq!(
            error("127.0.0.1"),
            "no port: give HOST:PORT, for example 127.0.0.1:7878 (7878 is the coordinator's \
             default port)"
        );
        assert_eq!(
            error("[::1]"),
            "no port: give HOST:PORT, for example [::1]:7878 (7878 is the coordinator's \
             default port)"
        );
        assert_eq!(
            error(":7878"),
            "no host: give HOST:PORT, for example 127.0.0.1:7878"
        );
        assert_eq!(
            error("host:http"),
            "\"http\" is not a port number: give HOST:PORT, for example host:7878"
        );
        assert_eq!(
            error("host:0"),
            "\"0\" is not a port number: give HOST:PORT, for example host:7878"
        );
        assert_eq!(
            error("host:65536"),
            "\"65536\" is not a port number: give HOST:PORT, for example host:7878"
        );
        assert_eq!(
            error("::1"),
            "an IPv6 address goes in brackets with its port: [::1]:7878"
        );
        assert_eq!(error("[::1:7878"), "an IPv6 address needs its closing `]`");
    }
}
