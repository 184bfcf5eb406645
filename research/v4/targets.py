"""Measures one model against model v4's targets, by the same commands for every model, and says which it meets.

    python research/v4/targets.py --bandai data/bandai --cmu data/cmu --merged data/bandai_cmu --out DIR
        [--model M] [--baseline BASE_DIR] [--seeds 16] [--threads 2]

Each measurement runs once into DIR as JSON (a measurement whose JSON is there already is read, not run again, so an
interrupted run resumes):
  vocabulary.json  scripts/vocabulary.py --seeds N on the CMU folder (the new verbs, three wordings each);
  coverage.json    research/v4/coverage_verbs.py's counts (known verbs never unknown, absent motions flagged);
  physical.json    research/side_accuracy.py on the Bandai folder (the README's physical-check command);
  t2m_merged.json  evaluate t2m on the merged folder with the merged evaluator (research/v4/evaluator);
  t2m_bandai.json  evaluate t2m on the Bandai folder with the bundled evaluator.
Every measurement samples the model alone, without side or verb redraws (``--side-redraws 0 --verb-redraws 0``).
Then prints each target, its value, its bar and whether it is met, and writes DIR/targets.json. BASE_DIR is the DIR of
this command on the model the issue compares against (the bundled v3.8; only its physical.json is read, and
research/v4/baseline_v38 keeps v3.8's): the Bandai pass rates and the turns are met when within noise of it (the 95%
interval of the difference reaches zero). Speed (scripts/bench_addon.py) and the extension zip's size
(build_addon.py) are measured by their own commands. A measurement, not a test.
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(HERE))

VERB_BAR = 0.8  # generated pass rate over the real clips' rate, every wording
ABSENT_BAR = 0.95  # absent motions flagged
SKATING_BAR = 0.5  # generated skating over the real clips', per locomotion content
BANDAI_R3_BAR = 0.94
MERGED_R3_OF_REAL = 0.9
LOCOMOTION = ("walk", "run", "walk-back")
TURNS = ("walk-turn-left", "walk-turn-right")
Z95 = 1.96


def measurement_commands(model: str | None, bandai: Path, cmu: Path, merged: Path, out: Path, seeds: int,
                         threads: int) -> dict[str, list[str]]:
    """{json file name: the command that writes it} (coverage runs in this process)."""
    py, m = sys.executable, ["--model", model] if model else []
    t2m = [py, "-m", "mld_core", "evaluate", "t2m", *m, "--replications", "2", "--mm-texts", "0",
           "--side-redraws", "0", "--verb-redraws", "0", "--threads", str(threads), "--no-progress"]
    return {
        "vocabulary.json": [py, str(ROOT / "scripts" / "vocabulary.py"), "--data", str(cmu), *m, "--seeds", str(seeds),
                            "--verb-redraws", "0", "--threads", str(threads), "--json", str(out / "vocabulary.json")],
        "physical.json": [py, str(ROOT / "research" / "side_accuracy.py"), "--data", str(bandai), *m, "--clip-length",
                          "--prompts", "both", "--seeds", "4", "--max-clips", "16", "--valid-references",
                          "--side-redraws", "0", "--verb-redraws", "0", "--threads", str(threads), "--json",
                          str(out / "physical.json")],
        "t2m_merged.json": [*t2m, "--data", str(merged), "--evaluator", str(HERE / "evaluator"),
                            "--json", str(out / "t2m_merged.json")],
        "t2m_bandai.json": [*t2m, "--data", str(bandai), "--json", str(out / "t2m_bandai.json")],
    }


def run_measurements(args: argparse.Namespace) -> dict[str, dict]:
    args.out.mkdir(parents=True, exist_ok=True)
    commands = measurement_commands(args.model, args.bandai, args.cmu, args.merged, args.out, args.seeds, args.threads)
    for name, command in commands.items():
        if not (args.out / name).is_file():
            print(f"[targets] {name}: {' '.join(command)}", flush=True)
            subprocess.run(command, check=True, cwd=ROOT)
    if not (args.out / "coverage.json").is_file():
        from coverage_verbs import coverage_counts

        from mld_core.pipeline import MLDPipeline

        counts = coverage_counts(MLDPipeline.from_pretrained(args.model))
        (args.out / "coverage.json").write_text(json.dumps(counts, indent=1) + "\n")
    return read_measurements(args.out)


def read_measurements(folder: Path, names=("vocabulary", "coverage", "physical", "t2m_merged", "t2m_bandai")) -> dict:
    return {n: json.loads((folder / f"{n}.json").read_text()) for n in names}


# ---- judging ------------------------------------------------------------------------------------------------


def within_noise(new: float, n_new: int, old: float, n_old: int) -> bool:
    """Whether rate ``new`` (of n_new takes) is not worse than ``old`` (of n_old) beyond the 95% interval of their
    difference."""
    se = math.sqrt(new * (1 - new) / max(n_new, 1) + old * (1 - old) / max(n_old, 1))
    return new - old + Z95 * se >= 0


def _physical_rates(physical: dict) -> dict[str, tuple[float, int]]:
    """{'captions' | 'paraphrases': (mean pass rate over contents, takes)} at each clip's own length."""
    gen = physical["generated"]
    return {label: (gen[key]["overall"]["all"]["mean_pass_rate"], gen[key]["overall"]["all"]["n"])
            for label, key in (("captions", "captions@clip"), ("paraphrases", "paraphrase@clip"))}


def _turns(physical: dict) -> tuple[float, int]:
    """The named side used on the walk-and-turn captions (pooled over both sides) and how many takes had one."""
    contents = physical["generated"]["captions@clip"]["contents"]
    sided = [(contents[c]["side_accuracy"], contents[c]["side_n"]) for c in TURNS if contents.get(c, {}).get("side_n")]
    n = sum(k for _, k in sided)
    return (sum(a * k for a, k in sided) / n if n else float("nan")), n


