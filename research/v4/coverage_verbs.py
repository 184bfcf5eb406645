"""Does prompt coverage know the CMU verbs and still flag motions no training data holds? Per model: the verdict of
the vocabulary benchmark's command and user prompts (scripts/vocabulary.py) and of research/v4/absent_motions.txt
(flagged: unknown or near, the target of research/coverage_calibration.py).

    python research/v4/coverage_verbs.py MODEL [MODEL ...]
"""

from __future__ import annotations

import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parents[1]))
sys.path.insert(0, str(HERE.parents[1] / "scripts"))

from mld_core.pipeline import MLDPipeline  # noqa: E402
from vocabulary import COMMANDS, USER  # noqa: E402


def coverage_counts(pipe) -> dict:
    """The verdicts of a loaded pipeline's coverage on the known-verb prompts and the absent motions."""
    absent = [line.strip() for line in (HERE / "absent_motions.txt").read_text().splitlines()
              if line.strip() and not line.startswith("#")]
    known = [p for table in (COMMANDS, USER) for p in table.values()]
    k = [c.verdict for c in pipe.coverage(known)]
    a = [c.verdict for c in pipe.coverage(absent)]
    return {"known": len(k), "known_unknown": k.count("unknown"), "known_near": k.count("near"),
            "absent": len(a), "absent_flagged": len(a) - a.count("known"), "absent_unknown": a.count("unknown"),
            "absent_near": a.count("near"),
            "known_called_unknown": [p for p, v in zip(known, k) if v == "unknown"],
            "absent_called_known": [p for p, v in zip(absent, a) if v == "known"]}


def main() -> int:
    for model in sys.argv[1:]:
        c = coverage_counts(MLDPipeline.from_pretrained(model))
        print(f"{model}: known verbs flagged unknown {c['known_unknown']}/{c['known']} (near {c['known_near']}); "
              f"absent motions flagged {c['absent_flagged']}/{c['absent']} = {c['absent_flagged'] / c['absent']:.2f} "
              f"(unknown {c['absent_unknown']}, near {c['absent_near']})")
        for prompt in c["known_called_unknown"]:
            print(f"  known verb called unknown: {prompt}")
        for prompt in c["absent_called_known"]:
            print(f"  absent motion called known: {prompt}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
