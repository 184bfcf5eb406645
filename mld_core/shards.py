"""Sharded generation: N machines make exactly the takes one machine would, and the shards join into one library.

Shard I of N (``--shard I/N``, counted from 0) takes prompt lines I, I + N, I + 2N, ... with the seeds those lines
have in the unsharded run (line i, variant v: seed + i * variants + v; the batch: seed + i). Each shard records
what it is (its index and count, the number of lines, and a fingerprint of the model and of every setting that
shapes a take); :func:`merge_npz` (``python -m mld_core merge``) and :func:`merge_manifests` (``batch.py --merge``)
join shards into the unsharded run's output, refusing shards of other models or settings, overlapping shards and
missing ones. Nothing here needs bpy or a model.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import numpy as np

from mld_core import inputs
from mld_core.fileio import OutputSet
from mld_core.inputs import InputError

SHARD_KEY = "shard"  # in a shard's .npz (a JSON string) and its batch manifest (an object)
SETTING_NAMES = {"model": "model files", "model_id": "model_id", "prompts": "prompt lines"}


def shard_lines(total: int, shard: tuple[int, int], what: str = "--shard") -> list[int]:
    """The line indices (0-based, of ``total``) shard (I, N) makes; refused when it has none."""
    index, count = shard
    lines = list(range(index, total, count))
    if not lines:
        raise InputError(f"{what} {index}/{count}: there are {total} prompt line(s), so shard {index} has none; "
                         f"use at most {total} shard(s)")
    return lines


def model_fingerprint(model_dir) -> str:
    """SHA-256 of what in a model folder (None: the bundled model) shapes a take: its config.json, weights and
    indexes (about 0.1 s for the bundled model); shards of other models, or other weights, differ here."""
    from mld_core.bundled import WEIGHTS_DIR, UnknownModel, bundled_models, model_folder
    from mld_core.model_route import is_auto

    if is_auto(model_dir):  # any bundled model may make a line
        joined = "".join(model_fingerprint(WEIGHTS_DIR / name) for name in bundled_models())
        return hashlib.sha256(("auto\0" + joined).encode()).hexdigest()
    try:
        folder = model_folder(model_dir)
    except UnknownModel:  # nothing to fingerprint: loading the model says why
        folder = Path(model_dir)
    digest = hashlib.sha256()
    for path in sorted(folder.glob("*")):
        if path.is_file() and (path.name == "config.json" or path.suffix in (".safetensors", ".npz")):
            digest.update(path.name.encode() + b"\0" + path.read_bytes())
    return digest.hexdigest()


def lines_fingerprint(lines) -> str:
    """SHA-256 of prompt lines as read (their text and frames): shards of other prompt files differ here."""
    text = "\n".join(f"{line.frames}\t{line.text}" for line in lines)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def file_fingerprint(path) -> str | None:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest() if path is not None else None


def shard_record(shard: tuple[int, int], lines: int, settings: dict) -> dict:
    """What a shard's output says about itself."""
    return {"index": shard[0], "count": shard[1], "lines": lines, "settings": settings}


