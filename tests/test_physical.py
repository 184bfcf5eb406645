"""Physical checks (mld_core.eval.physical) on synthetic motions built from a real standing pose, on their
mirror images, and on the real Bandai Namco fixture clips; plus a smoke run of research/side_accuracy.py."""

from __future__ import annotations

import importlib.util
import json

import numpy as np
import pytest

from mld_core.eval import physical as P
from mld_core.motion.features import mirror_joints

FPS = 20
ARM = {"left": (16, 18, 20), "right": (17, 19, 21)}  # shoulder, elbow, wrist
UPPER_BODY = [3, 6, 9, 12, 13, 14, 15, 16, 17, 18, 19, 20, 21]
LEGS = {"left": (4, 7, 10), "right": (5, 8, 11)}  # knee, ankle, foot


@pytest.fixture(scope="module")
def rest(request) -> np.ndarray:
    """Frame 0 of HumanML3D's sample 012314: a real person standing, arms down, facing +Z, left on +X."""
    from pathlib import Path

    path = Path(request.config.rootpath) / "tests" / "fixtures" / "humanml3d" / "new_joints_012314.npy"
    pose = np.load(path)[0].astype(np.float64)  # (22, 3)
    assert pose[1, 0] > pose[2, 0] and pose[16, 0] > pose[17, 0]  # left hip and shoulder on +X
    return pose


def still(pose: np.ndarray, seconds: float = 4.0) -> np.ndarray:
    return np.repeat(pose[None], int(seconds * FPS), axis=0)  # (T, 22, 3)


def rot_y(deg):
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_x(deg):
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_z(deg):
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def ramp(T: int, up: tuple[float, float], down: tuple[float, float] | None = None) -> np.ndarray:
    """0 -> 1 between seconds up[0]..up[1], back to 0 between down[0]..down[1] (T,)."""
    t = np.arange(T) / FPS
    a = np.clip((t - up[0]) / (up[1] - up[0]), 0, 1)
    if down is not None:
        a = a * (1 - np.clip((t - down[0]) / (down[1] - down[0]), 0, 1))
    return a


def raise_arm(joints: np.ndarray, side: str, amount: np.ndarray) -> np.ndarray:
    """Swing the arm sideways and up about its shoulder: amount 1 = pointing straight up (per frame)."""
    out = joints.copy()
    sh, el, wr = ARM[side]
    sign = 1.0 if side == "left" else -1.0  # left arm goes up through +X, right through -X
    for t, a in enumerate(amount):
        R = rot_z(sign * 180.0 * a)
        for j in (el, wr):
            out[t, j] = out[t, sh] + R @ (joints[t, j] - joints[t, sh])
    return out


def wave(joints: np.ndarray, side: str, amount: np.ndarray, hz: float = 1.5, amp: float = 0.08) -> np.ndarray:
    """Raised arm plus a sideways swing of the wrist while it is up."""
    out = raise_arm(joints, side, amount)
    t = np.arange(len(out)) / FPS
    out[:, ARM[side][2], 0] += amp * np.sin(2 * np.pi * hz * t) * (amount > 0.9)
    return out


def turn_in_place(joints: np.ndarray, degrees: np.ndarray) -> np.ndarray:
    """Rotate the whole body about the vertical through the pelvis by degrees[t] (positive about +Y)."""
    out = joints.copy()
    for t, d in enumerate(degrees):
        c = joints[t, 0] * np.array([1.0, 0.0, 1.0])
        out[t] = (joints[t] - c) @ rot_y(d).T + c
    return out


def walk(pose: np.ndarray, velocity, seconds: float = 4.0, step_s: float = 1.0, stance: float = 0.5,
         lift: float = 0.1, planted: bool = True) -> np.ndarray:
    """The pose travelling at ``velocity`` (m/s, xz) without turning. Each foot (ankle + toe) stands still
    for ``stance`` of the step cycle and swings forward, ``lift`` m high at mid-swing, for the rest, the
    right foot half a cycle after the left: stance 0.5 is a walk (always a foot down), less gives both feet
    in the air at once (a run). ``planted=False``: the feet glide along with the body (no steps at all)."""
    T = int(seconds * FPS)
    t = np.arange(T) / FPS
    v = np.array([velocity[0], 0.0, velocity[1]])
    out = pose[None] + t[:, None, None] * v  # (T, 22, 3)
    if planted:
        for side, shift in (("left", 0.0), ("right", 0.5)):
            phase = t / step_s + shift
            swing = np.clip((phase % 1.0 - stance) / (1.0 - stance), 0.0, 1.0)  # 0 in stance, 0 -> 1 in swing
            travelled = (np.floor(phase) + swing - shift + 0.5 * (1 - stance)) * step_s  # average = t
            height = lift * np.sin(np.pi * swing)
            for j in LEGS[side][1:]:
                out[:, j] = pose[j] + travelled[:, None] * v
                out[:, j, 1] += height
    return out


