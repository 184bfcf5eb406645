"""``data merge``: two prepared folders as one (splits kept, clashing ids prefixed, one Mean/Std, provenance), and
its refusals (every folder checked first, nothing written; of two runs racing for one --out, one wins)."""

from __future__ import annotations

import errno
import json
import os
import threading
from pathlib import Path

import numpy as np
import pytest

from mld_core.cli import main
from mld_core.data import terms
from mld_core.data import merge as merge_module
from mld_core.data.merge import MANIFEST
from mld_core.inputs import InputError
from mld_core.motion import features as F
from test_reliability import refused, snapshot


def _folder(root, ids, seed, actions=None):
    rng = np.random.default_rng(seed)
    (root / "new_joint_vecs").mkdir(parents=True)
    (root / "texts").mkdir()
    for split, names in ids.items():
        (root / f"{split}.txt").write_text("".join(f"{n}\n" for n in names))
        for n in names:
            np.save(root / "new_joint_vecs" / f"{n}.npy", rng.normal(size=(30, 263)).astype(np.float32))
            (root / "texts" / f"{n}.txt").write_text(f"a person does {n}.#a/DET#0.0#0.0\n")
    if actions:
        (root / "actions.json").write_text(json.dumps({"classes": sorted(set(actions.values())), "clips": actions}))
    return root


def test_merge_keeps_splits_prefixes_clashes_and_recomputes_stats(tmp_path, capsys):
    a = _folder(tmp_path / "bandai", {"train": ["c1", "c2"], "val": ["c3"], "test": ["c4"]}, 0, {"c1": "walk"})
    b = _folder(tmp_path / "cmu", {"train": ["c1", "j9"], "test": ["j8"]}, 1, {"j9": "jump"})
    out = tmp_path / "merged"
    assert main(["data", "merge", str(a), str(b), "--out", str(out)]) == 0
    train = (out / "train.txt").read_text().split()
    assert train == ["bandai_c1", "c2", "cmu_c1", "j9"]  # the shared id c1 is prefixed in both, the rest kept
    assert (out / "val.txt").read_text().split() == ["c3"] and (out / "test.txt").read_text().split() == ["c4", "j8"]
    prov = json.loads((out / "provenance.json").read_text())
    assert prov["cmu_c1"] == {"source": str(b), "id": "c1", "split": "train"}
    np.testing.assert_array_equal(np.load(out / "new_joint_vecs" / "cmu_c1.npy"), np.load(b / "new_joint_vecs" / "c1.npy"))
    feats = [np.load(out / "new_joint_vecs" / f"{i}.npy") for i in train]
    mean, std = F.mean_std(feats)
    np.testing.assert_allclose(np.load(out / "Mean.npy"), mean)
    np.testing.assert_allclose(np.load(out / "Std.npy"), std)
    assert json.loads((out / "actions.json").read_text())["clips"] == {"bandai_c1": "walk", "j9": "jump"}
    assert (out / "texts" / "j8.txt").read_text().startswith("a person does j8")
    # the README says what the folder holds: hours per source and split (30 feature frames a clip at 20 fps)
    readme = (out / "README.md").read_text()
    hours = 2 * 30 / 20 / 3600
    assert f"| train | {hours:.2f} | {hours:.2f} | {2 * hours:.2f} |" in readme and "| jump |" in readme
    assert not (out / "LICENSE").exists()  # neither source has one
    # refusals: nothing written
    refused(["data", "merge", a, b, "--out", out], tmp_path, capsys, "not empty")
    refused(["data", "merge", a, a, "--out", tmp_path / "m2"], tmp_path, capsys, "same folder twice")
    refused(["data", "merge", a, "--out", tmp_path / "m2"], tmp_path, capsys, "at least two")
    refused(["data", "merge", a, tmp_path / "nothing", "--out", tmp_path / "m2"], tmp_path, capsys, "not a HumanML3D")
    (b / "train.txt").write_text("c1\nmissing\n")
    refused(["data", "merge", a, b, "--out", tmp_path / "m3"], tmp_path, capsys, "no new_joint_vecs/missing.npy")


