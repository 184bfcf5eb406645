"""Running pip for Blender's Python in the background (bpy-free).

:class:`DependencyInstaller` runs a list of commands one after the other on a thread, keeps the last output
line for the UI and ends with a one-sentence message. Nothing is run unless the user presses the button.
"""

from __future__ import annotations

import importlib.util
import subprocess
import sys
import threading
from pathlib import Path

from .env import pip_install_command


def install_commands(target: Path, *, python: str | None = None, cpu_only: bool = True) -> list[list[str]]:
    """ensurepip (when pip is missing) followed by the pip install into ``target``."""
    python = python or sys.executable
    commands = []
    if importlib.util.find_spec("pip") is None:
        commands.append([python, "-m", "ensurepip", "--upgrade"])
    commands.append(pip_install_command(target, python=python, cpu_only=cpu_only))
    return commands


class DependencyInstaller:
    def __init__(self):
        self._thread: threading.Thread | None = None
        self.running = False
        self.failed = False
        self.message = ""
        self.last_line = ""
        self.log: list[str] = []

    def start(self, commands: list[list[str]], on_done=None) -> bool:
        """Start the commands on a thread; False if an installation is already running."""
        if self.running:
            return False
        self.running, self.failed, self.message, self.last_line = True, False, "", ""
        self.log = []
        self._thread = threading.Thread(target=self._run, args=(commands, on_done), daemon=True, name="mld-pip")
        self._thread.start()
        return True

    def wait(self, timeout: float | None = None) -> bool:
        if self._thread is not None:
            self._thread.join(timeout)
        return not self.running

    def _run(self, commands, on_done) -> None:
        try:
            for cmd in commands:
                self.log.append("$ " + " ".join(cmd))
                proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
                for line in proc.stdout:
                    line = line.rstrip()
                    print(line)  # the system console shows the full pip output
                    self.log.append(line)
                    if line.strip():
                        self.last_line = line.strip()
                code = proc.wait()
                if code != 0:
                    self.failed = True
                    self.message = f"'{' '.join(cmd[:4])} ...' failed (exit {code}): {self.last_line}"
                    return
            self.message = "Dependencies installed"
        except OSError as exc:
            self.failed = True
            self.message = f"Cannot run {commands[0][0]}: {exc}"
        finally:
            self.running = False
            if on_done is not None:
                on_done(self)
