"""Headless batch: prompts in, an animated .blend (one Action per prompt) and a JSON manifest out.

Inside Blender::

    blender -b [scene.blend] --python batch.py -- --prompts prompts.txt --out takes.blend \\
        [--armature NAME] [--seconds S] [--seed N] [--bvh-dir DIR] [--preview takes.png] [--overwrite]

With the bpy module from plain Python (the README's main command)::

    python blender_addon/batch.py --prompt "a person walks forward and waves" --out out/take.blend \\
        --preview out/take.png --overwrite

A prompt file has one take per line: plain text, or MLD's ``<frames> <text>`` (frames at 20 fps); blank lines
and ``#`` comments are skipped. Line i uses seed ``--seed + i``. Without ``--armature`` the canonical armature
(with a simple body mesh) is created, or reused if the file has one. The first take is assigned to the
armature; every take is an Action with a fake user. Outputs are written atomically (temporary file, then
rename); existing outputs are refused without ``--overwrite``. Exit codes: 0 done, 1 failed while running,
2 bad input.

Keying a user's rig (retargeted through a bone map, see docs/retarget.md)::

    python blender_addon/batch.py --prompts prompts.txt --out takes.blend \
        --rig character.blend --rig-object Armature [--bone-map map.json] \
        [--reduce] [--tolerance 0.5] [--rotation-mode QUATERNION|XYZ|...|KEEP] [--foot-lock] [--match effectors|directions] [--nla]
    python blender_addon/batch.py --prompt "a person bows" --out bow.blend --bvh-rig skeleton.bvh --bvh-scale 0.01

``--rig`` appends the objects of a .blend (the armature and its meshes); ``--bvh-rig`` imports a BVH file with
Blender's own importer (its clip is kept as an Action with a fake user, not assigned). The bone map is
``--bone-map`` (a JSON file saved by the panel's Save Map...), else the detected one; a map without the
required bones is bad input (exit 2, nothing written).

Into a game engine (docs/game_engines.md): the takes also as FBX / GLB / BVH files, with the travel in place or on a
root bone and engine bone names, listed with their sha256 in the manifest::

    python blender_addon/batch.py --prompts prompts.txt --out takes.blend --export fbx --export glb \
        [--export-dir DIR] [--one-file] [--root-motion object|in-place|root-bone] [--root-yaw] \
        [--bone-names canonical|mixamo|ue5|unity]
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

EXIT_OK, EXIT_FAILED, EXIT_USAGE = 0, 1, 2


class BatchError(Exception):
    """Bad input: printed as one line, exit code 2."""


def _addon_package():
    """This add-on's package, whether we run as a script (blender --python / python) or were imported."""
    if __package__:
        return importlib.import_module(__package__)
    here = Path(__file__).resolve().parent
    parent = str(here.parent)
    if parent not in sys.path:
        sys.path.insert(0, parent)
    return importlib.import_module(here.name)


_addon_package()  # puts mld_core (the vendored copy or the checkout) on sys.path
from mld_core import inputs, shards  # noqa: E402
from mld_core.bundled import UnknownModel, model_folder  # noqa: E402
from mld_core.model_route import is_auto  # noqa: E402
from mld_core.fileio import OutputSet  # noqa: E402
from mld_core.take_report import other_model_note, seam_lines, side_report  # noqa: E402


