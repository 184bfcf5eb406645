"""Bandai Namco -> HumanML3D-format folder: joints, captions, splits, and the prepare command end to end."""

from __future__ import annotations

import json
import tarfile

import numpy as np
import pytest

from mld_core.cli import main
from mld_core.data import bandai, captions, terms
from mld_core.motion import skeleton as sk
from mld_core.motion.bvh import read_bvh
from mld_core.motion.features import canonical_joints, features_to_joints, joints_to_features

FIXTURE_IDS = [
    "dataset-1_bye_normal_001",
    "dataset-2_walk-turn-left_normal_027",
    "dataset-2_wave-right-hand_normal_026",
]


@pytest.fixture
def bandai_dir(fixtures):
    return fixtures / "bandai"


def _joints(bandai_dir, cid):
    return bandai.clip_joints((bandai_dir / f"{cid}.bvh").read_bytes())


def test_mapping_gives_a_standing_person_in_metres(bandai_dir):
    bvh = read_bvh(bandai_dir / "dataset-2_wave-right-hand_normal_026.bvh")
    j = bandai.bandai_joints(bvh)  # (F, 22, 3) at 30 fps
    assert j.shape == (60, 22, 3)
    head, pelvis = j[:, sk.JOINT_NAMES.index("head")], j[:, 0]
    assert np.all(head[:, 1] - pelvis[:, 1] > 0.3) and 0.7 < np.median(pelvis[:, 1]) < 1.1
    # spine2 is the midpoint of Spine and Chest
    np.testing.assert_allclose(j[:, 6], 0.5 * (j[:, 3] + j[:, 9]), atol=1e-12)
    # the performer's right hand waves above the left one
    assert j[:, 21, 1].max() > j[:, 20, 1].max() + 0.3


def test_resample_30_to_20_fps_interpolates_linearly():
    x = np.arange(31, dtype=np.float64)[:, None, None] * np.ones((1, 22, 3))  # value = frame index at 30 fps
    y = bandai.resample_joints(x, 30.0, 20.0)
    assert y.shape[0] == 21  # 1 s -> 21 samples at t = k/20
    np.testing.assert_allclose(y[:, 0, 0], np.arange(21) * 1.5)
    assert bandai.source_fps(0.0333333) == 30.0


@pytest.mark.parametrize("cid", FIXTURE_IDS)
def test_bvh_to_features_round_trip_within_1mm(bandai_dir, cid):
    joints = _joints(bandai_dir, cid)  # (T, 22, 3) at 20 fps
    assert len(joints) == 40  # 60 frames at 30 fps = 1.967 s -> 40 samples at 20 fps
    feats = joints_to_features(joints)
    assert feats.shape == (39, 263) and feats.dtype == np.float32
    back = features_to_joints(feats)
    uniform = canonical_joints(joints)[:-1]
    assert np.abs(back - uniform).max() < 1e-3


def test_walk_turn_left_turns_to_the_performers_left(bandai_dir):
    j = canonical_joints(_joints(bandai_dir, "dataset-2_walk-turn-left_normal_027"))
    # facing +Z at frame 0, the performer's left is +X: the path bends towards +X
    assert j[-1, 0, 2] > 0.5 and j[-1, 0, 0] > 0.1


def test_clip_names_and_mirrored_labels():
    n = bandai.parse_clip_name("dataset-2_walk-turn-left_normal_027")
    assert (n.dataset, n.content, n.style, n.take) == ("dataset-2", "walk-turn-left", "normal", "027")
    assert bandai.parse_clip_name("dataset-1_walk-back_not-confident_001").style == "not-confident"
    with pytest.raises(ValueError):
        bandai.parse_clip_name("walk_normal")
    pairs = [("wave-left-hand", "wave-right-hand"), ("walk-turn-left", "walk-turn-right"),
             ("raise-up-left-hand", "raise-up-right-hand"), ("walk-left", "walk-right")]
    for a, b in pairs:
        assert captions.mirror_content(a) == b and captions.mirror_content(b) == a
    assert captions.mirror_content("bow") == "bow"


