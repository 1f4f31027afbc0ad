//! Small built-in demo inputs: procedurally animated BVH clips on a CMU-named rig (cm, Y up,
//! 30 fps) with caption sidecars, so the main job runs on a fresh clone with no data.

use std::f64::consts::TAU;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

/// A joint of the demo rig: name, parent index, rest offset (cm), channel order.
struct RigJoint {
    name: &'static str,
    parent: Option<usize>,
    offset: [f64; 3],
}

// Rest pose: T-pose facing +Z, legs along −Y, arms along ±X (the CMU convention).
const RIG: [RigJoint; 25] = [
    RigJoint {
        name: "Hips",
        parent: None,
        offset: [0.0, 95.0, 0.0],
    },
    RigJoint {
        name: "LHipJoint",
        parent: Some(0),
        offset: [9.0, -5.0, 0.0],
    },
    RigJoint {
        name: "LeftUpLeg",
        parent: Some(1),
        offset: [0.0, -1.0, 0.0],
    },
    RigJoint {
        name: "LeftLeg",
        parent: Some(2),
        offset: [0.0, -41.0, 0.0],
    },
    RigJoint {
        name: "LeftFoot",
        parent: Some(3),
        offset: [0.0, -41.0, 0.0],
    },
    RigJoint {
        name: "LeftToeBase",
        parent: Some(4),
        offset: [0.0, -7.0, 13.0],
    },
    RigJoint {
        name: "RHipJoint",
        parent: Some(0),
        offset: [-9.0, -5.0, 0.0],
    },
    RigJoint {
        name: "RightUpLeg",
        parent: Some(6),
        offset: [0.0, -1.0, 0.0],
    },
    RigJoint {
        name: "RightLeg",
        parent: Some(7),
        offset: [0.0, -41.0, 0.0],
    },
    RigJoint {
        name: "RightFoot",
        parent: Some(8),
        offset: [0.0, -41.0, 0.0],
    },
    RigJoint {
        name: "RightToeBase",
        parent: Some(9),
        offset: [0.0, -7.0, 13.0],
    },
    RigJoint {
        name: "LowerBack",
        parent: Some(0),
        offset: [0.0, 6.0, 0.0],
    },
    RigJoint {
        name: "Spine",
        parent: Some(11),
        offset: [0.0, 12.0, 0.0],
    },
    RigJoint {
        name: "Spine1",
        parent: Some(12),
        offset: [0.0, 14.0, 0.0],
    },
    RigJoint {
        name: "Neck",
        parent: Some(13),
        offset: [0.0, 18.0, 0.0],
    },
    RigJoint {
        name: "Neck1",
        parent: Some(14),
        offset: [0.0, 5.0, 0.0],
    },
    RigJoint {
        name: "Head",
        parent: Some(15),
        offset: [0.0, 6.0, 2.0],
    },
    RigJoint {
        name: "LeftShoulder",
        parent: Some(13),
        offset: [4.0, 16.0, 0.0],
    },
    RigJoint {
        name: "LeftArm",
        parent: Some(17),
        offset: [13.0, 0.0, 0.0],
    },
    RigJoint {
        name: "LeftForeArm",
        parent: Some(18),
        offset: [27.0, 0.0, 0.0],
    },
    RigJoint {
        name: "LeftHand",
        parent: Some(19),
        offset: [25.0, 0.0, 0.0],
    },
    RigJoint {
        name: "RightShoulder",
        parent: Some(13),
        offset: [-4.0, 16.0, 0.0],
    },
    RigJoint {
        name: "RightArm",
        parent: Some(21),
        offset: [-13.0, 0.0, 0.0],
    },
    RigJoint {
        name: "RightForeArm",
        parent: Some(22),
        offset: [-27.0, 0.0, 0.0],
    },
    RigJoint {
        name: "RightHand",
        parent: Some(23),
        offset: [-25.0, 0.0, 0.0],
    },
];

fn index(name: &str) -> usize {
    RIG.iter()
        .position(|j| j.name == name)
        .expect("demo rig joint")
}

/// Per-frame channel values: root position (cm) and per-joint (x, z, y) Euler angles in degrees.
struct Frame {
    root: [f64; 3],
    angles: Vec<[f64; 3]>,
}

