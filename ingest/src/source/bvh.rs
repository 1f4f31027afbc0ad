//! BVH motion capture files: a robust parser (any channel layout, typed errors naming the
//! line), forward kinematics to world positions, and [`read_clip`], which reads one file
//! and retargets it to SMPL-22 with a [`RigMap`].

use crate::budget;
use crate::error::IngestError;
use crate::quat::{self, Quat, Vec3};
use std::collections::HashSet;
use std::fmt;

/// Channels a joint may have per line of motion data.
const MAX_CHANNELS: usize = 6;

/// A parse error with the 1-based line of the input where it was found.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub struct BvhError {
    /// 1-based line number in the input.
    pub line: usize,
    /// What is wrong there.
    pub message: String,
}

impl fmt::Display for BvhError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "line {}: {}", self.line, self.message)
    }
}

fn err<T>(line: usize, message: impl Into<String>) -> Result<T, BvhError> {
    Err(BvhError {
        line,
        message: message.into(),
    })
}

/// One motion channel of a joint.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Channel {
    /// Translation along X (replaces the offset's X).
    Xposition,
    /// Translation along Y.
    Yposition,
    /// Translation along Z.
    Zposition,
    /// Rotation about X, degrees.
    Xrotation,
    /// Rotation about Y, degrees.
    Yrotation,
    /// Rotation about Z, degrees.
    Zrotation,
}

impl Channel {
    fn from_name(name: &[u8]) -> Option<Self> {
        // Exporters disagree on case (`Xrotation`, `XROTATION`, `xRotation`).
        let lower = name.to_ascii_lowercase();
        Some(match lower.as_slice() {
            b"xposition" => Self::Xposition,
            b"yposition" => Self::Yposition,
            b"zposition" => Self::Zposition,
            b"xrotation" => Self::Xrotation,
            b"yrotation" => Self::Yrotation,
            b"zrotation" => Self::Zrotation,
            _ => return None,
        })
    }

    /// Axis index (0 = X, 1 = Y, 2 = Z).
    pub fn axis(self) -> usize {
        match self {
            Self::Xposition | Self::Xrotation => 0,
            Self::Yposition | Self::Yrotation => 1,
            Self::Zposition | Self::Zrotation => 2,
        }
    }

    /// Whether this is a rotation channel.
    pub fn is_rotation(self) -> bool {
        matches!(self, Self::Xrotation | Self::Yrotation | Self::Zrotation)
    }
}

/// A joint (or End Site) of the hierarchy.
#[derive(Debug, Clone, PartialEq)]
pub struct BvhJoint {
    /// Joint name; End Sites are named `<parent>_End`.
    pub name: String,
    /// Index of the parent joint (`None` for a ROOT).
    pub parent: Option<usize>,
    /// Rest offset from the parent, in file units.
    pub offset: Vec3,
    /// Channels in file order (empty for End Sites).
    pub channels: Vec<Channel>,
    /// Index of this joint's first channel within a frame's values.
    pub first_channel: usize,
    /// Whether this is an End Site.
    pub end_site: bool,
}

/// A parsed BVH file: hierarchy plus motion values (frames × channels, row-major).
#[derive(Debug, Clone, PartialEq)]
pub struct Bvh {
    /// Joints and End Sites in file order (parents precede children).
    pub joints: Vec<BvhJoint>,
    /// Seconds per frame.
    pub frame_time: f64,
    /// Channels per frame, over all joints.
    pub num_channels: usize,
    /// Motion values, `num_frames × num_channels`.
    pub motion: Vec<f64>,
}

impl Bvh {
    /// Number of frames of motion.
    pub fn num_frames(&self) -> usize {
        self.motion
            .len()
            .checked_div(self.num_channels)
            .unwrap_or(0)
    }

    /// Names of all joints and End Sites, in file order.
    pub fn joint_names(&self) -> Vec<&str> {
        self.joints.iter().map(|j| j.name.as_str()).collect()
    }

