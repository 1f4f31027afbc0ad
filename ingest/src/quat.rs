//! Quaternions (w, x, y, z) and 3-vectors in f64, with HumanML3D's conventions.

/// A 3-vector.
pub type Vec3 = [f64; 3];
/// A quaternion stored as (w, x, y, z).
pub type Quat = [f64; 4];

/// The identity rotation.
pub const IDENTITY: Quat = [1.0, 0.0, 0.0, 0.0];

/// Vector difference a − b.
#[inline]
pub fn sub(a: Vec3, b: Vec3) -> Vec3 {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

/// Vector sum a + b.
#[inline]
pub fn add(a: Vec3, b: Vec3) -> Vec3 {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}

/// Vector scaled by s.
#[inline]
pub fn scale(a: Vec3, s: f64) -> Vec3 {
    [a[0] * s, a[1] * s, a[2] * s]
}

/// Dot product.
#[inline]
pub fn dot(a: Vec3, b: Vec3) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// Cross product a × b.
#[inline]
pub fn cross(a: Vec3, b: Vec3) -> Vec3 {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

/// Euclidean norm.
#[inline]
pub fn norm(a: Vec3) -> f64 {
    dot(a, a).sqrt()
}

/// Unit vector along a (a zero vector stays zero, as in the reference's `x / norm` with eps-free division guarded).
#[inline]
pub fn normalize(a: Vec3) -> Vec3 {
    let n = norm(a);
    if n > 0.0 {
        scale(a, 1.0 / n)
    } else {
        a
    }
}

/// Hamilton product q · r.
#[inline]
pub fn mul(q: Quat, r: Quat) -> Quat {
    [
        q[0] * r[0] - q[1] * r[1] - q[2] * r[2] - q[3] * r[3],
        q[0] * r[1] + q[1] * r[0] + q[2] * r[3] - q[3] * r[2],
        q[0] * r[2] - q[1] * r[3] + q[2] * r[0] + q[3] * r[1],
        q[0] * r[3] + q[1] * r[2] - q[2] * r[1] + q[3] * r[0],
    ]
}

/// Inverse of a unit quaternion (its conjugate).
#[inline]
pub fn inv(q: Quat) -> Quat {
    [q[0], -q[1], -q[2], -q[3]]
}

/// Quaternion scaled to unit norm.
#[inline]
pub fn qnormalize(q: Quat) -> Quat {
    let n = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]).sqrt();
    [q[0] / n, q[1] / n, q[2] / n, q[3] / n]
}

/// Rotate v by q: v + 2(w·(q⃗×v) + q⃗×(q⃗×v)).
#[inline]
pub fn rot(q: Quat, v: Vec3) -> Vec3 {
    let qv = [q[1], q[2], q[3]];
    let uv = cross(qv, v);
    let uuv = cross(qv, uv);
    [
        v[0] + 2.0 * (q[0] * uv[0] + uuv[0]),
        v[1] + 2.0 * (q[0] * uv[1] + uuv[1]),
        v[2] + 2.0 * (q[0] * uv[2] + uuv[2]),
    ]
}

/// Rotation taking direction u to direction v (HumanML3D `qbetween`): axis = u × v, w = |u||v| + u·v, normalised.
#[inline]
pub fn between(u: Vec3, v: Vec3) -> Quat {
    let axis = cross(u, v);
    let w = (dot(u, u) * dot(v, v)).sqrt() + dot(u, v);
    qnormalize([w, axis[0], axis[1], axis[2]])
}

/// Rotation of `angle` radians about the unit `axis`.
#[inline]
pub fn from_axis_angle(axis: Vec3, angle: f64) -> Quat {
    let (s, c) = (angle * 0.5).sin_cos();
    [c, axis[0] * s, axis[1] * s, axis[2] * s]
}

/// Rotation from an axis-angle vector (direction = axis, length = angle in radians).
#[inline]
pub fn from_rotvec(v: Vec3) -> Quat {
    let angle = norm(v);
    if angle < 1e-12 {
        return qnormalize([1.0, 0.5 * v[0], 0.5 * v[1], 0.5 * v[2]]);
    }
    from_axis_angle(scale(v, 1.0 / angle), angle)
}

/// Rotation matrix (row-major, m[row][col]) of a unit quaternion.
#[inline]
pub fn to_matrix(q: Quat) -> [[f64; 3]; 3] {
    let [w, x, y, z] = q;
    [
        [
            1.0 - 2.0 * (y * y + z * z),
            2.0 * (x * y - w * z),
            2.0 * (x * z + w * y),
        ],
        [
            2.0 * (x * y + w * z),
            1.0 - 2.0 * (x * x + z * z),
            2.0 * (y * z - w * x),
        ],
        [
            2.0 * (x * z - w * y),
            2.0 * (y * z + w * x),
            1.0 - 2.0 * (x * x + y * y),
        ],
    ]
}

