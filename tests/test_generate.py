"""`python -m mld_core generate` end to end on a tiny model, and its bad-input answers."""

from __future__ import annotations

import numpy as np
import pytest

from mld_core.checkpoint import DEFAULT_MODEL_DIR, load_config, save_json
from mld_core.cli import main
from mld_core.inputs import parse_prompt_lines, read_prompt_file
from mld_core.motion.bvh import read_bvh
from mld_core.testing import tiny_model


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    return tiny_model(tmp_path_factory.mktemp("tiny") / "model")


def test_prompt_lines_accept_mld_frame_prefixes():
    lines = parse_prompt_lines("# takes\n\n60 a person walks\na person waves\n  100   jumps twice  \n")
    assert [(p.text, p.seconds(4.0), p.line) for p in lines] == [
        ("a person walks", 3.0, 3), ("a person waves", 4.0, 4), ("jumps twice", 5.0, 5)]
    with pytest.raises(ValueError, match="no prompts"):
        parse_prompt_lines("\n# only a comment\n")
    with pytest.raises(ValueError, match="line 2: the length must be a positive whole number"):
        parse_prompt_lines("walk\n0 run\n")


def test_unreadable_prompt_file_names_the_line(tmp_path):
    bad = tmp_path / "p.txt"
    bad.write_bytes(b"a person walks\n\xff\xfe broken\n")
    with pytest.raises(ValueError, match="line 2: not UTF-8"):
        read_prompt_file(bad)
    with pytest.raises(ValueError, match="prompt file not found"):
        read_prompt_file(tmp_path / "missing.txt")


def test_generate_writes_npz_and_bvh(model, tmp_path, capsys):
    out = tmp_path / "take.npz"
    rc = main(["generate", "a person walks forward", "--model", str(model), "--seconds", "2", "--seed", "3",
               "--variants", "2", "--steps", "2", "--out", str(out), "--bvh", str(tmp_path / "take.bvh")])
    assert rc == 0
    data = np.load(out)
    assert data["features"].shape == (2, 40, 263) and data["features"].dtype == np.float32
    assert data["joints"].shape == (2, 40, 22, 3)
    assert data["lengths"].tolist() == [40, 40] and int(data["fps"]) == 20
    assert data["seeds"].tolist() == [3, 4] and str(data["model_id"]) == "tiny-text"
    assert list(data["prompts"]) == ["a person walks forward"] * 2
    bvhs = sorted(tmp_path.glob("take_*.bvh"))
    assert len(bvhs) == 2
    bvh = read_bvh(bvhs[0])
    assert bvh.num_frames == 40 and len(bvh.names) == 22
    assert bvh.joint_positions().shape == (40, 22, 3)


def test_generate_is_deterministic_per_seed(model, tmp_path):
    runs = []
    for name, seed in (("a", 1), ("b", 1), ("c", 2)):
        path = tmp_path / f"{name}.npz"
        assert main(["generate", "a person runs", "--model", str(model), "--seed", str(seed), "--steps", "2",
                     "--seconds", "2", "--out", str(path)]) == 0
        runs.append(np.load(path)["features"])
    np.testing.assert_array_equal(runs[0], runs[1])
    assert not np.allclose(runs[0], runs[2])


def test_generate_precision_option(model, tmp_path, capsys):
    paths = {}
    for precision in ("fp32", "bf16"):
        paths[precision] = tmp_path / f"{precision}.npz"
        assert main(["generate", "a person runs", "--model", str(model), "--seed", "1", "--steps", "2",
                     "--seconds", "2", "--precision", precision, "--out", str(paths[precision])]) == 0
    a, b = (np.load(paths[p])["features"] for p in ("fp32", "bf16"))
    assert a.shape == b.shape and np.isfinite(b).all() and not np.array_equal(a, b)
    with pytest.raises(SystemExit):
        main(["generate", "a person runs", "--model", str(model), "--precision", "fp8", "--out", str(tmp_path / "x.npz")])
    assert "invalid choice" in capsys.readouterr().err


def test_generate_prompt_file(model, tmp_path):
    prompts = tmp_path / "prompts.txt"
    prompts.write_text("60 a person walks\na person waves\n")
    out = tmp_path / "batch.npz"
    assert main(["generate", "--prompts", str(prompts), "--model", str(model), "--steps", "2", "--seconds", "2.5",
                 "--out", str(out)]) == 0
    assert np.load(out)["lengths"].tolist() == [60, 50]


