"""data pack / data unpack: a prepared folder carried as one file and rebuilt to train on."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mld_core.data import terms
from mld_core.data.dataset import load_split
from mld_core.data.pack import decode_joints, encode_joints, pack, read_pack, unpack
from mld_core.inputs import InputError
from mld_core.motion import features as F

FIXTURE = Path(__file__).parent / "fixtures" / "humanml3d"
REPO = Path(__file__).resolve().parents[1]


def _joints(seed: int, frames: int) -> np.ndarray:
    """A real clip's joints (the HumanML3D fixture), cut and moved a little per seed."""
    base = np.load(FIXTURE / "new_joints_012314.npy").astype(np.float32)
    rng = np.random.default_rng(seed)
    start = int(rng.integers(0, len(base) - frames))
    return base[start:start + frames] + rng.normal(0, 0.02, 3).astype(np.float32)


def _folder(root: Path) -> Path:
    """A prepared folder: train a, b (+ mirrors), val c, test d; captions per clip."""
    (root / "new_joints").mkdir(parents=True)
    (root / "new_joint_vecs").mkdir()
    (root / "texts").mkdir()
    splits = {"train": ["a", "b", "Ma", "Mb"], "val": ["c"], "test": ["d"]}
    for k, cid in enumerate("abcd"):
        joints = _joints(k, 40 + 10 * k)
        for name, j in ((cid, joints), (f"M{cid}", F.mirror_joints(joints))):
            np.save(root / "new_joints" / f"{name}.npy", j)
            np.save(root / "new_joint_vecs" / f"{name}.npy", F.joints_to_features(j))
            (root / "texts" / f"{name}.txt").write_text(f"a person does {name}#a/DET#0.0#0.0\n", encoding="utf-8")
    for split, ids in splits.items():
        (root / f"{split}.txt").write_text("".join(f"{i}\n" for i in ids), encoding="utf-8")
    np.save(root / "Mean.npy", np.load(FIXTURE / "Mean.npy"))
    np.save(root / "Std.npy", np.load(FIXTURE / "Std.npy"))
    (root / "actions.json").write_text('{"classes": ["x"], "clips": {"a": "x"}}', encoding="utf-8")
    terms.write(root, [terms.CMU])
    return root


def test_joints_round_trip_to_a_millimetre():
    rng = np.random.default_rng(0)
    clips = [_joints(s, n) for s, n in ((0, 30), (1, 3), (2, 77))]
    clips.append((rng.normal(0, 3, (5, 22, 3))).astype(np.float32))  # jumps of metres: the escape stream
    small, big = encode_joints(clips)
    back = decode_joints(small, big, [len(c) for c in clips])
    for a, b in zip(clips, back):
        assert b.shape == a.shape and b.dtype == np.float32
        assert np.abs(a - b).max() <= 0.0005 + 1e-6
    with pytest.raises(ValueError, match="residuals"):
        decode_joints(small, big, [len(c) for c in clips][:-1])


def test_pack_then_unpack_gives_a_folder_to_train_on(tmp_path):
    src = _folder(tmp_path / "src")
    done = pack(src, tmp_path / "p.npz", ("train", "val"))
    assert (done["clips"], done["mirrored"]) == (3, 2)  # a, b, c stored; Ma, Mb made again
    out = unpack(tmp_path / "p.npz", tmp_path / "out", workers=1)
    assert out["clips"] == 3 and out["mirrored"] == 2
    dst = tmp_path / "out"
    assert (dst / "train.txt").read_text().split() == ["a", "b", "Ma", "Mb"]
    assert (dst / "val.txt").read_text().split() == ["c"] and (dst / "test.txt").read_text() == ""
    assert sorted(p.stem for p in (dst / "new_joint_vecs").iterdir()) == ["Ma", "Mb", "a", "b", "c"]
    for cid in "abc":
        joints = np.round(np.load(src / "new_joints" / f"{cid}.npy") * 1000) / 1000
        own = np.load(dst / "new_joint_vecs" / f"{cid}.npy")
        assert own.shape == (len(joints) - 1, 263)
        np.testing.assert_allclose(own, F.joints_to_features(joints.astype(np.float32)), atol=1e-4)
        assert (dst / "texts" / f"{cid}.txt").read_text() == (src / "texts" / f"{cid}.txt").read_text()
    mirror = np.load(dst / "new_joint_vecs" / "Ma.npy")
    joints = (np.round(np.load(src / "new_joints" / "a.npy") * 1000) / 1000).astype(np.float32)
    np.testing.assert_allclose(mirror, F.joints_to_features(F.mirror_joints(joints)), atol=1e-4)
    assert (dst / "texts" / "Ma.txt").read_text().startswith("a person does Ma")
    np.testing.assert_array_equal(np.load(dst / "Mean.npy"), np.load(src / "Mean.npy"))
    assert (dst / "actions.json").read_text() == (src / "actions.json").read_text()
    assert terms.of_folder(dst) == [terms.CMU]  # the folder's terms travel with it
    assert [c.id for c in load_split(dst, "train")] == ["a", "b", "Ma", "Mb"]


