//! The `synth:` source: labelled procedural SMPL-22 motion at any scale.
//!
//! Each clip is forward kinematics of joint-angle curves on the HumanML3D skeleton
//! (`skeleton::RAW_OFFSETS` directions, `TARGET_OFFSETS` lengths scaled per clip and per
//! segment), 20 fps, 2–10 s. The root follows the feet rather than a scripted path: every
//! frame the body is lowered until its lowest joint touches y = 0 (plus a ballistic lift
//! during jump flights), and the horizontal root motion is whatever keeps the lower toe
//! where it was on the previous frame, so stance feet do not slide and the walking speed is
//! the one the legs produce.
//!
//! Clip `i` of stream `s` is a pure function of `(s, i)`. Within every block of
//! `ACTIONS.len() × EMOTIONS.len()` consecutive indices each (action, emotion) pair occurs
//! exactly once, in a seeded order.
//!
//! | scenario   | actions                 | lateralised (caption names the side) |
//! |------------|-------------------------|--------------------------------------|
//! | locomotion | walk, run, turn         | turn direction; walk/run when curving |
//! | greeting   | wave, bow               | wave hand                            |
//! | gesture    | raise hand, clap        | raised hand                          |
//! | fighting   | kick, punch             | kicking leg, punching arm            |
//! | dance      | dance step              | —                                    |
//! | daily      | sit down, jump          | —                                    |
//!
//! Emotions change the motion itself (the `style` label repeats the emotion):
//!
//! | emotion | tempo | amplitude | torso / head                 | arms            | other            |
//! |---------|-------|-----------|------------------------------|-----------------|------------------|
//! | neutral | 1.0   | 1.0       | upright, head level          | relaxed         | —                |
//! | happy   | 1.2   | 1.2       | upright, head up             | open, swinging  | springy bounce   |
//! | sad     | 0.8   | 0.7       | slight stoop, head hanging   | close, hunched  | smooth, slow     |
//! | angry   | 1.3   | 1.3       | leaning in, head forward     | bent elbows     | sharp, jerky     |
//! | tired   | 0.65  | 0.6       | heavy stoop, bent knees      | dangling        | side-to-side sway|
//! | proud   | 0.95  | 1.05      | chest out, chin up           | wide, shoulders back | —           |

use super::{Labels, RawClip};
use crate::quat::{self, Quat, Vec3};
use crate::skeleton::{Pose, NUM_JOINTS, PARENTS, RAW_OFFSETS, TARGET_OFFSETS};
use motionscale_core::rng::SplitMix64;
use std::f64::consts::{FRAC_PI_2, PI, TAU};
use std::path::PathBuf;

/// Frame rate of generated clips.
pub const FPS: f64 = 20.0;

/// Actions, in label order.
pub const ACTIONS: &[&str] = &[
    "walk",
    "run",
    "turn",
    "wave",
    "bow",
    "raise hand",
    "clap",
    "kick",
    "punch",
    "dance step",
    "sit down",
    "jump",
];

/// Emotions, in label order.
pub const EMOTIONS: &[&str] = &["neutral", "happy", "sad", "angry", "tired", "proud"];

/// Conversion note recorded in the manifest for synthetic clips.
pub const CONVERSION: &str = "synthetic SMPL-22 (metres, Y up)";

/// Scenario of a synthetic action (see the module table); `"other"` for an unknown action.
pub fn scenario_of(action: &str) -> &'static str {
    match action {
        "walk" | "run" | "turn" => "locomotion",
        "wave" | "bow" => "greeting",
        "raise hand" | "clap" => "gesture",
        "kick" | "punch" => "fighting",
        "dance step" => "dance",
        "sit down" | "jump" => "daily",
        _ => "other",
    }
}

/// `CLIPS[:SEED]` as on the command line (seed default 0); a leading `synth:` is accepted.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SynthSpec {
    /// Number of clips (indices 0..clips).
    pub clips: usize,
    /// Stream seed.
    pub seed: u64,
}

impl std::str::FromStr for SynthSpec {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        let body = s.strip_prefix("synth:").unwrap_or(s);
        let (clips, seed) = match body.split_once(':') {
            Some((c, sd)) => (c, Some(sd)),
            None => (body, None),
        };
        let clips: usize = clips.trim().parse().map_err(|e| {
            format!("synth spec {s:?}: clip count {clips:?} is not a non-negative integer ({e}); expected CLIPS[:SEED], e.g. synth:1000:7")
        })?;
        if clips == 0 {
            return Err(format!(
                "synth spec {s:?}: clip count must be at least 1; expected CLIPS[:SEED]"
            ));
        }
        let seed = match seed {
            Some(sd) => sd.trim().parse().map_err(|e| {
                format!("synth spec {s:?}: seed {sd:?} is not an unsigned 64-bit integer ({e}); expected CLIPS[:SEED]")
            })?,
            None => 0,
        };
        Ok(Self { clips, seed })
    }
}

/// Clip `index` of the stream `seed` (see the module doc).
pub fn generate(seed: u64, index: usize) -> RawClip {
    let (action, emotion) = cell(seed, index);
    let mut rng = Rng::new(seed, index as u64);
    let plan = Plan::draw(action, emotion, &mut rng);
    let body = Body::draw(&mut rng);
    let poses = animate(&plan, &body);
    let captions = captions(&plan, &mut rng);
    RawClip {
        clip_id: format!("synth_{seed}_{index:08}"),
        source: "synth".to_string(),
        source_path: PathBuf::from(format!("synth:{seed}")),
        fps: FPS,
        poses,
        labels: Labels {
            action: Some(ACTIONS[action].to_string()),
            style: Some(EMOTIONS[emotion].to_string()),
            emotion: Some(EMOTIONS[emotion].to_string()),
            scenario: Some(scenario_of(ACTIONS[action]).to_string()),
        },
        captions,
        conversion: CONVERSION.to_string(),
        split: None,
        span: None,
    }
}