def script_argv(argv=None) -> list[str]:
    """Our arguments: after ``--`` when Blender runs the script, else everything after the script name."""
    argv = list(sys.argv if argv is None else argv)
    if "--" in argv:
        return argv[argv.index("--") + 1 :]
    return argv[1:]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="batch.py",
        description="Generate takes from text prompts into an animated .blend (MLD text-to-motion).",
    )
    src = parser.add_mutually_exclusive_group(required=True)
    src.add_argument("--prompts", metavar="FILE", help="prompt file: one take per line, '<frames> <text>' allowed")
    src.add_argument("--prompt", metavar="TEXT", action="append", help="a prompt (repeat for several takes)")
    src.add_argument("--jobs", metavar="FILE", help="JSON job file: prompts with keys / path / loop, or sequences "
                     "(docs/control.md)")
    src.add_argument("--merge", metavar="MANIFEST", nargs="+",
                     help="join the manifests of every --shard of a run into one (--out MERGED.json; --bvh-dir DIR "
                          "gathers their BVH files); no Blender work")
    parser.add_argument("--out", required=True, metavar="OUT.blend", help="the .blend to write")
    parser.add_argument("--armature", metavar="NAME", help="armature object to key (default: the canonical one)")
    parser.add_argument("--seconds", type=float, default=4.0, help="length of lines without a frame count (4)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the first take; take i uses seed+i (0)")
    parser.add_argument("--steps", type=int, default=50, help="diffusion steps (50; a Draft runs its model's own)")
    parser.add_argument("--guidance", type=float, default=None, help="guidance scale (default: the model's)")
    parser.add_argument("--side-redraws", type=int, default=None, metavar="N",
                        help="a take that misses the side its prompt names is drawn again from its seed, at most N "
                             "times (default: the model's, 2; 0: never, as takes made before 2026-11-27)")
    parser.add_argument("--verb-redraws", type=int, default=None, metavar="N",
                        help="a take that does not show the checked verb its prompt names (a jump, a crawl, a kick) "
                             "is drawn again from its seed, at most N times (default: the model's, a Draft's own "
                             "where its config sets one; 0: never)")
    parser.add_argument("--draft", action="store_true",
                        help="Draft mode: the model's distilled denoiser and a guided step of its own (about 10x faster)")
    parser.add_argument("--model", metavar="DIR", help="model folder, a bundled model's name, e.g. v4_preview, or "
                        "auto: each line by the bundled model that makes it (default: the bundled default model)")
    parser.add_argument("--device", default="cpu", help="cpu, cuda, mps or auto (cpu)")
    parser.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: default)")
    parser.add_argument("--fps", type=float, default=None,
                        help="scene frame rate (default: the open file's, else the --rig file's, else 20)")
    parser.add_argument("--bvh-dir", metavar="DIR", help="also write each take as a BVH file here")
    parser.add_argument("--preview", metavar="PNG", help="render a strip of frames of the first take")
    parser.add_argument("--manifest", metavar="JSON", help="manifest path (default: OUT with .json)")
    parser.add_argument("--no-exact", action="store_true", help="key rotations (+ root) only, not bone offsets")
    parser.add_argument("--overwrite", action="store_true", help="replace existing outputs")
    rt = parser.add_argument_group("your own rig (retargeting)")
    rig_src = rt.add_mutually_exclusive_group()
    rig_src.add_argument("--rig", metavar="FILE.blend", help="append the objects of this .blend and key its armature")
    rig_src.add_argument("--bvh-rig", metavar="FILE.bvh", help="import this BVH file (Blender's importer) as the rig")
    rt.add_argument("--rig-object", metavar="NAME", help="the armature object in --rig (default: its only armature)")
    rt.add_argument("--bvh-scale", type=float, default=1.0, help="--bvh-rig import scale (1; 0.01 for centimetres)")
    rt.add_argument("--bone-map", metavar="JSON", help="bone map file (panel: Save Map...); default: detected")
    rt.add_argument("--reduce", dest="reduce", action="store_true", default=False,
                    help="key reduction (Bezier keys within --tolerance); routes the canonical rig through it too")
    rt.add_argument("--no-reduce", dest="reduce", action="store_false", help="a key on every frame (default)")
    rt.add_argument("--tolerance", type=float, default=0.5, help="key reduction tolerance in degrees (0.5)")
    rt.add_argument("--rotation-mode", default="QUATERNION", type=str.upper,
                    help="QUATERNION (default), an Euler order (XYZ, XZY, YXZ, YZX, ZXY, ZYX) or KEEP (each bone's own)")
    rt.add_argument("--foot-lock", action="store_true", help="hold feet in place while in contact")
    rt.add_argument("--match", choices=("effectors", "directions"), default="effectors",
                    help="effectors (default): hands and feet land where the take puts them; directions: every limb "
                    "points as in the take, feet may sink")
    rt.add_argument("--nla", action="store_true", help="put each take on its own NLA track instead of assigning it")
    importlib.import_module(f"{_addon_package().__name__}.worker.export_plan").add_arguments(parser)
    parser.add_argument("--shard", metavar="I/N", default=None,
                        help="make only shard I of N (from 0): lines I, I + N, ... with the seeds of the whole run; "
                             "--merge joins the shards' manifests (docs/training.md)")
    return parser


