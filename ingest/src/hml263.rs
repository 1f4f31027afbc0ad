//! HumanML3D 263-d motion features (the reference's `process_file`) and their inverse
//! (`recover_from_ric`), ported to f64 from `docs/features-263.md`.
//!
//! The port is mathematically identical to the reference, with two simplifications that
//! only change rounding: in step 1 the IK root rotation cancels in the FK (R · R⁻¹ · G), so
//! retargeting reduces to rescaling every bone along its own direction (so step 1's hip
//! order, quirky or fixed, cannot change the result); and in step 6 the
//! chained local rotation `R⁻¹ · between(u, v)` is computed as `G_parent⁻¹ · G_child`, where
//! G is the bone's global rotation `between(u, v)` (the chain start uses the root rotation).
//! Where the reference divides 0 by 0 (a bone or the facing exactly opposite its target
//! direction) this port uses the limiting half-turn instead of producing NaN.

use crate::error::IngestError;
use crate::quat::{self, Quat, Vec3};
use crate::skeleton::{
    Pose, CHAINS, FACE_JOINTS, FEET_LEFT, FEET_RIGHT, JOINT_NAMES, NUM_JOINTS, PARENTS,
    RAW_OFFSETS, TARGET_OFFSETS,
};
use std::sync::OnceLock;

/// Width of one feature row.
pub const FEATURE_DIM: usize = 263;

/// Feature blocks (start, end) used by block-averaged std: [0,1),[1,3),[3,4),[4,67),[67,193),[193,259),[259,263)
pub const BLOCKS: [(usize, usize); 7] = [
    (0, 1),
    (1, 3),
    (3, 4),
    (4, 67),
    (67, 193),
    (193, 259),
    (259, 263),
];

const RIC: usize = 4;
const ROT6D: usize = 67;
const LOCAL_VEL: usize = 193;
const FEET: usize = 259;
/// Foot joints in feature order: left (ankle, foot), then right.
const FEET_JOINTS: [usize; 4] = [FEET_LEFT[0], FEET_LEFT[1], FEET_RIGHT[0], FEET_RIGHT[1]];
/// Lower-leg joints whose offsets define the retargeting scale.
const LEG_JOINTS: [usize; 2] = [5, 8];

/// Gaussian sigma (frames) of the facing smoothing in step 6.
const SIGMA: f64 = 20.0;
/// Kernel radius: scipy's `int(truncate * sigma + 0.5)` with truncate = 4.
const RADIUS: usize = 80;
const TAPS: usize = 2 * RADIUS + 1;

/// Options of [`process`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Hml263Options {
    /// Foot-contact threshold on the squared per-frame displacement (m²); HumanML3D uses 0.002.
    pub feet_threshold: f64,
    /// Use the anatomically correct hip order in the IK facing of step 6 (not HumanML3D-compatible).
    pub fix_facing: bool,
}

impl Default for Hml263Options {
    fn default() -> Self {
        Self {
            feet_threshold: 0.002,
            fix_facing: false,
        }
    }
}

/// Output of [`process`] for a clip of T frames.
#[derive(Debug, Clone, PartialEq)]
pub struct Hml263 {
    /// Feature rows, (T−1) × [`FEATURE_DIM`], row-major.
    pub features: Vec<f32>,
    /// Global joint positions after retargeting, floor, origin and facing (steps 1–4), T frames.
    pub joints: Vec<Pose>,
}

/// Bones (parent, child, parent starts its chain) in chain order, so parents precede children.
const BONES: [(usize, usize, bool); NUM_JOINTS - 1] = bones();

const fn bones() -> [(usize, usize, bool); NUM_JOINTS - 1] {
    let mut out = [(0, 0, false); NUM_JOINTS - 1];
    let mut n = 0;
    let mut c = 0;
    while c < CHAINS.len() {
        let chain = CHAINS[c];
        let mut i = 1;
        while i < chain.len() {
            out[n] = (chain[i - 1], chain[i], i == 1);
            n += 1;
            i += 1;
        }
        c += 1;
    }
    out
}

/// Target bone lengths; each target offset has a single non-zero component.
const TARGET_LENGTHS: [f64; NUM_JOINTS] = target_lengths();

const fn target_lengths() -> [f64; NUM_JOINTS] {
    let mut out = [0.0; NUM_JOINTS];
    let mut j = 0;
    while j < NUM_JOINTS {
        let o = TARGET_OFFSETS[j];
        out[j] = o[0].abs() + o[1].abs() + o[2].abs();
        j += 1;
    }
    out
}