/// Unit quaternion (w ≥ 0) of a rotation matrix (row-major), by Shepperd's method.
pub fn from_matrix(m: [[f64; 3]; 3]) -> Quat {
    let tr = m[0][0] + m[1][1] + m[2][2];
    let q = if tr > 0.0 {
        let s = (tr + 1.0).sqrt() * 2.0;
        [
            0.25 * s,
            (m[2][1] - m[1][2]) / s,
            (m[0][2] - m[2][0]) / s,
            (m[1][0] - m[0][1]) / s,
        ]
    } else if m[0][0] > m[1][1] && m[0][0] > m[2][2] {
        let s = (1.0 + m[0][0] - m[1][1] - m[2][2]).sqrt() * 2.0;
        [
            (m[2][1] - m[1][2]) / s,
            0.25 * s,
            (m[0][1] + m[1][0]) / s,
            (m[0][2] + m[2][0]) / s,
        ]
    } else if m[1][1] > m[2][2] {
        let s = (1.0 + m[1][1] - m[0][0] - m[2][2]).sqrt() * 2.0;
        [
            (m[0][2] - m[2][0]) / s,
            (m[0][1] + m[1][0]) / s,
            0.25 * s,
            (m[1][2] + m[2][1]) / s,
        ]
    } else {
        let s = (1.0 + m[2][2] - m[0][0] - m[1][1]).sqrt() * 2.0;
        [
            (m[1][0] - m[0][1]) / s,
            (m[0][2] + m[2][0]) / s,
            (m[1][2] + m[2][1]) / s,
            0.25 * s,
        ]
    };
    let q = qnormalize(q);
    if q[0] < 0.0 {
        [-q[0], -q[1], -q[2], -q[3]]
    } else {
        q
    }
}

/// 6D rotation: the first two columns of the rotation matrix, concatenated (col0, col1).
#[inline]
pub fn to_rot6d(q: Quat) -> [f64; 6] {
    let m = to_matrix(q);
    [m[0][0], m[1][0], m[2][0], m[0][1], m[1][1], m[2][1]]
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::FRAC_PI_2;

    fn close(a: &[f64], b: &[f64]) {
        for (x, y) in a.iter().zip(b) {
            assert!((x - y).abs() < 1e-12, "{a:?} vs {b:?}");
        }
    }

    #[test]
    fn quarter_turn_about_y_maps_z_to_x() {
        // Hand-computed: q = (cos 45°, 0, sin 45°, 0); rotating +Z by +90° about +Y gives +X.
        let h = 0.5f64.sqrt();
        let q = from_axis_angle([0.0, 1.0, 0.0], FRAC_PI_2);
        close(&q, &[h, 0.0, h, 0.0]);
        close(&rot(q, [0.0, 0.0, 1.0]), &[1.0, 0.0, 0.0]);
        close(&rot(q, [1.0, 0.0, 0.0]), &[0.0, 0.0, -1.0]);
    }

    #[test]
    fn product_composes_rotations() {
        // Hand-computed: (90° about X)·(90° about Y) = (1/2)(1, 1, 1, 1).
        let qx = from_axis_angle([1.0, 0.0, 0.0], FRAC_PI_2);
        let qy = from_axis_angle([0.0, 1.0, 0.0], FRAC_PI_2);
        close(&mul(qx, qy), &[0.5, 0.5, 0.5, 0.5]);
        let v = [0.3, -1.2, 2.0];
        close(&rot(mul(qx, qy), v), &rot(qx, rot(qy, v)));
        close(&mul(qx, inv(qx)), &IDENTITY);
    }

    #[test]
    fn between_matches_hand_computed_values() {
        // X → Y: axis = X × Y = Z, w = 1 + 0 → (1, 0, 0, 1)/√2.
        let h = 0.5f64.sqrt();
        close(
            &between([1.0, 0.0, 0.0], [0.0, 1.0, 0.0]),
            &[h, 0.0, 0.0, h],
        );
        // Same direction, different lengths: identity.
        close(&between([0.0, 2.0, 0.0], [0.0, 3.0, 0.0]), &IDENTITY);
        let u = [0.2, 0.5, -0.7];
        let v = [-1.0, 0.1, 0.4];
        close(&rot(between(u, v), normalize(u)), &normalize(v));
    }

    #[test]
    fn rot6d_is_first_two_matrix_columns() {
        // 90° about Z: columns are (0,1,0) and (-1,0,0).
        let q = from_axis_angle([0.0, 0.0, 1.0], FRAC_PI_2);
        close(&to_rot6d(q), &[0.0, 1.0, 0.0, -1.0, 0.0, 0.0]);
    }

    #[test]
    fn matrix_round_trip() {
        for v in [
            [0.3, -0.2, 0.9],
            [3.0, 0.0, 0.0],
            [0.0, -3.1, 0.1],
            [0.1, 0.1, -3.0],
        ] {
            let q = from_rotvec(v);
            let q = if q[0] < 0.0 { scale4(q, -1.0) } else { q };
            close(&from_matrix(to_matrix(q)), &q);
        }
    }

    fn scale4(q: Quat, s: f64) -> Quat {
        [q[0] * s, q[1] * s, q[2] * s, q[3] * s]
    }
}