def retarget_inputs(args, addon):
    """(RetargetSettings, BoneMap or None) from the arguments, checked before any work (BatchError)."""
    wiring = importlib.import_module("mld_core.rig.keying")
    bone_maps = importlib.import_module("mld_core.rig.bone_maps")
    try:
        settings = wiring.RetargetSettings(
            reduce=args.reduce, tolerance_deg=args.tolerance, rotation_mode=args.rotation_mode,
            foot_lock=args.foot_lock, nla=args.nla, match=args.match,
        )
    except ValueError as exc:
        raise BatchError(str(exc)) from None
    if args.rig_object and not args.rig:
        raise BatchError("--rig-object needs --rig FILE.blend")
    if (args.rig or args.bvh_rig) and args.armature:
        raise BatchError("--armature names an object of the open file; with --rig use --rig-object")
    if args.rig:
        path = Path(args.rig)
        if not path.suffix.lower() == ".blend":
            raise BatchError(f"--rig must name a .blend file, got {path}")
        if not path.is_file():
            raise BatchError(f"rig file not found: {path}")
    if args.bvh_rig:
        path = Path(args.bvh_rig)
        if not path.is_file():
            raise BatchError(f"BVH rig not found: {path}")
        inputs.number_in_range(args.bvh_scale, "--bvh-scale", 1e-4, 1e4)
        _check_bvh_file(path)
    bone_map = None
    if args.bone_map:
        path = Path(args.bone_map)
        if not path.is_file():
            raise BatchError(f"bone map not found: {path}")
        try:
            bone_map = bone_maps.BoneMap.load(path)
        except (bone_maps.BoneMapError, OSError, UnicodeDecodeError, TypeError, ValueError, AttributeError) as exc:
            raise BatchError(f"--bone-map {path}: {exc}") from None
    return settings, bone_map


def _check_bvh_file(path: Path) -> None:
    """Read the BVH with mld_core's parser first, so a broken file is one clear line, not Blender's traceback."""
    from mld_core.motion.bvh import BVHError, read_bvh

    try:
        read_bvh(path)
    except (BVHError, OSError, UnicodeDecodeError, ValueError) as exc:
        raise BatchError(f"--bvh-rig {path} is not a usable BVH file: {str(exc).splitlines()[0]}") from None


def headless(problem: str) -> str:
    """A bone-map problem worded for the command line (the panel's advice names its buttons)."""
    return problem.replace(". Pick the bones in the Retarget panel (or press Detect)",
                           ": give a --bone-map file (the panel's Save Map... writes one)")


def _rig_file_scene(path: Path) -> tuple[float | None, set[str], set[str]]:
    """(frame rate, excluded collections, hidden collections) of the first scene of ``path``, read by linking it
    for a moment (nothing of it stays in this file)."""
    import bpy

    with bpy.data.libraries.load(str(path), link=True) as (src, dst):
        dst.scenes = list(src.scenes[:1])
    scenes = [sc for sc in dst.scenes if sc is not None]
    if not scenes:
        return None, set(), set()
    scene = scenes[0]
    fps = scene.render.fps / (scene.render.fps_base or 1.0)
    excluded, hidden = set(), set()
    stack = list(scene.view_layers[0].layer_collection.children) if scene.view_layers else []
    while stack:
        layer = stack.pop()
        if layer.exclude:
            excluded.add(layer.collection.name)
        if layer.hide_viewport:
            hidden.add(layer.collection.name)
        stack.extend(layer.children)
    library = scene.library
    bpy.data.scenes.remove(scene)
    if library is not None:
        bpy.data.libraries.remove(library)
    return fps, excluded, hidden


def _keep_collection_visibility(excluded: set[str], hidden: set[str]) -> None:
    """Exclude or hide the appended collections that were so in the rig file's view layer."""
    import bpy

    stack = list(bpy.context.view_layer.layer_collection.children)
    while stack:
        layer = stack.pop()
        name = layer.collection.name
        if name in excluded:
            layer.exclude = True
        elif name in hidden:
            layer.hide_viewport = True
        stack.extend(layer.children)


