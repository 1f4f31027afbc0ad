//! AMASS motions (`.npz`: SMPL+H `poses` T×156 or SMPL-X T×165 axis-angle, `trans`, `betas`,
//! `mocap_framerate` / `mocap_frame_rate`) turned into SMPL-22 joint positions with a body
//! model `.npz` (`v_template`, `shapedirs`, `J_regressor`, `kintree_table`), the way
//! HumanML3D's `raw_pose_processing` does it.
//!
//! Joints: rest joints J = J_regressor · (v_template + shapedirs · betas) (pose blendshapes do
//! not move the regressed rest joints), then forward kinematics of the first 22 axis-angle
//! rotations along the kinematic tree, rotating about the root joint, plus `trans`.

use super::{clip_id_of, RawClip, Reject};
use crate::error::IngestError;
use crate::npy::{self, NpyArray};
use crate::quat::{self, Quat, Vec3};
use crate::skeleton::{Pose, NUM_JOINTS};
use std::fs::File;
use std::io::Read;
use std::path::Path;

/// How AMASS's Z-up joints become Y up, recorded in each clip's `conversion`.
pub const CONVERSION: &str = "SMPL joints (metres) Z up -> Y up as HumanML3D: \
     (x, y, z) . [[1,0,0],[0,0,1],[0,1,0]] = (x, z, y), then x negated (its segment step's \
     data[..., 0] *= -1), net (-x, z, y), a proper rotation";

/// The parts of an SMPL-family body model needed for the 22 body joints' rest positions.
#[derive(Debug, Clone)]
pub struct BodyModel {
    /// Regressed template joints (J_regressor · v_template), joints 0..21.
    joint_template: [Vec3; NUM_JOINTS],
    /// Regressed shape directions (J_regressor · shapedirs), joints 0..21, each 3 × `num_betas`.
    joint_shapedirs: Vec<[Vec<f64>; 3]>,
    /// Number of shape coefficients the model has.
    num_betas: usize,
    /// Parent of each of joints 1..21 (the root's entry is unused).
    parents: [usize; NUM_JOINTS],
}

/// Read `.npz` entries (`<key>.npy`) from an open archive.
struct Npz {
    archive: zip::ZipArchive<File>,
    path: std::path::PathBuf,
}

impl Npz {
    fn open(path: &Path) -> Result<Self, IngestError> {
        let file = File::open(path).map_err(|e| IngestError::io(path, e))?;
        let archive = zip::ZipArchive::new(file)
            .map_err(|e| IngestError::file(path, format!("not an .npz (zip) archive: {e}")))?;
        Ok(Self {
            archive,
            path: path.to_path_buf(),
        })
    }

    /// The array stored under `key`, or `None` when the archive has no such entry.
    fn get(&mut self, key: &str) -> Result<Option<NpyArray>, IngestError> {
        let mut entry = match self.archive.by_name(&format!("{key}.npy")) {
            Ok(entry) => entry,
            Err(zip::result::ZipError::FileNotFound) => return Ok(None),
            Err(e) => return Err(IngestError::file(&self.path, format!("entry {key}: {e}"))),
        };
        let mut bytes = Vec::new();
        entry
            .read_to_end(&mut bytes)
            .map_err(|e| IngestError::file(&self.path, format!("entry {key}: {e}")))?;
        npy::parse_numeric(&bytes)
            .map(Some)
            .map_err(|e| IngestError::file(&self.path, format!("entry {key}: {e}")))
    }

    fn require(&mut self, key: &str) -> Result<NpyArray, IngestError> {
        self.get(key)?
            .ok_or_else(|| IngestError::file(&self.path, format!("no `{key}` array")))
    }
}

