"""Give a text model folder a verb denoiser: an action-conditioned model trained on the same latents.

    python scripts/attach_verb_guide.py TEXT_MODEL ACTION_MODEL --out DIR [--scale 8] [--overwrite]

DIR is TEXT_MODEL with ACTION_MODEL's denoiser as verb_denoiser.safetensors (fp16) and ``verb_guide`` in its
config.json: a Final take whose prompt names one of the action model's labels by a checked verb is guided by that
label too, at ``--scale`` (mld_core.condition.verb_guide). ACTION_MODEL must sample TEXT_MODEL's latents: the same
VAE weights and latent normalisation (train it with ``train denoiser --cond action --vae TEXT_MODEL``); anything else
is refused. Writes into a temporary folder first; refuses to replace DIR unless --overwrite is given.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from mld_core.checkpoint import (VERB_WEIGHTS, CheckpointError, VerbGuideConfig, load_config,  # noqa: E402
                                 load_weights, save_json, save_weights)
from mld_core.data import terms  # noqa: E402
from mld_core.data.verbs import VERBS  # noqa: E402
from mld_core.fileio import build_new_folder  # noqa: E402
from mld_core.inputs import InputError  # noqa: E402
from mld_core.models.denoiser import LatentDenoiser  # noqa: E402
from mld_core.models.vae import MotionVAE  # noqa: E402

VAE_TOLERANCE = 1e-3  # fp16 and fp32 copies of one VAE differ by rounding only
CARD_HEADING = "## Verb guidance"


def same_latents_problem(text_dir: Path, text, action_dir: Path, action) -> str:
    """Why the two folders (and their configs) do not sample the same latents ("" when they do)."""
    if text.denoiser is None or text.denoiser.cond != "text":
        return f"{text_dir} is not a text-conditioned model"
    if action.denoiser is None or action.denoiser.cond != "action":
        return f"{action_dir} is not an action-conditioned model"
    if not any(v in action.actions for v in VERBS):
        return f"{action_dir} has no label that is a checked verb ({', '.join(VERBS)})"
    if text.vae != action.vae or (text.latent_scale, text.latent_mean) != (action.latent_scale, action.latent_mean):
        return "the two models' VAEs or latent normalisations differ"
    vaes = []
    for folder, config in ((text_dir, text), (action_dir, action)):
        vae = MotionVAE(config.vae)
        load_weights(folder / "vae.safetensors", vae)
        vaes.append(vae.state_dict())
    worst = max(float((vaes[0][k].float() - vaes[1][k].float()).abs().max()) for k in vaes[0])
    if worst > VAE_TOLERANCE:
        return (f"the two models' VAE weights differ (by up to {worst:.3g}): train the action model on the text "
                "model's VAE")
    return ""


def attach(config, action_dir: Path, action, out: Path, scale: float) -> None:
    """Write the verb denoiser, the card's section (replacing an earlier one) and ``config`` with its verb_guide into
    ``out``, a copy of the text model's folder."""
    denoiser = LatentDenoiser(action.denoiser)
    load_weights(action_dir / "denoiser.safetensors", denoiser)
    config.verb_guide = VerbGuideConfig(action.denoiser, list(action.actions), scale)
    config.provenance = {**config.provenance, "verb_guide": {"model_id": action.model_id,
                                                             "training": action.provenance.get("denoiser_training")}}
    terms.add_to(config, terms.of_model(action))
    save_weights(out / VERB_WEIGHTS, denoiser, torch.float16)
    card = out / "MODEL_CARD.md"
    if card.is_file():
        text = card.read_text().split(f"\n{CARD_HEADING}\n")[0].rstrip("\n")
        card.write_text(text + "\n\n" + card_section(action, scale))
    save_json(out / "config.json", config.to_dict())


def card_section(action, scale: float) -> str:
    """The card's words on the verb denoiser: what it is, what it guides and how it was trained."""
    verbs = [v for v in VERBS if v in action.actions]
    training = action.provenance.get("denoiser_training") or {}
    steps = action.provenance.get("denoiser_steps")
    return (f"{CARD_HEADING}\n"
            f"`verb_denoiser.safetensors` is {action.model_id}, an action-conditioned denoiser on this model's own "
            f"latents (fp16). A Final take whose prompt names one of its labels by a checked verb ({', '.join(verbs)}) "
            f"is guided by that label as well as by the sentence, at scale {scale:g} "
            f"(`verb_guide` in config.json; mld_core/condition/verb_guide.py). Its training: "
            f"{steps if steps is not None else 'unknown'} steps, `{json.dumps(training, sort_keys=True)}`.\n")


def out_problem(out: Path, overwrite: bool, models: tuple) -> str:
    """Why ``out`` cannot be written ("" when it can): an existing folder without ``overwrite``, not a folder, or
    one of the two models or a folder inside one."""
    if out.exists() and not out.is_dir():
        return f"{out} exists and is not a folder"
    if out.exists() and not overwrite:
        return f"{out} exists (pass --overwrite to replace it)"
    target = out.resolve()
    if any(target == m.resolve() or target.is_relative_to(m.resolve()) for m in models):
        return "--out must be a new folder, not one of the two models or inside one"
    return ""


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("text_model", type=Path)
    ap.add_argument("action_model", type=Path)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--scale", type=float, default=8.0, help="the verb denoiser's guidance scale (default 8)")
    ap.add_argument("--overwrite", action="store_true")
    args = ap.parse_args(argv)
    problem = out_problem(args.out, args.overwrite, (args.text_model, args.action_model))
    if not 0 <= args.scale < 100:
        problem = f"--scale must be in [0, 100), got {args.scale:g}"
    try:
        if not problem:
            text, action = load_config(args.text_model), load_config(args.action_model)
            problem = same_latents_problem(args.text_model, text, args.action_model, action)
        if problem:
            print(f"error: {problem}", file=sys.stderr)
            return 2

        def write(folder: Path) -> None:
            shutil.copytree(args.text_model, folder, dirs_exist_ok=True)
            attach(text, args.action_model, action, folder, args.scale)

        if not args.out.exists():
            build_new_folder(args.out, write)  # of two runs racing for one new folder, one wins, the other keeps nothing
        else:  # --overwrite: built beside the old folder, which is removed only once the new one is complete
            tmp = Path(tempfile.mkdtemp(prefix=".verb_guide_", dir=args.out.parent))
            try:
                write(tmp)
                shutil.rmtree(args.out)
                tmp.rename(args.out)
            finally:
                shutil.rmtree(tmp, ignore_errors=True)
    except (CheckpointError, InputError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {args.out}: {args.text_model} guided by {args.action_model}'s verbs at {args.scale:g}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