def walk_turn(pose: np.ndarray, degrees: np.ndarray, speed: float = 1.2) -> np.ndarray:
    """A planted-feet walk whose path follows the facing, which turns by degrees[t] (positive about +Y)."""
    local = walk(pose, (0.0, speed), seconds=len(degrees) / FPS)  # (T, 22, 3) straight along +Z
    root = local[:, :1] * np.array([1.0, 0.0, 1.0])
    step = np.stack([rot_y(d) @ np.array([0.0, 0.0, speed / FPS]) for d in degrees])  # (T, 3)
    path = np.concatenate([np.zeros((1, 3)), np.cumsum(step[:-1], axis=0)])  # (T, 3)
    return np.stack([(local[t] - root[t]) @ rot_y(d).T + path[t] for t, d in enumerate(degrees)])


def bow_motion(pose: np.ndarray, degrees: float = 60.0, back_up: bool = True) -> np.ndarray:
    """Upper body pitched forward about the pelvis (positive about +X moves the head towards +Z)."""
    T = 4 * FPS
    amount = ramp(T, (0.5, 1.5), (2.5, 3.5) if back_up else None)
    out = still(pose)
    pivot = pose[0]
    for t, a in enumerate(amount):
        out[t, UPPER_BODY] = (pose[UPPER_BODY] - pivot) @ rot_x(degrees * a).T + pivot
    return out


# ---- hands ------------------------------------------------------------------------------------------------


def test_standing_still_shows_nothing(rest):
    v = P.verdicts(still(rest))
    assert v == {"raised": "none", "waving": "none", "turn": "none", "locomotion": "stand", "drift": "none",
                 "bow": False, "kick": "none", "jump": False, "get_low": False, "on_ground": False, "crawl": False,
                 "reach_floor": False, "inverted": False, "stand_up": False, "climb": False, "throw": False}


def test_raised_right_hand_and_its_mirror(rest):
    T = 4 * FPS
    j = raise_arm(still(rest), "right", ramp(T, (0.5, 1.0), (3.0, 3.5)))
    r = P.raised_hand(j)
    assert r.verdict == "right"
    assert r.detail["right_above_head_m"] > 0.1 and r.detail["left_above_shoulder_m"] < -0.3
    assert P.waving(j).verdict == "none"  # raising and lowering is not waving
    assert P.passes(j, "raise-up-right-hand") and not P.passes(j, "raise-up-left-hand")
    m = mirror_joints(j)
    assert P.raised_hand(m).verdict == "left"
    assert P.passes(m, "raise-up-left-hand") and not P.passes(m, "raise-up-right-hand")
    assert P.detected_side(P.classify(m), "raise-up-right-hand") == "left"


def test_a_hand_raised_too_briefly_does_not_count(rest):
    T = 4 * FPS
    t = np.arange(T)
    j = raise_arm(still(rest), "right", ((t >= 40) & (t < 42)).astype(float))  # up for 0.1 s
    assert P.raised_hand(j).verdict == "none"


def test_both_hands(rest):
    T = 4 * FPS
    a = ramp(T, (0.5, 1.0), (3.0, 3.5))
    j = raise_arm(raise_arm(still(rest), "right", a), "left", a)
    assert P.raised_hand(j).verdict == "both"
    assert P.passes(j, "raise-up-both-hands") and not P.passes(j, "raise-up-left-hand")


def test_waving_right_hand_and_its_mirror(rest):
    T = 5 * FPS
    j = wave(still(rest, 5), "right", ramp(T, (0.5, 1.0), (4.0, 4.5)))
    w = P.waving(j)
    assert w.verdict == "right" and w.detail["right_swings"] >= 8 and w.detail["left_swings"] == 0
    assert P.passes(j, "wave-right-hand") and not P.passes(j, "wave-left-hand")
    m = mirror_joints(j)
    assert P.waving(m).verdict == "left" and P.passes(m, "wave-left-hand")
    # A swing smaller than the hysteresis is not a wave.
    small = wave(still(rest, 5), "right", ramp(T, (0.5, 1.0), (4.0, 4.5)), amp=0.01)
    assert P.waving(small).verdict == "none"


# ---- turning and travelling ---------------------------------------------------------------------------------