def check_shards(records: list[dict], sources: list[Path]) -> None:
    """Shards that make one run: one count, one number of lines, one model and settings, and each index from 0 to
    N - 1 exactly once."""
    for record, source in zip(records, sources):
        if not isinstance(record, dict) or not {"index", "count", "lines", "settings"} <= set(record):
            raise InputError(f"{source} is not the output of a shard (made without --shard I/N)")
    first, first_source = records[0], sources[0]
    for record, source in zip(records[1:], sources[1:]):
        if record["count"] != first["count"]:
            raise InputError(f"{source} is shard {record['index']}/{record['count']} but {first_source} is shard "
                             f"{first['index']}/{first['count']}: shards of one run have one count")
        if record["lines"] != first["lines"]:
            raise InputError(f"{source} was made from {record['lines']} prompt lines, {first_source} from "
                             f"{first['lines']}: not shards of one prompt file")
        differ = sorted(k for k in set(record["settings"]) | set(first["settings"])
                        if record["settings"].get(k) != first["settings"].get(k))
        if differ:
            named = ", ".join(SETTING_NAMES.get(k, k) for k in differ)
            raise InputError(f"{source} and {first_source} were made with different {named}: shards of one run "
                             "share the model and every setting")
    seen: dict[int, Path] = {}
    for record, source in zip(records, sources):
        if record["index"] in seen:
            raise InputError(f"{seen[record['index']]} and {source} are both shard {record['index']}/"
                             f"{record['count']}: give each shard once")
        seen[record["index"]] = source
    missing = [i for i in range(first["count"]) if i not in seen]
    if missing:
        count = first["count"]
        raise InputError(f"shard(s) {', '.join(f'{i}/{count}' for i in missing)} missing: give all {count} shards "
                         "of the run")


def _check_sources(paths: list, suffix: str) -> list[Path]:
    paths = [Path(p) for p in paths]
    if len(paths) < 1:
        raise InputError("give the shards to merge")
    for path in paths:
        if not path.is_file():
            raise InputError(f"{path}: no such file")
        if path.suffix.lower() != suffix:
            raise InputError(f"{path}: shards to merge are all {suffix} files")
    return paths


# -- generate's .npz ---------------------------------------------------------------------------------------------
ROW_KEYS = ("features", "joints", "lengths", "prompts", "seeds", "draws")


def read_npz_shard(path: Path) -> dict:
    try:
        with np.load(path, allow_pickle=False) as data:
            content = {k: data[k] for k in data.files}
    except (OSError, ValueError) as exc:
        raise InputError(f"{path} is not a .npz file of takes: {str(exc).splitlines()[0]}") from None
    try:
        content[SHARD_KEY] = json.loads(str(content[SHARD_KEY])) if SHARD_KEY in content else None
    except ValueError:
        content[SHARD_KEY] = None
    return content


def merge_npz(paths: list, out, bvh=None, overwrite: bool = False) -> tuple[Path, list[Path]]:
    """Join ``generate --shard`` outputs into the .npz (and with ``bvh``, the BVH files) the unsharded run writes;
    returns (the .npz, the BVH files)."""
    from mld_core.generate import bvh_paths

    paths = _check_sources(paths, ".npz")
    shards = [read_npz_shard(p) for p in paths]
    records = [s[SHARD_KEY] for s in shards]
    check_shards(records, paths)
    rows = _merged_rows(shards)
    total = len(rows)
    outputs = {"--out": Path(out)}
    if bvh is not None:
        if not all(r["settings"].get("bvh") for r in records):
            raise InputError("--bvh: the shards were made without --bvh, so there are no BVH files to merge")
        outputs.update({f"--bvh ({p.name})": p for p in bvh_paths(Path(bvh), total)})
    inputs.check_outputs(outputs, {f"shard {i}": p for i, p in enumerate(paths)}, overwrite=overwrite)
    sources = _bvh_sources(shards, paths, rows) if bvh is not None else []
    merged = _stack(shards, rows)
    with OutputSet(overwrite=overwrite) as staged:
        staged.stage(out, lambda tmp: _save_npz(tmp, merged))
        targets = bvh_paths(Path(bvh), total) if bvh is not None else []
        for source, target in zip(sources, targets):
            staged.stage(target, lambda tmp, source=source: shutil.copyfile(source, tmp))
    return Path(out), targets


def _merged_rows(shards: list[dict]) -> list[tuple[int, int]]:
    """(shard, row) of every row in the unsharded run's order: by line, then as the shard wrote them."""
    order = []
    for s, shard in enumerate(shards):
        lines = np.asarray(shard.get("lines", []))
        if len(lines) != len(shard["lengths"]):
            raise InputError("a shard's .npz has no line of each take (made by an older version?)")
        order += [(int(line), s, r) for r, line in enumerate(lines)]
    order.sort()
    return [(s, r) for _, s, r in order]