/// Normalised Gaussian weights (scipy `_gaussian_kernel1d`: exp(−x²/2σ²) / sum), computed once.
fn gaussian_kernel() -> &'static [f64; TAPS] {
    static KERNEL: OnceLock<[f64; TAPS]> = OnceLock::new();
    KERNEL.get_or_init(|| {
        let mut w = [0.0; TAPS];
        for (i, wi) in w.iter_mut().enumerate() {
            let x = i as f64 - RADIUS as f64;
            *wi = (-0.5 / (SIGMA * SIGMA) * x * x).exp();
        }
        let sum: f64 = w.iter().sum();
        w.iter_mut().for_each(|wi| *wi /= sum);
        w
    })
}

/// scipy `gaussian_filter1d(xs, 20, mode='nearest')` into `out`; `pad` is scratch space.
fn gaussian_nearest(xs: &[f64], pad: &mut Vec<f64>, out: &mut [f64]) {
    let n = xs.len();
    let (Some(&first), Some(&last)) = (xs.first(), xs.last()) else {
        return;
    };
    pad.clear();
    pad.resize(RADIUS, first);
    pad.extend_from_slice(xs);
    pad.resize(n + 2 * RADIUS, last);
    let w = gaussian_kernel();
    for (o, &p) in out.iter_mut().zip(&pad[RADIUS..RADIUS + n]) {
        *o = w[RADIUS] * p;
    }
    // The kernel is symmetric: pair taps ±k. Tap-outer order keeps the inner loop a
    // contiguous, vectorisable axpy.
    for k in 1..=RADIUS {
        let (lo, hi) = (
            &pad[RADIUS - k..RADIUS - k + n],
            &pad[RADIUS + k..RADIUS + k + n],
        );
        for ((o, &a), &b) in out.iter_mut().zip(lo).zip(hi) {
            *o += w[RADIUS + k] * (a + b);
        }
    }
}

/// A rotation about +Y stored as (w, y) of the quaternion (w, 0, y, 0).
#[derive(Debug, Clone, Copy)]
struct Yaw {
    w: f64,
    y: f64,
}

impl Yaw {
    const IDENTITY: Yaw = Yaw { w: 1.0, y: 0.0 };

    /// `between((fx, 0, fz), +Z)`, or `None` for a zero vector. The half-turn stands in for the
    /// reference's 0/0 when the vector points exactly along −Z.
    fn to_z(fx: f64, fz: f64) -> Option<Yaw> {
        let n = (fx * fx + fz * fz).sqrt();
        if n == 0.0 {
            return None;
        }
        // w = |f| + f·z, rewritten for fz < 0 to avoid cancellation near the half-turn.
        let w = if fz >= 0.0 {
            n + fz
        } else {
            fx * fx / (n - fz)
        };
        let y = -fx;
        let qn = (w * w + y * y).sqrt();
        Some(if qn > 0.0 {
            Yaw {
                w: w / qn,
                y: y / qn,
            }
        } else {
            Yaw { w: 0.0, y: 1.0 }
        })
    }

    fn quat(self) -> Quat {
        [self.w, 0.0, self.y, 0.0]
    }

    /// (cos θ, sin θ) of the rotation angle θ, i.e. the rotation matrix's XZ entries.
    fn cos_sin(self) -> (f64, f64) {
        (1.0 - 2.0 * self.y * self.y, 2.0 * self.w * self.y)
    }
}

/// Rotate (x, z) by the yaw with matrix entries (c, s) = (cos θ, sin θ).
#[inline]
fn yaw_xz((c, s): (f64, f64), x: f64, z: f64) -> (f64, f64) {
    (c * x + s * z, c * z - s * x)
}

/// `between(u, v)` before normalisation, for a unit `u` and a non-zero `v` of known length
/// `n`: (|v| + u·v, u × v). Zero only where `v` points exactly against `u`.
#[inline]
fn between_unnormalised(u: Vec3, v: Vec3, n: f64) -> Quat {
    let d = quat::dot(u, v);
    let a = quat::cross(u, v);
    // w = |v| + u·v, rewritten for u·v < 0 to avoid cancellation near the half-turn.
    let w = if d >= 0.0 {
        n + d
    } else {
        quat::dot(a, a) / (n - d)
    };
    [w, a[0], a[1], a[2]]
}

/// The limit of `between(u, v)` as `v` turns to −u (the reference divides 0 by 0 there): a
/// half-turn about an axis perpendicular to the unit `u`.
fn half_turn(u: Vec3) -> Quat {
    let (ax, ay, az) = (u[0].abs(), u[1].abs(), u[2].abs());
    let e = if ax <= ay && ax <= az {
        [1.0, 0.0, 0.0]
    } else if ay <= az {
        [0.0, 1.0, 0.0]
    } else {
        [0.0, 0.0, 1.0]
    };
    let p = quat::normalize(quat::cross(u, e));
    [0.0, p[0], p[1], p[2]]
}

