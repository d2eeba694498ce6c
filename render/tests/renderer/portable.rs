//! The portable lane code, which AVX2 machines never run on their own, gives the same
//! bytes and the same ray counts as the AVX2 build on every example scene, with every
//! sampler (meshes, boxes and triangles included) and with and without the hierarchy (whose node tests follow the tracer's
//! instruction set too).

use render::simd::Isa;
use render::{parse_scene_with, render_frame, MeshFiles, Sampling, Tracer};

#[test]
fn portable_and_avx2_paths_give_the_same_bytes() {
    let best = Isa::best();
    if cfg!(target_arch = "x86_64") {
        assert_eq!(
            best,
            Isa::Avx2,
            "this x86-64 processor lacks AVX2, so there is no second path to compare"
        );
    }
    let dir = concat!(env!("CARGO_MANIFEST_DIR"), "/../scenes");
    let mut scenes: Vec<_> = std::fs::read_dir(dir)
        .expect("scenes/ is readable")
        .map(|e| e.expect("a directory entry").path())
        .filter(|p| p.extension().is_some_and(|e| e == "json"))
        .collect();
    scenes.sort();
    assert!(scenes.len() >= 5, "the example scenes are found");
    let samplers = [
        Sampling::Grid,
        Sampling::Jittered,
        Sampling::adaptive(2.0).expect("a valid target"),
    ];
    for path in &scenes {
        let text = std::fs::read_to_string(path).expect("scene is readable");
        let files = MeshFiles::beside(dir);
        let scene = parse_scene_with(&text, &files).expect("example scene loads");
        for sampling in samplers {
            for aa in [1, 3] {
                let mut settings = scene.settings;
                settings.width = settings.width.min(160);
                settings.height = settings.height.min(120);
                settings.aa = aa;
                settings.sampling = sampling;
                for bvh in [false, true] {
                    let render = |isa: Isa| {
                        let tracer = Tracer::with_bvh(&scene, settings, bvh).with_isa(isa);
                        render_frame(&tracer, 16, &|_| {})
                    };
                    let (fast, portable) = (render(best), render(Isa::Portable));
                    let what = format!("{} {sampling:?} aa {aa} bvh {bvh}", path.display());
                    assert!(fast.image == portable.image, "{what}: images differ");
                    assert_eq!(fast.rays, portable.rays, "{what}: rays");
                }
            }
        }
    }
}
