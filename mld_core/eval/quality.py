"""Per-take quality badges and the best-of-N order: what a user would otherwise find by scrubbing the timeline.

Every physical badge reads joints (T, 22, 3) in metres, Y up, the floor at y = 0 (as the prepared data and the
pipeline's output have it), at ``fps`` frames per second, with plain numpy:

- ``foot_skating_ratio``: the definition of GMD / OmniControl as MotionLCM reports it. A frame pair (t, t+1)
  skates for a toe joint (10 or 11) when the toe is below SKATE_HEIGHT_M above the floor in both frames while its
  horizontal speed exceeds SKATE_SPEED_MPS both frame to frame and averaged over a centred 5-frame window; the
  ratio is the share of frame pairs in which either toe skates. Floor = the take's lowest toe.
- ``foot_float``: the share of frames in which no toe is within FLOAT_HEIGHT_M of the floor (y = 0) while the body
  is not jumping. An airborne stretch is a jump (or a running stride) when it lasts at most FLIGHT_FREE_S, or when
  the pelvis rises over it at least half of what a ballistic flight of that length would (g d^2 / 16).
- ``ground_penetration_cm``: how deep the lowest joint goes below the floor (y = 0), centimetres (0 if never).
- ``jitter``: mean joint jerk (third derivative of position, m/s^3) relative to the real data's mean jerk
  (1.0 = as jerky as the motion capture; the reference is in the evaluator folder's quality_reference.json).
- adherence (:class:`QualityScorer`): the bundled evaluator's cosine similarity between the prompt and the motion,
  reported as a percentile of its distribution on real test pairs (50 = as well matched as a typical real clip and
  its own caption).
- ``side`` (:func:`side_badge`): for a prompt that names one side for a turn, a drift, a wave or a raised hand,
  whether the take used it ("named"), only the other side ("opposite"), or neither (``mld_core.eval.named_side``).
- ``verb`` (:func:`verb_badge`): for a prompt that names checked verbs (jump, crawl, kick, ...:
  ``mld_core.data.verbs``), whether the take shows them all by their physical checks ("shown") or not ("missed").

:func:`rank_score` combines the numbers (documented in docs/quality.md); :func:`best_first` orders variants by it,
deterministically (ties: the lower seed first), with takes that used the opposite side after the others and takes
that miss the prompt's verbs last.
``python scripts/quality_table.py`` measures every badge on the real test clips and on generated ones, and writes the
reference file.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from mld_core.data.verbs import verbs_in_order
from mld_core.eval import named_side, physical

L_TOE, R_TOE, PELVIS = 10, 11, 0
G = 9.81

SKATE_HEIGHT_M = 0.05
SKATE_SPEED_MPS = 0.5
SKATE_WINDOW = 5
FLOAT_HEIGHT_M = 0.05
FLIGHT_FREE_S = 0.25  # a running stride's flight (real runs: 0.1-0.2 s) never counts as floating

REFERENCE_NAME = "quality_reference.json"

# rank_score weights (docs/quality.md): adherence leads; each physical fault costs up to about half of it. Jitter
# counts both ways: a take far smoother than the capture has lost motion (waves that barely swing), one far jerkier
# shakes.
RANK_WEIGHTS = {"skating": 0.5, "float": 0.5, "penetration_per_cm": 0.05, "penetration_cap_cm": 10.0,
                "jitter_log": 0.25}


def _joints(joints) -> np.ndarray:
    j = np.asarray(joints, dtype=np.float64)
    if j.ndim != 3 or j.shape[1:] != (22, 3):
        raise ValueError(f"joints must have shape (T, 22, 3), got {j.shape}")
    if not np.isfinite(j).all():
        raise ValueError("joints contain NaN or infinite values")
    return j


def _centred_mean(x: np.ndarray, window: int) -> np.ndarray:
    """Mean over a centred window along axis 0 (shorter at the ends)."""
    half = window // 2
    c = np.concatenate([np.zeros((1,) + x.shape[1:]), np.cumsum(x, axis=0)])
    lo = np.clip(np.arange(len(x)) - half, 0, len(x))
    hi = np.clip(np.arange(len(x)) + half + 1, 0, len(x))
    return (c[hi] - c[lo]) / (hi - lo).reshape((-1,) + (1,) * (x.ndim - 1))


def foot_skating_ratio(joints, fps: float = 20.0) -> float:
    """Share of frame pairs in which a toe near the floor slides faster than 0.5 m/s (see the module docstring)."""
    j = _joints(joints)
    if len(j) < 2:
        return 0.0
    toes = j[:, [L_TOE, R_TOE]]  # (T, 2, 3)
    height = toes[:, :, 1] - toes[:, :, 1].min()  # (T, 2) above the take's lowest toe
    low = (height[:-1] < SKATE_HEIGHT_M) & (height[1:] < SKATE_HEIGHT_M)  # (T-1, 2) both frames
    speed = np.linalg.norm(np.diff(toes[:, :, [0, 2]], axis=0), axis=2) * fps  # (T-1, 2) horizontal m/s
    fast = (speed > SKATE_SPEED_MPS) & (_centred_mean(speed, SKATE_WINDOW) > SKATE_SPEED_MPS)
    return float((low & fast).any(axis=1).mean())


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    m = np.concatenate([[False], mask.astype(bool), [False]])
    edges = np.flatnonzero(np.diff(m.astype(np.int8)))
    return list(zip(edges[0::2].tolist(), edges[1::2].tolist()))


def foot_float(joints, fps: float = 20.0) -> float:
    """Share of frames with no toe within 5 cm of the floor (y = 0) outside jumps (see the module docstring)."""
    j = _joints(joints)
    airborne = j[:, [L_TOE, R_TOE], 1].min(axis=1) > FLOAT_HEIGHT_M  # (T,)
    pelvis = j[:, PELVIS, 1]
    floating = 0
    for a, b in _runs(airborne):
        d = (b - a) / fps
        if d <= FLIGHT_FREE_S:
            continue
        take_off = pelvis[max(a - 1, 0)]
        if pelvis[a:b].max() - take_off >= G * d * d / 16.0:
            continue  # rises like a real jump of that length
        floating += b - a
    return floating / len(j)


def ground_penetration_cm(joints) -> float:
    """Depth of the lowest joint below the floor (y = 0) in centimetres; 0 when nothing goes below."""
    j = _joints(joints)
    return float(max(0.0, -j[:, :, 1].min()) * 100.0)


# The 95th percentile of the largest joint jerk per 4-frame window over the first 200 Bandai test clips (m/s^3;
# research/control_table.py, real_jerk_p95): a sequence's seam that jerks more than this is rougher than real motion.
REAL_JERK_P95 = 950.0
SEAM_MARGIN_BEFORE, SEAM_MARGIN_AFTER = 3, 2  # frames around a seam's cross-fade that its jerk is judged over


def largest_joint_jerk(joints, fps: float = 20.0) -> np.ndarray:
    """(T-3,) the largest joint's jerk (m/s^3) in each 4-frame window."""
    return np.linalg.norm(np.diff(_joints(joints), n=3, axis=0), axis=-1).max(-1) * fps ** 3