    /// Index of the joint called `name`.
    pub fn joint_index(&self, name: &str) -> Option<usize> {
        self.joints.iter().position(|j| j.name == name)
    }

    /// Frame rate (1 / frame time).
    pub fn fps(&self) -> f64 {
        1.0 / self.frame_time
    }

    /// World positions by forward kinematics: `num_frames × joints.len()`, frame-major.
    ///
    /// Rotation channels compose in file order (intrinsic, degrees); position channels
    /// replace the matching offset component; world = parent_rot · translation + parent_pos.
    pub fn world_positions(&self) -> Vec<Vec3> {
        let nj = self.joints.len();
        let mut out = vec![[0.0; 3]; self.num_frames() * nj];
        let mut rots: Vec<Quat> = vec![quat::IDENTITY; nj];
        for (values, pos) in self
            .motion
            .chunks_exact(self.num_channels.max(1))
            .zip(out.chunks_exact_mut(nj.max(1)))
        {
            for (j, joint) in self.joints.iter().enumerate() {
                let mut translation = joint.offset;
                let mut local = quat::IDENTITY;
                let vals = &values[joint.first_channel..joint.first_channel + joint.channels.len()];
                for (&ch, &v) in joint.channels.iter().zip(vals) {
                    if ch.is_rotation() {
                        local = quat::mul(local, axis_rotation(ch.axis(), v.to_radians()));
                    } else {
                        translation[ch.axis()] = v;
                    }
                }
                match joint.parent {
                    None => {
                        pos[j] = translation;
                        rots[j] = local;
                    }
                    Some(p) => {
                        pos[j] = quat::add(quat::rot(rots[p], translation), pos[p]);
                        rots[j] = quat::mul(rots[p], local);
                    }
                }
            }
        }
        out
    }
}

/// Rotation of `angle` radians about coordinate axis `axis`.
#[inline]
fn axis_rotation(axis: usize, angle: f64) -> Quat {
    let (s, c) = (angle * 0.5).sin_cos();
    let mut q = [c, 0.0, 0.0, 0.0];
    q[axis + 1] = s;
    q
}

/// Byte-level tokenizer that tracks line numbers; `{` and `}` are always tokens of their own.
struct Lexer<'a> {
    bytes: &'a [u8],
    pos: usize,
    line: usize,
}

impl<'a> Lexer<'a> {
    fn new(bytes: &'a [u8]) -> Self {
        Self {
            bytes,
            pos: 0,
            line: 1,
        }
    }

    #[inline]
    fn skip_space(&mut self) {
        while let Some(&b) = self.bytes.get(self.pos) {
            if b == b'\n' {
                self.line += 1;
            } else if !b.is_ascii_whitespace() && b != 0x0b {
                break;
            }
            self.pos += 1;
        }
    }

    /// Next token and its line, or `None` at end of input.
    #[inline]
    fn next(&mut self) -> Option<(&'a [u8], usize)> {
        self.skip_space();
        let start = self.pos;
        let first = *self.bytes.get(start)?;
        if first == b'{' || first == b'}' {
            self.pos += 1;
            return Some((&self.bytes[start..start + 1], self.line));
        }
        while let Some(&b) = self.bytes.get(self.pos) {
            if b.is_ascii_whitespace() || b == 0x0b || b == b'{' || b == b'}' {
                break;
            }
            self.pos += 1;
        }
        Some((&self.bytes[start..self.pos], self.line))
    }

    fn expect_any(&mut self, what: &str) -> Result<(&'a [u8], usize), BvhError> {
        match self.next() {
            Some(t) => Ok(t),
            None => err(
                self.line,
                format!("unexpected end of file, expected {what}"),
            ),
        }
    }