def _append_rig(path: Path, name: str | None):
    """Append every object of ``path`` into the scene, in copies of the collections that held them (so what was
    hidden there, such as Rigify's widget shapes, stays hidden); returns the armature named ``name`` (or the only
    one)."""
    import bpy

    with bpy.data.libraries.load(str(path), link=False) as (src, dst):
        dst.objects = list(src.objects)
        dst.collections = list(src.collections)
    objects = [o for o in dst.objects if o is not None]
    collections = [c for c in dst.collections if c is not None]
    nested = {child for c in collections for child in c.children}
    scene_root = bpy.context.scene.collection
    for collection in collections:
        if collection not in nested and collection.name not in scene_root.children:
            scene_root.children.link(collection)
    for obj in objects:
        if not obj.users_collection:  # objects that stood only in the source scene's own collection
            scene_root.objects.link(obj)
    armatures = [o for o in objects if o.type == "ARMATURE"]
    if name:
        found = [o for o in armatures if o.name == name]
        if not found:
            raise BatchError(
                f"{path} has no armature named {name!r}; armatures: {', '.join(o.name for o in armatures) or 'none'}"
            )
        return found[0]
    if not armatures:
        raise BatchError(f"{path} has no armature object to key")
    if len(armatures) != 1:
        listed = ", ".join(o.name for o in armatures) or "none"
        raise BatchError(f"{path} has {len(armatures)} armatures ({listed}): name one with --rig-object")
    return armatures[0]


def _import_bvh_rig(path: Path, scale: float):
    """Import a BVH file with Blender's own importer; its clip stays in the file (fake user), unassigned."""
    import addon_utils
    import bpy

    addon_utils.enable("io_anim_bvh", default_set=True)
    before = set(bpy.data.objects)
    try:
        result = bpy.ops.import_anim.bvh(filepath=str(path), global_scale=float(scale))
    except RuntimeError as exc:
        raise BatchError(f"Blender could not import {path}: {str(exc).strip()}") from None
    new = [o for o in bpy.data.objects if o not in before and o.type == "ARMATURE"]
    if "FINISHED" not in result or not new:
        raise BatchError(f"Blender could not import {path} as an armature")
    obj = new[0]
    ad = obj.animation_data
    if ad is not None and ad.action is not None:
        ad.action.use_fake_user = True
        ad.action = None
    return obj


def output_paths(args) -> dict:
    out = Path(args.out)
    paths = {"blend": out, "manifest": Path(args.manifest) if args.manifest else out.with_suffix(".json")}
    if args.preview:
        paths["preview"] = Path(args.preview)
    return paths


OPTION = {"blend": "--out", "manifest": "--manifest", "preview": "--preview"}


def check_outputs(args, paths: dict) -> None:
    """Every output: a file name of the right kind, none equal to an input or another output, none existing
    without --overwrite (checked again when the outputs are put in place); --bvh-dir a writable folder that is
    none of those files and lies under none of them."""
    if not str(paths["blend"]).endswith(".blend"):
        raise BatchError(f"--out must name a .blend file, got {paths['blend']}")
    sources = {"--prompts": args.prompts, "--jobs": args.jobs, "--rig": args.rig, "--bvh-rig": args.bvh_rig,
               "--bone-map": args.bone_map}
    sources = {k: Path(v) for k, v in sources.items() if v}
    outputs = {OPTION[k]: p for k, p in paths.items()}
    inputs.check_outputs(outputs, sources, overwrite=args.overwrite)
    if args.bvh_dir:
        inputs.check_output_folder(Path(args.bvh_dir), "--bvh-dir", {**sources, **outputs})


def save_blend_copy(tmp: str) -> None:
    """Save a copy of the session into ``tmp`` (an OutputSet's temporary file)."""
    import bpy

    try:
        result = bpy.ops.wm.save_as_mainfile(filepath=tmp, copy=True, check_existing=False)
        if "FINISHED" not in result:
            raise RuntimeError(f"Blender could not save {tmp}")
    finally:
        if os.path.exists(tmp + "1"):  # Blender's backup of the (empty) temporary file
            os.unlink(tmp + "1")


def write_bvh(path: Path, take) -> None:
    """One take as BVH on the canonical skeleton, in centimetres (mld_core's writer renames atomically)."""
    from mld_core.motion.bvh import write_canonical_bvh

    write_canonical_bvh(path, take.root_positions, take.local_quats, 1.0 / take.fps, units_per_metre=100.0)


