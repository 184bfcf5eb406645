"""A MiniLM folder cut to the vocabulary of some texts gives the full encoder's vectors for those texts."""

from __future__ import annotations

import json

import torch

from mld_core.models import text_encoder as te
from mld_core.models.text_encoder import BertConfig, load_text_encoder
from mld_core.models.tokenizer import builtin_vocab
from mld_core.models.vocab_subset import restrict_vocabulary


def _source(folder):
    from safetensors.torch import save_file

    vocab = builtin_vocab()
    config = BertConfig(vocab_size=len(vocab), hidden_size=16, num_layers=1, num_heads=2, intermediate_size=32)
    gen = torch.Generator().manual_seed(5)
    folder.mkdir()
    save_file({k: torch.randn(s, generator=gen) * 0.1 for k, s in te._expected_shapes(config).items()},
              str(folder / "model.safetensors"))
    (folder / "vocab.txt").write_text("\n".join(vocab) + "\n", encoding="utf-8")
    (folder / "config.json").write_text(json.dumps({
        "model_type": "bert", "hidden_act": "gelu", "vocab_size": len(vocab), "hidden_size": 16,
        "num_hidden_layers": 1, "num_attention_heads": 2, "intermediate_size": 32, "max_position_embeddings": 512,
        "type_vocab_size": 2, "layer_norm_eps": 1e-12}))
    (folder / "sentence_bert_config.json").write_text(json.dumps({"max_seq_length": 64}))
    return folder, len(vocab)


def test_small_vocabulary_gives_the_same_vectors(tmp_path):
    source, full = _source(tmp_path / "full")
    texts = ["a person walks forward", "someone jumps, then turns left"]
    done = restrict_vocabulary(texts, tmp_path / "small", source=source, dtype=torch.float32)
    assert 5 < done["tokens"] < full and done["of"] == full
    assert json.loads((tmp_path / "small" / "config.json").read_text())["vocab_size"] == done["tokens"]
    assert (tmp_path / "small" / "sentence_bert_config.json").is_file()
    big = load_text_encoder({"kind": "minilm", "path": str(source)})
    small = load_text_encoder({"kind": "minilm", "path": str(tmp_path / "small")})
    assert torch.equal(small(texts).tokens, big(texts).tokens)
    assert torch.equal(small(texts).pooled, big(texts).pooled)
    # a word the texts never used is unknown to the small vocabulary
    other = ["a person crawls"]
    assert not torch.equal(small(other).pooled, big(other).pooled)


def test_half_precision_copy_is_close_and_small(tmp_path):
    source, _ = _source(tmp_path / "full")
    texts = ["a person walks forward"]
    restrict_vocabulary(texts, tmp_path / "half", source=source)
    stored = (tmp_path / "half" / "model.safetensors").stat().st_size
    assert stored < (source / "model.safetensors").stat().st_size / 2
    half = load_text_encoder({"kind": "minilm", "path": str(tmp_path / "half"), "dtype": "float32"})
    big = load_text_encoder({"kind": "minilm", "path": str(source)})
    cos = torch.nn.functional.cosine_similarity(half(texts).pooled, big(texts).pooled)
    assert float(cos.min()) > 0.999