def _stack(shards: list[dict], rows: list[tuple[int, int]]) -> dict:
    """The merged arrays: features padded with zeros and joints with each take's last pose, as the pipeline pads."""
    T = max(int(s["features"].shape[1]) for s in shards)
    features, joints = [], []
    for s, r in rows:
        f, j = shards[s]["features"][r], shards[s]["joints"][r]
        n = int(shards[s]["lengths"][r])
        features.append(np.concatenate([f, np.zeros((T - len(f),) + f.shape[1:], f.dtype)]))
        joints.append(np.concatenate([j, np.repeat(j[n - 1:n], T - len(j), axis=0)]))
    merged = {"features": np.stack(features), "joints": np.stack(joints)}
    for key in ("lengths", "prompts", "seeds", "draws"):
        if all(key in s for s in shards):
            merged[key] = np.asarray([shards[s][key][r] for s, r in rows])
    for key in ("fps", "model_id"):
        merged[key] = shards[0][key]
    if all("quality" in s for s in shards):
        per_shard = [json.loads(str(s["quality"])) for s in shards]
        merged["quality"] = np.array(json.dumps([per_shard[s][r] for s, r in rows]))
    return merged


def _save_npz(tmp: str, arrays: dict) -> None:
    with open(tmp, "wb") as f:
        np.savez(f, **arrays)


def _bvh_sources(shards: list[dict], paths: list[Path], rows: list[tuple[int, int]]) -> list[Path]:
    """Each merged row's BVH file as its shard wrote it (found where recorded, or beside the shard's .npz)."""
    found = []
    for s, r in rows:
        recorded = Path(shards[s][SHARD_KEY]["bvh"][r])
        candidates = [recorded, paths[s].parent / recorded, paths[s].parent / recorded.name]
        source = next((c for c in candidates if c.is_file()), None)
        if source is None:
            raise InputError(f"{paths[s]}: its BVH file {recorded} is missing (looked beside the shard too)")
        found.append(source)
    return found


# -- the batch's manifests ---------------------------------------------------------------------------------------
MACHINE_SETTINGS = ("device",)  # settings a shard may choose for its machine: its takes are the same


def read_manifest(path: Path) -> dict:
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise InputError(f"{path} is not a batch manifest (JSON): {str(exc).splitlines()[0]}") from None
    if not isinstance(data, dict) or data.get("format") != "mld-takes" or not isinstance(data.get("takes"), list):
        raise InputError(f"{path} is not a batch manifest (format mld-takes)")
    return data