/// (action, emotion) of clip `index`: a seeded permutation of all pairs per block of indices.
fn cell(seed: u64, index: usize) -> (usize, usize) {
    let cells = ACTIONS.len() * EMOTIONS.len();
    let block = (index / cells) as u64;
    let mut order: Vec<usize> = (0..cells).collect();
    let mut rng = Rng::new(seed ^ 0x5EED_B10C_0000_0000, block);
    for i in (1..cells).rev() {
        let j = rng.0.below(i as u64 + 1) as usize;
        order.swap(i, j);
    }
    let c = order[index % cells];
    (c / EMOTIONS.len(), c % EMOTIONS.len())
}

/// Seeded uniform draws on top of [`SplitMix64`].
struct Rng(SplitMix64);

impl Rng {
    fn new(seed: u64, index: u64) -> Self {
        let mut mix = SplitMix64(seed);
        let key = mix.next_u64() ^ index.wrapping_mul(0xD1B5_4A32_D192_ED03);
        let mut rng = SplitMix64(key);
        rng.next_u64();
        Self(rng)
    }

    fn range(&mut self, lo: f64, hi: f64) -> f64 {
        self.0.range(lo, hi)
    }

    /// Multiplicative jitter 1 ± `rel`.
    fn jitter(&mut self, rel: f64) -> f64 {
        self.range(1.0 - rel, 1.0 + rel)
    }

    fn coin(&mut self) -> bool {
        self.0.next_u64() >> 63 == 1
    }

    fn pick<'a>(&mut self, xs: &[&'a str]) -> &'a str {
        xs[self.0.index(xs.len())]
    }
}

/// How an emotion shapes motion (see the module table).
#[derive(Debug, Clone, Copy)]
struct Mood {
    /// Speed multiplier of every rhythm.
    tempo: f64,
    /// Multiplier of the action's main excursions.
    amp: f64,
    /// Forward torso pitch (rad; negative leans back).
    lean: f64,
    /// Forward head pitch relative to the torso (rad).
    head: f64,
    /// Shoulders rolled forward (rad; negative pulls them back).
    hunch: f64,
    /// Resting shoulder abduction (rad).
    open: f64,
    /// Resting knee bend (rad).
    crouch: f64,
    /// Knee-pumping bounce at twice the rhythm (rad).
    bounce: f64,
    /// Waveform exponent: < 1 snaps to the extremes (jerky), > 1 lingers near rest (sluggish).
    sharp: f64,
    /// Side-to-side pelvis roll (rad).
    sway: f64,
    /// Resting elbow bend (rad).
    elbow: f64,
}

const MOODS: [Mood; 6] = [
    Mood {
        tempo: 1.0,
        amp: 1.0,
        lean: 0.04,
        head: 0.0,
        hunch: 0.0,
        open: 0.08,
        crouch: 0.05,
        bounce: 0.0,
        sharp: 1.0,
        sway: 0.02,
        elbow: 0.15,
    },
    Mood {
        tempo: 1.2,
        amp: 1.2,
        lean: -0.02,
        head: -0.15,
        hunch: -0.05,
        open: 0.25,
        crouch: 0.06,
        bounce: 0.14,
        sharp: 0.85,
        sway: 0.06,
        elbow: 0.35,
    },
    Mood {
        tempo: 0.8,
        amp: 0.7,
        lean: 0.15,
        head: 0.6,
        hunch: 0.3,
        open: 0.0,
        crouch: 0.08,
        bounce: 0.0,
        sharp: 1.4,
        sway: 0.02,
        elbow: 0.05,
    },
    Mood {
        tempo: 1.3,
        amp: 1.3,
        lean: 0.16,
        head: 0.15,
        hunch: 0.12,
        open: 0.25,
        crouch: 0.15,
        bounce: 0.0,
        sharp: 0.5,
        sway: 0.0,
        elbow: 0.9,
    },
    Mood {
        tempo: 0.65,
        amp: 0.6,
        lean: 0.35,
        head: 0.25,
        hunch: 0.18,
        open: 0.02,
        crouch: 0.28,
        bounce: 0.0,
        sharp: 1.6,
        sway: 0.1,
        elbow: 0.05,
    },
    Mood {
        tempo: 0.95,
        amp: 1.05,
        lean: -0.14,
        head: -0.3,
        hunch: -0.25,
        open: 0.32,
        crouch: 0.0,
        bounce: 0.0,
        sharp: 1.0,
        sway: 0.0,
        elbow: 0.2,
    },
];

/// Everything drawn for one clip besides the body.
#[derive(Debug, Clone)]
struct Plan {
    action: usize,
    emotion: usize,
    mood: Mood,
    /// Active side for lateralised actions (0 left, 1 right); turn/curve direction sign.
    side: usize,
    frames: usize,
    duration: f64,
    heading0: f64,
    /// Heading change rate of walks and runs (rad/s; positive turns left).
    curve: f64,
    /// Total heading change of a turn (rad; positive turns left).
    turn: f64,
    /// Jumps travel forward rather than staying in place.
    forward: bool,
    /// Start phase of rhythms (rad).
    phase0: f64,
    /// Seconds standing before sitting down.
    lead_in: f64,
}