/// Forward (x, z) of a pose from the normalised across vector (steps 4 and 6), or `None`
/// when the across vector is zero. `reference_quirk` takes the IK's reversed hip pair.
#[inline]
fn facing(p: &Pose, reference_quirk: bool) -> Option<(f64, f64)> {
    let [r_hip, l_hip, r_sdr, l_sdr] = FACE_JOINTS;
    let hips = if reference_quirk {
        quat::sub(p[l_hip], p[r_hip])
    } else {
        quat::sub(p[r_hip], p[l_hip])
    };
    let across = quat::add(hips, quat::sub(p[r_sdr], p[l_sdr]));
    let n = quat::norm(across);
    if n == 0.0 {
        return None;
    }
    // (0, 1, 0) × across = (across.z, 0, −across.x).
    Some((across[2] / n, -across[0] / n))
}

fn bone_error(t: usize, p: usize, c: usize) -> String {
    format!(
        "frame {t}: bone {} → {} has zero length",
        JOINT_NAMES[p], JOINT_NAMES[c]
    )
}

/// Steps 1–2: validate, retarget to the target skeleton (bones rescaled along their
/// directions, root × leg-length ratio) and lift the floor to y = 0.
fn retarget(poses: &[Pose], out: &mut Vec<Pose>) -> Result<(), IngestError> {
    let first = &poses[0];
    let src_leg: f64 = LEG_JOINTS
        .iter()
        .map(|&j| quat::norm(quat::sub(first[j], first[PARENTS[j]])))
        .sum();
    let tgt_leg: f64 = LEG_JOINTS.iter().map(|&j| TARGET_LENGTHS[j]).sum();
    let scale = tgt_leg / src_leg;
    out.clear();
    let mut floor = f64::INFINITY;
    for (t, src) in poses.iter().enumerate() {
        for (j, v) in src.iter().enumerate() {
            if let Some(x) = v.iter().find(|x| !x.is_finite()) {
                return Err(format!(
                    "frame {t}, joint {j} ({}): non-finite coordinate {x}",
                    JOINT_NAMES[j]
                )
                .into());
            }
        }
        let mut dst = [[0.0; 3]; NUM_JOINTS];
        dst[0] = quat::scale(src[0], scale);
        // Bone vectors and their rescale factors first, in a branch-free pass whose square
        // roots and divisions can overlap; a zero-length bone gives an infinite factor.
        let mut bone = [[0.0; 3]; NUM_JOINTS - 1];
        let mut factor = [0.0; NUM_JOINTS - 1];
        for ((b, f), &(p, c, _)) in bone.iter_mut().zip(&mut factor).zip(&BONES) {
            *b = quat::sub(src[c], src[p]);
            *f = TARGET_LENGTHS[c] / quat::norm(*b);
        }
        for ((b, &f), &(p, c, _)) in bone.iter().zip(&factor).zip(&BONES) {
            if f.is_infinite() {
                return Err(bone_error(t, p, c).into());
            }
            dst[c] = quat::add(dst[p], quat::scale(*b, f));
        }
        floor = dst.iter().fold(floor, |m, v| m.min(v[1]));
        out.push(dst);
    }
    for pose in out.iter_mut() {
        pose.iter_mut().for_each(|v| v[1] -= floor);
    }
    Ok(())
}

/// Compute the HumanML3D 263-d features of a clip (T × 22 joint positions, metres, Y up).
/// Errors: fewer than 2 frames, non-finite input (names the frame/joint), a zero-length bone,
/// degenerate facing (zero across vector).
pub fn process(poses: &[Pose], opts: &Hml263Options) -> Result<Hml263, IngestError> {
    let mut out = Hml263 {
        features: Vec::new(),
        joints: Vec::new(),
    };
    Hml263Extractor::default().process_into(poses, opts, &mut out)?;
    Ok(out)
}

/// [`process`] with scratch buffers kept between clips, for callers that extract many clips
/// on one thread (saves the allocations and page faults of fresh buffers).
#[derive(Debug, Default)]
pub struct Hml263Extractor {
    fwd_x: Vec<f64>,
    fwd_z: Vec<f64>,
    smooth_x: Vec<f64>,
    smooth_z: Vec<f64>,
    pad: Vec<f64>,
    root: Vec<Yaw>,
}

