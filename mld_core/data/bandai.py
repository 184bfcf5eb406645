"""Prepare the Bandai Namco Research motion datasets as a HumanML3D-format training folder.

``prepare_bandai(src, out)`` (CLI: ``python -m mld_core data prepare bandai SRC --out DIR``) reads the BVH
clips from the released ``.tar.xz`` (streamed, nothing extracted to disk) or from an extracted folder,
and writes::

    new_joint_vecs/ID.npy   (T-1, 263) float32 HumanML3D features at 20 fps
    new_joints/ID.npy       (T-1, 22, 3) float32 joints recovered from those features (as HumanML3D stores them)
    texts/ID.txt            captions, one per line: ``caption#word/POS ...#0.0#0.0``
    train.txt val.txt test.txt all.txt
    Mean.npy Std.npy        over the train split (HumanML3D's per-group std)
    actions.json            {"classes": [content labels], "clips": {id: content}, "styles": {id: style}}
    README.md LICENSE       provenance and the CC BY-NC 4.0 licence of the motion data
    .mld_prepare.json       marks the folder as written by this command (so a rerun may replace it)

IDs are the BVH file stems (``dataset-2_walk-turn-left_normal_027``); mirrored copies (left <-> right,
with mirrored captions and content label) are ``"M" + ID`` and go to the same split as their source.

Processing of one clip: BVH -> world FK (cm, Y up; the garbage Hips OFFSET is overridden by its position
channels, joint_Root stays in the chain) -> the 22 SMPL-order joints (see BANDAI_TO_SMPL) in metres ->
linear resampling at t = k/20 s -> ``joints_to_features``.
"""

from __future__ import annotations

import concurrent.futures as cf
import hashlib
import json
import multiprocessing
import os
import re
import shutil
import sys
import tarfile
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from ..fileio import claim_folder
from ..inputs import InputError, check_output_folder
from ..motion.bvh import BVHError, parse_bvh
from . import captions as cap
from . import terms
from .take_checks import implausible

FORMAT_VERSION = 1
MANIFEST = ".mld_prepare.json"
TARGET_FPS = 20
MIN_FRAMES = 10  # at 20 fps (0.5 s); shorter clips are skipped and listed in the manifest

# SMPL-22 joint <- Bandai joint(s); two names = their midpoint (SMPL's spine2 sits between spine1 and spine3).
BANDAI_TO_SMPL: tuple[tuple[str, ...], ...] = (
    ("Hips",),  # pelvis
    ("UpperLeg_L",),  # left_hip
    ("UpperLeg_R",),  # right_hip
    ("Spine",),  # spine1
    ("LowerLeg_L",),  # left_knee
    ("LowerLeg_R",),  # right_knee
    ("Spine", "Chest"),  # spine2
    ("Foot_L",),  # left_ankle
    ("Foot_R",),  # right_ankle
    ("Chest",),  # spine3 (the shoulders hang off Chest as SMPL's collars hang off spine3)
    ("Toes_L",),  # left_foot
    ("Toes_R",),  # right_foot
    ("Neck",),  # neck
    ("Shoulder_L",),  # left_collar
    ("Shoulder_R",),  # right_collar
    ("Head",),  # head
    ("UpperArm_L",),  # left_shoulder
    ("UpperArm_R",),  # right_shoulder
    ("LowerArm_L",),  # left_elbow
    ("LowerArm_R",),  # right_elbow
    ("Hand_L",),  # left_wrist
    ("Hand_R",),  # right_wrist
)

_NAME_RE = re.compile(r"^(dataset-\d+)_(.+)_([^_]+)_(\d+)$")

CITATION = (
    "Makito Kobayashi, Chen-Chieh Liao, Keito Inoue, Sentaro Yojima, Masafumi Takahashi. "
    "Motion Capture Dataset for Practical Use of AI-based Motion Editing and Stylization. "
    "arXiv:2306.08861, 2023."
)


class PrepareError(Exception):
    """A problem with the command's input (bad SRC or --out); the CLI turns it into exit code 2."""


# --------------------------------------------------------------------------------------------------
# Clips
# --------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ClipName:
    id: str
    dataset: str
    content: str
    style: str
    take: str


def parse_clip_name(stem: str) -> ClipName:
    """``dataset-2_walk-turn-left_normal_027`` -> dataset, content, style, take."""
    m = _NAME_RE.match(stem)
    if not m:
        raise ValueError(f"not a Bandai clip name: {stem!r} (expected dataset-N_CONTENT_STYLE_NNN)")
    return ClipName(stem, *m.groups())