/// One demo motion: name, caption lines, duration (s), and its pose at time t.
struct Motion {
    name: &'static str,
    captions: &'static [&'static str],
    seconds: f64,
    pose: fn(f64) -> Frame,
}

fn rest() -> Frame {
    let mut angles = vec![[0.0; 3]; RIG.len()];
    // Arms hang down from the T-pose: rotate about Z.
    angles[index("LeftArm")][1] = -75.0;
    angles[index("RightArm")][1] = 75.0;
    Frame {
        root: [0.0, 95.0, 0.0],
        angles,
    }
}

fn walk_like(t: f64, speed: f64, cadence: f64, swing: f64) -> Frame {
    let mut f = rest();
    let phase = TAU * cadence * t;
    let (s, c) = phase.sin_cos();
    f.root = [
        0.0,
        95.0 - 2.0 * (2.0 * phase).cos().abs(),
        speed * 100.0 * t,
    ];
    // Negative rotation about X swings a downward leg forward (+Z).
    f.angles[index("LeftUpLeg")][0] = -swing * s;
    f.angles[index("RightUpLeg")][0] = swing * s;
    f.angles[index("LeftLeg")][0] = swing * 1.2 * (-c).max(0.0);
    f.angles[index("RightLeg")][0] = swing * 1.2 * c.max(0.0);
    f.angles[index("LeftArm")][0] = 0.8 * swing * s;
    f.angles[index("RightArm")][0] = -0.8 * swing * s;
    f
}

fn walk(t: f64) -> Frame {
    walk_like(t, 1.2, 0.9, 25.0)
}

fn run(t: f64) -> Frame {
    walk_like(t, 3.0, 1.4, 40.0)
}

fn wave(t: f64) -> Frame {
    let mut f = rest();
    let raise = (t / 0.8).min(1.0);
    f.angles[index("RightArm")][1] = 75.0 - 150.0 * raise;
    f.angles[index("RightForeArm")][1] = raise * 25.0 * (TAU * 1.5 * t).sin();
    f
}

fn squat(t: f64) -> Frame {
    let mut f = rest();
    let depth = 0.5 - 0.5 * (TAU * 0.4 * t).cos();
    f.root[1] = 95.0 - 35.0 * depth;
    f.root[2] = -10.0 * depth;
    for (hip, knee, foot) in [
        ("LeftUpLeg", "LeftLeg", "LeftFoot"),
        ("RightUpLeg", "RightLeg", "RightFoot"),
    ] {
        f.angles[index(hip)][0] = -80.0 * depth;
        f.angles[index(knee)][0] = 110.0 * depth;
        f.angles[index(foot)][0] = -30.0 * depth;
    }
    f.angles[index("LowerBack")][0] = 25.0 * depth;
    f.angles[index("LeftArm")][0] = -70.0 * depth;
    f.angles[index("RightArm")][0] = -70.0 * depth;
    f
}

fn jump(t: f64) -> Frame {
    let mut f = rest();
    let cycle = t % 1.5;
    // Crouch for 0.4 s, then a 0.6 s flight, then land and recover.
    let (crouch, height) = if cycle < 0.4 {
        ((cycle / 0.4 * TAU / 4.0).sin(), 0.0)
    } else if cycle < 1.0 {
        let u = (cycle - 0.4) / 0.6;
        (0.0, 4.0 * u * (1.0 - u) * 40.0)
    } else {
        (((1.5 - cycle) / 0.5 * TAU / 4.0).sin(), 0.0)
    };
    f.root[1] = 95.0 - 20.0 * crouch + height;
    for (hip, knee) in [("LeftUpLeg", "LeftLeg"), ("RightUpLeg", "RightLeg")] {
        f.angles[index(hip)][0] = -45.0 * crouch;
        f.angles[index(knee)][0] = 70.0 * crouch;
    }
    f.angles[index("LeftArm")][1] = -75.0 + 120.0 * (height / 40.0);
    f.angles[index("RightArm")][1] = 75.0 - 120.0 * (height / 40.0);
    f
}

fn turn(t: f64) -> Frame {
    let mut f = walk_like(t, 0.0, 0.9, 12.0);
    f.angles[0][2] = 90.0 * t;
    f.root[2] = 0.0;
    f
}