/// Shortest clip per action (s), so one full execution fits even at the slowest tempo.
fn min_duration(action: &str) -> f64 {
    match action {
        "sit down" | "bow" => 4.5,
        "jump" | "kick" | "raise hand" => 3.5,
        _ => 2.0,
    }
}

impl Plan {
    fn draw(action: usize, emotion: usize, rng: &mut Rng) -> Self {
        let base = MOODS[emotion];
        let mood = Mood {
            tempo: base.tempo * rng.jitter(0.08),
            amp: base.amp * rng.jitter(0.08),
            lean: base.lean + rng.range(-0.03, 0.03),
            head: base.head + rng.range(-0.05, 0.05),
            hunch: base.hunch + rng.range(-0.03, 0.03),
            open: (base.open + rng.range(-0.03, 0.03)).max(0.0),
            crouch: (base.crouch + rng.range(-0.02, 0.02)).max(0.0),
            bounce: base.bounce * rng.jitter(0.15),
            sharp: base.sharp * rng.jitter(0.08),
            sway: base.sway * rng.jitter(0.2),
            elbow: (base.elbow + rng.range(-0.05, 0.05)).max(0.0),
        };
        let duration = rng.range(min_duration(ACTIONS[action]), 10.0);
        let side = usize::from(rng.coin());
        let sign = if side == 0 { 1.0 } else { -1.0 };
        let curve = if rng.coin() {
            sign * rng.range(0.1, 0.3)
        } else {
            rng.range(-0.05, 0.05)
        };
        Self {
            action,
            emotion,
            mood,
            side,
            frames: (duration * FPS).round() as usize,
            duration,
            heading0: rng.range(-PI, PI),
            curve,
            turn: sign * rng.range(FRAC_PI_2, PI),
            forward: rng.coin(),
            phase0: rng.range(0.0, TAU),
            lead_in: rng.range(0.3, 1.0),
        }
    }

    /// Total heading change of a walk or run (rad).
    fn path_turn(&self) -> f64 {
        self.curve * self.duration
    }
}

/// Per-clip bone lengths (metres).
struct Body {
    offsets: [Vec3; NUM_JOINTS],
    /// Thigh and shin lengths per side, for leg IK.
    leg: [(f64, f64); 2],
    /// Height of the ankle above the toe in a flat stance, per side.
    foot_drop: [f64; 2],
}

impl Body {
    fn draw(rng: &mut Rng) -> Self {
        let size = rng.range(0.85, 1.15);
        let legs = rng.jitter(0.05);
        let arms = rng.jitter(0.05);
        let torso = rng.jitter(0.05);
        let width = rng.jitter(0.05);
        let mut offsets = [[0.0; 3]; NUM_JOINTS];
        for (j, o) in offsets.iter_mut().enumerate().skip(1) {
            let segment = match j {
                4 | 5 | 7 | 8 | 10 | 11 => legs,
                16..=21 => arms,
                1 | 2 | 13 | 14 => width,
                _ => torso,
            };
            let len = quat::norm(TARGET_OFFSETS[j]) * size * segment;
            *o = quat::scale(RAW_OFFSETS[j], len);
        }
        let leg = [0, 1].map(|k| (quat::norm(offsets[4 + k]), quat::norm(offsets[7 + k])));
        let foot_drop = [0, 1].map(|k| quat::norm(offsets[10 + k]) * FOOT_PITCH.sin());
        Self {
            offsets,
            leg,
            foot_drop,
        }
    }
}

/// Angles of one limb pair side (left-side sign conventions; the right side is mirrored).
#[derive(Debug, Clone, Copy, Default)]
struct Limb {
    /// Thigh forward from the world vertical (rad).
    hip_flex: f64,
    /// Leg out to the side (rad).
    hip_abd: f64,
    /// Knee flexion (rad, ≥ 0).
    knee: f64,
    /// Toe-down pitch of the foot beyond its flat stance pitch (rad).
    ankle: f64,
    /// Upper arm forward from the world vertical (rad).
    sh_flex: f64,
    /// Upper arm out to the side (rad).
    sh_abd: f64,
    /// Upper arm external rotation about its own axis (rad).
    sh_twist: f64,
    /// Elbow flexion (rad, ≥ 0).
    elbow: f64,
}

/// Joint angles of one frame, plus the root's heading and extra lift.
#[derive(Debug, Clone, Copy, Default)]
struct Angles {
    /// Pelvis (pitch forward, roll to the right, yaw to the left).
    pelvis: Vec3,
    /// Whole spine, spread over its three joints (pitch, roll, yaw).
    spine: Vec3,
    /// Neck pitch forward and yaw to the left.
    neck: [f64; 2],
    /// Shoulders rolled forward (rad).
    hunch: f64,
    /// Left then right.
    side: [Limb; 2],
    /// World heading (rad about +Y; 0 faces +Z, positive turns left).
    heading: f64,
    /// Height above the floor contact (jump flight), metres.
    lift: f64,
    /// Forward travel this frame beyond what the feet produce (jump flight), metres.
    drift: f64,
}

/// Foot pitch (toe down) in a flat stance: the SMPL-22 foot bone points down-forward.
const FOOT_PITCH: f64 = 0.45;
/// Joint limits applied to every frame: knee and elbow flexion (rad).
const MAX_FLEX: f64 = 2.5;

