//! The coordinator's HTTP side as private as its protocol: every route of the route
//! table walked without, with a wrong and with the right secret, over plain HTTP and
//! over TLS, and the settings that would expose it refused at start.

use std::path::Path;
use std::time::Duration;

use coordinator::http::{routes, Access};
use tempfile::TempDir;

use super::{submit_and_wait, tokens, SMALL};
use crate::support::{
    assert_same_png, header, json_error, ok, one_error_line, path_str, poll, render_reference,
    scene_path, shared, start_coordinator, start_worker_with, tessera, Answer, Site,
};

/// Who may call each route, as this test expects it: a route added to the table
/// without a line here fails the walk, so that no route is added without a decision.
const EXPECTED: &[(&str, &str, Access)] = &[
    ("GET", "/healthz", Access::Open),
    ("GET", "/readyz", Access::Open),
    ("GET", "/", Access::Page),
    ("GET", "/studio", Access::Page),
    ("POST", "/api/login", Access::Login),
    ("POST", "/api/logout", Access::Login),
    ("GET", "/metrics", Access::Scrape),
    ("GET", "/api/status", Access::Read),
    ("GET", "/jobs/{id}/image.png", Access::Read),
    ("GET", "/api/jobs/{id}/events", Access::Read),
    ("GET", "/api/jobs/{id}/preview.gif", Access::Read),
    ("GET", "/api/jobs/{id}/frames/{file}", Access::Read),
    ("GET", "/api/studio/scene", Access::Read),
    ("GET", "/api/studio/stream", Access::Read),
    ("GET", "/api/v1/events", Access::Read),
    ("POST", "/api/jobs/{id}/{action}", Access::Control),
    ("POST", "/api/workers/{worker}/{action}", Access::Control),
    ("POST", "/api/studio/open", Access::Control),
    ("POST", "/api/studio/view", Access::Control),
    ("POST", "/api/studio/submit", Access::Control),
    ("POST", "/api/studio/archive", Access::Control),
    ("POST", "/api/studio/files", Access::Upload),
    ("GET", "/api/v1/openapi.json", Access::Page),
    ("GET", "/api/v1/jobs", Access::Read),
    ("POST", "/api/v1/jobs", Access::Control),
    ("GET", "/api/v1/jobs/{id}", Access::Read),
    ("GET", "/api/v1/jobs/{id}/wait", Access::Read),
    ("GET", "/api/v1/jobs/{id}/events", Access::Read),
    ("GET", "/api/v1/jobs/{id}/image.png", Access::Read),
    ("GET", "/api/v1/jobs/{id}/frames/{frame}", Access::Read),
    ("POST", "/api/v1/jobs/{id}/pause", Access::Control),
    ("POST", "/api/v1/jobs/{id}/resume", Access::Control),
    ("POST", "/api/v1/jobs/{id}/priority", Access::Control),
    ("POST", "/api/v1/jobs/{id}/cancel", Access::Control),
    ("POST", "/api/v1/jobs/{id}/retry", Access::Control),
    ("POST", "/api/v1/jobs/{id}/requeue", Access::Control),
    ("POST", "/api/v1/jobs/{id}/refine", Access::Control),
    ("POST", "/api/v1/jobs/{id}/delete", Access::Control),
    ("GET", "/api/v1/workers", Access::Read),
    ("POST", "/api/v1/workers/{worker}/drain", Access::Control),
    ("POST", "/api/v1/workers/{worker}/disable", Access::Control),
    ("POST", "/api/v1/workers/{worker}/enable", Access::Control),
    ("POST", "/api/v1/files/lacking", Access::Control),
    ("PUT", "/api/v1/files/{file}", Access::Upload),
    ("POST", "/api/v1/resolve", Access::Control),
];

const SCRAPE_TOKEN: &str = "5c3a0e9d8b7f6a5e4d3c2b1a0f9e8d7c";

