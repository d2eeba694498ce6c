//! A mesh object's `transform` (the scene format, section 8): p' = A·p + t.
//!
//! The matrix is composed once, from the scene's parts or its 12 numbers, with the
//! renderer's own sines and cosines ([`crate::trig`]), so that it has the same bits on
//! every machine and a rotation by a multiple of 90° is exact. Points are mapped by one
//! fixed sequence of operations ([`Affine::point`]): the tracer maps a shared mesh's
//! vertices with it whenever it tests them, and so gives them exactly the bits a mesh
//! mapped once at load would have.

use crate::trig::sin_cos_deg;
use crate::vec3::Vec3;

/// What a scene's `transform` says, kept as written so the scene can be written back.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum TransformSpec {
    /// p' = translate + Rz·Ry·Rx·(scale ⊙ p), angles in degrees.
    Parts {
        scale: Vec3,
        rotate: Vec3,
        translate: Vec3,
    },
    /// A row-major 3 × 4 matrix [A | t].
    Matrix([f64; 12]),
}

impl TransformSpec {
    pub const IDENTITY: TransformSpec = TransformSpec::Parts {
        scale: Vec3::new(1.0, 1.0, 1.0),
        rotate: Vec3::ZERO,
        translate: Vec3::ZERO,
    };

    /// The affine map, or why there is none (a zero scale, a singular matrix, a
    /// non-finite entry), as the end of a sentence.
    pub fn affine(&self) -> Result<Affine, String> {
        let affine = match *self {
            TransformSpec::Parts {
                scale,
                rotate,
                translate,
            } => {
                if scale.x == 0.0 || scale.y == 0.0 || scale.z == 0.0 {
                    return Err(format!(
                        "scale must have no zero component, got {} {} {}",
                        scale.x, scale.y, scale.z
                    ));
                }
                let rx = rotation(0, rotate.x);
                let ry = rotation(1, rotate.y);
                let rz = rotation(2, rotate.z);
                let r = multiply(&rz, &multiply(&ry, &rx));
                let a = std::array::from_fn(|i| {
                    [r[i][0] * scale.x, r[i][1] * scale.y, r[i][2] * scale.z]
                });
                Affine {
                    a,
                    t: [translate.x, translate.y, translate.z],
                }
            }
            TransformSpec::Matrix(m) => Affine {
                a: [[m[0], m[1], m[2]], [m[4], m[5], m[6]], [m[8], m[9], m[10]]],
                t: [m[3], m[7], m[11]],
            },
        };
        if !affine
            .a
            .iter()
            .flatten()
            .chain(&affine.t)
            .all(|x| x.is_finite())
        {
            return Err("the matrix is not finite".into());
        }
        let det = affine.determinant();
        if det == 0.0 || !det.is_finite() {
            return Err(format!(
                "the matrix is singular (det(A) = {det}): it flattens the mesh"
            ));
        }
        Ok(affine)
    }
}

/// The rotation by `degrees` about axis `axis` (0 x, 1 y, 2 z), rows as in section 8.
fn rotation(axis: usize, degrees: f64) -> [[f64; 3]; 3] {
    let (s, c) = sin_cos_deg(degrees);
    match axis {
        0 => [[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]],
        1 => [[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]],
        _ => [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]],
    }
}

fn multiply(x: &[[f64; 3]; 3], y: &[[f64; 3]; 3]) -> [[f64; 3]; 3] {
    std::array::from_fn(|i| {
        std::array::from_fn(|j| x[i][0] * y[0][j] + x[i][1] * y[1][j] + x[i][2] * y[2][j])
    })
}

/// p' = A·p + t, with det(A) ≠ 0.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Affine {
    pub a: [[f64; 3]; 3],
    pub t: [f64; 3],
}

impl Affine {
    pub const IDENTITY: Affine = Affine {
        a: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        t: [0.0; 3],
    };

    pub fn is_identity(&self) -> bool {
        *self == Affine::IDENTITY
    }

    pub fn determinant(&self) -> f64 {
        let a = &self.a;
        a[0][0] * (a[1][1] * a[2][2] - a[1][2] * a[2][1])
            - a[0][1] * (a[1][0] * a[2][2] - a[1][2] * a[2][0])
            + a[0][2] * (a[1][0] * a[2][1] - a[1][1] * a[2][0])
    }

    /// A·p + t, always by these operations in this order.
    #[inline(always)]
    pub fn point(&self, p: [f64; 3]) -> Vec3 {
        let a = &self.a;
        Vec3::new(
            a[0][0] * p[0] + a[0][1] * p[1] + a[0][2] * p[2] + self.t[0],
            a[1][0] * p[0] + a[1][1] * p[1] + a[1][2] * p[2] + self.t[1],
            a[2][0] * p[0] + a[2][1] * p[1] + a[2][2] * p[2] + self.t[2],
        )
    }

    /// A·v, for directions.
    #[inline(always)]
    pub fn vector(&self, v: Vec3) -> Vec3 {
        let a = &self.a;
        Vec3::new(
            a[0][0] * v.x + a[0][1] * v.y + a[0][2] * v.z,
            a[1][0] * v.x + a[1][1] * v.y + a[1][2] * v.z,
            a[2][0] * v.x + a[2][1] * v.y + a[2][2] * v.z,
        )
    }

