"""Running bpy (Blender as a Python module) in a subprocess for tests.

bpy is heavy, keeps global state and writes user configuration, so every bpy test runs a script in a fresh
``python`` process with a timeout and ``BLENDER_USER_RESOURCES`` pointing at a temporary folder. A script
hands results back by printing one line ``RESULT <json>`` (see :func:`result_line`).
"""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
MARK = "RESULT "


def has_bpy() -> bool:
    return importlib.util.find_spec("bpy") is not None


requires_bpy = pytest.mark.skipif(not has_bpy(), reason="needs the bpy module (pip install bpy==5.0.1)")


def result_line() -> str:
    """Source of a helper the scripts use: ``emit(obj)`` prints the RESULT line."""
    return textwrap.dedent(
        f"""
        import json as _json, sys as _sys
        def emit(obj):
            _sys.stdout.write({MARK!r} + _json.dumps(obj) + "\\n")
            _sys.stdout.flush()
        """
    )


# The start of a script that uses the add-on from this checkout (``{tests}`` for the test helpers): a factory-fresh
# Blender with the add-on enabled. Joined before a script's own lines, formatted with repo= and tests=.
ADDON_PRELUDE = r"""
import sys
sys.path.insert(0, {repo!r})
sys.path.insert(0, {tests!r})
import bpy, addon_utils
bpy.ops.wm.read_factory_settings(use_empty=True)
addon_utils.enable("blender_addon", default_set=True)
"""


def addon_script(body: str, **fields) -> str:
    """``ADDON_PRELUDE`` + ``body``, formatted for this checkout and with ``fields`` (``body`` doubles its literal
    braces)."""
    return (ADDON_PRELUDE + body).format(repo=str(REPO), tests=str(REPO / "tests"), **fields)


def bpy_env(user_dir: Path, **extra) -> dict:
    env = dict(os.environ)
    env["BLENDER_USER_RESOURCES"] = str(user_dir)
    env.setdefault("OMP_NUM_THREADS", "1")
    env["PYTHONDONTWRITEBYTECODE"] = "1"
    env.pop("MLD_MODEL_DIR", None)
    env.update({k: str(v) for k, v in extra.items()})
    return env


def run_python(args, *, user_dir: Path, timeout: float = 120, cwd: Path = REPO, **env) -> subprocess.CompletedProcess:
    """Run ``python args...`` with the bpy environment; returns the finished process (no check)."""
    user_dir.mkdir(parents=True, exist_ok=True)
    return subprocess.run(
        [sys.executable, *map(str, args)],
        cwd=cwd,
        env=bpy_env(user_dir, **env),
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def run_bpy_script(source: str, tmp_path: Path, *, timeout: float = 120, name: str = "script.py", **env) -> dict:
    """Run a bpy script (``emit`` available) in a subprocess; returns its RESULT object. Fails the test with
    the process output if the script fails or emits nothing."""
    script = tmp_path / name
    script.write_text(result_line() + textwrap.dedent(source), encoding="utf-8")
    proc = run_python([script], user_dir=tmp_path / "blender_user", timeout=timeout, **env)
    results = [line[len(MARK):] for line in proc.stdout.splitlines() if line.startswith(MARK)]
    if proc.returncode != 0 or not results:
        pytest.fail(
            f"bpy script failed (exit {proc.returncode})\n--- stdout ---\n{proc.stdout[-4000:]}\n"
            f"--- stderr ---\n{proc.stderr[-4000:]}"
        )
    return json.loads(results[-1])