def test_left_turn_is_positive_yaw_towards_the_left_side(rest):
    T = 4 * FPS
    j = turn_in_place(still(rest), 90.0 * ramp(T, (1.0, 3.0)))
    c = P.turn(j)
    assert c.verdict == "left" and c.value == pytest.approx(90.0, abs=1.0)
    # The body ends up facing where its own left side pointed at frame 0.
    _, forward = P.body_frame(j)
    left0 = rest[1] - rest[2]
    left0[1] = 0.0
    assert forward[-1] @ (left0 / np.linalg.norm(left0)) > 0.95
    m = mirror_joints(j)
    assert P.turn(m).verdict == "right" and P.turn(m).value == pytest.approx(-90.0, abs=1.0)
    small = turn_in_place(still(rest), 20.0 * ramp(T, (1.0, 3.0)))
    assert P.turn(small).verdict == "none"


def test_walk_turn_labels(rest):
    T = 4 * FPS
    j = walk_turn(rest, 90.0 * ramp(T, (1.5, 2.5)))
    assert P.locomotion(j).verdict == "walk" and P.turn(j).verdict == "left"
    assert P.passes(j, "walk-turn-left") and not P.passes(j, "walk-turn-right")
    assert P.passes(mirror_joints(j), "walk-turn-right")


def test_walk_forward(rest):
    j = walk(rest, (0.0, 1.2))
    c = P.locomotion(j)
    assert c.verdict == "walk"
    assert c.value == pytest.approx(1.2, rel=0.05) and c.detail["forward_mps"] > 1.1
    assert c.detail["flight_fraction"] == 0.0
    assert P.turn(j).verdict == "none" and P.drift(j).verdict == "none"
    assert P.passes(j, "walk") and not P.passes(j, "run") and not P.passes(j, "walk-back")


def test_walk_backward_run_and_glide(rest):
    back = walk(rest, (0.0, -0.8))
    assert P.locomotion(back).verdict == "backward" and P.passes(back, "walk-back")
    fast = walk(rest, (0.0, 3.0), step_s=0.7, stance=0.35)
    assert P.locomotion(fast).verdict == "run" and P.passes(fast, "run") and P.passes(fast, "dash")
    # A slow run is told from a walk by its flight phase: both feet off the ground at once.
    jog = walk(rest, (0.0, 1.6), step_s=0.7, stance=0.35)
    c = P.locomotion(jog)
    assert c.verdict == "run" and c.value < P.RUN_MIN_SPEED <= 2.0
    assert P.RUN_MIN_FLIGHT <= c.detail["flight_fraction"] < 0.35
    # The same steps with the feet sliding over the floor instead of lifting: a walk.
    shuffle = walk(rest, (0.0, 1.6), step_s=0.7, stance=0.35, lift=0.0)
    assert P.locomotion(shuffle).verdict == "walk" and P.locomotion(shuffle).detail["flight_fraction"] == 0.0
    # Travelling without any steps is a glide, neither a walk nor a run.
    glide = walk(rest, (0.0, 1.2), planted=False)
    assert P.locomotion(glide).verdict == "glide" and not P.passes(glide, "walk")
    assert P.locomotion(walk(rest, (0.0, 3.0), planted=False)).verdict == "glide"


def test_drift(rest):
    # 30 degrees to the performer's left (+X) while facing +Z.
    left = walk(rest, (1.0 * np.sin(np.radians(30)), 1.0 * np.cos(np.radians(30))))
    d = P.drift(left)
    assert d.verdict == "left" and d.value == pytest.approx(30.0, abs=1.0)
    assert P.passes(left, "walk-left") and not P.passes(left, "walk-right")
    assert P.drift(mirror_joints(left)).verdict == "right"
    assert P.passes(mirror_joints(left), "walk-right")
    assert P.locomotion(walk(rest, (0.1, 0.0))).verdict == "stand"  # 0.1 m/s is standing about


# ---- bow, kick ------------------------------------------------------------------------------------------------


def test_bow_leans_forward_and_comes_back(rest):
    j = bow_motion(rest)
    c = P.bow(j)
    assert c.verdict is True and c.value > 50 and c.detail["head_drop_m"] > 0.1
    assert P.passes(j, "bow") and P.passes(mirror_joints(j), "bow")
    assert P.bow(bow_motion(rest, back_up=False)).verdict is False  # stays down
    assert P.bow(bow_motion(rest, degrees=-40.0)).verdict is False  # leaning back
    assert P.bow(bow_motion(rest, degrees=10.0)).verdict is False  # a nod of the torso


def test_kick_right_and_its_mirror(rest):
    j = still(rest)
    up = slice(30, 40)  # half a second with the right foot high in front
    for k in LEGS["right"][1:]:
        j[up, k] = rest[0] + np.array([-0.1, 0.0, 0.6]) + (0.0, 0.9 - rest[0, 1], 0.0)
    assert P.kick(j).verdict == "right" and P.passes(j, "kick")
    assert P.kick(mirror_joints(j)).verdict == "left"
    behind = still(rest)
    behind[up, 8] = rest[0] + np.array([-0.1, -0.2, -0.4])  # heel flicked up behind, as when running
    assert P.kick(behind).verdict == "none"