impl Hml263Extractor {
    /// Like [`process`], but writes into `out`, reusing its vectors' capacity; on error `out`
    /// holds partial results.
    pub fn process_into(
        &mut self,
        poses: &[Pose],
        opts: &Hml263Options,
        out: &mut Hml263,
    ) -> Result<(), IngestError> {
        let frames = poses.len();
        if frames < 2 {
            return Err(format!("need at least 2 frames, got {frames}").into());
        }
        let joints = &mut out.joints;
        retarget(poses, joints)?;

        // Steps 3–4: frame-0 root to the XZ origin, frame 0 facing +Z (correct hip order here).
        let (fx, fz) = facing(&joints[0], false)
            .ok_or("frame 0: degenerate facing (across vector is zero)".to_string())?;
        let face = Yaw::to_z(fx, fz)
            .ok_or("frame 0: degenerate facing (across vector is vertical)".to_string())?
            .cos_sin();
        let (ox, oz) = (joints[0][0][0], joints[0][0][2]);
        let quirk = !opts.fix_facing;
        self.fwd_x.clear();
        self.fwd_z.clear();
        for (t, pose) in joints.iter_mut().enumerate() {
            for v in pose.iter_mut() {
                (v[0], v[2]) = yaw_xz(face, v[0] - ox, v[2] - oz);
            }
            let (x, z) = facing(pose, quirk)
                .ok_or_else(|| format!("frame {t}: degenerate facing (across vector is zero)"))?;
            self.fwd_x.push(x);
            self.fwd_z.push(z);
        }

        // Step 6 root rotations: smoothed facing to +Z, frame 0 forced to identity.
        self.smooth_x.resize(frames, 0.0);
        self.smooth_z.resize(frames, 0.0);
        gaussian_nearest(&self.fwd_x, &mut self.pad, &mut self.smooth_x[..frames]);
        gaussian_nearest(&self.fwd_z, &mut self.pad, &mut self.smooth_z[..frames]);
        self.root.clear();
        self.root.push(Yaw::IDENTITY);
        for t in 1..frames {
            let r = Yaw::to_z(self.smooth_x[t], self.smooth_z[t]).ok_or_else(|| {
                format!("frame {t}: degenerate facing (smoothed forward vector is zero)")
            })?;
            self.root.push(r);
        }

        out.features.clear();
        out.features.resize((frames - 1) * FEATURE_DIM, 0.0);
        for (t, row) in out.features.chunks_exact_mut(FEATURE_DIM).enumerate() {
            let (r, r_next) = (self.root[t], self.root[t + 1]);
            write_row(row, &joints[t], &joints[t + 1], r, r_next, opts);
        }
        Ok(())
    }
}

/// Fill one feature row from frames t and t+1 (retargeted, so every bone has its target
/// length) and their root rotations.
fn write_row(row: &mut [f32], cur: &Pose, next: &Pose, r: Yaw, r_next: Yaw, opts: &Hml263Options) {
    // Step 7: angular velocity = arcsin of y of r[t+1] · r[t]⁻¹; linear velocity in r[t+1]'s frame.
    let dy = r_next.y * r.w - r_next.w * r.y;
    row[0] = dy.clamp(-1.0, 1.0).asin() as f32;
    let (vx, vz) = yaw_xz(
        r_next.cos_sin(),
        next[0][0] - cur[0][0],
        next[0][2] - cur[0][2],
    );
    row[1] = vx as f32;
    row[2] = vz as f32;
    row[3] = cur[0][1] as f32;

    // Step 8: positions relative to the root's XZ, in the root's frame.
    let cs = r.cos_sin();
    for (j, v) in cur.iter().enumerate().skip(1) {
        let (x, z) = yaw_xz(cs, v[0] - cur[0][0], v[2] - cur[0][2]);
        let o = RIC + 3 * (j - 1);
        row[o] = x as f32;
        row[o + 1] = v[1] as f32;
        row[o + 2] = z as f32;
    }

    // Step 6 locals: G_parent⁻¹ · G_child, with the root rotation at each chain start.
    // Unnormalised bone rotations, then all their norms in one branch-free pass whose square
    // roots and divisions can overlap.
    let mut unnormalised = [[0.0; 4]; NUM_JOINTS - 1];
    for (q, &(p, c, _)) in unnormalised.iter_mut().zip(&BONES) {
        let v = quat::sub(cur[c], cur[p]);
        *q = between_unnormalised(RAW_OFFSETS[c], v, TARGET_LENGTHS[c]);
    }
    let mut inv_norm = [0.0; NUM_JOINTS - 1];
    for (k, q) in inv_norm.iter_mut().zip(&unnormalised) {
        *k = 1.0 / (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]).sqrt();
    }
    let mut global = [quat::IDENTITY; NUM_JOINTS];
    for ((q, &k), &(p, c, chain_start)) in unnormalised.iter().zip(&inv_norm).zip(&BONES) {
        let g = if k.is_finite() {
            q.map(|x| x * k)
        } else {
            half_turn(RAW_OFFSETS[c])
        };
        let parent = if chain_start { r.quat() } else { global[p] };
        global[c] = g;
        let six = quat::to_rot6d(quat::mul(quat::inv(parent), g));
        let o = ROT6D + 6 * (c - 1);
        for (dst, v) in row[o..o + 6].iter_mut().zip(six) {
            *dst = v as f32;
        }
    }

    // Step 9: joint displacements to the next frame, in the root's frame.
    for (j, (a, b)) in cur.iter().zip(next).enumerate() {
        let (x, z) = yaw_xz(cs, b[0] - a[0], b[2] - a[2]);
        let o = LOCAL_VEL + 3 * j;
        row[o] = x as f32;
        row[o + 1] = (b[1] - a[1]) as f32;
        row[o + 2] = z as f32;
    }

    // Step 5: foot contacts.
    for (k, &j) in FEET_JOINTS.iter().enumerate() {
        let d = quat::sub(next[j], cur[j]);
        row[FEET + k] = if quat::dot(d, d) < opts.feet_threshold {
            1.0
        } else {
            0.0
        };
    }
}

