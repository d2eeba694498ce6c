//! Section 8's shapes on a farm. Triangles and boxes need no file; a mesh's file is on
//! the client's machine, and travels with the job by content: `tessera submit` and
//! `tessera up` upload what the coordinator lacks, workers fetch it, and the image is
//! byte for byte `tessera render`'s. A scene naming a mesh sent without its files is
//! refused by the coordinator in the loader's own line, and it serves the next job
//! unharmed.

use std::time::{Duration, Instant};

use coordinator::client::Client;
use protocol::{JobSpec, Overrides};
use tempfile::TempDir;
use transport::Endpoint;

use crate::support::{
    assert_job_image, assert_same_png, client, entries, ok, path_str, render_reference, shared,
    start_coordinator_in, start_worker, submit_scene, tessera, tessera_env, wait_done,
    wait_for_workers, write_mesh_scene, write_shapes_scene, LOADER_REFUSAL, REGISTER_TIMEOUT,
};

const JOB_TIMEOUT: Duration = Duration::from_secs(60);
const SMALL: &[&str] = &["--width", "200", "--height", "150"];

#[test]
fn a_farm_renders_triangles_boxes_and_meshes_as_render_does() {
    let _turn = shared();
    let dir = TempDir::new().unwrap();
    let d = dir.path();
    let (mut coordinator, addr) = start_coordinator_in(d);
    let _workers = [start_worker(d, &addr, "w1"), start_worker(d, &addr, "w2")];
    wait_for_workers(d, &addr, 2, REGISTER_TIMEOUT);
    let mesh_scene = write_mesh_scene(d);
    let mesh_scene = path_str(&mesh_scene);

    // `submit`: the mesh's file is uploaded, fetched by the workers, and the image is
    // `tessera render`'s; a second job on the same file uploads nothing.
    for args in [&["--tile", "16"][..], &["--tile", "32", "--aa", "3"][..]] {
        let args = [args, SMALL].concat();
        let job = submit_scene(d, &addr, mesh_scene, &args);
        wait_done(d, &addr, job, JOB_TIMEOUT);
        assert_job_image(
            d,
            &addr,
            job,
            mesh_scene,
            &args,
            &format!("a mesh, {args:?}"),
        );
    }

    // The coordinator, sent the scene's text by another client without its files:
    // refused in one line, the renderer's own.
    let text = std::fs::read_to_string(mesh_scene).unwrap();
    let refused = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap()
        .block_on(async {
            let mut client = Client::connect(&Endpoint::plain(&addr)).await.unwrap();
            client
                .submit(JobSpec {
                    scene: text,
                    overrides: Overrides::default(),
                    priority: 0,
                    verification: Default::default(),
                    time_limit_ms: None,
                    name: "cube".into(),
                    submitter: "test".into(),
                    frame: 1,
                    frames: None,
                    assets: Vec::new(),
                    after: Vec::new(),
                    require: Vec::new(),
                })
                .await
        })
        .expect_err("the coordinator refuses a mesh scene without its files")
        .to_string();
    assert_eq!(refused, LOADER_REFUSAL);
    assert!(coordinator.is_running(), "the coordinator died");
    let jobs = ok(client(d, &addr, &["list", "--json"]), "list --json");
    let listed: serde_json::Value = serde_json::from_str(jobs.stdout.trim()).unwrap();
    assert_eq!(
        listed.as_array().map(Vec::len),
        Some(2),
        "the refused scene left no job: {listed}"
    );

    // Triangles and boxes, on the same coordinator: `tessera render`'s image, for two
    // tile sizes and for adaptive sampling.
    let shapes = write_shapes_scene(d);
    let shapes = path_str(&shapes);
    for args in [
        &["--tile", "16"][..],
        &["--tile", "48", "--aa", "3"][..],
        &[
            "--tile",
            "32",
            "--sampler",
            "adaptive",
            "--aa",
            "8",
            "--target-error",
            "2",
        ][..],
    ] {
        let args = [args, SMALL].concat();
        let job = submit_scene(d, &addr, shapes, &args);
        wait_done(d, &addr, job, JOB_TIMEOUT);
        assert_job_image(
            d,
            &addr,
            job,
            shapes,
            &args,
            &format!("triangles and boxes, {args:?}"),
        );
    }
}

#[test]
fn up_renders_meshes_and_refuses_a_missing_mesh_file_before_starting_a_farm() {
    let _turn = shared();
    let dir = TempDir::new().unwrap();
    let d = dir.path();
    let mesh_scene = write_mesh_scene(d);
    let mesh_scene = path_str(&mesh_scene);
    // A scene naming a file that is not there: refused in the loader's words, before
    // any farm starts (its own temporary directory shows none was).
    let text = std::fs::read_to_string(mesh_scene).unwrap();
    let gone = d.join("gone.json");
    std::fs::write(&gone, text.replace("cube.obj", "gone.obj")).unwrap();
    let gone = path_str(&gone);
    let tmp = d.join("tmp");
    std::fs::create_dir(&tmp).unwrap();
    let started = Instant::now();
    let run = tessera_env(
        d,
        &["up", gone, "-o", "gone.png"],
        &[("TMPDIR", path_str(&tmp))],
    );
    let took = started.elapsed();
    assert!(
        !run.status.success(),
        "up of a scene whose mesh is missing succeeded"
    );
    let stderr = String::from_utf8_lossy(&run.stderr);
    let lines: Vec<&str> = stderr.lines().collect();
    assert_eq!(lines.len(), 1, "{stderr}");
    assert!(
        lines[0].starts_with(&format!("error: {gone}: objects[1].file: "))
            && lines[0].contains("gone.obj: cannot read it"),
        "{stderr}"
    );
    assert!(run.stdout.is_empty(), "{:?}", run.stdout);
    assert!(took < Duration::from_secs(5), "refused only after {took:?}");
    assert_eq!(entries(&tmp), Vec::<String>::new(), "up started a farm");
    assert!(!d.join("gone.png").exists());

    // The mesh scene and the triangles and boxes: `tessera render`'s images.
    let shapes = write_shapes_scene(d);
    for (scene, what) in [
        (mesh_scene, "a mesh"),
        (path_str(&shapes), "triangles and boxes"),
    ] {
        let reference = render_reference(d, scene, "reference.png", SMALL);
        let out = d.join("up.png");
        let up = [
            &[
                "up",
                scene,
                "--workers",
                "2",
                "--tile",
                "24",
                "-o",
                path_str(&out),
            ][..],
            SMALL,
        ]
        .concat();
        ok(
            tessera(d, &up, JOB_TIMEOUT),
            &format!("tessera {}", up.join(" ")),
        );
        assert_same_png(&out, &reference, &format!("up of {what}"));
    }
}