def test_captions_are_varied_deterministic_and_sided():
    a = captions.captions_for("walk-turn-left", "exhausted", "dataset-2_walk-turn-left_exhausted_003")
    assert a == captions.captions_for("walk-turn-left", "exhausted", "dataset-2_walk-turn-left_exhausted_003")
    assert len(a) >= 3 and len(set(a)) == len(a)
    assert all("left" in s and "right" not in s for s in a)
    assert any(w in " ".join(a) for w in ("exhausted", "wearily", "trudges", "worn out", "tired", "drags"))
    others = captions.captions_for("walk-turn-left", "exhausted", "dataset-2_walk-turn-left_exhausted_004")
    assert others != a  # seeded by the clip id
    for content in captions.CONTENTS:
        for style in captions.STYLES:
            caps = captions.captions_for(content, style, f"x_{content}_{style}_001")
            assert len(set(caps)) >= 3, (content, style)
            if "right" in content:
                assert all("right" in c and "left" not in c for c in caps), caps
    line = captions.caption_line("a person waves the right hand.")
    text, tokens, start, end = line.split("#")
    assert text == "a person waves the right hand." and (start, end) == ("0.0", "0.0")
    assert tokens.split() == ["a/DET", "person/NOUN", "waves/VERB", "the/DET", "right/ADJ", "hand/NOUN"]


def test_splits_are_stratified_stable_and_keep_small_strata_in_train():
    labels = {f"d2_walk_normal_{i:03d}": ("walk", "normal") for i in range(40)}
    labels.update({f"d2_run_active_{i:03d}": ("run", "active") for i in range(20)})
    labels.update({f"d1_bow_{s}_001": ("bow", s) for s in ("happy", "sad", "angry", "old", "proud",
                                                           "giant", "musical", "tired", "active", "normal")})
    labels["d1_kick_normal_001"] = ("kick", "normal")
    labels.update({"d1_call_normal_001": ("call", "normal"), "d1_call_normal_002": ("call", "normal")})
    s1 = bandai.assign_splits(labels)
    s2 = bandai.assign_splits(dict(reversed(list(labels.items()))))
    assert s1 == s2
    walk = [s1[k] for k in labels if k.startswith("d2_walk")]
    assert (walk.count("train"), walk.count("val"), walk.count("test")) == (32, 4, 4)
    run = [s1[k] for k in labels if k.startswith("d2_run")]
    assert (run.count("train"), run.count("val"), run.count("test")) == (16, 2, 2)
    bow = [s1[k] for k in labels if "bow" in k]  # 10 single-clip strata pooled per content
    assert (bow.count("train"), bow.count("val"), bow.count("test")) == (8, 1, 1)
    assert s1["d1_kick_normal_001"] == "train"
    assert s1["d1_call_normal_001"] == s1["d1_call_normal_002"] == "train"


def _prepare(src, out, *extra):
    return main(["data", "prepare", "bandai", str(src), "--out", str(out), "--quiet", *extra])


def _check_folder(out, ids):
    all_ids = sorted(ids + ["M" + i for i in ids])
    assert (out / "all.txt").read_text().split() == all_ids
    split = {}
    for name in ("train", "val", "test"):
        for cid in (out / f"{name}.txt").read_text().split():
            split[cid] = name
    assert sorted(split) == all_ids
    for cid in ids:
        assert split[cid] == split["M" + cid]
    for cid in all_ids:
        vecs = np.load(out / "new_joint_vecs" / f"{cid}.npy")
        joints = np.load(out / "new_joints" / f"{cid}.npy")
        assert vecs.dtype == np.float32 and vecs.shape == (39, 263)
        assert joints.shape == (39, 22, 3)
        np.testing.assert_allclose(features_to_joints(vecs), joints, atol=1e-5)
        lines = (out / "texts" / f"{cid}.txt").read_text().splitlines()
        assert len(lines) >= 3 and all(len(line.split("#")) == 4 for line in lines)
    actions = json.loads((out / "actions.json").read_text())
    assert actions["classes"] == sorted(set(actions["classes"]))
    assert actions["clips"]["dataset-2_wave-right-hand_normal_026"] == "wave-right-hand"
    assert actions["clips"]["Mdataset-2_wave-right-hand_normal_026"] == "wave-left-hand"
    assert actions["clips"]["Mdataset-2_walk-turn-left_normal_027"] == "walk-turn-right"
    assert actions["clips"]["Mdataset-1_bye_normal_001"] == "bye"
    assert actions["styles"]["Mdataset-1_bye_normal_001"] == "normal"
    mean, std = np.load(out / "Mean.npy"), np.load(out / "Std.npy")
    assert mean.shape == std.shape == (263,) and np.isfinite(mean).all() and (std > 0).all()
    m_text = (out / "texts" / "Mdataset-2_wave-right-hand_normal_026.txt").read_text()
    assert "left hand" in m_text and "right" not in m_text
    # the mirrored clip waves its left hand
    mj = np.load(out / "new_joints" / "Mdataset-2_wave-right-hand_normal_026.npy")
    assert mj[:, 20, 1].max() > mj[:, 21, 1].max() + 0.3
    assert "CC BY-NC 4.0" in (out / "README.md").read_text()
    assert "Bandai Namco Research" in (out / "LICENSE").read_text()
    assert terms.of_folder(out) == [terms.BANDAI]  # whose terms weights trained on it carry


