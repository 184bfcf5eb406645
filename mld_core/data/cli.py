"""``python -m mld_core data prepare <dataset> SRC --out DIR``, ``data merge A B ... --out C`` and ``data summary DIR``:
build HumanML3D-format training folders and say what they hold."""

from __future__ import annotations

import time
from pathlib import Path


def register(groups) -> None:
    prepare = groups["data"].add_parser("prepare", help="write a HumanML3D-format folder from a motion dataset")
    datasets = prepare.add_subparsers(dest="dataset", metavar="DATASET")
    p = datasets.add_parser(
        "bandai",
        help="the Bandai Namco Research motion datasets (CC BY-NC 4.0)",
        description="Read the Bandai Namco BVH clips (the released .tar.xz, streamed, or its extracted "
        "folder) and write features, joints, generated captions, splits, Mean/Std and actions.json "
        "to --out. Rerunning replaces a previous output of this command; any other non-empty "
        "folder is refused.",
    )
    p.add_argument("src", metavar="SRC", help="bandai-namco-research-motiondataset.tar.xz or its extracted folder")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (new, empty, or a previous output)")
    p.add_argument("--workers", type=int, default=2, help="worker processes (default 2; 1 = in-process)")
    p.add_argument("--no-mirror", action="store_true", help="do not add the mirrored M<id> copies")
    p.add_argument("--limit", type=int, default=None, help="only the first N clips (quick trials)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_run_bandai)
    b = datasets.add_parser(
        "bvh",
        help="any folder of BVH files (any skeleton, units, up axis, frame rate) with captions",
        description="Map every BVH under SRC onto the 22 joints (bone-map detection as in the add-on), detect units "
        "and up axis, trim leading T-pose frames, cut each caption's span into segments of at most 9.8 s, mirror, "
        "and write features, captions, splits (by file) and Mean/Std to --out. Captions: --captions CSV/TSV "
        "(file, caption[, start_s, end_s]; several rows per file allowed), else a .txt beside each BVH (one caption "
        "per line), else --caption-template. Files that cannot be used are listed with their reason in "
        "prepare_report.json.",
    )
    b.add_argument("src", metavar="SRC", help="a folder of .bvh files (searched recursively)")
    b.add_argument("--out", required=True, metavar="DIR", help="output folder (new, empty, or a previous output)")
    b.add_argument("--captions", type=Path, default=None, metavar="FILE", help="CSV/TSV: file, caption[, start_s, end_s]")
    b.add_argument("--caption-template", default=None, metavar="TEXT",
                   help="fallback caption, e.g. 'a person {name}' ({name}: the file name in words, {folder})")
    b.add_argument("--bone-map", type=Path, default=None, metavar="FILE", help="a bone map JSON (as the add-on saves)")
    b.add_argument("--units", default=None, help="m, cm, mm, in, ft or metres per unit (default: detect)")
    b.add_argument("--up", choices=("y", "z"), default=None, help="the files' up axis (default: detect)")
    b.add_argument("--no-mirror", action="store_true", help="do not add the mirrored M<id> copies")
    b.add_argument("--licence", default="its owner's", metavar="TEXT",
                   help="the library's terms, recorded in terms.json and so in every model trained on it")
    b.add_argument("--commercial-use", choices=("yes", "no"), default=None,
                   help="whether those terms allow weights trained on it in commercial products (default: not said)")
    b.set_defaults(func=_run_bvh)
    c = datasets.add_parser(
        "cmu-joints",
        help="the whole CMU motion capture database as joint positions (cmu-mocap-joints.tar.xz)",
        description="Read the CMU joints archive (streamed) or its extracted folder: map the 20 joints onto the 22, "
        "convert to metres, drop leading frames that jump impossibly, resample to 20 fps, cut trials into windows of "
        "at most 9.8 s captioned from KIT sentences and CMU's descriptions (long trials that list several actions: "
        "per window, the actions a physical detector finds), check each window's plausibility, mirror, split by "
        "subject, and write a HumanML3D-format folder. Skipped trials and rejected windows are listed with their "
        "reason in prepare_report.json; uncaptioned windows in uncaptioned.txt.",
    )
    c.add_argument("src", metavar="SRC", help="cmu-mocap-joints.tar.xz or its extracted folder")
    c.add_argument("--out", required=True, metavar="DIR", help="output folder (new, empty, or a previous output)")
    c.add_argument("--no-mirror", action="store_true", help="do not add the mirrored M<id> copies")
    c.add_argument("--limit", type=int, default=None, help="only the first N trials (quick trials)")
    c.add_argument("--captions", choices=("all", "cmu"), default="all",
                   help="all: CMU's descriptions and KIT Motion-Language sentences (default); cmu: CMU's "
                   "descriptions only, for weights whose use CMU's terms alone govern")
    c.add_argument("--quiet", action="store_true", help="no progress bar")
    c.set_defaults(func=_run_cmu_joints)
    prepare.set_defaults(func=lambda args: _missing_dataset(prepare))
    su = groups["data"].add_parser("summary", help="hours per source, checked verb and split of a prepared folder",
                                   description="Print the hours (mirrored copies included) per source, per split and "
                                   "per checked verb (the captions that ask for it) of a HumanML3D-format folder.")
    su.add_argument("folder", type=Path, metavar="DIR", help="a prepared or merged folder")
    su.set_defaults(func=_run_summary)
    m = groups["data"].add_parser("merge", help="several HumanML3D-format folders as one (splits kept, one Mean/Std)",
                                  description="Merge HumanML3D-format folders: splits kept, ids prefixed with their "
                                  "folder's name where two folders share one, Mean/Std over the merged train split, "
                                  "provenance.json per clip.")
    m.add_argument("sources", nargs="+", type=Path, metavar="DIR", help="two or more prepared folders")
    m.add_argument("--out", required=True, type=Path, metavar="DIR", help="a new (or empty) folder")
    m.set_defaults(func=_run_merge)
    pk = groups["data"].add_parser("pack", help="one small file of a prepared folder, to carry to another machine",
                                   description="Write the joints (to a millimetre), captions, split lists and Mean/Std "
                                   "of a prepared folder's splits to one file (mirrored copies are made again when "
                                   "unpacking). `data unpack` rebuilds a folder to train on from it.")
    pk.add_argument("folder", type=Path, metavar="DIR", help="a prepared or merged folder (with new_joints/)")
    pk.add_argument("--out", required=True, type=Path, metavar="FILE", help="the pack file to write (.npz)")
    pk.add_argument("--splits", default="train,val", help="comma-separated splits to pack (default train,val)")
    pk.set_defaults(func=_run_pack)
    up = groups["data"].add_parser("unpack", help="a folder to train on, from a `data pack` file",
                                   description="Rebuild a HumanML3D-format folder from a pack: features computed from "
                                   "the packed joints, mirrored copies made again.")
    up.add_argument("pack", type=Path, metavar="FILE", help="a file written by `data pack`")
    up.add_argument("--out", required=True, type=Path, metavar="DIR", help="a new (or empty) folder")
    up.add_argument("--workers", type=int, default=2, help="processes computing features (default 2)")
    up.set_defaults(func=_run_unpack)


def _run_summary(args) -> int:
    from ..cli import UsageError
    from .summary import folder_summary, summary_table

    if not (args.folder / "train.txt").is_file() or not (args.folder / "new_joint_vecs").is_dir():
        raise UsageError(f"{args.folder} is not a HumanML3D-format folder (no train.txt or new_joint_vecs/)")
    try:
        print(summary_table(folder_summary(args.folder)), end="")
    except (OSError, ValueError, UnicodeDecodeError) as exc:
        raise UsageError(f"cannot read {args.folder}: {str(exc).splitlines()[0]}") from None
    return 0


def _run_pack(args) -> int:
    from ..cli import UsageError
    from ..inputs import InputError
    from .pack import pack

    try:
        done = pack(args.folder, args.out, tuple(s.strip() for s in args.splits.split(",") if s.strip()))
    except InputError as exc:
        raise UsageError(str(exc)) from None
    print(f"wrote {done['out']}: {done['clips']} clips (+{done['mirrored']} mirrored, made again when unpacking), "
          f"{done['bytes'] / 1e6:.1f} MB")
    return 0


def _run_unpack(args) -> int:
    from ..cli import UsageError
    from ..inputs import InputError, int_in_range
    from .pack import unpack

    try:
        done = unpack(args.pack, args.out, int_in_range(args.workers, "--workers", 1, 256))
    except InputError as exc:
        raise UsageError(str(exc)) from None
    print(f"wrote {done['out']}: {done['clips']} clips + {done['mirrored']} mirrored, {done['frames']} feature frames")
    return 0


def _run_merge(args) -> int:
    from ..cli import UsageError
    from ..inputs import InputError
    from .merge import merge

    try:
        summary = merge(args.sources, args.out)
    except InputError as exc:
        raise UsageError(str(exc)) from None
    s = summary["splits"]
    print(f"wrote {summary['out']}: train {s['train']}, val {s['val']}, test {s['test']} clips from "
          f"{len(summary['sources'])} folders")
    return 0


def _run_bvh(args) -> int:
    from ..cli import UsageError
    from .bandai import PrepareError
    from .bvh_library import LibraryOptions, prepare_bvh

    start = time.perf_counter()
    options = LibraryOptions(captions=args.captions, caption_template=args.caption_template, bone_map=args.bone_map,
                             units=args.units, up=args.up, mirror=not args.no_mirror, licence=args.licence,
                             commercial=None if args.commercial_use is None else args.commercial_use == "yes")
    try:
        s = prepare_bvh(args.src, args.out, options)
    except PrepareError as exc:
        raise UsageError(str(exc)) from None
    sp = s["splits"]
    print(f"wrote {s['out']}: {s['mapped']} of {s['files']} files mapped ({len(s['skipped'])} skipped, reasons in "
          f"prepare_report.json), {s['clips']} segments + {s['mirrored']} mirrored, {s['frames']} frames; train "
          f"{sp['train']}, val {sp['val']}, test {sp['test']}; {time.perf_counter() - start:.1f} s")
    return 0


def _run_cmu_joints(args) -> int:
    from ..cli import UsageError
    from .bandai import PrepareError
    from .cmu_joints import prepare_cmu_joints

    if args.limit is not None and args.limit < 1:
        raise UsageError("--limit must be at least 1")
    start = time.perf_counter()
    try:
        s = prepare_cmu_joints(args.src, args.out, mirror=not args.no_mirror, limit=args.limit,
                               progress=not args.quiet, captions=args.captions)
    except PrepareError as exc:
        raise UsageError(str(exc)) from None
    sp = s["splits"]
    print(f"wrote {s['out']}: {s['prepared']} of {s['trials']} trials ({len(s['skipped'])} skipped, reasons in "
          f"prepare_report.json), {s['windows']} windows + {s['mirrored']} mirrored, {s['hours']} h; "
          f"{s['uncaptioned']} uncaptioned; train {sp['train']}, val {sp['val']}, test {sp['test']}; "
          f"{time.perf_counter() - start:.1f} s")
    return 0


def _missing_dataset(parser) -> int:
    parser.print_help()
    return 2


def _run_bandai(args) -> int:
    from ..cli import UsageError
    from .bandai import PrepareError, prepare_bandai

    if args.workers < 1:
        raise UsageError("--workers must be at least 1")
    if args.limit is not None and args.limit < 1:
        raise UsageError("--limit must be at least 1")
    start = time.perf_counter()
    try:
        summary = prepare_bandai(args.src, args.out, workers=args.workers, mirror=not args.no_mirror,
                                 progress=not args.quiet, limit=args.limit)
    except PrepareError as exc:
        raise UsageError(str(exc)) from None
    took = time.perf_counter() - start
    s = summary["splits"]
    print(
        f"wrote {summary['out']}: {summary['clips']} clips + {summary['mirrored']} mirrored, "
        f"{summary['frames']} frames at 20 fps; train {s['train']}, val {s['val']}, test {s['test']}; "
        f"{len(summary['skipped'])} skipped; {took:.1f} s"
    )
    return 0
