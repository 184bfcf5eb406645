"""Reading and writing BVH motion files with numpy only.

``read_bvh(path)`` (or ``parse_bvh(text)``) returns a :class:`Bvh`: the joint hierarchy (names, parents,
offsets, channels, End Sites), the frame time and the raw MOTION values. ``Bvh.joint_positions()`` runs
forward kinematics and returns world positions ``(F, J, 3)`` in the file's units.

Conventions (the usual ones, shared by Blender's importer):
- A joint's local transform is ``T(t) @ R`` where ``t`` is its OFFSET, except that position channels, when a
  joint has them, replace the offset (per axis). Many exporters write 6 channels on every joint with the
  position channels equal to the offsets; some (Bandai Namco) write a meaningless root OFFSET.
- Rotation channels are Euler angles in degrees, applied in the order they are listed:
  ``Zrotation Xrotation Yrotation`` means ``R = Rz @ Rx @ Ry`` (column vectors, ``world = parent @ local``).

Any malformed input (not a BVH, broken hierarchy, truncated MOTION block, wrong number of values, NaN/inf,
zero frames, unreadable numbers) raises :class:`BVHError`, a ``ValueError`` that names the line.
``write_bvh`` writes a file from names, parents, offsets, root positions and local rotations (matrices or
wxyz quaternions) with a chosen Euler order; it writes to a temporary file and renames it into place.
"""

from __future__ import annotations

import os
import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mld_core.fileio import atomic_write

__all__ = [
    "BVHError",
    "Bvh",
    "parse_bvh",
    "read_bvh",
    "write_bvh",
    "euler_to_matrix",
    "matrix_to_euler",
    "quat_to_matrix",
]

_AXES = {"X": 0, "Y": 1, "Z": 2}
_CHANNEL_NAMES = {f"{a}{kind}" for a in "XYZ" for kind in ("position", "rotation")}


class BVHError(ValueError):
    """A malformed BVH file. ``line`` is the 1-based line number (or None when unknown)."""

    def __init__(self, message: str, line: int | None = None, source: str | None = None):
        self.line = line
        self.source = source
        self.reason = message
        where = ""
        if source:
            where = f"{source}"
        if line is not None:
            where = f"{where}:{line}" if where else f"line {line}"
        super().__init__(f"{where}: {message}" if where else message)


# --------------------------------------------------------------------------------------------------
# Rotations
# --------------------------------------------------------------------------------------------------


def _axis_matrices(axis: int, radians: np.ndarray) -> np.ndarray:
    """Rotation matrices about one axis: (...,) -> (..., 3, 3)."""
    c, s = np.cos(radians), np.sin(radians)
    out = np.zeros(radians.shape + (3, 3))
    i, j = [(1, 2), (2, 0), (0, 1)][axis]  # the plane rotated by this axis (right-handed)
    out[..., axis, axis] = 1.0
    out[..., i, i] = c
    out[..., i, j] = -s
    out[..., j, i] = s
    out[..., j, j] = c
    return out


def euler_to_matrix(degrees: np.ndarray, order: str) -> np.ndarray:
    """Euler angles (..., len(order)) in degrees -> (..., 3, 3); ``order="ZXY"`` gives Rz @ Rx @ Ry."""
    degrees = np.asarray(degrees, dtype=np.float64)
    order = order.upper()
    if degrees.shape[-1] != len(order) or any(a not in _AXES for a in order):
        raise ValueError(f"bad Euler order {order!r} for angles of shape {degrees.shape}")
    out = np.broadcast_to(np.eye(3), degrees.shape[:-1] + (3, 3)).copy()
    radians = np.deg2rad(degrees)
    for n, a in enumerate(order):
        out = out @ _axis_matrices(_AXES[a], radians[..., n])
    return out