def test_folders_of_one_name_with_the_same_ids_keep_every_clip(tmp_path, capsys):
    ids = {"train": ["c1", "c2", "c3"], "test": ["c4", "c5", "c6"]}
    x, y = _folder(tmp_path / "x" / "data", ids, 0), _folder(tmp_path / "y" / "data", ids, 1)
    out = tmp_path / "M"
    assert main(["data", "merge", str(x), str(y), "--out", str(out)]) == 0
    merged = (out / "all.txt").read_text().split()
    assert len(merged) == 12 and len(set(merged)) == 12
    assert len(list((out / "new_joint_vecs").iterdir())) == 12  # none overwritten
    for source, prefix in ((x, "x_data"), (y, "y_data")):
        for cid in ids["train"] + ids["test"]:
            assert (out / "new_joint_vecs" / f"{prefix}_{cid}.npy").read_bytes() == \
                (source / "new_joint_vecs" / f"{cid}.npy").read_bytes()


def test_the_sources_licences_travel_with_the_merge(tmp_path):
    a = _folder(tmp_path / "bandai", {"train": ["c1"]}, 0)
    b = _folder(tmp_path / "cmu", {"train": ["j1"]}, 1)
    (a / "LICENSE").write_text("CC BY-NC 4.0 (Bandai Namco Research Inc.)\n")
    (b / "LICENSE").write_text("mocap.cs.cmu.edu terms\n")
    assert main(["data", "merge", str(a), str(b), "--out", str(tmp_path / "m")]) == 0
    text = (tmp_path / "m" / "LICENSE").read_text()
    assert "CC BY-NC 4.0" in text and "mocap.cs.cmu.edu" in text
    assert "`LICENSE`" in (tmp_path / "m" / "README.md").read_text()
    # the sources' terms joined: one that forbids commercial use makes the merge non-commercial; a source
    # without terms.json is of unknown terms
    terms.write(a, [terms.BANDAI])
    terms.write(b, [terms.CMU])
    assert main(["data", "merge", str(a), str(b), "--out", str(tmp_path / "m2")]) == 0
    assert terms.of_folder(tmp_path / "m2") == [terms.BANDAI, terms.CMU]
    assert terms.commercial_use(terms.of_folder(tmp_path / "m2")) is False
    (a / "terms.json").unlink()
    assert main(["data", "merge", str(a), str(b), "--out", str(tmp_path / "m3")]) == 0
    merged = terms.of_folder(tmp_path / "m3")
    assert merged[1] == terms.CMU and merged[0]["commercial"] is None and terms.commercial_use(merged) is None


def test_bandai_and_cmu_ids_that_do_not_clash_stay_as_they_are(tmp_path):
    bandai_ids = {"train": ["dataset-2_walk_normal_001", "Mdataset-2_walk_normal_001"], "test": ["dataset-1_bye_001"]}
    cmu_ids = {"train": ["01_01_00000_00196", "M01_01_00000_00196"], "val": ["02_03_00000_00120"]}
    a, b = _folder(tmp_path / "bandai", bandai_ids, 0), _folder(tmp_path / "cmu", cmu_ids, 1)
    assert main(["data", "merge", str(a), str(b), "--out", str(tmp_path / "m")]) == 0
    for source, ids in ((a, bandai_ids), (b, cmu_ids)):
        for split, names in ids.items():
            assert set(names) <= set((tmp_path / "m" / f"{split}.txt").read_text().split())
            for n in names:
                assert (tmp_path / "m" / "new_joint_vecs" / f"{n}.npy").read_bytes() == \
                    (source / "new_joint_vecs" / f"{n}.npy").read_bytes()


def _garbage_npy(a, b):
    (b / "new_joint_vecs" / "j9.npy").write_bytes(b"not a numpy file at all")