def test_prepare_end_to_end_from_folder_and_rerun(bandai_dir, tmp_path, capsys):
    out = tmp_path / "h3d"
    assert _prepare(bandai_dir, out, "--workers", "1") == 0
    _check_folder(out, FIXTURE_IDS)
    first = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()}
    # Rerunning replaces our own previous output with identical files, and leaves no temporary folders.
    assert _prepare(bandai_dir, out, "--workers", "1") == 0
    second = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()}
    assert first == second
    assert sorted(p.name for p in tmp_path.iterdir()) == ["h3d"]
    assert "3 clips + 3 mirrored" in capsys.readouterr().out


def test_prepare_streams_a_tar_xz(bandai_dir, tmp_path):
    archive = tmp_path / "bandai.tar.xz"
    with tarfile.open(archive, "w:xz") as tar:
        for p in sorted(bandai_dir.iterdir()):
            tar.add(p, arcname=f"dataset/x/data/{p.name}")
    out = tmp_path / "h3d"
    assert _prepare(archive, out, "--workers", "1") == 0
    _check_folder(out, FIXTURE_IDS)
    # the archive's LICENSE file is carried into the output's LICENSE
    assert "excerpts (about two seconds each" in (out / "LICENSE").read_text()


@pytest.mark.slow
def test_prepare_with_two_worker_processes_matches_one(bandai_dir, tmp_path):
    """Spawned workers (about 10 s: each imports torch) give byte-identical files."""
    one, two = tmp_path / "one", tmp_path / "two"
    assert _prepare(bandai_dir, one, "--workers", "1") == 0
    assert _prepare(bandai_dir, two, "--workers", "2") == 0
    files = sorted(p.relative_to(one) for p in one.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(two) for p in two.rglob("*") if p.is_file())
    for f in files:
        assert (one / f).read_bytes() == (two / f).read_bytes(), f


def test_bad_src_and_bad_out_exit_2_and_touch_nothing(bandai_dir, tmp_path, capsys):
    out = tmp_path / "h3d"
    assert _prepare(tmp_path / "missing.tar.xz", out) == 2
    assert "does not exist" in capsys.readouterr().err
    junk = tmp_path / "junk.tar.xz"
    junk.write_bytes(b"not an archive at all")
    assert _prepare(junk, out) == 2
    assert "tar archive" in capsys.readouterr().err
    empty = tmp_path / "empty"
    empty.mkdir()
    assert _prepare(empty, out) == 2
    assert "no Bandai clips" in capsys.readouterr().err
    assert not out.exists()

    users = tmp_path / "users"
    users.mkdir()
    (users / "thesis.txt").write_text("precious")
    assert _prepare(bandai_dir, users, "--workers", "1") == 2
    assert "not empty" in capsys.readouterr().err
    assert [p.name for p in users.iterdir()] == ["thesis.txt"]
    assert (users / "thesis.txt").read_text() == "precious"

    a_file = tmp_path / "file.txt"
    a_file.write_text("x")
    assert _prepare(bandai_dir, a_file, "--workers", "1") == 2
    assert a_file.read_text() == "x"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["empty", "file.txt", "junk.tar.xz", "users"]


def test_a_broken_clip_is_skipped_with_a_warning(bandai_dir, tmp_path, capsys):
    src = tmp_path / "src"
    src.mkdir()
    for cid in FIXTURE_IDS[:2]:
        (src / f"{cid}.bvh").write_bytes((bandai_dir / f"{cid}.bvh").read_bytes())
    text = (bandai_dir / f"{FIXTURE_IDS[2]}.bvh").read_text()
    (src / f"{FIXTURE_IDS[2]}.bvh").write_text(text[: len(text) // 2])  # truncated MOTION block
    out = tmp_path / "h3d"
    assert _prepare(src, out, "--workers", "1") == 0
    err = capsys.readouterr().err
    assert "skipped dataset-2_wave-right-hand_normal_026" in err and "expected 132" in err
    manifest = json.loads((out / bandai.MANIFEST).read_text())
    assert list(manifest["skipped"]) == [FIXTURE_IDS[2]]
    assert len((out / "all.txt").read_text().split()) == 4