    fn expect(&mut self, word: &str) -> Result<usize, BvhError> {
        let (tok, line) = self.expect_any(&format!("'{word}'"))?;
        if tok.eq_ignore_ascii_case(word.as_bytes()) {
            Ok(line)
        } else {
            err(line, format!("expected '{word}', found '{}'", show(tok)))
        }
    }

    fn number(&mut self, what: &str) -> Result<f64, BvhError> {
        let (tok, line) = self.expect_any(what)?;
        match parse_f64(tok) {
            Some(v) if v.is_finite() => Ok(v),
            Some(_) => err(line, format!("non-finite {what} '{}'", show(tok))),
            None => err(
                line,
                format!("expected {what} (a number), found '{}'", show(tok)),
            ),
        }
    }

    /// A `Keyword:` label, also accepted as `Keyword :`.
    fn label(&mut self, word: &str) -> Result<usize, BvhError> {
        let (tok, line) = self.expect_any(&format!("'{word}:'"))?;
        let bare = tok.strip_suffix(b":").unwrap_or(tok);
        if !bare.eq_ignore_ascii_case(word.as_bytes()) {
            return err(line, format!("expected '{word}:', found '{}'", show(tok)));
        }
        if !tok.ends_with(b":") {
            self.expect(":")?;
        }
        Ok(line)
    }
}

/// A token for an error message: lossy UTF-8, shortened to 40 characters.
fn show(tok: &[u8]) -> String {
    let s = String::from_utf8_lossy(tok);
    if s.chars().count() > 40 {
        format!("{}…", s.chars().take(40).collect::<String>())
    } else {
        s.into_owned()
    }
}

/// Exact powers of ten for the fast float path.
const POW10: [f64; 23] = [
    1e0, 1e1, 1e2, 1e3, 1e4, 1e5, 1e6, 1e7, 1e8, 1e9, 1e10, 1e11, 1e12, 1e13, 1e14, 1e15, 1e16,
    1e17, 1e18, 1e19, 1e20, 1e21, 1e22,
];

/// Parse a decimal number. Plain decimals with ≤ 15 significant digits and small exponents
/// take Clinger's exact fast path (one multiply or divide of exact values, so correctly
/// rounded); anything else falls back to `str::parse`.
#[inline]
pub(crate) fn parse_f64(tok: &[u8]) -> Option<f64> {
    let mut i = 0;
    let neg = match tok.first() {
        Some(b'-') => {
            i = 1;
            true
        }
        Some(b'+') => {
            i = 1;
            false
        }
        _ => false,
    };
    let mut mant: u64 = 0;
    let mut sig = 0u32;
    let mut digits = 0;
    // Accumulate a run of digits into the mantissa; returns how many there were.
    let mut run = |i: &mut usize| {
        let start = *i;
        while let Some(&b) = tok.get(*i).filter(|b| b.is_ascii_digit()) {
            if mant != 0 || b != b'0' {
                sig += 1;
            }
            mant = mant.wrapping_mul(10).wrapping_add(u64::from(b - b'0'));
            *i += 1;
        }
        *i - start
    };
    digits += run(&mut i);
    let mut exp: i64 = 0;
    if tok.get(i) == Some(&b'.') {
        i += 1;
        let fraction = run(&mut i);
        digits += fraction;
        exp -= fraction as i64;
    }
    if digits > 0 && matches!(tok.get(i), Some(b'e' | b'E')) {
        i += 1;
        let eneg = match tok.get(i) {
            Some(b'-') => {
                i += 1;
                true
            }
            Some(b'+') => {
                i += 1;
                false
            }
            _ => false,
        };
        let start = i;
        let mut e: i64 = 0;
        while let Some(&b) = tok.get(i) {
            if !b.is_ascii_digit() || e > 100_000 {
                break;
            }
            e = e * 10 + i64::from(b - b'0');
            i += 1;
        }
        if i == start {
            return None;
        }
        exp += if eneg { -e } else { e };
    }
    if digits > 0 && i == tok.len() && sig <= 15 && (-22..=22).contains(&exp) {
        let m = mant as f64;
        let v = if exp >= 0 {
            m * POW10[exp as usize]
        } else {
            m / POW10[(-exp) as usize]
        };
        return Some(if neg { -v } else { v });
    }
    std::str::from_utf8(tok).ok()?.parse().ok()
}

