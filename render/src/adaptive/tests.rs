use super::*;
use crate::{parse_scene, RenderSettings};

/// A small scene with edges, a mirror, a checkerboard and a tiny sphere.
fn tracer(aa: u32) -> Tracer {
    let scene = parse_scene(
        r#"{
            "camera": { "position": [0, 1.5, -6], "look_at": [0, 0.5, 0] },
            "lights": [ { "position": [4, 6, -4], "color": [1, 1, 1] } ],
            "objects": [
              { "type": "plane", "normal": [0, 1, 0], "distance": 0, "color": [1, 1, 1, 2] },
              { "type": "sphere", "center": [-1, 1, 0], "radius": 1, "color": [0.9, 0.2, 0.2, 0.5] },
              { "type": "sphere", "center": [1.2, 0.6, -1], "radius": 0.6, "color": [0.2, 0.4, 0.9, 0] },
              { "type": "sphere", "center": [0.3, 2.2, 1], "radius": 0.01, "color": [1, 1, 1, 0] }
            ]
          }"#,
    )
    .expect("the test scene parses");
    let settings = RenderSettings {
        width: 72,
        height: 40,
        aa,
        max_depth: 4,
        sampling: Sampling::Adaptive { target_milli: 1000 },
    };
    Tracer::new(&scene, settings)
}

fn direct(t: &Tracer, target: f64) -> RungFrame {
    render_to_target(t, None, target, &mut |_, _| true).1
}

#[test]
fn the_ladder_falls_from_infinity_to_zero_in_exact_steps() {
    assert_eq!(threshold(0), f64::INFINITY);
    assert_eq!(threshold(1), 16_777_216.0);
    assert_eq!(threshold(9), 8_388_608.0);
    assert_eq!(threshold(LAST_RUNG), 0.0);
    for k in 1..LAST_RUNG {
        assert!(threshold(k + 1) < threshold(k), "rung {k}");
    }
    assert_eq!(sample_cap(1), 1);
    assert_eq!(sample_cap(3), 8);
    assert_eq!(sample_cap(8), 64);
}

#[test]
fn a_lower_target_costs_more_and_estimates_less() {
    let t = tracer(8);
    let coarse = direct(&t, 8.0);
    let fine = direct(&t, 2.0);
    assert!(
        fine.rung > coarse.rung,
        "{} {} {} {}",
        fine.rung,
        coarse.rung,
        fine.estimated_error(),
        coarse.estimated_error()
    );
    assert!(fine.totals.samples > coarse.totals.samples);
    assert!(fine.estimated_error() <= 2.0);
    assert!(coarse.estimated_error() <= 8.0);
}

#[test]
fn refining_gives_the_bytes_of_a_direct_render() {
    let t = tracer(8);
    let (region, first) = render_to_target(&t, None, 4.0, &mut |_, _| true);
    let blocks = region.into_blocks();
    let full = Rect {
        x: 0,
        y: 0,
        width: 72,
        height: 40,
    };
    let resumed = Region::new(&t, Region::footprints(&t), full, Some(blocks)).unwrap();
    let (_, refined) = render_to_target(&t, Some(resumed), 1.0, &mut |_, _| true);
    let straight = direct(&t, 1.0);
    assert!(refined.rung > first.rung);
    assert_eq!(refined.rung, straight.rung);
    assert_eq!(refined.image.rgb, straight.image.rgb);
    assert_eq!(refined.totals, straight.totals);
}

#[test]
fn a_larger_cap_continues_from_the_smaller_one() {
    let small = tracer(4);
    let (region, _) = render_to_target(&small, None, 0.5, &mut |_, _| true);
    let big = tracer(8);
    let full = Rect {
        x: 0,
        y: 0,
        width: 72,
        height: 40,
    };
    let resumed = Region::new(
        &big,
        Region::footprints(&big),
        full,
        Some(region.into_blocks()),
    )
    .unwrap();
    let (_, refined) = render_to_target(&big, Some(resumed), 0.5, &mut |_, _| true);
    let straight = direct(&big, 0.5);
    assert_eq!(refined.image.rgb, straight.image.rgb);
    assert_eq!(refined.totals, straight.totals);
}

#[test]
fn tiles_advanced_apart_give_the_frame_of_the_whole() {
    let t = tracer(8);
    let whole = direct(&t, 1.0);
    let footprints = Region::footprints(&t);
    let mut image = Image::black(72, 40);
    let mut totals = RungTotals::default();
    for rect in crate::rect::tiles(t.settings(), 16) {
        let mut region = Region::new(&t, footprints.clone(), rect, None).unwrap();
        region.advance_to(whole.rung + 3);
        region.paint(whole.rung, &mut image);
        totals.add(&region.totals(whole.rung).unwrap());
    }
    assert_eq!(image.rgb, whole.image.rgb);
    assert_eq!(totals, whole.totals);
}

#[test]
fn misaligned_tiles_and_damaged_states_are_refused() {
    let t = tracer(8);
    let fp = Region::footprints(&t);
    let odd = Rect {
        x: 4,
        y: 0,
        width: 16,
        height: 16,
    };
    assert!(matches!(
        Region::new(&t, fp.clone(), odd, None),
        Err(RegionError::Misaligned(_))
    ));
    let rect = Rect {
        x: 0,
        y: 0,
        width: 16,
        height: 16,
    };
    let mut region = Region::new(&t, fp.clone(), rect, None).unwrap();
    region.advance_to(200);
    let good = region.into_blocks();
    let mut short = good.clone();
    short[1].levels[0].rgb.pop();
    let mut nan = good.clone();
    nan[2].sums[3][0][1] = f64::NAN;
    let mut skipped = good.clone();
    let again = skipped[0].levels[0].clone();
    skipped[0].levels.push(again);
    for bad in [short, nan, skipped, good[1..].to_vec()] {
        let err = Region::new(&t, fp.clone(), rect, Some(bad)).err().unwrap();
        assert!(matches!(err, RegionError::BadState { .. }), "{err}");
    }
    assert!(Region::new(&t, fp, rect, Some(good)).is_ok());
}
