//! Export of SMPL-22 joint positions as BVH (e.g. for Blender): the SMPL-22 hierarchy with the
//! HumanML3D target skeleton as OFFSETs, in centimetres (Blender's BVH importer has a scale
//! option; 0.01 gives metres), Y up, and per-frame joint rotations recovered by inverse kinematics.
//!
//! The bones out of the pelvis and spine3 take the motion's own shape ([`rest_offsets`]).
//!
//! IK: a joint with one child takes the minimal rotation that turns the rest bone towards the
//! observed child, relative to its parent's global rotation, so single-child chains are exact
//! relative to their parent's position. A joint with several children (pelvis: hips and spine;
//! spine3: neck and collars) takes the least-squares rotation of the rest child directions onto
//! the observed ones (Horn's quaternion method); its children are then off by the mismatch of
//! the observed shape against the rigid rest shape.

use crate::quat::{self, Quat, Vec3, IDENTITY};
use crate::skeleton::{Pose, JOINT_NAMES, NUM_JOINTS, PARENTS, TARGET_OFFSETS};
use std::fmt::Write as _;
use std::path::Path;

/// BVH length unit per metre (OFFSETs and root positions are written in centimetres).
pub const UNITS_PER_METRE: f64 = 100.0;

/// Rotation channel order of every joint; the rotation is Rz · Ry · Rx.
const ROTATION_CHANNELS: &str = "Zrotation Yrotation Xrotation";

/// Children of each joint, in joint order.
fn children(j: usize) -> impl Iterator<Item = usize> {
    (1..NUM_JOINTS).filter(move |&c| PARENTS[c] == j)
}

/// BVH text of a motion: SMPL-22 hierarchy, one MOTION line per pose, `Frame Time` = 1/fps.
pub fn write_bvh(joints: &[Pose], fps: f64) -> String {
    let mut out = String::from("HIERARCHY\n");
    let offsets = rest_offsets(joints);
    write_joint(&mut out, &offsets, 0, 0);
    let _ = writeln!(out, "MOTION\nFrames: {}", joints.len());
    let _ = writeln!(out, "Frame Time: {:.8}", 1.0 / fps);
    let order = hierarchy_order();
    for pose in joints {
        let locals = local_rotations(pose, &offsets);
        let mut values = Vec::with_capacity(3 + 3 * NUM_JOINTS);
        values.extend(pose[0].iter().map(|v| v * UNITS_PER_METRE));
        values.extend(order.iter().flat_map(|&j| euler_zyx_degrees(locals[j])));
        let line = values
            .iter()
            .map(|v| format!("{v:.6}"))
            .collect::<Vec<_>>()
            .join(" ");
        out.push_str(&line);
        out.push('\n');
    }
    out
}

/// Write [`write_bvh`]'s text to `path` atomically.
pub fn write_bvh_file(path: &Path, joints: &[Pose], fps: f64) -> std::io::Result<()> {
    motionscale_core::write_atomic(path, write_bvh(joints, fps).as_bytes())
}

/// Joints in the depth-first order of the HIERARCHY section, which the MOTION values follow.
pub fn hierarchy_order() -> Vec<usize> {
    fn visit(j: usize, order: &mut Vec<usize>) {
        order.push(j);
        for c in children(j) {
            visit(c, order);
        }
    }
    let mut order = Vec::with_capacity(NUM_JOINTS);
    visit(0, &mut order);
    order
}

fn write_joint(out: &mut String, offsets: &[Vec3; NUM_JOINTS], j: usize, depth: usize) {
    let pad = "  ".repeat(depth);
    let offset = offset_text(offsets[j]);
    if j == 0 {
        let _ = writeln!(out, "ROOT {}\n{{", JOINT_NAMES[j]);
        let _ = writeln!(out, "{pad}  OFFSET {offset}");
        let _ = writeln!(
            out,
            "{pad}  CHANNELS 6 Xposition Yposition Zposition {ROTATION_CHANNELS}"
        );
    } else {
        let _ = writeln!(out, "{pad}JOINT {}\n{pad}{{", JOINT_NAMES[j]);
        let _ = writeln!(out, "{pad}  OFFSET {offset}");
        let _ = writeln!(out, "{pad}  CHANNELS 3 {ROTATION_CHANNELS}");
    }
    let mut leaf = true;
    for c in children(j) {
        leaf = false;
        write_joint(out, offsets, c, depth + 1);
    }
    if leaf {
        // End Site half a bone further along the leaf's own bone, so viewers draw its last segment.
        let _ = writeln!(
            out,
            "{pad}  End Site\n{pad}  {{\n{pad}    OFFSET {}\n{pad}  }}",
            offset_text(quat::scale(offsets[j], 0.5))
        );
    }
    let _ = writeln!(out, "{pad}}}");
}