def _nan_features(a, b):
    feats = np.load(b / "new_joint_vecs" / "j8.npy")
    feats[3, 7] = np.nan
    np.save(b / "new_joint_vecs" / "j8.npy", feats)


def _kit_width(a, b):
    for n in ("c1", "j9", "j8"):
        np.save(b / "new_joint_vecs" / f"{n}.npy", np.zeros((30, 251), np.float32))


BROKEN_SOURCES = [
    (_garbage_npy, "cmu/new_joint_vecs/j9.npy is not a readable numpy array file"),
    (_nan_features, "cmu/new_joint_vecs/j8.npy holds NaN or infinite values"),
    (_kit_width, "cmu/new_joint_vecs/c1.npy has 251 features per frame, not HumanML3D's 263"),
    (lambda a, b: np.save(b / "new_joint_vecs" / "j8.npy", np.zeros(263, np.float32)), "has shape (263,)"),
    (lambda a, b: np.save(b / "new_joint_vecs" / "j8.npy", np.zeros((0, 263), np.float32)), "has shape (0, 263)"),
    (lambda a, b: (b / "new_joint_vecs" / "j8.npy").write_bytes(b"\x93NUMPY\x01\x00"), "not a readable numpy array"),
    (lambda a, b: (b / "train.txt").write_text("\n\n"), "cmu/train.txt names no clip"),
    (lambda a, b: (b / "train.txt").write_bytes(b"c1\nj\xe9\xff9\n"), "cmu/train.txt, line 2: not UTF-8"),
    (lambda a, b: (b / "test.txt").write_bytes(b"\xff\xfej8\n"), "cmu/test.txt, line 1: not UTF-8"),
    (lambda a, b: (b / "texts" / "j9.txt").write_bytes(b"a person \xff jumps"), "texts/j9.txt, line 1: not UTF-8"),
    (lambda a, b: (a / "actions.json").write_text("{garbage"), "bandai/actions.json is not valid JSON"),
    (lambda a, b: (a / "actions.json").write_text("[1, 2]"), "bandai/actions.json: expected"),
    (lambda a, b: (a / "actions.json").write_text('{"clips": {"c1": 3}}'), "bandai/actions.json: expected"),
    (lambda a, b: (a / "actions.json").write_text("[" * 100_000 + "]" * 100_000), "not valid JSON"),
    (lambda a, b: (b / "test.txt").write_text("j8\nc1\n"), "clip c1 is listed twice (also in train.txt)"),
    (lambda a, b: (b / "test.txt").write_text("../train\n"), "'../train' is not a clip id"),
    (lambda a, b: (b / "new_joints").mkdir() or (b / "new_joints" / "j9.npy").write_text("x"),
     "cmu/new_joints/j9.npy is not a readable numpy array"),
]


@pytest.mark.parametrize("breakage, words", BROKEN_SOURCES, ids=[w[:40] for _, w in BROKEN_SOURCES])
def test_every_folder_is_checked_before_anything_is_written(tmp_path, capsys, breakage, words):
    a = _folder(tmp_path / "bandai", {"train": ["c1", "c2"], "val": ["c3"]}, 0, {"c1": "walk"})
    b = _folder(tmp_path / "cmu", {"train": ["c1", "j9"], "test": ["j8"]}, 1)
    breakage(a, b)
    refused(["data", "merge", a, b, "--out", tmp_path / "new" / "merged"], tmp_path, capsys, words)


def test_ids_that_would_still_meet_are_refused(tmp_path, capsys):
    ids = {"train": ["c1"]}
    x, y, q = (_folder(tmp_path / p, ids, i) for i, p in enumerate(("x/data", "y/data", "q/x_data")))
    refused(["data", "merge", x, y, q, "--out", tmp_path / "m"], tmp_path, capsys,
            "would both prefix them with 'x_data_'")
    a, b = _folder(tmp_path / "a", ids, 3), _folder(tmp_path / "b", ids, 4)
    z = _folder(tmp_path / "z", {"train": ["a_c1"]}, 5)  # a's c1 becomes a_c1: z's own a_c1 would be lost
    refused(["data", "merge", a, b, z, "--out", tmp_path / "m"], tmp_path, capsys, "the merged id a_c1 would name two")