def bandai_joints(bvh) -> np.ndarray:
    """World positions of the 22 SMPL-order joints (F, 22, 3) in metres, from a parsed Bandai BVH."""
    pos = bvh.joint_positions()  # (F, J, 3) cm
    cols = []
    for names in BANDAI_TO_SMPL:
        idx = [bvh.index(n) for n in names]
        cols.append(pos[:, idx].mean(axis=1))
    return np.stack(cols, axis=1) / 100.0  # (F, 22, 3) m


def source_fps(frame_time: float) -> float:
    """Frames per second of a BVH; 0.0333333 is read as exactly 30."""
    fps = 1.0 / frame_time
    return float(round(fps)) if abs(fps - round(fps)) < 1e-3 else fps


def resample_joints(joints: np.ndarray, fps_in: float, fps_out: float = TARGET_FPS) -> np.ndarray:
    """Linear interpolation of positions at t = k / fps_out for every t inside the clip."""
    n = len(joints)
    duration = (n - 1) / fps_in
    k = int(np.floor(duration * fps_out + 1e-6)) + 1
    t = np.arange(k) * (fps_in / fps_out)  # in input frames
    lo = np.minimum(np.floor(t).astype(np.int64), n - 1)
    hi = np.minimum(lo + 1, n - 1)
    w = (t - lo)[:, None, None]
    return joints[lo] * (1.0 - w) + joints[hi] * w


def clip_joints(data: bytes | str, source: str | None = None) -> np.ndarray:
    """Bandai BVH text -> (T, 22, 3) joints in metres at 20 fps. Raises BVHError / KeyError on bad files."""
    bvh = parse_bvh(data, source=source)
    return resample_joints(bandai_joints(bvh), source_fps(bvh.frame_time))


# --------------------------------------------------------------------------------------------------
# Sources: a .tar(.xz/.gz/.bz2) archive, streamed, or a folder
# --------------------------------------------------------------------------------------------------


def _is_clip_member(name: str) -> bool:
    base = name.rsplit("/", 1)[-1]
    return base.endswith(".bvh") and not base.startswith(".") and _NAME_RE.match(base[:-4]) is not None


def check_source(src: Path) -> str:
    """'folder' or 'archive'; raises PrepareError when SRC is unusable."""
    if not src.exists():
        raise PrepareError(f"SRC {src} does not exist (expected the Bandai .tar.xz or its extracted folder)")
    if src.is_dir():
        if not any(_is_clip_member(p.name) for p in src.rglob("*.bvh")):
            raise PrepareError(f"SRC folder {src} contains no Bandai clips (dataset-N_CONTENT_STYLE_NNN.bvh)")
        return "folder"
    if not tarfile.is_tarfile(src):
        raise PrepareError(f"SRC {src} is neither a folder nor a readable tar archive (.tar.xz)")
    return "archive"


def iter_source(src: Path) -> Iterator[tuple[str, bytes]]:
    """(file stem, BVH bytes) for every Bandai clip in SRC, plus ('LICENSE:<path>', text) for licence files."""
    if src.is_dir():
        for p in sorted(src.rglob("*")):
            if p.is_file() and _is_clip_member(p.name):
                yield p.name[:-4], p.read_bytes()
            elif p.is_file() and p.name == "LICENSE":
                yield f"LICENSE:{p.relative_to(src)}", p.read_bytes()
        return
    for name, data in iter_tar(src, lambda n: _is_clip_member(n) or n.rsplit("/", 1)[-1] == "LICENSE"):
        base = name.rsplit("/", 1)[-1]
        yield (base[:-4], data) if base != "LICENSE" else (f"LICENSE:{name}", data)


def iter_tar(src: Path, wanted: Callable[[str], bool]) -> Iterator[tuple[str, bytes]]:
    """(member name, bytes) of every file in the tar archive ``src`` (streamed, any compression) whose name
    ``wanted`` accepts; a corrupt or truncated archive is a PrepareError."""
    try:
        with tarfile.open(src, mode="r|*") as tar:
            for member in tar:
                if member.isfile() and wanted(member.name):
                    yield member.name, tar.extractfile(member).read()
    except (tarfile.TarError, EOFError, OSError) as exc:
        if isinstance(exc, (FileNotFoundError, PermissionError)):
            raise
        raise PrepareError(f"cannot read the archive {src}: {exc}") from exc
    except Exception as exc:  # lzma/zlib errors from a corrupt stream
        if type(exc).__module__ in ("lzma", "zlib", "_lzma", "_bz2", "bz2", "gzip"):
            raise PrepareError(f"cannot read the archive {src}: {exc}") from exc
        raise


