"""Record the takes the pipeline makes on every one of its paths, so a change of its code can prove that its takes did
not change.

    python scripts/record_takes.py --out tests/fixtures/takes_reference.npz      # record
    python scripts/record_takes.py --compare tests/fixtures/takes_reference.npz  # compare; prints each case's result

Runs the bundled model (``MLDPipeline.from_pretrained()``) on one thread on short takes (2 s; a sequence of two
segments) through each path of ``MLDPipeline.__call__``: plain Final, Final without stepping, a Draft, a prompt that
names a side (content anchor, side contrast and a side redraw), directed takes (pose keys, a root path and a loop;
stepped and not), two variants ranked (the second first), a sequence, an unconditional take without repairs, and a
tiny action model (``mld_core.testing.tiny_model``). Stores each case's features, joints, lengths, seeds, draws,
constraint residuals and seam jerks. ``--compare`` prints per case ``same`` or the largest difference and exits 1
when any array differs in a single bit.

Float sums depend on the CPU's vector units and on the precision the Draft picks there, so the recording keeps the
machine it was made on (torch version, CPU capability, vendor and AMX, the Draft's precision); takes are compared bit
for bit only on a machine of the same kind (elsewhere ``--compare`` says so and exits 3: record a reference there
first).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

WALK = "a person walks forward"
TURN_LEFT = "a person walks and turns left"
WAVE = "a person waves the right hand"
SIDED_SEED = 3  # a seed whose first draw of TURN_LEFT at 2 s misses the side, so that a side redraw is kept


def _directed():
    from mld_core.take_fixes.constraints import Constraints, Loop, PoseKeys, RootPath

    keys = PoseKeys({20: {"pelvis": [0.0, 0.9, 0.5], "right_wrist": [-0.3, 1.5, 0.7]}})
    return Constraints([keys, RootPath([0, 39], [[0.0, 0.0], [0.0, 1.0]]), Loop()])


def cases(pipe, action_pipe) -> dict:
    """name -> a function making that case's MLDOutput."""
    return {
        "final": lambda: pipe(WALK, 2.0, seed=0),
        "final_unstepped": lambda: pipe(WALK, 2.0, seed=1, step=False),
        "draft": lambda: pipe(WAVE, 2.0, seed=2, draft=True),
        "sided_redrawn": lambda: pipe(TURN_LEFT, 2.0, seed=SIDED_SEED),
        "directed_stepped": lambda: pipe(WALK, 2.0, seed=4, constraints=_directed()),
        "directed_unstepped": lambda: pipe(WALK, 2.0, seed=4, constraints=_directed(), step=False),
        "ranked_variants": lambda: pipe(WAVE, 2.0, seed=6, num_variants=2, rank=True),
        "sequence": lambda: pipe.sequence([(WALK, 2.0), (WAVE, 1.5)], seed=6),
        "unconditional_unrepaired": lambda: pipe(WALK, 2.0, seed=7, unconditional=True, repair=False),
        "action_tiny": lambda: action_pipe([], 1.0, actions=["wave"], seed=8),
    }


def cpu_kind() -> str:
    """The CPU's name and whether it has AMX tiles (torch's own CPU capabilities, as ``native_bf16`` reads them): two
    CPUs of one vector capability (AVX512) still sum bfloat16 and float32 products differently when oneDNN picks AMX
    kernels on one of them."""
    import torch

    try:
        caps = torch.cpu.get_capabilities()
    except (AttributeError, RuntimeError):
        return "unknown"
    return f"{caps.get('cpu_name') or caps.get('architecture') or 'unknown'}{' amx' if caps.get('amx_tile') else ''}"


def machine(pipe) -> str:
    """What the takes' bits depend on besides the code: torch, the CPU (vendor, vector and matrix units), the Draft's
    precision."""
    import torch

    return (f"torch {torch.__version__}; cpu {torch.backends.cpu.get_cpu_capability()} {cpu_kind()}; "
            f"draft {pipe.draft_precision}")


def arrays(out) -> dict:
    """An MLDOutput's recorded arrays."""
    rows = range(len(out.lengths))
    stored = {"features": out.features, "joints": out.joints, "lengths": np.asarray(out.lengths, np.int64),
              "seeds": np.asarray(out.seeds, np.int64), "draws": np.asarray(out.draws or [0] * len(rows), np.int64)}
    if out.residuals is not None:
        stored["residuals"] = np.array([[m for _, m, _ in out.residuals[r]] for r in rows], np.float64)
    if out.seams is not None:
        stored["seams"] = np.array([[jerk for _, jerk, _ in out.seams[r]] for r in rows], np.float64)
    return stored


def record() -> dict:
    """Every case's arrays as ``{"case/array": array}``, and ``machine``."""
    import torch

    from mld_core.pipeline import MLDPipeline
    from mld_core.testing import tiny_pipeline

    torch.set_num_threads(1)
    pipe = MLDPipeline.from_pretrained()
    with tempfile.TemporaryDirectory() as tmp:
        action_pipe = tiny_pipeline(Path(tmp) / "tiny_action", cond="action")
        result = {"machine": np.array(machine(pipe))}
        for name, make in cases(pipe, action_pipe).items():
            for key, value in arrays(make()).items():
                result[f"{name}/{key}"] = value
    return result


def compare(new: dict, reference: dict) -> dict[str, str]:
    """Per case ``same``, or what differs (the largest difference of each array that is not bit-identical)."""
    verdicts = {}
    for case in sorted({k.split("/")[0] for k in (*reference, *new) if "/" in k}):
        problems = []
        for key in sorted({k for k in (*reference, *new) if k.startswith(case + "/")}):
            if key not in new or key not in reference:
                problems.append(f"{key.split('/', 1)[1]} {'missing' if key not in new else 'not recorded'}")
            elif new[key].shape != reference[key].shape or new[key].dtype != reference[key].dtype:
                problems.append(f"{key.split('/', 1)[1]} {new[key].dtype}{list(new[key].shape)} vs recorded "
                                f"{reference[key].dtype}{list(reference[key].shape)}")
            elif not np.array_equal(new[key], reference[key]):
                gap = np.abs(new[key].astype(np.float64) - reference[key].astype(np.float64)).max()
                problems.append(f"{key.split('/', 1)[1]} differs by up to {gap:.3g}")
        verdicts[case] = "; ".join(problems) or "same"
    return verdicts


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    what = parser.add_mutually_exclusive_group(required=True)
    what.add_argument("--out", type=Path, help="record the takes into this .npz")
    what.add_argument("--compare", type=Path, help="compare fresh takes with this recording")
    args = parser.parse_args(argv)
    if args.out:
        takes = record()
        args.out.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(args.out, **takes)
        print(f"recorded {len({k.split('/')[0] for k in takes if '/' in k})} cases on {takes['machine']}: "
              f"{args.out} ({args.out.stat().st_size / 1024:.0f} KB)")
        return 0
    with np.load(args.compare) as data:
        reference = {k: data[k] for k in data.files}
    takes = record()
    if str(takes["machine"]) != str(reference["machine"]):
        print(f"recorded on {reference['machine']}, this machine is {takes['machine']}: takes compare bit for bit "
              "only on the same kind; record a reference here first")
        return 3
    verdicts = compare(takes, reference)
    for case, verdict in verdicts.items():
        print(f"{case}: {verdict}")
    differing = sum(v != "same" for v in verdicts.values())
    print(f"{differing} of {len(verdicts)} cases differ")
    return 1 if differing else 0


if __name__ == "__main__":
    sys.exit(main())
