//! The files a scene names, on a farm of real processes: an upload that resumes where
//! it stopped across a coordinator killed and restarted, bytes that are not what their
//! sender claimed refused and not kept, and a worker whose cache keeps a file across
//! its restarts fetching it once. Every image is byte for byte `tessera render`'s.

use std::path::Path;
use std::time::Duration;

use coordinator::client::{Client, LocalFile};
use protocol::{AssetKey, AssetRef, JobSpec, Overrides};
use tempfile::TempDir;
use transport::Endpoint;

use crate::support::{
    assert_job_image, http_get_text, metric_value, path_str, restart_coordinator, shared,
    start_coordinator_with_http, start_restartable_coordinator, start_worker, start_worker_with,
    submit_scene, wait_done, wait_for_workers, write_mesh_scene, REGISTER_TIMEOUT,
};

const JOB_TIMEOUT: Duration = Duration::from_secs(60);
const SMALL: &[&str] = &["--width", "160", "--height", "120"];

/// A mesh of more than two chunks: a strip of `quads` quads, written as OBJ text.
fn write_big_mesh(dir: &Path, quads: usize) -> Vec<u8> {
    let mut obj = String::new();
    for i in 0..=quads {
        let x = -2.0 + 4.0 * i as f64 / quads as f64;
        obj.push_str(&format!(
            "v {x:.6} -1.000000 0.500000\nv {x:.6} 1.000000 0.500000\n"
        ));
    }
    for i in 0..quads {
        let a = 2 * i + 1;
        obj.push_str(&format!(
            "f {} {} {}\nf {} {} {}\n",
            a,
            a + 2,
            a + 1,
            a + 1,
            a + 2,
            a + 3
        ));
    }
    std::fs::write(dir.join("big.obj"), &obj).unwrap();
    let scene = r#"{"camera": {"position": "0 0 -5", "look_at": "0 0 0"},
        "lights": [{"position": "0 3 -4", "color": "1 1 1"}],
        "objects": [{"type": "mesh", "file": "big.obj", "color": "0.4 0.8 0.5 0"}]}"#;
    std::fs::write(dir.join("big.json"), scene).unwrap();
    obj.into_bytes()
}

fn key_of(bytes: &[u8]) -> AssetKey {
    let id = assets::AssetId::of(bytes);
    AssetKey {
        sha256: id.sha256,
        size: id.size,
    }
}

fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap()
}

#[test]
fn an_upload_resumes_across_a_coordinator_restart_and_a_lie_is_refused() {
    let _turn = shared();
    let dir = TempDir::new().unwrap();
    let d = dir.path();
    let bytes = write_big_mesh(d, 40_000);
    assert!(
        bytes.len() > 2 * protocol::ASSET_CHUNK,
        "{} bytes",
        bytes.len()
    );
    let key = key_of(&bytes);
    let file = LocalFile {
        asset: AssetRef {
            name: "big.obj".into(),
            key,
        },
        path: d.join("big.obj"),
    };
    let (mut coordinator, addr) = start_restartable_coordinator(d);
    let rt = runtime();
    // The first chunk, then the coordinator is killed.
    rt.block_on(async {
        let mut client = Client::connect(&Endpoint::plain(&addr)).await.unwrap();
        let lacking = client.lacking(vec![key]).await.unwrap();
        assert_eq!(lacking.len(), 1);
        assert_eq!(lacking[0].received, 0);
        let first = protocol::AssetRequest::Upload {
            key,
            offset: 0,
            bytes: bytes[..protocol::ASSET_CHUNK].to_vec(),
        };
        client
            .request(protocol::ClientRequest::Assets(first))
            .await
            .unwrap();
    });
    coordinator.kill9();
    let _coordinator = restart_coordinator(d, &addr, &[]);
    let job = rt.block_on(async {
        let mut client = Client::connect(&Endpoint::plain(&addr)).await.unwrap();
        // What was acknowledged survived: the upload resumes after the first chunk.
        let lacking = client.lacking(vec![key]).await.unwrap();
        assert_eq!(lacking[0].received, protocol::ASSET_CHUNK as u64);
        client.upload(&file, lacking[0].received).await.unwrap();
        assert!(client.lacking(vec![key]).await.unwrap().is_empty());

        // Bytes that are not what their sender claims: refused, nothing kept.
        let claimed = key_of(b"the bytes claimed");
        let lie = protocol::AssetRequest::Upload {
            key: claimed,
            offset: 0,
            bytes: b"other bytes, same len".to_vec()[..claimed.size as usize].to_vec(),
        };
        let refused = client
            .request(protocol::ClientRequest::Assets(lie))
            .await
            .expect_err("a lying upload is refused")
            .to_string();
        assert!(refused.contains("not stored"), "{refused}");
        assert!(!refused.contains('\n'), "{refused}");
        let lacking = client.lacking(vec![claimed]).await.unwrap();
        assert_eq!(lacking[0].received, 0, "nothing of the lie was kept");

        let scene = std::fs::read_to_string(d.join("big.json")).unwrap();
        let spec = JobSpec {
            scene,
            overrides: Overrides {
                width: Some(160),
                height: Some(120),
                ..Overrides::default()
            },
            priority: 0,
            verification: Default::default(),
            time_limit_ms: None,
            name: "big".into(),
            submitter: "test".into(),
            frame: 1,
            frames: None,
            assets: Vec::new(),
            after: Vec::new(),
            require: Vec::new(),
        };
        client
            .submit_with_files(spec, std::slice::from_ref(&file))
            .await
            .unwrap()
    });
    let _worker = start_worker(d, &addr, "w1");
    wait_done(d, &addr, job, JOB_TIMEOUT);
    let scene = d.join("big.json");
    assert_job_image(d, &addr, job, path_str(&scene), SMALL, "a resumed upload");
}

