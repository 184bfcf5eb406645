"""How well constrained takes meet their constraints, on the bundled model (a measurement: prints a table).

    .venv/bin/python research/control_table.py --data DIR [--clips 8] [--seeds 2] [--threads 2]

- pose keys: 4 keyed frames (pelvis, wrists, ankles) taken from real test clips (--data: a prepared folder),
  generated from the clip's first caption at its length: mean error at the keyed frames, keyed joints and root;
- root paths: straight, curved and S-shaped, at a walking (1.2 m/s) and a running (3 m/s) speed, 4 s: mean root
  error over the path, and the foot skating ratio (mld_core.eval.quality) against free samples of the prompt;
- loops: the largest joint gap between the last and the first frame, and the velocity jump across the seam;
- sequences: walk 3 s -> wave the right hand 2 s -> bow 2 s (and run -> walk-back): each segment's content check
  (mld_core.eval.physical) on its own seconds (after the half second it repeats of the previous segment's end)
  against free samples of its prompt, and the largest joint jerk at each seam (from just before its cross-fade to
  just after it) against the real test clips' 95th percentile of the same measure;
- time per constrained 4 s take against the free one.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from mld_core.take_fixes.constraints import Constraints, Loop, PoseKeys, RootPath  # noqa: E402
from mld_core.eval import physical  # noqa: E402
from mld_core.eval.quality import foot_skating_ratio, largest_joint_jerk  # noqa: E402
from mld_core.motion.skeleton import JOINT_NAMES  # noqa: E402

KEYED = ("pelvis", "left_wrist", "right_wrist", "left_ankle", "right_ankle")


def pose_keys(pipe, data: Path, clips: int) -> dict:
    ids = [line.strip() for line in (data / "test.txt").read_text().splitlines() if line.strip()]
    ids = [i for i in ids if not i.startswith("M")]
    keyed, root, free_err, times = [], [], [], []
    for cid in ids:
        joints = np.load(data / "new_joints" / f"{cid}.npy")[:196]
        if len(joints) < 60:
            continue
        caption = (data / "texts" / f"{cid}.txt").read_text().splitlines()[0].split("#")[0]
        frames = np.linspace(5, len(joints) - 5, 4).astype(int)
        targets = {int(f): {n: joints[f, JOINT_NAMES.index(n)].tolist() for n in KEYED} for f in frames}
        t0 = time.perf_counter()
        out = pipe([caption], seconds=len(joints) / 20, seed=0, constraints=Constraints([PoseKeys(targets)]))
        times.append(time.perf_counter() - t0)
        free = pipe([caption], seconds=len(joints) / 20, seed=0)

        def error(j, names):
            return np.mean([np.linalg.norm(j[f, JOINT_NAMES.index(n)] - targets[f][n]) for f in targets for n in names])

        keyed.append(error(out.joints[0], KEYED[1:]))
        root.append(error(out.joints[0], ("pelvis",)))
        free_err.append(error(free.joints[0], KEYED))
        if len(keyed) == clips:
            break
    return {"clips": len(keyed), "keyed_cm": 100 * np.mean(keyed), "root_cm": 100 * np.mean(root),
            "free_cm": 100 * np.mean(free_err), "time_s": float(np.median(times))}


def path_points(shape: str, speed: float, seconds: float = 4.0) -> RootPath:
    t = np.linspace(0, 1, 9)
    length = speed * seconds
    if shape == "straight":
        xz = np.stack([0 * t, length * t], -1)
    elif shape == "curved":  # a quarter circle to the left
        r = length / (np.pi / 2)
        xz = np.stack([r - r * np.cos(t * np.pi / 2), r * np.sin(t * np.pi / 2)], -1)
    else:  # S: a sine across the forward axis
        xz = np.stack([0.15 * length * np.sin(2 * np.pi * t), length * t], -1)
    frames = np.round(t * (seconds * 20 - 1)).astype(int)
    return RootPath(list(frames), xz)


def root_paths(pipe, seeds: int) -> list[dict]:
    rows = []
    for prompt, speed in (("a person walks forward", 1.2), ("a person runs forward", 3.0)):
        free = pipe([prompt], seconds=4, seed=0, num_variants=seeds)
        free_skate = np.mean([foot_skating_ratio(j) for j in free.joints])
        for shape in ("straight", "curved", "S"):
            path = path_points(shape, speed)
            out = pipe([prompt], seconds=4, seed=0, num_variants=seeds, constraints=Constraints([path]))
            errors = [path.residual(j) for j in out.joints]
            skate = np.mean([foot_skating_ratio(j) for j in out.joints])
            rows.append({"prompt": prompt, "shape": shape, "speed": speed, "root_cm": 100 * np.mean(errors),
                         "skating": skate, "free_skating": free_skate})
    return rows


def loops(pipe, seeds: int) -> list[dict]:
    rows = []
    for prompt in ("a person walks forward", "a person waves the right hand", "a person runs forward"):
        out = pipe([prompt], seconds=4, seed=0, num_variants=seeds, constraints=Constraints([Loop()]))
        gaps = [Loop().residual(j) for j in out.joints]
        jumps = []
        for j in out.joints:
            seam = (j[1] - j[0]) - (j[-1] - j[-2])
            inner = np.diff(j, 2, axis=0)  # frame-to-frame velocity changes inside the take
            jumps.append(np.linalg.norm(seam, axis=-1).max() / np.percentile(np.linalg.norm(inner, axis=-1).max(-1), 95))
        rows.append({"prompt": prompt, "gap_cm": 100 * max(gaps), "seam_jump_vs_p95": float(np.max(jumps))})
    return rows


SEQUENCES = [
    [("a person walks forward", 3.0, "walk"), ("a person waves the right hand", 2.0, "wave-right-hand"),
     ("a person bows", 2.0, "bow")],
    [("a person runs forward", 3.0, "run"), ("a person walks backwards", 3.0, "walk-back")],
]


def real_jerk_p95(data: Path, clips: int = 200) -> float:
    ids = [line.strip() for line in (data / "test.txt").read_text().splitlines() if line.strip()][:clips]
    jerks = [largest_joint_jerk(np.load(data / "new_joints" / f"{i}.npy")) for i in ids]
    return float(np.percentile(np.concatenate(jerks), 95))


def sequences(pipe, seeds: int, data: Path) -> list[dict]:
    p95 = real_jerk_p95(data)
    rows = []
    for segments in SEQUENCES:
        passed, free_passed, seams = [], [], []
        for seed in range(seeds):
            out = pipe.sequence([(p, s) for p, s, _ in segments], seed=seed)
            starts = out.timings["segments"] + [int(out.lengths[0])]
            overlap = 10  # a later segment's first 0.5 s repeat the previous one's last: judge its own frames,
            # its seconds from there (a middle one's last 0.5 s fade into the next)
            for k, (prompt, seconds, label) in enumerate(segments):
                own = starts[k] + (overlap if k else 0)
                end = min(own + int(round(seconds * pipe.fps)), starts[k + 1] + overlap)
                passed.append(physical.passes(out.joints[0, own:end], label))
                free = pipe([prompt], seconds=seconds, seed=seed)
                free_passed.append(physical.passes(free.joints[0, : int(free.lengths[0])], label))
            seams += [jerk for _, jerk, _ in out.seams[0]]  # from just before each fade to just after it
        rows.append({"sequence": " -> ".join(label for _, _, label in segments), "pass": np.mean(passed),
                     "free_pass": np.mean(free_passed), "seam_jerk": max(seams), "real_p95": p95})
    return rows


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--clips", type=int, default=8)
    parser.add_argument("--seeds", type=int, default=2)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args(argv)
    import torch

    from mld_core.pipeline import MLDPipeline

    torch.set_num_threads(args.threads)
    pipe = MLDPipeline.from_pretrained()
    k = pose_keys(pipe, args.data, args.clips)
    print(f"pose keys ({k['clips']} test clips, 4 keyed frames): keyed joints {k['keyed_cm']:.2f} cm, root "
          f"{k['root_cm']:.2f} cm (free samples: {k['free_cm']:.1f} cm); {k['time_s']:.2f} s per take")
    print("| prompt | path | speed (m/s) | root error (cm) | skating | free skating |")
    for r in root_paths(pipe, args.seeds):
        print(f"| {r['prompt']} | {r['shape']} | {r['speed']:.1f} | {r['root_cm']:.1f} | {r['skating']:.2f} | "
              f"{r['free_skating']:.2f} |")
    print("| prompt | loop gap (cm) | seam velocity jump / take's own p95 |")
    for r in loops(pipe, args.seeds):
        print(f"| {r['prompt']} | {r['gap_cm']:.2f} | {r['seam_jump_vs_p95']:.2f} |")
    print("| sequence | segments passing their check | free samples | largest seam jerk | real p95 |")
    for r in sequences(pipe, args.seeds, args.data):
        print(f"| {r['sequence']} | {r['pass']:.2f} | {r['free_pass']:.2f} | {r['seam_jerk']:.0f} | {r['real_p95']:.0f} |")
    t0 = time.perf_counter()
    pipe(["a person walks forward"], seconds=4, seed=0)
    free_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    pipe(["a person walks forward"], seconds=4, seed=0, constraints=Constraints([path_points("curved", 1.2)]))
    print(f"time, 4 s take: free {free_s:.2f} s, with a path {time.perf_counter() - t0:.2f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
