"""Average the denoisers of model folders that share one VAE into a new model folder (a weight average).

    python research/average_denoisers.py A B [C ...] --out DIR [--weights 0.5,0.5] [--model-id ID]
        [--only text_proj,token_proj,...]

Fine-tunes that start from one denoiser can be averaged weight by weight; the average often keeps part of each
fine-tune's gain (docs/evaluation.md). The first folder gives everything but the denoiser: the VAE, the
config (repairs, stepping, sampling), the coverage index and any Draft (which stays the first folder's student).
The denoiser is the weighted mean of all the folders' denoisers, computed in float32 and stored in the first
folder's precision; config.json's provenance records the folders and weights under ``denoiser_average``.
``--only`` averages just the named top-level modules (e.g. the text-reading ``text_proj,token_proj,token_pool,
null_condition``) and keeps the first folder's weights for the rest; with ``--weights 0,1`` it transplants them.

Refuses folders whose VAE weights or denoiser configs differ, and an existing --out; writes into a temporary folder
first, so a refusal or an error leaves nothing behind.
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import sys
import tempfile
from pathlib import Path

import torch
from safetensors.torch import load_file, save_file

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from mld_core.checkpoint import CheckpointError, load_config, save_json  # noqa: E402
from mld_core.data import terms  # noqa: E402


def check_compatible(folders: list[Path]) -> None:
    """Raise CheckpointError unless every folder has the first one's denoiser config and VAE weights."""
    first = load_config(folders[0])
    vae = load_file(folders[0] / "vae.safetensors")
    for folder in folders[1:]:
        if load_config(folder).denoiser != first.denoiser:
            raise CheckpointError(f"{folder}'s denoiser config differs from {folders[0]}'s")
        other = load_file(folder / "vae.safetensors")
        if other.keys() != vae.keys() or any(not torch.equal(other[k], vae[k]) for k in vae):
            raise CheckpointError(f"{folder}'s VAE differs from {folders[0]}'s: their latents do not match")


def average_state(states: list[dict], weights: list[float], only: tuple[str, ...] = ()) -> dict:
    """Weighted mean of state dicts with the same keys and shapes, in the first one's dtypes; with ``only``, of the
    weights under those top-level modules alone (the rest: the first state's)."""
    out = {}
    for key, ref in states[0].items():
        if only and key.split(".")[0] not in only:
            out[key] = ref
            continue
        total = sum(w * s[key].float() for s, w in zip(states, weights))
        out[key] = total.to(ref.dtype).contiguous()
    return out


def average_denoisers(folders: list[Path], out: Path, weights: list[float], model_id: str | None = None,
                      only: tuple[str, ...] = ()) -> Path:
    """Write the averaged model folder at ``out`` (see the module docstring); returns ``out``."""
    if out.exists():
        raise CheckpointError(f"{out} exists; choose a new folder")
    if not out.parent.is_dir():
        raise CheckpointError(f"{out.parent} is not a folder; create it first")
    check_compatible(folders)
    states = [load_file(folder / "denoiser.safetensors") for folder in folders]
    modules = {key.split(".")[0] for key in states[0]}
    if set(only) - modules:
        raise CheckpointError(f"no module {', '.join(sorted(set(only) - modules))} in the denoiser; it has "
                              f"{', '.join(sorted(modules))}")
    tmp = Path(tempfile.mkdtemp(prefix=".average-", dir=out.parent))
    try:
        staged = tmp / "model"
        shutil.copytree(folders[0], staged)
        save_file(average_state(states, weights, only), staged / "denoiser.safetensors")
        cfg = json.loads((staged / "config.json").read_text())
        ids = [json.loads((f / "config.json").read_text()).get("model_id") or f.name for f in folders]
        record = {"models": ids, "weights": weights, **({"modules": list(only)} if only else {})}
        cfg.setdefault("provenance", {})["denoiser_average"] = record
        cfg["training_data"] = terms.union(*(terms.of_model(load_config(f)) for f in folders))
        if model_id:
            cfg["model_id"] = model_id
        save_json(staged / "config.json", cfg)
        load_config(staged)
        staged.rename(out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return out


def parse_weights(text: str | None, n: int) -> list[float]:
    """'0.5,0.5' -> [0.5, 0.5]; None -> equal weights. They must be n non-negative numbers summing to 1."""
    if text is None:
        return [1.0 / n] * n
    weights = [float(w) for w in text.split(",")]
    if len(weights) != n or not all(math.isfinite(w) and w >= 0 for w in weights) or abs(sum(weights) - 1.0) > 1e-6:
        raise ValueError(f"--weights needs {n} non-negative numbers summing to 1, got {text!r}")
    return weights


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folders", type=Path, nargs="+", help="model folders, the first one gives all but the denoiser")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--weights", default=None, help="comma-separated, one per folder, summing to 1 (default equal)")
    parser.add_argument("--model-id", default=None)
    parser.add_argument("--only", default="", help="comma-separated top-level denoiser modules to average (default all)")
    args = parser.parse_args(argv)
    if len(args.folders) < 2:
        parser.error("give at least two model folders")
    try:
        weights = parse_weights(args.weights, len(args.folders))
        only = tuple(m.strip() for m in args.only.split(",") if m.strip())
        average_denoisers(args.folders, args.out, weights, args.model_id, only)
    except (ValueError, CheckpointError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {args.out}: the denoisers of {', '.join(map(str, args.folders))} averaged with weights {weights}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