fn clamp01(x: f64) -> f64 {
    x.clamp(0.0, 1.0)
}

fn smoothstep(x: f64) -> f64 {
    let x = clamp01(x);
    x * x * (3.0 - 2.0 * x)
}

/// Half-sine bump over u ∈ [a, b], zero outside.
fn bump(u: f64, a: f64, b: f64) -> f64 {
    (PI * clamp01((u - a) / (b - a))).sin()
}

/// The mood's waveform shaping of an oscillation in [−1, 1]: p > 1 lingers near zero (signed
/// power), p < 1 snaps toward the extremes (a tanh, whose slope stays bounded).
fn shape(x: f64, p: f64) -> f64 {
    if p >= 1.0 {
        x.signum() * x.abs().powf(p)
    } else {
        let gain = 4.0 * (1.0 - p);
        (gain * x).tanh() / gain.tanh()
    }
}

/// Hip swing of a leg at gait phase u ∈ [0, 1) as a fraction of the amplitude (+1 forward),
/// and the swing progress when the foot is in the air. Stance (u < duty) sweeps the leg back at
/// constant angular speed, so both feet move alike in double support; the swing is a cubic
/// Hermite whose end slopes match that speed, so the foot lands without a jolt.
fn stride(u: f64, duty: f64) -> (f64, Option<f64>) {
    if u < duty {
        return (1.0 - 2.0 * u / duty, None);
    }
    let s = (u - duty) / (1.0 - duty);
    let slope = -2.0 * (1.0 - duty) / duty;
    let (s2, s3) = (s * s, s * s * s);
    let h = -(2.0 * s3 - 3.0 * s2 + 1.0)
        + slope * (s3 - 2.0 * s2 + s)
        + (-2.0 * s3 + 3.0 * s2)
        + slope * (s3 - s2);
    (h, Some(s))
}

/// Rz(z) · Rx(x) · Ry(y).
fn euler(x: f64, y: f64, z: f64) -> Quat {
    let qz = quat::from_axis_angle([0.0, 0.0, 1.0], z);
    let qx = quat::from_axis_angle([1.0, 0.0, 0.0], x);
    let qy = quat::from_axis_angle([0.0, 1.0, 0.0], y);
    quat::mul(qz, quat::mul(qx, qy))
}

/// [`euler`] for a side: mirroring about X keeps X rotations and negates Y and Z ones.
fn side_euler(side: usize, x: f64, y: f64, z: f64) -> Quat {
    if side == 0 {
        euler(x, y, z)
    } else {
        euler(x, -y, -z)
    }
}

fn rx(a: f64) -> Quat {
    quat::from_axis_angle([1.0, 0.0, 0.0], a)
}

impl Plan {
    /// Angles at time `t` (s): the mood's posture, then the action on top.
    fn angles(&self, t: f64, body: &Body) -> Angles {
        let m = &self.mood;
        let mut a = Angles {
            heading: self.heading0,
            ..Angles::default()
        };
        let breath = (TAU * 0.25 * t + self.phase0).sin();
        a.spine[0] = m.lean + 0.02 * breath;
        a.neck[0] = m.head;
        a.hunch = m.hunch;
        let sway = m.sway * (TAU * 0.3 * m.tempo * t + self.phase0).sin();
        a.pelvis[1] = sway;
        a.spine[1] = -0.5 * sway;
        let bounce = m.bounce * 0.5 * (1.0 - (2.0 * TAU * m.tempo * t).cos());
        for l in a.side.iter_mut() {
            l.knee = m.crouch + bounce;
            l.hip_flex = 0.5 * l.knee;
            l.sh_abd = m.open;
            l.elbow = m.elbow;
            l.sh_flex = 0.1 * m.elbow;
        }
        match ACTIONS[self.action] {
            "walk" => self.gait(t, &mut a, body, false),
            "run" => self.gait(t, &mut a, body, true),
            "turn" => self.turn(t, &mut a),
            "wave" => self.wave(t, &mut a),
            "bow" => self.bow(t, &mut a),
            "raise hand" => self.raise_hand(t, &mut a),
            "clap" => self.clap(t, &mut a),
            "kick" => self.kick(t, &mut a),
            "punch" => self.punch(t, &mut a),
            "dance step" => self.dance(t, &mut a),
            "sit down" => self.sit_down(t, &mut a),
            _ => self.jump(t, &mut a),
        }
        for l in a.side.iter_mut() {
            l.knee = l.knee.clamp(0.0, MAX_FLEX);
            l.elbow = l.elbow.clamp(0.0, MAX_FLEX);
        }
        a
    }

    /// Rhythm phase (rad) at `freq` Hz scaled by the tempo.
    fn phase(&self, t: f64, freq: f64) -> f64 {
        TAU * freq * self.mood.tempo * t + self.phase0
    }

