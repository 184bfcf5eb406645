"""Carry a prepared data folder to another machine as one small file: ``data pack`` writes it, ``data unpack``
rebuilds a HumanML3D-format folder from it.

A pack holds, for every clip of the chosen splits, its joints (``new_joints``: quantised to a millimetre, stored as
second differences in time, channel by channel, and xz-compressed), its captions, the split lists, Mean/Std,
actions.json, LICENSE and terms.json. Mirrored copies (``M<id>``) are not stored: unpacking mirrors the joints again.
Unpacking computes the features from the joints with ``joints_to_features``, so an unpacked clip is one frame shorter
than the packed one and its features differ from the original folder's by the quantisation (under a millimetre) and
by the inverse kinematics being run on recovered joints. It is a folder to train on, not a copy: evaluate on the original.

The whole CMU + Bandai Namco train and val splits (23.8 hours with the mirrored copies) pack into about 25 MB.
"""

from __future__ import annotations

import json
import lzma
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from ..fileio import atomic_write, build_new_folder
from ..inputs import InputError, check_output_folder, read_utf8
from ..motion import features as F
from ..motion.skeleton import FEATURE_DIM

FORMAT = "mld-core-data-pack"
VERSION = 1
SPLITS = ("train", "val", "test")
MILLIMETRES = 1000.0
_ESCAPE = -128  # an int8 residual of this value means: the next int32 of the escape stream


# 1. Joints <-> compressed residuals -------------------------------------------------------------------------------
def encode_joints(clips: list[np.ndarray]) -> tuple[bytes, bytes]:
    """Joints (T, 22, 3) in metres -> (int8 residual stream, int32 escape stream), both xz-compressed."""
    small, big = [], []
    for joints in clips:
        x = np.round(joints.reshape(len(joints), -1) * MILLIMETRES).astype(np.int64)  # (T, 66) millimetres
        r = np.diff(np.diff(x, axis=0, prepend=0), axis=0, prepend=0).T.reshape(-1)  # (66 * T,) channel-major
        escaped = np.abs(r) >= 128
        small.append(np.where(escaped, _ESCAPE, r).astype(np.int8))
        big.append(r[escaped].astype(np.int32))
    compress = lambda parts: lzma.compress(np.concatenate(parts).tobytes(), preset=9 | lzma.PRESET_EXTREME)  # noqa: E731
    return compress(small or [np.zeros(0, np.int8)]), compress(big or [np.zeros(0, np.int32)])


def decode_joints(small: bytes, big: bytes, lengths: list[int], joints: int = 22) -> list[np.ndarray]:
    """The inverse of :func:`encode_joints`: clips of (T, joints, 3) float32 metres, T from ``lengths``."""
    r = np.frombuffer(lzma.decompress(small), np.int8).astype(np.int64)
    escapes = np.frombuffer(lzma.decompress(big), np.int32)
    r[r == _ESCAPE] = escapes
    channels = joints * 3
    clips, at = [], 0
    for T in lengths:
        res = r[at: at + channels * T].reshape(channels, T).T  # (T, 66)
        at += channels * T
        x = np.cumsum(np.cumsum(res, axis=0), axis=0)
        clips.append((x / MILLIMETRES).astype(np.float32).reshape(T, joints, 3))
    if at != len(r):
        raise ValueError(f"the pack holds {len(r)} residuals, its clips need {at}")
    return clips


# 2. Pack ----------------------------------------------------------------------------------------------------------
EXTRAS = ("actions.json", "LICENSE", "README.md", "terms.json")  # the folder's small files a pack carries as text


def _split_ids(folder: Path, split: str) -> list[str]:
    path = folder / f"{split}.txt"
    return [line.strip() for line in read_utf8(path, str(path)).splitlines() if line.strip()] if path.is_file() else []


def pack(folder, out, splits=("train", "val")) -> dict:
    """Write the pack of ``folder``'s ``splits`` to the file ``out``; returns a summary (clips, mirrored, bytes)."""
    folder, out = Path(folder).expanduser(), Path(out).expanduser()
    for name in ("new_joints", "Mean.npy", "Std.npy"):
        if not (folder / name).exists():
            raise InputError(f"{folder} is not a prepared folder with joints (no {name}); pack the output of "
                             "`data prepare` or `data merge`")
    unknown = [s for s in splits if s not in SPLITS]
    if unknown or not splits:
        raise InputError(f"--splits: {', '.join(unknown) or 'none given'}; choose from {', '.join(SPLITS)}")
    if out.is_dir():
        raise InputError(f"--out {out} is a folder; name the pack file to write")
    if out.resolve().is_relative_to(folder.resolve()):
        raise InputError(f"--out {out} lies inside the folder being packed; write the pack elsewhere")
    lists = {s: _split_ids(folder, s) for s in splits}
    ids, mirrored = [], []
    for split in splits:
        listed = set(lists[split])
        for cid in lists[split]:
            if cid.startswith("M") and cid[1:] in listed:
                mirrored.append(cid[1:])  # made again from its source's joints
            else:
                ids.append(cid)
    clips, lengths, texts = [], [], {}
    for cid in ids:
        path = folder / "new_joints" / f"{cid}.npy"
        if not path.is_file():
            raise InputError(f"{folder}: {cid} is listed but new_joints/{cid}.npy is missing")
        joints = np.load(path, allow_pickle=False)
        if joints.ndim != 3 or joints.shape[1:] != (22, 3) or not np.isfinite(joints).all() or len(joints) < 3:
            raise InputError(f"{path}: expected finite joints of shape (T >= 3, 22, 3), got {joints.shape}")
        clips.append(joints)
        lengths.append(len(joints))
    for cid in ids + [f"M{c}" for c in mirrored]:
        text = folder / "texts" / f"{cid}.txt"
        if text.is_file():
            texts[cid] = read_utf8(text, str(text))
    small, big = encode_joints(clips)
    meta = {"format": FORMAT, "version": VERSION, "ids": ids, "lengths": lengths, "mirrored": mirrored,
            "splits": lists, "source": folder.name}
    extras = {name: read_utf8(folder / name, str(folder / name)) for name in EXTRAS if (folder / name).is_file()}
    arrays = {"meta": _bytes(json.dumps(meta)), "joints": np.frombuffer(small, np.uint8),
              "escapes": np.frombuffer(big, np.uint8), "texts": _bytes(lzma.compress(json.dumps(texts).encode())),
              "extras": _bytes(lzma.compress(json.dumps(extras).encode())),
              "mean": np.load(folder / "Mean.npy"), "std": np.load(folder / "Std.npy")}
    atomic_write(out, lambda tmp: _save_npz(tmp, arrays))
    return {"clips": len(ids), "mirrored": len(mirrored), "bytes": out.stat().st_size, "out": str(out)}