/// A joint being read, with the line its block opened on (for brace errors).
struct Open {
    joint: usize,
    line: usize,
    has_offset: bool,
    has_end_site: bool,
}

/// Parse BVH text.
pub fn parse(text: &str) -> Result<Bvh, BvhError> {
    parse_bytes(text.as_bytes())
}

/// Parse BVH bytes (ASCII is all the grammar needs; joint names are read as lossy UTF-8).
pub fn parse_bytes(bytes: &[u8]) -> Result<Bvh, BvhError> {
    // Some Windows exporters start the file with a UTF-8 byte order mark.
    let bytes = bytes.strip_prefix(b"\xef\xbb\xbf").unwrap_or(bytes);
    let mut lx = Lexer::new(bytes);
    let joints = parse_hierarchy(&mut lx)?;
    let num_channels: usize = joints.iter().map(|j| j.channels.len()).sum();
    if num_channels == 0 {
        return err(lx.line, "the hierarchy has no channels");
    }
    let frames_line = lx.label("Frames")?;
    let (tok, line) = lx.expect_any("the frame count")?;
    let frames: usize = match std::str::from_utf8(tok).ok().and_then(|s| s.parse().ok()) {
        Some(n) => n,
        None => {
            return err(
                line,
                format!(
                    "Frames must be a non-negative integer, found '{}'",
                    show(tok)
                ),
            )
        }
    };
    if frames == 0 {
        return err(frames_line, "zero frames: the file has no motion");
    }
    lx.expect("Frame")?;
    let time_line = lx.label("Time")?;
    let frame_time = frame_time(&mut lx, time_line)?;
    budget::check_timing(frames, frame_time).or_else(|e| err(time_line, e))?;
    check_size(frames, num_channels, joints.len()).or_else(|e| err(frames_line, e))?;
    let motion = parse_motion(&mut lx, &joints, frames, num_channels)?;
    Ok(Bvh {
        joints,
        frame_time,
        num_channels,
        motion,
    })
}

/// The value of `Frame Time:`, which must stand on the label's own line: a value taken
/// from the next line would be the first motion value, and every later error would mislead.
fn frame_time(lx: &mut Lexer, label_line: usize) -> Result<f64, BvhError> {
    let before = (lx.pos, lx.line);
    let (tok, line) = lx.expect_any("the frame time")?;
    if line != label_line {
        (lx.pos, lx.line) = before;
        return err(
            label_line,
            "empty Frame Time: no value after 'Frame Time:' on its line",
        );
    }
    match parse_f64(tok) {
        Some(v) if v.is_finite() && v > 0.0 => Ok(v),
        _ => err(
            line,
            format!(
                "frame time must be a positive number, found '{}'",
                show(tok)
            ),
        ),
    }
}

/// The motion-size budgets, checked before the motion values are allocated.
fn check_size(frames: usize, channels: usize, joints: usize) -> Result<(), IngestError> {
    let values = frames.saturating_mul(channels);
    if values > budget::MAX_VALUES {
        return Err(format!(
            "Frames: {frames} × {channels} channels = {values} values, over the {}-value budget",
            budget::MAX_VALUES
        )
        .into());
    }
    let positions = frames.saturating_mul(joints);
    if positions > budget::MAX_JOINT_FRAMES {
        return Err(format!(
            "Frames: {frames} × {joints} joints = {positions} joint positions, over the {} budget",
            budget::MAX_JOINT_FRAMES
        )
        .into());
    }
    Ok(())
}

