//! The `synth:` source: determinism, physical sanity, captions that match the motion, and a
//! softmax-regression probe showing that action and emotion labels are in the motion.

use ingest::hml263::{self, Hml263Options, FEATURE_DIM};
use ingest::skeleton::{Pose, FEET_LEFT, FEET_RIGHT, NUM_JOINTS, PARENTS};
use ingest::source::synth::{self, SynthSpec, ACTIONS, EMOTIONS, FPS};
use ingest::source::RawClip;
use std::time::Instant;

fn dist(a: [f64; 3], b: [f64; 3]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

/// Angle (degrees) between bone parent→joint and joint→child.
fn flexion(pose: &Pose, parent: usize, joint: usize, child: usize) -> f64 {
    let u: Vec<f64> = (0..3).map(|k| pose[joint][k] - pose[parent][k]).collect();
    let v: Vec<f64> = (0..3).map(|k| pose[child][k] - pose[joint][k]).collect();
    let dot: f64 = u.iter().zip(&v).map(|(a, b)| a * b).sum();
    let nu = u.iter().map(|a| a * a).sum::<f64>().sqrt();
    let nv = v.iter().map(|a| a * a).sum::<f64>().sqrt();
    (dot / (nu * nv)).clamp(-1.0, 1.0).acos().to_degrees()
}

fn min_foot_height(poses: &[Pose]) -> f64 {
    poses
        .iter()
        .flat_map(|p| FEET_LEFT.iter().chain(&FEET_RIGHT).map(move |&j| p[j][1]))
        .fold(f64::INFINITY, f64::min)
}

#[test]
fn same_seed_and_index_give_the_same_clip() {
    for i in [0, 1, 71, 72, 5000] {
        let a = synth::generate(4, i);
        let b = synth::generate(4, i);
        assert_eq!(a.poses, b.poses);
        assert_eq!(a.labels, b.labels);
        assert_eq!(a.captions, b.captions);
        assert_eq!(a.clip_id, format!("synth_4_{i:08}"));
        assert_eq!(a.source, "synth");
        assert_eq!(a.source_path.to_str(), Some("synth:4"));
        assert_eq!(a.fps, FPS);
        assert_eq!(a.conversion, "synthetic SMPL-22 (metres, Y up)");
        assert_eq!(a.split, None);
        let other = synth::generate(5, i);
        assert_ne!(a.poses, other.poses, "seeds 4 and 5, clip {i}");
    }
    let spec: SynthSpec = "synth:3:9".parse().unwrap();
    assert_eq!((spec.clips, spec.seed), (3, 9));
}

#[test]
fn clips_are_physically_plausible() {
    let opts = Hml263Options::default();
    let mut slide_sum = 0.0;
    let mut slide_n = 0usize;
    let mut worst_clip_slide: (f64, String) = (0.0, String::new());
    let mut max_knee: f64 = 0.0;
    let mut max_elbow: f64 = 0.0;
    let mut per_action = vec![(0.0, 0usize); ACTIONS.len()];
    for i in 0..300 {
        let clip = synth::generate(11, i);
        let id = format!("{} ({:?})", clip.clip_id, clip.labels);
        let frames = clip.poses.len();
        assert!(
            (40..=200).contains(&frames),
            "{id}: {frames} frames, expected 2–10 s at 20 fps"
        );
        // Bone lengths are those of the clip's first frame, to FK rounding.
        let first = clip.poses[0];
        for (t, pose) in clip.poses.iter().enumerate() {
            for j in 1..NUM_JOINTS {
                let len0 = dist(first[j], first[PARENTS[j]]);
                let len = dist(pose[j], pose[PARENTS[j]]);
                assert!(
                    (len - len0).abs() <= 1e-9 * len0,
                    "{id} frame {t} joint {j}: bone {len} vs {len0}"
                );
            }
            for (hip, knee, ankle) in [(1, 4, 7), (2, 5, 8)] {
                let k = flexion(pose, hip, knee, ankle);
                assert!(k <= 150.0, "{id} frame {t}: knee flexion {k:.1}°");
                max_knee = max_knee.max(k);
            }
            for (sh, el, wr) in [(16, 18, 20), (17, 19, 21)] {
                let e = flexion(pose, sh, el, wr);
                assert!(e <= 150.0, "{id} frame {t}: elbow flexion {e:.1}°");
                max_elbow = max_elbow.max(e);
            }
            // Knees never bend forward: the shin turns backward relative to the thigh.
            for (hip, knee, ankle, sign) in [(1, 4, 7, 1.0), (2, 5, 8, 1.0)] {
                let lateral = [
                    pose[1][0] - pose[2][0],
                    pose[1][1] - pose[2][1],
                    pose[1][2] - pose[2][2],
                ];
                let thigh: Vec<f64> = (0..3).map(|k| pose[knee][k] - pose[hip][k]).collect();
                let shin: Vec<f64> = (0..3).map(|k| pose[ankle][k] - pose[knee][k]).collect();
                let c = [
                    thigh[1] * shin[2] - thigh[2] * shin[1],
                    thigh[2] * shin[0] - thigh[0] * shin[2],
                    thigh[0] * shin[1] - thigh[1] * shin[0],
                ];
                let s: f64 = sign * (c[0] * lateral[0] + c[1] * lateral[1] + c[2] * lateral[2]);
                assert!(
                    s >= -1e-4,
                    "{id} frame {t}: knee {knee} hyperextended ({s})"
                );
            }
        }
        let raw_min = min_foot_height(&clip.poses);
        assert!(raw_min.abs() <= 0.02, "{id}: raw min foot height {raw_min}");
        let feats = hml263::process(&clip.poses, &opts).unwrap();
        let min = min_foot_height(&feats.joints);
        assert!(min.abs() <= 0.02, "{id}: processed min foot height {min}");
        assert!(feats.features.iter().all(|v| v.is_finite()), "{id}");
        // Sliding: horizontal speed of a foot joint between consecutive frames in which it
        // is within 2 cm of the floor (in contact).
        let mut clip_sum = 0.0;
        let mut clip_n = 0usize;
        for w in clip.poses.windows(2) {
            for &j in FEET_LEFT.iter().chain(&FEET_RIGHT) {
                if w[0][j][1] < 0.02 && w[1][j][1] < 0.02 {
                    let dx = w[1][j][0] - w[0][j][0];
                    let dz = w[1][j][2] - w[0][j][2];
                    clip_sum += (dx * dx + dz * dz).sqrt() * FPS;
                    clip_n += 1;
                }
            }
        }
        assert!(clip_n > 0, "{id}: no foot ever touches the floor");
        let clip_mean = clip_sum / clip_n as f64;
        if clip_mean > worst_clip_slide.0 {
            worst_clip_slide = (clip_mean, id.clone());
        }
        slide_sum += clip_sum;
        slide_n += clip_n;
        let a = ACTIONS
            .iter()
            .position(|a| Some(*a) == clip.labels.action.as_deref())
            .unwrap();
        per_action[a].0 += clip_sum;
        per_action[a].1 += clip_n;
    }
    let mean = slide_sum / slide_n as f64;
    println!(
        "foot sliding in contact: mean {:.2} cm/s over {slide_n} foot-frames; worst clip {:.2} cm/s ({}); max knee {max_knee:.1}°, max elbow {max_elbow:.1}°",
        100.0 * mean,
        100.0 * worst_clip_slide.0,
        worst_clip_slide.1
    );
    for (a, (sum, n)) in ACTIONS.iter().zip(&per_action) {
        println!("  {a:>10}: {:.2} cm/s", 100.0 * sum / (*n).max(1) as f64);
    }
    assert!(mean < 0.05, "mean contact sliding {mean} m/s");
    assert!(
        worst_clip_slide.0 < 0.20,
        "worst clip sliding {:?}",
        worst_clip_slide
    );
}

/// Lateralised captions: the named hand or leg is the one that moves.
#[test]
fn captions_name_the_action_and_the_moving_side() {
    let keywords: &[(&str, &[&str])] = &[
        ("walk", &["walk"]),
        ("run", &["run", "jog"]),
        ("turn", &["turn"]),
        ("wave", &["wave"]),
        ("bow", &["bow"]),
        ("raise hand", &["raise", "hand up"]),
        ("clap", &["clap"]),
        ("kick", &["kick"]),
        ("punch", &["punch"]),
        ("dance step", &["danc"]),
        ("sit down", &["sit"]),
        ("jump", &["jump", "hop"]),
    ];
    let mut lateral_checked = 0;
    for i in 0..400 {
        let clip = synth::generate(21, i);
        let action = clip.labels.action.clone().unwrap();
        let words = keywords.iter().find(|(a, _)| *a == action).unwrap().1;
        assert_eq!(clip.captions.len(), 3, "{}", clip.clip_id);
        let mut distinct = clip.captions.clone();
        distinct.dedup();
        assert_eq!(distinct.len(), 3, "{:?}", clip.captions);
        for c in &clip.captions {
            assert!(
                words.iter().any(|w| c.contains(w)),
                "{}: {c:?} does not name {action}",
                clip.clip_id
            );
        }
        let says = |w: &str| clip.captions.iter().all(|c| c.contains(w));
        let side = if says(" left") {
            Some(0)
        } else if says(" right") {
            Some(1)
        } else {
            None
        };
        let peak = |j: usize| clip.poses.iter().map(|p| p[j][1]).fold(f64::MIN, f64::max);
        let moving = match action.as_str() {
            "wave" | "raise hand" => Some((peak(20), peak(21))),
            "kick" => Some((peak(10), peak(11))),
            "punch" => {
                // Reach: wrist distance from its shoulder, largest over the clip.
                let reach = |w: usize, s: usize| {
                    clip.poses
                        .iter()
                        .map(|p| dist(p[w], p[s]))
                        .fold(f64::MIN, f64::max)
                };
                Some((reach(20, 16), reach(21, 17)))
            }
            "turn" => {
                // Heading from the hip axis: across = (cos h, 0, −sin h) for heading h (left > 0).
                let facing = |p: &Pose| {
                    let (x, z) = (p[1][0] - p[2][0], p[1][2] - p[2][2]);
                    (-z).atan2(x)
                };
                let mut total = 0.0;
                for w in clip.poses.windows(2) {
                    let mut d = facing(&w[1]) - facing(&w[0]);
                    d = (d + std::f64::consts::PI).rem_euclid(std::f64::consts::TAU)
                        - std::f64::consts::PI;
                    total += d;
                }
                Some((total, -total))
            }
            _ => None,
        };
        if let Some((left, right)) = moving {
            let side = side
                .unwrap_or_else(|| panic!("{}: {:?} names no side", clip.clip_id, clip.captions));
            let named_moves_more = if side == 0 {
                left > right
            } else {
                right > left
            };
            assert!(
                named_moves_more,
                "{} {action}: captions {:?}, left {left:.3} right {right:.3}",
                clip.clip_id, clip.captions
            );
            lateral_checked += 1;
        }
    }
    assert!(lateral_checked > 100, "{lateral_checked}");
}

/// Per-clip statistics of the 263 features: mean and std of every dimension, and the mean
/// absolute frame-to-frame change of the velocity blocks (tempo and jerkiness).
fn clip_stats(clip: &RawClip) -> Vec<f64> {
    let feats = hml263::process(&clip.poses, &Hml263Options::default()).unwrap();
    let rows = feats.features.len() / FEATURE_DIM;
    let mut out = vec![0.0; 3 * FEATURE_DIM];
    for r in feats.features.chunks_exact(FEATURE_DIM) {
        for (d, &v) in r.iter().enumerate() {
            out[d] += v as f64;
            out[FEATURE_DIM + d] += (v as f64) * (v as f64);
        }
    }
    for w in feats
        .features
        .chunks_exact(FEATURE_DIM)
        .collect::<Vec<_>>()
        .windows(2)
    {
        for d in 0..FEATURE_DIM {
            out[2 * FEATURE_DIM + d] += (w[1][d] - w[0][d]).abs() as f64;
        }
    }
    for d in 0..FEATURE_DIM {
        let mean = out[d] / rows as f64;
        out[d] = mean;
        out[FEATURE_DIM + d] = (out[FEATURE_DIM + d] / rows as f64 - mean * mean)
            .max(0.0)
            .sqrt();
        out[2 * FEATURE_DIM + d] /= (rows - 1).max(1) as f64;
    }
    out
}

/// Softmax regression with L2, full-batch Adam; returns the weights (classes × (dim + 1)).
fn train_softmax(x: &[Vec<f64>], y: &[usize], classes: usize, l2: f64, epochs: usize) -> Vec<f64> {
    let dim = x[0].len() + 1;
    let n = x.len() as f64;
    let mut w = vec![0.0; classes * dim];
    let (mut m, mut v) = (vec![0.0; w.len()], vec![0.0; w.len()]);
    let (lr, b1, b2) = (0.02, 0.9, 0.999);
    let mut p = vec![0.0; classes];
    for epoch in 1..=epochs {
        let mut grad: Vec<f64> = w.iter().map(|wi| l2 * wi).collect();
        for (xi, &yi) in x.iter().zip(y) {
            for (c, pc) in p.iter_mut().enumerate() {
                let row = &w[c * dim..(c + 1) * dim];
                *pc = row[dim - 1] + row.iter().zip(xi).map(|(a, b)| a * b).sum::<f64>();
            }
            let max = p.iter().cloned().fold(f64::MIN, f64::max);
            let z: f64 = p
                .iter_mut()
                .map(|pc| {
                    *pc = (*pc - max).exp();
                    *pc
                })
                .sum();
            for (c, pc) in p.iter().enumerate() {
                let e = (pc / z - f64::from(u8::from(c == yi))) / n;
                let g = &mut grad[c * dim..(c + 1) * dim];
                for (gk, xk) in g.iter_mut().zip(xi) {
                    *gk += e * xk;
                }
                g[dim - 1] += e;
            }
        }
        let (c1, c2) = (1.0 - b1_pow(b1, epoch), 1.0 - b1_pow(b2, epoch));
        for k in 0..w.len() {
            m[k] = b1 * m[k] + (1.0 - b1) * grad[k];
            v[k] = b2 * v[k] + (1.0 - b2) * grad[k] * grad[k];
            w[k] -= lr * (m[k] / c1) / ((v[k] / c2).sqrt() + 1e-8);
        }
    }
    w
}

fn b1_pow(b: f64, e: usize) -> f64 {
    b.powi(e as i32)
}

fn accuracy(w: &[f64], x: &[Vec<f64>], y: &[usize], classes: usize) -> f64 {
    let dim = x[0].len() + 1;
    let correct = x
        .iter()
        .zip(y)
        .filter(|(xi, &yi)| {
            let score = |c: usize| {
                let row = &w[c * dim..(c + 1) * dim];
                row[dim - 1] + row.iter().zip(xi.iter()).map(|(a, b)| a * b).sum::<f64>()
            };
            let best = (0..classes)
                .max_by(|&a, &b| score(a).total_cmp(&score(b)))
                .unwrap_or(0);
            best == yi
        })
        .count();
    correct as f64 / y.len() as f64
}

#[test]
fn labels_are_recoverable_from_the_motion() {
    let start = Instant::now();
    let data = |seed: u64, n: usize| {
        let clips: Vec<RawClip> = (0..n).map(|i| synth::generate(seed, i)).collect();
        let x: Vec<Vec<f64>> = clips.iter().map(clip_stats).collect();
        let label = |c: &RawClip, names: &[&str], pick: fn(&RawClip) -> Option<String>| {
            let l = pick(c).unwrap();
            names.iter().position(|n| *n == l).unwrap()
        };
        let actions: Vec<usize> = clips
            .iter()
            .map(|c| label(c, ACTIONS, |c| c.labels.action.clone()))
            .collect();
        let emotions: Vec<usize> = clips
            .iter()
            .map(|c| label(c, EMOTIONS, |c| c.labels.emotion.clone()))
            .collect();
        (x, actions, emotions)
    };
    let (mut train, train_a, train_e) = data(1, 1200);
    let (mut test, test_a, test_e) = data(2, 600);
    let dims = train[0].len();
    for d in 0..dims {
        let mean = train.iter().map(|r| r[d]).sum::<f64>() / train.len() as f64;
        let var = train.iter().map(|r| (r[d] - mean).powi(2)).sum::<f64>() / train.len() as f64;
        let sd = if var > 1e-12 { var.sqrt() } else { 1.0 };
        for r in train.iter_mut().chain(test.iter_mut()) {
            r[d] = (r[d] - mean) / sd;
        }
    }
    let features_s = start.elapsed().as_secs_f64();
    let wa = train_softmax(&train, &train_a, ACTIONS.len(), 1e-3, 300);
    let we = train_softmax(&train, &train_e, EMOTIONS.len(), 1e-3, 300);
    let acc_a = accuracy(&wa, &test, &test_a, ACTIONS.len());
    let acc_e = accuracy(&we, &test, &test_e, EMOTIONS.len());
    let train_acc_e = accuracy(&we, &train, &train_e, EMOTIONS.len());
    println!(
        "held-out accuracy (train seed 1 ×1200, test seed 2 ×600): action {:.1}%, emotion {:.1}% (emotion train {:.1}%); data {features_s:.1}s, total {:.1}s",
        100.0 * acc_a,
        100.0 * acc_e,
        100.0 * train_acc_e,
        start.elapsed().as_secs_f64()
    );
    assert!(acc_a >= 0.90, "action accuracy {acc_a}");
    assert!(acc_e >= 0.90, "emotion accuracy {acc_e}");
}