# --------------------------------------------------------------------------------------------------
# Splits
# --------------------------------------------------------------------------------------------------


def _hash(text: str) -> str:
    return hashlib.sha1(text.encode("utf-8")).hexdigest()


def assign_splits(labels: dict[str, tuple[str, str]], val: float = 0.1, test: float = 0.1,
                  min_stratum: int = 5) -> dict[str, str]:
    """Deterministic split of clip ids stratified by (content, style).

    Strata with fewer than ``min_stratum`` clips are pooled per content (dataset-1 has one clip per
    content x style). Within a stratum, ids are ordered by a fixed hash; the first round(test*n) go to
    test, the next round(val*n) to val, the rest to train. A stratum of fewer than 3 clips is all train,
    and every stratum keeps at least one train clip. The result depends only on the ids and labels.
    """
    strata: dict[tuple, list[str]] = {}
    for cid, (content, style) in labels.items():
        strata.setdefault((content, style), []).append(cid)
    pooled: dict[tuple, list[str]] = {}
    for (content, style), ids in strata.items():
        key = (content, style) if len(ids) >= min_stratum else (content, "*")
        pooled.setdefault(key, []).extend(ids)
    out: dict[str, str] = {}
    for key in sorted(pooled):
        ids = sorted(pooled[key], key=lambda i: (_hash(i), i))
        n = len(ids)
        n_test = int(np.floor(test * n + 0.5)) if n >= 3 else 0
        n_val = int(np.floor(val * n + 0.5)) if n >= 3 else 0
        while n_test + n_val >= n and (n_test or n_val):
            if n_val >= n_test and n_val:
                n_val -= 1
            else:
                n_test -= 1
        for k, cid in enumerate(ids):
            out[cid] = "test" if k < n_test else "val" if k < n_test + n_val else "train"
    return out


# --------------------------------------------------------------------------------------------------
# Workers
# --------------------------------------------------------------------------------------------------


def _init_worker() -> None:
    try:
        import torch

        torch.set_num_threads(1)
    except Exception:  # pragma: no cover
        pass


def write_splits(root: Path, splits: dict[str, list[str]]) -> list[str]:
    """train/val/test.txt and all.txt of ``splits`` (name -> ids), and Mean/Std over the train split's features
    (already under ``root``); returns every id, sorted. PrepareError when the train split is empty."""
    from ..motion.features import mean_std

    for name, ids in splits.items():
        (root / f"{name}.txt").write_text("".join(f"{i}\n" for i in sorted(ids)), encoding="utf-8")
    all_ids = sorted(i for ids in splits.values() for i in ids)
    (root / "all.txt").write_text("".join(f"{i}\n" for i in all_ids), encoding="utf-8")
    train = [np.load(root / "new_joint_vecs" / f"{i}.npy") for i in sorted(splits["train"])]
    if not train:
        raise PrepareError("the train split is empty")
    mean, std = mean_std(train)
    np.save(root / "Mean.npy", np.asarray(mean, dtype=np.float32))
    np.save(root / "Std.npy", np.asarray(std, dtype=np.float32))
    return all_ids


def _write_clip(root: Path, cid: str, joints: np.ndarray, lines: list[str]) -> int:
    from ..motion.features import features_to_joints, joints_to_features

    vecs = joints_to_features(joints)  # (T-1, 263)
    if not np.isfinite(vecs).all():
        raise ValueError("non-finite features")
    rec = features_to_joints(vecs).astype(np.float32)  # (T-1, 22, 3)
    np.save(root / "new_joint_vecs" / f"{cid}.npy", vecs.astype(np.float32))
    np.save(root / "new_joints" / f"{cid}.npy", rec)
    (root / "texts" / f"{cid}.txt").write_text("\n".join(lines) + "\n", encoding="utf-8")
    return int(len(vecs))