    /// The cofactor matrix cof(A) = det(A)·A⁻ᵀ: it maps normals as the inverse transpose
    /// does, up to a positive or negative factor that normalising removes, without a
    /// division.
    pub fn normal_matrix(&self) -> [[f64; 3]; 3] {
        let a = &self.a;
        let c = |r0: usize, r1: usize, c0: usize, c1: usize| {
            a[r0][c0] * a[r1][c1] - a[r0][c1] * a[r1][c0]
        };
        [
            [c(1, 2, 1, 2), -c(1, 2, 0, 2), c(1, 2, 0, 1)],
            [-c(0, 2, 1, 2), c(0, 2, 0, 2), -c(0, 2, 0, 1)],
            [c(0, 1, 1, 2), -c(0, 1, 0, 2), c(0, 1, 0, 1)],
        ]
    }

    /// The inverse map, computed in double: for taking rays into a shared mesh's own
    /// coordinates, where the tracer allows for its rounding.
    pub fn inverse(&self) -> Affine {
        let cof = self.normal_matrix();
        let det = self.determinant();
        // A⁻¹ = cof(A)ᵀ / det(A).
        let inv: [[f64; 3]; 3] = std::array::from_fn(|i| std::array::from_fn(|j| cof[j][i] / det));
        let t = self.t;
        let it = std::array::from_fn(|i| -(inv[i][0] * t[0] + inv[i][1] * t[1] + inv[i][2] * t[2]));
        Affine { a: inv, t: it }
    }

    /// The largest row sum of |A|: ‖A·v‖∞ ≤ norm·‖v‖∞.
    pub fn norm(&self) -> f64 {
        self.a
            .iter()
            .map(|row| row.iter().map(|x| x.abs()).sum::<f64>())
            .fold(0.0, f64::max)
    }
}

/// Normalises `n` mapped by a normal matrix, or gives `None` where it is zero or not
/// finite.
pub(crate) fn map_normal(m: &[[f64; 3]; 3], n: [f64; 3]) -> Option<Vec3> {
    let v = Vec3::new(
        m[0][0] * n[0] + m[0][1] * n[1] + m[0][2] * n[2],
        m[1][0] * n[0] + m[1][1] * n[1] + m[1][2] * n[2],
        m[2][0] * n[0] + m[2][1] * n[1] + m[2][2] * n[2],
    );
    let len = v.length();
    (len > 0.0 && len.is_finite()).then(|| v / len)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parts(scale: Vec3, rotate: Vec3, translate: Vec3) -> TransformSpec {
        TransformSpec::Parts {
            scale,
            rotate,
            translate,
        }
    }

    #[test]
    fn quarter_turns_are_exact_and_follow_the_formats_order() {
        // Rx by 90° then Rz by 90°: x → x → y; y → z → z; z → −y → x.
        let a = parts(
            Vec3::new(1.0, 1.0, 1.0),
            Vec3::new(90.0, 0.0, 90.0),
            Vec3::ZERO,
        )
        .affine()
        .unwrap();
        assert_eq!(a.point([1.0, 0.0, 0.0]), Vec3::new(0.0, 1.0, 0.0));
        assert_eq!(a.point([0.0, 1.0, 0.0]), Vec3::new(0.0, 0.0, 1.0));
        assert_eq!(a.point([0.0, 0.0, 1.0]), Vec3::new(1.0, 0.0, 0.0));
        let b = parts(
            Vec3::new(2.0, 3.0, 4.0),
            Vec3::new(0.0, -270.0, 0.0),
            Vec3::new(1.0, 2.0, 3.0),
        )
        .affine()
        .unwrap();
        // Ry(−270°) = Ry(90°): (x, y, z) → (z, y, −x).
        assert_eq!(
            b.point([0.5, 0.25, 0.125]),
            Vec3::new(0.5 + 1.0, 0.75 + 2.0, -1.0 + 3.0)
        );
    }

    #[test]
    fn zero_scales_and_singular_matrices_are_refused() {
        assert!(parts(Vec3::new(1.0, 0.0, 1.0), Vec3::ZERO, Vec3::ZERO)
            .affine()
            .unwrap_err()
            .contains("scale must have no zero component"));
        let flat =
            TransformSpec::Matrix([1.0, 2.0, 3.0, 0.0, 2.0, 4.0, 6.0, 0.0, 0.0, 0.0, 1.0, 0.0]);
        assert!(flat.affine().unwrap_err().contains("singular"));
        let fine =
            TransformSpec::Matrix([0.0, 0.0, 2.0, 1.0, 0.0, 3.0, 0.0, 2.0, 4.0, 0.0, 0.0, 3.0]);
        let a = fine.affine().unwrap();
        assert_eq!(a.point([1.0, 1.0, 1.0]), Vec3::new(3.0, 5.0, 7.0));
        let back = a.inverse().point([3.0, 5.0, 7.0]);
        assert!(
            (back - Vec3::new(1.0, 1.0, 1.0)).length() < 1e-15,
            "{back:?}"
        );
    }

    #[test]
    fn normals_follow_the_inverse_transpose() {
        // A stretch along x tilts a 45° normal towards x... the other way.
        let a = parts(Vec3::new(2.0, 1.0, 1.0), Vec3::ZERO, Vec3::ZERO)
            .affine()
            .unwrap();
        let n = map_normal(&a.normal_matrix(), [1.0, 1.0, 0.0]).unwrap();
        let expected = Vec3::new(0.5, 1.0, 0.0).normalize();
        assert!((n - expected).length() < 1e-15, "{n:?}");
        // The tangent (1, −1, 0) maps to (2, −1, 0): still perpendicular.
        assert!(n.dot(a.vector(Vec3::new(1.0, -1.0, 0.0))).abs() < 1e-15);
    }
}
