//! Structured mutation fuzzing of the whole per-input BVH path, shared by
//! `examples/fuzz_bvh.rs` and the tests: seeded generators of valid BVH files (random rigs
//! of several shapes, and SMPL-22 humanoids that go all the way to features), mutations that
//! target the grammar (tokens, counts, frame times, braces, lines), and a panic-catching check
//! of one input through parse → retarget → budgets → resample → segment → features.

use crate::budget::MAX_RESAMPLED_FRAMES;
use crate::hml263::FEATURE_DIM;
use crate::pipeline::{process_clip, IngestOptions};
use crate::quat::Vec3;
use crate::skeleton::{JOINT_NAMES, NUM_JOINTS, PARENTS, TARGET_OFFSETS};
use crate::source::bvh::{parse_bytes, Channel};
use crate::source::retarget::clip_from_bytes;
use motionscale_core::rng::SplitMix64 as Rng;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::Path;

/// A joint for [`write_bvh`]: parents must precede children.
#[derive(Debug, Clone)]
pub struct SeedJoint {
    /// Joint name.
    pub name: String,
    /// Parent index (`None` for a ROOT).
    pub parent: Option<usize>,
    /// Rest offset.
    pub offset: Vec3,
    /// Channels in file order.
    pub channels: Vec<Channel>,
}

/// Text layout choices for [`write_bvh`].
#[derive(Debug, Clone, Copy, Default)]
pub struct Layout {
    /// Use CRLF line endings.
    pub crlf: bool,
    /// Indent with tabs instead of two spaces.
    pub tabs: bool,
    /// Wrap motion values after this many per line (`None`: one frame per line).
    pub wrap: Option<usize>,
}

/// Render a BVH file; leaves get an End Site; `motion` is frames × channels, row-major.
pub fn write_bvh(joints: &[SeedJoint], frame_time: f64, motion: &[f64], layout: Layout) -> String {
    let nl = if layout.crlf { "\r\n" } else { "\n" };
    let ind = |d: usize| if layout.tabs { "\t" } else { "  " }.repeat(d);
    let mut out = format!("HIERARCHY{nl}");
    fn emit(
        joints: &[SeedJoint],
        j: usize,
        depth: usize,
        out: &mut String,
        nl: &str,
        ind: &dyn Fn(usize) -> String,
    ) {
        let kw = if joints[j].parent.is_none() {
            "ROOT"
        } else {
            "JOINT"
        };
        let [x, y, z] = joints[j].offset;
        let names: Vec<String> = joints[j]
            .channels
            .iter()
            .map(|c| format!("{c:?}"))
            .collect();
        out.push_str(&format!(
            "{i}{kw} {n}{nl}{i}{{{nl}{i2}OFFSET {x} {y} {z}{nl}{i2}CHANNELS {c} {names}{nl}",
            i = ind(depth),
            i2 = ind(depth + 1),
            n = joints[j].name,
            c = names.len(),
            names = names.join(" "),
        ));
        let children: Vec<usize> = (0..joints.len())
            .filter(|&k| joints[k].parent == Some(j))
            .collect();
        if children.is_empty() {
            out.push_str(&format!(
                "{i}End Site{nl}{i}{{{nl}{i2}OFFSET 0 1 0{nl}{i}}}{nl}",
                i = ind(depth + 1),
                i2 = ind(depth + 2)
            ));
        }
        for c in children {
            emit(joints, c, depth + 1, out, nl, ind);
        }
        out.push_str(&format!("{}}}{nl}", ind(depth)));
    }
    for (j, joint) in joints.iter().enumerate() {
        if joint.parent.is_none() {
            emit(joints, j, 0, &mut out, nl, &ind);
        }
    }
    let channels: usize = joints.iter().map(|j| j.channels.len()).sum();
    let frames = motion.len().checked_div(channels).unwrap_or(0);
    out.push_str(&format!(
        "MOTION{nl}Frames: {frames}{nl}Frame Time: {frame_time}{nl}"
    ));
    let per_line = layout.wrap.unwrap_or(channels).max(1);
    for frame in motion.chunks(channels.max(1)) {
        for line in frame.chunks(per_line) {
            let vals: Vec<String> = line.iter().map(|v| v.to_string()).collect();
            out.push_str(&vals.join(" "));
            out.push_str(nl);
        }
    }
    out
}

const ALL_CHANNELS: [Channel; 6] = [
    Channel::Xposition,
    Channel::Yposition,
    Channel::Zposition,
    Channel::Xrotation,
    Channel::Yrotation,
    Channel::Zrotation,
];

