"""Loading HumanML3D-format folders (263-d and KIT's 251-d), sampling items, collating batches."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from mld_core.data.dataset import (
    Caption,
    DatasetError,
    MotionDataset,
    balanced_weights,
    collate,
    load_mean_std,
    load_split,
    parse_caption_line,
    read_actions,
)


def _write_folder(root, dim=263, actions=True):
    """A tiny folder: clip lengths 50, 30 (too short for min 40), 250 (too long for max 200), 120 with spans."""
    rng = np.random.default_rng(0)
    (root / "new_joint_vecs").mkdir(parents=True)
    (root / "texts").mkdir()
    lengths = {"000001": 50, "000002": 30, "000003": 250, "000004": 120, "M000001": 50}
    texts = {
        "000001": ["a person walks forward.#a/DET person/NOUN walks/VERB forward/ADV#0.0#0.0",
                   "someone strolls ahead.#someone/PRON strolls/VERB ahead/ADV#0.0#0.0"],
        "000002": ["a short clip.#a/DET short/ADJ clip/NOUN#0.0#0.0"],
        "000003": ["a long clip.#a/DET long/ADJ clip/NOUN#0.0#0.0"],
        # 120 frames = 6 s: one span of 1..4 s (40 frames), one too short (0.5 s), one broken (NaN)
        "000004": ["a person jumps.#a/DET person/NOUN jumps/VERB#1.0#3.0",
                   "a person blinks.#a/DET person/NOUN blinks/VERB#2.0#2.5",
                   "a person waves.#a/DET person/NOUN waves/VERB#nan#nan"],
        "M000001": ["a person walks forward.#a/DET person/NOUN walks/VERB forward/ADV#0.0#0.0"],
    }
    for cid, n in lengths.items():
        np.save(root / "new_joint_vecs" / f"{cid}.npy", rng.normal(size=(n, dim)).astype(np.float32))
        (root / "texts" / f"{cid}.txt").write_text("\n".join(texts[cid]) + "\n")
    (root / "train.txt").write_text("000001\n000002\n000003\n000004\nM000001\n000099\n")  # 000099: missing
    (root / "val.txt").write_text("000004\n")
    (root / "test.txt").write_text("")
    np.save(root / "Mean.npy", np.full(dim, 0.5, np.float32))
    np.save(root / "Std.npy", np.full(dim, 2.0, np.float32))
    if actions:
        (root / "actions.json").write_text(json.dumps({
            "classes": ["jump", "walk"],
            "clips": {"000001": "walk", "M000001": "walk", "000004": "jump"},
            "styles": {"000001": "normal"},
        }))
    return root


def test_parse_caption_line():
    c = parse_caption_line("a man kicks.#a/DET man/NOUN kicks/VERB#1.5#3.0\n")
    assert c == Caption("a man kicks.", 1.5, 3.0, ("a/DET", "man/NOUN", "kicks/VERB"))
    assert c.frames(20, 100) == (30, 60)
    assert not c.whole_clip
    whole = parse_caption_line("a man kicks.#a/DET#0.0#0.0")
    assert whole.whole_clip and whole.frames(20, 100) == (0, 100)
    assert parse_caption_line("just text").whole_clip
    assert parse_caption_line("bad times#x#nan#nan").whole_clip
    assert parse_caption_line("   \n") is None


def test_load_split_filters_and_parses(tmp_path):
    root = _write_folder(tmp_path / "h3d")
    with pytest.warns(UserWarning, match="000099"):
        clips = load_split(root, "train", min_frames=40, max_frames=200)
    assert [c.id for c in clips] == ["000001", "000004", "M000001"]
    c1, c4, m1 = clips
    assert c1.features.dtype == np.float32 and c1.features.shape == (50, 263)
    assert [c.text for c in c1.captions] == ["a person walks forward.", "someone strolls ahead."]
    assert c1.action == "walk" and c1.style == "normal" and m1.action == "walk" and c4.action == "jump"
    # the 0.5 s span is shorter than 40 frames: dropped; the NaN span becomes a whole-clip caption
    assert [(c.text, c.start_s, c.end_s) for c in c4.captions] == [
        ("a person jumps.", 1.0, 3.0), ("a person waves.", 0.0, 0.0)]
    everything = load_split(root, "val")  # defaults keep short and long clips
    assert [c.id for c in everything] == ["000004"]
    with pytest.warns(UserWarning):
        no_max = [c.id for c in load_split(root, "train", min_frames=1)]
    assert no_max == ["000001", "000002", "000003", "000004", "M000001"]


def test_uncaptioned_clips_are_kept_only_when_asked(tmp_path):
    root = _write_folder(tmp_path / "h3d")
    np.save(root / "new_joint_vecs" / "000005.npy", np.zeros((60, 263), np.float32))
    (root / "texts" / "000005.txt").write_text("")  # a window nobody could caption
    np.save(root / "new_joint_vecs" / "000006.npy", np.zeros((60, 263), np.float32))  # no texts file at all
    (root / "val.txt").write_text("000004\n000005\n000006\n")
    with pytest.warns(UserWarning, match="000006"):
        assert [c.id for c in load_split(root, "val", min_frames=40)] == ["000004"]  # the denoiser's view
    motion = load_split(root, "val", min_frames=40, captioned=False)  # the VAE's view
    assert [c.id for c in motion] == ["000004", "000005", "000006"]
    assert motion[1].captions == [] and motion[2].captions == []


def test_kit_251_features_and_missing_actions(tmp_path):
    root = _write_folder(tmp_path / "kit", dim=251, actions=False)
    with pytest.warns(UserWarning):
        clips = load_split(root, "train", min_frames=24, max_frames=200)
    assert {c.features.shape[1] for c in clips} == {251}
    assert all(c.action is None and c.fps == 12.5 for c in clips)
    assert read_actions(root) is None
    mean, std = load_mean_std(root)
    assert mean.shape == (251,) and std.shape == (251,)


def test_bad_folders_raise_dataset_error(tmp_path):
    with pytest.raises(DatasetError, match="does not exist"):
        load_split(tmp_path / "nope", "train")
    root = _write_folder(tmp_path / "h3d")
    with pytest.raises(DatasetError, match="no dev.txt"):
        load_split(root, "dev")
    (root / "Std.npy").unlink()
    with pytest.raises(DatasetError, match="Std.npy"):
        load_mean_std(root)
    (root / "actions.json").write_text("{not json")
    with pytest.raises(DatasetError):
        read_actions(root)


def test_dataset_items_normalise_crop_and_use_caption_spans(tmp_path):
    root = _write_folder(tmp_path / "h3d")
    with pytest.warns(UserWarning):
        clips = load_split(root, "train", min_frames=40, max_frames=200)
    mean, std = load_mean_std(root)
    ds = MotionDataset(clips, mean, std, max_frames=32, seed=0)
    assert len(ds) == 3 and ds.classes == ["jump", "walk"]
    item = ds[0]
    assert item["length"] == 32 and item["features"].shape == (32, 263)
    expected = (clips[0].features[item["start"]: item["start"] + 32] - 0.5) / 2.0
    np.testing.assert_allclose(item["features"].numpy(), expected, rtol=1e-6)
    assert item["text"] in {"a person walks forward.", "someone strolls ahead."}
    assert item["action"] == "walk" and item["action_index"] == 1
    # Seeded: the same (seed, epoch, index) gives the same item; other epochs differ somewhere.
    again = ds[0]
    assert again["start"] == item["start"] and again["text"] == item["text"]
    starts = set()
    for epoch in range(8):
        ds.epoch = epoch
        starts.add(ds[0]["start"])
    assert len(starts) > 1
    # The spanned caption selects frames 20..60 of clip 000004; the whole-clip one may start anywhere.
    ds_full = MotionDataset(clips, max_frames=None, seed=1)
    seen = set()
    for epoch in range(30):
        ds_full.epoch = epoch
        it = ds_full[1]
        seen.add(it["text"])
        if it["text"] == "a person jumps.":
            assert it["start"] == 20 and it["length"] == 40
            np.testing.assert_array_equal(it["features"].numpy(), clips[1].features[20:60])
        else:
            assert it["length"] == 120 and it["start"] == 0
    assert seen == {"a person jumps.", "a person waves."}


def test_crop_lengths_and_unit_length(tmp_path):
    root = _write_folder(tmp_path / "h3d")
    with pytest.warns(UserWarning):
        clips = load_split(root, "train", min_frames=40, max_frames=200)
    ds = MotionDataset(clips, crop_frames=(8, 30), unit_length=4, seed=3)
    lengths = set()
    for epoch in range(40):
        ds.epoch = epoch
        for i in range(len(ds)):
            it = ds[i]
            assert 8 <= it["length"] <= 30 and it["length"] % 4 == 0
            assert it["features"].shape[0] == it["length"]
            lengths.add(it["length"])
    assert len(lengths) > 3
    unseeded = MotionDataset(clips, max_frames=20)
    torch.manual_seed(0)
    a = [unseeded[0]["start"] for _ in range(10)]
    torch.manual_seed(0)
    assert a == [unseeded[0]["start"] for _ in range(10)]
    with pytest.raises(ValueError):
        MotionDataset(clips, crop_frames=(10, 5))
    with pytest.raises(DatasetError):
        MotionDataset([])


def test_collate_pads_and_returns_lengths(tmp_path):
    root = _write_folder(tmp_path / "h3d")
    with pytest.warns(UserWarning):
        clips = load_split(root, "train", min_frames=40, max_frames=200)
    ds = MotionDataset(clips, max_frames=None, seed=0)
    batch = collate([ds[0], ds[1]])
    lengths = batch["lengths"].tolist()
    assert lengths[0] == 50 and lengths[1] in (40, 120)
    assert batch["features"].shape == (2, max(lengths), 263)
    assert batch["mask"].sum(1).tolist() == lengths
    assert torch.all(batch["features"][0, 50:] == 0)
    assert batch["ids"] == ["000001", "000004"] and batch["actions"] == ["walk", "jump"]
    assert batch["action_index"].tolist() == [1, 0]
    loader = torch.utils.data.DataLoader(ds, batch_size=3, collate_fn=collate)
    (only,) = list(loader)
    assert only["features"].shape[0] == 3


def test_balanced_weights_equalise_labels(tmp_path):
    root = _write_folder(tmp_path / "h3d")
    with pytest.warns(UserWarning):
        clips = load_split(root, "train", min_frames=40, max_frames=200)
    w = balanced_weights(clips)  # walk x2, jump x1
    assert w.tolist() == [0.5, 1.0, 0.5]