def test_an_output_that_cannot_be_written_is_one_line(tmp_path, capsys, monkeypatch):
    a = _folder(tmp_path / "bandai", {"train": ["c1"]}, 0)
    b = _folder(tmp_path / "cmu", {"train": ["j9"]}, 1)
    (tmp_path / "a_file").write_text("x")
    refused(["data", "merge", a, b, "--out", tmp_path / "a_file" / "m"], tmp_path, capsys, "is a file, not a folder")
    refused(["data", "merge", a, b, "--out", tmp_path / "a_file"], tmp_path, capsys, "exists and is not a folder")
    locked = tmp_path / "locked"
    locked.mkdir()
    access = os.access  # a folder this user may not write in (the tests may run as root, who may write anywhere)
    monkeypatch.setattr(os, "access", lambda p, mode, **kw: Path(p) != locked and access(p, mode, **kw))
    refused(["data", "merge", a, b, "--out", locked / "m"], tmp_path, capsys, f"the folder {locked} cannot be written")
    monkeypatch.undo()

    def disk_full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(merge_module.np, "save", disk_full)  # fails half-way: the folders it made go too
    refused(["data", "merge", a, b, "--out", tmp_path / "new" / "deeper" / "m"], tmp_path, capsys,
            "cannot write --out")


def test_two_merges_racing_for_one_out_have_one_winner(tmp_path, monkeypatch):
    a = _folder(tmp_path / "bandai", {"train": ["c1", "c2"]}, 0)
    b = _folder(tmp_path / "cmu", {"train": ["c1", "j9"]}, 1)
    out, barrier, results = tmp_path / "m", threading.Barrier(2, timeout=60), []
    from mld_core import fileio

    claim = fileio.claim_folder

    def claim_together(tmp, path):  # both runs have checked --out and built their folders: now both claim it
        barrier.wait()
        claim(tmp, path)

    monkeypatch.setattr(fileio, "claim_folder", claim_together)

    def run(sources):
        try:
            results.append(merge_module.merge(sources, out)["sources"])
        except InputError as exc:
            results.append(str(exc))

    runs = [threading.Thread(target=run, args=(s,)) for s in ([a, b], [b, a])]
    for r in runs:
        r.start()
    for r in runs:
        r.join()
    won = [r for r in results if isinstance(r, dict)]
    lost = [r for r in results if isinstance(r, str)]
    assert len(won) == 1 and len(lost) == 1 and "written by another run meanwhile" in lost[0], results
    order = list(won[0])  # the winner's sources, in its order: its files are all there, the loser's none
    assert json.loads((out / MANIFEST).read_text())["sources"] == order
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bandai", "cmu", "m"]  # no temporary folder left


def test_a_merge_refuses_an_out_another_run_wrote_meanwhile(tmp_path, capsys, monkeypatch):
    a = _folder(tmp_path / "bandai", {"train": ["c1"]}, 0)
    b = _folder(tmp_path / "cmu", {"train": ["j9"]}, 1)
    out = tmp_path / "m"
    out.mkdir()  # empty: may be used
    from mld_core import fileio

    claim, after = fileio.claim_folder, {}

    def other_run_first(tmp, path):  # between this run's check of --out and its claim, another run writes it
        (out / "theirs.txt").write_text("another run's output")
        after.update((k, v) for k, v in snapshot(tmp_path).items() if not k.startswith(Path(tmp).name))
        claim(tmp, path)

    monkeypatch.setattr(fileio, "claim_folder", other_run_first)
    code = main(["data", "merge", str(a), str(b), "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2 and err.count("error:") == 1 and "written by another run meanwhile" in err, err
    assert "Traceback" not in err and snapshot(tmp_path) == after  # theirs kept, nothing of this run left