#[test]
fn a_worker_with_a_cache_fetches_a_file_once_across_its_restarts() {
    let _turn = shared();
    let dir = TempDir::new().unwrap();
    let d = dir.path();
    let (_coordinator, addr, http) = start_coordinator_with_http(d, &[]);
    let cache = d.join("cache");
    let cache_arg = ["--cache-dir", path_str(&cache)];
    let scene = write_mesh_scene(d);
    let scene = path_str(&scene);
    let sent = || {
        metric_value(
            &http_get_text(&http, "/metrics"),
            "tessera_asset_sent_bytes_total",
        )
        .expect("the metric of bytes sent")
    };
    let mut before = 0.0;
    for (round, tile) in ["16", "24"].into_iter().enumerate() {
        let worker = start_worker_with(d, &addr, "cached", &cache_arg);
        wait_for_workers(d, &addr, 1, REGISTER_TIMEOUT);
        let args = [&["--tile", tile][..], SMALL].concat();
        let job = submit_scene(d, &addr, scene, &args);
        wait_done(d, &addr, job, JOB_TIMEOUT);
        assert_job_image(d, &addr, job, scene, &args, &format!("round {round}"));
        let now = sent();
        if round == 0 {
            assert!(now > 0.0, "the worker fetched nothing");
            shows_the_files(d, &addr, &http, job);
        } else {
            assert_eq!(now, before, "the restarted worker fetched the file again");
        }
        before = now;
        drop(worker);
        // The coordinator sees the worker go before the next one joins.
        crate::support::poll("the worker to leave", REGISTER_TIMEOUT, || {
            crate::support::try_workers(d, &addr)
                .is_some_and(|w| w.is_empty())
                .then_some(())
        });
    }
    assert!(
        std::fs::read_dir(&cache).unwrap().next().is_some(),
        "the cache directory is empty"
    );
}

/// `tessera status`, `tessera workers` and the status page show the job's files, the
/// worker's cache and the coordinator's store (a worker reports its cache at most a
/// second after it changed).
fn shows_the_files(d: &Path, addr: &str, http: &str, job: u64) {
    let size = std::fs::metadata(d.join("cube.obj")).unwrap().len();
    let status = crate::support::status_json(d, addr, job);
    assert_eq!(
        status["assets"],
        serde_json::json!({ "files": 1, "bytes": size }),
        "{status}"
    );
    let line = crate::support::ok(
        crate::support::client(d, addr, &["status", &job.to_string()]),
        "status",
    );
    assert!(line.stdout.contains(", 1 file ("), "{}", line.stdout);
    let cache = crate::support::poll("the worker's cache report", REGISTER_TIMEOUT, || {
        let workers = crate::support::try_workers(d, addr)?;
        let cache = workers.first()?["cache"].clone();
        (cache["files"] == 1 && cache["bytes"] == size).then_some(cache)
    });
    assert!(cache["capacity"].as_u64().unwrap() > size, "{cache}");
    assert_eq!(cache["fetching"], 0, "{cache}");
    assert!(cache["geometry_triangles"].as_u64().unwrap() > 0, "{cache}");
    assert_eq!(cache["problem"], serde_json::Value::Null, "{cache}");
    let listing = crate::support::ok(crate::support::client(d, addr, &["workers"]), "workers");
    assert!(
        listing.stdout.contains(", cache 1 file "),
        "{}",
        listing.stdout
    );
    let page: serde_json::Value =
        serde_json::from_str(&http_get_text(http, "/api/status")).unwrap();
    assert_eq!(page["store"]["files"], 1, "{page}");
    assert_eq!(page["store"]["bytes"], size, "{page}");
    assert_eq!(page["jobs"][0]["assets"]["files"], 1, "{page}");
    assert_eq!(page["workers"][0]["cache"]["files"], 1, "{page}");
}

