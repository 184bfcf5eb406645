"""Metric functions on inputs with known answers."""

from __future__ import annotations

import numpy as np
import pytest

from mld_core.eval import metrics as M


def _random_rotation(rng) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def _random_spd(rng, d: int) -> np.ndarray:
    a = rng.normal(size=(d, d))
    return a @ a.T / d + 0.1 * np.eye(d)


def test_sqrtm_psd_squares_back():
    rng = np.random.default_rng(0)
    a = _random_spd(rng, 6)
    root = M.sqrtm_psd(a)
    np.testing.assert_allclose(root @ root, a, atol=1e-10)
    np.testing.assert_allclose(root, root.T, atol=1e-12)


def test_fid_of_a_set_with_itself_is_zero():
    x = np.random.default_rng(1).normal(size=(500, 16))
    assert M.fid(x, x) == pytest.approx(0.0, abs=1e-8)


def test_frechet_distance_matches_closed_form_for_commuting_covariances():
    # Diagonal covariances commute: tr sqrt(S1 S2) = sum sqrt(a_i b_i).
    mu1, mu2 = np.array([0.0, 1.0, 2.0]), np.array([1.0, -1.0, 2.5])
    a, b = np.array([1.0, 4.0, 0.25]), np.array([9.0, 1.0, 1.0])
    expected = ((mu1 - mu2) ** 2).sum() + (a + b - 2 * np.sqrt(a * b)).sum()
    assert M.frechet_distance(mu1, np.diag(a), mu2, np.diag(b)) == pytest.approx(expected, rel=1e-12)


def test_frechet_distance_general_covariances_matches_definition():
    # Non-commuting case against the definition, with sqrt(S1 S2) = S1^(1/2) (S1^(1/2) S2 S1^(1/2))^(1/2) S1^(-1/2).
    rng = np.random.default_rng(2)
    s1, s2 = _random_spd(rng, 5), _random_spd(rng, 5)
    mu1, mu2 = rng.normal(size=5), rng.normal(size=5)
    r1 = M.sqrtm_psd(s1)
    covmean = r1 @ M.sqrtm_psd(r1 @ s2 @ r1) @ np.linalg.inv(r1)
    np.testing.assert_allclose(covmean @ covmean, s1 @ s2, atol=1e-9)  # it is a square root of S1 S2
    expected = ((mu1 - mu2) ** 2).sum() + np.trace(s1 + s2 - 2 * covmean)
    assert M.frechet_distance(mu1, s1, mu2, s2) == pytest.approx(expected, rel=1e-10)
    # symmetric in its arguments
    assert M.frechet_distance(mu2, s2, mu1, s1) == pytest.approx(expected, rel=1e-8)


def test_fid_of_two_sampled_gaussians_approaches_closed_form():
    rng = np.random.default_rng(3)
    d, n = 4, 200_000
    mu_a, mu_b = np.zeros(d), np.array([1.0, 0.0, -0.5, 0.0])
    sd_a, sd_b = np.array([1.0, 2.0, 0.5, 1.0]), np.array([1.0, 1.0, 1.0, 3.0])
    xa = mu_a + sd_a * rng.normal(size=(n, d))
    xb = mu_b + sd_b * rng.normal(size=(n, d))
    expected = ((mu_a - mu_b) ** 2).sum() + ((sd_a - sd_b) ** 2).sum()  # = 1.25 + 5.25 = 6.5
    assert M.fid(xa, xb) == pytest.approx(expected, rel=0.02)
    assert M.fid(xa, xa[::-1]) == pytest.approx(0.0, abs=1e-8)


def test_kid_is_near_zero_for_same_distribution_and_positive_otherwise():
    rng = np.random.default_rng(4)
    a, b = rng.normal(size=(400, 8)), rng.normal(size=(400, 8))
    same, _ = M.kid(a, b, n_subsets=10, subset_size=200, rng=0)
    shifted, _ = M.kid(a, b + 1.0, n_subsets=10, subset_size=200, rng=0)
    assert abs(same) < 0.02
    assert shifted > 0.3


def test_r_precision_of_a_perfect_evaluator_is_one():
    rng = np.random.default_rng(5)
    text = rng.normal(size=(320, 32))
    hits, mm_dist = M.r_precision(text, text.copy(), rng=0)
    np.testing.assert_allclose(hits, [1.0, 1.0, 1.0])
    assert mm_dist == pytest.approx(0.0, abs=1e-6)
    hits_t, _ = M.r_precision(text, text + 0.01, rng=0, query="text")
    np.testing.assert_allclose(hits_t, [1.0, 1.0, 1.0])


