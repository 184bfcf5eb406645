"""Export a trained run folder as a shippable model folder: fp16 safetensors, config.json and MODEL_CARD.md.

    python scripts/export_model.py RUN_DIR [--out mld_core/weights/default] [--notes notes.md] [--model-id ID]
        [--data DIR] [--vae-decoder VAE_RUN]

A VAE-only run (``train vae``, no denoiser) exports as a VAE folder: its config.json, the VAE in fp16 and a card
listing every sitting it has had (``provenance.vae_lineage``), a folder to continue from (``train vae --init FOLDER``)
or to train denoisers on (``train denoiser --vae FOLDER``); it does not generate.

--vae-decoder takes the decoder side of VAE_RUN's VAE, trained with only its decoder modules from RUN_DIR's VAE
(``train vae --init RUN_DIR --config '{"train_modules": ["latent_positions", "decoder", "head"]}'``): the encoder,
and so the denoiser's latents, stay RUN_DIR's; a VAE with another encoder is refused.

A model folder's Draft (draft.safetensors, draft_text.safetensors) is exported with it; a config naming a Draft
whose draft.safetensors is missing is refused.

The run's prompt-coverage index (coverage_index.npz, written by training) is copied; a run without one gets an
index built from ``--data``'s train captions (mld_core.condition.coverage), else the folder ships without one and
reports coverage as unavailable.

Refuses to replace an existing folder unless --overwrite is given; writes into a temporary folder first.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from mld_core.checkpoint import (DEFAULT_MODEL_DIR, DRAFT_TEXT_WEIGHTS, VERB_WEIGHTS, CheckpointError,  # noqa: E402
                                 load_config, load_weights, save_model)
from mld_core.data import terms  # noqa: E402
from mld_core.fileio import make_parents  # noqa: E402
from mld_core.inputs import InputError, check_output_folder, parse_json  # noqa: E402
from mld_core.models.denoiser import LatentDenoiser  # noqa: E402
from mld_core.models.vae import MotionVAE, take_decoder  # noqa: E402
from mld_core.training.common import recorded_training_data  # noqa: E402
from mld_core.training.draft import DRAFT_WEIGHTS, install_draft  # noqa: E402

CARD = """# {model_id}

Motion Latent Diffusion (Chen et al., CVPR 2023) {cond}-to-motion model, {origin} on {hardware}.

| | |
|---|---|
| data | {data} |
| licence | {licence} |
| text encoder | all-MiniLM-L6-v2 (frozen; Apache-2.0), pooled vector + {pool} attention-pooled token features |
| VAE | latent {n} x {d}; encoder/decoder {vae_layers} layers each, d {d}, 4 heads, ff 1024, long skips: {skip} |
| denoiser | {den_layers} layers, d {den_d}, condition: {reads}, target-length conditioning: {length} |
| sampling | DDIM {steps} steps, classifier-free guidance {guidance} |
| lengths | {min_s:g} s to {max_s:g} s at 20 fps |
| weights | fp16 safetensors, {size_mb:.1f} MB |

## Training
{training}

## Measurements
{metrics}
{limits}"""

BANDAI_DATA = "Bandai Namco Research Motion dataset (3,076 BVH clips + left/right mirrors, 20 fps, HumanML3D 263-d features)"
BANDAI_LIMITS = """
## Limits
Trained on 24 content classes of one dataset (walking, running, turning, waving and raising hands, a few gestures
and dances, bows, punches, kicks, with 7-15 styles such as elderly, tired, happy, feminine). Prompts far from those
contents fall back to the nearest ones; the folder's `coverage_index.npz` (the training captions' sentence vectors)
lets the pipeline say so before generating (`MLDPipeline.coverage`, docs/quality.md). Not for commercial use.
"""


VAE_CARD = """# {model_id}

The VAE of a Motion Latent Diffusion model (Chen et al., CVPR 2023) alone, with no denoiser: a folder to continue
training from (`python -m mld_core train vae --init FOLDER`) or to train denoisers on (`python -m mld_core train
denoiser --vae FOLDER`). It does not generate from text by itself.