# ---- labels and errors ---------------------------------------------------------------------------------------


def test_labels_sides_and_errors(rest):
    assert P.side_of("wave-left-hand") == "left" and P.side_of("walk-turn-right") == "right"
    assert P.side_of("walk-left") == "left" and P.side_of("bow") is None
    assert P.side_check_for("wave-right-hand") == "raised" and P.side_check_for("walk-turn-left") == "turn"
    assert P.side_check_for("walk-right") == "drift" and P.side_check_for("run") is None
    assert P.mirror_label("raise-up-left-hand") == "raise-up-right-hand" and P.mirror_label("bow") == "bow"
    assert P.expected_for("punch") is None and P.expected_for("wave-both-hands") == {"waving": {"both"}}
    for label in P.CHECKED_LABELS:
        assert set(P.expected_for(label)) <= set(P.CHECKS)
    with pytest.raises(ValueError, match="no physical check"):
        P.passes(still(rest), "punch")
    with pytest.raises(ValueError, match=r"\(T, 22, 3\)"):
        P.classify(np.zeros((10, 21, 3)))
    with pytest.raises(ValueError, match="at least 2 frames"):
        P.classify(rest[None])
    bad = still(rest)
    bad[3, 4, 1] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        P.classify(bad)
    c = P.classify(still(rest))["raised"].as_dict()
    assert c["verdict"] == "none" and isinstance(c["value"], float)


# ---- real clips -------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def bandai_clips(request):
    """The real Bandai Namco fixture clips (2 s crops), canonicalised like the prepared data."""
    from pathlib import Path

    from mld_core.data import bandai
    from mld_core.motion.features import canonical_joints

    folder = Path(request.config.rootpath) / "tests" / "fixtures" / "bandai"
    clips = {p.stem: canonical_joints(bandai.clip_joints(p.read_bytes())) for p in sorted(folder.glob("*.bvh"))}
    if not clips:
        pytest.skip(f"no Bandai fixture clips in {folder}")
    return clips


@pytest.mark.parametrize("stem,label", [("dataset-2_walk-turn-left_normal_027", "walk-turn-left"),
                                        ("dataset-2_wave-right-hand_normal_026", "wave-right-hand")])
def test_real_clips_pass_their_label_and_mirrors_the_mirrored_label(bandai_clips, stem, label):
    if stem not in bandai_clips:
        pytest.skip(f"fixture {stem}.bvh missing")
    j = bandai_clips[stem]
    assert P.passes(j, label), P.failed_checks(j, label)
    assert not P.passes(j, P.mirror_label(label))
    m = mirror_joints(j)
    assert P.passes(m, P.mirror_label(label)) and not P.passes(m, label)
    assert P.detected_side(P.classify(m), P.mirror_label(label)) == P.side_of(P.mirror_label(label))


def test_real_bye_clip_raises_the_right_hand(bandai_clips):
    # dataset-1_bye_normal_001 waves slowly at shoulder height: only its first 2 s are here, which hold
    # too few swings for the waving check, but the hand it waves with is up.
    stem = "dataset-1_bye_normal_001"
    if stem not in bandai_clips:
        pytest.skip(f"fixture {stem}.bvh missing")
    assert P.raised_hand(bandai_clips[stem]).verdict == "right"
    assert P.raised_hand(mirror_joints(bandai_clips[stem])).verdict == "left"


# ---- the script ------------------------------------------------------------------------------------------------