/// A random valid BVH: 1–8 joints in a random tree, 1–6 channels each in random order,
/// 1–6 frames, random layout and number formatting.
pub fn generate(rng: &mut Rng) -> String {
    let n = 1 + rng.index(8);
    let joints: Vec<SeedJoint> = (0..n)
        .map(|j| {
            let mut pool = ALL_CHANNELS.to_vec();
            let count = if j == 0 || rng.index(2) == 0 {
                if rng.index(2) == 0 {
                    6
                } else {
                    3
                }
            } else {
                1 + rng.index(6)
            };
            let channels = (0..count)
                .map(|_| pool.remove(rng.index(pool.len())))
                .collect();
            SeedJoint {
                name: format!("J{j}"),
                parent: if j == 0 { None } else { Some(rng.index(j)) },
                offset: [
                    rng.range(-20.0, 20.0),
                    rng.range(-20.0, 20.0),
                    rng.range(-20.0, 20.0),
                ],
                channels,
            }
        })
        .collect();
    let channels: usize = joints.iter().map(|j| j.channels.len()).sum();
    let frames = 1 + rng.index(6);
    let motion: Vec<f64> = (0..frames * channels)
        .map(|_| match rng.index(4) {
            0 => rng.range(-1e-5, 1e-5),
            1 => rng.range(-180.0, 180.0).round(),
            _ => rng.range(-180.0, 180.0),
        })
        .collect();
    let layout = Layout {
        crlf: rng.index(2) == 0,
        tabs: rng.index(2) == 0,
        wrap: (rng.index(3) == 0).then(|| 1 + rng.index(7)),
    };
    write_bvh(
        &joints,
        1.0 / (10.0 + rng.index(111) as f64),
        &motion,
        layout,
    )
}

/// A random valid BVH of the SMPL-22 rig (our export's joint names, centimetres): root
/// translation and 3 rotations per joint drifting smoothly over 10–249 frames at 10–120 fps,
/// so that unmutated it is retargeted and, when long enough, ingested.
pub fn humanoid(rng: &mut Rng) -> String {
    let rotations = vec![Channel::Zrotation, Channel::Xrotation, Channel::Yrotation];
    let joints: Vec<SeedJoint> = (0..NUM_JOINTS)
        .map(|j| SeedJoint {
            name: JOINT_NAMES[j].to_string(),
            parent: (j > 0).then_some(PARENTS[j]),
            offset: TARGET_OFFSETS[j].map(|v| v * 100.0),
            channels: if j == 0 {
                [&ALL_CHANNELS[..3], &rotations[..]].concat()
            } else {
                rotations.clone()
            },
        })
        .collect();
    let channels = 3 + 3 * NUM_JOINTS;
    let frames = 10 + rng.index(240);
    let mut value: Vec<f64> = (0..channels).map(|_| rng.range(-20.0, 20.0)).collect();
    value[1] += 90.0;
    let mut motion = Vec::with_capacity(frames * channels);
    for _ in 0..frames {
        value.iter_mut().for_each(|v| *v += rng.range(-3.0, 3.0));
        motion.extend_from_slice(&value);
    }
    let fps = 10.0 + rng.index(111) as f64;
    write_bvh(&joints, 1.0 / fps, &motion, Layout::default())
}

/// Replacement tokens that stress the grammar and the number parser.
const NASTY: [&str; 24] = [
    "nan",
    "NaN",
    "inf",
    "-inf",
    "1e400",
    "-1e400",
    "abc",
    "{",
    "}",
    "-1",
    "0",
    "-0",
    "99999999999999999999",
    "4294967297",
    "18446744073709551615",
    "1e-400",
    "ROOT",
    "JOINT",
    "End",
    "MOTION",
    "Frames:",
    "CHANNELS",
    "Xrotation",
    "",
];

/// Byte ranges of whitespace-separated tokens.
fn tokens(input: &[u8]) -> Vec<(usize, usize)> {
    let mut out = Vec::new();
    let mut i = 0;
    while i < input.len() {
        while i < input.len() && input[i].is_ascii_whitespace() {
            i += 1;
        }
        let start = i;
        while i < input.len() && !input[i].is_ascii_whitespace() {
            i += 1;
        }
        if i > start {
            out.push((start, i));
        }
    }
    out
}

/// Byte ranges of lines (each including its newline).
fn lines(input: &[u8]) -> Vec<(usize, usize)> {
    let mut out = Vec::new();
    let mut start = 0;
    for (i, &b) in input.iter().enumerate() {
        if b == b'\n' {
            out.push((start, i + 1));
            start = i + 1;
        }
    }
    if start < input.len() {
        out.push((start, input.len()));
    }
    out
}

fn splice(input: &[u8], (s, e): (usize, usize), with: &[u8]) -> Vec<u8> {
    [&input[..s], with, &input[e..]].concat()
}