impl BodyModel {
    /// Load a body model `.npz` (SMPL, SMPL+H or SMPL-X; any gender).
    pub fn load(path: &Path) -> Result<Self, IngestError> {
        let mut npz = Npz::open(path)?;
        let where_ = path.display();
        let v_template = npz.require("v_template")?;
        let shapedirs = npz.require("shapedirs")?;
        let regressor = npz.require("J_regressor")?;
        let kintree = npz.require("kintree_table")?;
        let &[verts, 3] = v_template.shape.as_slice() else {
            return Err(format!(
                "{where_}: v_template shape {:?} is not V×3",
                v_template.shape
            )
            .into());
        };
        let &[sv, 3, num_betas] = shapedirs.shape.as_slice() else {
            return Err(format!(
                "{where_}: shapedirs shape {:?} is not V×3×B",
                shapedirs.shape
            )
            .into());
        };
        let &[joints, rv] = regressor.shape.as_slice() else {
            return Err(format!(
                "{where_}: J_regressor shape {:?} is not J×V (a dense array is needed)",
                regressor.shape
            )
            .into());
        };
        if sv != verts || rv != verts {
            return Err(format!(
                "{where_}: vertex counts disagree: v_template {verts}, shapedirs {sv}, J_regressor {rv}"
            ).into());
        }
        if joints < NUM_JOINTS {
            return Err(format!(
                "{where_}: J_regressor has {joints} joints, at least {NUM_JOINTS} are needed"
            )
            .into());
        }
        let &[2, tree_joints] = kintree.shape.as_slice() else {
            return Err(format!(
                "{where_}: kintree_table shape {:?} is not 2×J",
                kintree.shape
            )
            .into());
        };
        if tree_joints < NUM_JOINTS {
            return Err(format!(
                "{where_}: kintree_table has {tree_joints} joints, at least {NUM_JOINTS} are needed"
            )
            .into());
        }
        let mut parents = [0; NUM_JOINTS];
        for (j, parent) in parents.iter_mut().enumerate() {
            let p = kintree.data[j];
            // The root's parent is stored as -1 or 2^32 - 1.
            let is_root = p < 0.0 || p >= tree_joints as f64;
            match (j, is_root) {
                (0, true) => {}
                (0, false) => return Err(format!("{where_}: kintree_table: joint 0 has parent {p}, expected none").into()),
                (_, false) if (p as usize) < j => *parent = p as usize,
                _ => {
                    return Err(format!(
                        "{where_}: kintree_table: joint {j} has parent {p}; joints 1..21 need an earlier joint as parent"
                    ).into())
                }
            }
        }
        let mut joint_template = [[0.0; 3]; NUM_JOINTS];
        let mut joint_shapedirs: Vec<[Vec<f64>; 3]> = (0..NUM_JOINTS)
            .map(|_| std::array::from_fn(|_| vec![0.0; num_betas]))
            .collect();
        for j in 0..NUM_JOINTS {
            for v in 0..verts {
                let w = regressor.data[j * verts + v];
                // Regressors are sparse (a few dozen vertices per joint); skip the zeros.
                if w == 0.0 {
                    continue;
                }
                for k in 0..3 {
                    joint_template[j][k] += w * v_template.data[v * 3 + k];
                    let dirs =
                        &shapedirs.data[(v * 3 + k) * num_betas..(v * 3 + k + 1) * num_betas];
                    for (acc, d) in joint_shapedirs[j][k].iter_mut().zip(dirs) {
                        *acc += w * d;
                    }
                }
            }
        }
        Ok(Self {
            joint_template,
            joint_shapedirs,
            num_betas,
            parents,
        })
    }

    /// Rest joint positions for shape coefficients `betas` (extra ones ignored, missing ones 0).
    pub fn rest_joints(&self, betas: &[f64]) -> [Vec3; NUM_JOINTS] {
        let mut rest = self.joint_template;
        let used = betas.len().min(self.num_betas);
        for (j, r) in rest.iter_mut().enumerate() {
            for (k, rk) in r.iter_mut().enumerate() {
                *rk += self.joint_shapedirs[j][k][..used]
                    .iter()
                    .zip(&betas[..used])
                    .map(|(d, b)| d * b)
                    .sum::<f64>();
            }
        }
        rest
    }

    /// Joint positions (Z up, as SMPL gives them) of one frame: 22 axis-angle rotations
    /// (root first) and the root translation.
    pub fn pose_joints(
        &self,
        rest: &[Vec3; NUM_JOINTS],
        axis_angles: &[Vec3; NUM_JOINTS],
        trans: Vec3,
    ) -> Pose {
        let mut global: [Quat; NUM_JOINTS] = [quat::IDENTITY; NUM_JOINTS];
        let mut pos = [[0.0; 3]; NUM_JOINTS];
        for j in 0..NUM_JOINTS {
            let local = quat::from_rotvec(axis_angles[j]);
            if j == 0 {
                // SMPL rotates about the root joint, so the root stays at its rest place.
                global[0] = local;
                pos[0] = quat::add(rest[0], trans);
            } else {
                let p = self.parents[j];
                global[j] = quat::mul(global[p], local);
                pos[j] = quat::add(pos[p], quat::rot(global[p], quat::sub(rest[j], rest[p])));
            }
        }
        pos
    }
}

