"""Where in Final's steps verb guidance does its work: scripts/vocabulary.py on a guided model whose verb denoiser's
term is added on one interval of the steps only, or computed on some of its steps and reused on those between.

    python research/v4/verb_guide_interval.py [--interval LO HI] [--every N] -- --data DIR --model GUIDED [...]

LO and HI are fractions of the sampler's steps, the noisiest first: step k of n is guided when LO * n <= k < HI * n
("0 0.5": the first half, "0.5 1": the last half; default "0 1", every step). With ``--every N`` the verb denoiser
runs on the first guided step and every N-th after it, and its term is reused on the guided steps between (N - 1 of
every N steps without its pass). Everything after ``--`` goes to scripts/vocabulary.py. A measurement for
research/v4/README.md: it wraps the pipeline's verb guidance for this process only and changes no model.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "scripts"))

from mld_core.pipeline import MLDPipeline  # noqa: E402
from mld_core.sampling import VerbGuidance  # noqa: E402


class IntervalVerbGuidance:
    """A VerbGuidance whose term is added only at the timesteps ``active``, computed on the first of them and every
    ``every``-th after it, and reused on those between."""

    def __init__(self, guidance: VerbGuidance, active: frozenset, every: int = 1):
        self.guidance, self.active, self.every = guidance, active, every
        self.guided, self.term = 0, None

    def add_to(self, eps, z, t, lengths):
        if int(t) not in self.active:
            return eps
        self.guided += 1
        if (self.guided - 1) % self.every == 0:
            guided = self.guidance.add_to(eps, z, t, lengths)
            self.term = guided - eps  # (B, n, d): the term on its rows, 0 on the others
            return guided
        return eps + self.term


def guided_timesteps(timesteps, lo: float, hi: float) -> frozenset:
    """The timesteps of steps k with lo * n <= k < hi * n."""
    steps = [int(t) for t in timesteps]
    n = len(steps)
    return frozenset(steps[math.ceil(lo * n): math.ceil(hi * n)])


def guide_only_on(lo: float, hi: float, every: int = 1) -> None:
    """Make every pipeline of this process add the verb term on the interval [lo, hi) of its steps, computed on every
    ``every``-th of them."""
    plain = MLDPipeline._verb_guidance

    def on_interval(self, call):
        g = plain(self, call)
        if g is None:
            return None
        active = guided_timesteps(self.scheduler.timesteps, lo, hi)  # the caller has set the call's timesteps
        return IntervalVerbGuidance(g, active, every)

    MLDPipeline._verb_guidance = on_interval


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    ours, rest = (argv[:argv.index("--")], argv[argv.index("--") + 1:]) if "--" in argv else (argv, [])
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--interval", nargs=2, type=float, default=(0.0, 1.0), metavar=("LO", "HI"))
    ap.add_argument("--every", type=int, default=1, metavar="N")
    args = ap.parse_args(ours)
    lo, hi = args.interval
    if not 0 <= lo < hi <= 1:
        print(f"error: --interval needs 0 <= LO < HI <= 1, got {lo:g} {hi:g}", file=sys.stderr)
        return 2
    if args.every < 1:
        print(f"error: --every needs a whole number of at least 1, got {args.every}", file=sys.stderr)
        return 2
    guide_only_on(lo, hi, args.every)
    import vocabulary

    return vocabulary.main(rest)


if __name__ == "__main__":
    raise SystemExit(main())
