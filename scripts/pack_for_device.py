"""Pack what a training GPU without internet needs, in as few bytes as can travel with a checkout: the data folder's
train and val splits (``data pack``) and the MiniLM text encoder cut to the words of every caption it will train
on (mld_core.models.vocab_subset), so the machine needs neither the dataset archives nor the encoder's package.

    python scripts/pack_for_device.py --data data/bandai_cmu --out device_pack
    #     [--vae runs/vae]   # a VAE to continue or to train denoisers on, in fp16
    # then, on the GPU machine, from the checkout with device_pack/ in it:
    scripts/train_on_device.sh --pack device_pack/data.npz --text-encoder device_pack/minilm --minutes 8

The merged Bandai Namco + CMU folder packs into about 26 MB of data and 23 MB of encoder (2 minutes each on one
core). The encoder folder is for training only: the model it trains names the full encoder in its config.
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

from safetensors.torch import load_file, save_file

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from mld_core.data.dataset import DatasetError, load_split, read_captions  # noqa: E402
from mld_core.data.pack import pack  # noqa: E402
from mld_core.inputs import InputError  # noqa: E402
from mld_core.models.text_encoder import TextEncoderError  # noqa: E402
from mld_core.models.vocab_subset import restrict_vocabulary  # noqa: E402
from mld_core.training.denoiser import text_units, with_reworded_captions  # noqa: E402


def training_texts(data: Path, rewordings: int, seeds: int) -> list[str]:
    """Every caption of the folder, and the rewordings a denoiser run makes of its train captions (seeds 0..n-1,
    turns reworded too), sorted."""
    units = text_units(load_split(data, "train"), 20)
    texts = set()
    for seed in range(seeds):
        for unit_texts in with_reworded_captions(units, rewordings, seed, turns=True):
            texts.update(unit_texts)
    for path in (data / "texts").glob("*.txt"):
        texts.update(c.text for c in read_captions(path))
    return sorted(texts)


def copy_vae(run: Path, out: Path) -> str:
    """A VAE folder's config.json and its weights in fp16, for ``train vae --init`` and ``train denoiser --vae``."""
    for name in ("config.json", "vae.safetensors"):
        if not (run / name).is_file():
            raise InputError(f"--vae {run} has no {name}: name a VAE run or model folder")
    out.mkdir(parents=True, exist_ok=True)
    weights = load_file(str(run / "vae.safetensors"))
    save_file({k: v.half() if v.is_floating_point() else v for k, v in weights.items()}, str(out / "vae.safetensors"))
    shutil.copyfile(run / "config.json", out / "config.json")
    return f"{out} ({(out / 'vae.safetensors').stat().st_size / 1e6:.1f} MB)"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", required=True, type=Path, help="a prepared or merged folder (with new_joints/)")
    p.add_argument("--out", required=True, type=Path, help="the folder to write data.npz and minilm/ into")
    p.add_argument("--splits", default="train,val", help="splits to pack (default train,val)")
    p.add_argument("--rewordings", type=int, default=4, help="rewordings per caption the runs will use (default 4)")
    p.add_argument("--seeds", type=int, default=3, help="run seeds whose rewordings to cover (default 3: 0, 1, 2)")
    p.add_argument("--vae", type=Path, default=None,
                   help="a VAE run or model folder to carry too, in fp16 (OUT/vae: config.json, vae.safetensors)")
    args = p.parse_args(argv)
    made = not args.out.exists()
    try:
        if not (args.data / "new_joints").is_dir():
            raise InputError(f"{args.data} is not a prepared folder with joints (no new_joints); pack the output of "
                             "`data prepare` or `data merge`")
        args.out.mkdir(parents=True, exist_ok=True)
        done = pack(args.data, args.out / "data.npz", tuple(s for s in args.splits.split(",") if s))
        print(f"data: {done['out']} ({done['clips']} clips + {done['mirrored']} mirrored, {done['bytes'] / 1e6:.1f} MB)")
        texts = training_texts(args.data, args.rewordings, args.seeds)
        kept = restrict_vocabulary(texts, args.out / "minilm")
        size = sum(f.stat().st_size for f in (args.out / "minilm").rglob("*") if f.is_file())
        print(f"text encoder: {args.out / 'minilm'} ({kept['tokens']} of {kept['of']} word pieces for "
              f"{len(texts)} captions, {size / 1e6:.1f} MB)")
        if args.vae is not None:
            print(f"VAE: {copy_vae(args.vae, args.out / 'vae')}")
    except (InputError, DatasetError, TextEncoderError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        if made and args.out.is_dir() and not any(args.out.iterdir()):
            args.out.rmdir()
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