def process_clip(root: str, stem: str, data: bytes, mirror: bool = True) -> dict:
    """Worker: one BVH -> files for ID (and M+ID) under ``root``. Returns a summary or {'error': ...}."""
    from ..motion import features as F

    name = parse_clip_name(stem)
    root = Path(root)
    try:
        joints = clip_joints(data, source=f"{stem}.bvh")
    except (BVHError, KeyError) as exc:
        return {"id": stem, "error": str(exc)}
    if len(joints) < MIN_FRAMES + 1:
        return {"id": stem, "error": f"too short ({len(joints)} frames at {TARGET_FPS} fps)"}
    why = implausible(joints, TARGET_FPS)
    if why:
        return {"id": stem, "error": f"implausible: {why}"}
    texts = cap.captions_for(name.content, name.style, stem)
    out = {"id": stem, "content": name.content, "style": name.style, "dataset": name.dataset,
           "captions": texts}
    try:
        out["frames"] = _write_clip(root, stem, joints, [cap.caption_line(t) for t in texts])
        if mirror:
            m_texts = [F.mirror_text(t) for t in texts]
            out["mirror_frames"] = _write_clip(root, "M" + stem, F.mirror_joints(joints),
                                               [cap.caption_line(t) for t in m_texts])
            out["mirror_captions"] = m_texts
    except ValueError as exc:
        return {"id": stem, "error": f"feature extraction failed: {exc}"}
    return out


# --------------------------------------------------------------------------------------------------
# The output folder
# --------------------------------------------------------------------------------------------------


def _read_manifest(folder: Path) -> dict | None:
    try:
        data = json.loads((folder / MANIFEST).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) and data.get("written_by") == "mld_core data prepare" else None


def written_files(folder: Path) -> list[str]:
    """Every file under ``folder``, as sorted paths relative to it."""
    return sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*") if not p.is_dir())


_LAYOUT_FILES = {MANIFEST, "LICENSE", "README.md", "Mean.npy", "Std.npy", "actions.json", "all.txt", "train.txt",
                 "val.txt", "test.txt"}
_LAYOUT_DIRS = {"new_joint_vecs", "new_joints", "texts"}


def _ours(relative: str, listed: set | None) -> bool:
    """Whether a previous run wrote this file: ``listed`` in its manifest (older manifests list no files: then the
    folder layout this command writes decides)."""
    if relative == MANIFEST:
        return True
    if listed is not None:
        return relative in listed
    top, _, rest = relative.partition("/")
    return relative in _LAYOUT_FILES if not rest else (top in _LAYOUT_DIRS and "/" not in rest)


def _identity(folder: Path) -> tuple | None:
    """Which output ``folder`` holds: None when it is absent or empty, else (device, inode, its manifest's mtime)."""
    try:
        if not any(folder.iterdir()):
            return None
        st, manifest = folder.stat(), (folder / MANIFEST).stat()
    except OSError:
        return None
    return st.st_dev, st.st_ino, manifest.st_mtime_ns


def check_out(out: Path) -> tuple | None:
    """Refuse an --out that holds anything but a previous output of this command: a rerun replaces only the files
    that run listed in its manifest, so a file the user added there stops it (nothing is changed). Returns what it
    found there (None: nothing), for :func:`swap_into_place`."""
    _check_out(out)
    return _identity(out)


def _check_out(out: Path) -> None:
    try:
        check_output_folder(out, "--out", staged_beside=True)
    except InputError as exc:
        raise PrepareError(str(exc)) from None
    if not out.is_dir() or not any(out.iterdir()):
        return
    manifest = _read_manifest(out)
    if manifest is None:
        raise PrepareError(
            f"--out {out} is not empty and was not written by this command (no {MANIFEST}); "
            "choose a new or empty folder - nothing was changed"
        )
    listed = set(manifest["files"]) if isinstance(manifest.get("files"), list) else None
    extra = [f for f in written_files(out) if not _ours(f, listed)]
    if extra:
        raise PrepareError(
            f"--out {out} holds {len(extra)} file(s) this command did not write (e.g. {extra[0]}); move them out "
            "or choose another folder - nothing was changed"
        )