/// The joints of a BVH hierarchy as it is read: the blocks still open, the names seen and
/// the channels so far.
#[derive(Default)]
struct Hierarchy {
    joints: Vec<BvhJoint>,
    stack: Vec<Open>,
    // A set, so a header with very many joints stays linear to check.
    names: HashSet<String>,
    channels: usize,
}

impl Hierarchy {
    /// `ROOT name {` or `JOINT name {` (`is_root`) on `line`.
    fn open_joint(&mut self, lx: &mut Lexer, line: usize, is_root: bool) -> Result<(), BvhError> {
        let parent = match (is_root, self.stack.last()) {
            (true, None) => None,
            (false, Some(open)) if !self.joints[open.joint].end_site => Some(open.joint),
            (true, Some(_)) => return err(line, "ROOT inside another joint"),
            (false, _) => return err(line, "JOINT outside a ROOT or inside an End Site"),
        };
        let (name, nline) = lx.expect_any("a joint name")?;
        if name == b"{" || name == b"}" {
            return err(nline, "missing joint name");
        }
        if self.stack.len() >= budget::MAX_DEPTH {
            return err(
                nline,
                format!(
                    "joints nested deeper than the {}-level budget",
                    budget::MAX_DEPTH
                ),
            );
        }
        let name = String::from_utf8_lossy(name).into_owned();
        self.open_block(lx, (name, nline), parent, false)
    }

    /// A new joint block `name` (read on `line`) under `parent`, up to its `{`.
    fn open_block(
        &mut self,
        lx: &mut Lexer,
        (name, line): (String, usize),
        parent: Option<usize>,
        end_site: bool,
    ) -> Result<(), BvhError> {
        if !self.names.insert(name.clone()) {
            return err(line, format!("duplicate joint name '{name}'"));
        }
        let open_line = lx.expect("{")?;
        self.joints.push(BvhJoint {
            name,
            parent,
            offset: [0.0; 3],
            channels: Vec::new(),
            first_channel: self.channels,
            end_site,
        });
        self.stack.push(Open {
            joint: self.joints.len() - 1,
            line: open_line,
            has_offset: false,
            has_end_site: false,
        });
        Ok(())
    }

    /// `End Site {` on `line`.
    fn open_end_site(&mut self, lx: &mut Lexer, line: usize) -> Result<(), BvhError> {
        lx.expect("Site")?;
        let Some(open) = self.stack.last_mut() else {
            return err(line, "End Site outside a joint");
        };
        let parent = open.joint;
        if self.joints[parent].end_site || open.has_end_site {
            return err(
                line,
                format!("second End Site in '{}'", self.joints[parent].name),
            );
        }
        open.has_end_site = true;
        let name = format!("{}_End", self.joints[parent].name);
        self.open_block(lx, (name, line), Some(parent), true)
    }

    /// `CHANNELS n name…` on `line`.
    fn read_channels(&mut self, lx: &mut Lexer, line: usize) -> Result<(), BvhError> {
        let Some(open) = self.stack.last() else {
            return err(line, "CHANNELS outside a joint");
        };
        let joint = &mut self.joints[open.joint];
        if joint.end_site {
            return err(line, "CHANNELS in an End Site");
        }
        if !joint.channels.is_empty() {
            return err(line, format!("second CHANNELS in '{}'", joint.name));
        }
        let (ntok, nline) = lx.expect_any("a channel count")?;
        let n: usize = match std::str::from_utf8(ntok).ok().and_then(|s| s.parse().ok()) {
            Some(n) if (1..=MAX_CHANNELS).contains(&n) => n,
            _ => {
                return err(
                    nline,
                    format!(
                        "wrong channel count '{}' for '{}': expected 1 to {MAX_CHANNELS}",
                        show(ntok),
                        joint.name
                    ),
                )
            }
        };
        for k in 0..n {
            let (ctok, cline) = lx.expect_any("a channel name")?;
            let Some(ch) = Channel::from_name(ctok) else {
                return err(
                    cline,
                    format!(
                        "wrong channel count or unknown channel name: CHANNELS {n} for '{}' \
                         has '{}' where channel {} of {n} should be",
                        joint.name,
                        show(ctok),
                        k + 1
                    ),
                );
            };
            if joint.channels.contains(&ch) {
                return err(
                    cline,
                    format!("channel {ch:?} repeated in '{}'", joint.name),
                );
            }
            joint.channels.push(ch);
        }
        joint.first_channel = self.channels;
        self.channels += n;
        if self.channels > budget::MAX_CHANNELS {
            return err(
                nline,
                format!(
                    "{} channels per frame, over the {}-channel budget",
                    self.channels,
                    budget::MAX_CHANNELS
                ),
            );
        }
        Ok(())
    }
}