/// A concrete request of a route: its path with the parameters filled in so that the
/// request, once allowed, changes nothing that matters (a job or worker that does not
/// exist, a studio request without a body), and the body a POST sends.
fn concrete(path: &str, job: u64) -> (String, &'static str) {
    // The API's job controls act on a job that does not exist (its reads on the job).
    let controlled = path.starts_with("/api/v1/jobs/{id}/")
        && !["wait", "events", "image.png", "{frame}"]
            .iter()
            .any(|read| path.ends_with(read));
    let job = if controlled { 987_654 } else { job };
    let path = path
        .replace("/api/jobs/{id}/{action}", "/api/jobs/987654/pause")
        .replace("{frame}", "1")
        .replace("{file}", &format!("{}-1?offset=0", "0".repeat(64)))
        .replace("{id}", &job.to_string())
        .replace("{worker}/{action}", "nobody/drain")
        .replace("{worker}", "nobody")
        .replace("{file}", "1.png");
    let path = match path.as_str() {
        "/api/studio/stream" => "/api/studio/stream?session=none".to_owned(),
        // What is kept, then the end: an answer read to its end.
        "/api/v1/events" => "/api/v1/events?after=0&follow=false".to_owned(),
        // Not a mesh: stored nowhere.
        "/api/studio/files" => "/api/studio/files?name=none.obj".to_owned(),
        _ => path,
    };
    (path, "{}")
}

/// One request of `route` with `auth` headers: JSON, or raw bytes for an upload.
fn ask(site: &Site, method: &str, path: &str, body: &str, auth: &[(&str, &str)]) -> Answer {
    let kind = if path.starts_with("/api/studio/files") || method == "PUT" {
        "application/octet-stream"
    } else {
        "application/json"
    };
    let mut headers = vec![("Content-Type", kind)];
    headers.extend_from_slice(auth);
    let body = if method == "POST" || method == "PUT" {
        body.as_bytes()
    } else {
        b""
    };
    site.request(method, path, &headers, body, Duration::from_secs(20))
        .unwrap_or_else(|| panic!("no answer to {method} {path} from {}", site.addr))
}

/// Walks every route of the table on `site`, checking each answer against its access.
fn walk(site: &Site, job: u64, client_token: &str, what: &str) {
    let right = format!("Bearer {client_token}");
    let scrape = format!("Bearer {SCRAPE_TOKEN}");
    let none: &[(&str, &str)] = &[];
    let wrong = [("Authorization", "Bearer not-the-secret")];
    let with_right = [("Authorization", right.as_str())];
    let with_scrape = [("Authorization", scrape.as_str())];
    // A session, as the page's login form makes it.
    let login = ask(
        site,
        "POST",
        "/api/login",
        &format!("{{\"secret\": \"{client_token}\"}}"),
        none,
    );
    assert_eq!(login.status, 204, "{what}: login: {:?}", login.body);
    let set_cookie = header(&login.head, "set-cookie").expect("a session cookie");
    assert!(
        set_cookie.contains("httponly") && set_cookie.contains("samesite=strict"),
        "{what}: {set_cookie}"
    );
    assert_eq!(
        set_cookie.contains("; secure"),
        site.tls.is_some(),
        "{what}: Secure exactly over TLS: {set_cookie}"
    );
    // The answer's head is lowercased; the cookie's value is hex and digits.
    let cookie = set_cookie.split(';').next().unwrap().to_owned();
    let with_session = [("Cookie", cookie.as_str())];

    for route in routes() {
        let method = route.method.as_str();
        let (path, body) = concrete(route.path, job);
        let name = format!("{what}: {method} {path} ({})", route.access.as_str());
        let status = |auth: &[(&str, &str)]| ask(site, method, &path, body, auth).status;
        match route.access {
            Access::Open | Access::Page => {
                for auth in [none, &wrong[..], &with_right[..]] {
                    assert_eq!(status(auth), 200, "{name}");
                }
            }
            Access::Login => {
                let answer = ask(site, method, &path, body, none);
                assert!(
                    ![401, 403].contains(&answer.status),
                    "{name}: {}",
                    String::from_utf8_lossy(&answer.body)
                );
            }
            Access::Read | Access::Control | Access::Upload | Access::Scrape => {
                let refused = ask(site, method, &path, body, none);
                assert_eq!(refused.status, 401, "{name} without a secret");
                let line = json_error(&refused.body);
                assert!(line.contains("Authorization: Bearer"), "{name}: {line}");
                assert_eq!(status(&wrong), 403, "{name} with a wrong secret");
                for (auth, how) in [(&with_right, "the secret"), (&with_session, "a session")] {
                    let answer = ask(site, method, &path, body, auth);
                    assert!(
                        ![401, 403].contains(&answer.status),
                        "{name} with {how}: {} {}",
                        answer.status,
                        String::from_utf8_lossy(&answer.body)
                    );
                    let changes = matches!(route.access, Access::Control | Access::Upload);
                    if !changes && !path.contains("frames") {
                        assert!(
                            [200, 304, 404].contains(&answer.status),
                            "{name} with {how}: {}",
                            answer.status
                        );
                    }
                }
                let scraping = status(&with_scrape);
                match route.access {
                    Access::Scrape => assert_eq!(scraping, 200, "{name} with the scrape token"),
                    _ => assert_eq!(scraping, 403, "{name} with the scrape token"),
                }
            }
        }
    }
    // What the reads give is the farm's own: the job's image, with the secret only.
    let image = ask(
        site,
        "GET",
        &format!("/jobs/{job}/image.png"),
        "",
        &with_right,
    );
    assert_eq!(image.status, 200, "{what}: the image");
    assert!(image.body.starts_with(b"\x89PNG"), "{what}: a PNG");
    // Logging out empties the cookie.
    let out = ask(site, "POST", "/api/logout", "{}", &with_session);
    let cleared = header(&out.head, "set-cookie").expect("a cleared cookie");
    assert!(cleared.contains("max-age=0"), "{what}: {cleared}");
}