/// recover_from_ric: features (n×263 row-major) → n×22 joint positions. A trailing partial
/// row is ignored.
pub fn recover_joints(features: &[f32]) -> Vec<Pose> {
    let mut out = Vec::with_capacity(features.len() / FEATURE_DIM);
    // Root yaw quaternion (cos a, 0, sin a, 0), a = Σ_{k<t} f[k][0]; inverse rotation has −sin a.
    let mut angle = 0.0f64;
    let (mut root_x, mut root_z) = (0.0f64, 0.0f64);
    let mut prev_vel: Option<(f64, f64)> = None;
    for row in features.chunks_exact(FEATURE_DIM) {
        let inv_rot = Yaw {
            w: angle.cos(),
            y: -angle.sin(),
        }
        .cos_sin();
        if let Some((vx, vz)) = prev_vel {
            let (dx, dz) = yaw_xz(inv_rot, vx, vz);
            root_x += dx;
            root_z += dz;
        }
        let mut pose = [[0.0; 3]; NUM_JOINTS];
        pose[0] = [root_x, f64::from(row[3]), root_z];
        for (j, v) in pose.iter_mut().enumerate().skip(1) {
            let o = RIC + 3 * (j - 1);
            let (x, z) = yaw_xz(inv_rot, f64::from(row[o]), f64::from(row[o + 2]));
            *v = [x + root_x, f64::from(row[o + 1]), z + root_z];
        }
        out.push(pose);
        angle += f64::from(row[0]);
        prev_vel = Some((f64::from(row[1]), f64::from(row[2])));
    }
    out
}