def _prepare_scene(args, addon):
    """The scene and the armature to key (creating the canonical one if needed)."""
    import bpy

    if not bpy.data.filepath:
        # no .blend given: start from an empty scene rather than the default cube
        bpy.ops.wm.read_factory_settings(use_empty=True)
        bpy.context.scene.render.fps = 20
        bpy.context.scene.render.fps_base = 1.0
    scene = bpy.context.scene
    if args.fps:
        fps = float(args.fps)
        scene.render.fps, scene.render.fps_base = max(1, round(fps)), round(fps) / fps
    rig = importlib.import_module(addon.__name__ + ".scene.canonical_armature")
    if args.rig:
        fps, excluded, hidden = _rig_file_scene(Path(args.rig))
        if fps and not args.fps:  # the rig file's frame rate, unless --fps says otherwise
            scene.render.fps, scene.render.fps_base = max(1, round(fps)), round(fps) / fps
        obj = _append_rig(Path(args.rig), args.rig_object)
        _keep_collection_visibility(excluded, hidden)
        return scene, obj
    if args.bvh_rig:
        return scene, _import_bvh_rig(Path(args.bvh_rig), args.bvh_scale)
    if args.armature:
        obj = bpy.data.objects.get(args.armature)
        if obj is None:
            names = [o.name for o in bpy.data.objects if o.type == "ARMATURE"]
            raise BatchError(f"no object named {args.armature!r}; armatures here: {', '.join(names) or 'none'}")
        return scene, obj
    obj = bpy.data.objects.get(rig.CANONICAL_NAME)
    if obj is not None and rig.is_canonical(obj):
        return scene, obj
    return scene, rig.create_canonical_armature(bpy.context, body=True)


def check_rig(obj, bone_map, addon) -> str:
    """Whether ``obj`` can be keyed (with ``bone_map``, else its detected map); returns the map's source."""
    apply = importlib.import_module(addon.__name__ + ".scene.key_takes")
    rig = importlib.import_module(addon.__name__ + ".scene.canonical_armature")
    wiring = importlib.import_module("mld_core.rig.keying")
    if bone_map is not None:
        problem = apply.not_editable(obj) or wiring.map_problem(bone_map, obj.data.bones.keys(), obj.name)
        if problem:
            raise BatchError(problem.replace(". Pick the bones in the Retarget panel (or press Detect)",
                                             " (fix the --bone-map file)"))
        return bone_map.source
    problem = apply.check_target(obj)
    if problem:
        raise BatchError(headless(problem))
    return "canonical" if rig.is_canonical(obj) else apply.bone_map_of(obj).source


@dataclass
class _Inputs:
    """Everything a batch run needs from its arguments, checked before any work."""

    lines: list
    requests: list
    model_dir: str | None
    paths: dict
    bvh_dir: Path | None
    retarget: object  # mld_core.rig.keying.RetargetSettings
    bone_map: object  # a BoneMap from --bone-map, or None
    export: object = None  # worker.export_plan.ExportPlan for --export (the files under the takes' planned names)
    shard: tuple | None = None  # --shard: ((I, N), lines in the whole run, their fingerprint)


def checked_inputs(args, addon) -> _Inputs:
    """1. Inputs: prompts, numbers, the model folder, every output path, dependencies, keying options."""
    batchfile = importlib.import_module(f"{addon.__name__}.worker.batchfile")
    env = importlib.import_module(f"{addon.__name__}.env")
    model_dir = args.model or env.model_dir_override()
    if model_dir and not is_auto(model_dir):
        try:  # a folder, or a bundled model's name (mld_core.bundled), recorded as given
            folder = model_folder(model_dir)
        except UnknownModel as exc:
            raise BatchError(str(exc)) from None
        if not folder.is_dir():
            raise BatchError(f"model folder not found: {model_dir}")
    extras = None
    if args.jobs:
        lines, extras = batchfile.read_job_file(args.jobs, model_dir)
    elif args.prompts:
        lines = batchfile.read_prompt_file(args.prompts)
    else:
        lines = batchfile.parse_prompt_lines("\n".join(p.replace("\n", " ") for p in args.prompt), source="--prompt")
    requests = batchfile.requests_from_lines(
        lines, default_seconds=args.seconds, seed=args.seed, extras=extras, steps=args.steps, guidance=args.guidance,
        variants=1, model_dir=model_dir, device=args.device, threads=args.threads, draft=args.draft,
    )
    for name, most in (("side_redraws", inputs.MAX_SIDE_REDRAWS), ("verb_redraws", inputs.MAX_VERB_REDRAWS)):
        if getattr(args, name) is not None:
            redraws = inputs.int_in_range(getattr(args, name), "--" + name.replace("_", "-"), 0, most)
            requests = [r.with_(extra={**r.extra, name: redraws}) for r in requests]
    shard = None
    if args.shard is not None:  # shard I of N: lines I, I + N, ... with the seeds they have in the whole run
        shard = (inputs.check_shard(args.shard), len(lines), shards.lines_fingerprint(lines))
        keep = shards.shard_lines(len(lines), shard[0])
        lines, requests = [lines[i] for i in keep], [requests[i] for i in keep]
    inputs.check_fps(args.fps, "--fps")
    inputs.number_in_range(args.tolerance, "--tolerance", 0, 180)
    paths = output_paths(args)
    check_outputs(args, paths)
    bvh_dir = Path(args.bvh_dir) if args.bvh_dir else None
    import bpy

    export_plan = importlib.import_module(f"{addon.__name__}.worker.export_plan")
    planned = export_plan.planned_names(requests, [a.name for a in bpy.data.actions])  # as the takes will be named
    export = export_plan.batch_plan(args, paths, OPTION, bvh_dir, planned)  # --export's files, checked
    missing = env.missing_modules()
    if missing:
        raise BatchError(env.dependency_message(missing))
    retarget, bone_map = retarget_inputs(args, addon)
    return _Inputs(lines, requests, model_dir, paths, bvh_dir, retarget, bone_map, export, shard)


