"""BERT uncased WordPiece tokenizer in plain Python (no ``transformers``/``tokenizers`` at run time).

It reproduces the ids of Hugging Face's fast ``BertTokenizerFast`` as configured for all-MiniLM-L6-v2
(``do_lower_case=True``, ``strip_accents`` following lowercase, Chinese characters split), which is what
sentence-transformers feeds the model:

1. Special tokens written literally in the text (``[CLS]``, ``[SEP]``, ``[PAD]``, ``[UNK]``, ``[MASK]``, case-sensitive)
   are kept as single tokens, as the HF tokenizers do for their added tokens.
2. Normalisation (per piece of text between such tokens): drop NUL, U+FFFD and control, format and private-use
   characters (Unicode Cc, Cf, Co; tab, newline and carriage return count as white space; unassigned code points are
   kept and end up as [UNK]); every white space character becomes a space; CJK ideographs get spaces around them;
   NFD and removal of non-spacing marks (accents: "café" -> "cafe"); lowercase character by character (so a final
   capital sigma lowers to "σ", as in Rust).
3. Pre-tokenisation: split on white space; every punctuation character (ASCII punctuation, including symbols such as
   ``$ + < = > ^ ` | ~``, or Unicode category P*) is a token of its own.
4. WordPiece: greedy longest-match-first with the ``##`` continuation prefix; a word longer than 100 characters, or one
   with a part that matches nothing, becomes a single ``[UNK]``.
5. ``[CLS] ... [SEP]``, truncating the word pieces so that the total (specials included) is at most ``max_length``.

``WordPieceTokenizer.batch`` pads a batch to its longest sequence with ``[PAD]`` and returns the attention mask.
This module needs only numpy.

Checked against the fast tokenizer (tokenizers 0.23, Python 3.11) on every code point placed inside a word: the two
differ only on about 560 code points that were assigned or re-categorised in recent Unicode versions (the Rust crates
and Python's ``unicodedata`` ship different Unicode tables: e.g. combining marks and punctuation added after Unicode 10,
which HF keeps inside words and we strip or split off). On 3,000 random mixed-script texts the ids are identical.
"""

from __future__ import annotations

import os
import unicodedata
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

__all__ = ["WordPieceTokenizer", "SPECIAL_TOKENS", "builtin_vocab"]

SPECIAL_TOKENS = ("[PAD]", "[UNK]", "[CLS]", "[SEP]", "[MASK]")
MAX_INPUT_CHARS_PER_WORD = 100

_CJK_RANGES = (
    (0x4E00, 0x9FFF),
    (0x3400, 0x4DBF),
    (0x20000, 0x2A6DF),
    (0x2A700, 0x2B73F),
    (0x2B740, 0x2B81F),
    (0x2B920, 0x2CEAF),  # sic: the HF fast tokenizer starts this block at 0x2B920 (the slow one at 0x2B820)
    (0xF900, 0xFAFF),
    (0x2F800, 0x2FA1F),
)


def _is_cjk(cp: int) -> bool:
    return any(lo <= cp <= hi for lo, hi in _CJK_RANGES)


# The Unicode White_Space property (Rust's char::is_whitespace, which the HF fast tokenizer uses).
_WHITESPACE = frozenset(
    "\t\n\x0b\x0c\r \x85\xa0\u1680\u2000\u2001\u2002\u2003\u2004\u2005\u2006\u2007\u2008\u2009\u200a"
    "\u2028\u2029\u202f\u205f\u3000"
)


def _is_whitespace(ch: str) -> bool:
    return ch in _WHITESPACE


def _is_control(ch: str) -> bool:
    # Control (Cc), format (Cf) and private-use (Co) characters are dropped; unassigned code points (Cn) are kept
    # (they end up as [UNK]), as the HF fast tokenizer does.
    if ch in "\t\n\r":
        return False
    return unicodedata.category(ch) in ("Cc", "Cf", "Co", "Cs")


def _is_punctuation(ch: str) -> bool:
    cp = ord(ch)
    if 33 <= cp <= 47 or 58 <= cp <= 64 or 91 <= cp <= 96 or 123 <= cp <= 126:
        return True
    return unicodedata.category(ch).startswith("P")


def normalize(text: str) -> str:
    """BertNormalizer (clean text, split CJK, strip accents, lowercase), as the fast tokenizer does it."""
    out = []
    for ch in text:
        cp = ord(ch)
        if cp == 0 or cp == 0xFFFD or _is_control(ch):
            continue
        if _is_whitespace(ch):
            out.append(" ")
        elif _is_cjk(cp):
            out.append(f" {ch} ")
        else:
            out.append(ch)
    text = unicodedata.normalize("NFD", "".join(out))
    text = "".join(ch for ch in text if unicodedata.category(ch) != "Mn")
    return "".join(ch.lower() for ch in text)  # per character, like Rust's char::to_lowercase


def pre_tokenize(text: str) -> list[str]:
    """Split normalised text on white space and isolate every punctuation character."""
    words: list[str] = []
    current: list[str] = []
    for ch in text:
        if _is_whitespace(ch):
            if current:
                words.append("".join(current))
                current = []
        elif _is_punctuation(ch):
            if current:
                words.append("".join(current))
                current = []
            words.append(ch)
        else:
            current.append(ch)
    if current:
        words.append("".join(current))
    return words


def builtin_vocab() -> list[str]:
    """A small vocabulary that tokenizes any ASCII text (for tiny random test encoders without the weights package):
    the specials, printable ASCII characters, their ``##`` continuations and a few motion words."""
    words = list(SPECIAL_TOKENS)
    chars = [chr(c) for c in range(33, 127) if not chr(c).isupper()]
    words += chars + ["##" + c for c in chars if c.isalnum()]
    words += (
        "a the person walks walk forward backward backwards left right hand hands arm arms leg legs waves wave "
        "runs run jumps jump turns turn around raises raise kicks kick sits down up bows and with then slowly "
        "quickly circle steps step"
    ).split()
    seen: set[str] = set()
    return [w for w in words if not (w in seen or seen.add(w))]