def seam_jerk(joints, start: int, fade: int, fps: float = 20.0) -> float:
    """The largest joint jerk (m/s^3) of a seam whose cross-fade spans frames [start, start + fade), judged from
    SEAM_MARGIN_BEFORE frames before it to SEAM_MARGIN_AFTER after it."""
    jerk = largest_joint_jerk(joints, fps)
    return float(jerk[max(0, start - SEAM_MARGIN_BEFORE): start + fade + SEAM_MARGIN_AFTER].max())


def mean_jerk(joints, fps: float = 20.0) -> float:
    """Mean magnitude of the joints' third derivative (m/s^3) over joints and frames (0 under 4 frames)."""
    j = _joints(joints)
    if len(j) < 4:
        return 0.0
    jerk = np.diff(j, n=3, axis=0) * fps ** 3  # (T-3, 22, 3)
    return float(np.linalg.norm(jerk, axis=2).mean())


@dataclass
class Badges:
    """One take's badges; ``adherence`` is a percentile (0-100) or None without an evaluator."""

    adherence: float | None
    similarity: float | None
    skating: float
    float: float
    penetration_cm: float
    jitter: float
    side: str | None = None  # "named" / "opposite" / "neither" (mld_core.eval.named_side); None: no side asked
    verb: str | None = None  # "shown" / "missed": every checked verb the prompt names shown or not; None: none named

    def as_dict(self) -> dict:
        return {k: (v if v is None or isinstance(v, str) else round(float(v), 4)) for k, v in asdict(self).items()}