/// A relay corrupting the first two chunks of files on their way to the worker: the
/// worker finds each file wrong by its hash, fetches it again, and renders the job
/// exactly; the network's fault quarantines nobody.
#[test]
fn file_chunks_corrupted_on_the_way_are_fetched_again_and_nobody_is_quarantined() {
    let _turn = shared();
    let dir = TempDir::new().unwrap();
    let d = dir.path();
    let (_coordinator, addr, http) = start_coordinator_with_http(d, &[]);
    let relay = crate::support::flip_relay::FlipRelay::start_flipping_files(&addr, 2);
    let _worker = start_worker(d, relay.address(), "behind");
    wait_for_workers(d, &addr, 1, REGISTER_TIMEOUT);
    let scene = write_mesh_scene(d);
    let scene = path_str(&scene);
    let job = submit_scene(d, &addr, scene, SMALL);
    wait_done(d, &addr, job, JOB_TIMEOUT);
    assert_job_image(d, &addr, job, scene, SMALL, "files corrupted on the way");
    assert_eq!(relay.files_flipped(), 2, "the relay corrupted no chunk");
    let metrics = http_get_text(&http, "/metrics");
    let size = std::fs::metadata(d.join("cube.obj")).unwrap().len() as f64;
    assert_eq!(
        metric_value(&metrics, "tessera_asset_sent_bytes_total"),
        Some(3.0 * size),
        "the file was not fetched three times"
    );
    assert_eq!(
        metric_value(&metrics, "tessera_workers_quarantined_total"),
        Some(0.0)
    );
}

/// An animated scene whose object is a mesh, every frame on a farm (`tessera up
/// --frames all`): the sequence is found from the scene read with its files, each
/// file travels once, and every frame is `tessera render --frames all`'s.
#[test]
fn an_animated_mesh_scene_renders_every_frame_as_render_does() {
    let _turn = shared();
    let dir = TempDir::new().unwrap();
    let d = dir.path();
    write_mesh_scene(d);
    let scene = r#"{"lights": [{"position": "-7 10 -10", "color": "1 1 1"}],
        "objects": [{"type": "mesh", "file": "cube.obj", "color": "0.85 0.3 0.25 0"},
                    {"type": "plan", "normal": "0 1 0", "distance": -1, "color": "0.5 0.25 0.2 2"}],
        "camera": {"position": "0 2.5 -8", "look_at": "0 0 0"},
        "animation": {"frames": 4, "fps": 24, "tracks": [{"target": "camera.position",
            "interpolation": "linear",
            "keys": [{"frame": 1, "value": "0 2.5 -8"}, {"frame": 4, "value": "3 2.5 -7"}]}]}}"#;
    std::fs::write(d.join("anim.json"), scene).unwrap();
    let anim = path_str(&d.join("anim.json")).to_owned();
    let run = |args: &[&str]| {
        let all = [args, SMALL].concat();
        crate::support::ok(
            crate::support::tessera(d, &all, JOB_TIMEOUT),
            &format!("tessera {}", all.join(" ")),
        );
    };
    run(&[
        "render",
        &anim,
        "--frames",
        "all",
        "-o",
        path_str(&d.join("local")),
    ]);
    run(&[
        "up",
        &anim,
        "--frames",
        "all",
        "-o",
        path_str(&d.join("farm")),
    ]);
    for k in 1..=4 {
        let name = format!("frame_{k:04}.png");
        let local = std::fs::read(d.join("local").join(&name)).unwrap();
        let farm = std::fs::read(d.join("farm").join(&name))
            .unwrap_or_else(|e| panic!("the farm wrote no {name}: {e}"));
        assert!(local == farm, "{name} differs from tessera render's");
    }
}
