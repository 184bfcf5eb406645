"""Do directed takes step? Foot skating of takes on a root path, looped takes and prompt sequences, with and without
stepping (mld_core.take_fixes.stepping.step_feet), on the bundled model (a measurement: prints a table, asserts
nothing).

    .venv/bin/python research/directed_skating.py [--model DIR] [--seeds 8] [--threads 1] [--json out.json]

Each case runs ``--seeds`` seeds twice, ``step=True`` and ``step=False`` (everything else the same: the
constraints' own refinement and the repairs). Columns: the mean foot skating ratio (mld_core.eval.quality), the
share of constraints met (paths and loops; for a sequence, the share of its seams no rougher than real motion,
``MLDOutput.seams``) and the mean seconds per take.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mld_core.take_fixes.constraints import Constraints, Loop, RootPath  # noqa: E402
from mld_core.eval.quality import foot_skating_ratio  # noqa: E402

PATHS = {  # name: (prompt, seconds, frames of the path's points, their (x, z) in metres)
    "path: straight 4.8 m": ("a person walks forward", 4.0, [0, 79], [[0.0, 0.0], [0.0, 4.8]]),
    "path: a bend to the right": ("a person walks forward", 4.0, [0, 40, 79], [[0.0, 0.0], [0.0, 2.4], [-2.0, 4.0]]),
    "path: 3 m backwards": ("a person walks backwards", 4.0, [0, 79], [[0.0, 0.0], [0.0, -3.0]]),
}
LOOPS = {"loop: a walk cycle": ("a person walks forward", 2.0), "loop: a run cycle": ("a person runs forward", 2.0)}
SEQUENCES = {
    "sequence: walk, turn left": [("a person walks forward", 3.0), ("a person turns left and walks", 3.0)],
    "sequence: run, walk backwards": [("a person runs forward", 3.0), ("a person walks backwards", 3.0)],
    "sequence: walk, wave, walk left": [("a person walks forward", 3.0), ("a person waves with the right hand", 2.0),
                                        ("a person walks to the left", 3.0)],
}


def constrained(pipe, prompt: str, seconds: float, constraints, seeds: int, step: bool) -> dict:
    t0 = time.perf_counter()
    out = pipe(prompt, seconds, seed=0, num_variants=seeds, constraints=constraints, step=step)
    return {"skating": [foot_skating_ratio(j[:n]) for j, n in zip(out.joints, out.lengths)],
            "met": [met for row in out.residuals for _, _, met in row],
            "seconds_per_take": (time.perf_counter() - t0) / seeds}


def sequence(pipe, segments, seeds: int, step: bool) -> dict:
    t0 = time.perf_counter()
    outs = [pipe.sequence(segments, seed=seed, step=step) for seed in range(seeds)]
    return {"skating": [foot_skating_ratio(o.joints[0]) for o in outs],
            "met": [within for o in outs for _, _, within in o.seams[0]],
            "seconds_per_take": (time.perf_counter() - t0) / seeds}


def cases(pipe, seeds: int, step: bool):
    for name, (prompt, seconds, frames, points) in PATHS.items():
        yield name, constrained(pipe, prompt, seconds, Constraints([RootPath(frames, np.array(points))]), seeds, step)
    for name, (prompt, seconds) in LOOPS.items():
        yield name, constrained(pipe, prompt, seconds, Constraints([Loop()]), seeds, step)
    for name, segments in SEQUENCES.items():
        yield name, sequence(pipe, segments, seeds, step)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default=None, help="model folder (default: the bundled model)")
    parser.add_argument("--seeds", type=int, default=8)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    import torch

    from mld_core.checkpoint import CheckpointError
    from mld_core.pipeline import MLDPipeline

    torch.set_num_threads(args.threads)
    try:
        pipe = MLDPipeline.from_pretrained(args.model)
    except CheckpointError as exc:
        print(f"error: --model {args.model}: {exc}", file=sys.stderr)
        return 2
    rows = {True: dict(cases(pipe, args.seeds, True)), False: dict(cases(pipe, args.seeds, False))}
    print(f"{pipe.model_id}, {args.seeds} seeds a case; stepped / not stepped")
    print(f"{'case':34s} {'skating':>15s} {'met':>11s} {'s per take':>13s}")
    for name in rows[True]:
        on, off = rows[True][name], rows[False][name]
        print(f"{name:34s} {np.mean(on['skating']):7.3f} /{np.mean(off['skating']):6.3f} "
              f"{np.mean(on['met']):5.2f} /{np.mean(off['met']):5.2f} "
              f"{on['seconds_per_take']:6.2f} /{off['seconds_per_take']:5.2f}")
    if args.json:
        args.json.write_text(json.dumps({"model": pipe.model_id, "seeds": args.seeds,
                                         "stepped": rows[True], "not_stepped": rows[False]}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
