//! The parts of the suite that need no program to run: reading what the programs print
//! (render times, phases, the floor, peak memory), comparing images, dates and medians.

use super::image::{decode_ppm, Rgb};
use super::report::civil_date;
use super::spheres::parse_floor;
use super::*;

#[test]
fn reads_the_render_time_of_tessera_render() {
    let line = "t.png: 600x400, 4 samples/pixel (grid 2x2, 960000 in all), estimated \
                error 17.547 levels, 0.086 s, 31.7 M rays/s (1 threads)\n";
    assert_eq!(tessera_seconds(line), Some(0.086));
    assert_eq!(tessera_seconds("nothing here"), None);
}

#[test]
fn reads_the_anchors_phases() {
    let line = "/tmp/a.png: 600x400, aa 2, mode packet8, spheres user(double), 1 threads: \
                parse 0.004 s, build 0.002 s, tracing 0.129 s (cpu 0.066 s), write 0.013 s, \
                2716246 rays, 21.0 M rays/s (camera 960000, reflection 196993, shadow 1559253)";
    assert_eq!(labelled_seconds(line, "parse"), Some(0.004));
    assert_eq!(labelled_seconds(line, "build"), Some(0.002));
    assert_eq!(labelled_seconds(line, "tracing"), Some(0.129));
    assert_eq!(labelled_seconds(line, "render"), None);
    let seed = "s.ppm: 600x400, aa 2, 1 thread: parse 0.000 s, render 0.517 s";
    assert_eq!(labelled_seconds(seed, "render"), Some(0.517));
}

#[test]
fn reads_the_floor() {
    let out = "\
double AVX2 camera rays     : 2716160 rays x 3 objects: best of 11 19.94 ms = 7.34 ns/ray = 2.45 ns per ray-object test, 136 M rays/s (rays hitting: 79%)
double AVX2 random rays     : 2716160 rays x 3 objects: best of 11 28.67 ms = 10.55 ns/ray
float  AVX2 camera rays     : 2716160 rays x 3 objects: best of 11 10.73 ms = 3.95 ns/ray
double AVX2 camera, skip    : 2716160 rays x 3 objects: best of 11 19.01 ms = 7.00 ns/ray
double AVX2 shading         : 1156608 hits, 2 lights: best of 11 13.63 ms = 11.78 ns/hit
";
    let floor = parse_floor(out).expect("both lines");
    assert_eq!(floor.intersection_ms, 19.01);
    assert_eq!(floor.shading_ms, 13.63);
    let without_skip: String = out
        .lines()
        .filter(|l| !l.contains("skip"))
        .collect::<Vec<_>>()
        .join("\n");
    assert_eq!(
        parse_floor(&without_skip).map(|f| f.intersection_ms),
        Some(19.94)
    );
    assert_eq!(
        parse_floor("double AVX2 camera rays : best of 3 1.0 ms"),
        None
    );
}

#[test]
fn compares_images_pixel_by_pixel() {
    let a = Rgb {
        width: 2,
        height: 1,
        bytes: vec![0, 0, 0, 10, 20, 30],
    };
    let same = Rgb {
        bytes: a.bytes.clone(),
        ..a
    };
    assert_eq!(compare(&a, &same), "identical");
    let other = Rgb {
        bytes: vec![0, 0, 0, 10, 23, 30],
        ..a
    };
    assert_eq!(compare(&a, &other), "1 pixel differs (up to 3 levels)");
    let ppm = decode_ppm(b"P6\n2 1\n255\n\x00\x00\x00\x0a\x14\x1e").expect("valid");
    assert_eq!(compare(&a, &ppm), "identical");
}

#[test]
fn reads_the_peak_resident_set() {
    let status = "Name:\ttessera\nVmPeak:\t  123 kB\nVmHWM:\t   45678 kB\nVmRSS:\t 100 kB\n";
    assert_eq!(vm_hwm_kib(status), Some(45678));
    assert_eq!(vm_hwm_kib("Name:\tzombie\n"), None);
}

#[test]
fn dates_from_days_since_1970() {
    assert_eq!(civil_date(0), "1970-01-01");
    assert_eq!(civil_date(11_016), "2000-02-29");
    assert_eq!(civil_date(19_723), "2024-01-01");
}

#[test]
fn median_of_odd_and_even_counts() {
    assert_eq!(median(vec![3.0, 1.0, 2.0]), Some(2.0));
    assert_eq!(median(vec![4.0, 1.0, 2.0, 3.0]), Some(2.5));
    assert_eq!(median(Vec::new()), None);
}
