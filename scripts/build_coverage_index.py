"""Build a model folder's prompt-coverage index from its training captions.

    python scripts/build_coverage_index.py --data DIR --model mld_core/weights/default [--split train]

Reads the unique captions of the data folder's split (and each clip's content label from actions.json), encodes
them (side and style words removed) with the model's own text encoder and writes MODEL/coverage_index.npz
(mld_core.condition.coverage). Training writes it too; scripts/export_model.py copies or builds it.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from mld_core.condition import coverage  # noqa: E402
from mld_core.checkpoint import DEFAULT_MODEL_DIR, load_config, save_json  # noqa: E402
from mld_core.data import terms  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, required=True, help="HumanML3D-format folder (texts/, SPLIT.txt, actions.json)")
    ap.add_argument("--model", type=Path, default=DEFAULT_MODEL_DIR, help="model folder to write the index into")
    ap.add_argument("--split", default="train")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args(argv)
    import torch

    from mld_core.models.text_encoder import load_text_encoder

    torch.set_num_threads(args.threads)
    config = load_config(args.model)
    t0 = time.perf_counter()
    index = coverage.build_for_folder(args.data, load_text_encoder(config.text_encoder), args.split)
    path = index.save(args.model / coverage.INDEX_NAME)
    terms.add_to(config, terms.of_folder(args.data))  # the index holds its captions' vectors
    save_json(args.model / "config.json", config.to_dict())
    print(f"wrote {path}: {len(index)} normalised captions, {len(index.known_contents)} contents, "
          f"{path.stat().st_size / 1e6:.2f} MB in {time.perf_counter() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