/// [`recover_joints`] as n×22×3 f32 values, the layout of a HumanML3D `new_joints` file.
pub fn recover_joints_f32(features: &[f32]) -> Vec<f32> {
    recover_joints(features)
        .iter()
        .flatten()
        .flatten()
        .map(|&v| v as f32)
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A pose built from per-joint offsets (joint minus parent), root at 0.95 m.
    fn build(offsets: &[Vec3; NUM_JOINTS]) -> Pose {
        let mut p = [[0.0; 3]; NUM_JOINTS];
        p[0] = [0.0, 0.95, 0.0];
        for &(par, c, _) in &BONES {
            p[c] = quat::add(p[par], offsets[c]);
        }
        p
    }

    /// A standing pose facing +Z with the target bone lengths; the arms are lowered slightly
    /// so no bone is exactly along its rest direction's opposite.
    fn base_pose() -> Pose {
        let mut o = TARGET_OFFSETS;
        o[16] = [0.1, o[16][1], 0.02];
        o[17] = [-0.1, o[17][1], 0.02];
        build(&o)
    }

    /// A deterministic walking-like clip: root moves and turns, limbs swing.
    fn clip(frames: usize) -> Vec<Pose> {
        let base = base_pose();
        (0..frames)
            .map(|t| {
                let ph = t as f64 * 0.21;
                let turn = quat::from_axis_angle([0.0, 1.0, 0.0], 0.4 * (t as f64 * 0.05).sin());
                let swing = quat::from_axis_angle([1.0, 0.0, 0.0], 0.5 * ph.sin());
                let mut p = [[0.0; 3]; NUM_JOINTS];
                p[0] = [0.02 * t as f64, 0.95 + 0.02 * ph.cos(), 0.03 * t as f64];
                for &(par, c, _) in &BONES {
                    let rest = quat::sub(base[c], base[par]);
                    let local = if matches!(c, 4 | 7 | 18) {
                        quat::rot(swing, rest)
                    } else if matches!(c, 5 | 8 | 19) {
                        quat::rot(quat::inv(swing), rest)
                    } else {
                        rest
                    };
                    p[c] = quat::add(p[par], quat::rot(turn, local));
                }
                p
            })
            .collect()
    }

    fn transform(poses: &[Pose], q: Quat, shift: Vec3, scale: f64) -> Vec<Pose> {
        poses
            .iter()
            .map(|p| p.map(|v| quat::add(quat::scale(quat::rot(q, v), scale), shift)))
            .collect()
    }

    fn max_diff(a: &[f32], b: &[f32]) -> f32 {
        a.iter()
            .zip(b)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f32::max)
    }

    #[test]
    fn bones_follow_chain_order() {
        assert_eq!(BONES[0], (0, 2, true));
        assert_eq!(BONES[4], (0, 1, true));
        assert_eq!(BONES[11], (9, 12, false));
        assert_eq!(BONES[17], (9, 13, true));
        assert!((TARGET_LENGTHS[8] - 0.425643325).abs() < 1e-15);
    }

    #[test]
    fn gaussian_kernel_is_normalised_gaussian() {
        let w = gaussian_kernel();
        assert!((w.iter().sum::<f64>() - 1.0).abs() < 1e-14);
        // Centre weight ≈ 1 / (σ√(2π)) (the 4σ truncation removes only ~6e-5 of the mass).
        let centre = 1.0 / (SIGMA * (2.0 * std::f64::consts::PI).sqrt());
        assert!((w[RADIUS] - centre).abs() < 2e-6, "{}", w[RADIUS]);
        assert!((w[RADIUS + 20] / w[RADIUS] - (-0.5f64).exp()).abs() < 1e-15);
        assert_eq!(w[RADIUS - 7], w[RADIUS + 7]);
    }

    #[test]
    fn gaussian_filter_constant_impulse_and_border() {
        let w = gaussian_kernel();
        let mut pad = Vec::new();
        let constant = vec![0.7; 37];
        let mut out = vec![0.0; 37];
        gaussian_nearest(&constant, &mut pad, &mut out);
        assert!(out.iter().all(|v| (v - 0.7).abs() < 1e-14));

        // Impulse in the middle of a long signal: the response is the kernel itself.
        let mut impulse = vec![0.0; 301];
        impulse[150] = 1.0;
        let mut out = vec![0.0; 301];
        gaussian_nearest(&impulse, &mut pad, &mut out);
        for k in 0..TAPS {
            assert!((out[150 - RADIUS + k] - w[k]).abs() < 1e-16);
        }
        assert_eq!(out[150 - RADIUS - 1], 0.0);

        // 'nearest' border: a first-sample impulse counts once for every clamped tap,
        // so y[0] = w[0] + (1 − w[0]) / 2 and y[1] = (1 − w[0]) / 2.
        let mut edge = vec![0.0; 200];
        edge[0] = 1.0;
        let mut out = vec![0.0; 200];
        gaussian_nearest(&edge, &mut pad, &mut out);
        assert!((out[0] - (1.0 + w[RADIUS]) / 2.0).abs() < 1e-15);
        assert!((out[1] - (1.0 - w[RADIUS]) / 2.0).abs() < 1e-15);

        // Shorter than the radius: every tap clamps to one of the two samples.
        let mut out = vec![0.0; 2];
        gaussian_nearest(&[1.0, 3.0], &mut pad, &mut out);
        let left: f64 = w[..=RADIUS].iter().sum();
        assert!((out[0] - (left + 3.0 * (1.0 - left))).abs() < 1e-14);
    }

    #[test]
    fn bone_rotation_matches_quat_between_and_has_half_turn_limit() {
        for v in [[0.3, -0.9, 0.1], [0.0, -2.0, 0.0], [-0.2, 0.5, 1.5]] {
            let u = [0.0, -1.0, 0.0];
            let a = quat::qnormalize(between_unnormalised(u, v, quat::norm(v)));
            let b = quat::between(u, v);
            assert!(
                a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-14),
                "{a:?} vs {b:?}"
            );
        }
        for u in [[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0]] {
            assert_eq!(between_unnormalised(u, quat::scale(u, -2.5), 2.5), [0.0; 4]);
            let q = half_turn(u);
            let r = quat::rot(q, u);
            assert!(quat::norm(quat::add(r, u)) < 1e-15, "{u:?} → {r:?}");
        }
        let y = Yaw::to_z(0.0, -3.0).expect("non-zero");
        assert_eq!((y.w, y.y), (0.0, 1.0));
        assert!(Yaw::to_z(0.0, 0.0).is_none());
    }

    /// The reference's step 1, literally: IK with chained locals, then FK with target offsets.
    fn literal_retarget(poses: &[Pose], quirk: bool) -> Vec<Pose> {
        let p0 = &poses[0];
        let src_leg = quat::norm(quat::sub(p0[5], p0[2])) + quat::norm(quat::sub(p0[8], p0[5]));
        let scale = (TARGET_LENGTHS[5] + TARGET_LENGTHS[8]) / src_leg;
        poses
            .iter()
            .enumerate()
            .map(|(t, p)| {
                let (fx, fz) = facing(p, quirk).expect("facing");
                let fwd = quat::normalize([fx, 0.0, fz]);
                let root = if t == 0 {
                    quat::IDENTITY
                } else {
                    quat::between(fwd, [0.0, 0.0, 1.0])
                };
                let mut local = [quat::IDENTITY; NUM_JOINTS];
                for chain in CHAINS {
                    let mut r = root;
                    for w in chain.windows(2) {
                        let v = quat::normalize(quat::sub(p[w[1]], p[w[0]]));
                        let l = quat::mul(quat::inv(r), quat::between(RAW_OFFSETS[w[1]], v));
                        local[w[1]] = l;
                        r = quat::mul(r, l);
                    }
                }
                let mut out = [[0.0; 3]; NUM_JOINTS];
                out[0] = quat::scale(p[0], scale);
                for chain in CHAINS {
                    let mut r = root;
                    for w in chain.windows(2) {
                        r = quat::mul(r, local[w[1]]);
                        out[w[1]] = quat::add(quat::rot(r, TARGET_OFFSETS[w[1]]), out[w[0]]);
                    }
                }
                out
            })
            .collect()
    }

    #[test]
    fn retarget_equals_literal_ik_then_fk() {
        let poses = transform(&clip(12), quat::IDENTITY, [0.0, 0.0, 0.0], 1.17);
        let mut ours = Vec::new();
        retarget(&poses, &mut ours).expect("retarget");
        let floor = |ps: &[Pose]| {
            ps.iter()
                .flat_map(|p| p.iter().map(|v| v[1]))
                .fold(f64::INFINITY, f64::min)
        };
        for quirk in [true, false] {
            let lit = literal_retarget(&poses, quirk);
            let f = floor(&lit);
            for (a, b) in ours.iter().zip(&lit) {
                for (x, y) in a.iter().zip(b) {
                    for k in 0..3 {
                        let y = if k == 1 { y[k] - f } else { y[k] };
                        assert!((x[k] - y).abs() < 1e-12, "{x:?} vs {y:?}");
                    }
                }
            }
        }
    }

    #[test]
    fn yaw_translation_and_scale_leave_features_unchanged() {
        let poses = clip(60);
        let base = process(&poses, &Hml263Options::default()).expect("base");
        let yaw = quat::from_axis_angle([0.0, 1.0, 0.0], 2.3);
        let moved = transform(&poses, yaw, [3.0, 0.4, -7.5], 1.0);
        let out = process(&moved, &Hml263Options::default()).expect("moved");
        assert!(max_diff(&base.features, &out.features) < 2e-6);
        // A uniformly larger performer retargets to the same skeleton.
        let scaled = transform(&poses, quat::IDENTITY, [0.0, 0.0, 0.0], 1.3);
        let out = process(&scaled, &Hml263Options::default()).expect("scaled");
        assert!(max_diff(&base.features, &out.features) < 2e-6);
        // A tilt is not an invariance: the features must change.
        let tilt = quat::from_axis_angle([1.0, 0.0, 0.0], 0.3);
        let out = process(
            &transform(&poses, tilt, [0.0; 3], 1.0),
            &Hml263Options::default(),
        )
        .expect("tilted");
        assert!(max_diff(&base.features, &out.features) > 1e-2);
    }

    #[test]
    fn features_recover_the_global_joints() {
        for frames in [2, 3, 4, 90, 200] {
            let out = process(&clip(frames), &Hml263Options::default()).expect("process");
            assert_eq!(out.features.len(), (frames - 1) * FEATURE_DIM);
            assert_eq!(out.joints.len(), frames);
            assert!(out.features.iter().all(|v| v.is_finite()));
            let rec = recover_joints(&out.features);
            assert_eq!(rec.len(), frames - 1);
            for (t, (a, b)) in rec.iter().zip(&out.joints).enumerate() {
                for (x, y) in a.iter().zip(b) {
                    for k in 0..3 {
                        assert!((x[k] - y[k]).abs() < 1e-5, "T={frames} frame {t}");
                    }
                }
            }
        }
    }

    #[test]
    fn extractor_reuse_matches_fresh_process() {
        let opts = Hml263Options::default();
        let mut ex = Hml263Extractor::default();
        let mut out = process(&clip(3), &opts).expect("warm-up");
        for frames in [120, 7, 120, 2] {
            let poses = clip(frames);
            ex.process_into(&poses, &opts, &mut out).expect("reuse");
            assert_eq!(out, process(&poses, &opts).expect("fresh"), "T={frames}");
        }
    }

    #[test]
    fn facing_steps_put_frame_zero_on_the_floor_at_the_origin_facing_z() {
        let poses = transform(
            &clip(5),
            quat::from_axis_angle([0.0, 1.0, 0.0], -1.1),
            [1.0, 2.0, 3.0],
            1.0,
        );
        let out = process(&poses, &Hml263Options::default()).expect("process");
        let j0 = &out.joints[0];
        assert!(j0[0][0].abs() < 1e-12 && j0[0][2].abs() < 1e-12);
        let min_y = out
            .joints
            .iter()
            .flat_map(|p| p.iter().map(|v| v[1]))
            .fold(f64::INFINITY, f64::min);
        assert!(min_y.abs() < 1e-12);
        let (fx, fz) = facing(j0, false).expect("facing");
        assert!(fx.abs() < 1e-12 && fz > 0.0);
    }

    #[test]
    fn fix_facing_selects_the_hip_order_of_the_root_rotation() {
        // A static pose with the shoulders twisted 0.5 rad against the hips.
        let mut pose = base_pose();
        let twist = quat::from_axis_angle([0.0, 1.0, 0.0], 0.5);
        for j in [13, 14, 16, 17, 18, 19, 20, 21] {
            pose[j] = quat::add(pose[9], quat::rot(twist, quat::sub(pose[j], pose[9])));
        }
        let poses = vec![pose; 4];
        for fix in [false, true] {
            let opts = Hml263Options {
                fix_facing: fix,
                ..Default::default()
            };
            let out = process(&poses, &opts).expect("process");
            let g = &out.joints[1];
            let (fx, fz) = facing(g, !fix).expect("facing");
            let yaw = fx.atan2(fz);
            // ric of row 1 = joints relative to the root, turned by −yaw (forward onto +Z).
            let row = &out.features[FEATURE_DIM..2 * FEATURE_DIM];
            let (c, s) = (yaw.cos(), yaw.sin());
            for j in 1..NUM_JOINTS {
                let (x, z) = (g[j][0] - g[0][0], g[j][2] - g[0][2]);
                let o = RIC + 3 * (j - 1);
                assert!(
                    (f64::from(row[o]) - (c * x - s * z)).abs() < 1e-6,
                    "fix={fix}"
                );
                assert!(
                    (f64::from(row[o + 2]) - (s * x + c * z)).abs() < 1e-6,
                    "fix={fix}"
                );
            }
            // Frame 0's root rotation is the identity: its ric is the plain offset.
            for j in 1..NUM_JOINTS {
                let o = RIC + 3 * (j - 1);
                let x = out.joints[0][j][0] - out.joints[0][0][0];
                assert!((f64::from(out.features[o]) - x).abs() < 1e-6);
            }
        }
    }

    #[test]
    fn foot_contacts_follow_the_threshold() {
        let mut poses = clip(3);
        // Freeze frame 1 = frame 2 so every foot is still between them.
        poses[2] = poses[1];
        let out = process(&poses, &Hml263Options::default()).expect("process");
        assert_eq!(
            &out.features[FEATURE_DIM + FEET..2 * FEATURE_DIM],
            &[1.0; 4]
        );
        let strict = Hml263Options {
            feet_threshold: 0.0,
            ..Default::default()
        };
        let out = process(&poses, &strict).expect("process");
        assert_eq!(
            &out.features[FEATURE_DIM + FEET..2 * FEATURE_DIM],
            &[0.0; 4]
        );
    }

    #[test]
    fn bad_input_is_rejected_with_its_location() {
        let opts = Hml263Options::default();
        assert!(process(&clip(1), &opts)
            .unwrap_err()
            .to_string()
            .contains("at least 2 frames"));
        let mut poses = clip(4);
        poses[2][7][1] = f64::NAN;
        let e = process(&poses, &opts).unwrap_err().to_string();
        assert!(e.contains("frame 2") && e.contains("l_ankle"), "{e}");
        let mut poses = clip(4);
        poses[3][10] = poses[3][7];
        let e = process(&poses, &opts).unwrap_err().to_string();
        assert!(e.contains("frame 3") && e.contains("l_foot"), "{e}");
        // Hips and collars vertical, shoulders hanging: the across vector points along Y.
        let mut o = TARGET_OFFSETS;
        o[1] = [0.0, TARGET_LENGTHS[1], 0.0];
        o[2] = [0.0, -TARGET_LENGTHS[2], 0.0];
        o[13] = [0.0, TARGET_LENGTHS[13], 0.0];
        o[14] = [0.0, TARGET_LENGTHS[14], 0.0];
        let poses = vec![build(&o); 3];
        let e = process(&poses, &opts).unwrap_err().to_string();
        assert!(e.contains("degenerate facing"), "{e}");
    }
}