    /// Walk or run by leg IK: each toe follows a stance line on the floor (constant backward
    /// speed, so double-support feet move alike and the pinned root never drags a foot) and a
    /// swing arc above it. The hips ride as high as the most inclined supporting leg allows
    /// (an inverted-pendulum bob); a swinging leg counts in proportion to how close it is to
    /// landing or lift-off, so the height has no jumps.
    fn gait(&self, t: f64, a: &mut Angles, body: &Body, run: bool) {
        let m = &self.mood;
        let (freq, step, clearance, arm, duty) = if run {
            (1.35, 1.0, 0.22, 0.6, 0.55)
        } else {
            (0.9, 0.75, 0.09, 0.45, 0.6)
        };
        let phase = self.phase(t, freq);
        let amp = m.amp.clamp(0.5, 1.4);
        let reach = body
            .leg
            .iter()
            .map(|l| l.0 + l.1)
            .fold(f64::INFINITY, f64::min);
        let step = (step * amp * reach / 0.82).min(reach);
        let strides = [0, 1].map(|k| {
            let u = ((phase / TAU) + 0.5 * k as f64).rem_euclid(1.0);
            stride(u, duty)
        });
        let support = strides
            .iter()
            .map(|&(h, swing)| {
                let w = swing.map_or(1.0, |s| {
                    1.0 - smoothstep(s / 0.3) + smoothstep((s - 0.7) / 0.3)
                });
                w * (0.5 * step * h).abs()
            })
            .fold(0.0, f64::max);
        let straight = (0.98 - 0.1 * m.crouch) * reach;
        let depth = (straight * straight - support * support).sqrt()
            - m.bounce * 0.15 * (2.0 * phase).cos().abs();
        a.heading += self.curve * t;
        if run {
            a.spine[0] += 0.12;
        }
        for (k, l) in a.side.iter_mut().enumerate() {
            let (h, swing) = strides[k];
            let (thigh, shin) = body.leg[k];
            let lift = swing.map_or(0.0, |s| (PI * s).sin().powi(2));
            let fwd = 0.5 * step * h;
            let up = -depth + body.foot_drop[k] + clearance * amp.sqrt() * lift;
            let d = (fwd * fwd + up * up).sqrt().min(0.999 * (thigh + shin));
            let cos_knee = (thigh * thigh + shin * shin - d * d) / (2.0 * thigh * shin);
            let cos_hip = (thigh * thigh + d * d - shin * shin) / (2.0 * thigh * d);
            l.knee = PI - cos_knee.clamp(-1.0, 1.0).acos();
            l.hip_flex = fwd.atan2(-up) + cos_hip.clamp(-1.0, 1.0).acos();
            l.ankle -= 0.25 * lift;
            l.sh_flex -= arm * amp * (1.0 + m.open) * shape(h, m.sharp);
            l.elbow += if run { 1.3 } else { 0.2 * h.min(0.0).abs() };
        }
        a.spine[2] += 0.08 * amp * phase.sin();
        a.pelvis[1] = 0.0;
    }

    fn turn(&self, t: f64, a: &mut Angles) {
        let m = &self.mood;
        let phase = self.phase(t, 1.0);
        let d = self.duration;
        let progress = smoothstep((t - 0.15 * d) / (0.7 * d));
        a.heading += self.turn * progress;
        let moving = bump(t, 0.1 * d, 0.9 * d);
        for (k, l) in a.side.iter_mut().enumerate() {
            let lift = (phase + k as f64 * PI).sin().max(0.0) * moving;
            l.hip_flex += 0.35 * m.amp * lift;
            l.knee += 0.7 * m.amp * lift;
        }
        a.neck[1] += 0.35 * self.turn.signum() * moving;
    }

    fn wave(&self, t: f64, a: &mut Angles) {
        let m = &self.mood;
        let d = self.duration;
        let ramp = 0.5 / m.tempo;
        let env = smoothstep(t / ramp) * smoothstep((d - t) / ramp);
        let l = &mut a.side[self.side];
        l.sh_abd += (1.2 + 0.25 * m.amp - l.sh_abd) * env;
        l.sh_twist = FRAC_PI_2 * env;
        let swing = shape(self.phase(t, 1.6).sin(), m.sharp);
        l.elbow += (1.3 + 0.35 * m.amp * swing) * env;
    }

    fn bow(&self, t: f64, a: &mut Angles) {
        let m = &self.mood;
        let period = 3.5 / m.tempo;
        let u = (t / period).fract();
        let depth = 0.9 * m.amp.sqrt() * bump(u, 0.0, 0.8).powf(0.6 * m.sharp);
        a.pelvis[0] += 0.35 * depth;
        a.spine[0] += 0.6 * depth;
        a.neck[0] += 0.2 * depth;
    }

    fn raise_hand(&self, t: f64, a: &mut Angles) {
        let m = &self.mood;
        let period = 3.2 / m.tempo;
        let u = (t / period).fract();
        let up = smoothstep(u / 0.2) * smoothstep((0.85 - u) / 0.2);
        let l = &mut a.side[self.side];
        l.sh_flex += (2.55 + 0.2 * m.amp.min(1.3) - l.sh_flex) * up;
        l.elbow *= 1.0 - 0.7 * up;
        let other = &mut a.side[1 - self.side];
        other.sh_flex += 0.05 * up;
    }

    fn clap(&self, t: f64, a: &mut Angles) {
        let m = &self.mood;
        let d = self.duration;
        let ramp = 0.4 / m.tempo;
        let env = smoothstep(t / ramp) * smoothstep((d - t) / ramp);
        let beat = shape(self.phase(t, 1.5).sin(), m.sharp);
        for l in a.side.iter_mut() {
            l.sh_flex += 0.8 * env;
            l.sh_abd += (0.2 - l.sh_abd) * env;
            l.sh_twist = -FRAC_PI_2 * env;
            l.elbow += (1.25 + 0.3 * m.amp.min(1.3) * beat) * env;
        }
    }