def physical_badges(joints, fps: float = 20.0, reference_jerk: float | None = None) -> dict:
    """skating, float, penetration_cm and jitter (jerk / reference_jerk; the raw jerk when no reference)."""
    jerk = mean_jerk(joints, fps)
    return {"skating": foot_skating_ratio(joints, fps), "float": foot_float(joints, fps),
            "penetration_cm": ground_penetration_cm(joints),
            "jitter": jerk / reference_jerk if reference_jerk else jerk}


def rank_score(b: Badges) -> float:
    """Higher is better: adherence / 100 - 0.5 skating - 0.5 float - 0.05 / cm penetration (capped at 10 cm)
    - 0.25 |ln jitter| (0 for real-like jerk; adherence counts 0.5 when unknown)."""
    w = RANK_WEIGHTS
    adherence = 0.5 if b.adherence is None else b.adherence / 100.0
    return float(adherence - w["skating"] * b.skating - w["float"] * b.float
                 - w["penetration_per_cm"] * min(b.penetration_cm, w["penetration_cap_cm"])
                 - w["jitter_log"] * abs(np.log(max(b.jitter, 1e-3))))


def best_first(badges: Sequence[Badges], seeds: Sequence[int]) -> list[int]:
    """Indices of ``badges`` from the best rank_score down; equal scores keep the lower seed first. Takes that
    used the side opposite the one the prompt names (side "opposite") come after all others, whatever their score,
    and takes that do not show the checked verbs the prompt names (verb "missed") after those."""
    keys = [(b.verb == "missed", b.side == "opposite", -round(rank_score(b), 9), int(s), i)
            for i, (b, s) in enumerate(zip(badges, seeds))]
    return [key[-1] for key in sorted(keys)]


def percentile(value: float, quantiles: Sequence[float]) -> float:
    """Where ``value`` falls in a distribution given by its 0..100 percentiles (evenly spaced), 0-100."""
    q = np.asarray(quantiles, np.float64)
    return float(np.interp(value, q, np.linspace(0.0, 100.0, len(q))))


class QualityScorer:
    """Badges for takes: the physical ones plus adherence by the evaluator, against the real-data reference."""

    def __init__(self, evaluator=None, reference: dict | None = None):
        self.evaluator = evaluator
        self.reference = reference or {}

    @classmethod
    def from_pretrained(cls, directory: str | Path | None = None, text_encoder=None) -> "QualityScorer":
        """The evaluator folder (None: the bundled one) and its quality_reference.json; ``text_encoder`` (the
        pipeline's, when it is the same sentence encoder) saves loading a second copy.
        An evaluator folder that is missing leaves adherence out (the physical badges still work)."""
        from mld_core.eval.evaluator import DEFAULT_DIR, Evaluator, EvaluatorError

        directory = Path(directory) if directory is not None else DEFAULT_DIR
        try:
            evaluator = Evaluator.from_pretrained(directory)
        except EvaluatorError:
            evaluator = None
        spec = getattr(text_encoder, "spec", {}) or {}
        if evaluator is not None and text_encoder is not None and not spec.get("path") \
                and spec.get("kind") == evaluator.config.text_encoder.get("kind") \
                and not evaluator.config.text_encoder.get("path"):
            evaluator._text_encoder = text_encoder  # the same sentence encoder: no second copy
        path = directory / REFERENCE_NAME
        reference = json.loads(path.read_text()) if path.is_file() else {}
        return cls(evaluator, reference)

    def similarity(self, prompts: Sequence[str], features: Sequence[np.ndarray]) -> np.ndarray:
        """Cosine similarity (N,) of each prompt with its motion's features (T_i, 263), by the evaluator."""
        text = self.evaluator.encode_text(list(prompts))  # (N, E) unit
        motion = self.evaluator.encode_motion([np.asarray(f, np.float32) for f in features])  # (N, E) unit
        return np.einsum("ne,ne->n", text, motion)

    def score(self, prompts: Sequence[str], joints: Sequence[np.ndarray], features: Sequence[np.ndarray] | None = None,
              fps: float = 20.0) -> list[Badges]:
        """Badges per take. ``features`` (T_i, 263) are computed from the joints when not given."""
        joints = [np.asarray(j) for j in joints]
        measured = [physical_badges(j, fps, self.reference.get("jerk_mean")) for j in joints]
        sides = [side_badge(p, j, fps) for p, j in zip(prompts, joints)] if prompts else [None] * len(joints)
        verbs = [verb_badge(p, j, fps) for p, j in zip(prompts, joints)] if prompts else [None] * len(joints)
        sims = [None] * len(joints)
        pct = [None] * len(joints)
        if self.evaluator is not None and prompts and all(p for p in prompts):
            if features is None:
                from mld_core.motion.features import joints_to_features

                features = [joints_to_features(j, fps) for j in joints]
            sims = [float(s) for s in self.similarity(prompts, features)]
            quantiles = self.reference.get("similarity_percentiles")
            pct = [percentile(s, quantiles) if quantiles else None for s in sims]
        return [Badges(a, s, **p, side=side, verb=verb)
                for a, s, p, side, verb in zip(pct, sims, measured, sides, verbs)]