fn offset_text(v: Vec3) -> String {
    format!(
        "{:.6} {:.6} {:.6}",
        v[0] * UNITS_PER_METRE,
        v[1] * UNITS_PER_METRE,
        v[2] * UNITS_PER_METRE
    )
}

/// BVH OFFSETs (metres) for a motion: [`TARGET_OFFSETS`], except that the bones from a joint with
/// several children (pelvis → hips, spine1; spine3 → neck, collars) take the motion's own shape:
/// their observed offsets, turned back by the rotation best fitting them to the target
/// directions, averaged over the frames (mean direction, mean length). SMPL-derived joints keep these bones rigid but not along
/// the axis-aligned target directions (the hips sit below the pelvis), so target directions
/// would leave centimetres of error that no rotation can remove.
pub fn rest_offsets(joints: &[Pose]) -> [Vec3; NUM_JOINTS] {
    let mut offsets = TARGET_OFFSETS;
    if joints.is_empty() {
        return offsets;
    }
    for j in 0..NUM_JOINTS {
        let kids: Vec<usize> = children(j).collect();
        if kids.len() < 2 {
            continue;
        }
        let mut sums = vec![[0.0; 3]; kids.len()];
        let mut lengths = vec![0.0; kids.len()];
        for pose in joints {
            let seen: Vec<Vec3> = kids.iter().map(|&c| quat::sub(pose[c], pose[j])).collect();
            let pairs: Vec<(Vec3, Vec3)> = kids
                .iter()
                .map(|&c| TARGET_OFFSETS[c])
                .zip(seen.iter().copied())
                .collect();
            let back = quat::inv(fit_rotation(&pairs));
            for ((sum, length), s) in sums.iter_mut().zip(&mut lengths).zip(&seen) {
                *sum = quat::add(*sum, quat::rot(back, *s));
                *length += quat::norm(*s);
            }
        }
        // Mean direction at the mean length, so the bone keeps its observed length.
        for ((&c, sum), length) in kids.iter().zip(&sums).zip(&lengths) {
            offsets[c] = quat::scale(quat::normalize(*sum), length / joints.len() as f64);
        }
    }
    offsets
}

/// Local rotation of every joint (relative to its parent; the root's is global) whose forward
/// kinematics over `offsets` reproduces `pose` as closely as the rest shape allows.
pub fn local_rotations(pose: &Pose, offsets: &[Vec3; NUM_JOINTS]) -> [Quat; NUM_JOINTS] {
    let mut local = [IDENTITY; NUM_JOINTS];
    let mut global = [IDENTITY; NUM_JOINTS];
    // Parents precede children in SMPL-22 order, so one pass sees every parent first.
    for j in 0..NUM_JOINTS {
        let parent_global = if j == 0 { IDENTITY } else { global[PARENTS[j]] };
        let to_parent_frame = quat::inv(parent_global);
        let pairs: Vec<(Vec3, Vec3)> = children(j)
            .map(|c| {
                (
                    offsets[c],
                    quat::rot(to_parent_frame, quat::sub(pose[c], pose[j])),
                )
            })
            .filter(|(_, seen)| quat::norm(*seen) > 1e-9)
            .collect();
        local[j] = match pairs.as_slice() {
            [] => IDENTITY,
            [(rest, seen)] => quat::between(*rest, *seen),
            _ => fit_rotation(&pairs),
        };
        global[j] = quat::qnormalize(quat::mul(parent_global, local[j]));
    }
    local
}

/// Rotation best turning the `from` directions onto the `to` directions (unit-weighted
/// least squares), by Horn's method: the top eigenvector of a symmetric 4×4 matrix.
pub fn fit_rotation(pairs: &[(Vec3, Vec3)]) -> Quat {
    let mut s = [[0.0; 3]; 3];
    for &(a, b) in pairs {
        let (a, b) = (quat::normalize(a), quat::normalize(b));
        for (r, row) in s.iter_mut().enumerate() {
            for (c, v) in row.iter_mut().enumerate() {
                *v += a[r] * b[c];
            }
        }
    }
    let [[sxx, sxy, sxz], [syx, syy, syz], [szx, szy, szz]] = s;
    let n = [
        [sxx + syy + szz, syz - szy, szx - sxz, sxy - syx],
        [syz - szy, sxx - syy - szz, sxy + syx, szx + sxz],
        [szx - sxz, sxy + syx, -sxx + syy - szz, syz + szy],
        [sxy - syx, szx + sxz, syz + szy, -sxx - syy + szz],
    ];
    let (values, vectors) = jacobi_eigen4(n);
    let best = (0..4)
        .max_by(|&a, &b| values[a].total_cmp(&values[b]))
        .unwrap_or(0);
    quat::qnormalize([
        vectors[0][best],
        vectors[1][best],
        vectors[2][best],
        vectors[3][best],
    ])
}