    fn kick(&self, t: f64, a: &mut Angles) {
        let m = &self.mood;
        let period = 1.8 / m.tempo;
        let u = (t / period).fract();
        let lift = bump(u, 0.1, 0.7).powf(m.sharp);
        let extend = bump(u, 0.28, 0.52).powi(2);
        let high = (1.2 * m.amp).min(1.6);
        a.spine[0] -= 0.12 * lift;
        for l in a.side.iter_mut() {
            l.sh_flex += 0.5;
            l.sh_abd += 0.1;
            l.elbow = 1.6;
        }
        let l = &mut a.side[self.side];
        l.hip_flex += high * lift;
        l.knee += 1.4 * lift * (1.0 - 0.9 * extend);
        l.ankle -= 0.3 * lift;
    }

    fn punch(&self, t: f64, a: &mut Angles) {
        let m = &self.mood;
        let period = 1.1 / m.tempo;
        let u = (t / period).fract();
        let hit = bump(u, 0.0, 0.45).powf(m.sharp);
        let reach = m.amp.min(1.3);
        for l in a.side.iter_mut() {
            l.knee += 0.2;
            l.hip_flex += 0.1;
            l.sh_flex += 0.4;
            l.sh_abd += 0.1;
            l.elbow = 2.0;
        }
        let sign = if self.side == 0 { 1.0 } else { -1.0 };
        a.spine[2] -= sign * 0.35 * reach * hit;
        let l = &mut a.side[self.side];
        l.sh_flex += 1.1 * reach * hit;
        l.elbow = 2.0 - 1.9 * hit;
    }

    fn dance(&self, t: f64, a: &mut Angles) {
        let m = &self.mood;
        let phase = self.phase(t, 0.8);
        let amp = m.amp.min(1.3);
        let pump = 0.15 * (1.0 - (2.0 * phase).cos());
        for (k, l) in a.side.iter_mut().enumerate() {
            let s = (phase + k as f64 * PI).sin();
            // Squared, so each foot leaves and meets the floor at rest.
            let step = s.max(0.0).powi(2);
            l.hip_abd += 0.25 * amp * step;
            l.knee += 0.9 * step + pump;
            l.hip_flex += 0.45 * step + 0.5 * pump;
            l.sh_abd += 0.6 + 0.5 * amp * shape(s, m.sharp);
            l.elbow += 0.7;
        }
        a.spine[1] += 0.1 * amp * phase.sin();
        a.neck[0] += 0.1 * (2.0 * phase).sin();
    }

    fn sit_down(&self, t: f64, a: &mut Angles) {
        let m = &self.mood;
        let descent = 1.6 / m.tempo;
        let s = smoothstep((t - self.lead_in) / descent);
        let mid = bump(t, self.lead_in, self.lead_in + descent);
        a.spine[0] += 0.45 * mid;
        for l in a.side.iter_mut() {
            l.hip_flex += 1.45 * s;
            l.knee += 1.5 * s;
            l.sh_flex += 0.5 * mid + 0.6 * s;
            l.elbow += 0.8 * s;
        }
    }

    fn jump(&self, t: f64, a: &mut Angles) {
        let m = &self.mood;
        let height = (0.22 * m.amp).clamp(0.08, 0.32);
        let flight = (8.0 * height / 9.81).sqrt();
        let (down, land) = (0.5 / m.tempo, 0.5 / m.tempo);
        let period = down + flight + land;
        let c = t % period;
        let deep = (0.9 * m.amp).clamp(0.5, 1.2);
        let (knee, arms) = if c < down {
            let u = c / down;
            let k = bump(u, 0.0, 1.0).powf(m.sharp);
            (deep * k, -0.6 * k)
        } else if c < down + flight {
            let u = (c - down) / flight;
            a.lift = 4.0 * height * u * (1.0 - u);
            if self.forward {
                a.drift = 0.4 * m.amp.min(1.3) / (flight * FPS);
            }
            (
                0.5 * bump(u, 0.0, 1.0),
                2.4 * m.amp.min(1.2) * bump(u, 0.0, 1.0),
            )
        } else {
            let u = (c - down - flight) / land;
            (0.8 * deep * bump(u, 0.0, 1.0), 0.0)
        };
        a.spine[0] += 0.3 * knee;
        for l in a.side.iter_mut() {
            l.knee += knee;
            l.hip_flex += 0.5 * knee;
            l.sh_flex += arms;
        }
    }
}

/// Local joint rotations of a frame (root rotation includes the heading).
fn rotations(a: &Angles) -> [Quat; NUM_JOINTS] {
    let mut q = [quat::IDENTITY; NUM_JOINTS];
    let heading = quat::from_axis_angle([0.0, 1.0, 0.0], a.heading);
    q[0] = quat::mul(heading, euler(a.pelvis[0], a.pelvis[2], a.pelvis[1]));
    let spine = euler(a.spine[0] / 3.0, a.spine[2] / 3.0, a.spine[1] / 3.0);
    q[3] = spine;
    q[6] = spine;
    q[9] = spine;
    q[12] = euler(a.neck[0], a.neck[1], 0.0);
    let torso = a.pelvis[0] + a.spine[0];
    for (k, l) in a.side.iter().enumerate() {
        // Angles are from the world vertical: undo the parents' pitch so legs and arms hang.
        q[1 + k] = side_euler(k, -(l.hip_flex + a.pelvis[0]), 0.0, l.hip_abd);
        q[4 + k] = rx(l.knee);
        q[7 + k] = rx(FOOT_PITCH + l.ankle + l.hip_flex - l.knee);
        q[13 + k] = rx(-a.hunch);
        q[16 + k] = side_euler(k, -(l.sh_flex + torso - a.hunch), l.sh_twist, l.sh_abd);
        q[18 + k] = rx(-l.elbow);
    }
    q
}

