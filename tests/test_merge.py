"""``data merge``: two prepared folders as one (splits kept, clashing ids prefixed, one Mean/Std, provenance), and
its refusals (nothing written)."""

from __future__ import annotations

import json

import numpy as np

from mld_core.cli import main
from mld_core.motion import features as F
from test_reliability import refused


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
    # refusals: nothing written
    refused(["data", "merge", a, b, "--out", out], tmp_path, capsys, "not empty")
    refused(["data", "merge", a, a, "--out", tmp_path / "m2"], tmp_path, capsys, "same folder twice")
    refused(["data", "merge", a, "--out", tmp_path / "m2"], tmp_path, capsys, "at least two")
    refused(["data", "merge", a, tmp_path / "nothing", "--out", tmp_path / "m2"], tmp_path, capsys, "not a HumanML3D")
    (b / "train.txt").write_text("c1\nmissing\n")
    refused(["data", "merge", a, b, "--out", tmp_path / "m3"], tmp_path, capsys, "no new_joint_vecs/missing.npy")