/// Read one AMASS motion `.npz` into SMPL-22 joints (metres, Y up) at its capture frame rate.
pub fn read_clip(path: &Path, rel_path: &Path, model: &BodyModel) -> Result<RawClip, Reject> {
    let mut npz = Npz::open(path).map_err(|e| Reject::new("read", e))?;
    let parse = |e: IngestError| Reject::new("parse", e);
    let where_ = path.display();
    let poses = npz.get("poses").map_err(parse)?.ok_or_else(|| {
        Reject::new(
            "parse",
            format!("{where_}: no `poses` array: not a motion file (e.g. a subject's shape.npz)"),
        )
    })?;
    let trans = npz.require("trans").map_err(parse)?;
    let betas = npz.require("betas").map_err(parse)?;
    let fps_array = match npz.get("mocap_framerate").map_err(parse)? {
        Some(a) => a,
        None => npz.get("mocap_frame_rate").map_err(parse)?.ok_or_else(|| {
            Reject::new(
                "parse",
                format!(
                    "{where_}: no `mocap_framerate` (SMPL+H) or `mocap_frame_rate` (SMPL-X) array"
                ),
            )
        })?,
    };
    let fps = match fps_array.data.as_slice() {
        [fps] if fps.is_finite() && *fps > 0.0 => *fps,
        other => {
            return Err(Reject::new(
                "parse",
                format!("{where_}: frame rate {other:?} is not one positive number"),
            ))
        }
    };
    let &[frames, width] = poses.shape.as_slice() else {
        return Err(Reject::new(
            "parse",
            format!(
                "{where_}: poses shape {:?} is not T×N axis-angles",
                poses.shape
            ),
        ));
    };
    if width < 3 * NUM_JOINTS || width % 3 != 0 {
        return Err(Reject::new(
            "parse",
            format!(
                "{where_}: poses has {width} values per frame, expected 3 per joint and at least {}",
                3 * NUM_JOINTS
            ),
        ));
    }
    if frames == 0 {
        return Err(Reject::new(
            "parse",
            format!("{where_}: poses has zero frames"),
        ));
    }
    if trans.shape != [frames, 3] {
        return Err(Reject::new(
            "parse",
            format!(
                "{where_}: trans shape {:?} does not match poses ({frames} frames × 3)",
                trans.shape
            ),
        ));
    }
    if let Some(i) = betas.data.iter().position(|b| !b.is_finite()) {
        return Err(Reject::new(
            "parse",
            format!("{where_}: betas[{i}] is not finite"),
        ));
    }
    let rest = model.rest_joints(&betas.data);
    let mut out = Vec::with_capacity(frames);
    for t in 0..frames {
        let row = &poses.data[t * width..(t + 1) * width];
        let angles: [Vec3; NUM_JOINTS] =
            std::array::from_fn(|j| [row[3 * j], row[3 * j + 1], row[3 * j + 2]]);
        let tr = [
            trans.data[3 * t],
            trans.data[3 * t + 1],
            trans.data[3 * t + 2],
        ];
        if angles.iter().flatten().chain(&tr).any(|v| !v.is_finite()) {
            return Err(Reject::new(
                "parse",
                format!("{where_}: frame {t}: non-finite pose or translation"),
            ));
        }
        let mut pose = model.pose_joints(&rest, &angles, tr);
        for p in pose.iter_mut() {
            *p = [-p[0], p[2], p[1]];
        }
        out.push(pose);
    }
    Ok(RawClip {
        clip_id: clip_id_of(rel_path),
        source: "amass".into(),
        source_path: path.to_path_buf(),
        fps,
        poses: out,
        labels: Default::default(),
        captions: Vec::new(),
        conversion: CONVERSION.into(),
        split: None,
        span: None,
    })
}
