"""research/average_denoisers.py: a model folder whose denoiser is the weighted mean of folders sharing one VAE."""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file

from mld_core.testing import tiny_model

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "research"))

from average_denoisers import main  # noqa: E402


@pytest.fixture
def folders(tmp_path):
    """a and b share a's VAE and config; b's denoiser is another seed's; c has its own VAE."""
    a, c = tiny_model(tmp_path / "a", seed=0), tiny_model(tmp_path / "c", seed=1)
    b = tmp_path / "b"
    shutil.copytree(a, b)
    shutil.copyfile(c / "denoiser.safetensors", b / "denoiser.safetensors")
    return a, b, c


def test_the_average_is_the_weighted_mean_and_the_rest_is_the_first_folder(folders, tmp_path, capsys):
    from mld_core.pipeline import MLDPipeline

    a, b, _ = folders
    out = tmp_path / "avg"
    assert main([str(a), str(b), "--out", str(out), "--weights", "0.25,0.75", "--model-id", "soup"]) == 0
    da, db, avg = (load_file(f / "denoiser.safetensors") for f in (a, b, out))
    assert avg.keys() == da.keys() and any(not torch.equal(da[k], db[k]) for k in da)
    for k in da:
        assert avg[k].dtype == da[k].dtype
        torch.testing.assert_close(avg[k], 0.25 * da[k] + 0.75 * db[k])
    assert (out / "vae.safetensors").read_bytes() == (a / "vae.safetensors").read_bytes()
    cfg = json.loads((out / "config.json").read_text())
    assert cfg["model_id"] == "soup" and cfg["provenance"]["denoiser_average"] == {
        "models": ["tiny-text", "tiny-text"], "weights": [0.25, 0.75]}
    # weights 1, 0 give the first model's motions exactly
    one = tmp_path / "one"
    assert main([str(a), str(b), "--out", str(one), "--weights", "1,0"]) == 0
    capsys.readouterr()
    kw = dict(seconds=2.0, seed=3, num_inference_steps=2)
    same, first, other = (torch.as_tensor(MLDPipeline.from_pretrained(f)(["a person walks"], **kw).joints)
                          for f in (one, a, out))
    assert torch.equal(same, first) and not torch.equal(same, other)


def test_folders_that_do_not_share_a_vae_or_bad_weights_are_refused_and_leave_nothing(folders, tmp_path, capsys):
    a, b, c = folders
    out = tmp_path / "avg"
    assert main([str(a), str(c), "--out", str(out)]) == 2
    assert "VAE differs" in capsys.readouterr().err and not out.exists()
    for weights in ("0.5", "0.7,0.7", "-0.5,1.5", "x,y", "nan,nan", "inf,-inf"):
        assert main([str(a), str(b), "--out", str(out), f"--weights={weights}"]) == 2
        assert capsys.readouterr().err.startswith("error: ") and not out.exists()
    assert main([str(a), str(b), "--out", str(tmp_path / "no" / "avg")]) == 2
    assert "is not a folder" in capsys.readouterr().err
    out.mkdir()
    assert main([str(a), str(b), "--out", str(out)]) == 2
    assert "exists" in capsys.readouterr().err and list(out.iterdir()) == []
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a", "avg", "b", "c"]  # no temporary folder left


def test_only_named_modules_are_averaged_and_the_rest_is_the_first_folders(folders, tmp_path, capsys):
    a, b, _ = folders
    out = tmp_path / "text"
    assert main([str(a), str(b), "--out", str(out), "--weights", "0,1", "--only", "text_proj,token_proj"]) == 0
    da, db, got = (load_file(f / "denoiser.safetensors") for f in (a, b, out))
    moved = [k for k in da if k.split(".")[0] in ("text_proj", "token_proj")]
    assert moved and len(moved) < len(da)
    for k in da:
        assert torch.equal(got[k], db[k] if k in moved else da[k])
    assert json.loads((out / "config.json").read_text())["provenance"]["denoiser_average"]["modules"] == [
        "text_proj", "token_proj"]
    capsys.readouterr()
    assert main([str(a), str(b), "--out", str(tmp_path / "bad"), "--only", "text_projection"]) == 2
    assert "no module text_projection" in capsys.readouterr().err and not (tmp_path / "bad").exists()