def test_r_precision_of_a_random_evaluator_is_chance():
    rng = np.random.default_rng(6)
    n = 32 * 2000
    hits, _ = M.r_precision(rng.normal(size=(n, 8)), rng.normal(size=(n, 8)), rng=1)
    np.testing.assert_allclose(hits, np.array([1, 2, 3]) / 32, atol=0.006)


def test_r_precision_counts_ranks_on_a_hand_example():
    # 4 pairs in one pool of 4: motions 0, 1 exact; motion 2 is closest to text 3, then its own;
    # motion 3 is far from its own text (rank 4).
    text = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0], [10.0, 10.0]])
    motion = np.array([[0.0, 0.0], [10.0, 0.0], [6.0, 10.0], [-10.0, -10.0]])
    hits, mm_dist = M.r_precision(text, motion, batch_size=4, shuffle=False, top_k=4)
    np.testing.assert_allclose(hits, [0.5, 0.75, 0.75, 1.0])
    expected = (0 + 0 + 6 + np.hypot(20, 20)) / 4
    assert mm_dist == pytest.approx(expected)
    assert M.matching_score(text, motion) == pytest.approx(expected)


def test_r_precision_breaks_exact_ties_at_random_in_expectation():
    # 4 motions, texts 0 and 1 identical (same caption): motion 0 and motion 1 each tie with 2 texts at
    # distance 0 -> P(top-1) = 1/2, P(top-2) = 1. Motions 2, 3 are exact and unique.
    text = np.array([[0.0, 0.0], [0.0, 0.0], [10.0, 0.0], [0.0, 10.0]])
    hits, _ = M.r_precision(text, text.copy(), batch_size=4, shuffle=False)
    np.testing.assert_allclose(hits, [(0.5 + 0.5 + 1 + 1) / 4, 1.0, 1.0])


def test_r_precision_drops_the_incomplete_last_pool_and_rejects_too_few():
    x = np.random.default_rng(7).normal(size=(70, 4))
    hits, _ = M.r_precision(x, x, rng=0)  # 2 pools of 32, 6 pairs dropped
    np.testing.assert_allclose(hits, 1.0)
    with pytest.raises(ValueError, match="at least 32"):
        M.r_precision(x[:10], x[:10])


def test_diversity_and_multimodality_on_known_geometry():
    # Points on two antipodal spots: pairs are either 0 or 2 apart.
    x = np.zeros((600, 3))
    x[:300, 0] = 1.0
    x[300:, 0] = -1.0
    div = M.diversity(x, times=300, rng=0)
    assert 0.7 < div < 1.3  # about half of the pairs cross: expected value 1.0
    # identical generations per text -> multimodality 0; unit circle spread -> positive
    same = np.repeat(np.random.default_rng(0).normal(size=(5, 1, 4)), 30, axis=1)
    assert M.multimodality(same, times=10, rng=0) == 0.0
    spread = np.random.default_rng(1).normal(size=(5, 30, 4))
    assert M.multimodality(spread, times=10, rng=0) > 1.0
    with pytest.raises(ValueError):
        M.diversity(x[:100], times=300)


def test_action_multimodality_is_zero_for_constant_actions_and_accuracy_counts():
    emb = np.array([[0.0, 0.0]] * 5 + [[3.0, 4.0]] * 5)
    labels = np.array([0] * 5 + [1] * 5)
    assert M.action_multimodality(emb, labels, times=20, rng=0) == 0.0
    assert M.accuracy(np.array([0, 1, 1, 0]), np.array([0, 1, 0, 0])) == 0.75
    logits = np.array([[2.0, 1.0], [0.0, 1.0], [5.0, -1.0]])
    assert M.accuracy(logits, np.array([0, 1, 1])) == pytest.approx(2 / 3)


def test_procrustes_recovers_rotated_scaled_shifted_copy():
    rng = np.random.default_rng(8)
    target = rng.normal(size=(10, 22, 3))  # 10 frames, 22 joints
    source = np.empty_like(target)
    for f in range(10):
        rot, scale, shift = _random_rotation(rng), rng.uniform(0.5, 2.0), rng.normal(size=3)
        # source = transformed copy of target; alignment must undo it
        source[f] = scale * target[f] @ rot.T + shift
    aligned = M.similarity_transform(source, target)
    np.testing.assert_allclose(aligned, target, atol=1e-9)
    assert M.pa_mpjpe(source, target).max() < 1e-9
    assert M.mpjpe(source, target).mean() > 0.1  # without alignment the error is large


def test_procrustes_does_not_reflect():
    rng = np.random.default_rng(9)
    target = rng.normal(size=(22, 3))
    mirrored = target * np.array([-1.0, 1.0, 1.0])
    # a mirror image cannot be undone by a proper rotation: error stays clearly positive
    assert M.pa_mpjpe(mirrored[None], target[None])[0] > 0.05