def matrix_to_euler(matrices: np.ndarray, order: str) -> np.ndarray:
    """Rotation matrices (..., 3, 3) -> Euler angles (..., 3) in degrees with ``R = Ra @ Rb @ Rc``.

    ``order`` is any permutation of "XYZ". At gimbal lock the last angle is set to 0.
    """
    m = np.asarray(matrices, dtype=np.float64)
    order = order.upper()
    if sorted(order) != ["X", "Y", "Z"]:
        raise ValueError(f"Euler order must be a permutation of XYZ, got {order!r}")
    i, j, k = (_AXES[a] for a in order)
    sign = 1.0 if (j - i) % 3 == 1 else -1.0  # +1 for cyclic orders (XYZ, YZX, ZXY)
    sin_b = np.clip(sign * m[..., i, k], -1.0, 1.0)
    beta = np.arcsin(sin_b)
    cos_b = np.sqrt(np.maximum(0.0, 1.0 - sin_b * sin_b))
    alpha = np.arctan2(-sign * m[..., j, k], m[..., k, k])
    gamma = np.arctan2(-sign * m[..., i, j], m[..., i, i])
    locked = cos_b < 1e-6
    if np.any(locked):
        alpha = np.where(locked, np.arctan2(sign * m[..., k, j], m[..., j, j]), alpha)
        gamma = np.where(locked, 0.0, gamma)
    return np.rad2deg(np.stack([alpha, beta, gamma], axis=-1))


