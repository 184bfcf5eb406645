"""Draft mode: the consistency scheduler, the Draft denoiser in the pipeline, the text cache and the faster decode."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from mld_core.checkpoint import CheckpointError
from mld_core.models.denoiser import DenoiserConfig, LatentDenoiser
from mld_core.models.transformer import TransformerConfig, packs_in
from mld_core.inputs import InputError
from mld_core.schedulers import DDIMScheduler, LCMScheduler
from mld_core.testing import tiny_pipeline


@pytest.fixture(scope="module")
def pipe(tmp_path_factory):
    return tiny_pipeline(tmp_path_factory.mktemp("draft") / "m", draft=True)


# -- the scheduler ----------------------------------------------------------------------------------------------
def test_lcm_timesteps_come_from_the_50_step_grid():
    s = LCMScheduler()
    assert s.skip == 20 and s.grid[0] == 1 and s.grid[-1] == 981
    s.set_timesteps(1)
    assert s.timesteps.tolist() == [981]
    s.set_timesteps(4)
    assert s.timesteps.tolist() == [981, 741, 481, 241]
    for n in range(1, 51):  # every step a timestep of its own (rounding once repeated one at 50)
        s.set_timesteps(n)
        assert len(set(s.timesteps.tolist())) == n and (s.timesteps.diff() < 0).all()
    with pytest.raises(ValueError, match="1..50"):
        s.set_timesteps(51)


def test_consistency_function_is_the_identity_at_t0_and_the_x0_estimate_at_large_t():
    s = LCMScheduler()
    x, eps = torch.randn(3, 2, 4), torch.randn(3, 2, 4)
    assert torch.allclose(s.denoised(eps, torch.zeros(3, dtype=torch.long), x), x, atol=1e-6)
    t = torch.tensor([981, 981, 981])
    a = s.alphas_cumprod[981]
    x0 = (x - (1 - a).sqrt() * eps) / a.sqrt()
    assert torch.allclose(s.denoised(eps, t, x), x0, atol=1e-5)


def test_teacher_step_is_a_ddim_step_on_the_50_step_grid():
    lcm, ddim = LCMScheduler(), DDIMScheduler()
    ddim.set_timesteps(50)
    x, eps = torch.randn(1, 2, 4), torch.randn(1, 2, 4)
    expected, _ = ddim.step(eps, 481, x)
    assert torch.allclose(lcm.teacher_step(eps, torch.tensor([481]), x), expected, atol=1e-6)


def test_multistep_renoises_between_steps_and_returns_the_estimate_at_the_last():
    s = LCMScheduler()
    s.set_timesteps(2)
    x, eps, noise = torch.randn(1, 2, 4), torch.randn(1, 2, 4), torch.randn(1, 2, 4)
    nxt, est = s.step(eps, 981, x, noise)
    a = s.alphas_cumprod[481]
    assert torch.allclose(nxt, a.sqrt() * est + (1 - a).sqrt() * noise, atol=1e-6)
    last, est2 = s.step(eps, 481, nxt)
    assert torch.equal(last, est2)
    with pytest.raises(ValueError, match="noise"):
        s.step(eps, 981, x)


def test_ddim_step_between_any_two_timesteps_matches_the_ddim_scheduler():
    lcm, ddim = LCMScheduler(), DDIMScheduler()
    ddim.set_timesteps(50)
    x, eps = torch.randn(2, 2, 4), torch.randn(2, 2, 4)
    assert torch.allclose(lcm.ddim_step(eps, 481, 461, x), ddim.step(eps, 481, x)[0], atol=1e-6)
    a = lcm.alphas_cumprod[481]
    clean = (x - (1 - a).sqrt() * eps) / a.sqrt()  # to the clean sample
    assert torch.allclose(lcm.ddim_step(eps, 481, -1, x), clean, atol=1e-5)
    per_row = lcm.ddim_step(eps, torch.tensor([481, 241]), torch.tensor([-1, 1]), x)
    assert torch.allclose(per_row[0], clean[0], atol=1e-5) and torch.allclose(per_row[1], lcm.ddim_step(
        eps[1:], 241, 1, x[1:])[0], atol=1e-6)
    lcm.set_timesteps(2)
    assert [lcm.next_timestep(981), lcm.next_timestep(481)] == [481, -1]


def test_renoising_with_the_implied_noise_continues_the_same_sample():
    x, eps, noise = torch.randn(1, 2, 4), torch.randn(1, 2, 4), torch.randn(1, 2, 4)
    steps = {}
    for gamma in (0.0, 0.5, 1.0):
        s = LCMScheduler(fresh_noise=gamma)
        s.set_timesteps(2)
        steps[gamma], est = s.step(eps, 981, x, noise if gamma else None)
    a_t, a_next = s.alphas_cumprod[981], s.alphas_cumprod[481]
    implied = (x - a_t.sqrt() * est) / (1 - a_t).sqrt()  # the noise that takes the estimate back to x at t = 981
    assert torch.allclose(a_t.sqrt() * est + (1 - a_t).sqrt() * implied, x, atol=1e-5)
    assert torch.allclose(steps[0.0], a_next.sqrt() * est + (1 - a_next).sqrt() * implied, atol=1e-5)
    assert torch.allclose(steps[1.0], a_next.sqrt() * est + (1 - a_next).sqrt() * noise, atol=1e-5)
    half = a_next.sqrt() * est + (1 - a_next).sqrt() * (0.5 ** 0.5 * implied + 0.5 ** 0.5 * noise)
    assert torch.allclose(steps[0.5], half, atol=1e-5)
    assert not LCMScheduler(fresh_noise=0.0).needs_noise and LCMScheduler().needs_noise
    for bad in (-0.1, 1.5):
        with pytest.raises(ValueError, match="fresh_noise"):
            LCMScheduler(fresh_noise=bad)


# -- the Draft denoiser ------------------------------------------------------------------------------------------
def test_a_fresh_student_with_a_guidance_input_predicts_what_its_teacher_does():
    block = TransformerConfig(dim=32, heads=2, ff_dim=64, layers=1, dropout=0.0)
    cfg = DenoiserConfig(latent_tokens=1, latent_dim=32, cond="none", transformer=block)
    torch.manual_seed(0)
    teacher = LatentDenoiser(cfg).eval()
    student = LatentDenoiser(DenoiserConfig(**{**cfg.to_dict(), "guidance_input": True})).eval()
    student.load_state_dict(teacher.state_dict(), strict=False)
    z, t, L = torch.randn(2, 1, 32), torch.tensor([5, 900]), torch.tensor([40, 60])
    cond = teacher.null_tokens(2)
    with torch.no_grad():
        assert torch.allclose(student(z, t, cond, L, guidance=torch.tensor([2.0, 7.0])), teacher(z, t, cond, L),
                              atol=1e-6)
    with pytest.raises(ValueError, match="guidance"):
        student(z, t, cond, L)


def test_draft_rows_equal_single_runs_and_guidance_steers(pipe):
    both = pipe(["a person walks", "a person waves"], seconds=[1.5, 2.0], seed=[4, 9], draft=True)
    one = pipe(["a person waves"], seconds=2.0, seed=9, draft=True)
    assert np.allclose(both.joints[1, :40], one.joints[0], atol=1e-5)
    assert pipe.config.guidance_scale != 3.0
    other = pipe(["a person waves"], seconds=2.0, seed=9, draft=True, guidance_scale=3.0)
    assert not np.allclose(other.joints, one.joints, atol=1e-4)
    with pytest.raises(InputError, match="outside the 3-5 this model's Draft was distilled for"):
        pipe(["a person waves"], seconds=2.0, draft=True, guidance_scale=8.0)  # a scale it never learnt
    again = pipe(["a person waves"], seconds=2.0, seed=9, draft=True)
    assert np.array_equal(again.joints, one.joints)


def test_draft_steps_default_to_the_config_and_are_bounded_by_the_grid(pipe):
    calls = []
    pipe("a person walks", 1.5, draft=True, callback=lambda k, n: calls.append(n))
    assert calls == [2, 2]  # config draft.num_inference_steps
    calls.clear()
    pipe("a person walks", 1.5, draft=True, num_inference_steps=1, callback=lambda k, n: calls.append(n))
    assert calls == [1]
    with pytest.raises(ValueError, match="num_inference_steps"):
        pipe("a person walks", 1.5, draft=True, num_inference_steps=51)


def test_draft_differs_from_final_and_a_model_without_a_draft_says_so(pipe, tmp_path):
    final = pipe("a person walks", 1.5, seed=1)
    draft = pipe("a person walks", 1.5, seed=1, draft=True)
    assert not np.allclose(final.joints, draft.joints)
    plain = tiny_pipeline(tmp_path / "plain")
    assert plain.draft_denoiser is None
    with pytest.raises(CheckpointError, match="no Draft denoiser"):
        plain("a person walks", 1.5, draft=True)


def test_a_bad_draft_section_is_a_checkpoint_error(tmp_path):
    import json

    from mld_core.checkpoint import load_config
    from mld_core.testing import tiny_model

    folder = tiny_model(tmp_path / "m", draft=True)
    data = json.loads((folder / "config.json").read_text())
    data["draft"]["num_inference_steps"] = 0
    (folder / "config.json").write_text(json.dumps(data))
    with pytest.raises(CheckpointError, match="draft.num_inference_steps"):
        load_config(folder)
    for key, value, words in (("guidance_min", 9.0, "at most draft.guidance_max"), ("original_steps", 2.5,
                              "draft.original_steps"), ("sigma_data", float("nan"), "draft.sigma_data"),
                              ("fresh_noise", 1.5, "draft.fresh_noise"), ("fresh_noise", "all", "draft.fresh_noise"),
                              ("text_layers", 0, "draft.text_layers"), ("text_layers", 2.5, "draft.text_layers"),
                              ("teacher_guidance", 0.5, "draft.teacher_guidance"),
                              ("teacher_guidance", "high", "draft.teacher_guidance"),
                              ("teacher_verb_guide", "yes", "draft.teacher_verb_guide"),
                              ("teacher_verb_guide", 1, "draft.teacher_verb_guide"),
                              ("timesteps", [981], "draft.timesteps"), ("timesteps", [481, 981], "draft.timesteps"),
                              ("timesteps", [981, 480], "draft.timesteps"), ("timesteps", "late", "draft.timesteps"),
                              ("timesteps", [981, True], "draft.timesteps"), ("timesteps", [[981], 601],
                              "draft.timesteps"), ("timesteps", [981.0, 601], "draft.timesteps")):
        (folder / "config.json").write_text(json.dumps({**data, "draft": {**data["draft"], "num_inference_steps": 2,
                                                                           key: value}}))
        with pytest.raises(CheckpointError, match=words):
            load_config(folder)
    (folder / "draft.safetensors").unlink()
    data["draft"]["num_inference_steps"] = 2
    (folder / "config.json").write_text(json.dumps(data))
    from mld_core.pipeline import MLDPipeline

    with pytest.warns(UserWarning, match="Draft mode is unavailable"):
        pipe = MLDPipeline.from_pretrained(folder)  # a broken Draft costs only the Draft
    assert pipe("a person walks", 1.5, num_inference_steps=2).joints.shape[1] == 30
    with pytest.raises(CheckpointError, match="Draft mode is unavailable: missing weights file.*draft.safetensors"):
        pipe("a person walks", 1.5, draft=True)


# -- the text cache and the faster decode ----------------------------------------------------------------------
def test_each_prompt_is_encoded_once_and_the_cache_is_bounded(pipe, monkeypatch):
    seen = []
    encoder = pipe.text_encoder
    real = type(encoder).forward

    def counting(self, texts):
        seen.extend(texts)
        return real(self, texts)

    pipe.clear_text_cache()
    first = pipe(["walks forward", "turns left", "walks forward"], 1.5, seed=0)
    monkeypatch.setattr(type(encoder), "forward", counting)
    again = pipe(["turns left", "walks forward"], 1.5, seed=[0, 0])
    assert seen == [] and np.allclose(again.joints[1], first.joints[0], atol=1e-5)
    pipe(["sits down"], 1.5)
    assert seen == ["a person sits down"]  # encoded as a sentence (commands_as_sentences), kept as typed
    monkeypatch.setattr(pipe._text_cache, "SIZE", 2)
    pipe(["jumps"], 1.5)
    assert list(pipe._text_cache) == ["sits down", "jumps"]


def test_packed_decoding_equals_the_masked_module_path(pipe):
    z = torch.randn(2, 1, 32)
    with torch.inference_mode():
        batch = pipe.vae.decode(z, torch.tensor([30, 22]))  # padded: the module path
        single = pipe.vae.decode(z[1:], torch.tensor([22]))  # no padding: the packed functional path
    assert torch.allclose(batch[1, :22], single[0], atol=1e-5)
    assert (batch[1, 22:] == 0).all()


def test_the_decoders_fixed_queries_are_self_attended_once_per_length(pipe):
    vae = pipe.vae
    z = torch.randn(3, 1, 32)
    memory = z + vae.latent_positions
    queries = vae.frame_positions[:25].expand(3, -1, -1)
    with torch.inference_mode():
        vae.decoder._fixed_queries.clear()
        plain = vae.decoder(queries, memory=memory)
        cached = vae.decoder(queries, memory=memory, fixed_queries=25)
        again = vae.decode(z, torch.tensor([25, 25, 25]))
        assert set(vae.decoder._fixed_queries) == {25}
        vae.decode(z[:1], torch.tensor([20]))
        head = vae.head(cached)
    assert torch.allclose(cached, plain, atol=1e-6)
    assert torch.equal(again, head)
    assert set(vae.decoder._fixed_queries) == {20, 25}
    vae.decoder.pack_for_cpu_inference()  # new weights or precision: computed again
    assert not vae.decoder._fixed_queries
    with torch.inference_mode():
        vae.decode(z[:1], torch.tensor([25]))
    vae.load_state_dict({k: v.clone() for k, v in vae.state_dict().items()})  # loaded weights: stale too
    assert not vae.decoder._fixed_queries and not vae.decoder._packed
    vae.decoder.pack_for_cpu_inference()


def test_packed_text_encoder_equals_the_plain_one():
    from mld_core.models.text_encoder import MiniLMEncoder

    plain = MiniLMEncoder.random(seed=3, vocab_path="builtin")
    packed = MiniLMEncoder.random(seed=3, vocab_path="builtin")
    if not packed.pack_for_cpu_inference():
        pytest.skip("this torch build has no oneDNN prepacked linear ops")
    texts = ["a person walks forward", "waves"]
    a, b = plain(texts), packed(texts)
    assert torch.allclose(a.tokens, b.tokens, atol=1e-5) and torch.allclose(a.pooled, b.pooled, atol=1e-6)


def test_generate_draft_on_the_command_line(tmp_path, capsys):
    from mld_core.cli import main
    from mld_core.testing import tiny_model
    from test_reliability import refused

    model = tiny_model(tmp_path / "draft_model", draft=True)
    assert main(["generate", "a person walks", "--model", str(model), "--draft", "--seconds", "2",
                 "--out", str(tmp_path / "d.npz")]) == 0
    assert np.load(tmp_path / "d.npz")["joints"].shape[:2] == (1, 40)
    plain = tiny_model(tmp_path / "plain_model")
    refused(["generate", "a person walks", "--model", plain, "--draft", "--out", tmp_path / "p.npz"], tmp_path, capsys,
            "has no Draft denoiser")
    refused(["generate", "a person walks", "--model", model, "--draft", "--guidance", "9", "--out",
             tmp_path / "g.npz"], tmp_path, capsys, "outside the 3-5")
    assert main(["generate", "a person walks", "--model", str(model), "--draft", "--guidance", "0", "--seconds", "2",
                 "--out", str(tmp_path / "g0.npz")]) == 0  # 0 is the model's default, as --help says
    (model / "draft.safetensors").write_bytes(b"not safetensors")  # a broken Draft: Final still works
    with pytest.warns(UserWarning, match="Draft mode is unavailable"):
        refused(["generate", "a person walks", "--model", model, "--draft", "--out", tmp_path / "b.npz"], tmp_path,
                capsys, "corrupt weights file")


def test_a_draft_request_is_checked_against_the_model_before_any_work(tmp_path):
    from mld_core.inputs import validate_request
    from mld_core.testing import tiny_model

    with_draft, plain = tiny_model(tmp_path / "d", draft=True), tiny_model(tmp_path / "p")
    assert validate_request("a walk", draft=True, model_dir=with_draft, guidance=4.5).draft
    with pytest.raises(InputError, match="no Draft denoiser"):  # the panel and the batch say so before a job runs
        validate_request("a walk", draft=True, model_dir=plain)
    with pytest.raises(InputError, match="outside the 3-5"):
        validate_request("a walk", draft=True, model_dir=with_draft, guidance=7.5)
    assert not validate_request("a walk", model_dir=plain, guidance=7.5).draft  # Final: any scale


def test_a_draft_has_its_own_default_guidance(tmp_path):
    import json

    from mld_core.pipeline import MLDPipeline
    from mld_core.testing import tiny_model

    folder = tiny_model(tmp_path / "m", draft=True)
    data = json.loads((folder / "config.json").read_text())
    data["draft"]["guidance_scale"] = 3.0
    (folder / "config.json").write_text(json.dumps(data))
    pipe = MLDPipeline.from_pretrained(folder)
    assert pipe.default_guidance(draft=True) == 3.0 and pipe.default_guidance() == pipe.config.guidance_scale != 3.0
    own = pipe("a person walks", 1.5, seed=2, draft=True)
    assert np.array_equal(own.joints, pipe("a person walks", 1.5, seed=2, draft=True, guidance_scale=3.0).joints)
    assert not np.allclose(own.joints, pipe("a person walks", 1.5, seed=2, draft=True,
                                            guidance_scale=pipe.config.guidance_scale).joints, atol=1e-4)
    data["draft"]["guidance_scale"] = 9.0  # outside what it learnt
    (folder / "config.json").write_text(json.dumps(data))
    with pytest.raises(CheckpointError, match="draft.guidance_scale"):
        MLDPipeline.from_pretrained(folder)


def _tiny_model_with_a_teacher_step(folder):
    """A tiny model whose Draft samples as the bundled one does: a consistency step, then a teacher step."""
    import json

    from mld_core.testing import tiny_model

    folder = tiny_model(folder, draft=True)
    data = json.loads((folder / "config.json").read_text())
    data["draft"].update(teacher_steps=1, fresh_noise=0.0)
    (folder / "config.json").write_text(json.dumps(data))
    return folder, data


def test_bad_draft_timesteps_say_what_the_grid_is():
    from mld_core.schedulers import LCMScheduler, SchedulerConfig

    one_point = LCMScheduler(SchedulerConfig(), original_steps=1)
    with pytest.raises(ValueError, match=r"1 descending points of its grid 1; got \[5\]"):
        one_point.checked_timesteps([5], 1)
    with pytest.raises(ValueError, match=r"2 descending points of its grid 1, 21, \.\.\., 981"):
        LCMScheduler(SchedulerConfig()).checked_timesteps([981, 601.5], 2)
    assert LCMScheduler(SchedulerConfig()).checked_timesteps((981, np.int64(601)), 2).tolist() == [981, 601]


def test_the_drafts_configured_timesteps_set_where_its_teacher_step_takes_over(tmp_path):
    from mld_core.pipeline import MLDPipeline

    folder, _ = _tiny_model_with_a_teacher_step(tmp_path / "m")
    pipe = MLDPipeline.from_pretrained(folder, draft_precision="fp32")
    even = pipe("a person walks", 1.5, seed=5, draft=True, repair=False)
    assert pipe.draft_scheduler.timesteps.tolist() == [981, 481]  # null: spread evenly over the 50-point grid
    pipe.config.draft.timesteps = [981, 581]
    later = pipe("a person walks", 1.5, seed=5, draft=True, repair=False)
    assert pipe.draft_scheduler.timesteps.tolist() == [981, 581]
    s, L = pipe.default_guidance(draft=True), torch.tensor([30])  # by hand: re-noised to 581, then the teacher
    z = torch.randn(1, 1, 32, generator=torch.Generator().manual_seed(5))
    with torch.no_grad():
        cond, null = pipe._condition(["a person walks"], None, "text", pipe.draft_denoiser)
        lcm = pipe.draft_scheduler
        est = lcm.denoised(pipe.draft_denoiser(z, torch.tensor([981]), cond, L, guidance=torch.tensor([s])),
                           torch.tensor(981), z)
        a981, a581 = lcm.alphas_cumprod[981], lcm.alphas_cumprod[581]
        z = a581.sqrt() * est + (1 - a581).sqrt() * (z - a981.sqrt() * est) / (1 - a981).sqrt()
        t_cond, t_null = pipe._condition(["a person walks"], None, "text", pipe.denoiser)
        e_null, e_cond = pipe.denoiser(torch.cat([z, z]), torch.tensor([581, 581]), torch.cat([t_null, t_cond]),
                                       torch.cat([L, L])).chunk(2)
        by_hand = pipe.latents_to_features(lcm.ddim_step(e_null + s * (e_cond - e_null), 581, -1, z), L)
    assert np.allclose(later.features, by_hand, atol=1e-5) and not np.allclose(later.features, even.features, atol=1e-4)
    pipe("a person walks", 1.5, seed=5, draft=True, num_inference_steps=3, repair=False)
    assert len(pipe.draft_scheduler.timesteps) == 3  # other step counts spread evenly


def test_teacher_steps_finish_a_draft_with_guided_ddim_steps_of_the_model_denoiser(tmp_path):
    import json

    from mld_core.pipeline import MLDPipeline

    folder, data = _tiny_model_with_a_teacher_step(tmp_path / "m")

    pipe = MLDPipeline.from_pretrained(folder, draft_precision="fp32")
    calls = []
    out = pipe("a person walks", 1.5, seed=5, draft=True, repair=False, callback=lambda k, n: calls.append((k, n)))
    assert calls == [(1, 2), (2, 2)]  # the teacher's step is one of the Draft's two
    # the same by hand: a consistency step at 981, re-noised with its implied noise to 481, a guided DDIM step to 0
    s, L = pipe.default_guidance(draft=True), torch.tensor([30])
    z = torch.randn(1, 1, 32, generator=torch.Generator().manual_seed(5))
    with torch.no_grad():
        cond, _ = pipe._condition(["a person walks"], None, "text", pipe.draft_denoiser)
        eps = pipe.draft_denoiser(z, torch.tensor([981]), cond, L, guidance=torch.tensor([s]))
        lcm = pipe.draft_scheduler
        est = lcm.denoised(eps, torch.tensor(981), z)
        a981, a481 = lcm.alphas_cumprod[981], lcm.alphas_cumprod[481]
        z = a481.sqrt() * est + (1 - a481).sqrt() * (z - a981.sqrt() * est) / (1 - a981).sqrt()
        t_cond, t_null = pipe._condition(["a person walks"], None, "text", pipe.denoiser)
        e_null, e_cond = pipe.denoiser(torch.cat([z, z]), torch.tensor([481, 481]), torch.cat([t_null, t_cond]),
                                       torch.cat([L, L])).chunk(2)
        z0 = lcm.ddim_step(e_null + s * (e_cond - e_null), 481, -1, z)
        by_hand = pipe.latents_to_features(z0, L)
        z0_at_2 = lcm.ddim_step(e_null + 2.0 * (e_cond - e_null), 481, -1, z)  # config draft.teacher_guidance 2
        by_hand_at_2 = pipe.latents_to_features(z0_at_2, L)
    assert np.allclose(out.features, by_hand, atol=1e-5)
    pipe.config.draft.teacher_guidance = 2.0  # the teacher step's own scale; the consistency step keeps s
    at_2 = pipe("a person walks", 1.5, seed=5, draft=True, repair=False)
    pipe.config.draft.teacher_guidance = None
    assert np.allclose(at_2.features, by_hand_at_2, atol=1e-5) and not np.allclose(at_2.features, by_hand, atol=1e-4)
    calls.clear()  # one step leaves no room for a teacher step: the consistency step alone
    one = pipe("a person walks", 1.5, seed=5, draft=True, num_inference_steps=1, repair=False,
               callback=lambda k, n: calls.append((k, n)))
    assert calls == [(1, 1)]
    with torch.no_grad():
        alone = pipe.latents_to_features(est, L)
    assert np.allclose(one.features, alone, atol=1e-5)
    three = pipe("a person walks", 1.5, seed=5, draft=True, num_inference_steps=3, repair=False)
    pipe.draft_teacher = pipe.draft_denoiser.__class__(pipe.config.denoiser).eval()  # another teacher ...
    assert not np.allclose(three.features, pipe("a person walks", 1.5, seed=5, draft=True, num_inference_steps=3,
                                                repair=False).features, atol=1e-4)  # ... changes only the last step
    bad = {**data, "draft": {**data["draft"], "teacher_steps": 50}}
    (folder / "config.json").write_text(json.dumps(bad))
    with pytest.raises(CheckpointError, match="draft.teacher_steps"):
        MLDPipeline.from_pretrained(folder)


def test_the_pooled_text_tokens_are_the_same_with_and_without_gradients():
    from mld_core.models.denoiser import AttentionPool

    torch.manual_seed(0)
    pool = AttentionPool(32, 2, 4).eval()
    tokens, valid = torch.randn(3, 7, 32), torch.ones(3, 7, dtype=torch.bool)
    valid[1, 4:], valid[2, 1:] = False, False  # padded rows
    with torch.enable_grad():
        module_path = pool(tokens, valid)  # nn.MultiheadAttention
    with torch.no_grad():
        functional = pool(tokens, valid)
    assert torch.allclose(module_path, functional, atol=1e-6)


def test_pooling_projected_tokens_folds_the_projection_and_follows_new_weights():
    from torch import nn

    from mld_core.models.denoiser import AttentionPool

    torch.manual_seed(0)
    pool, project = AttentionPool(32, 2, 4).eval(), nn.Linear(48, 32)
    tokens, valid = torch.randn(3, 7, 48), torch.ones(3, 7, dtype=torch.bool)
    valid[1, 4:], valid[2, 1:] = False, False
    with torch.enable_grad():
        reference = pool(project(tokens), valid)  # the module path, projection first
    with torch.no_grad():
        folded = pool.pool_projected(tokens, valid, project)
        assert pool._fold is not None
        again = pool.pool_projected(tokens, valid, project)
        project.weight.mul_(2.0)  # an in-place update (an optimiser step, load_state_dict) ...
        changed = pool.pool_projected(tokens, valid, project)
    torch.testing.assert_close(folded, reference, atol=1e-5, rtol=0)
    assert torch.equal(again, folded)
    with torch.enable_grad():
        torch.testing.assert_close(changed, pool(project(tokens), valid), atol=1e-5, rtol=0)  # ... is followed
    grads = pool.pool_projected(tokens, valid, project)  # with gradients: the plain path, which trains
    grads.sum().backward()
    assert project.weight.grad is not None and pool.queries.grad is not None
    with torch.no_grad():
        project.weight = nn.Parameter(project.weight * 0.5)  # a new tensor, perhaps at a freed address
        replaced = pool.pool_projected(tokens, valid, project)
        with torch.autocast("cpu", dtype=torch.bfloat16):  # a fold made under autocast ...
            pool._fold_key = None
            pool.pool_projected(tokens, valid, project)
        after_autocast = pool.pool_projected(tokens, valid, project)  # ... is the weights' own precision
    with torch.enable_grad():
        torch.testing.assert_close(replaced, pool(project(tokens), valid), atol=1e-5, rtol=0)
        torch.testing.assert_close(after_autocast, pool(project(tokens), valid), atol=1e-5, rtol=0)
    with torch.inference_mode():  # a model built in inference mode: its weights keep no version counter
        frozen_pool, frozen_project = AttentionPool(32, 2, 4).eval(), nn.Linear(48, 32)
        frozen_pool.load_state_dict(pool.state_dict())
        frozen_project.load_state_dict(project.state_dict())
        torch.testing.assert_close(frozen_pool.pool_projected(tokens, valid, frozen_project), replaced, atol=1e-5,
                                   rtol=0)


def test_packed_skip_projections_serve_long_sequences_only():
    from mld_core.models.transformer import SkipTransformer, TransformerConfig

    torch.manual_seed(0)
    stack = SkipTransformer(TransformerConfig(dim=32, heads=2, ff_dim=64, layers=3, cross_attention=True)).eval()
    memory = torch.randn(1, 2, 32)
    if not stack.pack_for_cpu_inference():
        pytest.skip("this torch build has no oneDNN prepacked linear ops")
    calls = []
    real = stack.skip_projections[0].forward
    stack.skip_projections[0].forward = lambda x: calls.append(x.shape[1]) or real(x)
    with torch.no_grad():
        for batch, frames in ((1, 8), (5, 8), (1, 31), (1, 32)):
            stack(torch.randn(batch, frames, 32), memory=memory.expand(batch, -1, -1))
    assert calls == [8, 8, 31]  # 32 frames took the packed product; a batch of short sequences never does
    x = torch.randn(1, 40, 32)
    with torch.no_grad():
        packed = stack(x, memory=memory)
    with torch.enable_grad():
        plain = stack(x, memory=memory)  # the module path
    torch.testing.assert_close(packed, plain, atol=1e-4, rtol=0)
    stack.load_state_dict(stack.state_dict())
    assert stack._packed_projections == []


def test_bf16_products_in_a_float32_stack_stay_close_to_float32():
    from mld_core.models.transformer import SkipTransformer, TransformerConfig

    torch.manual_seed(0)
    stack = SkipTransformer(TransformerConfig(dim=32, heads=2, ff_dim=64, layers=3, cross_attention=True)).eval()
    x, memory = torch.randn(1, 20, 32), torch.randn(1, 2, 32)
    with torch.no_grad():
        reference = stack(x, memory=memory)
        if not stack.pack_for_cpu_inference(torch.bfloat16):
            pytest.skip("this torch build has no oneDNN prepacked linear ops")
        mixed = stack(x, memory=memory)
    assert mixed.dtype == torch.float32
    assert 0 < (mixed - reference).abs().max() < 0.05


# -- the Draft's precision ----------------------------------------------------------------------------------------
@pytest.mark.skipif(not packs_in(torch.bfloat16), reason="this CPU's oneDNN packs no bfloat16 (it needs AVX512-BW/VL/DQ "
                    "or AVX-NE-CONVERT), so a Draft asked for bf16 runs in fp32")
def test_a_bf16_draft_leaves_final_unchanged_and_keeps_its_rows_close_to_single_runs(tmp_path):
    from mld_core.models.text_encoder import TextEmbedding

    fp32 = tiny_pipeline(tmp_path / "m", draft=True, draft_precision="fp32")
    bf16 = tiny_pipeline(tmp_path / "m", draft=True, draft_precision="bf16")
    assert bf16.draft_precision == "bf16" and fp32.draft_precision == "fp32"
    assert bf16.draft_text_encoder.dtype == torch.bfloat16 and bf16.draft_text_encoder is not bf16.text_encoder
    for stack in (bf16.draft_denoiser.transformer, bf16.draft_vae.decoder):  # float32 modules, bf16 products
        assert next(stack.parameters()).dtype == torch.float32
        assert {p[0].dtype for layer in stack._packed.values() for p in layer.values()} == {torch.bfloat16}
    assert bf16.draft_vae is not bf16.vae
    assert {bf16.denoiser.latent_in.weight.dtype, bf16.vae.head.weight.dtype, bf16.text_encoder.dtype} == {torch.float32}
    draft = bf16("a person walks", 1.5, seed=3, draft=True)  # its bf16 embedding of the prompt is cached ...
    assert isinstance(bf16._draft_text_cache["a person walks"], TextEmbedding)
    final = bf16("a person walks", 1.5, seed=3)  # ... and never reaches Final
    assert np.array_equal(final.joints, fp32("a person walks", 1.5, seed=3).joints)
    reference = fp32("a person walks", 1.5, seed=3, draft=True).joints
    assert np.isfinite(draft.joints).all() and 0 < np.abs(draft.joints - reference).max() < 0.05
    both = bf16(["a person waves", "a person walks"], seconds=[2.0, 1.5], seed=[9, 3], draft=True)
    assert np.abs(both.joints[1, :30] - draft.joints[0]).max() < 0.02  # bf16 rounding differs with the batch size
    bf16.clear_text_cache()
    assert not bf16._draft_text_cache and not bf16._text_cache


@pytest.mark.skipif(not packs_in(torch.bfloat16), reason="this CPU's oneDNN packs no bfloat16 (it needs AVX512-BW/VL/DQ "
                    "or AVX-NE-CONVERT), so a Draft asked for bf16 runs in fp32")
def test_a_drafts_teacher_is_the_float32_denoiser_whatever_finals_precision(tmp_path):
    from mld_core.pipeline import MLDPipeline

    folder, _ = _tiny_model_with_a_teacher_step(tmp_path / "m")
    plain = MLDPipeline.from_pretrained(folder, draft_precision="fp32")
    assert plain.draft_teacher is plain.denoiser
    bf16_final = MLDPipeline.from_pretrained(folder, precision="bf16", draft_precision="fp32")
    assert bf16_final.draft_teacher is not bf16_final.denoiser  # Final's weights are rounded to bf16: not its
    draft = plain("a person walks", 1.5, seed=2, draft=True).joints
    assert np.allclose(bf16_final("a person walks", 1.5, seed=2, draft=True).joints, draft, atol=1e-5)
    bf16_draft = MLDPipeline.from_pretrained(folder, draft_precision="bf16")
    teacher = bf16_draft.draft_teacher
    assert teacher is not bf16_draft.denoiser and next(teacher.parameters()).dtype == torch.float32
    assert {p[0].dtype for layer in teacher.transformer._packed.values() for p in layer.values()} == {torch.bfloat16}
    assert 0 < np.abs(bf16_draft("a person walks", 1.5, seed=2, draft=True).joints - draft).max() < 0.05


def test_auto_draft_precision_is_bf16_only_on_cpus_that_compute_it_natively(monkeypatch):
    import mld_core.pipeline as pipeline

    monkeypatch.setattr(pipeline, "packs_in", lambda dtype: True)  # a CPU whose oneDNN packs bfloat16
    monkeypatch.setattr(pipeline, "native_bf16", lambda: True)
    assert pipeline.draft_precision_for("auto") == "bf16" and pipeline.draft_precision_for("fp32") == "fp32"
    monkeypatch.setattr(pipeline, "native_bf16", lambda: False)
    assert pipeline.draft_precision_for("auto") == "fp32" and pipeline.draft_precision_for("bf16") == "bf16"
    with pytest.raises(ValueError, match="draft_precision must be one of auto, fp32, bf16"):
        pipeline.draft_precision_for("fp16")
    monkeypatch.setattr(pipeline, "packing_available", lambda: False)  # no oneDNN: no bf16 products
    with pytest.warns(UserWarning, match="runs in fp32"):
        assert pipeline.draft_precision_for("bf16") == "fp32"
    monkeypatch.setattr(pipeline, "packing_available", lambda: True)
    monkeypatch.setattr(pipeline, "packs_in", lambda dtype: False)  # oneDNN, but no bfloat16 packing (AVX2 only)
    with pytest.warns(UserWarning, match="runs in fp32"):
        assert pipeline.draft_precision_for("bf16") == "fp32"


@pytest.mark.skipif(not packs_in(torch.bfloat16), reason="this CPU's oneDNN packs no bfloat16 (it needs AVX512-BW/VL/DQ "
                    "or AVX-NE-CONVERT), so a Draft asked for bf16 runs in fp32")
def test_an_encoder_passed_in_is_the_drafts_too(tmp_path):
    from mld_core.models.text_encoder import MiniLMEncoder
    from mld_core.pipeline import MLDPipeline
    from mld_core.testing import tiny_model

    folder = tiny_model(tmp_path / "m", draft=True)
    mine = MiniLMEncoder.random(seed=0, hidden=32, layers=2, heads=2, vocab_path="builtin")
    pipe = MLDPipeline.from_pretrained(folder, text_encoder=mine, draft_precision="bf16")
    assert pipe.draft_text_encoder is mine and pipe.draft_vae is not pipe.vae
    assert np.isfinite(pipe("a person walks", 1.5, draft=True).joints).all()
