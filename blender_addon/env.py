"""Where things are and what is installed (bpy-free).

- The add-on's own folder, and where ``mld_core`` comes from: ``<add-on>/_vendor/mld_core`` inside the
  extension zip, the repository's ``mld_core`` when run from a checkout (``<repo>/blender_addon``).
- Which runtime dependencies are missing (torch, safetensors, tqdm, numpy), checked without importing them.
- The pip command that installs them for Blender's own Python into the add-on's user folder.
"""

from __future__ import annotations

import importlib.util
import os
import sys
from pathlib import Path

ADDON_DIR = Path(__file__).resolve().parent
VENDOR_DIR = ADDON_DIR / "_vendor"
REPO_DIR = ADDON_DIR.parent

from .worker.dependencies import (  # noqa: F401 - the add-on's identity and dependencies, for the Blender layer
    ADDON_ID,
    ADDON_VERSION,
    ADDON_VERSION_STRING,
    REQUIRED_MODULES,
    dependency_message,
    missing_modules,
)

# What the Preferences button installs; the CPU wheel index keeps torch small on Linux and Windows.
PIP_PACKAGES = ("torch==2.13.0", "safetensors>=0.4", "tqdm>=4.60")
TORCH_CPU_INDEX = "https://download.pytorch.org/whl/cpu"

# Folder (inside the add-on's user folder) that the dependency installer fills; added to sys.path.
USER_SITE_SUBDIR = "site-packages"


def mld_core_location() -> Path | None:
    """The folder that holds ``mld_core`` for this add-on: the vendored copy wins over a checkout."""
    for base in (VENDOR_DIR, REPO_DIR):
        if (base / "mld_core" / "__init__.py").is_file():
            return base
    return None


def setup_import_paths() -> Path | None:
    """Make ``import mld_core`` work: put the vendored copy (or the checkout) first on ``sys.path``."""
    base = mld_core_location()
    if base is None:
        return None
    text = str(base)
    if base == VENDOR_DIR:
        if text in sys.path:
            sys.path.remove(text)
        sys.path.insert(0, text)  # our own copy wins over any other mld_core
    elif importlib.util.find_spec("mld_core") is None:
        sys.path.insert(0, text)
    return base


def user_site_dir() -> Path | None:
    """The add-on's user folder for pip-installed dependencies (needs bpy; None outside Blender)."""
    try:
        import bpy  # noqa: F401  (only the path helper below)
    except ImportError:
        return None
    package = __package__ or ADDON_ID
    try:  # extensions (Blender 4.2+): <user extensions>/.user/<repo>/<id>/site-packages
        return Path(bpy.utils.extension_path_user(package, path=USER_SITE_SUBDIR, create=False))
    except (ValueError, AttributeError, RuntimeError):
        pass
    try:  # a legacy add-on: a folder in Blender's user scripts
        return Path(bpy.utils.user_resource("SCRIPTS", path=f"{ADDON_ID}_{USER_SITE_SUBDIR}"))
    except Exception:  # noqa: BLE001 - any failure just means there is no user folder
        return None


def add_user_site_packages(path: Path | None = None) -> Path | None:
    """Append the dependency folder (if it exists) to ``sys.path`` so modules installed there import."""
    path = path if path is not None else user_site_dir()
    if path is None or not Path(path).is_dir():
        return None
    text = str(path)
    if text not in sys.path:
        sys.path.append(text)
        importlib.invalidate_caches()
    return Path(path)


_unused: set[str] = set()


def pip_install_command(target: Path, *, python: str | None = None, cpu_only: bool = True) -> list[str]:
    """The pip command installing the dependencies for ``python`` (Blender's) into ``target``."""
    cmd = [python or sys.executable, "-m", "pip", "install", "--upgrade", "--no-input", "--target", str(target)]
    if cpu_only and sys.platform != "darwin":
        cmd += ["--extra-index-url", TORCH_CPU_INDEX]
    return cmd + list(PIP_PACKAGES)


def bundled_model_dir() -> Path | None:
    """The default model shipped with mld_core (``mld_core/weights/default``), if present."""
    base = mld_core_location()
    if base is None:
        return None
    path = base / "mld_core" / "weights" / "default"
    return path if path.is_dir() else None


def model_dir_override() -> str | None:
    """``MLD_MODEL_DIR`` from the environment (used when the preferences leave the model folder empty)."""
    value = os.environ.get("MLD_MODEL_DIR", "").strip()
    return value or None


def env_flag(name: str) -> bool:
    return os.environ.get(name, "").strip().lower() in {"1", "true", "yes", "on"}
