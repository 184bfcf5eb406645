"""What the add-on is and what it needs (bpy-free, imports nothing): its id and version, and which runtime
dependencies of mld_core are missing, checked without importing them."""

from __future__ import annotations

import importlib.util
import sys

ADDON_ID = "mld_motion"
ADDON_VERSION = (0, 1, 0)
ADDON_VERSION_STRING = ".".join(map(str, ADDON_VERSION))

# Runtime dependencies of mld_core (numpy ships with Blender; the others may have to be installed).
REQUIRED_MODULES = ("numpy", "torch", "safetensors", "tqdm")
_found: set[str] = set()


def missing_modules(names: tuple[str, ...] = REQUIRED_MODULES) -> list[str]:
    """Names among ``names`` that cannot be imported (checked with find_spec, nothing is imported).

    Found modules are remembered (the panel asks on every redraw); missing ones are looked up again, so
    installing them takes effect without a restart.
    """
    missing = []
    for name in names:
        if name in _found or sys.modules.get(name) is not None:
            continue
        try:
            spec = importlib.util.find_spec(name)
        except (ImportError, ValueError):
            spec = None
        if spec is None:
            missing.append(name)
        else:
            _found.add(name)
    return missing


def dependency_message(missing: list[str]) -> str:
    """One sentence telling the user what is missing and how to get it."""
    if not missing:
        return ""
    return (
        f"Missing Python module{'s' if len(missing) > 1 else ''} {', '.join(missing)} in Blender's Python: "
        "open Edit > Preferences > Add-ons > MLD Text to Motion and press 'Install dependencies' "
        "(downloads PyTorch CPU, about 200 MB), or install the zip built with bundled wheels"
    )
