"""The benchmark: timing helpers, FLOP counting, the raw-motion baseline (tiny seeded models)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from mld_core.bench import (RawMotionBaseline, _count_flops, _TrainMode, format_bench, mld_flops, raw_flops,
                            run_bench, time_pipeline)
from mld_core.pipeline import MLDPipeline


@pytest.fixture(scope="module")
def pipe(tmp_path_factory):
    from mld_core.testing import tiny_pipeline

    return tiny_pipeline(tmp_path_factory.mktemp("bench") / "model")


def test_flop_counter_counts_linear_and_fused_transformer_layers():
    lin = torch.nn.Linear(16, 8)
    x = torch.randn(5, 16)
    assert _count_flops(lambda: lin(x)) == 2 * 5 * 16 * 8
    layer = torch.nn.TransformerEncoderLayer(32, 4, 64, 0.1, batch_first=True, norm_first=True).eval()
    B, S, d, ff = 2, 10, 32, 64
    expected = 2 * B * S * (4 * d * d + 2 * d * ff) + 2 * 2 * B * S * S * d  # projections + QK^T and AV
    seq = torch.randn(B, S, d)
    with _TrainMode(layer):
        assert _count_flops(lambda: layer(seq)) == expected
    assert not layer.training  # mode restored


def test_time_pipeline_reports_per_prompt_parts(pipe):
    prompts = ["a person walks", "a person runs", "a person waves"]
    r1 = time_pipeline(pipe, prompts, seconds=2.0, batch_size=1, warmup=0)
    r2 = time_pipeline(pipe, prompts, seconds=2.0, batch_size=2, warmup=0)
    for r, bs in ((r1, 1), (r2, 2)):
        assert r["prompts"] == 3 and r["batch_size"] == bs
        assert r["aits_s"] > 0 and r["wall_aits_s"] >= r["aits_s"] * 0.999
        assert r["aits_s"] == pytest.approx(sum(r["parts"].values()))
    with pytest.raises(ValueError):
        time_pipeline(pipe, [], seconds=2.0)


def test_raw_baseline_has_mld_width_and_depth_and_denoises_frames(pipe):
    raw = RawMotionBaseline(pipe, frames=40)
    assert raw.config.transformer == pipe.denoiser.config.transformer
    assert raw.config.latent_tokens == 40 and raw.config.latent_dim == 263
    out = raw.sample(["a person walks", "a person runs"], scheduler="ddim", steps=3)
    assert out["features"].shape == (2, 40, 263) and np.isfinite(out["features"]).all()
    assert out["steps_run"] == out["steps"] == 3
    part = raw.sample(["a person walks"], scheduler="ddpm", steps=1000, max_steps=2)
    assert part["steps_run"] == 2 and part["steps"] == 1000


def test_flops_scale_with_steps_and_sequence(pipe):
    frames = 40
    mld = mld_flops(pipe, "a person walks", frames, steps=10)
    raw = RawMotionBaseline(pipe, frames)
    ddim, ddpm = raw_flops(raw, "a person walks", 50), raw_flops(raw, "a person walks", 1000)
    assert mld["total"] == mld["condition"] + 10 * mld["per_step"] + mld["decode"]
    assert ddpm["per_step"] == ddim["per_step"] > 10 * mld["per_step"]  # 40 frame tokens vs 1 latent token
    assert ddpm["total"] - ddpm["condition"] == 20 * (ddim["total"] - ddim["condition"])
    assert ddim["condition"] == mld["condition"]  # same text encoder and condition path
    # Counting FLOPs runs the modules in train mode: the prepacked inference weights come back afterwards.
    if torch.backends.mkldnn.is_available():
        assert pipe.denoiser.transformer._packed and raw.model.transformer._packed


def test_run_bench_with_raw_baseline_prints_ratios_and_says_untrained(pipe, tmp_path):
    result = run_bench(pipe, baseline="raw", prompts=2, seconds=2.0, ddpm_prompts=1, ddpm_timed_steps=2,
                       progress=False, log=lambda *_: None)
    names = [m["name"] for m in result["methods"]]
    assert names == ["MLD", "raw-motion DDIM", "raw-motion DDPM (MDM-style)"]
    ddpm = result["methods"][2]
    assert ddpm["batch32"]["extrapolated"] and ddpm["batch32"]["steps_timed"] == 2
    assert not ddpm["batch1"]["extrapolated"] and ddpm["batch1"]["prompts"] == 1
    assert result["methods"][0]["ratio_batch1"] == 1.0
    assert ddpm["flops_ratio"] > result["methods"][1]["flops_ratio"] > 1.0
    text = format_bench(result)
    assert "UNTRAINED" in text and "extrapolated per step" in text and "timed on 1 of the 2 prompts" in text
    json.dumps(result)  # JSON-ready


def test_run_bench_in_bf16(tmp_path):
    from mld_core.testing import tiny_model

    result = run_bench(MLDPipeline.from_pretrained(tiny_model(tmp_path / "m"), precision="bf16"), baseline="raw",
                       prompts=1, seconds=2.0, ddpm_prompts=1, ddpm_timed_steps=1, raw_ddim_prompts=1,
                       progress=False, log=lambda *_: None)
    assert result["precision"] == "bf16" and "bf16 denoiser" in format_bench(result)
    assert all(m["flops"]["per_step"] > 0 for m in result["methods"])


def test_bench_cli_rejects_bad_arguments(capsys):
    from mld_core.cli import main

    assert main(["bench", "--prompts", "0"]) == 2
    assert "--prompts" in capsys.readouterr().err
    assert main(["bench", "--model", "/nonexistent/model"]) == 2


def test_busy_note_and_other_load():
    from mld_core.bench import OtherLoad, busy_note

    assert busy_note(0.4, 2) is None
    assert busy_note(None, 2) is None
    note = busy_note(1.5, 2)
    assert note.startswith("WARNING") and "1.5 of the 2 CPUs" in note
    probe = OtherLoad()
    sum(i * i for i in range(200_000))  # our own work does not count as other load
    value = probe.cpus()
    assert value is None or value >= 0.0


def test_aits_times_one_draw_per_prompt():
    """A take that misses its prompt's side is not drawn again while timing (AITS: one sample per prompt)."""
    calls = []

    def pipe(prompts, **kw):
        calls.append(kw)
        return None

    time_pipeline(pipe, ["a person turns left while walking"], warmup=0)
    assert [(c["side_redraws"], c["verb_redraws"]) for c in calls] == [(0, 0)]