def run(args) -> int:
    if args.merge:
        return merge(args)
    addon = _addon_package()
    t_start = time.perf_counter()
    # 1. Inputs, all checked before any work.
    inp = checked_inputs(args, addon)
    # 2. Scene and armature (and whether its bone map can take the motion: before the model loads).
    scene, obj = _prepare_scene(args, addon)
    map_source = check_rig(obj, inp.bone_map, addon)
    # 3. Model (once), then one take per line.
    model_cache = importlib.import_module(f"{addon.__name__}.worker.model_cache")
    t0 = time.perf_counter()
    cache = model_cache.PipelineCache()
    pipe = cache.get(None if is_auto(inp.model_dir) else inp.model_dir, args.device, args.threads)  # Auto: default
    load_s = time.perf_counter() - t0
    if args.draft and getattr(pipe, "draft_denoiser", None) is None:
        raise BatchError(f"--draft: the model {getattr(pipe, 'model_id', '?')} has no Draft denoiser "
                         "(make one with `python -m mld_core train draft`)")
    print(f"model {getattr(pipe, 'model_id', '?')} loaded in {load_s:.2f} s")
    records, bvh_takes = key_every_line(args, addon, inp, pipe, scene, obj, cache)
    export = None
    if inp.export is not None:  # the files checked again under the takes' real names, then written with the others
        names = [record["name"] for record in records]
        plan = importlib.import_module(f"{addon.__name__}.worker.export_plan").batch_plan(
            args, inp.paths, OPTION, inp.bvh_dir, names)
        export = importlib.import_module(f"{addon.__name__}.scene.export_takes").stager(
            obj, names, plan, inp.bone_map, scene)
    # 4. Outputs: the .blend, the manifest, the preview, the BVHs: staged, then put in place together.
    env = importlib.import_module(f"{addon.__name__}.env")
    manifest = _manifest(args, inp.paths, obj, map_source, pipe, inp.model_dir, inp.retarget, scene, records, env,
                         load_s, t_start)
    if inp.shard is not None:
        manifest["shard"] = shard_record(inp.shard, manifest, inp.model_dir)
    write_outputs(args, addon, inp.paths, scene, obj, manifest, bvh_takes, t_start, export)
    print(f"wrote {inp.paths['blend']} ({len(records)} take{'s' if len(records) != 1 else ''}) and "
          f"{inp.paths['manifest']}")
    return EXIT_OK


