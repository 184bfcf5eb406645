"""research/v4/device_run.sh end to end on the CPU: a GPU sitting is rare and short, so the script it runs is
exercised here on a tiny pack (scripts/pack_for_device.py) with the bundled VAE, a few seconds per stage."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tarfile
from io import BytesIO
from pathlib import Path

import numpy as np
import pytest
from safetensors.torch import load_file

from test_pack import _folder
from test_text_encoder import needs_package

REPO = Path(__file__).resolve().parents[1]
BUNDLED = REPO / "mld_core" / "weights" / "default"
GPU_CONFIG = REPO / "research" / "v4" / "vae_gpu.json"

pytestmark = [
    pytest.mark.slow,
    needs_package,
    pytest.mark.skipif(shutil.which("bash") is None, reason="needs bash"),
    pytest.mark.skipif(not (BUNDLED / "vae.safetensors").is_file(), reason="needs the bundled model's VAE"),
]


def _run(args: list[str], env: dict | None = None, timeout: int = 600) -> subprocess.CompletedProcess:
    return subprocess.run(args, cwd=REPO, capture_output=True, text=True, timeout=timeout,
                          env={**os.environ, "PYTHON": sys.executable, **(env or {})})


def _unpack_parts(out: Path, into: Path) -> list[str]:
    parts = sorted(out.glob("v4.tar.part-*"))
    assert parts, "the sitting brought nothing back"
    blob = b"".join(p.read_bytes() for p in parts)
    with tarfile.open(fileobj=BytesIO(blob)) as tar:
        tar.extractall(into, filter="data")
        return [m.name.removeprefix("./") for m in tar.getmembers()]


@pytest.fixture(scope="module")
def pack(tmp_path_factory) -> Path:
    """A tiny folder packed for the device, with the bundled VAE beside it."""
    root = tmp_path_factory.mktemp("pack")
    data = _folder(root / "data")
    packed = _run([sys.executable, "scripts/pack_for_device.py", "--data", str(data), "--out", str(root / "pack"),
                   "--vae", str(BUNDLED)])
    assert packed.returncode == 0, packed.stderr[-2000:]
    return root / "pack"


@pytest.fixture(scope="module")
def sitting(tmp_path_factory, pack):
    """One sitting on the CPU: 0.02 minutes of VAE, then the three denoisers 0.02 minutes each."""
    root = tmp_path_factory.mktemp("sitting")
    config = {**json.loads(GPU_CONFIG.read_text()), "label_boost": {"x": 6}}  # the tiny pack's one action label
    (root / "vae.json").write_text(json.dumps(config))
    done = _run(["bash", "research/v4/device_run.sh", str(pack / "data.npz"), str(pack / "minilm"), str(pack / "vae"),
                 str(root / "out"), "0.02", "0.02", "cpu"],
                env={"V4_WORK": str(root / "work"), "V4_VAE_CONFIG": str(root / "vae.json")})
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-2000:]
    back = root / "back"
    names = _unpack_parts(root / "out", back)
    return back, names, done.stdout


def test_a_sitting_brings_back_the_vae_three_denoisers_and_their_logs(sitting):
    back, names, stdout = sitting
    for run in ("den_a", "den_b", "den_c"):
        assert f"{run}: done" in stdout
        assert {f"export_{run}/config.json", f"export_{run}/denoiser.safetensors", f"{run}_log.jsonl"} <= set(names)
        assert f"export_{run}/vae.safetensors" not in names  # the VAE travels once, as vae_fp16
    assert {"vae_log.jsonl", "vae_train_config.json", "vae_fp16.safetensors"} <= set(names)
    assert json.loads((back / "vae_train_config.json").read_text())["label_boost"] == {"x": 6.0}  # V4_VAE_CONFIG's
    vae, bundled = load_file(back / "vae_fp16.safetensors"), load_file(BUNDLED / "vae.safetensors")
    assert vae.keys() == bundled.keys()
    assert all(str(v.dtype) == "torch.float16" for v in vae.values() if v.is_floating_point())
    assert any(not np.array_equal(vae[k].float().numpy(), bundled[k].float().numpy()) for k in vae)  # it trained


def test_the_exports_put_together_generate(sitting):
    from mld_core.pipeline import MLDPipeline

    back, _, _ = sitting
    for run in ("den_a", "den_c"):
        shutil.copy(back / "vae_fp16.safetensors", back / f"export_{run}" / "vae.safetensors")
    text = MLDPipeline.from_pretrained(back / "export_den_a")(["a person does a"], seconds=2.0, num_inference_steps=3)
    assert text.joints.shape == (1, 40, 22, 3) and np.isfinite(text.joints).all()
    action = MLDPipeline.from_pretrained(back / "export_den_c")
    out = action(["x"], seconds=2.0, actions=["x"], num_inference_steps=3)
    assert out.joints.shape == (1, 40, 22, 3) and np.isfinite(out.joints).all()


def test_a_vae_from_scratch_owes_nothing_to_the_bundled_one(tmp_path, pack):
    done = _run(["bash", "research/v4/device_run.sh", str(pack / "data.npz"), str(pack / "minilm"), "scratch",
                 str(tmp_path / "out"), "0.02", "0", "cpu"], env={"V4_WORK": str(tmp_path / "work")})
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-2000:]
    assert "from scratch" in done.stdout and "brings back the VAE alone" in done.stdout
    names = _unpack_parts(tmp_path / "out", tmp_path / "back")
    assert "vae_fp16.safetensors" in names and not any(n.startswith("export_") for n in names)
    config = json.loads((tmp_path / "back" / "vae_train_config.json").read_text())
    assert config["init"] is None
    # the architecture the denoisers expect: the bundled model's latent, tensor for tensor
    vae, bundled = load_file(tmp_path / "back" / "vae_fp16.safetensors"), load_file(BUNDLED / "vae.safetensors")
    assert {k: v.shape for k, v in vae.items()} == {k: v.shape for k, v in bundled.items()}


def test_a_vae_from_scratch_needs_minutes(tmp_path):
    done = _run(["bash", "research/v4/device_run.sh", "p.npz", "minilm", "scratch", str(tmp_path / "out"), "0", "3"],
                env={"V4_WORK": str(tmp_path / "work")})
    assert done.returncode == 2 and "needs VAE_MINUTES above 0" in done.stderr
    assert not (tmp_path / "work").exists()


def test_bad_minutes_are_refused_before_anything_runs(tmp_path):
    done = _run(["bash", "research/v4/device_run.sh", "p.npz", "minilm", "vae", str(tmp_path / "out"), "seven"],
                env={"V4_WORK": str(tmp_path / "work")})
    assert done.returncode == 2 and "minutes must be a number" in done.stderr
    assert not (tmp_path / "work").exists()


def test_a_missing_vae_config_is_refused_before_anything_runs(tmp_path):
    done = _run(["bash", "research/v4/device_run.sh", "p.npz", "minilm", "vae", str(tmp_path / "out")],
                env={"V4_WORK": str(tmp_path / "work"), "V4_VAE_CONFIG": str(tmp_path / "nope.json")})
    assert done.returncode == 2 and "no VAE config at" in done.stderr
    assert not (tmp_path / "work").exists() and not (tmp_path / "out").exists()


def test_the_boosted_gpu_config_is_the_plain_one_with_kicks_and_throws_drawn_more_often():
    boosted = json.loads((GPU_CONFIG.parent / "vae_gpu_boost.json").read_text())
    assert boosted.pop("label_boost") == {"kick": 6, "throw": 20}
    assert boosted == json.loads(GPU_CONFIG.read_text())


@pytest.mark.parametrize("out", ["work", "work/out", "."])
def test_an_out_that_holds_or_is_inside_the_run_folders_is_refused(tmp_path, out):
    done = _run(["bash", "research/v4/device_run.sh", "p.npz", "minilm", "vae", str(tmp_path / out)],
                env={"V4_WORK": str(tmp_path / "work")})
    assert done.returncode == 2 and "must not hold one another" in done.stderr
    assert not (tmp_path / "work").exists()