def test_mpjpe_root_alignment_and_units():
    t = np.zeros((3, 22, 3))
    p = t + np.array([0.5, 0.0, 0.0])  # whole body shifted by 0.5 m
    assert M.mpjpe(p, t).max() == 0.0
    np.testing.assert_allclose(M.mpjpe(p, t, align_root=False), 0.5)
    p2 = t.copy()
    p2[:, 5] += np.array([0.0, 0.022, 0.0])  # one joint off by 22 mm -> 1 mm mean over 22 joints
    errors = M.reconstruction_errors([p2], [t])
    assert errors["MPJPE"] == pytest.approx(1.0)
    assert errors["MPJPE_global"] == pytest.approx(1.0)


def test_accel_error_of_constant_velocity_motion_is_zero():
    rng = np.random.default_rng(10)
    start, vel = rng.normal(size=(22, 3)), rng.normal(size=(22, 3))
    frames = np.arange(30)[:, None, None]
    moving = start + vel * frames  # constant velocity
    still = np.repeat(start[None], 30, axis=0)
    np.testing.assert_allclose(M.accel_error(moving, still), 0.0, atol=1e-12)
    # a pure drift at constant velocity on top of a target leaves the acceleration error at 0
    target = rng.normal(size=(30, 22, 3))
    assert M.reconstruction_errors([target + vel * frames], [target])["ACCEL"] == pytest.approx(0.0, abs=1e-9)
    # one bumped frame: second differences -2 d, d, d around it -> known error
    bumped = target.copy()
    bumped[10] += np.array([0.0, 0.001, 0.0])  # 1 mm on every joint
    acc = M.accel_error(bumped, target)
    np.testing.assert_allclose(acc[[8, 9, 10]], [0.001, 0.002, 0.001])
    assert M.reconstruction_errors([bumped], [target])["ACCEL"] == pytest.approx(4.0 / 28)


def test_reconstruction_errors_weight_frames_equally():
    t1, t2 = np.zeros((4, 22, 3)), np.zeros((8, 22, 3))
    p1 = t1.copy()
    p1[:, 3] += [0.0, 0.0, 0.022]  # 1 mm per frame over 4 frames, 0 over the other 8
    out = M.reconstruction_errors([p1, t2], [t1, t2])
    assert out["MPJPE"] == pytest.approx(4 / 12)


def test_mean_ci_matches_hand_computation():
    values = [1.0, 2.0, 3.0, 4.0]
    mean, ci = M.mean_ci(values)
    # std (ddof 0) = sqrt(1.25); 1.96 * sqrt(1.25) / 2 = 1.09567...
    assert mean == 2.5
    assert ci == pytest.approx(1.96 * np.sqrt(1.25) / 2)
    assert ci == pytest.approx(1.0956733, rel=1e-6)
    assert M.mean_ci([5.0]) == (5.0, 0.0)


def test_largest_joint_jerk_and_a_seams_window():
    from mld_core.eval.quality import largest_joint_jerk, seam_jerk

    t = np.arange(20, dtype=np.float64) / 20.0
    joints = np.zeros((20, 22, 3))
    joints[:, 3, 0] = t ** 3  # jerk 6 m/s^3 throughout for one joint
    joints[:, 5, 1] = 0.5 * t ** 3  # 3 m/s^3 for another
    np.testing.assert_allclose(largest_joint_jerk(joints), np.full(17, 6.0), rtol=1e-9)
    joints[12, 7, 2] = 0.01  # a 1 cm pop at frame 12: windows 9-12 see it
    jerk = largest_joint_jerk(joints)
    assert jerk[9:13].min() > 6.0 and np.allclose(jerk[:9], 6.0) and np.allclose(jerk[13:], 6.0)
    assert seam_jerk(joints, 12, 1) == jerk[9:15].max()  # from 3 frames before the fade to 2 after it
    assert seam_jerk(joints, 2, 1) == pytest.approx(6.0)  # a window that ends before the pop


def test_only_seams_rougher_than_real_motion_get_a_line():
    from mld_core.take_report import seam_lines, seam_records

    seams = [(1, 640.0, True), (2, 2559.4, False)]
    prompts = ["a person walks forward", "a person waves the right hand", "a person bows"]
    assert seam_lines(seams, prompts) == ['the seam into segment 3 ("a person bows") jerks 2,559 m/s^3, 2.7x real '
                                          "motion's 95th percentile: check it, or try another seed"]
    assert seam_lines(None, prompts) == [] and seam_lines(seams[:1], prompts) == []
    assert seam_records(seams) == [{"segment": 2, "jerk": 640.0, "within_real": True},
                                   {"segment": 3, "jerk": 2559.4, "within_real": False}]