@pytest.mark.parametrize("argv, message", [
    (["generate", "   "], "empty prompt"),
    (["generate", "walk", "--seconds", "0.5"], "seconds must be between"),
    (["generate", "walk", "--seconds", "60"], "seconds must be between"),
    (["generate", "walk", "--variants", "0"], "--variants"),
])
def test_bad_input_exits_2_with_a_message(model, tmp_path, capsys, argv, message):
    out = tmp_path / "x.npz"
    assert main(argv + ["--model", str(model), "--out", str(out)]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


def test_bad_prompt_file_and_model_exit_2(model, tmp_path, capsys):
    prompts = tmp_path / "p.txt"
    prompts.write_text("a person walks\n9999 far too long\n")
    assert main(["generate", "--prompts", str(prompts), "--model", str(model), "--out", str(tmp_path / "x.npz")]) == 2
    assert "line 2" in capsys.readouterr().err
    assert main(["generate", "walk", "--model", str(tmp_path / "nope"), "--out", str(tmp_path / "x.npz")]) == 2
    assert "model folder not found" in capsys.readouterr().err


def test_overlong_prompt_is_truncated_with_a_warning(model, tmp_path, capsys):
    long_prompt = "a person walks " + "!" * 280  # under the 300-character cap, over the 256-token encoder
    assert main(["generate", long_prompt, "--model", str(model), "--steps", "1", "--seconds", "2",
                 "--out", str(tmp_path / "x.npz")]) == 0
    assert "tokens; only the first" in capsys.readouterr().err


def test_unconditional_generation(model, tmp_path):
    out = tmp_path / "u.npz"
    assert main(["generate", "--unconditional", "--model", str(model), "--steps", "2", "--seconds", "2",
                 "--out", str(out)]) == 0
    assert np.isfinite(np.load(out)["joints"]).all()


@pytest.mark.skipif(not (DEFAULT_MODEL_DIR / "config.json").is_file(), reason="the bundled default model is not built")
def test_generate_with_the_bundled_default_model(tmp_path):
    paths = [tmp_path / f"{k}.npz" for k in "abc"]
    for path, seed in zip(paths, (0, 0, 1)):
        assert main(["generate", "a person waves the right hand", "--seconds", "3", "--seed", str(seed),
                     "--steps", "10", "--out", str(path)]) == 0
    a, b, c = (np.load(p) for p in paths)
    assert a["joints"].shape == (1, 60, 22, 3) and np.isfinite(a["joints"]).all()
    np.testing.assert_array_equal(a["features"], b["features"])
    assert not np.allclose(a["features"], c["features"])
    # a plausible human: feet near the floor, head about 1.4-1.9 m above them
    j = a["joints"][0]
    height = j[:, 15, 1] - np.minimum(j[:, 10, 1], j[:, 11, 1])
    assert 1.2 < float(np.median(height)) < 2.0


@pytest.mark.skipif(not (DEFAULT_MODEL_DIR / "config.json").is_file(), reason="the bundled default model is not built")
def test_a_take_that_turns_the_other_way_is_drawn_again_and_says_so(tmp_path, capsys):
    """Seed 41 of this caption turns left on the default model without its side contrast (v3.6 and v3.7 did); its
    second draw turns right, as asked. With the side contrast (v3.8's default) its first draw turns right."""
    import shutil

    prompt = "the person walks forward and turns to the right, with youthful energy."
    argv = ["generate", prompt, "--seconds", "6.6", "--seed", "41", "--threads", "2"]
    assert main(argv + ["--side-redraws", "0", "--out", str(tmp_path / "contrasted.npz")]) == 0
    assert "warning" not in capsys.readouterr().err  # the bundled model: the side contrast turns it right
    plain = shutil.copytree(DEFAULT_MODEL_DIR, tmp_path / "no_contrast")
    config = load_config(plain)
    assert config.side_contrast > 0
    config.side_contrast = 0.0
    save_json(plain / "config.json", config.to_dict())
    argv += ["--model", str(plain)]
    assert main(argv + ["--side-redraws", "0", "--out", str(tmp_path / "first.npz")]) == 0
    assert "warning: take 0 (seed 41): it turns left, not right as the prompt says" in capsys.readouterr().err
    assert main(argv + ["--out", str(tmp_path / "redrawn.npz")]) == 0
    err = capsys.readouterr().err
    assert "note: take 0 (seed 41) is draw 1 of its seed: the first did not turn right as the prompt says" in err
    assert "warning" not in err
    first, redrawn = np.load(tmp_path / "first.npz"), np.load(tmp_path / "redrawn.npz")
    assert first["draws"].tolist() == [0] and redrawn["draws"].tolist() == [1] and redrawn["seeds"].tolist() == [41]
    assert not np.allclose(first["joints"], redrawn["joints"])