fn parse_hierarchy(lx: &mut Lexer) -> Result<Vec<BvhJoint>, BvhError> {
    lx.expect("HIERARCHY")?;
    let mut h = Hierarchy::default();
    loop {
        let Some((tok, line)) = lx.next() else {
            return match h.stack.last() {
                Some(open) => err(
                    lx.line,
                    format!(
                        "unbalanced braces: '{}' opened on line {} is never closed",
                        h.joints[open.joint].name, open.line
                    ),
                ),
                None => err(lx.line, "missing MOTION section"),
            };
        };
        let upper = tok.to_ascii_uppercase();
        match upper.as_slice() {
            b"ROOT" | b"JOINT" => h.open_joint(lx, line, upper == b"ROOT")?,
            b"END" => h.open_end_site(lx, line)?,
            b"OFFSET" => {
                let Some(open) = h.stack.last_mut() else {
                    return err(line, "OFFSET outside a joint");
                };
                if open.has_offset {
                    return err(
                        line,
                        format!("second OFFSET in '{}'", h.joints[open.joint].name),
                    );
                }
                open.has_offset = true;
                let mut offset = [0.0; 3];
                for v in offset.iter_mut() {
                    *v = lx.number("OFFSET value")?;
                }
                h.joints[open.joint].offset = offset;
            }
            b"CHANNELS" => h.read_channels(lx, line)?,
            b"}" => {
                let Some(open) = h.stack.pop() else {
                    return err(line, "unbalanced braces: '}' without a matching '{'");
                };
                let joint = &h.joints[open.joint];
                if !open.has_offset {
                    return err(line, format!("'{}' has no OFFSET", joint.name));
                }
                if !joint.end_site && joint.channels.is_empty() {
                    return err(line, format!("'{}' has no CHANNELS", joint.name));
                }
            }
            b"MOTION" => {
                if let Some(open) = h.stack.last() {
                    return err(
                        line,
                        format!(
                            "unbalanced braces: MOTION while '{}' opened on line {} is still open",
                            h.joints[open.joint].name, open.line
                        ),
                    );
                }
                if h.joints.is_empty() {
                    return err(line, "MOTION before any ROOT");
                }
                return Ok(h.joints);
            }
            _ if Channel::from_name(tok).is_some() => {
                return err(
                    line,
                    format!(
                    "wrong channel count: channel name '{}' after the CHANNELS count was used up",
                    show(tok)
                ),
                )
            }
            _ => return err(line, format!("unexpected '{}' in the hierarchy", show(tok))),
        }
    }
}

/// The joint owning channel `c` of a frame, and that channel.
fn channel_kind(joints: &[BvhJoint], c: usize) -> Option<(&BvhJoint, Channel)> {
    joints
        .iter()
        .find(|j| c >= j.first_channel && c < j.first_channel + j.channels.len())
        .map(|j| (j, j.channels[c - j.first_channel]))
}

/// Name of the joint and channel at index `c` of a frame, for error messages.
fn channel_label(joints: &[BvhJoint], c: usize) -> String {
    channel_kind(joints, c)
        .map(|(j, ch)| format!("{} {ch:?}", j.name))
        .unwrap_or_default()
}