/// Joint positions relative to the root (root at the origin, heading applied).
fn local_pose(body: &Body, a: &Angles) -> Pose {
    let local = rotations(a);
    let mut global = [quat::IDENTITY; NUM_JOINTS];
    let mut pose = [[0.0; 3]; NUM_JOINTS];
    global[0] = local[0];
    for j in 1..NUM_JOINTS {
        let p = PARENTS[j];
        pose[j] = quat::add(pose[p], quat::rot(global[p], body.offsets[j]));
        global[j] = quat::mul(global[p], local[j]);
    }
    pose
}

/// Toe joints, whose contact pins the root.
const TOES: [usize; 2] = [10, 11];

/// Place each frame's body in the world: lowest joint on the floor (plus lift), and the
/// root moved between consecutive frames so that the toe staying lowest over both frames
/// keeps its floor position (choosing over both frames, not one, matters when a run's double
/// support is shorter than a frame).
fn animate(plan: &Plan, body: &Body) -> Vec<Pose> {
    let mut out: Vec<Pose> = Vec::with_capacity(plan.frames);
    let mut root = [0.0, 0.0, 0.0];
    let mut prev: Option<(Pose, f64)> = None;
    for f in 0..plan.frames {
        let a = plan.angles(f as f64 / FPS, body);
        let local = local_pose(body, &a);
        let floor = local.iter().fold(f64::INFINITY, |m, p| m.min(p[1]));
        if let Some((before, floor_before)) = prev {
            let height = |toe: usize| (before[toe][1] - floor_before).max(local[toe][1] - floor);
            let toe = if height(TOES[0]) <= height(TOES[1]) {
                TOES[0]
            } else {
                TOES[1]
            };
            root[0] += before[toe][0] - local[toe][0];
            root[2] += before[toe][2] - local[toe][2];
        }
        root[0] += a.drift * a.heading.sin();
        root[2] += a.drift * a.heading.cos();
        root[1] = a.lift - floor;
        let mut pose = local;
        for p in pose.iter_mut() {
            *p = quat::add(*p, root);
        }
        out.push(pose);
        prev = Some((local, floor));
    }
    out
}

/// Side word of a lateralised clip.
fn side_word(side: usize) -> &'static str {
    if side == 0 {
        "left"
    } else {
        "right"
    }
}

/// Direction word of a signed heading change (positive turns left).
fn turn_word(angle: f64) -> &'static str {
    if angle > 0.0 {
        "left"
    } else {
        "right"
    }
}

/// Verb phrases (third person) for the clip's action, side and path.
fn action_phrases(plan: &Plan) -> Vec<String> {
    let side = side_word(plan.side);
    let curving = plan.path_turn().abs() > 0.6;
    let bend = turn_word(plan.path_turn());
    let with_path = |base: &[&str]| -> Vec<String> {
        base.iter()
            .map(|p| {
                if curving {
                    format!("{p}, curving to the {bend}")
                } else {
                    p.to_string()
                }
            })
            .collect()
    };
    match ACTIONS[plan.action] {
        "walk" => with_path(&["walks forward", "walks ahead", "walks along"]),
        "run" => with_path(&["runs forward", "runs ahead", "jogs forward"]),
        "turn" => {
            let dir = turn_word(plan.turn);
            let how = if plan.turn.abs() > 2.4 {
                "turns around"
            } else {
                "turns"
            };
            vec![
                format!("{how} to the {dir}"),
                format!("{how} to the {dir} on the spot"),
                format!("steps in place and {how} to the {dir}"),
            ]
        }
        "wave" => vec![
            format!("waves with the {side} hand"),
            format!("waves their {side} hand"),
            format!("raises the {side} hand and waves"),
        ],
        "bow" => vec![
            "bows".to_string(),
            "takes a bow".to_string(),
            "bows forward from the waist".to_string(),
        ],
        "raise hand" => vec![
            format!("raises the {side} hand"),
            format!("raises their {side} arm overhead"),
            format!("puts the {side} hand up in the air"),
        ],
        "clap" => vec![
            "claps".to_string(),
            "claps their hands".to_string(),
            "claps in front of the chest".to_string(),
        ],
        "kick" => vec![
            format!("kicks with the {side} leg"),
            format!("kicks forward with the {side} foot"),
            format!("throws kicks with the {side} leg"),
        ],
        "punch" => vec![
            format!("punches with the {side} fist"),
            format!("throws punches with the {side} arm"),
            format!("punches forward with the {side} hand"),
        ],
        "dance step" => vec![
            "dances from side to side".to_string(),
            "does a dance step".to_string(),
            "dances, stepping side to side".to_string(),
        ],
        "sit down" => vec![
            "sits down".to_string(),
            "sits down on a chair".to_string(),
            "bends the knees and sits down".to_string(),
        ],
        _ => {
            if plan.forward {
                vec![
                    "jumps forward".to_string(),
                    "jumps ahead".to_string(),
                    "hops forward with both feet".to_string(),
                ]
            } else {
                vec![
                    "jumps up and down".to_string(),
                    "jumps in place".to_string(),
                    "hops on the spot with both feet".to_string(),
                ]
            }
        }
    }
}