/// Apply one random mutation to `input`; `other` is a second input for splicing.
pub fn mutate(rng: &mut Rng, input: &[u8], other: &[u8]) -> Vec<u8> {
    let toks = tokens(input);
    // Tokens of the motion section (counts, frame time, values).
    let motion = toks
        .iter()
        .position(|t| &input[t.0..t.1] == b"MOTION")
        .map_or(&toks[..0], |m| &toks[m + 1..]);
    let lns = lines(input);
    match rng.index(13) {
        10..=12 if !motion.is_empty() => {
            // A value becomes another finite number that still parses: huge, tiny, negative.
            let t = motion[rng.index(motion.len())];
            let magnitude = 10f64.powf(rng.range(-30.0, 30.0));
            let with = match rng.index(3) {
                0 => "1e26".to_string(),
                1 => format!("{magnitude:e}"),
                _ => format!("{:e}", -magnitude),
            };
            splice(input, t, with.as_bytes())
        }
        0 if !input.is_empty() => {
            let mut out = input.to_vec();
            for _ in 0..1 + rng.index(4) {
                let i = rng.index(out.len());
                out[i] ^= 1 << rng.index(8);
            }
            out
        }
        1 if !toks.is_empty() => {
            let t = toks[rng.index(toks.len())];
            splice(input, t, NASTY[rng.index(NASTY.len())].as_bytes())
        }
        2 if !toks.is_empty() => {
            // Numbers become words, huge or negative values, and the other way round.
            let t = toks[rng.index(toks.len())];
            let with = match rng.index(4) {
                0 => format!("{}", rng.next_u64()),
                1 => format!("-{}", rng.index(1000)),
                2 => format!("{:e}", rng.range(-1e300, 1e300)),
                _ => "word".to_string(),
            };
            splice(input, t, with.as_bytes())
        }
        3 if !lns.is_empty() => splice(input, lns[rng.index(lns.len())], b""),
        4 if !lns.is_empty() => {
            let l = lns[rng.index(lns.len())];
            let dup = input[l.0..l.1].repeat(1 + rng.index(3));
            splice(input, (l.0, l.0), &dup)
        }
        5 => input[..rng.index(input.len() + 1)].to_vec(),
        6 => {
            let braces: Vec<usize> = (0..input.len())
                .filter(|&i| input[i] == b'{' || input[i] == b'}')
                .collect();
            if braces.is_empty() {
                input.to_vec()
            } else {
                let i = braces[rng.index(braces.len())];
                splice(input, (i, i + 1), b"")
            }
        }
        7 => {
            // Edit a count or the frame time: the number after CHANNELS, Frames: or Time:.
            let counts: Vec<(usize, usize)> = toks
                .windows(2)
                .filter(|w| {
                    let k = &input[w[0].0..w[0].1];
                    k == b"CHANNELS" || k == b"Frames:" || k == b"Time:"
                })
                .map(|w| w[1])
                .collect();
            if counts.is_empty() {
                input.to_vec()
            } else {
                let t = counts[rng.index(counts.len())];
                let with = match rng.index(6) {
                    0 => rng.index(8).to_string(),
                    1 => "-3".to_string(),
                    2 => "4000000000000".to_string(),
                    3 => ["100000", "1000", "0.9", "1e-9", "0.0001", ""][rng.index(6)].to_string(),
                    4 => format!("{:e}", rng.range(0.0, 1.0).powi(8) * 1e6),
                    _ => (1usize << (rng.index(40) + 20)).to_string(),
                };
                splice(input, t, with.as_bytes())
            }
        }
        8 => {
            let a = rng.index(input.len() + 1);
            let b = rng.index(other.len() + 1);
            [&input[..a], &other[b..]].concat()
        }
        _ => {
            let mut out = input.to_vec();
            if !out.is_empty() {
                let i = rng.index(out.len());
                out.insert(i, b" \t\r\n\x0b\x00\xff"[rng.index(7)]);
            }
            out
        }
    }
}

/// How far one input got along the per-input path.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Outcome {
    /// Refused by the parser.
    Unparsed,
    /// Parsed, then refused by retargeting (unknown rig, implausible size, not UTF-8).
    NotRetargeted,
    /// Retargeted and processed: `clips` clips ingested, `rejects` rejected (at least one
    /// of the two: every input is accounted for).
    Processed {
        /// Clips ingested (mirrored copies included).
        clips: usize,
        /// Clips or segments rejected.
        rejects: usize,
    },
}

