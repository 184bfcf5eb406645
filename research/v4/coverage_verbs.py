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


def main() -> int:
    absent = [line.strip() for line in (HERE / "absent_motions.txt").read_text().splitlines()
              if line.strip() and not line.startswith("#")]
    known = [p for table in (COMMANDS, USER) for p in table.values()]
    for model in sys.argv[1:]:
        pipe = MLDPipeline.from_pretrained(model)
        k = [c.verdict for c in pipe.coverage(known)]
        a = [c.verdict for c in pipe.coverage(absent)]
        flagged = len(a) - a.count("known")
        print(f"{model}: known verbs flagged unknown {k.count('unknown')}/{len(k)} (near {k.count('near')}); "
              f"absent motions flagged {flagged}/{len(a)} = {flagged / len(a):.2f} "
              f"(unknown {a.count('unknown')}, near {a.count('near')})")
        for prompt, verdict in zip(known, k):
            if verdict == "unknown":
                print(f"  known verb called unknown: {prompt}")
        for prompt, verdict in zip(absent, a):
            if verdict == "known":
                print(f"  absent motion called known: {prompt}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