def side_badge(prompt: str | None, joints: np.ndarray, fps: float = 20.0) -> str | None:
    """"named" / "opposite" / "neither" for a prompt that names one side (mld_core.eval.named_side), else None."""
    ask = named_side.asked_side(prompt) if prompt else None
    return None if ask is None else named_side.side_used(ask, physical.classify(joints, fps))


def verbs_shown(prompt: str | None, joints: np.ndarray, fps: float = 20.0) -> tuple[int, int]:
    """(how many of the checked verbs the prompt names the take shows by their physical checks, how many it names)."""
    verbs = verbs_in_order(prompt) if prompt else []
    return sum(bool(physical.shows(joints, verb, fps)) for verb in verbs), len(verbs)


def verb_badge(prompt: str | None, joints: np.ndarray, fps: float = 20.0) -> str | None:
    """"shown" when the take shows every checked verb the prompt names (mld_core.data.verbs) by its physical check,
    "missed" when not, None when the prompt names none."""
    shown, named = verbs_shown(prompt, joints, fps)
    return None if not named else "shown" if shown == named else "missed"


def rank_output(out, scorer: QualityScorer, num_variants: int, prompts: Sequence[str] | None = None):
    """``out`` (an MLDOutput) with ``badges`` set and each prompt's ``num_variants`` consecutive rows reordered best
    first. ``prompts`` overrides the rows' prompts for adherence ([] = no adherence: action or unconditional)."""
    from dataclasses import replace

    rows = range(len(out.lengths))
    texts = out.prompts if prompts is None else (prompts or None)
    badges = scorer.score(texts, [out.joints[i, : int(out.lengths[i])] for i in rows],
                          [out.features[i, : int(out.lengths[i])] for i in rows], out.fps)
    order = []
    for start in range(0, len(badges), num_variants):
        group = list(range(start, start + num_variants))
        order += [group[k] for k in best_first([badges[i] for i in group], [out.seeds[i] for i in group])]
    return replace(out, badges=badges).select(order)


def format_table(seeds: Sequence[int], badges: Sequence[Badges]) -> str:
    """The CLI's table: one row per take, in the given order."""
    lines = [f"{'seed':>6s} {'adherence':>9s} {'skating':>7s} {'float':>5s} {'penetr.':>7s} {'jitter':>6s} {'rank':>6s}"
             f" {'side':>8s} {'verb':>6s}"]
    for seed, b in zip(seeds, badges):
        adh = "-" if b.adherence is None else f"{b.adherence:.0f}"
        lines.append(f"{seed:6d} {adh:>9s} {b.skating:7.2f} {b.float:5.2f} {b.penetration_cm:5.1f}cm "
                     f"{b.jitter:6.2f} {rank_score(b):6.2f} {b.side or '-':>8s} {b.verb or '-':>6s}")
    return "\n".join(lines)