fn read_token(path: &Path) -> String {
    std::fs::read_to_string(path).unwrap().trim().to_owned()
}

#[test]
fn every_http_route_asks_for_what_its_row_says_over_plain_http_and_tls() {
    let _turn = shared();
    let listed: Vec<(String, String, Access)> = routes()
        .into_iter()
        .map(|r| (r.method.to_string(), r.path.to_owned(), r.access))
        .collect();
    let expected: Vec<(String, String, Access)> = EXPECTED
        .iter()
        .map(|&(m, p, a)| (m.to_owned(), p.to_owned(), a))
        .collect();
    for route in &listed {
        assert!(
            expected.contains(route),
            "{} {} ({}) is served but this test has no decision for it: add it to EXPECTED",
            route.0,
            route.1,
            route.2.as_str()
        );
    }
    for route in &expected {
        assert!(listed.contains(route), "{route:?} is no longer served");
    }

    let dir = TempDir::new().unwrap();
    let d = dir.path();
    let (worker_token, client_token) = tokens(d);
    let scrape_token = d.join("metrics.token");
    std::fs::write(&scrape_token, format!("{SCRAPE_TOKEN}\n")).unwrap();
    let secret = read_token(&client_token);
    for tls in [false, true] {
        let what = if tls { "over TLS" } else { "plain" };
        let run = d.join(what);
        std::fs::create_dir_all(&run).unwrap();
        let http = format!("127.0.0.1:{}", crate::support::free_port());
        let mut args = vec![
            "--http",
            &http,
            "--worker-token-file",
            path_str(&worker_token),
            "--client-token-file",
            path_str(&client_token),
            "--metrics-token-file",
            path_str(&scrape_token),
        ];
        if tls {
            args.push("--tls-auto");
        }
        let data = run.join("data");
        let (mut coordinator, addr) =
            start_coordinator(&run, &data, "127.0.0.1:0", &args, "coordinator.log");
        let mut auth = vec!["--token-file", path_str(&client_token)];
        let fingerprint;
        if tls {
            let out = tessera(
                &run,
                &[
                    "coordinator",
                    "--data",
                    path_str(&data),
                    "--tls-auto",
                    "--print-fingerprint",
                ],
                Duration::from_secs(30),
            );
            fingerprint = out.stdout.trim().to_owned();
            auth.extend(["--tls-fingerprint", fingerprint.as_str()]);
        }
        let mut worker_auth = vec!["--token-file", path_str(&worker_token)];
        worker_auth.extend(auth.iter().skip(2));
        let _worker = start_worker_with(&run, &addr, "w", &worker_auth);
        let out = submit_and_wait(&run, &addr, "job.png", &auth);
        let reference = render_reference(&run, &scene_path("seed.json"), "reference.png", SMALL);
        assert_same_png(&out, &reference, what);
        let site = if tls {
            Site::https(&http, &data.join("tls").join("cert.pem"))
        } else {
            Site::plain(&http)
        };
        walk(&site, 1, &secret, what);
        if !tls {
            // A new scrape token, reloaded on SIGHUP as the others are: the old one
            // no longer opens the metrics.
            std::fs::write(&scrape_token, "b7e4a1c8d2f5e9a3c6b0d4f8e2a5c9b1\n").unwrap();
            coordinator.signal("HUP");
            let scrape = |token: &str| {
                let auth = format!("Bearer {token}");
                ask(
                    &site,
                    "GET",
                    "/metrics",
                    "",
                    &[("Authorization", auth.as_str())],
                )
                .status
            };
            poll("the new scrape token", Duration::from_secs(10), || {
                (scrape("b7e4a1c8d2f5e9a3c6b0d4f8e2a5c9b1") == 200).then_some(())
            });
            assert_eq!(
                scrape(SCRAPE_TOKEN),
                403,
                "the old scrape token after the reload"
            );
            std::fs::write(&scrape_token, format!("{SCRAPE_TOKEN}\n")).unwrap();
        }
        if tls {
            // Plain HTTP to the TLS port is told to use https://.
            let plain = Site::plain(&http)
                .request("GET", "/api/status", &[], b"", Duration::from_secs(10))
                .expect("a plain answer");
            assert_eq!(plain.status, 400);
            assert_eq!(
                json_error(&plain.body),
                format!("this port speaks HTTPS: use https://{http}/api/status")
            );
            // Except health, for supervisors that cannot speak TLS.
            for path in ["/healthz", "/readyz"] {
                let health = Site::plain(&http)
                    .request("GET", path, &[], b"", Duration::from_secs(10))
                    .expect("a plain answer");
                assert_eq!(health.status, 200, "plain {path}");
            }
        }
        drop(coordinator);
    }
}

