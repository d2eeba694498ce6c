//! The surface of an axis-aligned box, by the slab method: the hit is where the ray
//! enters the last of the three slabs (or, from inside, leaves the first), so the faces
//! meet without a gap. A ray meeting an edge or corner exactly takes the face of x,
//! then y, then z (section 8).

use crate::vec3::Vec3;

/// A box hit: distance, the axis of the face, and the face's outward normal sign.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct BoxHit {
    pub t: f64,
    pub axis: usize,
    pub outward: f64,
}

fn get(v: Vec3, k: usize) -> f64 {
    match k {
        0 => v.x,
        1 => v.y,
        _ => v.z,
    }
}

/// The nearest t in (0, `t_max`] where the ray meets the surface of the box.
#[inline(always)]
pub(crate) fn hit(min: Vec3, max: Vec3, origin: Vec3, dir: Vec3, t_max: f64) -> Option<BoxHit> {
    let mut near = (f64::NEG_INFINITY, 0usize);
    let mut far = (f64::INFINITY, 0usize);
    for k in 0..3 {
        let (lo, hi, o, d) = (get(min, k), get(max, k), get(origin, k), get(dir, k));
        if d == 0.0 {
            if o < lo || o > hi {
                return None;
            }
            continue;
        }
        let (a, b) = ((lo - o) / d, (hi - o) / d);
        let (enter, leave) = if d > 0.0 { (a, b) } else { (b, a) };
        if enter > near.0 {
            near = (enter, k);
        }
        if leave < far.0 {
            far = (leave, k);
        }
    }
    if near.0 > far.0 {
        return None;
    }
    let (t, axis, entering) = if near.0 > 0.0 {
        (near.0, near.1, true)
    } else if far.0 > 0.0 {
        (far.0, far.1, false)
    } else {
        return None;
    };
    #[expect(
        clippy::neg_cmp_op_on_partial_ord,
        reason = "a NaN distance must be refused too"
    )]
    if !(t <= t_max) {
        return None;
    }
    // Entering through the low face of an axis the ray climbs is the face at min.
    let climbs = get(dir, axis) > 0.0;
    let outward = if climbs == entering { -1.0 } else { 1.0 };
    Some(BoxHit { t, axis, outward })
}

/// The point of a box face at `p` (on the ray), its coordinate on the face's axis set
/// to the face's plane exactly, and the origin for a ray leaving it in direction `dir`:
/// that coordinate moved one representable number to `dir`'s side of the face.
pub(crate) fn on_face(min: Vec3, max: Vec3, hit: &BoxHit, p: Vec3, dir: Vec3) -> (Vec3, Vec3) {
    let plane = if hit.outward > 0.0 {
        get(max, hit.axis)
    } else {
        get(min, hit.axis)
    };
    let set = |v: Vec3, x: f64| match hit.axis {
        0 => Vec3::new(x, v.y, v.z),
        1 => Vec3::new(v.x, x, v.z),
        _ => Vec3::new(v.x, v.y, x),
    };
    let point = set(p, plane);
    let leaving = if get(dir, hit.axis) > 0.0 {
        plane.next_up()
    } else {
        plane.next_down()
    };
    (point, set(p, leaving))
}

#[cfg(test)]
mod tests {
    use super::*;

    const MIN: Vec3 = Vec3::new(-1.0, -1.0, -1.0);
    const MAX: Vec3 = Vec3::new(1.0, 1.0, 1.0);

    #[test]
    fn faces_from_outside_and_inside() {
        let h = hit(
            MIN,
            MAX,
            Vec3::new(0.0, 0.0, -5.0),
            Vec3::new(0.0, 0.0, 1.0),
            f64::INFINITY,
        )
        .unwrap();
        assert_eq!(
            h,
            BoxHit {
                t: 4.0,
                axis: 2,
                outward: -1.0
            }
        );
        let inside = hit(
            MIN,
            MAX,
            Vec3::ZERO,
            Vec3::new(0.0, -1.0, 0.0),
            f64::INFINITY,
        )
        .unwrap();
        assert_eq!(
            inside,
            BoxHit {
                t: 1.0,
                axis: 1,
                outward: -1.0
            }
        );
        assert!(hit(
            MIN,
            MAX,
            Vec3::new(0.0, 0.0, -5.0),
            Vec3::new(0.0, 0.0, -1.0),
            f64::INFINITY
        )
        .is_none());
        assert!(hit(
            MIN,
            MAX,
            Vec3::new(2.0, 0.0, -5.0),
            Vec3::new(0.0, 0.0, 1.0),
            f64::INFINITY
        )
        .is_none());
    }

    #[test]
    fn an_edge_goes_to_x_then_y_then_z() {
        // Towards the edge x = 1, y = 1 along the diagonal of x and y.
        let d = Vec3::new(-1.0, -1.0, 0.0).normalize();
        let h = hit(MIN, MAX, Vec3::new(3.0, 3.0, 0.0), d, f64::INFINITY).unwrap();
        assert_eq!((h.axis, h.outward), (0, 1.0));
        let corner = Vec3::new(-1.0, -1.0, -1.0).normalize();
        let h = hit(MIN, MAX, Vec3::new(3.0, 3.0, 3.0), corner, f64::INFINITY).unwrap();
        assert_eq!((h.axis, h.outward), (0, 1.0));
    }

    #[test]
    fn a_ray_leaving_a_face_does_not_meet_it_again() {
        let dir = Vec3::new(0.3, 0.2, -1.0).normalize();
        let h = hit(MIN, MAX, Vec3::new(0.1, 0.1, -3.0), -dir, f64::INFINITY);
        let h = h.unwrap();
        let p = Vec3::new(0.1, 0.1, -3.0) + (-dir) * h.t;
        let (_, origin) = on_face(MIN, MAX, &h, p, dir);
        assert!(hit(MIN, MAX, origin, dir, f64::INFINITY).is_none());
    }
}