def _bytes(data) -> np.ndarray:
    return np.frombuffer(data if isinstance(data, bytes) else data.encode(), np.uint8)


def _save_npz(path: str, arrays: dict) -> None:
    with open(path, "wb") as f:
        np.savez(f, **arrays)


# 3. Unpack --------------------------------------------------------------------------------------------------------
def read_pack(path) -> dict:
    """The pack's meta, joints, texts, extras and statistics; a file that is not a pack is refused in one line."""
    path = Path(path).expanduser()
    if not path.is_file():
        raise InputError(f"{path} is not a file; name a pack written by `data pack`")
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
        meta = json.loads(arrays["meta"].tobytes())
        if meta.get("format") != FORMAT or meta.get("version") != VERSION:
            raise ValueError("not a data pack of this version")
        joints = decode_joints(arrays["joints"].tobytes(), arrays["escapes"].tobytes(), meta["lengths"])
        texts = json.loads(lzma.decompress(arrays["texts"].tobytes()))
        if arrays["mean"].shape != (FEATURE_DIM,) or arrays["std"].shape != (FEATURE_DIM,):
            raise ValueError(f"its Mean/Std are not ({FEATURE_DIM},) vectors")
        extras = json.loads(lzma.decompress(arrays["extras"].tobytes()))
    except (OSError, KeyError, ValueError, EOFError, lzma.LZMAError) as exc:
        raise InputError(f"{path} is not a readable data pack ({str(exc).splitlines()[0] if str(exc) else exc!r})") \
            from None
    return {"meta": meta, "joints": dict(zip(meta["ids"], joints)), "texts": texts, "extras": extras,
            "mean": arrays["mean"], "std": arrays["std"]}


def _features(job: tuple[np.ndarray, bool]) -> tuple[np.ndarray, np.ndarray | None]:
    joints, mirror = job
    own = F.joints_to_features(joints).astype(np.float32)
    return own, (F.joints_to_features(F.mirror_joints(joints)).astype(np.float32) if mirror else None)


def unpack(path, out, workers: int = 1) -> dict:
    """Write a HumanML3D-format folder ``out`` (new or empty) from the pack at ``path``, the features computed by
    ``workers`` processes; returns a summary. Nothing is left behind on failure."""
    out = Path(out).expanduser().absolute()
    check_output_folder(out, "--out", staged_beside=True)
    if out.exists() and any(out.iterdir()):
        raise InputError(f"--out {out} is not empty; choose a new or empty folder - nothing was changed")
    pack_data = read_pack(path)
    frames = build_new_folder(out, lambda tmp: _write(tmp, pack_data, max(1, int(workers))))
    meta = pack_data["meta"]
    return {"out": str(out), "clips": len(meta["ids"]), "mirrored": len(meta["mirrored"]), "frames": frames}


def _write(tmp: Path, data: dict, workers: int) -> int:
    meta, joints = data["meta"], data["joints"]
    for sub in ("new_joint_vecs", "texts"):
        (tmp / sub).mkdir()
    mirrored = set(meta["mirrored"])
    jobs = [(joints[cid], cid in mirrored) for cid in meta["ids"]]
    if workers > 1:
        with ProcessPoolExecutor(workers) as pool:
            results = list(pool.map(_features, jobs, chunksize=16))
    else:
        results = [_features(job) for job in jobs]
    frames = 0
    for cid, (own, mirror) in zip(meta["ids"], results):
        np.save(tmp / "new_joint_vecs" / f"{cid}.npy", own)
        frames += len(own)
        if mirror is not None:
            np.save(tmp / "new_joint_vecs" / f"M{cid}.npy", mirror)
            frames += len(mirror)
    for cid, text in data["texts"].items():
        (tmp / "texts" / f"{cid}.txt").write_text(text, encoding="utf-8")
    for split in SPLITS:
        ids = meta["splits"].get(split, [])
        (tmp / f"{split}.txt").write_text("".join(f"{i}\n" for i in ids), encoding="utf-8")
    (tmp / "all.txt").write_text("".join(f"{i}\n" for s in SPLITS for i in meta["splits"].get(s, [])),
                                 encoding="utf-8")
    mean, std = data["mean"], data["std"]
    np.save(tmp / "Mean.npy", mean)
    np.save(tmp / "Std.npy", std)
    for name, text in data["extras"].items():
        (tmp / name).write_text(text, encoding="utf-8")
    return frames