#[test]
fn an_http_side_other_machines_reach_needs_tls_and_the_client_secret() {
    let _turn = shared();
    let dir = TempDir::new().unwrap();
    let d = dir.path();
    let (worker_token, client_token) = tokens(d);
    // A coordinator whose HTTP side listens on every address, with `extra` flags.
    let exposed = |extra: &[&str]| {
        let mut args = vec![
            "coordinator",
            "--listen",
            "127.0.0.1:0",
            "--data",
            "data",
            "--http",
            "0.0.0.0:0",
        ];
        args.extend_from_slice(extra);
        tessera(d, &args, Duration::from_secs(30))
    };
    let refusal =
        |extra: &[&str]| one_error_line(&exposed(extra), "a coordinator exposing its HTTP side");
    let secrets = [
        "--worker-token-file",
        path_str(&worker_token),
        "--client-token-file",
        path_str(&client_token),
    ];
    assert_eq!(
        refusal(&secrets),
        "error: refusing to serve HTTP on 0.0.0.0:0 without TLS: the client secret, scenes \
         and images would cross the network in clear. Give --tls-auto (or --tls-cert and \
         --tls-key): the HTTP side then serves HTTPS with the same certificate; or bind \
         --http to 127.0.0.1 (or pass --http-insecure)"
    );
    // With TLS the same settings pass: `--print-config` makes the start's checks
    // without binding anything.
    let mut accepted = vec!["--tls-auto", "--print-config"];
    accepted.extend_from_slice(&secrets);
    ok(
        exposed(&accepted),
        "--print-config of an HTTPS side with both tokens",
    );
    let line = refusal(&["--tls-auto", "--http-insecure"]);
    assert!(
        line.starts_with("error: refusing to serve HTTP on 0.0.0.0:0 without a client token: "),
        "{line}"
    );
    // The scrape token must be a secret of its own.
    let mut same = secrets.to_vec();
    same.extend(["--metrics-token-file", path_str(&client_token)]);
    let line = one_error_line(
        &tessera(
            d,
            &[
                &["coordinator", "--listen", "127.0.0.1:0", "--data", "data"][..],
                &same,
            ]
            .concat(),
            Duration::from_secs(30),
        ),
        "a scrape token equal to the client token",
    );
    assert!(
        line.contains("the scrape token is the same secret as the client token"),
        "{line}"
    );
}
