//! Section 8's shapes on a farm. Triangles and boxes need no file: a farm renders them,
//! byte for byte as `tessera render` does, on a farm started by hand and by `tessera
//! up`. A mesh's file is on the client's machine, which a farm never sees: `tessera
//! submit` and `tessera up` refuse a scene with a mesh in one line before anything
//! reaches a farm (`up` before it starts one), the coordinator refuses such a scene sent
//! to it all the same, and it serves the next job unharmed.

use std::time::{Duration, Instant};

use coordinator::client::Client;
use protocol::{JobSpec, Overrides};
use tempfile::TempDir;
use transport::Endpoint;

use crate::support::{
    assert_job_image, assert_same_png, client, entries, farm_refusal, ok, one_error_line, path_str,
    render_reference, shared, start_coordinator_in, start_worker, submit_scene, tessera,
    tessera_env, wait_done, wait_for_workers, write_mesh_scene, write_shapes_scene, LOADER_REFUSAL,
    REGISTER_TIMEOUT,
};

const JOB_TIMEOUT: Duration = Duration::from_secs(60);
const SMALL: &[&str] = &["--width", "200", "--height", "150"];

#[test]
fn a_farm_renders_triangles_and_boxes_as_render_does_and_refuses_meshes() {
    let _turn = shared();
    let dir = TempDir::new().unwrap();
    let d = dir.path();
    let (mut coordinator, addr) = start_coordinator_in(d);
    let _workers = [start_worker(d, &addr, "w1"), start_worker(d, &addr, "w2")];
    wait_for_workers(d, &addr, 2, REGISTER_TIMEOUT);
    let mesh_scene = write_mesh_scene(d);
    let mesh_scene = path_str(&mesh_scene);

    // `submit`: one line, before the scene goes anywhere.
    let run = client(d, &addr, &["submit", mesh_scene]);
    assert_eq!(
        one_error_line(&run, "submit of a mesh scene"),
        farm_refusal(mesh_scene)
    );
    let run = client(
        d,
        &addr,
        &["submit", mesh_scene, "--wait", "-o", "mesh.png"],
    );
    one_error_line(&run, "submit --wait of a mesh scene");
    assert!(!d.join("mesh.png").exists());

    // The coordinator, sent the scene's text by another client: refused in one line,
    // the renderer's own.
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
                })
                .await
        })
        .expect_err("the coordinator refuses a mesh scene")
        .to_string();
    assert_eq!(refused, LOADER_REFUSAL);
    assert!(coordinator.is_running(), "the coordinator died");
    let jobs = ok(client(d, &addr, &["list", "--json"]), "list --json");
    assert_eq!(jobs.stdout.trim(), "[]", "the refused scenes left no job");

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
fn up_renders_triangles_and_boxes_and_refuses_a_mesh_before_starting_a_farm() {
    let _turn = shared();
    let dir = TempDir::new().unwrap();
    let d = dir.path();
    let mesh_scene = write_mesh_scene(d);
    let mesh_scene = path_str(&mesh_scene);
    // Its own temporary directory, to see that no farm was started in it.
    let tmp = d.join("tmp");
    std::fs::create_dir(&tmp).unwrap();
    let started = Instant::now();
    let run = tessera_env(
        d,
        &["up", mesh_scene, "-o", "mesh.png"],
        &[("TMPDIR", path_str(&tmp))],
    );
    let took = started.elapsed();
    assert!(!run.status.success(), "up of a mesh scene succeeded");
    let stderr = String::from_utf8_lossy(&run.stderr);
    let lines: Vec<&str> = stderr.lines().collect();
    assert_eq!(lines, [farm_refusal(mesh_scene)], "{stderr}");
    assert!(run.stdout.is_empty(), "{:?}", run.stdout);
    assert!(took < Duration::from_secs(5), "refused only after {took:?}");
    assert_eq!(entries(&tmp), Vec::<String>::new(), "up started a farm");
    assert!(!d.join("mesh.png").exists());

    let shapes = write_shapes_scene(d);
    let shapes = path_str(&shapes);
    let reference = render_reference(d, shapes, "reference.png", SMALL);
    let out = d.join("up.png");
    let up = [
        &[
            "up",
            shapes,
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
    assert_same_png(&out, &reference, "up of triangles and boxes");
}