def _readme(summary: dict) -> str:
    s = summary
    return f"""# Bandai Namco Research motion datasets in HumanML3D format

Written by `python -m mld_core data prepare bandai` (format version {FORMAT_VERSION}).

- {s['clips']} clips from the BVH files + {s['mirrored']} mirrored copies (`M` + id), {s['frames']} frames at
  {TARGET_FPS} fps ({s['frames'] / TARGET_FPS / 3600:.2f} h) including the mirrored copies.
- Splits (stratified by content x style, deterministic): train {s['splits']['train']}, val {s['splits']['val']},
  test {s['splits']['test']} ids (mirrored copies included, always in their source's split).
- `new_joint_vecs/ID.npy`: HumanML3D's 263-dim features (T-1, 263); `new_joints/ID.npy`: joints
  recovered from them (T-1, 22, 3), metres, Y up, facing +Z at frame 0.
- `texts/ID.txt`: generated English captions (`caption#word/POS ...#0.0#0.0`; 0.0/0.0 = the whole clip),
  built from the content and style labels; sides are the performer's own.
- `actions.json`: `classes` (content labels), `clips` (id -> content), `styles` (id -> style).
- `Mean.npy`, `Std.npy`: feature statistics over the train split.
- Skipped clips: {len(s['skipped'])} (listed in `{MANIFEST}`).

## Source and licence

The motion data is derived from the Bandai-Namco-Research-Motiondataset-1 and -2 by Bandai Namco Research
Inc. (https://github.com/BandaiNamcoResearchInc/Bandai-Namco-Research-Motiondataset), licensed under
Creative Commons Attribution-NonCommercial 4.0 International (CC BY-NC 4.0); see LICENSE. Changes: joint
positions were retargeted to a 22-joint skeleton, resampled from 30 to 20 fps, converted to HumanML3D
features, mirrored, and captioned automatically. Non-commercial use only.

Please cite: {CITATION}
"""


def _license(original: str | None) -> str:
    head = (
        "The motion data in this folder is derived from the Bandai-Namco-Research-Motiondataset\n"
        "(c) 2022 Bandai Namco Research Inc., licensed under the Creative Commons\n"
        "Attribution-NonCommercial 4.0 International licence (CC BY-NC 4.0):\n"
        "https://creativecommons.org/licenses/by-nc/4.0/legalcode\n"
        "It was modified (retargeted, resampled, converted to features, mirrored, captioned).\n"
        f"Reference: {CITATION}\n"
    )
    if original:
        return head + "\nThe licence text as distributed with the dataset follows.\n\n" + original
    return head


def swap_into_place(tmp: Path, out: Path, found: tuple | None) -> None:
    """Rename the finished folder ``tmp`` to ``out``. Only ``found``, what :func:`check_out` found there when the run
    began, is replaced: a new or empty ``out`` is claimed only if still new or empty, a previous output (checked
    again) is moved aside, renamed over and then removed. An output another run put there meanwhile wins:
    PrepareError, and this run keeps nothing."""
    another_run = (f"--out {out} was written by another run meanwhile; this run kept nothing - choose another folder "
                   "or run it again")
    try:
        _check_out(out)
    except OSError:  # another run is moving a previous output out of the way right now
        raise PrepareError(another_run) from None
    except PrepareError:
        if _identity(out) != found:  # what is there now is not what this run found: another run's doing
            raise PrepareError(another_run) from None
        raise
    try:
        if found is None:
            claim_folder(tmp, out)
        else:
            _replace(tmp, out, found)
    except FileExistsError:
        raise PrepareError(another_run) from None
    except OSError as exc:
        raise PrepareError(f"cannot write --out {out}: {exc.strerror or exc}") from None


def _replace(tmp: Path, out: Path, found: tuple) -> None:
    """Put ``tmp`` in place of the previous output ``found`` at ``out``; FileExistsError when ``out`` holds another
    output by then (put back as it was)."""
    old = Path(tempfile.mkdtemp(prefix=f".{out.name}.old-", dir=out.parent))
    os.rmdir(old)
    try:
        os.rename(out, old)
    except FileNotFoundError:  # another run moved it first
        raise FileExistsError(out) from None
    if _identity(old) != found:  # a newer output, not the one this run found: it stays
        claim_folder(old, out)
        raise FileExistsError(out)
    try:
        claim_folder(tmp, out)
    except FileExistsError:  # a run that began after the previous output was moved aside: its output wins
        shutil.rmtree(old, ignore_errors=True)
        raise
    except OSError:
        claim_folder(old, out)  # the previous output back in place
        raise
    shutil.rmtree(old, ignore_errors=True)