def test_unpack_with_workers_equals_one_process(tmp_path):
    pack(_folder(tmp_path / "src"), tmp_path / "p.npz", ("train",))
    unpack(tmp_path / "p.npz", tmp_path / "one", workers=1)
    unpack(tmp_path / "p.npz", tmp_path / "two", workers=2)
    for f in sorted((tmp_path / "one" / "new_joint_vecs").iterdir()):
        assert np.array_equal(np.load(f), np.load(tmp_path / "two" / "new_joint_vecs" / f.name))


def test_bad_input_is_refused_and_nothing_is_left(tmp_path):
    src = _folder(tmp_path / "src")
    with pytest.raises(InputError, match="not a prepared folder"):
        pack(tmp_path, tmp_path / "p.npz")
    with pytest.raises(InputError, match="--splits: dev"):
        pack(src, tmp_path / "p.npz", ("train", "dev"))
    with pytest.raises(InputError, match="is a folder"):
        pack(src, src)
    mean = (src / "Mean.npy").read_bytes()
    with pytest.raises(InputError, match="inside the folder being packed"):
        pack(src, src / "Mean.npy")
    assert (src / "Mean.npy").read_bytes() == mean
    (src / "new_joints" / "b.npy").unlink()
    with pytest.raises(InputError, match="b is listed"):
        pack(src, tmp_path / "p.npz")
    assert not (tmp_path / "p.npz").exists()
    (tmp_path / "junk.npz").write_bytes(b"not a pack")
    with pytest.raises(InputError, match="not a readable data pack"):
        read_pack(tmp_path / "junk.npz")
    with pytest.raises(InputError, match="not a readable data pack"):
        unpack(tmp_path / "junk.npz", tmp_path / "out")
    assert not (tmp_path / "out").exists()
    np.savez(tmp_path / "other.npz", x=np.zeros(3))
    with pytest.raises(InputError, match="not a readable data pack"):
        read_pack(tmp_path / "other.npz")
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "keep.txt").write_text("mine")
    with pytest.raises(InputError, match="not empty"):
        unpack(tmp_path / "junk.npz", tmp_path / "full")
    assert (tmp_path / "full" / "keep.txt").read_text() == "mine"


def test_cli_pack_and_unpack(tmp_path):
    src = _folder(tmp_path / "src")

    def run(*args):
        return subprocess.run([sys.executable, "-m", "mld_core", "data", *args], cwd=REPO, capture_output=True,
                              text=True, timeout=120)

    r = run("pack", str(src), "--out", str(tmp_path / "p.npz"), "--splits", "train")
    assert r.returncode == 0 and "2 clips (+2 mirrored" in r.stdout
    r = run("unpack", str(tmp_path / "p.npz"), "--out", str(tmp_path / "out"), "--workers", "1")
    assert r.returncode == 0 and "2 clips + 2 mirrored" in r.stdout
    r = run("unpack", str(tmp_path / "missing.npz"), "--out", str(tmp_path / "out2"))
    assert r.returncode == 2 and r.stderr.strip().startswith("error:") and len(r.stderr.strip().splitlines()) == 1
    r = run("unpack", str(tmp_path / "p.npz"), "--out", str(tmp_path / "out3"), "--workers", "0")
    assert r.returncode == 2 and "--workers" in r.stderr and not (tmp_path / "out3").exists()
