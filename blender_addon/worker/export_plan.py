"""The batch's game-engine export planned from its flags (bpy-free): the settings (``--export``, ``--root-motion``,
``--root-yaw``, ``--bone-names``, ``--one-file``), the files for the takes (``--export-dir``, default beside
``--out``) and their checks against the batch's other outputs and inputs: before any work with the takes' names
as they will be made, and again once the takes exist."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from mld_core.inputs import InputError
from mld_core.rig import engine_export as ee

from .naming import action_name, unique_name


@dataclass(frozen=True)
class ExportPlan:
    settings: ee.ExportSettings
    folder: Path
    files: tuple  # engine_export.ExportFile


def add_arguments(parser) -> None:
    """The batch's flags for game engines (docs/game_engines.md)."""
    group = parser.add_argument_group("game engines (docs/game_engines.md)")
    group.add_argument("--export", metavar="FORMAT", action="append", default=[],
                       help="also write the takes as fbx, glb or bvh files (repeat, or fbx,glb, for several)")
    group.add_argument("--export-dir", metavar="DIR", help="folder of the exported files (default: beside --out)")
    group.add_argument("--one-file", action="store_true",
                       help="one FBX / GLB holding every take as its own animation, named after --out (BVH: one "
                            "file per take)")
    group.add_argument("--root-motion", metavar="MODE", default=None,
                       help="object (default: the hips carry the travel), in-place (travel removed) or root-bone "
                            "(travel on a root bone)")
    group.add_argument("--root-yaw", action="store_true", help="in-place / root-bone: the turning goes too")
    group.add_argument("--bone-names", metavar="NAMING", default=None,
                       help="bone names in the exported files: canonical (default), mixamo, ue5 or unity")


def settings_from_args(args) -> ee.ExportSettings | None:
    """The export settings, or None without ``--export`` (refused: the other export flags alone)."""
    if not args.export:
        given = [flag for flag, value in (("--export-dir", args.export_dir), ("--one-file", args.one_file),
                                           ("--root-motion", args.root_motion), ("--root-yaw", args.root_yaw),
                                           ("--bone-names", args.bone_names)) if value]
        if given:
            raise InputError(f"{given[0]} needs --export FORMAT (fbx, glb or bvh)")
        return None
    settings = ee.ExportSettings.parse(args.export, args.root_motion or "object", args.root_yaw,
                                       args.bone_names or "canonical", args.one_file)
    if settings.yaw and settings.root_motion == "object":
        raise InputError("--root-yaw needs --root-motion in-place or root-bone (with object the hips keep "
                         "their turning)")
    return settings


def planned_names(requests, existing=()) -> list[str]:
    """The Action names the batch will give its takes (as ``scene/key_takes`` names them)."""
    taken, names = set(existing), []
    for request in requests:
        name = unique_name(action_name(request.prompt, request.seed), taken)
        taken.add(name)
        names.append(name)
    return names


def plan(args, paths: dict, take_names, options: dict, bvh_files: dict | None = None) -> ExportPlan | None:
    """The export's files for ``take_names``, checked with the batch's outputs ``paths`` (keys: blend, manifest,
    preview; ``options`` names their flags) and ``bvh_files`` ({label: path}), and against its input files: none
    equal to another, none existing without --overwrite, the folder writable. None without --export."""
    settings = settings_from_args(args)
    if settings is None:
        return None
    folder = Path(args.export_dir) if args.export_dir else Path(paths["blend"]).parent
    from mld_core.inputs import check_output_folder

    check_output_folder(folder, "--export-dir")
    files = ee.export_files(folder, Path(paths["blend"]).stem, list(take_names), settings)
    others = {options[k]: Path(p) for k, p in paths.items()}
    others.update(bvh_files or {})
    sources = {flag: Path(value) for flag, value in (("--prompts", args.prompts), ("--jobs", args.jobs),
                                                     ("--rig", args.rig), ("--bvh-rig", args.bvh_rig),
                                                     ("--bone-map", args.bone_map)) if value}
    ee.check_export_files(files, others, sources, overwrite=args.overwrite)
    return ExportPlan(settings, folder, tuple(files))


def batch_plan(args, paths: dict, options: dict, bvh_dir: Path | None, names) -> ExportPlan | None:
    """The batch's export plan for the takes ``names`` (None without --export), checked with its ``paths``
    (``options`` names their flags) and the ``bvh_dir`` files the takes get."""
    if not args.export and not any((args.export_dir, args.one_file, args.root_motion, args.root_yaw,
                                    args.bone_names)):
        return None
    bvh = {f"--bvh-dir file ({n})": bvh_dir / f"{n}.bvh" for n in names} if bvh_dir is not None else {}
    return plan(args, paths, names, options, bvh)