fn parse_motion(
    lx: &mut Lexer,
    joints: &[BvhJoint],
    frames: usize,
    num_channels: usize,
) -> Result<Vec<f64>, BvhError> {
    // Within the value budget (checked by the caller), so this cannot overflow.
    let expected = frames * num_channels;
    // Every value takes at least two bytes (a digit and a separator), so the remaining
    // input bounds what can be present; never allocate from the untrusted count alone.
    let remaining = lx.bytes.len() - lx.pos;
    let mut motion = Vec::with_capacity(expected.min(remaining / 2 + 1));
    // Rotation bound per channel (positions are bounded after retargeting, in metres).
    let bound: Vec<f64> = (0..num_channels)
        .map(|c| match channel_kind(joints, c) {
            Some((_, ch)) if ch.is_rotation() => budget::MAX_ROTATION_DEGREES,
            _ => f64::INFINITY,
        })
        .collect();
    let mut column = 0;
    while motion.len() < expected {
        let Some((tok, line)) = lx.next() else {
            let found = motion.len();
            return err(
                lx.line,
                format!(
                    "truncated: expected {expected} values ({frames} frames × {num_channels} \
                     channels), found {found}; frame {} of {frames} is incomplete",
                    found / num_channels + 1
                ),
            );
        };
        match parse_f64(tok) {
            Some(v) if v.is_finite() && v.abs() <= bound[column] => {
                motion.push(v);
                column = if column + 1 == num_channels {
                    0
                } else {
                    column + 1
                };
            }
            Some(v) if v.is_finite() => {
                let n = motion.len();
                return err(
                    line,
                    format!(
                        "implausible rotation {v:e}° at frame {} channel {} ({}), beyond ±{:e}°",
                        n / num_channels + 1,
                        column + 1,
                        channel_label(joints, column),
                        budget::MAX_ROTATION_DEGREES
                    ),
                );
            }
            parsed => {
                let n = motion.len();
                let what = if parsed.is_some() {
                    "non-finite value"
                } else {
                    "text in a numeric field"
                };
                return err(
                    line,
                    format!(
                        "{what} '{}' at frame {} channel {} ({})",
                        show(tok),
                        n / num_channels + 1,
                        n % num_channels + 1,
                        channel_label(joints, n % num_channels)
                    ),
                );
            }
        }
    }
    if let Some((tok, line)) = lx.next() {
        return err(
            line,
            format!(
                "extra data '{}' after the {frames} frames declared by Frames:",
                show(tok)
            ),
        );
    }
    Ok(motion)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fast_float_path_matches_std() {
        for s in [
            "0",
            "-0",
            "1.5",
            "-0.53398",
            "93.523",
            "1.87007e-05",
            "-1.23785e-05",
            "5.1072e-06",
            "123456789012345",
            "0.000322201",
            "1e22",
            "1e-22",
            "2.5E+3",
            ".5",
            "5.",
            "+3.25",
            "12345678901234567890",
            "1e300",
            "4.9e-324",
        ] {
            let want: f64 = s.parse().unwrap();
            let got = parse_f64(s.as_bytes()).unwrap();
            assert_eq!(got.to_bits(), want.to_bits(), "{s}");
        }
        for s in ["", "-", "abc", "1.2.3", "1e", "e5", "1x", "--1"] {
            assert!(parse_f64(s.as_bytes()).is_none(), "{s}");
        }
        assert!(parse_f64(b"nan").unwrap().is_nan());
        assert!(parse_f64(b"1e400").unwrap().is_infinite());
    }

    #[test]
    fn channel_names_ignore_case() {
        assert_eq!(Channel::from_name(b"XROTATION"), Some(Channel::Xrotation));
        assert_eq!(Channel::from_name(b"zPosition"), Some(Channel::Zposition));
        assert_eq!(Channel::from_name(b"Wrotation"), None);
    }
}