def key_every_line(args, addon, inp: _Inputs, pipe, scene, obj, cache) -> tuple[list, list]:
    """3. One take per prompt line, keyed as its own Action (the first assigned); (manifest records, BVHs to
    write). Under --model auto each line goes to the bundled model that makes it (``cache`` keeps them)."""
    generation = importlib.import_module(f"{addon.__name__}.worker.generation")
    model_choice = importlib.import_module(f"{addon.__name__}.worker.model_choice")
    key_takes = importlib.import_module(f"{addon.__name__}.scene.key_takes")
    min_s, max_s = getattr(pipe, "min_seconds", None), getattr(pipe, "max_seconds", None)
    records, bvh_takes = [], []
    for index, (line, request) in enumerate(zip(inp.lines, inp.requests)):
        if min_s is not None and not (min_s - 1e-6 <= request.seconds <= max_s + 1e-6):
            raise BatchError(f"line {line.line}: this model makes {min_s:g} to {max_s:g} s, got {request.seconds:g}")
        t0 = time.perf_counter()
        if is_auto(request.model_dir):
            pipe = _routed_pipe(model_choice, cache, request, line)
        result = generation.generate(pipe, request)
        report = key_takes.apply_result(obj, result, scene, exact=not args.no_exact, assign=index == 0,
                                        options=inp.retarget, bone_map=inp.bone_map)
        take = result.takes[0]
        take.name = report.actions[0]
        if take.coverage is not None and take.coverage.verdict == "unknown":
            print(f"warning: line {line.line}: {take.coverage.warning()}", file=sys.stderr)
            note = other_model_note(take.coverage, getattr(pipe, "model_id", ""))
            if note:
                print(f"note: line {line.line}: {note}", file=sys.stderr)
        level, side_text = side_report(take.prompt, getattr(take.badges, "side", None), take.draw,
                                       redrawn_for=take.redrawn_for, verb=getattr(take.badges, "verb", None))
        if level:
            print(f"{level}: line {line.line}: {side_text}", file=sys.stderr)
        for kind, metres, met in take.residuals or []:
            if not met:
                print(f"warning: job {line.line}: the {kind} constraint is off by {metres * 100:.1f} cm (best effort)",
                      file=sys.stderr)
        for seam in seam_lines(take.seams, [prompt for prompt, _ in take.segments or []]):
            print(f"warning: job {line.line}: {seam}", file=sys.stderr)
        record = take.summary()
        if "job" in request.extra:
            record["job"] = request.extra["job"]
        record.update(line=line.line, scene_frames=report.frames, scene_fps=report.fps,
                      time_s=round(time.perf_counter() - t0, 4), key_s=round(report.key_seconds, 4), keys=report.keys,
                      retargeted=report.retargeted, reduction_ratio=round(report.reduction_ratio, 4))
        if inp.bvh_dir is not None:
            bvh_path = inp.bvh_dir / f"{take.name}.bvh"
            inputs.check_outputs({"--bvh-dir file": bvh_path}, overwrite=args.overwrite)
            bvh_takes.append((bvh_path, take))
            record["bvh"] = str(bvh_path)
        records.append(record)
        if index == 0:
            scene.frame_end = scene.frame_start + max(report.frames, 1) - 1
        print(f"[{index + 1}/{len(inp.requests)}] {take.name}: {take.frames} frames ({request.seconds:g} s) in "
              f"{record['time_s']:.2f} s")
    return records, bvh_takes


def _routed_pipe(model_choice, cache, request, line):
    """The pipeline Auto chose for a line, said on stderr when it is not the default."""
    try:
        pipe, said = model_choice.route_request(cache, request)
    except ValueError as exc:  # a Draft asked of a model without one
        raise BatchError(f"line {line.line}: {exc}") from None
    for why in said:
        print(f"note: line {line.line}: {why}", file=sys.stderr)
    return pipe


def write_outputs(args, addon, paths: dict, scene, obj, manifest: dict, bvh_takes: list, t_start: float,
                  export=None) -> None:
    """4. Every output staged beside its target, then all renamed together (none on any failure); ``export``
    stages --export's files and gives the manifest's "export" section."""
    with OutputSet(overwrite=args.overwrite) as outputs:
        outputs.stage(paths["blend"], save_blend_copy, suffix=".blend")
        for bvh_path, take in bvh_takes:
            outputs.stage(bvh_path, lambda tmp, take=take: write_bvh(Path(tmp), take), suffix=".bvh")
        if "preview" in paths:
            preview = importlib.import_module(f"{addon.__name__}.scene.preview")
            t0 = time.perf_counter()
            outputs.stage(paths["preview"], lambda tmp: preview.render_preview(scene, obj, tmp), suffix=".png")
            manifest["preview"] = str(paths["preview"])
            manifest["timing"]["preview_s"] = round(time.perf_counter() - t0, 4)
            print(f"preview {paths['preview']} in {manifest['timing']['preview_s']:.2f} s")
        if export is not None:
            t0 = time.perf_counter()
            manifest["export"] = export(outputs)
            manifest["timing"]["export_s"] = round(time.perf_counter() - t0, 4)
        manifest["timing"]["total_s"] = round(time.perf_counter() - t_start, 4)
        text = json.dumps(manifest, indent=2) + "\n"
        outputs.stage(paths["manifest"], lambda tmp: Path(tmp).write_text(text, encoding="utf-8"))


