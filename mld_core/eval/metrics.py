"""Evaluation metrics of Guo et al. (CVPR 2022) and MLD (Chen et al., CVPR 2023), in numpy.

Everything here is a plain function of arrays; nothing knows about models. Embedding metrics take
(N, D) arrays from an evaluator; reconstruction metrics take joint positions in metres and report
millimetres. Randomised metrics take a ``numpy.random.Generator`` so a replication is reproducible.

- ``fid``: Frechet distance between Gaussians fitted to two embedding sets. The matrix square root is
  done with symmetric eigendecompositions only: tr sqrt(S1 S2) = sum sqrt(eig(sqrt(S1) S2 sqrt(S1))),
  since sqrt(S1) S2 sqrt(S1) is symmetric positive semi-definite and similar to S1 S2.
- ``kid``: kernel inception distance (unbiased polynomial-kernel MMD over random subsets).
- ``r_precision``: each motion is ranked against a pool of 32 texts (its own + the 31 others of its
  batch of 32, as Guo et al. batch the test set); top-1/2/3 hit rates. Also returns MM-Dist.
  Identical captions in a pool are exact ties, broken at random (in expectation).
- ``matching_score`` (MM-Dist): mean Euclidean distance between a motion and its own text.
- ``diversity``: mean distance between 300 random pairs of motions.
- ``multimodality``: mean distance between 10 random pairs of motions generated from the same text.
- ``action_multimodality``: the action-to-motion variant (random same-action pairs, as ACTOR/MLD).
- ``mpjpe`` / ``pa_mpjpe`` / ``accel_error``: VAE reconstruction errors; ``reconstruction_errors``
  aggregates them over variable-length sequences in millimetres, weighting every frame equally.
- ``accuracy``: classification accuracy (action-to-motion).
- ``mean_ci``: mean and 95% confidence interval 1.96 * std / sqrt(n) over replications (np.std,
  ddof=0, exactly as the T2M/MLD evaluation scripts report).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

__all__ = [
    "sqrtm_psd",
    "activation_statistics",
    "frechet_distance",
    "fid",
    "kid",
    "euclidean_distance_matrix",
    "r_precision",
    "matching_score",
    "diversity",
    "multimodality",
    "action_multimodality",
    "accuracy",
    "similarity_transform",
    "mpjpe",
    "pa_mpjpe",
    "accel_error",
    "reconstruction_errors",
    "mean_ci",
]


def _as_np(x) -> np.ndarray:
    if hasattr(x, "detach"):  # torch tensor
        x = x.detach().cpu().numpy()
    return np.asarray(x)


def _rng(rng) -> np.random.Generator:
    if rng is None or isinstance(rng, (int, np.integer)):
        return np.random.default_rng(rng)
    return rng


# --------------------------------------------------------------------------------------------------
# Distribution distances
# --------------------------------------------------------------------------------------------------


def sqrtm_psd(a: np.ndarray) -> np.ndarray:
    """Square root of a symmetric positive semi-definite matrix (negative round-off eigenvalues -> 0)."""
    a = np.asarray(a, dtype=np.float64)
    a = 0.5 * (a + a.T)
    w, v = np.linalg.eigh(a)
    w = np.sqrt(np.clip(w, 0.0, None))
    return (v * w) @ v.T


def activation_statistics(x) -> tuple[np.ndarray, np.ndarray]:
    """Mean (D,) and covariance (D, D) (unbiased, like np.cov) of embeddings (N, D)."""
    x = _as_np(x).astype(np.float64)
    if x.ndim != 2 or x.shape[0] < 2:
        raise ValueError(f"need embeddings of shape (N>=2, D), got {x.shape}")
    return x.mean(axis=0), np.cov(x, rowvar=False).reshape(x.shape[1], x.shape[1])


def frechet_distance(mu1, sigma1, mu2, sigma2) -> float:
    """||mu1 - mu2||^2 + tr(S1 + S2 - 2 (S1 S2)^(1/2)) for two Gaussians."""
    mu1, mu2 = np.atleast_1d(np.asarray(mu1, np.float64)), np.atleast_1d(np.asarray(mu2, np.float64))
    s1, s2 = np.atleast_2d(np.asarray(sigma1, np.float64)), np.atleast_2d(np.asarray(sigma2, np.float64))
    if mu1.shape != mu2.shape or s1.shape != s2.shape:
        raise ValueError(f"shape mismatch: {mu1.shape} vs {mu2.shape}, {s1.shape} vs {s2.shape}")
    root1 = sqrtm_psd(s1)
    middle = root1 @ (0.5 * (s2 + s2.T)) @ root1  # symmetric PSD, same eigenvalues as S1 S2
    eig = np.linalg.eigvalsh(0.5 * (middle + middle.T))
    tr_covmean = float(np.sqrt(np.clip(eig, 0.0, None)).sum())
    diff = mu1 - mu2
    value = float(diff @ diff + np.trace(s1) + np.trace(s2) - 2.0 * tr_covmean)
    return max(value, 0.0) if value > -1e-9 else value


def fid(emb_a, emb_b) -> float:
    """Frechet distance between the Gaussians fitted to two embedding sets (N, D) and (M, D)."""
    return frechet_distance(*activation_statistics(emb_a), *activation_statistics(emb_b))


def _poly_mmd2_unbiased(x: np.ndarray, y: np.ndarray, degree: int = 3, coef0: float = 1.0) -> float:
    gamma = 1.0 / x.shape[1]
    kxx = (gamma * x @ x.T + coef0) ** degree
    kyy = (gamma * y @ y.T + coef0) ** degree
    kxy = (gamma * x @ y.T + coef0) ** degree
    m, n = len(x), len(y)
    sxx = (kxx.sum() - np.trace(kxx)) / (m * (m - 1))
    syy = (kyy.sum() - np.trace(kyy)) / (n * (n - 1))
    return float(sxx + syy - 2.0 * kxy.mean())


def kid(emb_a, emb_b, *, n_subsets: int = 50, subset_size: int = 1000, rng=None) -> tuple[float, float]:
    """Kernel inception distance: mean and std of the unbiased cubic-kernel MMD^2 over random subsets."""
    a, b = _as_np(emb_a).astype(np.float64), _as_np(emb_b).astype(np.float64)
    rng = _rng(rng)
    size = min(subset_size, len(a), len(b))
    if size < 2:
        raise ValueError("KID needs at least 2 embeddings in each set")
    values = []
    for _ in range(n_subsets):
        ia = rng.choice(len(a), size, replace=False)
        ib = rng.choice(len(b), size, replace=False)
        values.append(_poly_mmd2_unbiased(a[ia], b[ib]))
    return float(np.mean(values)), float(np.std(values))


# --------------------------------------------------------------------------------------------------
# Text-motion matching
# --------------------------------------------------------------------------------------------------


def euclidean_distance_matrix(a, b) -> np.ndarray:
    """dist[i, j] = ||a[i] - b[j]|| for a (N, D), b (M, D)."""
    a, b = _as_np(a).astype(np.float64), _as_np(b).astype(np.float64)
    sq = (a * a).sum(1)[:, None] + (b * b).sum(1)[None, :] - 2.0 * a @ b.T
    return np.sqrt(np.clip(sq, 0.0, None))


def _batches(n: int, batch_size: int, rng, shuffle: bool) -> list[np.ndarray]:
    if n < batch_size:
        raise ValueError(f"R-precision needs at least {batch_size} pairs (one pool), got {n}")
    order = _rng(rng).permutation(n) if shuffle else np.arange(n)
    count = n // batch_size  # drop the last incomplete pool, as the T2M loader does (drop_last)
    return [order[i * batch_size : (i + 1) * batch_size] for i in range(count)]


def r_precision(
    text_emb,
    motion_emb,
    *,
    top_k: int = 3,
    batch_size: int = 32,
    rng=None,
    shuffle: bool = True,
    query: str = "motion",
) -> tuple[np.ndarray, float]:
    """R-precision top-1..top_k and MM-Dist for matched pairs (text_emb[i], motion_emb[i]).

    Pairs are split into pools of ``batch_size`` (after a random shuffle); in each pool every motion
    (``query="motion"``, the papers' wording) or every text (``query="text"``, the released T2M code)
    is ranked against the pool's texts (motions) by Euclidean distance. Returns (hits (top_k,), mm_dist),
    where hits[k-1] is the fraction of queries whose true partner is among the k nearest (exact distance
    ties, e.g. two motions with the same caption, are broken at random in expectation) and mm_dist is
    the mean matched distance over the same pairs.
    """
    t, m = _as_np(text_emb), _as_np(motion_emb)
    if t.shape != m.shape or t.ndim != 2:
        raise ValueError(f"text and motion embeddings must both be (N, D); got {t.shape} and {m.shape}")
    if query not in ("motion", "text"):
        raise ValueError("query must be 'motion' or 'text'")
    hits = np.zeros(top_k)
    dist_sum, count = 0.0, 0
    for idx in _batches(len(t), batch_size, rng, shuffle):
        dist = euclidean_distance_matrix(m[idx], t[idx])  # (B motions, B texts)
        if query == "text":
            dist = dist.T
        own = np.diagonal(dist)[:, None]
        # Candidates strictly closer than the true partner, and those at exactly its distance (itself
        # included; duplicate captions give exact ties). Ties are broken at random, in expectation:
        # P(true partner within the k nearest) = clip((k - closer) / tied, 0, 1).
        closer = (dist < own).sum(axis=1)
        tied = (dist == own).sum(axis=1)
        for k in range(top_k):
            hits[k] += np.clip((k + 1 - closer) / tied, 0.0, 1.0).sum()
        dist_sum += float(np.diagonal(dist).sum())
        count += len(idx)
    return hits / count, dist_sum / count


def matching_score(text_emb, motion_emb) -> float:
    """MM-Dist: mean Euclidean distance between each motion and its own text."""
    t, m = _as_np(text_emb).astype(np.float64), _as_np(motion_emb).astype(np.float64)
    if t.shape != m.shape:
        raise ValueError(f"shape mismatch {t.shape} vs {m.shape}")
    return float(np.linalg.norm(t - m, axis=1).mean())


def diversity(emb, times: int = 300, rng=None) -> float:
    """Mean distance between ``times`` random pairs (two draws without replacement, as T2M)."""
    x = _as_np(emb).astype(np.float64)
    if x.ndim != 2:
        raise ValueError(f"embeddings must be (N, D), got {x.shape}")
    if len(x) < times:
        raise ValueError(f"diversity with {times} pairs needs at least {times} samples, got {len(x)}")
    rng = _rng(rng)
    first = rng.choice(len(x), times, replace=False)
    second = rng.choice(len(x), times, replace=False)
    return float(np.linalg.norm(x[first] - x[second], axis=1).mean())


def multimodality(emb, times: int = 10, rng=None) -> float:
    """Mean distance between ``times`` random pairs of generations per text; emb (n_texts, n_repeats, D)."""
    x = _as_np(emb).astype(np.float64)
    if x.ndim != 3:
        raise ValueError(f"embeddings must be (n_texts, n_repeats, D), got {x.shape}")
    if x.shape[1] < times:
        raise ValueError(f"multimodality with {times} pairs needs at least {times} repeats, got {x.shape[1]}")
    rng = _rng(rng)
    first = rng.choice(x.shape[1], times, replace=False)
    second = rng.choice(x.shape[1], times, replace=False)
    return float(np.linalg.norm(x[:, first] - x[:, second], axis=2).mean())


def action_multimodality(emb, labels, times: int = 20, rng=None) -> float:
    """Action-to-motion multimodality: for every action present, ``times`` random same-action pairs."""
    x, y = _as_np(emb).astype(np.float64), _as_np(labels).astype(np.int64)
    rng = _rng(rng)
    dists = []
    for label in np.unique(y):
        members = np.flatnonzero(y == label)
        first = rng.choice(members, times, replace=True)
        second = rng.choice(members, times, replace=True)
        dists.append(np.linalg.norm(x[first] - x[second], axis=1))
    return float(np.concatenate(dists).mean())


def accuracy(pred, labels) -> float:
    """Fraction correct; ``pred`` is either labels (N,) or logits/probabilities (N, C)."""
    p, y = _as_np(pred), _as_np(labels)
    if p.ndim == 2:
        p = p.argmax(axis=1)
    if p.shape != y.shape:
        raise ValueError(f"shape mismatch {p.shape} vs {y.shape}")
    return float((p == y).mean())


# --------------------------------------------------------------------------------------------------
# Reconstruction
# --------------------------------------------------------------------------------------------------


def similarity_transform(source, target) -> np.ndarray:
    """Procrustes alignment with scale: the s R x + t closest to ``target``, applied to ``source``.

    source, target: (..., J, 3). Each leading index (e.g. each frame) is aligned independently.
    """
    x, y = _as_np(source).astype(np.float64), _as_np(target).astype(np.float64)
    if x.shape != y.shape or x.shape[-1] != 3:
        raise ValueError(f"need matching (..., J, 3) arrays, got {x.shape} and {y.shape}")
    mu_x, mu_y = x.mean(-2, keepdims=True), y.mean(-2, keepdims=True)
    x0, y0 = x - mu_x, y - mu_y
    k = np.swapaxes(x0, -1, -2) @ y0  # (..., 3, 3) cross-covariance
    u, s, vt = np.linalg.svd(k)
    d = np.sign(np.linalg.det(u @ vt))  # reflection fix: det(R) = +1
    d = np.where(d == 0, 1.0, d)
    z = np.ones(s.shape)
    z[..., -1] = d
    # rotation in the row-vector convention: x0 @ rot ~ y0
    rot = (u * z[..., None, :]) @ vt
    var_x = (x0 * x0).sum(axis=(-1, -2))
    scale = (s * z).sum(-1) / np.where(var_x > 0, var_x, 1.0)
    return scale[..., None, None] * (x0 @ rot) + mu_y


def mpjpe(pred, target, *, align_root: bool = True, root: int = 0) -> np.ndarray:
    """Per-frame mean joint error (T,) (input units); root-relative when ``align_root``. Inputs (T, J, 3)."""
    p, t = _as_np(pred).astype(np.float64), _as_np(target).astype(np.float64)
    if p.shape != t.shape:
        raise ValueError(f"shape mismatch {p.shape} vs {t.shape}")
    if align_root:
        p = p - p[..., root : root + 1, :]
        t = t - t[..., root : root + 1, :]
    return np.linalg.norm(p - t, axis=-1).mean(-1)


def pa_mpjpe(pred, target) -> np.ndarray:
    """Per-frame mean joint error (T,) after per-frame Procrustes alignment with scale."""
    t = _as_np(target).astype(np.float64)
    aligned = similarity_transform(pred, t)
    return np.linalg.norm(aligned - t, axis=-1).mean(-1)


def accel_error(pred, target) -> np.ndarray:
    """Per-frame (T-2,) mean joint error of the second differences x[t-1] - 2 x[t] + x[t+1]."""
    p, t = _as_np(pred).astype(np.float64), _as_np(target).astype(np.float64)
    if p.shape != t.shape:
        raise ValueError(f"shape mismatch {p.shape} vs {t.shape}")
    acc_p = p[:-2] - 2.0 * p[1:-1] + p[2:]
    acc_t = t[:-2] - 2.0 * t[1:-1] + t[2:]
    return np.linalg.norm(acc_p - acc_t, axis=-1).mean(-1)


def reconstruction_errors(preds: Sequence, targets: Sequence, *, unit_scale: float = 1000.0) -> dict:
    """MPJPE (root-relative), global MPJPE, PA-MPJPE and acceleration error over sequences of joints.

    preds/targets: sequences of (T_i, J, 3) arrays in metres. Every frame counts once (the accel error
    over the T_i - 2 interior frames), as MLD's reconstruction metric does. Returns millimetres
    (``unit_scale`` = 1000): {"MPJPE", "MPJPE_global", "PA-MPJPE", "ACCEL"}.
    """
    if len(preds) != len(targets) or not len(preds):
        raise ValueError("need the same, non-zero number of predicted and target sequences")
    sums = {"MPJPE": 0.0, "MPJPE_global": 0.0, "PA-MPJPE": 0.0, "ACCEL": 0.0}
    frames = accel_frames = 0
    for p, t in zip(preds, targets):
        sums["MPJPE"] += float(mpjpe(p, t).sum())
        sums["MPJPE_global"] += float(mpjpe(p, t, align_root=False).sum())
        sums["PA-MPJPE"] += float(pa_mpjpe(p, t).sum())
        frames += len(t)
        if len(t) > 2:
            sums["ACCEL"] += float(accel_error(p, t).sum())
            accel_frames += len(t) - 2
    out = {k: v / frames * unit_scale for k, v in sums.items() if k != "ACCEL"}
    out["ACCEL"] = sums["ACCEL"] / accel_frames * unit_scale if accel_frames else float("nan")
    return out


# --------------------------------------------------------------------------------------------------
# Replications
# --------------------------------------------------------------------------------------------------


def mean_ci(values) -> tuple[float, float]:
    """(mean, 95% confidence half-width) over replications: 1.96 * np.std(values) / sqrt(n)."""
    v = np.asarray(values, dtype=np.float64).ravel()
    if v.size == 0:
        raise ValueError("no values")
    return float(v.mean()), float(1.96 * v.std() / np.sqrt(v.size))