/// Eigenvalues and eigenvectors (columns) of a symmetric 4×4 matrix by cyclic Jacobi rotations.
fn jacobi_eigen4(mut a: [[f64; 4]; 4]) -> ([f64; 4], [[f64; 4]; 4]) {
    let mut v = [[0.0; 4]; 4];
    for (i, row) in v.iter_mut().enumerate() {
        row[i] = 1.0;
    }
    for _sweep in 0..50 {
        let off: f64 = (0..4)
            .flat_map(|p| (p + 1..4).map(move |q| (p, q)))
            .map(|(p, q)| a[p][q] * a[p][q])
            .sum();
        if off < 1e-30 {
            break;
        }
        for p in 0..4 {
            for q in p + 1..4 {
                if a[p][q].abs() < 1e-300 {
                    continue;
                }
                let theta = (a[q][q] - a[p][p]) / (2.0 * a[p][q]);
                let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
                let c = 1.0 / (t * t + 1.0).sqrt();
                let s = t * c;
                for row in a.iter_mut() {
                    let (x, y) = (row[p], row[q]);
                    row[p] = c * x - s * y;
                    row[q] = s * x + c * y;
                }
                let (row_p, row_q) = (a[p], a[q]);
                a[p] = std::array::from_fn(|k| c * row_p[k] - s * row_q[k]);
                a[q] = std::array::from_fn(|k| s * row_p[k] + c * row_q[k]);
                for row in v.iter_mut() {
                    let (vkp, vkq) = (row[p], row[q]);
                    row[p] = c * vkp - s * vkq;
                    row[q] = s * vkp + c * vkq;
                }
            }
        }
    }
    ([a[0][0], a[1][1], a[2][2], a[3][3]], v)
}

/// Euler angles (degrees) in channel order Z, Y, X of a rotation R = Rz(z) · Ry(y) · Rx(x).
pub fn euler_zyx_degrees(q: Quat) -> [f64; 3] {
    let m = quat::to_matrix(q);
    let sy = (-m[2][0]).clamp(-1.0, 1.0);
    let y = sy.asin();
    let (z, x) = if sy.abs() < 1.0 - 1e-12 {
        (m[1][0].atan2(m[0][0]), m[2][1].atan2(m[2][2]))
    } else {
        // Gimbal lock: only z ± x is defined; put it all in z.
        ((-m[0][1]).atan2(m[1][1]), 0.0)
    };
    [z.to_degrees(), y.to_degrees(), x.to_degrees()]
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: &[f64], b: &[f64], tol: f64) {
        for (x, y) in a.iter().zip(b) {
            assert!((x - y).abs() < tol, "{a:?} vs {b:?}");
        }
    }

    #[test]
    fn horn_fit_recovers_a_rotation() {
        let q = quat::from_rotvec([0.4, -1.1, 0.7]);
        let dirs = [[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]];
        let pairs: Vec<_> = dirs.iter().map(|&d| (d, quat::rot(q, d))).collect();
        let fit = fit_rotation(&pairs);
        let fit = if fit[0] * q[0] < 0.0 {
            [-fit[0], -fit[1], -fit[2], -fit[3]]
        } else {
            fit
        };
        close(&fit, &q, 1e-10);
    }

    #[test]
    fn euler_angles_rebuild_the_rotation() {
        for v in [
            [0.3, -0.2, 0.9],
            [0.0, std::f64::consts::FRAC_PI_2, 0.0],
            [2.0, 1.0, -0.5],
        ] {
            let q = quat::from_rotvec(v);
            let [z, y, x] = euler_zyx_degrees(q);
            let rebuilt = quat::mul(
                quat::from_axis_angle([0.0, 0.0, 1.0], z.to_radians()),
                quat::mul(
                    quat::from_axis_angle([0.0, 1.0, 0.0], y.to_radians()),
                    quat::from_axis_angle([1.0, 0.0, 0.0], x.to_radians()),
                ),
            );
            let p = [0.2, -0.7, 0.4];
            close(&quat::rot(rebuilt, p), &quat::rot(q, p), 1e-6);
        }
    }
}
