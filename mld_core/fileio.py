"""Writing files so that a reader never sees half of one: a temporary file in the same folder, then a rename
(one file: :func:`atomic_write`; several that must appear together or not at all: :class:`OutputSet`; a whole
folder built under a temporary name: :func:`claim_folder`)."""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path
from typing import Callable


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def atomic_write(path: str | os.PathLike, write: Callable[[str], None], suffix: str = ".tmp") -> Path:
    """Call ``write(tmp_path)``, give the file ordinary permissions (0666 minus the umask; mkstemp makes 0600),
    then rename it onto ``path``. On any error the temporary file is removed and ``path`` is left untouched.
    ``suffix`` names the temporary file for writers that pick a format from the name."""
    path = Path(path)
    if path.is_dir():
        raise IsADirectoryError(f"{path} is a folder; name a file")
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=suffix)
    os.close(fd)
    try:
        write(tmp)
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return path


def make_parents(folder: Path) -> list[Path]:
    """Make ``folder`` and the folders above it that are missing; returns those made, outermost first."""
    missing = []
    while not folder.exists():
        missing.append(folder)
        folder = folder.parent
    for f in reversed(missing):
        f.mkdir()
    return missing[::-1]


class OutputSet:
    """Several outputs written beside their targets under temporary names, then put in place all together or not
    at all. Without ``overwrite`` each target is claimed exclusively at commit time (a hard link, which fails if the
    name exists), so of two runs racing for one path only one wins and the other leaves nothing behind.

        with OutputSet(overwrite=False) as outputs:
            outputs.stage(npz_path, write_npz)
            outputs.stage(bvh_path, write_bvh)
        # leaving the block without an error commits; an error discards every staged file
    """

    def __init__(self, overwrite: bool = False):
        self.overwrite = overwrite
        self._staged: list[tuple[str, Path]] = []
        self._made_dirs: list[Path] = []

    def stage(self, path: str | os.PathLike, write: Callable[[str], None], suffix: str = ".tmp") -> Path:
        """Call ``write(tmp_path)`` now; the file takes the name ``path`` at :meth:`commit`."""
        path = Path(path)
        self._make_parent(path.parent)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=suffix)
        os.close(fd)
        self._staged.append((tmp, path))
        write(tmp)
        os.chmod(tmp, 0o666 & ~_umask())
        return path

    def commit(self) -> list[Path]:
        placed: list[Path] = []
        try:
            for tmp, path in self._staged:
                if self.overwrite:
                    os.replace(tmp, path)
                else:
                    _claim(tmp, path)
                placed.append(path)
        except BaseException:
            for path in placed:
                if not self.overwrite:
                    path.unlink(missing_ok=True)
            self.discard()
            raise
        self._staged.clear()
        return placed

    def discard(self) -> None:
        for tmp, _ in self._staged:
            if os.path.exists(tmp):
                os.unlink(tmp)
        self._staged.clear()
        for folder in reversed(self._made_dirs):
            try:
                folder.rmdir()
            except OSError:
                pass
        self._made_dirs.clear()

    def _make_parent(self, folder: Path) -> None:
        self._made_dirs += make_parents(folder)

    def __enter__(self) -> "OutputSet":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.commit()
        else:
            self.discard()


def _claim(tmp: str, path: Path) -> None:
    """Give ``tmp`` the name ``path`` only if no file has it (FileExistsError otherwise), then drop ``tmp``."""
    try:
        os.link(tmp, path)
    except FileExistsError:
        raise FileExistsError(f"{path} exists (written by another run?); pass --overwrite to replace it") from None
    except OSError:  # no hard links here: claim the name with an exclusive create, then move the file onto it
        fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
        os.close(fd)
        os.replace(tmp, path)
        return
    os.unlink(tmp)


def claim_folder(tmp: str | os.PathLike, path: str | os.PathLike) -> None:
    """Give the finished folder ``tmp`` the name ``path`` only if nothing but an empty folder has it: a rename never
    replaces a folder that holds anything, so of two runs racing for one new folder only one wins. The loser gets
    FileExistsError and keeps ``tmp`` (its caller removes it); any other failure is raised as it is."""
    tmp, path = Path(tmp), Path(path)
    try:
        os.rename(tmp, path)
        return
    except OSError:
        if not os.path.lexists(path):
            raise
        if not path.is_dir() or path.is_symlink() or any(path.iterdir()):
            raise FileExistsError(f"{path} exists (written by another run?)") from None
    try:  # an empty folder: POSIX renames onto it above; Windows does not, so it is removed first
        path.rmdir()
        os.rename(tmp, path)
    except OSError:
        raise FileExistsError(f"{path} exists (written by another run?)") from None


def build_new_folder(out: str | os.PathLike, write: Callable[[Path], object], what: str = "--out"):
    """Build a new folder: ``write(tmp)`` fills a temporary sibling of ``out``, which then takes the name ``out``
    only if that is still new or empty. Returns what ``write`` returned. On any failure nothing is left, not even
    the parent folders this made; another run that took ``out`` meanwhile and an OSError are an InputError."""
    from .inputs import InputError

    out = Path(out)
    made = [p for p in reversed(out.parents) if not p.exists()]
    tmp = None
    try:
        for folder in made:
            folder.mkdir(exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.partial-", dir=out.parent))
        result = write(tmp)
        try:
            claim_folder(tmp, out)
        except FileExistsError:
            raise InputError(f"{what} {out} was written by another run meanwhile; this run kept nothing - choose "
                             "another folder") from None
        return result
    except OSError as exc:
        raise InputError(f"cannot write {what} {out}: {exc.strerror or exc}; choose another folder") from None
    finally:
        if tmp is not None and tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
        if not out.exists():
            for folder in reversed(made):
                try:
                    folder.rmdir()
                except OSError:
                    break
