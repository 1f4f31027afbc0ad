//! Structured mutation fuzzing of the BVH parser, shared by `examples/fuzz_bvh.rs` and the
//! tests: a seeded generator of valid BVH files of several shapes, mutations that target
//! the grammar (tokens, counts, braces, lines), and a panic-catching check of one input.

use super::{parse_bytes, Channel};
use crate::quat::Vec3;
use crate::rng::SplitMix64 as Rng;
use std::panic::{catch_unwind, AssertUnwindSafe};

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
    let lns = lines(input);
    match rng.index(10) {
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
            // Edit a count: the number after CHANNELS or Frames:.
            let counts: Vec<(usize, usize)> = toks
                .windows(2)
                .filter(|w| {
                    let k = &input[w[0].0..w[0].1];
                    k == b"CHANNELS" || k == b"Frames:"
                })
                .map(|w| w[1])
                .collect();
            if counts.is_empty() {
                input.to_vec()
            } else {
                let t = counts[rng.index(counts.len())];
                let with = match rng.index(4) {
                    0 => rng.index(8).to_string(),
                    1 => "-3".to_string(),
                    2 => "4000000000000".to_string(),
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

/// Parse `input` and run forward kinematics on success, catching panics.
///
/// `Ok(true)`: parsed; `Ok(false)`: rejected with an error; `Err`: the panic message.
pub fn check(input: &[u8]) -> Result<bool, String> {
    catch_unwind(AssertUnwindSafe(|| match parse_bytes(input) {
        Ok(bvh) => {
            let world = bvh.world_positions();
            assert_eq!(world.len(), bvh.num_frames() * bvh.joints.len());
            true
        }
        Err(e) => {
            assert!(e.line >= 1 && !e.message.is_empty(), "bad error {e:?}");
            false
        }
    }))
    .map_err(|p| {
        p.downcast_ref::<String>()
            .cloned()
            .or_else(|| p.downcast_ref::<&str>().map(|s| s.to_string()))
            .unwrap_or_else(|| "panic".to_string())
    })
}

/// A corpus of seed inputs and a generator of mutated inputs from it.
pub struct Fuzzer {
    /// Seeded random state.
    pub rng: Rng,
    /// Seed inputs (generated and read from files).
    pub seeds: Vec<Vec<u8>>,
}

impl Fuzzer {
    /// A fuzzer with `generated` random seed BVHs plus `extra` seeds.
    pub fn new(seed: u64, generated: usize, extra: Vec<Vec<u8>>) -> Self {
        let mut rng = Rng(seed);
        let mut seeds: Vec<Vec<u8>> = (0..generated)
            .map(|_| generate(&mut rng).into_bytes())
            .collect();
        seeds.extend(extra);
        Self { rng, seeds }
    }

    /// Next input: a seed (or a fresh generated file) with 1–4 stacked mutations.
    pub fn next_input(&mut self) -> Vec<u8> {
        let mut input = if self.seeds.is_empty() || self.rng.index(8) == 0 {
            generate(&mut self.rng).into_bytes()
        } else {
            self.seeds[self.rng.index(self.seeds.len())].clone()
        };
        for _ in 0..1 + self.rng.index(4) {
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
    fn generated_seeds_parse() {
        let mut rng = Rng(7);
        for _ in 0..200 {
            let text = generate(&mut rng);
            assert_eq!(check(text.as_bytes()), Ok(true), "{text}");
        }
    }

    #[test]
    fn two_thousand_mutations_neither_panic_nor_hang() {
        let mut fuzzer = Fuzzer::new(42, 32, Vec::new());
        let (mut ok, mut rejected) = (0, 0);
        let start = std::time::Instant::now();
        for i in 0..2000 {
            let input = fuzzer.next_input();
            match check(&input) {
                Ok(true) => ok += 1,
                Ok(false) => rejected += 1,
                Err(p) => panic!(
                    "input {i} panicked: {p}\n{}",
                    String::from_utf8_lossy(&input)
                ),
            }
        }
        assert!(ok > 20 && rejected > 500, "ok {ok} rejected {rejected}");
        assert!(start.elapsed().as_secs() < 60);
    }
}