def shard_record(shard: tuple, manifest: dict, model_dir) -> dict:
    """What a shard's manifest says about itself: which shard, of how many lines, and the model and settings its
    takes were made with (the device aside: a machine's own choice)."""
    (index, count), total, prompts = shard
    settings = {k: v for k, v in manifest["settings"].items() if k not in shards.MACHINE_SETTINGS}
    settings.update(model_id=manifest["model_id"], model=shards.model_fingerprint(model_dir), prompts=prompts,
                    armature=manifest["armature"], bone_map=manifest["rig"]["bone_map"],
                    bvh=any("bvh" in take for take in manifest["takes"]))
    return shards.shard_record((index, count), total, settings)


def merge(args) -> int:
    """--merge: the shards' manifests (and with --bvh-dir their BVH files) joined into one library manifest."""
    out, bvhs = shards.merge_manifests(args.merge, args.out, args.bvh_dir, args.overwrite)
    gathered = f" and {len(bvhs)} BVH file(s) in {args.bvh_dir}" if bvhs else ""
    print(f"wrote {out} ({len(args.merge)} shards){gathered}")
    return EXIT_OK


def _manifest(args, paths, obj, map_source, pipe, model_dir, retarget, scene, records, env, load_s,
              t_start) -> dict:
    return {
        "format": "mld-takes",
        "version": 1,
        "blend": str(paths["blend"]),
        "armature": obj.name,
        "rig": {"blend": args.rig or "", "bvh": args.bvh_rig or "", "bone_map_file": args.bone_map or "",
                "bone_map": map_source},
        "model_id": "auto" if is_auto(model_dir) else getattr(pipe, "model_id", ""),  # Auto: each record's own
        "model_dir": model_dir or "",
        "addon_version": env.ADDON_VERSION_STRING,
        "settings": {
            "seconds": args.seconds,
            "seed": args.seed,
            "steps": pipe.config.draft.num_inference_steps if args.draft else args.steps,  # the steps it ran
            "draft": args.draft,
            "draft_teacher_steps": min(pipe.config.draft.teacher_steps, pipe.config.draft.num_inference_steps - 1)
            if args.draft else 0,  # how many of those were the model's own guided DDIM steps
            "draft_precision": getattr(pipe, "draft_precision", "fp32") if args.draft else "",
            "draft_text_layers": getattr(pipe, "draft_text_layers", None) if args.draft else None,
            "draft_teacher_guidance": pipe.config.draft.teacher_guidance if args.draft else None,
            "draft_timesteps": pipe.config.draft.timesteps if args.draft else None,  # null: spread evenly
            "guidance": args.guidance,
            "device": args.device,
            "exact": not args.no_exact,
            "retarget": retarget.to_dict(),
            "scene_fps": scene.render.fps / (scene.render.fps_base or 1.0),
            "frame_start": scene.frame_start,
        },
        "timing": {"load_s": round(load_s, 4), "total_s": round(time.perf_counter() - t_start, 4)},
        "takes": records,
    }


def main(argv=None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(script_argv(argv))
    except SystemExit as exc:  # argparse already printed the problem
        return EXIT_USAGE if exc.code else EXIT_OK
    addon = _addon_package()
    user_errors = (BatchError, inputs.InputError, FileExistsError)
    try:
        return run(args)
    except user_errors as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # noqa: BLE001 - one readable line; the traceback only with MLD_DEBUG=1
        jobs = importlib.import_module(addon.__name__ + ".worker.jobs")
        if os.environ.get("MLD_DEBUG"):
            import traceback

            traceback.print_exc()
        print(f"error: {jobs.user_message(exc)}", file=sys.stderr)
        return EXIT_FAILED


if __name__ == "__main__":
    code = main()
    sys.stdout.flush()
    sys.stderr.flush()
    if code:
        # Under `blender -b --python` a SystemExit would only end the script; os._exit ends Blender with the code.
        if "bpy" in sys.modules and getattr(sys.modules["bpy"].app, "binary_path", "") and "--" in sys.argv:
            os._exit(code)
        raise SystemExit(code)