def _load_script(rootpath):
    spec = importlib.util.spec_from_file_location("side_accuracy", rootpath / "research" / "side_accuracy.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _labelled_folder(bandai_clips, root):
    """A tiny HumanML3D-format test split from two fixture clips and their mirrors, with actions.json."""
    from mld_core.motion.features import joints_to_features

    (root / "new_joints").mkdir(parents=True)
    (root / "new_joint_vecs").mkdir()
    (root / "texts").mkdir()
    labels = {}
    wanted = {"dataset-2_walk-turn-left_normal_027": ("walk-turn-left", "a person walks and turns left."),
              "dataset-2_wave-right-hand_normal_026": ("wave-right-hand", "a person waves the right hand.")}
    for stem, (label, text) in wanted.items():
        if stem not in bandai_clips:
            pytest.skip(f"fixture {stem}.bvh missing")
        for cid, j, lab, cap in ((stem, bandai_clips[stem], label, text),
                                 ("M" + stem, mirror_joints(bandai_clips[stem]), P.mirror_label(label),
                                  text.replace("left", "LEFT").replace("right", "left").replace("LEFT", "right"))):
            np.save(root / "new_joints" / f"{cid}.npy", j.astype(np.float32))
            np.save(root / "new_joint_vecs" / f"{cid}.npy", joints_to_features(j))
            (root / "texts" / f"{cid}.txt").write_text(f"{cap}#x#0.0#0.0\n", encoding="utf-8")
            labels[cid] = lab
    (root / "test.txt").write_text("\n".join(labels) + "\n", encoding="utf-8")
    (root / "actions.json").write_text(json.dumps({"classes": sorted(set(labels.values())), "clips": labels}))
    return root


def test_side_accuracy_script_end_to_end(bandai_clips, tmp_path, request, capsys):
    """A tiny HumanML3D-format folder from the fixture clips, scored real-only and with a tiny random model."""
    from mld_core.testing import tiny_model

    root = _labelled_folder(bandai_clips, tmp_path / "data")
    script = _load_script(request.config.rootpath)
    contents = "wave-right-hand,wave-left-hand,walk-turn-left,walk-turn-right"
    out = tmp_path / "real.json"
    assert script.main(["--data", str(root), "--real-only", "--contents", contents, "--json", str(out)]) == 0
    real = json.loads(out.read_text())["real"]
    for c in contents.split(","):
        assert real["contents"][c]["n"] == 1
        assert real["contents"][c]["pass_rate"] == 1.0 and real["contents"][c]["side_accuracy"] == 1.0
    assert real["overall"]["sided"]["side_accuracy"] == 1.0

    model = tiny_model(tmp_path / "tiny")
    out2 = tmp_path / "gen.json"
    assert script.main(["--data", str(root), "--model", str(model), "--contents", "wave-right-hand,walk-turn-left",
                        "--seeds", "2", "--seconds", "2", "--clip-length", "--steps", "2", "--vae-recon",
                        "--per-prompt", "--json", str(out2)]) == 0
    rep = json.loads(out2.read_text())
    # per paraphrase: 4 per content and length, each 2 seeds, adding up to the content's row
    rows = [r for r in rep["paraphrases"] if r["content"] == "walk-turn-left" and r["length"] == "clip"]
    assert len(rows) == 4 and {r["n"] for r in rows} == {2}
    assert sum(r["pass_rate"] * r["n"] for r in rows) == pytest.approx(
        rep["generated"]["paraphrase@clip"]["contents"]["walk-turn-left"]["pass_rate"] * 8)
    printed = capsys.readouterr().out
    assert "changes direction to their left" in printed
    assert set(rep["generated"]) == {"captions@2s", "captions@clip", "paraphrase@2s", "paraphrase@clip",
                                     "vae-recon@2s", "vae-recon@clip"}
    assert rep["generated"]["vae-recon@clip"]["contents"]["walk-turn-left"]["n"] == 1
    # captions: 1 clip x 2 seeds per content; paraphrases: 4 per content x 2 seeds
    assert rep["generated"]["captions@2s"]["contents"]["wave-right-hand"]["n"] == 2
    assert rep["generated"]["paraphrase@clip"]["contents"]["walk-turn-left"]["n"] == 8
    for mode in rep["generated"].values():
        for c in mode["contents"].values():
            assert 0.0 <= c["pass_rate"] <= 1.0 and c["side_accuracy"] + c["opposite_side"] <= 1.0
            # each take's numbers, for a paired comparison of two runs, add up to the row
            assert len(c["takes"]["passed"]) == len(c["takes"]["skating"]) == len(c["takes"]["keys"]) == c["n"]
            assert sum(c["takes"]["passed"]) / c["n"] == c["pass_rate"]
            assert sum(c["takes"]["skating"]) / c["n"] == pytest.approx(c["skating"], abs=1e-5)
    assert "takes" not in rep["real"]["contents"]["walk-turn-left"] and "takes" not in rep["paraphrases"][0]
    # a key per take: prompt | seconds | seed | variant; a paraphrase's 2 seeds are variants 0 and 1 of seed 0
    keys = rep["generated"]["paraphrase@2s"]["contents"]["walk-turn-left"]["takes"]["keys"]
    assert len(set(keys)) == 8 and all(k.endswith(("|0|0", "|0|1")) and "|2.000|" in k for k in keys)
    # side redraws (the model's default, 2): which takes are a later draw of their seed, and the time they took
    assert rep["side_redraws"] == 2 and rep["redraws"]["seconds"] >= 0.0
    kept = rep["redraws"]["kept"]["paraphrase@clip"]["walk-turn-left"]
    assert kept["takes"] == 8 and 0 <= kept["redrawn"] <= 8
    recon = rep["generated"]["vae-recon@clip"]["contents"]["walk-turn-left"]["takes"]["keys"]
    assert recon == ["dataset-2_walk-turn-left_normal_027|clip"]
    with pytest.raises(SystemExit):
        script.main(["--data", str(root), "--model", str(model), "--first-seed", "-1"])
    assert "--first-seed must be >= 0" in capsys.readouterr().err
    assert "side" in printed


def test_side_of_a_wave_is_the_waving_hand_else_the_raised_one(rest):
    T = 5 * FPS
    a = ramp(T, (0.5, 1.0), (4.0, 4.5))
    both_up_left_waves = wave(raise_arm(still(rest, 5), "right", a), "left", a)
    r = P.classify(both_up_left_waves)
    assert r["raised"].verdict == "both" and r["waving"].verdict == "left"
    assert P.detected_side(r, "wave-left-hand") == "left" and P.detected_side(r, "raise-up-left-hand") == "both"
    only_raised = P.classify(raise_arm(still(rest, 5), "right", a))
    assert P.detected_side(only_raised, "wave-left-hand") == "right"


def test_a_jump_leaves_the_floor_with_the_pelvis_rising(rest):
    j = still(rest, 3.0)
    t = np.arange(len(j)) / FPS
    flight = (t >= 1.0) & (t < 1.45)  # 0.45 s in the air, up to 0.25 m
    height = np.where(flight, 0.25 * np.sin(np.pi * (t - 1.0) / 0.45), 0.0)
    jumped = j + height[:, None, None] * np.array([0.0, 1.0, 0.0])
    c = P.jump(jumped)
    assert c.verdict is True and c.value == pytest.approx(0.35, abs=0.1) and P.passes(jumped, "jump")
    assert P.jump(j).verdict is False
    # A running stride's flight: feet off the floor briefly, the pelvis level: no jump.
    fast = walk(rest, (0.0, 3.0), step_s=0.7, stance=0.35)
    assert P.locomotion(fast).verdict == "run" and P.jump(fast).verdict is False


def test_valid_references_leave_out_only_the_captions_of_clips_that_fail_their_own_checks(bandai_clips, request):
    script = _load_script(request.config.rootpath)
    turn, wave_clip = "dataset-2_walk-turn-left_normal_027", "dataset-2_wave-right-hand_normal_026"
    if turn not in bandai_clips or wave_clip not in bandai_clips:
        pytest.skip("fixture clips missing")
    # a wave filed under walk-turn-left: its own capture does not walk and turn, so no take of its caption can pass
    clips = {"walk-turn-left": [_test_clip("turn", bandai_clips[turn]),
                                _test_clip("mislabelled", bandai_clips[wave_clip])]}
    failing = script.failing_references(clips, FPS)
    assert failing == {"walk-turn-left": ["mislabelled"]}
    every = script.build_requests(clips, ["captions", "paraphrase"], ["clip"], 2, 16, 2.0, 9.8)
    valid = script.build_requests(clips, ["captions", "paraphrase"], ["clip"], 2, 16, 2.0, 9.8,
                                  frozenset(failing["walk-turn-left"]))
    assert [r for r in every if r["prompt"] != "caption of mislabelled"] == valid
    assert len(every) - len(valid) == 2 and sum(r["source"] == "paraphrase" for r in valid) == 4
    fresh = script.build_requests(clips, ["captions", "paraphrase"], ["clip"], 2, 16, 2.0, 9.8, first_seed=16)
    assert [r["seed"] for r in every if r["source"] == "captions"] == [0, 1, 0, 1]
    assert [r["seed"] for r in fresh if r["source"] == "captions"] == [16, 17, 16, 17]
    assert {r["seed"] for r in fresh if r["source"] == "paraphrase"} == {16}
    assert [{**r, "seed": 0} for r in fresh] == [{**r, "seed": 0} for r in every]  # the same prompts otherwise


def _test_clip(cid: str, joints) -> dict:
    return {"id": cid, "joints": joints, "captions": [f"caption of {cid}"], "seconds": len(joints) / FPS,
            "split": "test"}


def test_skating_source_reconstructs_through_diffusion_space(bandai_clips, tmp_path, request):
    """research/skating_source.py's VAE rows decode each clip's own VAE mean (whatever the latent normalisation)."""
    from mld_core.pipeline import MLDPipeline
    from mld_core.testing import tiny_model

    root = _labelled_folder(bandai_clips, tmp_path / "data")
    spec = importlib.util.spec_from_file_location("skating_source", request.config.rootpath / "research" / "skating_source.py")
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    model = tiny_model(tmp_path / "tiny")
    out = tmp_path / "source.json"
    assert script.main(["--data", str(root), "--model", str(model), "--clips", "1", "--json", str(out)]) == 0
    rows = json.loads(out.read_text())
    assert set(rows) == {"walk-turn-left", "walk-turn-right"}
    assert all(np.isfinite(v) for r in rows.values() for row in r.values() for v in row.values())
    pipe = MLDPipeline.from_pretrained(model)
    pipe.config.latent_scale, pipe.config.latent_mean = 1.7, -0.3  # a trained model's diffusion-space normalisation
    clip = np.load(root / "new_joint_vecs" / "dataset-2_walk-turn-left_normal_027.npy")
    expected = pipe.latents_to_features(*pipe.features_to_latents([clip]))[0]  # (T, F): the VAE mean decoded
    np.testing.assert_allclose(script.reconstruct(pipe, [clip])[0], expected, atol=1e-5)


def test_directed_skating_refuses_a_missing_model_folder_in_one_line(tmp_path, capsys, request):
    spec = importlib.util.spec_from_file_location("directed_skating",
                                                  request.config.rootpath / "research" / "directed_skating.py")
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    assert script.main(["--model", str(tmp_path / "none"), "--seeds", "1"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: --model") and "not found" in err and "Traceback" not in err


def test_directed_skating_counts_a_sequences_seams(tmp_path, request):
    from mld_core.pipeline import MLDPipeline
    from mld_core.testing import tiny_model

    spec = importlib.util.spec_from_file_location("directed_skating",
                                                  request.config.rootpath / "research" / "directed_skating.py")
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    pipe = MLDPipeline.from_pretrained(tiny_model(tmp_path / "tiny"))
    row = script.sequence(pipe, [("a person walks", 2.0), ("a person bows", 2.0)], seeds=2, step=False)
    assert len(row["skating"]) == 2 and row["met"] == [False, False]  # one seam a take; the tiny model's are rough


@pytest.mark.parametrize("redraws", ["-1", "9"])
def test_side_accuracy_refuses_side_redraws_out_of_range_before_any_work(request, tmp_path, capsys, redraws):
    mod = _load_script(request.config.rootpath)
    with pytest.raises(SystemExit) as exit_info:
        mod.main(["--data", str(tmp_path / "absent"), "--side-redraws", redraws])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert f"--side-redraws must be between 0 and 8, got {redraws}" in err and "Traceback" not in err


# ---- the CMU verbs ---------------------------------------------------------------------------------------------


def lowered(pose: np.ndarray, drop: np.ndarray, joints=None) -> np.ndarray:
    """The pose with ``joints`` (default: all but the feet) lowered by drop[t] metres, the feet kept on the floor."""
    keep = {7, 8, 10, 11}
    moved = [j for j in range(22) if j not in keep] if joints is None else list(joints)
    out = still(pose, len(drop) / FPS)
    out[:, moved, 1] -= drop[:, None]
    return out


def test_sitting_down_gets_low_and_standing_up_after_it_counts(rest):
    pelvis = rest[0, 1] - rest[:, 1].min()  # about 0.9 m above the floor
    down = 0.3 * ramp(4 * FPS, (0.5, 1.0), (2.5, 3.0))  # sits 0.3 m lower for 1.5 s, then back up
    sit = lowered(rest, down)
    assert P.get_low(sit).verdict is True and P.get_low(sit).value == pytest.approx(pelvis - 0.3, abs=0.01)
    assert P.stand_up(sit).verdict is True and P.shows(sit, "stand_up") and P.shows(sit, "get_low")
    assert P.on_ground(sit).verdict is False  # sitting on a chair is not on the ground
    stays = lowered(rest, 0.3 * ramp(4 * FPS, (0.5, 1.0)))
    assert P.get_low(stays).verdict is True and P.stand_up(stays).verdict is False  # never comes back up
    crouch_briefly = lowered(rest, 0.3 * ramp(4 * FPS, (1.0, 1.05), (1.1, 1.15)))
    assert P.get_low(crouch_briefly).verdict is False  # down for a tenth of a second only


def test_lying_on_the_ground_and_reaching_the_floor(rest):
    lying = still(rest)
    lying[:, :, 1] = rest[:, 1].min() + 0.1 * (rest[:, 1] - rest[:, 1].min()) / 1.7  # everything within 10 cm
    assert P.on_ground(lying).verdict is True and P.get_low(lying).verdict is True
    assert P.reach_floor(lying).verdict is False  # hands low, but the pelvis is down too: not a pick-up
    reach = still(rest)
    reach[40:44, 21] = rest[[11]] + np.array([0.0, 0.05, 0.3])  # the right wrist at the floor for 0.2 s
    assert P.reach_floor(reach).verdict is True and P.shows(reach, "reach_floor")
    assert P.reach_floor(mirror_joints(reach)).verdict is True


def test_handstand_is_inverted(rest):
    flipped = still(rest)
    top = rest[:, 1].max()
    flipped[30:50, :, 1] = top - (rest[:, 1] - rest[:, 1].min())  # upside down for a second
    assert P.inverted(flipped).verdict is True and P.shows(flipped, "inverted")
    assert P.inverted(still(rest)).verdict is False


def test_crawl_needs_all_fours_and_travel(rest):
    floor = rest[:, 1].min()
    fours = still(rest)
    fours[:, :, 1] = floor + 0.45 * (rest[:, 1] - floor)  # head about 0.7 m, pelvis 0.4 m, wrists near the floor
    fours[:, [20, 21], 1] = floor + 0.05
    moving = fours + (np.arange(len(fours)) / FPS * 0.4)[:, None, None] * np.array([0.0, 0.0, 1.0])
    assert P.crawl(moving).verdict is True and P.crawl(moving).detail["travel_m"] > 1.0
    assert P.crawl(fours).verdict is False  # on all fours without moving


def test_climbing_holds_the_feet_up_and_a_jump_is_brief(rest):
    climb = still(rest)
    climb[40:, :, 1] += 0.4  # up onto something 40 cm high for 2 s
    assert P.climb(climb).verdict is True and P.shows(climb, "climb")
    assert P.jump(climb).verdict is False  # standing on a platform is no flight
    hop = still(rest)
    hop[40:46, :, 1] += 0.3  # 0.3 s in the air
    assert P.jump(hop).verdict is True and P.climb(hop).verdict is False


def test_throw_is_a_fast_forward_hand(rest):
    throw = still(rest)
    t = np.arange(6)
    throw[40:46, 21] = rest[17] + np.array([0.0, 0.0, -0.4]) + t[:, None] * np.array([0.0, 0.0, 0.25])  # 5 m/s
    assert P.throw(throw).verdict is True and P.throw(throw).value == pytest.approx(5.0, abs=0.01)
    slow = still(rest)
    slow[40:46, 21] = rest[17] + np.array([0.0, 0.0, -0.4]) + t[:, None] * np.array([0.0, 0.0, 0.05])
    assert P.throw(slow).verdict is False
    assert P.verb_result(throw, "throw") == (True, pytest.approx(5.0, abs=0.01))  # the deciding check's value
    assert P.verb_result(slow, "throw") == (False, pytest.approx(1.0, abs=0.01))
    back = still(rest)
    back[40:46, 21] = rest[17] - t[:, None] * np.array([0.0, 0.0, 0.25])  # flung backwards
    assert P.throw(back).verdict is False


def test_shows_knows_its_verbs(rest):
    from mld_core.data.verbs import VERBS

    assert set(VERBS) <= set(P.SHOWN_VERBS)
    assert not any(P.shows(still(rest), v) for v in VERBS)
    with pytest.raises(ValueError, match="no physical check for the verb"):
        P.shows(still(rest), "juggle")
    with pytest.raises(ValueError, match="no physical check for the verb"):
        P.verb_result(still(rest), "juggle")


def test_the_verb_badge_says_whether_a_take_shows_every_verb_its_prompt_names(rest):
    from blender_addon.worker.coverage_watch import badge_lines
    from mld_core import take_report
    from mld_core.eval import quality

    sit = lowered(rest, 0.3 * ramp(4 * FPS, (0.5, 1.0), (2.5, 3.0)))  # gets low, then stands up
    squat = "a person squats down and stands back up"  # names get_low and stand_up
    scorer = quality.QualityScorer(None, {"jerk_mean": 1.0})  # physical badges only
    badges = scorer.score([squat, squat, "a person squats down", "a person waves"], [sit, still(rest), sit, sit])
    assert [b.verb for b in badges] == ["shown", "missed", "shown", None]
    assert [b.verb for b in scorer.score(None, [sit])] == [None]  # no prompt (actions, unconditional)
    assert quality.verb_badge("someone jumps and squats", sit) == "missed"  # every verb named, not one of them
    props = take_report.custom_properties(None, badges[1])
    assert props["mld_verb"] == "missed" and "mld_verb" not in take_report.custom_properties(None, badges[3])
    assert ("Verb: missed", "the jump, crawl, kick, ... the prompt names: all shown by their checks, or missed") \
        in badge_lines(props)
    assert take_report.take_record(None, badges[0])["badges"]["verb"] == "shown"
    table = quality.format_table([1, 2, 3], badges[:3]).splitlines()
    assert [line.split()[-1] for line in table] == ["verb", "shown", "missed", "shown"]


def test_takes_that_miss_their_verbs_rank_after_all_others_even_opposite_ones():
    from mld_core.eval import quality

    def badges(adherence, side=None, verb=None):
        return quality.Badges(adherence, None, 0.0, 0.0, 0.0, 1.0, side, verb)

    b = [badges(95, verb="missed"), badges(20, "named", "shown"), badges(90, "opposite", "shown"), badges(50)]
    assert quality.rank_score(b[0]) == quality.rank_score(badges(95))  # the score itself is unchanged
    assert quality.best_first(b, [0, 1, 2, 3]) == [3, 1, 2, 0]
    assert quality.best_first([b[0], badges(95, verb="missed")], [5, 4]) == [1, 0]  # among them: score, then seed