class WordPieceTokenizer:
    """BERT uncased WordPiece tokenizer. ``vocab``: a vocab.txt path (one token per line, id = line number) or a
    list of tokens. ``max_length``: the most tokens per text, [CLS] and [SEP] included."""

    def __init__(self, vocab: str | os.PathLike | Sequence[str], max_length: int = 512):
        if isinstance(vocab, (str, os.PathLike)):
            path = Path(vocab)
            try:
                tokens = path.read_text(encoding="utf-8").split("\n")
            except OSError as e:
                raise FileNotFoundError(f"cannot read the tokenizer vocabulary {path}: {e}") from e
            except UnicodeDecodeError as e:
                raise ValueError(f"the tokenizer vocabulary {path} is not UTF-8 text (corrupt?): {e}") from e
            if tokens and tokens[-1] == "":
                tokens.pop()
            tokens = [t.rstrip("\r") for t in tokens]
            source = str(path)
        else:
            tokens = list(vocab)
            source = "the given vocabulary"
        self.vocab: dict[str, int] = {}
        for i, tok in enumerate(tokens):
            self.vocab.setdefault(tok, i)
        missing = [t for t in SPECIAL_TOKENS if t not in self.vocab]
        if missing:
            raise ValueError(f"{source} lacks the special tokens {missing} (not a BERT vocab.txt?)")
        if max_length < 2:
            raise ValueError(f"max_length must be at least 2 ([CLS] and [SEP]), got {max_length}")
        self.max_length = int(max_length)
        self.pad_id = self.vocab["[PAD]"]
        self.unk_id = self.vocab["[UNK]"]
        self.cls_id = self.vocab["[CLS]"]
        self.sep_id = self.vocab["[SEP]"]
        self._special_ids = {t: self.vocab[t] for t in SPECIAL_TOKENS}
        self._cache: dict[str, list[int]] = {}

    def __len__(self) -> int:
        return len(self.vocab)

    # -- pieces ------------------------------------------------------------------------------------------------
    def _wordpiece(self, word: str) -> list[int]:
        cached = self._cache.get(word)
        if cached is not None:
            return cached
        if len(word) > MAX_INPUT_CHARS_PER_WORD:
            ids = [self.unk_id]
        else:
            ids = []
            start, n = 0, len(word)
            while start < n:
                end = n
                found = None
                while start < end:
                    piece = word[start:end] if start == 0 else "##" + word[start:end]
                    found = self.vocab.get(piece)
                    if found is not None:
                        break
                    end -= 1
                if found is None:
                    ids = [self.unk_id]
                    break
                ids.append(found)
                start = end
        if len(self._cache) < 50_000:
            self._cache[word] = ids
        return ids

    def _split_specials(self, text: str) -> list[tuple[str, bool]]:
        """Cut the raw text at literal special tokens: [(piece, is_special)]."""
        parts: list[tuple[str, bool]] = []
        i = start = 0
        while i < len(text):
            if text[i] == "[":
                for tok in SPECIAL_TOKENS:
                    if text.startswith(tok, i):
                        if start < i:
                            parts.append((text[start:i], False))
                        parts.append((tok, True))
                        i += len(tok)
                        start = i
                        break
                else:
                    i += 1
            else:
                i += 1
        if start < len(text):
            parts.append((text[start:], False))
        return parts

    def tokenize_ids(self, text: str) -> list[int]:
        """Word-piece ids of one text, without [CLS]/[SEP] and without truncation."""
        if not isinstance(text, str):
            raise TypeError(f"expected a str, got {type(text).__name__}")
        ids: list[int] = []
        for piece, special in self._split_specials(text):
            if special:
                ids.append(self._special_ids[piece])
                continue
            for word in pre_tokenize(normalize(piece)):
                ids.extend(self._wordpiece(word))
        return ids

    def tokenize(self, text: str) -> list[str]:
        """Word-piece strings of one text (for inspection), without [CLS]/[SEP]."""
        inv = self.inverse_vocab
        return [inv[i] for i in self.tokenize_ids(text)]

    @property
    def inverse_vocab(self) -> dict[int, str]:
        inv = getattr(self, "_inv", None)
        if inv is None:
            inv = self._inv = {i: t for t, i in self.vocab.items()}
        return inv

    def encode(self, text: str, max_length: int | None = None) -> list[int]:
        """[CLS] pieces [SEP], pieces truncated so that the whole is at most ``max_length`` (default: the
        tokenizer's) ids."""
        limit = self.max_length if max_length is None else int(max_length)
        if limit < 2:
            raise ValueError(f"max_length must be at least 2, got {limit}")
        ids = self.tokenize_ids(text)[: limit - 2]
        return [self.cls_id, *ids, self.sep_id]

    def batch(self, texts: Iterable[str], max_length: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Encode and right-pad a batch: ``ids`` (B, L) int64 with [PAD], ``mask`` (B, L) bool, True = real token;
        L = the longest encoded text of the batch."""
        seqs = [self.encode(t, max_length) for t in texts]
        length = max((len(s) for s in seqs), default=0)
        ids = np.full((len(seqs), length), self.pad_id, dtype=np.int64)
        mask = np.zeros((len(seqs), length), dtype=bool)
        for i, s in enumerate(seqs):
            ids[i, : len(s)] = s
            mask[i, : len(s)] = True
        return ids, mask