const MOTIONS: [Motion; 6] = [
    Motion {
        name: "demo_walk",
        captions: &[
            "a person walks forward at a steady pace.",
            "someone strolls straight ahead.",
        ],
        seconds: 6.0,
        pose: walk,
    },
    Motion {
        name: "demo_run",
        captions: &["a person runs forward.", "someone jogs quickly ahead."],
        seconds: 4.0,
        pose: run,
    },
    Motion {
        name: "demo_wave",
        captions: &[
            "a person raises the right hand and waves.",
            "someone waves hello with the right arm.",
        ],
        seconds: 4.0,
        pose: wave,
    },
    Motion {
        name: "demo_squat",
        captions: &[
            "a person squats down and stands back up.",
            "someone does deep knee bends.",
        ],
        seconds: 5.0,
        pose: squat,
    },
    Motion {
        name: "demo_jump",
        captions: &[
            "a person jumps up in place twice.",
            "someone hops straight up.",
        ],
        seconds: 3.0,
        pose: jump,
    },
    Motion {
        name: "demo_turn",
        captions: &[
            "a person turns around in place to the left.",
            "someone steps around turning left.",
        ],
        seconds: 4.0,
        pose: turn,
    },
];

/// Demo frame rate (not 20, so the demo exercises resampling).
pub const DEMO_FPS: f64 = 30.0;

fn hierarchy(out: &mut String, j: usize, depth: usize) {
    let all = &RIG;
    let pad = "  ".repeat(depth);
    let joint = &all[j];
    let kw = if joint.parent.is_none() {
        "ROOT"
    } else {
        "JOINT"
    };
    let [x, y, z] = if joint.parent.is_none() {
        [0.0; 3]
    } else {
        joint.offset
    };
    let _ = writeln!(
        out,
        "{pad}{kw} {}\n{pad}{{\n{pad}  OFFSET {x:.4} {y:.4} {z:.4}",
        joint.name
    );
    if joint.parent.is_none() {
        let _ = writeln!(
            out,
            "{pad}  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation"
        );
    } else {
        let _ = writeln!(out, "{pad}  CHANNELS 3 Zrotation Xrotation Yrotation");
    }
    let children: Vec<usize> = (0..all.len())
        .filter(|&c| all[c].parent == Some(j))
        .collect();
    if children.is_empty() {
        let _ = writeln!(
            out,
            "{pad}  End Site\n{pad}  {{\n{pad}    OFFSET 0.0 2.0 0.0\n{pad}  }}"
        );
    }
    for c in children {
        hierarchy(out, c, depth + 1);
    }
    let _ = writeln!(out, "{pad}}}");
}

/// Depth-first joint order, matching the order channels appear in the MOTION section.
fn dfs_order(j: usize, out: &mut Vec<usize>) {
    out.push(j);
    let all = &RIG;
    for c in (0..all.len()).filter(|&c| all[c].parent == Some(j)) {
        dfs_order(c, out);
    }
}

fn bvh_text(motion: &Motion) -> String {
    let mut text = String::from("HIERARCHY\n");
    hierarchy(&mut text, 0, 0);
    let frames = (motion.seconds * DEMO_FPS) as usize;
    let _ = writeln!(
        text,
        "MOTION\nFrames: {frames}\nFrame Time: {:.8}",
        1.0 / DEMO_FPS
    );
    let mut order = Vec::new();
    dfs_order(0, &mut order);
    for k in 0..frames {
        let f = (motion.pose)(k as f64 / DEMO_FPS);
        let mut values = vec![f.root[0], f.root[1], f.root[2]];
        for &j in &order {
            let [x, z, y] = f.angles[j];
            values.extend([z, x, y]);
        }
        let line: Vec<String> = values.iter().map(|v| format!("{v:.4}")).collect();
        text.push_str(&line.join(" "));
        text.push('\n');
    }
    text
}

/// Write the demo BVH clips and their `<clip>.txt` caption sidecars into `dir`.
pub fn write_demo_inputs(dir: &Path) -> std::io::Result<Vec<PathBuf>> {
    let mut written = Vec::new();
    for motion in &MOTIONS {
        let path = dir.join(format!("{}.bvh", motion.name));
        motionscale_core::write_atomic(&path, bvh_text(motion).as_bytes())?;
        let captions = motion.captions.join("\n") + "\n";
        motionscale_core::write_atomic(&path.with_extension("txt"), captions.as_bytes())?;
        written.push(path);
    }
    Ok(written)
}