/// (adverbs, trailing clauses, article + adjective) describing an emotion.
fn manner(
    emotion: usize,
) -> (
    &'static [&'static str],
    &'static [&'static str],
    &'static [&'static str],
) {
    match EMOTIONS[emotion] {
        "happy" => (
            &["happily", "cheerfully", "joyfully"],
            &[
                "with a bounce in their step",
                "looking happy",
                "full of joy",
            ],
            &["a happy", "a cheerful"],
        ),
        "sad" => (
            &["sadly", "gloomily", "dejectedly"],
            &["head hanging low", "looking sad", "shoulders slumped"],
            &["a sad", "a downcast"],
        ),
        "angry" => (
            &["angrily", "furiously", "aggressively"],
            &[
                "looking angry",
                "with sharp, forceful movements",
                "full of rage",
            ],
            &["an angry", "a furious"],
        ),
        "tired" => (
            &["wearily", "sluggishly", "tiredly"],
            &[
                "looking exhausted",
                "bent over and worn out",
                "dragging their body",
            ],
            &["a tired", "an exhausted"],
        ),
        "proud" => (
            &["proudly", "confidently", "with pride"],
            &[
                "chest out and head held high",
                "with a proud posture",
                "looking confident",
            ],
            &["a proud", "a confident"],
        ),
        _ => (
            &["calmly", "normally", "casually"],
            &[
                "in a relaxed way",
                "at a normal pace",
                "without any particular emotion",
            ],
            &["a calm", "a relaxed"],
        ),
    }
}

/// Three captions from different templates, each naming the action and the manner.
fn captions(plan: &Plan, rng: &mut Rng) -> Vec<String> {
    let phrases = action_phrases(plan);
    let (adverbs, clauses, adjectives) = manner(plan.emotion);
    let start = rng.0.below(phrases.len() as u64) as usize;
    let template = rng.0.below(4) as usize;
    (0..3)
        .map(|k| {
            let act = &phrases[(start + k) % phrases.len()];
            match (template + k) % 4 {
                0 => format!("a person {act} {}.", rng.pick(adverbs)),
                1 => format!("someone {act}, {}.", rng.pick(clauses)),
                2 => format!("{} person {act}.", rng.pick(adjectives)),
                _ => format!(
                    "the person {} {act}, {}.",
                    rng.pick(adverbs),
                    rng.pick(clauses)
                ),
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spec_parses_and_explains_errors() {
        let s: SynthSpec = "synth:1000:7".parse().unwrap();
        assert_eq!(
            s,
            SynthSpec {
                clips: 1000,
                seed: 7
            }
        );
        let s: SynthSpec = "25".parse().unwrap();
        assert_eq!(s, SynthSpec { clips: 25, seed: 0 });
        let e = "synth:abc".parse::<SynthSpec>().unwrap_err();
        assert!(e.contains("clip count \"abc\""), "{e}");
        let e = "synth:10:x".parse::<SynthSpec>().unwrap_err();
        assert!(e.contains("seed \"x\""), "{e}");
        let e = "synth:0".parse::<SynthSpec>().unwrap_err();
        assert!(e.contains("at least 1"), "{e}");
    }

    #[test]
    fn every_block_holds_each_pair_once() {
        let cells = ACTIONS.len() * EMOTIONS.len();
        for block in 0..3 {
            let mut seen = vec![0; cells];
            for i in block * cells..(block + 1) * cells {
                let (a, e) = cell(9, i);
                seen[a * EMOTIONS.len() + e] += 1;
            }
            assert!(seen.iter().all(|&n| n == 1), "block {block}: {seen:?}");
        }
        assert_ne!(
            (0..cells).map(|i| cell(1, i)).collect::<Vec<_>>(),
            (0..cells).map(|i| cell(2, i)).collect::<Vec<_>>()
        );
    }

    #[test]
    fn scenarios_cover_every_action() {
        for a in ACTIONS {
            assert_ne!(scenario_of(a), "other", "{a}");
        }
        assert_eq!(scenario_of("fly"), "other");
    }

    #[test]
    fn joint_angles_stay_within_human_limits() {
        let mut rng = Rng::new(3, 0);
        for (action, action_name) in ACTIONS.iter().enumerate() {
            for (emotion, emotion_name) in EMOTIONS.iter().enumerate() {
                let plan = Plan::draw(action, emotion, &mut rng);
                let body = Body::draw(&mut rng);
                for f in 0..plan.frames {
                    let a = plan.angles(f as f64 / FPS, &body);
                    for l in &a.side {
                        let what = format!("{action_name} {emotion_name} frame {f}: {l:?}");
                        assert!((0.0..=150f64.to_radians()).contains(&l.knee), "{what}");
                        assert!((0.0..=150f64.to_radians()).contains(&l.elbow), "{what}");
                        assert!((-0.7..=1.8).contains(&l.hip_flex), "{what}");
                        assert!((-1.0..=3.0).contains(&l.sh_flex), "{what}");
                        assert!((-0.2..=1.6).contains(&l.sh_abd), "{what}");
                    }
                }
            }
        }
    }

    #[test]
    fn euler_rotations_follow_the_documented_signs() {
        let down = [0.0, -1.0, 0.0];
        // Knee flexion swings the shin backward (−Z); hip flexion swings the thigh forward.
        assert!(quat::rot(rx(0.5), down)[2] < 0.0);
        assert!(quat::rot(side_euler(0, -0.5, 0.0, 0.0), down)[2] > 0.0);
        // Abduction moves the left limb to +X and the right limb to −X.
        assert!(quat::rot(side_euler(0, 0.0, 0.0, 0.5), down)[0] > 0.0);
        assert!(quat::rot(side_euler(1, 0.0, 0.0, 0.5), down)[0] < 0.0);
    }
}