def merge_manifests(paths: list, out, bvh_dir=None, overwrite: bool = False) -> tuple[Path, list[Path]]:
    """Join ``batch.py --shard`` manifests into one library manifest (takes in the prompt file's order, each naming
    the .blend that holds its Action) and, with ``bvh_dir``, the shards' BVH files into one folder; returns (the
    manifest, the BVH files)."""
    paths = _check_sources(paths, ".json")
    manifests = [read_manifest(p) for p in paths]
    check_shards([m.get(SHARD_KEY) for m in manifests], paths)
    out = Path(out)
    if out.suffix.lower() != ".json":
        raise InputError(f"--out {out}: the merged manifest is a .json file")
    takes = []
    for path, manifest in zip(paths, manifests):
        takes += [(take, path, manifest) for take in manifest["takes"]]
    takes.sort(key=lambda item: item[0].get("line", 0))
    outputs, copies = {"--out": out}, []
    if bvh_dir is not None:
        inputs.check_output_folder(Path(bvh_dir), "--bvh-dir")
        for take, path, _ in takes:
            if not take.get("bvh"):
                raise InputError(f"{path}: take {take.get('name')} has no BVH file (made without --bvh-dir)")
            source = _beside(Path(take["bvh"]), path)
            target = Path(bvh_dir) / source.name
            if any(target == t for _, t in copies):
                raise InputError(f"two takes have the BVH name {source.name}: merge them into separate folders")
            copies.append((source, target))
        outputs.update({f"--bvh-dir file ({t.name})": t for _, t in copies})
    inputs.check_outputs(outputs, {f"shard {i}": p for i, p in enumerate(paths)}, overwrite=overwrite)
    first = manifests[0]
    merged = {key: value for key, value in first.items() if key not in ("blend", "takes", "timing", "preview",
                                                                          SHARD_KEY)}
    merged["settings"] = {k: v for k, v in first["settings"].items() if k not in MACHINE_SETTINGS}
    merged["blends"] = [m.get("blend", "") for m in manifests]
    merged["merged_from"] = [str(p) for p in paths]
    merged["takes"] = []
    by_source = dict(zip([str(s) for s, _ in copies], [str(t) for _, t in copies]))
    for take, path, manifest in takes:
        entry = {**take, "blend": manifest.get("blend", "")}
        if bvh_dir is not None:
            entry["bvh"] = by_source[str(_beside(Path(take["bvh"]), path))]
        merged["takes"].append(entry)
    text = json.dumps(merged, indent=2) + "\n"
    with OutputSet(overwrite=overwrite) as staged:
        staged.stage(out, lambda tmp: Path(tmp).write_text(text, encoding="utf-8"))
        for source, target in copies:
            staged.stage(target, lambda tmp, source=source: shutil.copyfile(source, tmp), suffix=".bvh")
    return out, [t for _, t in copies]


def _beside(recorded: Path, manifest: Path) -> Path:
    """A file a manifest names: where recorded, else by the same relative path or name beside the manifest."""
    for candidate in (recorded, manifest.parent / recorded, manifest.parent / recorded.parent.name / recorded.name,
                      manifest.parent / recorded.name):
        if candidate.is_file():
            return candidate
    raise InputError(f"{manifest}: its file {recorded} is missing (looked beside the manifest too)")


# -- python -m mld_core merge ------------------------------------------------------------------------------------
def run(args) -> int:
    """``merge``: .npz shards of ``generate`` or .json manifests of the batch, by their suffix."""
    kinds = {Path(p).suffix.lower() for p in args.shards}
    for path in args.shards:
        if Path(path).suffix.lower() not in (".npz", ".json"):
            raise InputError(f"{path}: merge takes generate's .npz shards or the batch's .json manifests")
    if kinds == {".npz"}:
        if args.bvh_dir is not None:
            raise InputError("--bvh-dir merges batch manifests' BVH files; for .npz shards give --bvh OUT.bvh")
        out, bvhs = merge_npz(args.shards, args.out, args.bvh, args.overwrite)
    elif kinds == {".json"}:
        if args.bvh is not None:
            raise InputError("--bvh merges generate's .npz shards; for batch manifests give --bvh-dir DIR")
        out, bvhs = merge_manifests(args.shards, args.out, args.bvh_dir, args.overwrite)
    else:
        raise InputError("give either generate's .npz shards or the batch's .json manifests to merge, not both")
    print(f"wrote {out} ({len(args.shards)} shards)" + (f" and {len(bvhs)} BVH file(s)" if bvhs else ""))
    return 0


def register(groups) -> None:
    p = groups["root"].add_parser(
        "merge", help="join the outputs of sharded runs (generate --shard, batch.py --shard) into one")
    p.add_argument("shards", nargs="+", help="every shard's .npz (generate) or .json manifest (batch.py)")
    p.add_argument("--out", required=True, help="the merged .npz or manifest .json")
    p.add_argument("--bvh", default=None, help=".npz shards made with --bvh: the merged run's BVH name")
    p.add_argument("--bvh-dir", default=None, help="manifests made with --bvh-dir: one folder for every take's BVH")
    p.add_argument("--overwrite", action="store_true", help="replace existing output files")
    p.set_defaults(func=run)
