//! The rules a coordinator's settings must follow before it accepts anyone: the
//! secrets must differ, a coordinator that other machines can reach must ask both
//! roles for proof, and an HTTP side that other machines can reach must ask for the
//! client secret over TLS, unless its operator says otherwise in so many words.

use std::fmt;
use std::net::SocketAddr;

use thiserror::Error;

use crate::server::Config;

/// Settings under which peers could do what their role does not allow. The messages
/// name the command line's flags, which is where an operator fixes them.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
pub enum Unsafe {
    /// A client's credential would also let it join as a worker, and render tiles.
    #[error(
        "the worker token and the client token are the same secret, so any client could \
         join as a worker: give two different secrets (e.g. each from `openssl rand \
         -hex 32`)"
    )]
    SameSecret,
    /// Anyone who can reach the address could submit jobs or pose as a worker.
    #[error(
        "refusing to listen on {listen} without {missing}: anyone who can reach it could \
         submit jobs or pose as a worker. Give --worker-token-file FILE and \
         --client-token-file FILE (or pass --insecure to accept peers without proof)"
    )]
    Unproven {
        listen: SocketAddr,
        missing: MissingTokens,
    },
    /// The scrape token opens the metrics only; equal to a role's secret it would
    /// hand that role's rights to the monitoring system.
    #[error(
        "the scrape token is the same secret as the {role} token: give the metrics a \
         secret of their own (e.g. from `openssl rand -hex 32`)"
    )]
    ScrapeIsRoleSecret { role: &'static str },
    /// Anyone who can reach the HTTP address could read every job and image.
    #[error(
        "refusing to serve HTTP on {http} without a client token: anyone who can reach it \
         could see every job, image and worker. Give --client-token-file FILE, bind --http \
         to 127.0.0.1 (or pass --insecure)"
    )]
    OpenHttp { http: SocketAddr },
    /// The client secret, scenes and images would cross the network in clear.
    #[error(
        "refusing to serve HTTP on {http} without TLS: the client secret, scenes and images \
         would cross the network in clear. Give --tls-auto (or --tls-cert and --tls-key): \
         the HTTP side then serves HTTPS with the same certificate; or bind --http to \
         127.0.0.1 (or pass --http-insecure)"
    )]
    PlainHttp { http: SocketAddr },
}

/// Which roles' tokens a coordinator lacks.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MissingTokens {
    Both,
    Worker,
    Client,
}

impl fmt::Display for MissingTokens {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            MissingTokens::Both => "a token for workers and one for clients",
            MissingTokens::Worker => "a token for workers",
            MissingTokens::Client => "a token for clients",
        })
    }
}