def prepare_bandai(src, out, *, workers: int = 2, mirror: bool = True, progress: bool = True,
                   limit: int | None = None) -> dict:
    """Build the HumanML3D-format folder ``out`` from the Bandai source ``src``; returns a summary dict.

    Raises PrepareError for a bad SRC or --out before anything is written. The folder is built in a
    temporary sibling and renamed into place; an existing previous output is replaced only at the end.
    """
    from tqdm import tqdm

    src = Path(src).expanduser()
    out = Path(out).expanduser().absolute()
    kind = check_source(src)
    found = check_out(out)
    try:
        if out.resolve().is_relative_to(src.resolve()) and kind == "folder":
            raise PrepareError(f"--out {out} must not be inside SRC {src}")
    except OSError:
        pass
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.partial-", dir=out.parent))
    try:
        for sub in ("new_joint_vecs", "new_joints", "texts"):
            (tmp / sub).mkdir()
        results: list[dict] = []
        licenses: dict[str, str] = {}
        total = sum(1 for p in src.rglob("*.bvh") if _is_clip_member(p.name)) if kind == "folder" else None
        if limit is not None and total is not None:
            total = min(total, limit)
        bar = tqdm(total=total, unit="clip", desc="bandai", disable=not progress, dynamic_ncols=True)

        def sources():
            n = 0
            for stem, data in iter_source(src):
                if stem.startswith("LICENSE:"):
                    licenses[stem[8:]] = data.decode("utf-8", errors="replace")
                    continue
                if limit is not None and n >= limit:
                    continue
                n += 1
                yield stem, data

        if workers <= 1:
            _init_worker()
            for stem, data in sources():
                results.append(process_clip(str(tmp), stem, data, mirror))
                bar.update(1)
        else:
            ctx = multiprocessing.get_context("spawn")
            with cf.ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=_init_worker) as pool:
                pending: set[cf.Future] = set()
                for stem, data in sources():
                    pending.add(pool.submit(process_clip, str(tmp), stem, data, mirror))
                    if len(pending) >= 4 * workers:
                        done, pending = cf.wait(pending, return_when=cf.FIRST_COMPLETED)
                        for fut in done:
                            results.append(fut.result())
                            bar.update(1)
                for fut in cf.as_completed(pending):
                    results.append(fut.result())
                    bar.update(1)
        bar.close()

        ok = sorted((r for r in results if "error" not in r), key=lambda r: r["id"])
        skipped = {r["id"]: r["error"] for r in results if "error" in r}
        for cid, why in sorted(skipped.items()):
            print(f"warning: skipped {cid}: {why}", file=sys.stderr)
        if not ok:
            raise PrepareError(f"no usable clips in {src}")

        split_of = assign_splits({r["id"]: (r["content"], r["style"]) for r in ok})
        splits: dict[str, list[str]] = {"train": [], "val": [], "test": []}
        clips_label: dict[str, str] = {}
        clips_style: dict[str, str] = {}
        for r in ok:
            ids = [r["id"]] + (["M" + r["id"]] if mirror else [])
            labels = [r["content"]] + ([cap.mirror_content(r["content"])] if mirror else [])
            for cid, label in zip(ids, labels):
                splits[split_of[r["id"]]].append(cid)
                clips_label[cid] = label
                clips_style[cid] = r["style"]
        all_ids = write_splits(tmp, splits)

        actions = {
            "classes": sorted(set(clips_label.values())),
            "clips": {i: clips_label[i] for i in all_ids},
            "styles": {i: clips_style[i] for i in all_ids},
        }
        (tmp / "actions.json").write_text(json.dumps(actions, indent=1, sort_keys=False) + "\n", encoding="utf-8")

        frames = sum(r["frames"] + r.get("mirror_frames", 0) for r in ok)
        summary = {
            "written_by": "mld_core data prepare",
            "dataset": "bandai",
            "format_version": FORMAT_VERSION,
            "fps": TARGET_FPS,
            "clips": len(ok),
            "mirrored": len(ok) if mirror else 0,
            "frames": int(frames),
            "source_frames_20fps": int(sum(r["frames"] + 1 for r in ok)),
            "splits": {k: len(v) for k, v in splits.items()},
            "classes": actions["classes"],
            "skipped": skipped,
        }
        lic = next((licenses[k] for k in sorted(licenses)), None)
        (tmp / "README.md").write_text(_readme(summary), encoding="utf-8")
        (tmp / "LICENSE").write_text(_license(lic), encoding="utf-8")
        terms.write(tmp, [terms.BANDAI])
        manifest = {**summary, "files": written_files(tmp)}  # what a rerun may replace, and nothing else
        (tmp / MANIFEST).write_text(json.dumps(manifest, indent=1) + "\n", encoding="utf-8")

        swap_into_place(tmp, out, found)
        summary["out"] = str(out)
        return summary
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