| | |
|---|---|
| data | `{data}` (its sittings' data folders are listed below) |
| licence | {licence} |
| VAE | latent {n} x {d}; encoder/decoder {layers} layers each, d {dim}, long skips: {skip}; KL weight {kl:g} |
| steps | {own} in its own sitting, {steps} over the {sittings} sittings below |
| weights | fp16 safetensors, {size_mb:.1f} MB |

## Training, oldest sitting first
{training}

## Measurements
{metrics}
"""


def condition_kind(denoiser) -> str:
    """The card's name for what the denoiser reads: "text", "action", or "text + verb hint (jump, ...)"."""
    if denoiser.verb_hints:
        return f"{denoiser.cond} + verb hint ({', '.join(denoiser.verb_hints)})"
    return denoiser.cond


def card_origin(config) -> str:
    """How the card's first line says the model came about: from scratch, or fine-tuned from the weights its
    Training section names."""
    training = config.provenance.get("denoiser_training") or {}
    return "fine-tuned from the weights named under Training" if training.get("init") else "trained from scratch"


ATTRIBUTIONS = {
    terms.BANDAI["name"]: 'attribution: Bandai Namco Research Inc., Kobayashi et al. 2023, "Motion Capture Dataset '
                          'for Practical Use of AI-based Motion Editing and Stylization"',
    terms.CMU["name"]: 'CMU: "The data used in this project was obtained from mocap.cs.cmu.edu. The database was '
                       'created with funding from NSF EIA-0196217."',
    terms.KIT["name"]: 'KIT-ML: Plappert, Mandery and Asfour, "The KIT Motion-Language Dataset", Big Data 4(4), 2016',
}


def card_licence(config) -> str:
    """The card's licence row: whose terms the weights carry (config ``training_data``) and the attributions."""
    sources = terms.of_model(config)
    credits = [ATTRIBUTIONS[e["name"]] for e in sources if e["name"] in ATTRIBUTIONS]
    return "; ".join([terms.licence_summary(sources), *credits])


def card_limits(notes: str) -> str:
    """The Bandai model's Limits section, unless the notes hold their own."""
    return "" if "## Limits" in notes else BANDAI_LIMITS


def vae_sittings(config) -> list[dict]:
    """Every sitting of a VAE folder's training, oldest first: its lineage, then the run's own."""
    prov = config.provenance
    own = {"model_id": config.model_id, "steps": prov.get("vae_steps"), "training": prov.get("vae_training")}
    return [*prov.get("vae_lineage", []), own]


def sitting_line(sitting: dict) -> str:
    """One sitting as a card line: where it started, its steps, and its settings."""
    training = dict(sitting.get("training") or {})
    start = training.pop("init", None) or "nothing (from scratch)"
    return (f"- {sitting.get('model_id')}: {sitting.get('steps')} steps from {start}; "
            f"`{json.dumps(training, sort_keys=True)}`")


def vae_card(config, vae, notes: str) -> str:
    sittings = vae_sittings(config)
    steps = sum(int(s.get("steps") or 0) for s in sittings)
    enc = config.vae.encoder
    return VAE_CARD.format(model_id=config.model_id, data=(config.provenance.get("vae_training") or {}).get("data"),
                           licence=card_licence(config),
                           n=config.vae.latent_tokens, d=config.vae.latent_dim, layers=enc.layers, dim=enc.dim,
                           skip=enc.skip, kl=config.vae.kl_weight, steps=f"{steps:,}", sittings=len(sittings),
                           own=f"{int(sittings[-1].get('steps') or 0):,}",
                           size_mb=sum(p.numel() for p in vae.state_dict().values()) * 2 / 1e6,
                           training="\n".join(sitting_line(s) for s in sittings), metrics=notes)


def write_coverage_index(run: Path, folder: Path, config, data: Path | None) -> None:
    from mld_core.condition import coverage

    if (run / coverage.INDEX_NAME).is_file():
        shutil.copyfile(run / coverage.INDEX_NAME, folder / coverage.INDEX_NAME)
    elif data is not None and config.denoiser.cond == "text":
        from mld_core.models.text_encoder import load_text_encoder

        coverage.build_for_folder(data, load_text_encoder(config.text_encoder)).save(folder / coverage.INDEX_NAME)
    else:
        print(f"note: {run} has no {coverage.INDEX_NAME}; pass --data DIR to build one (coverage: unavailable)",
              file=sys.stderr)


def swap_decoder(config, vae: MotionVAE, vae_run: Path) -> None:
    """``vae`` takes the decoder side of ``vae_run``'s VAE (same encoder, same feature normalisation); the
    provenance records that run's training."""
    donor_config = load_config(vae_run)
    if not all(a.shape == b.shape and np.allclose(a, b, rtol=1e-6, atol=1e-9)  # atol: a zero mean read back as 3e-18
               for a, b in zip(donor_config.mean_std, config.mean_std)):
        raise ValueError("its feature normalisation (mean/std) is another data folder's")
    donor = MotionVAE(donor_config.vae)
    load_weights(vae_run / "vae.safetensors", donor)
    take_decoder(vae, donor)
    prov = donor_config.provenance
    config.provenance["vae_decoder_training"] = prov.get("vae_training")
    terms.add_to(config, terms.of_model(donor_config))
    for key in ("vae_val_mpjpe_mm", "vae_val_global_mpjpe_mm", "vae_steps"):
        config.provenance[f"{key}_decoder"] = prov.get(key)


MODEL_FILES = {"config.json", "vae.safetensors", "denoiser.safetensors", "MODEL_CARD.md", "coverage_index.npz"}


def out_problem(out: Path, overwrite: bool) -> str:
    """Why ``out`` cannot take the exported model ('' when it can): a file, a folder that is not empty without
    --overwrite, or one holding anything an export does not write (that is never deleted)."""
    if out.exists() and not out.is_dir():
        return f"{out} is a file, not a model folder"
    entries = sorted(p.name for p in out.iterdir()) if out.is_dir() else []
    if entries and not overwrite:
        return f"{out} exists; pass --overwrite"
    foreign = [name for name in entries if name not in MODEL_FILES]
    if foreign:
        return f"{out} holds {', '.join(foreign[:3])}, which an export does not write; move it out first"
    return ""


def read_notes(path: Path | None) -> str:
    """The --notes markdown for the card's measurements (UTF-8), or the default line."""
    if path is None:
        return "See the README's results table."
    try:
        return path.read_bytes().decode("utf-8")
    except FileNotFoundError:
        raise InputError(f"--notes {path}: file not found") from None
    except OSError as exc:
        raise InputError(f"cannot read --notes {path}: {exc.strerror or exc}") from None
    except UnicodeDecodeError as exc:
        raise InputError(f"--notes {path}: not UTF-8 text ({exc.reason} at byte {exc.start}); save it as UTF-8") \
            from None


def check_data(data: Path | None) -> None:
    """--data, when given: a HumanML3D-format folder with train captions (the coverage index is built from them)."""
    if data is None:
        return
    from mld_core.condition.coverage import training_captions

    if not data.is_dir():
        raise InputError(f"--data {data}: no such folder")
    try:
        captions, _ = training_captions(data, "train")
    except (OSError, ValueError) as exc:
        raise InputError(f"--data {data}: {str(exc).splitlines()[0]}") from None
    if not captions:
        raise InputError(f"--data {data}: no train captions to build the coverage index from")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--out", type=Path, default=DEFAULT_MODEL_DIR)
    ap.add_argument("--model-id", default=None)
    ap.add_argument("--notes", type=Path, default=None, help="markdown with measurements for the card")
    ap.add_argument("--overwrite", action="store_true")
    ap.add_argument("--data", type=Path, default=None, help="data folder to build the coverage index from "
                    "(when the run has none)")
    ap.add_argument("--vae-decoder", type=Path, default=None, help="a VAE run whose decoder side replaces the run's "
                    "(its encoder must be the run's)")
    ap.add_argument("--hardware", default="two CPU cores", help="what the card says it was trained on")
    ap.add_argument("--data-description", default=BANDAI_DATA, metavar="TEXT",
                    help="the card's data row (default: the Bandai Namco dataset's); notes with a '## Limits' "
                         "section replace the Bandai model's Limits too")
    ap.add_argument("--text-encoder", default=None, metavar="JSON",
                    help="the text encoder the exported config names (default: the run's), e.g. "
                         "'{\"kind\": \"minilm\"}' for a run trained with a copy cut to its captions "
                         "(mld_core.models.vocab_subset)")
    args = ap.parse_args(argv)
    try:
        config = load_config(args.run)
    except CheckpointError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    vae_only = config.denoiser is None
    problem = out_problem(args.out, args.overwrite)
    try:
        if problem:
            raise InputError(problem)
        if vae_only and (args.vae_decoder or args.data or args.text_encoder):
            raise InputError(f"{args.run} is a VAE alone: --vae-decoder, --data and --text-encoder apply to a model "
                             "with a denoiser")
        check_output_folder(args.out, "--out", staged_beside=True)
        metrics = read_notes(args.notes)
        check_data(args.data)
        if args.text_encoder is not None:
            spec = parse_json(args.text_encoder, "--text-encoder")
            if not isinstance(spec, dict) or not isinstance(spec.get("kind"), str):
                raise InputError("--text-encoder must be a JSON object with a \"kind\", e.g. {\"kind\": \"minilm\"}")
            config.text_encoder = spec
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    vae, den = MotionVAE(config.vae), (None if vae_only else LatentDenoiser(config.denoiser))
    try:
        load_weights(args.run / "vae.safetensors", vae)
        if den is not None:
            load_weights(args.run / "denoiser.safetensors", den)
    except CheckpointError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.vae_decoder is not None:
        try:
            swap_decoder(config, vae, args.vae_decoder)
        except (CheckpointError, ValueError) as exc:
            print(f"error: --vae-decoder {args.vae_decoder}: {exc}", file=sys.stderr)
            return 2
    if config.draft is not None and not (args.run / DRAFT_WEIGHTS).is_file():
        print(f"error: {args.run} names a Draft in config.json but has no {DRAFT_WEIGHTS}", file=sys.stderr)
        return 2
    if config.verb_guide is not None and not (args.run / VERB_WEIGHTS).is_file():
        print(f"error: {args.run} names a verb denoiser in config.json but has no {VERB_WEIGHTS}", file=sys.stderr)
        return 2
    if args.model_id:
        config.model_id = args.model_id
    if config.training_data is None:  # a run begun before the records: what its train_config.json names
        config.training_data = recorded_training_data(args.run)
    if not vae_only and args.data is not None and not (args.run / "coverage_index.npz").is_file():
        terms.add_to(config, terms.of_folder(args.data))  # the coverage index is built from its captions
    if vae_only:
        return write_folder(args.out, config, vae, None, vae_card(config, vae, metrics), args.run)
    prov = config.provenance
    training = "\n".join(f"- {k}: `{json.dumps(v)}`" for k, v in prov.items())
    size = sum(p.numel() for m in (vae, den) for p in m.state_dict().values()) * 2 / 1e6
    card = CARD.format(model_id=config.model_id, pool=config.denoiser.text_pool_tokens, n=config.vae.latent_tokens,
                       d=config.vae.latent_dim, vae_layers=config.vae.encoder.layers, skip=config.vae.encoder.skip,
                       den_layers=config.denoiser.transformer.layers, den_d=config.denoiser.transformer.dim,
                       cond=config.denoiser.cond, reads=condition_kind(config.denoiser),
                       length=config.denoiser.length_conditioning,
                       steps=config.num_inference_steps, guidance=config.guidance_scale,
                       min_s=config.min_frames / config.fps, max_s=config.max_frames / config.fps, size_mb=size,
                       training=training, metrics=metrics, hardware=args.hardware, origin=card_origin(config),
                       data=args.data_description, limits=card_limits(metrics), licence=card_licence(config))
    return write_folder(args.out, config, vae, den, card, args.run, args.data)


def write_folder(out: Path, config, vae, den, card: str, run: Path, data: Path | None = None) -> int:
    """The exported folder, written beside ``out`` and then renamed into place: a failed export leaves nothing."""
    made = make_parents(out.parent)
    tmp = Path(tempfile.mkdtemp(dir=out.parent, prefix=f".{out.name}."))
    try:
        save_model(tmp, config, vae, den, dtype=torch.float16, card=card)
        if den is not None:
            write_coverage_index(run, tmp, config, data)
        if den is not None and config.verb_guide is not None:  # a verb denoiser samples the same latents too
            shutil.copyfile(run / VERB_WEIGHTS, tmp / VERB_WEIGHTS)
        if den is not None and config.draft is not None:  # the Draft samples the same latents: it serves a
            if (run / DRAFT_TEXT_WEIGHTS).is_file():        # swapped-in decoder too
                shutil.copyfile(run / DRAFT_TEXT_WEIGHTS, tmp / DRAFT_TEXT_WEIGHTS)
            install_draft(run, tmp)
        if out.exists():
            shutil.rmtree(out)
        tmp.chmod(0o755)
        tmp.rename(out)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp)
        if not out.exists():  # a failed export leaves none of the folders it made
            for folder in reversed(made):
                folder.rmdir()
    total = sum(f.stat().st_size for f in out.iterdir()) / 1e6
    print(f"wrote {out} ({total:.1f} MB)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