def quat_to_matrix(quats: np.ndarray) -> np.ndarray:
    """Quaternions (..., 4) wxyz (normalised here) -> rotation matrices (..., 3, 3)."""
    q = np.asarray(quats, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    out = np.empty(q.shape[:-1] + (3, 3))
    out[..., 0, 0] = 1 - 2 * (y * y + z * z)
    out[..., 0, 1] = 2 * (x * y - w * z)
    out[..., 0, 2] = 2 * (x * z + w * y)
    out[..., 1, 0] = 2 * (x * y + w * z)
    out[..., 1, 1] = 1 - 2 * (x * x + z * z)
    out[..., 1, 2] = 2 * (y * z - w * x)
    out[..., 2, 0] = 2 * (x * z - w * y)
    out[..., 2, 1] = 2 * (y * z + w * x)
    out[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return out


# --------------------------------------------------------------------------------------------------
# The file
# --------------------------------------------------------------------------------------------------


@dataclass
class Bvh:
    """A parsed BVH file. Joints are in file (depth-first) order; parents[j] < j, -1 for roots."""

    names: list[str]
    parents: np.ndarray  # (J,) int
    offsets: np.ndarray  # (J, 3) float64, file units
    channels: list[tuple[str, ...]]  # per joint, e.g. ("Xposition", ..., "Yrotation")
    frame_time: float
    motion: np.ndarray  # (F, C) float64, all channels of a frame in file order
    end_sites: dict[int, np.ndarray] = field(default_factory=dict)  # joint index -> End Site offset (3,)

    @property
    def num_frames(self) -> int:
        return int(self.motion.shape[0])

    @property
    def num_joints(self) -> int:
        return len(self.names)

    @property
    def fps(self) -> float:
        return 1.0 / self.frame_time

    def index(self, name: str) -> int:
        try:
            return self.names.index(name)
        except ValueError:
            raise KeyError(f"no joint named {name!r} (joints: {', '.join(self.names)})") from None

    def _channel_columns(self) -> list[int]:
        starts, c = [], 0
        for ch in self.channels:
            starts.append(c)
            c += len(ch)
        return starts

    def local_translations(self) -> np.ndarray:
        """(F, J, 3): each joint's translation in its parent's frame (offsets overridden by position channels)."""
        F = self.num_frames
        out = np.broadcast_to(self.offsets, (F,) + self.offsets.shape).copy()
        for j, (start, ch) in enumerate(zip(self._channel_columns(), self.channels)):
            for n, name in enumerate(ch):
                if name.endswith("position"):
                    out[:, j, _AXES[name[0]]] = self.motion[:, start + n]
        return out

    def local_rotations(self) -> np.ndarray:
        """(F, J, 3, 3): each joint's rotation relative to its parent (identity without rotation channels)."""
        F, J = self.num_frames, self.num_joints
        out = np.empty((F, J, 3, 3))
        for j, (start, ch) in enumerate(zip(self._channel_columns(), self.channels)):
            cols = [start + n for n, name in enumerate(ch) if name.endswith("rotation")]
            order = "".join(name[0] for name in ch if name.endswith("rotation"))
            out[:, j] = euler_to_matrix(self.motion[:, cols], order) if cols else np.eye(3)
        return out

    def root_positions(self) -> np.ndarray:
        """(F, 3): translation of the first root joint."""
        return self.local_translations()[:, 0]

    def world_transforms(self) -> tuple[np.ndarray, np.ndarray]:
        """World rotations (F, J, 3, 3) and positions (F, J, 3)."""
        t = self.local_translations()
        r = self.local_rotations()
        rot = np.empty_like(r)
        pos = np.empty_like(t)
        for j, p in enumerate(self.parents):
            if p < 0:
                rot[:, j] = r[:, j]
                pos[:, j] = t[:, j]
            else:
                rot[:, j] = rot[:, p] @ r[:, j]
                pos[:, j] = pos[:, p] + np.einsum("fab,fb->fa", rot[:, p], t[:, j])
        return rot, pos

    def joint_positions(self) -> np.ndarray:
        """World positions (F, J, 3) of all joints (End Sites excluded), in the file's units."""
        return self.world_transforms()[1]


class _Tokens:
    """Whitespace tokens of the hierarchy part with their 1-based line numbers."""

    def __init__(self, lines: list[str], first_line: int, source: str | None):
        self.items: list[tuple[str, int]] = []
        for n, line in enumerate(lines):
            for tok in line.split():
                # Braces glued to words ("Hips{") are split off.
                for part in re.split(r"([{}])", tok):
                    if part:
                        self.items.append((part, first_line + n))
        self.pos = 0
        self.source = source
        self.last_line = first_line + max(len(lines) - 1, 0)

    def peek(self) -> tuple[str, int] | None:
        return self.items[self.pos] if self.pos < len(self.items) else None

    def next(self, what: str) -> tuple[str, int]:
        if self.pos >= len(self.items):
            raise BVHError(f"unexpected end of the hierarchy, expected {what}", self.last_line, self.source)
        item = self.items[self.pos]
        self.pos += 1
        return item

    def expect(self, word: str) -> int:
        tok, line = self.next(repr(word))
        if tok != word:
            raise BVHError(f"expected {word!r}, found {tok!r}", line, self.source)
        return line

    def number(self, what: str) -> float:
        tok, line = self.next(what)
        try:
            value = float(tok)
        except ValueError:
            raise BVHError(f"unreadable number {tok!r} for {what}", line, self.source) from None
        if not np.isfinite(value):
            raise BVHError(f"{what} is not finite ({tok})", line, self.source)
        return value


def _parse_hierarchy(tok: _Tokens):
    names: list[str] = []
    parents: list[int] = []
    offsets: list[list[float]] = []
    channels: list[tuple[str, ...]] = []
    end_sites: dict[int, np.ndarray] = {}
    src = tok.source

    def read_name(keyword_line: int) -> str:
        parts = []
        while True:
            item = tok.peek()
            if item is None:
                raise BVHError("unexpected end of the hierarchy after a joint keyword", keyword_line, src)
            if item[0] == "{":
                break
            parts.append(tok.next("a joint name")[0])
        if not parts:
            raise BVHError("joint without a name", keyword_line, src)
        return " ".join(parts)

    def read_joint(parent: int, keyword_line: int) -> None:
        name = read_name(keyword_line)
        tok.expect("{")
        index = len(names)
        names.append(name)
        parents.append(parent)
        offsets.append([0.0, 0.0, 0.0])
        channels.append(())
        seen_offset = False
        while True:
            word, line = tok.next("'}'")
            key = word.upper()
            if word == "}":
                break
            if key == "OFFSET":
                offsets[index] = [tok.number(f"the OFFSET of {name}") for _ in range(3)]
                seen_offset = True
            elif key == "CHANNELS":
                n_tok, n_line = tok.next("a channel count")
                try:
                    n = int(n_tok)
                except ValueError:
                    raise BVHError(f"unreadable channel count {n_tok!r}", n_line, src) from None
                if not 0 <= n <= 6:
                    raise BVHError(f"a joint may have 0 to 6 channels, found {n}", n_line, src)
                chans = []
                for _ in range(n):
                    c, c_line = tok.next("a channel name")
                    c = c[0].upper() + c[1:].lower() if c else c
                    if c not in _CHANNEL_NAMES:
                        raise BVHError(f"unknown channel {c!r}", c_line, src)
                    if c in chans:
                        raise BVHError(f"channel {c!r} listed twice for {name}", c_line, src)
                    chans.append(c)
                channels[index] = tuple(chans)
            elif key == "JOINT":
                read_joint(index, line)
            elif key == "END":
                site, site_line = tok.next("'Site'")
                if site.upper() != "SITE":
                    raise BVHError(f"expected 'End Site', found 'End {site}'", site_line, src)
                tok.expect("{")
                end = [0.0, 0.0, 0.0]
                while True:
                    w, w_line = tok.next("'}' closing the End Site")
                    if w == "}":
                        break
                    if w.upper() != "OFFSET":
                        raise BVHError(f"unexpected {w!r} in an End Site", w_line, src)
                    end = [tok.number(f"the End Site OFFSET of {name}") for _ in range(3)]
                end_sites[index] = np.array(end)
            else:
                raise BVHError(f"unexpected {word!r} in joint {name}", line, src)
        if not seen_offset:
            raise BVHError(f"joint {name} has no OFFSET", keyword_line, src)

    tok.expect("HIERARCHY")
    while tok.peek() is not None:
        word, line = tok.next("ROOT")
        if word.upper() != "ROOT":
            raise BVHError(f"expected ROOT, found {word!r}", line, src)
        read_joint(-1, line)
    if not names:
        raise BVHError("the hierarchy has no joints", tok.last_line, src)
    return names, parents, offsets, channels, end_sites


_MOTION_RE = re.compile(r"^[ \t]*MOTION[ \t]*\r?$", re.MULTILINE)


def _line_end(text: str, pos: int) -> int:
    end = text.find("\n", pos)
    return len(text) if end < 0 else end + 1


def _header_value(text: str, pos: int, line_no: int, label: str, src: str | None) -> tuple[str, int, int]:
    """Skip blank lines and read ``label value`` -> (value token, next pos, its line number)."""
    while pos < len(text):
        end = _line_end(text, pos)
        line = text[pos:end].strip()
        if line:
            parts = line.split(":", 1)
            if len(parts) != 2 or parts[0].strip().lower() != label.lower() or not parts[1].strip():
                raise BVHError(f"expected '{label}: ...', found {line[:60]!r}", line_no, src)
            return parts[1].strip(), end, line_no
        pos, line_no = end, line_no + 1
    raise BVHError(f"the MOTION block ends before '{label}:'", line_no, src)


def _diagnose_motion(data: str, first_line: int, frames: int, width: int, src: str | None) -> None:
    """Slow path: find the first bad line of the MOTION data and raise a BVHError for it."""
    lines = data.splitlines()
    count = 0
    last = first_line
    for n, line in enumerate(lines):
        parts = line.split()
        line_no = first_line + n
        if not parts:
            continue
        count += 1
        last = line_no
        if count > frames:
            raise BVHError(f"more frame lines than 'Frames: {frames}'", line_no, src)
        if len(parts) != width:
            raise BVHError(f"frame {count} has {len(parts)} values, expected {width}", line_no, src)
        for p in parts:
            try:
                v = float(p)
            except ValueError:
                raise BVHError(f"unreadable number {p[:40]!r}", line_no, src) from None
            if not np.isfinite(v):
                raise BVHError(f"non-finite value {p!r}", line_no, src)
    if count < frames:
        raise BVHError(f"truncated MOTION block: 'Frames: {frames}' but only {count} frame lines", last, src)
    raise BVHError("malformed MOTION block", first_line, src)  # pragma: no cover - defensive


def parse_bvh(text: str | bytes, source: str | None = None) -> Bvh:
    """Parse BVH text (str or bytes). ``source`` (a file name) is used in error messages."""
    if isinstance(text, (bytes, bytearray)):
        text = bytes(text).decode("utf-8", errors="replace")
    if text.startswith("\ufeff"):
        text = text[1:]
    stripped = text.lstrip()
    if not stripped[:9].upper().startswith("HIERARCHY"):
        first = text[: len(text) - len(stripped)].count("\n") + 1
        raise BVHError("not a BVH file (it does not start with HIERARCHY)", first, source)
    m = _MOTION_RE.search(text)
    if m is None:
        raise BVHError("no MOTION section", text.count("\n") + 1, source)
    head = text[: m.start()]
    head_lines = head.splitlines()
    tok = _Tokens(head_lines, 1, source)
    try:
        names, parents, offsets, channels, end_sites = _parse_hierarchy(tok)
    except RecursionError:
        line = tok.items[min(tok.pos, len(tok.items) - 1)][1] if tok.items else 1
        raise BVHError("the hierarchy is nested too deeply", line, source) from None

    motion_line = head.count("\n") + 1
    pos = _line_end(text, m.start())
    frames_tok, pos, frames_line = _header_value(text, pos, motion_line + 1, "Frames", source)
    try:
        frames = int(frames_tok)
    except ValueError:
        raise BVHError(f"unreadable frame count {frames_tok!r}", frames_line, source) from None
    if frames <= 0:
        raise BVHError(f"the file has no frames (Frames: {frames})", frames_line, source)
    ft_tok, pos, ft_line = _header_value(text, pos, frames_line + 1, "Frame Time", source)
    try:
        frame_time = float(ft_tok)
    except ValueError:
        raise BVHError(f"unreadable frame time {ft_tok!r}", ft_line, source) from None
    if not np.isfinite(frame_time) or frame_time <= 0:
        raise BVHError(f"frame time must be positive, found {ft_tok}", ft_line, source)

    width = sum(len(c) for c in channels)
    data = text[pos:]
    data_line = ft_line + 1
    if width == 0:
        motion = np.zeros((frames, 0))
    else:
        values = None
        body = data.strip()
        # Fast path: one C-level parse of the whole block; any doubt -> the slow, line-by-line diagnosis.
        if body and body.count("\n") + 1 == frames:
            with warnings.catch_warnings():
                warnings.simplefilter("error")
                try:
                    values = np.fromstring(body, dtype=np.float64, sep=" ")
                except (ValueError, DeprecationWarning):
                    values = None
        if values is None or values.size != frames * width:
            _diagnose_motion(data, data_line, frames, width, source)
        motion = values.reshape(frames, width)
        bad = ~np.isfinite(motion)
        if bad.any():
            row = int(np.argwhere(bad.any(axis=1))[0, 0])
            leading = data[: len(data) - len(data.lstrip())].count("\n")
            raise BVHError(f"non-finite value in frame {row + 1}", data_line + leading + row, source)
    return Bvh(
        names=names,
        parents=np.asarray(parents, dtype=np.int64),
        offsets=np.asarray(offsets, dtype=np.float64).reshape(-1, 3),
        channels=channels,
        frame_time=frame_time,
        motion=motion,
        end_sites=end_sites,
    )


def read_bvh(path: str | os.PathLike) -> Bvh:
    """Read a BVH file. Raises BVHError (a ValueError naming file and line) when it is malformed."""
    path = Path(path)
    with open(path, "rb") as f:
        raw = f.read()
    return parse_bvh(raw, source=str(path))


# --------------------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------------------


def _depth_first(parents: np.ndarray) -> list[int]:
    children: dict[int, list[int]] = {}
    for j, p in enumerate(parents):
        children.setdefault(int(p), []).append(j)
    order: list[int] = []

    def visit(j: int) -> None:
        order.append(j)
        for c in children.get(j, []):
            visit(c)

    for r in children.get(-1, []):
        visit(r)
    return order


def write_bvh(
    path: str | os.PathLike,
    names: list[str],
    parents,
    offsets,
    root_positions,
    local_rotations,
    frame_time: float,
    order: str = "ZXY",
    end_sites: dict[int, np.ndarray] | None = None,
    precision: int = 6,
) -> None:
    """Write a BVH file.

    names (J,), parents (J,) with -1 for the root(s), offsets (J, 3), root_positions (F, 3) of the first root (other roots stay at their offsets),
    local_rotations (F, J, 3, 3) matrices or (F, J, 4) wxyz quaternions, relative to the parent.
    Roots get 6 channels (position + rotation), other joints 3 rotation channels, in Euler ``order``
    (e.g. "ZXY" writes ``Zrotation Xrotation Yrotation``, meaning R = Rz @ Rx @ Ry). Joints are written
    depth-first (reading the file back gives that order). Leaf joints get an End Site (``end_sites`` maps
    joint index -> offset; zero by default). The file is written to a temporary name and renamed.
    """
    names = [str(n) for n in names]
    parents = np.asarray(parents, dtype=np.int64)
    offsets = np.asarray(offsets, dtype=np.float64)
    root_positions = np.asarray(root_positions, dtype=np.float64)
    rot = np.asarray(local_rotations, dtype=np.float64)
    J = len(names)
    if parents.shape != (J,) or offsets.shape != (J, 3):
        raise ValueError(f"need parents ({J},) and offsets ({J}, 3); got {parents.shape} and {offsets.shape}")
    if any(p >= J or p < -1 or p == j for j, p in enumerate(parents)):
        raise ValueError("parents must be indices of other joints or -1")
    if rot.ndim == 3 and rot.shape[-1] == 4:
        rot = quat_to_matrix(rot)
    if rot.ndim != 4 or rot.shape[1:] != (J, 3, 3):
        raise ValueError(f"local_rotations must be (F, {J}, 3, 3) or (F, {J}, 4); got {np.shape(local_rotations)}")
    F = rot.shape[0]
    if F == 0:
        raise ValueError("cannot write a BVH with zero frames")
    if root_positions.shape != (F, 3):
        raise ValueError(f"root_positions must be ({F}, 3); got {root_positions.shape}")
    if not (np.isfinite(rot).all() and np.isfinite(root_positions).all() and np.isfinite(offsets).all()):
        raise ValueError("non-finite values in the motion")
    if not (np.isfinite(frame_time) and frame_time > 0):
        raise ValueError(f"frame_time must be positive, got {frame_time}")
    order = order.upper()
    if sorted(order) != ["X", "Y", "Z"]:
        raise ValueError(f"order must be a permutation of XYZ, got {order!r}")
    if any(not n or any(ch.isspace() for ch in n) or "{" in n or "}" in n for n in names):
        raise ValueError("joint names must be non-empty without whitespace or braces")
    visit = _depth_first(parents)
    if len(visit) != J:
        raise ValueError("parents do not form a forest (a cycle?)")
    end_sites = end_sites or {}
    has_child = {int(p) for p in parents if p >= 0}
    rot_channels = " ".join(f"{a}rotation" for a in order)

    def fmt(v) -> str:
        return " ".join(f"{x:.{precision}f}" for x in v)

    lines = ["HIERARCHY"]
    depth_of: dict[int, int] = {}
    stack: list[int] = []  # open joints
    for j in visit:
        p = int(parents[j])
        while stack and stack[-1] != p:
            k = stack.pop()
            lines.append("\t" * depth_of[k] + "}")
        depth = len(stack)
        depth_of[j] = depth
        ind = "\t" * depth
        lines.append(f"{ind}{'ROOT' if p < 0 else 'JOINT'} {names[j]}")
        lines.append(f"{ind}{{")
        lines.append(f"{ind}\tOFFSET {fmt(offsets[j])}")
        if p < 0:
            lines.append(f"{ind}\tCHANNELS 6 Xposition Yposition Zposition {rot_channels}")
        else:
            lines.append(f"{ind}\tCHANNELS 3 {rot_channels}")
        if j not in has_child:
            lines.append(f"{ind}\tEnd Site")
            lines.append(f"{ind}\t{{")
            lines.append(f"{ind}\t\tOFFSET {fmt(np.asarray(end_sites.get(j, np.zeros(3)), dtype=np.float64))}")
            lines.append(f"{ind}\t}}")
        stack.append(j)
    while stack:
        k = stack.pop()
        lines.append("\t" * depth_of[k] + "}")
    lines += ["MOTION", f"Frames: {F}", f"Frame Time: {frame_time:.8f}"]

    euler = matrix_to_euler(rot, order)  # (F, J, 3)
    columns = []
    for j in visit:
        if parents[j] < 0:
            columns.append(root_positions if j == visit[0] else np.broadcast_to(offsets[j], (F, 3)))
        columns.append(euler[:, j])
    table = np.concatenate(columns, axis=1)
    table = np.where(np.abs(table) < 0.5 * 10.0**-precision, 0.0, table)  # no "-0.000000"
    row = " ".join([f"%.{precision}f"] * table.shape[1])
    body = "\n".join(row % tuple(r) for r in table)

    def write(tmp: str) -> None:
        with open(tmp, "w", encoding="utf-8", newline="\n") as f:
            f.write("\n".join(lines))
            f.write("\n")
            f.write(body)
            f.write("\n")

    atomic_write(path, write)


def write_canonical_bvh(path: str | os.PathLike, root_positions, local_rotations, frame_time: float,
                        units_per_metre: float = 1.0) -> None:
    """A take of the canonical 22-joint skeleton (mld_core.motion.skeleton, rest offsets in metres) as BVH: root
    positions (F, 3) in metres, local rotations (F, 22, 4) wxyz; ``units_per_metre`` 100 writes centimetres."""
    from mld_core.motion import skeleton

    write_bvh(path, list(skeleton.JOINT_NAMES), list(skeleton.PARENTS),
              np.asarray(skeleton.REST_OFFSETS) * units_per_metre,
              np.asarray(root_positions, np.float64) * units_per_metre, local_rotations, frame_time)