impl Config {
    /// Checks the secrets against each other and against the addresses listened on.
    /// On a loopback address only this machine's users can connect, so no token is
    /// needed there; elsewhere both roles need one, unless `insecure` accepts the
    /// roles without a token as they are. An HTTP address elsewhere needs the client
    /// token (or `insecure`) and TLS (or `http_insecure`): `tls` says whether the
    /// coordinator will serve it, since its certificate is read (or made) only once
    /// these checks pass.
    pub fn check_security(
        &self,
        insecure: bool,
        http_insecure: bool,
        tls: bool,
    ) -> Result<(), Unsafe> {
        let (worker, client) = (&self.worker_secret, &self.client_secret);
        if worker.is_some() && worker == client {
            return Err(Unsafe::SameSecret);
        }
        if let Some(scrape) = &self.metrics_secret {
            for (role, secret) in [("worker", worker), ("client", client)] {
                if secret.as_ref() == Some(scrape) {
                    return Err(Unsafe::ScrapeIsRoleSecret { role });
                }
            }
        }
        if let Some(http) = self.http.filter(|h| !h.ip().is_loopback()) {
            if client.is_none() && !insecure {
                return Err(Unsafe::OpenHttp { http });
            }
            if !tls && !http_insecure {
                return Err(Unsafe::PlainHttp { http });
            }
        }
        let missing = match (worker.is_some(), client.is_some()) {
            (true, true) => return Ok(()),
            (false, false) => MissingTokens::Both,
            (false, true) => MissingTokens::Worker,
            (true, false) => MissingTokens::Client,
        };
        if self.listen.ip().is_loopback() || insecure {
            return Ok(());
        }
        Err(Unsafe::Unproven {
            listen: self.listen,
            missing,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn config(listen: &str, worker: Option<&str>, client: Option<&str>) -> Config {
        let mut config = Config::new(listen.parse().unwrap(), "unused".into());
        config.worker_secret = worker.map(|s| s.as_bytes().to_vec());
        config.client_secret = client.map(|s| s.as_bytes().to_vec());
        config
    }

    #[test]
    fn loopback_needs_no_token() {
        for listen in ["127.0.0.1:7878", "[::1]:0"] {
            assert_eq!(
                config(listen, None, None).check_security(false, false, false),
                Ok(())
            );
            assert_eq!(
                config(listen, Some("w"), None).check_security(false, false, false),
                Ok(())
            );
        }
    }

    #[test]
    fn another_address_needs_both_tokens_or_insecure() {
        let error = |worker, client| {
            config("0.0.0.0:7878", worker, client)
                .check_security(false, false, false)
                .unwrap_err()
                .to_string()
        };
        assert_eq!(
            error(None, None),
            "refusing to listen on 0.0.0.0:7878 without a token for workers and one for \
             clients: anyone who can reach it could submit jobs or pose as a worker. Give \
             --worker-token-file FILE and --client-token-file FILE (or pass --insecure to \
             accept peers without proof)"
        );
        assert!(error(None, Some("c")).contains(" without a token for workers: "));
        assert!(error(Some("w"), None).contains(" without a token for clients: "));
        let both = config("10.1.2.3:7878", Some("w"), Some("c"));
        assert_eq!(both.check_security(false, false, false), Ok(()));
        let open = config("0.0.0.0:7878", None, Some("c"));
        assert_eq!(open.check_security(true, false, false), Ok(()));
    }

    #[test]
    fn an_http_side_others_reach_needs_the_client_token_and_tls() {
        let mut farm = config("10.1.2.3:7878", Some("w"), Some("c"));
        farm.http = Some("127.0.0.1:9090".parse().unwrap());
        assert_eq!(farm.check_security(false, false, false), Ok(()));
        let http: SocketAddr = "0.0.0.0:9090".parse().unwrap();
        farm.http = Some(http);
        assert_eq!(
            farm.check_security(false, false, false),
            Err(Unsafe::PlainHttp { http })
        );
        assert_eq!(farm.check_security(false, true, false), Ok(()));
        assert_eq!(farm.check_security(false, false, true), Ok(()));
        assert!(Unsafe::PlainHttp { http }
            .to_string()
            .starts_with("refusing to serve HTTP on 0.0.0.0:9090 without TLS: "));
        let mut open = config("127.0.0.1:7878", None, None);
        open.http = Some(http);
        assert_eq!(
            open.check_security(false, true, false),
            Err(Unsafe::OpenHttp { http })
        );
        assert_eq!(open.check_security(true, true, false), Ok(()));
    }

    #[test]
    fn the_scrape_token_is_a_secret_of_its_own() {
        let mut farm = config("127.0.0.1:7878", Some("w"), Some("c"));
        farm.metrics_secret = Some(b"m".to_vec());
        assert_eq!(farm.check_security(false, false, false), Ok(()));
        farm.metrics_secret = Some(b"c".to_vec());
        assert_eq!(
            farm.check_security(false, false, false),
            Err(Unsafe::ScrapeIsRoleSecret { role: "client" })
        );
    }

    #[test]
    fn the_roles_secrets_must_differ_on_any_address() {
        for (listen, insecure) in [("127.0.0.1:7878", false), ("0.0.0.0:7878", true)] {
            let same = config(listen, Some("s"), Some("s"));
            assert_eq!(
                same.check_security(insecure, false, false),
                Err(Unsafe::SameSecret)
            );
        }
        assert_eq!(
            Unsafe::SameSecret.to_string(),
            "the worker token and the client token are the same secret, so any client could \
             join as a worker: give two different secrets (e.g. each from `openssl rand -hex \
             32`)"
        );
    }
}
