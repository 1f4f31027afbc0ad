"""Reference speed of the original HumanML3D feature extraction, for `motionscale bench ingest
--reference DIR`.

Runs the upstream code itself from a checkout of EricGuo5513/HumanML3D (commit 9176e8f, the
one the conformance fixtures were made with): `common/`, `paramUtil.py` and the function
cells of `motion_representation.ipynb` (`uniform_skeleton`, `process_file`) are executed
unchanged, with the constants of the notebook's `__main__` block and the fixtures' target
skeleton (frame 0 of `humanml3d_new_joints_012314.npy`, see the fixtures README). Run-time
shims only: `np.float` (removed from NumPy), `scipy.ndimage.filters` (moved), and a stub for
the unused `tqdm` import. Nothing of the upstream code is stored in this repository.

It times `process_file(joints, 0.002)` on fixture (a) (170 frames, one thread) and checks the
output against `a_asis_features.npy`.

usage: humanml3d_speed.py --humanml3d DIR --fixtures DIR [--reps 50] [--out FILE]
Prints JSON: frames/s, median seconds per call, the largest difference from the fixture.
"""
import argparse
import importlib.util
import json
import os
import statistics
import sys
import time
import types
import warnings

import numpy as np

from reference_output import emit


def shim():
    # torch.cross without dim warns on every call of the upstream code.
    warnings.filterwarnings("ignore")
    np.float = float
    import scipy.ndimage
    sys.modules.setdefault("scipy.ndimage.filters", scipy.ndimage)
    if importlib.util.find_spec("tqdm") is None:
        stub = types.ModuleType("tqdm")
        stub.tqdm = lambda x, *a, **k: x
        sys.modules["tqdm"] = stub


def upstream(checkout):
    """The notebook's imports and function cells, executed in one namespace."""
    sys.path.insert(0, checkout)
    with open(os.path.join(checkout, "motion_representation.ipynb")) as f:
        cells = [c for c in json.load(f)["cells"] if c["cell_type"] == "code"]
    ns = {"__name__": "humanml3d_reference"}
    for cell in cells:
        source = "".join(cell["source"])
        if source.startswith(("from os.path", "def ")):
            exec(compile(source, "motion_representation.ipynb", "exec"), ns)
    return ns


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--humanml3d", required=True)
    ap.add_argument("--fixtures", required=True)
    ap.add_argument("--reps", type=int, default=50)
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    shim()
    import torch
    torch.set_num_threads(1)
    ns = upstream(args.humanml3d)
    ns.update(l_idx1=5, l_idx2=8, fid_r=[8, 11], fid_l=[7, 10], face_joint_indx=[2, 1, 17, 16],
              r_hip=2, l_hip=1, joints_num=22)
    ns["n_raw_offsets"] = torch.from_numpy(ns["t2m_raw_offsets"])
    ns["kinematic_chain"] = ns["t2m_kinematic_chain"]
    target = np.load(os.path.join(args.fixtures, "humanml3d_new_joints_012314.npy"))[0]
    skeleton = ns["Skeleton"](ns["n_raw_offsets"], ns["kinematic_chain"], "cpu")
    ns["tgt_offsets"] = skeleton.get_offsets_joints(torch.from_numpy(target))
    joints = np.load(os.path.join(args.fixtures, "a_asis_joints.npy"))
    expected = np.load(os.path.join(args.fixtures, "a_asis_features.npy"))
    process_file = ns["process_file"]
    features = process_file(joints, 0.002)[0]
    samples = []
    for _ in range(args.reps):
        t0 = time.perf_counter()
        process_file(joints, 0.002)
        samples.append(time.perf_counter() - t0)
    median = statistics.median(samples)
    out = {
        "frames": int(len(joints)),
        "median_s": median,
        "min_s": min(samples),
        "frames_per_s": len(joints) / median,
        "max_abs_diff_from_fixture": float(np.abs(features - expected).max()),
        "reps": args.reps,
    }
    emit(out, args.out)


if __name__ == "__main__":
    main()