/// Run `input` through the whole per-input path (parse and forward kinematics, retarget,
/// budgets and plausibility, resample, segment, mirror, features), catching panics and
/// checking that every outcome is accounted for and every ingested clip is within budget
/// and finite. `Err`: the panic message.
pub fn check(input: &[u8]) -> Result<Outcome, String> {
    catch_unwind(AssertUnwindSafe(|| {
        let bvh = match parse_bytes(input) {
            Ok(bvh) => bvh,
            Err(e) => {
                assert!(e.line >= 1 && !e.message.is_empty(), "bad error {e:?}");
                return Outcome::Unparsed;
            }
        };
        let world = bvh.world_positions();
        assert_eq!(world.len(), bvh.num_frames() * bvh.joints.len());
        let path = Path::new("fuzz.bvh");
        let raw = match clip_from_bytes(input, path, path, None) {
            Ok(raw) => raw,
            Err(r) => {
                assert!(!r.reason.is_empty(), "reject without a reason");
                return Outcome::NotRetargeted;
            }
        };
        let opts = IngestOptions {
            mirror: true,
            ..Default::default()
        };
        let (clips, rejects) = process_clip(&raw, &opts);
        assert!(
            !clips.is_empty() || !rejects.is_empty(),
            "neither ingested nor rejected"
        );
        for c in &clips {
            let n = c.num_frames as usize;
            assert!(n <= MAX_RESAMPLED_FRAMES, "{n} frames ingested");
            assert_eq!(c.features.len(), n * FEATURE_DIM);
            assert!(c.features.iter().chain(&c.joints).all(|v| v.is_finite()));
        }
        Outcome::Processed {
            clips: clips.len(),
            rejects: rejects.len(),
        }
    }))
    .map_err(|p| {
        p.downcast_ref::<String>()
            .cloned()
            .or_else(|| p.downcast_ref::<&str>().map(|s| s.to_string()))
            .unwrap_or_else(|| "panic".to_string())
    })
}

/// A generated seed: a random rig for even `k`, a humanoid for odd `k`.
fn fresh(rng: &mut Rng, k: usize) -> String {
    if k % 2 == 0 {
        generate(rng)
    } else {
        humanoid(rng)
    }
}

/// A corpus of seed inputs and a generator of mutated inputs from it.
pub struct Fuzzer {
    /// Seeded random state.
    pub rng: Rng,
    /// Seed inputs (generated and read from files).
    pub seeds: Vec<Vec<u8>>,
}

impl Fuzzer {
    /// A fuzzer with `generated` random seed BVHs (random rigs and humanoids, half each)
    /// plus `extra` seeds.
    pub fn new(seed: u64, generated: usize, extra: Vec<Vec<u8>>) -> Self {
        let mut rng = Rng(seed);
        let mut seeds: Vec<Vec<u8>> = (0..generated)
            .map(|k| fresh(&mut rng, k).into_bytes())
            .collect();
        seeds.extend(extra);
        Self { rng, seeds }
    }

    /// Next input: a seed (or a fresh generated file) with one mutation half the time, 1–4
    /// stacked ones otherwise.
    pub fn next_input(&mut self) -> Vec<u8> {
        let mut input = if self.seeds.is_empty() || self.rng.index(8) == 0 {
            let k = self.rng.index(2);
            fresh(&mut self.rng, k).into_bytes()
        } else {
            self.seeds[self.rng.index(self.seeds.len())].clone()
        };
        let mutations = if self.rng.index(2) == 0 {
            1
        } else {
            1 + self.rng.index(4)
        };
        for _ in 0..mutations {
            let other = if self.seeds.is_empty() {
                Vec::new()
            } else {
                self.seeds[self.rng.index(self.seeds.len())].clone()
            };
            input = mutate(&mut self.rng, &input, &other);
        }
        input
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn generated_seeds_parse_and_humanoids_are_ingested() {
        let mut rng = Rng(7);
        for _ in 0..100 {
            let text = generate(&mut rng);
            assert_ne!(check(text.as_bytes()), Ok(Outcome::Unparsed), "{text}");
        }
        let ingested = (0..40)
            .filter(|_| {
                let text = humanoid(&mut rng);
                match check(text.as_bytes()) {
                    Ok(Outcome::Processed { clips, .. }) => clips > 0,
                    other => panic!("{other:?}\n{text}"),
                }
            })
            .count();
        // Clips under 20 frames after resampling are rejected as too short.
        assert!(ingested > 20, "{ingested} of 40 humanoids ingested");
    }

    #[test]
    fn two_thousand_mutations_neither_panic_nor_lose_an_input() {
        let mut fuzzer = Fuzzer::new(42, 32, Vec::new());
        let (mut unparsed, mut processed, mut ingested) = (0, 0, 0);
        for i in 0..2000 {
            let input = fuzzer.next_input();
            match check(&input) {
                Ok(Outcome::Unparsed) => unparsed += 1,
                Ok(Outcome::NotRetargeted) => {}
                Ok(Outcome::Processed { clips, .. }) => {
                    processed += 1;
                    ingested += usize::from(clips > 0);
                }
                Err(p) => panic!(
                    "input {i} panicked: {p}\n{}",
                    String::from_utf8_lossy(&input)
                ),
            }
        }
        assert!(
            unparsed > 500 && processed > 50 && ingested > 40,
            "unparsed {unparsed} processed {processed} ingested {ingested}"
        );
    }
}