def _r3(t2m: dict) -> tuple[float, float]:
    """(the model's R@3, the Real row's R@3)."""
    rows, model_row = t2m["rows"], t2m["order"][1]
    return rows[model_row]["R@3"]["mean"], rows["Real"]["R@3"]["mean"]


def judge(results: dict[str, dict], baseline: dict[str, dict] | None = None) -> list[dict]:
    """One row per target: name, value (text), bar (text), met (True/False, None where no baseline decides it)."""
    rows = []
    by_verb: dict[str, dict[str, float]] = {}
    for r in results["vocabulary"]["rows"]:
        by_verb.setdefault(r["verb"], {})[r["wording"]] = r["ratio"]
    for verb, ratios in by_verb.items():
        worst = min(ratios.values())
        rows.append({"target": f"verb {verb}", "value": " / ".join(f"{v:.2f}" for v in ratios.values()),
                     "bar": f">= {VERB_BAR} on every wording", "met": bool(worst >= VERB_BAR)})
    cov = results["coverage"]
    rows.append({"target": "known verbs never unknown", "value": f"{cov['known_unknown']} of {cov['known']} unknown",
                 "bar": "0", "met": cov["known_unknown"] == 0})
    flagged = cov["absent_flagged"] / cov["absent"]
    rows.append({"target": "absent motions flagged", "value": f"{flagged:.2f}", "bar": f">= {ABSENT_BAR}",
                 "met": flagged >= ABSENT_BAR})
    physical = results["physical"]
    rates, base_rates = _physical_rates(physical), _physical_rates(baseline["physical"]) if baseline else None
    for label, (rate, n) in rates.items():
        bar, met = "within noise of the baseline", None
        if base_rates:
            bar += f" ({base_rates[label][0]:.3f})"
            met = within_noise(rate, n, *base_rates[label])
        rows.append({"target": f"Bandai physical pass, {label}", "value": f"{rate:.3f}", "bar": bar, "met": met})
    real, gen = physical["real"]["contents"], physical["generated"]["captions@clip"]["contents"]
    for c in LOCOMOTION:
        if c in real and c in gen and real[c]["skating"]:
            ratio = gen[c]["skating"] / real[c]["skating"]
            rows.append({"target": f"skating {c} (x real)", "value": f"{ratio:.2f}", "bar": f"<= {SKATING_BAR}",
                         "met": ratio <= SKATING_BAR})
    turns, n = _turns(physical)
    bar, met = "as the baseline", None
    if baseline:
        base_turns, base_n = _turns(baseline["physical"])
        bar += f" ({base_turns:.3f})"
        met = within_noise(turns, n, base_turns, base_n)
    rows.append({"target": "turns to the named side", "value": f"{turns:.3f}", "bar": bar, "met": met})
    r3, _ = _r3(results["t2m_bandai"])
    rows.append({"target": "Bandai t2m R@3", "value": f"{r3:.3f}", "bar": f">= {BANDAI_R3_BAR}",
                 "met": r3 >= BANDAI_R3_BAR})
    r3, real_r3 = _r3(results["t2m_merged"])
    rows.append({"target": "merged t2m R@3 (x Real)", "value": f"{r3 / real_r3:.2f} ({r3:.3f} / {real_r3:.3f})",
                 "bar": f">= {MERGED_R3_OF_REAL}", "met": r3 / real_r3 >= MERGED_R3_OF_REAL})
    return rows


def format_rows(rows: list[dict]) -> str:
    mark = {True: "met", False: "NOT met", None: "-"}
    width = max(len(r["target"]) for r in rows)
    lines = [f"{'target':{width}}  {'value':24} {'bar':36} met"]
    lines += [f"{r['target']:{width}}  {r['value']:24} {r['bar']:36} {mark[r['met']]}" for r in rows]
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", default=None, help="a model folder (default: the bundled model)")
    ap.add_argument("--bandai", required=True, type=Path, help="the folder of data prepare bandai")
    ap.add_argument("--cmu", required=True, type=Path, help="the folder of data prepare cmu-joints")
    ap.add_argument("--merged", required=True, type=Path, help="the folder of data merge (Bandai + CMU)")
    ap.add_argument("--out", required=True, type=Path, help="where the measurements' JSON go")
    ap.add_argument("--baseline", type=Path, default=None, help="the --out folder of this command on the baseline")
    ap.add_argument("--seeds", type=int, default=16, help="vocabulary seeds per prompt (default 16)")
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args(argv)
    for flag, folder in (("--bandai", args.bandai), ("--cmu", args.cmu), ("--merged", args.merged)):
        if not folder.is_dir():
            print(f"error: {flag} {folder} is not a folder", file=sys.stderr)
            return 2
    if args.out.resolve() in {args.bandai.resolve(), args.cmu.resolve(), args.merged.resolve()}:
        print(f"error: --out {args.out} is a data folder: give the measurements a folder of their own", file=sys.stderr)
        return 2
    if args.baseline is not None and not (args.baseline / "physical.json").is_file():
        print(f"error: --baseline {args.baseline} holds no measurements of this command", file=sys.stderr)
        return 2
    try:
        results = run_measurements(args)
    except subprocess.CalledProcessError as exc:
        print(f"error: a measurement failed (exit {exc.returncode}): {' '.join(exc.cmd)}", file=sys.stderr)
        return 1
    rows = judge(results, read_measurements(args.baseline, ("physical",)) if args.baseline else None)
    (args.out / "targets.json").write_text(json.dumps({"model": args.model or "default", "rows": rows}, indent=1) + "\n")
    print(format_rows(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
