"""The MLD model core: schedulers, VAE, denoiser, pipeline (tiny seeded models, seconds each)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from mld_core.checkpoint import CheckpointError
from mld_core.models.denoiser import DenoiserConfig, LatentDenoiser
from mld_core.models.transformer import SkipTransformer, TransformerConfig
from mld_core.models.vae import MotionVAE, VAEConfig
from mld_core.pipeline import Cancelled, MLDPipeline
from mld_core.schedulers import DDIMScheduler, DDPMScheduler, SchedulerConfig
from mld_core.testing import tiny_model, tiny_pipeline


def tiny_vae(seed=0, skip=True, n=1) -> MotionVAE:
    torch.manual_seed(seed)
    block = dict(dim=32, heads=2, ff_dim=64, layers=3, dropout=0.0, skip=skip)
    return MotionVAE(VAEConfig(feature_dim=263, latent_tokens=n, latent_dim=32, max_frames=64,
                               encoder=TransformerConfig(**block),
                               decoder=TransformerConfig(**block, cross_attention=True))).eval()


# -- schedulers -------------------------------------------------------------------------------------------------
def test_ddim_timesteps_follow_mld_settings():
    s = DDIMScheduler()
    s.set_timesteps(50)
    assert s.timesteps[:3].tolist() == [981, 961, 941]
    assert s.timesteps[-1].item() == 1
    assert len(s.timesteps) == 50
    # scaled_linear betas: sqrt-space linear from 0.00085 to 0.012
    assert s.betas[0].item() == pytest.approx(0.00085, rel=1e-5)
    assert s.betas[-1].item() == pytest.approx(0.012, rel=1e-5)
    with pytest.raises(ValueError):
        s.set_timesteps(0)


def test_ddim_step_recovers_x0_from_true_noise():
    s = DDIMScheduler()
    s.set_timesteps(10)
    g = torch.Generator().manual_seed(0)
    x0, eps = torch.randn(4, 1, 8, generator=g), torch.randn(4, 1, 8, generator=g)
    t = int(s.timesteps[0])
    xt = s.add_noise(x0, eps, torch.full((4,), t))
    _, pred_x0 = s.step(eps, t, xt)
    assert torch.allclose(pred_x0, x0, atol=1e-4)


def test_ddpm_add_noise_matches_closed_form():
    s = DDPMScheduler()
    x0, eps = torch.ones(2, 3), torch.zeros(2, 3)
    t = torch.tensor([0, 999])
    out = s.add_noise(x0, eps, t)
    a = s.alphas_cumprod
    assert torch.allclose(out[:, 0], a[t].sqrt())


def test_schedulers_match_diffusers_where_installed():
    diffusers = pytest.importorskip("diffusers", reason="diffusers is not installed (optional parity check)")
    kw = dict(num_train_timesteps=1000, beta_start=0.00085, beta_end=0.012, beta_schedule="scaled_linear",
              set_alpha_to_one=False, steps_offset=1, clip_sample=False)
    ref = diffusers.DDIMScheduler(**kw)
    ours = DDIMScheduler(SchedulerConfig())
    ref.set_timesteps(50)
    ours.set_timesteps(50)
    assert ref.timesteps.tolist() == ours.timesteps.tolist()
    g = torch.Generator().manual_seed(1)
    x, eps = torch.randn(2, 1, 16, generator=g), torch.randn(2, 1, 16, generator=g)
    for t in ours.timesteps[:5].tolist() + [1]:
        want = ref.step(eps, t, x, eta=0.0).prev_sample
        got, _ = ours.step(eps, t, x)
        assert torch.allclose(got, want, atol=1e-6)
    noise_ref = diffusers.DDPMScheduler(**{k: v for k, v in kw.items() if k not in ("set_alpha_to_one", "steps_offset")})
    t = torch.tensor([0, 500])
    assert torch.allclose(DDPMScheduler().add_noise(x, eps, t), noise_ref.add_noise(x, eps, t), atol=1e-6)


# -- transformer and VAE -----------------------------------------------------------------------------------------
def test_skip_transformer_needs_odd_layers_and_can_turn_skips_off():
    with pytest.raises(ValueError):
        TransformerConfig(layers=4)
    plain = SkipTransformer(TransformerConfig(dim=16, heads=2, ff_dim=32, layers=4, skip=False))
    assert len(plain.skip_projections) == 0 and len(plain.middle_blocks) == 4
    skipped = SkipTransformer(TransformerConfig(dim=16, heads=2, ff_dim=32, layers=5))
    assert len(skipped.input_blocks) == 2 and len(skipped.middle_blocks) == 1 and len(skipped.skip_projections) == 2


@pytest.mark.parametrize("n", [1, 2])
def test_vae_shapes_and_padding_never_changes_valid_frames(n):
    vae = tiny_vae(n=n)
    torch.manual_seed(1)
    a, b = torch.randn(1, 30, 263), torch.randn(1, 17, 263)
    batch = torch.zeros(2, 30, 263)
    batch[0], batch[1, :17] = a[0], b[0]
    batch[1, 17:] = 1e3  # garbage in the padding must not leak
    lengths = torch.tensor([30, 17])
    with torch.no_grad():
        mu, logvar = vae.encode(batch, lengths)
        mu_b, _ = vae.encode(b, torch.tensor([17]))
        assert mu.shape == logvar.shape == (2, n, 32)
        assert torch.allclose(mu[1], mu_b[0], atol=1e-5)
        out = vae.decode(mu, lengths)
        out_b = vae.decode(mu_b, torch.tensor([17]))
    assert out.shape == (2, 30, 263)
    assert torch.allclose(out[1, :17], out_b[0], atol=1e-5)
    assert torch.all(out[1, 17:] == 0)



def test_grown_latent_decodes_copied_tokens_as_the_old_latent_and_keeps_every_other_weight():
    """grow_latent(n -> m, m a multiple of n): the decoder reads a latent whose token i is the old token i mod n
    exactly as it read the old latent (noise 0); the encoder's tokens i >= n start as copies (mu and log-variance alike); every other weight
    is the old model's; the noise only moves the copies; a smaller latent is refused."""
    from mld_core.models.vae import grow_latent

    vae = tiny_vae(n=2)
    torch.manual_seed(3)
    x, lengths = torch.randn(2, 30, 263), torch.tensor([30, 21])
    grown = grow_latent(vae, 6)
    assert grown.config.latent_tokens == 6 and vae.config.latent_tokens == 2
    with torch.no_grad():
        z, _ = vae.encode(x, lengths)
        tiled = z[:, [0, 1, 0, 1, 0, 1]]  # (B, 6, d)
        assert torch.allclose(grown.decode(tiled, lengths), vae.decode(z, lengths), atol=1e-5)
        mu, logvar = grown.encode(x, lengths)
    assert mu.shape == logvar.shape == (2, 6, 32)
    assert torch.equal(mu[:, 4], mu[:, 0]) and torch.equal(logvar[:, 3], logvar[:, 1])  # copies, before training
    old, new = vae.state_dict(), grown.state_dict()
    assert all(torch.equal(old[k], new[k]) for k in old if k not in ("distribution_tokens", "latent_positions"))
    noisy = grow_latent(vae, 6, noise=0.01, seed=1).state_dict()
    assert torch.equal(noisy["latent_positions"][:2], old["latent_positions"])
    assert 0 < (noisy["latent_positions"][2:] - new["latent_positions"][2:]).abs().max() < 0.1
    assert torch.equal(noisy["distribution_tokens"][:2], old["distribution_tokens"][:2])  # the old mu tokens
    assert torch.equal(noisy["distribution_tokens"][6:8], old["distribution_tokens"][2:])  # the old log-variance ones
    with pytest.raises(ValueError, match="cannot be grown"):
        grow_latent(vae, 1)

def test_vae_rejects_too_long_input():
    vae = tiny_vae()
    with pytest.raises(ValueError, match="max_frames"):
        vae.encode(torch.zeros(1, 65, 263), torch.tensor([65]))


def test_vae_training_loss_falls():
    torch.manual_seed(0)
    vae = tiny_vae()
    vae.train()
    x = torch.randn(4, 20, 263) * 0.5
    lengths = torch.full((4,), 20)
    opt = torch.optim.Adam(vae.parameters(), lr=3e-3)
    losses = []
    for _ in range(30):
        loss, _ = vae.loss(x, lengths)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.7 * losses[0]


# -- denoiser ----------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("cross", [False, True])
def test_denoiser_condition_kinds_and_shapes(cross):
    block = TransformerConfig(dim=32, heads=2, ff_dim=64, layers=3, dropout=0.0, cross_attention=cross)
    for cond in ("none", "action"):
        den = LatentDenoiser(DenoiserConfig(latent_tokens=2, latent_dim=16, cond=cond, num_actions=3, transformer=block))
        c = den.condition_tokens(2, actions=torch.tensor([0, 2])) if cond == "action" else den.null_tokens(2)
        eps = den(torch.randn(2, 2, 16), torch.tensor([10, 500]), c, torch.tensor([40, 80]))
        assert eps.shape == (2, 2, 16)
    den = LatentDenoiser(DenoiserConfig(cond="action", num_actions=3, latent_dim=16, transformer=block))
    a = den.condition_tokens(2, actions=torch.tensor([0, 1]))
    dropped = den.condition_tokens(2, actions=torch.tensor([0, 1]), drop=torch.tensor([False, True]))
    assert torch.equal(dropped[0], a[0]) and torch.equal(dropped[1], den.null_condition)


@pytest.mark.parametrize("cross", [False, True])
def test_denoiser_carried_to_another_condition_keeps_its_shared_weights(cross):
    """with_condition(text -> action): the transformer, latent, time and length layers are the text denoiser's; the
    positions keep time, the first condition token and the latent; the class embedding is fresh and seeded, also
    when an action model is carried to other labels of the same count; a denoiser of another transformer is refused."""
    from mld_core.models.denoiser import with_condition

    block = TransformerConfig(dim=32, heads=2, ff_dim=64, layers=1, dropout=0.0, cross_attention=cross)
    torch.manual_seed(0)
    text = LatentDenoiser(DenoiserConfig(latent_tokens=2, latent_dim=16, text_dim=24, text_pool_tokens=3,
                                         transformer=block))
    action_cfg = DenoiserConfig(**{**text.config.to_dict(), "cond": "action", "num_actions": 4})
    action = with_condition(text, action_cfg, seed=5)
    old, new = text.state_dict(), action.state_dict()
    shared = [k for k in new if k.startswith(("transformer.", "latent_in", "latent_out", "time_mlp", "length_mlp"))]
    assert len(shared) > 10 and all(torch.equal(old[k], new[k]) for k in shared)
    assert torch.equal(new["null_condition"], old["null_condition"][:1])
    if cross:
        assert torch.equal(new["positions"], old["positions"])
        assert torch.equal(new["cond_positions"], old["cond_positions"][:1])
    else:  # (1 + C + n, d): time, condition, latent
        assert new["positions"].shape[0] == 1 + 1 + 2
        assert torch.equal(new["positions"][:2], old["positions"][:2])
        assert torch.equal(new["positions"][-2:], old["positions"][-2:])
    assert new["action_embedding.weight"].shape == (4, 32) and not any(k.startswith("text_proj") for k in new)
    rng = torch.random.get_rng_state()
    again = with_condition(text, action_cfg, seed=5).state_dict()["action_embedding.weight"]
    assert torch.equal(rng, torch.random.get_rng_state())  # the caller's random stream is left as it was
    assert torch.equal(again, new["action_embedding.weight"])
    relabelled = with_condition(action, action_cfg, seed=6).state_dict()  # other labels, as many: a fresh embedding
    assert not torch.equal(relabelled["action_embedding.weight"], new["action_embedding.weight"])
    assert all(torch.equal(relabelled[k], new[k]) for k in shared)
    eps = action(torch.randn(2, 2, 16), torch.tensor([10, 500]), action.condition_tokens(2, actions=torch.tensor([0, 3])),
                 torch.tensor([40, 80]))
    assert eps.shape == (2, 2, 16) and torch.isfinite(eps).all()
    deeper = DenoiserConfig(**{**action_cfg.to_dict(), "transformer": {**block.__dict__, "ff_dim": 32}})
    with pytest.raises(ValueError, match="only the condition may differ"):
        with_condition(text, deeper)


def test_denoiser_length_conditioning_changes_prediction():
    torch.manual_seed(0)
    den = LatentDenoiser(DenoiserConfig(cond="none", latent_dim=16,
                                        transformer=TransformerConfig(dim=32, heads=2, ff_dim=64, layers=1, dropout=0.0)))
    z, t, c = torch.randn(1, 1, 16), torch.tensor([100]), den.null_tokens(1)
    assert not torch.allclose(den(z, t, c, torch.tensor([40])), den(z, t, c, torch.tensor([160])))


# -- pipeline ----------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def pipe(tmp_path_factory):
    return tiny_pipeline(tmp_path_factory.mktemp("tiny"), seed=0)


def test_pipeline_shapes_determinism_and_seeds(pipe):
    out = pipe(["a person walks", "a person waves"], seconds=[2.0, 3.0], seed=3, num_variants=2, num_inference_steps=2)
    assert out.features.shape == (4, 60, 263) and out.joints.shape == (4, 60, 22, 3)
    assert out.lengths.tolist() == [40, 40, 60, 60]
    assert out.seeds == [3, 4, 3, 4]
    assert np.isfinite(out.joints).all()
    assert np.all(out.features[0, 40:] == 0)
    again = pipe(["a person walks", "a person waves"], seconds=[2.0, 3.0], seed=3, num_variants=2, num_inference_steps=2)
    np.testing.assert_array_equal(out.features, again.features)
    assert not np.allclose(out.features[0, :40], out.features[1, :40])


def test_per_prompt_seeds_equal_single_runs(pipe):
    both = pipe(["a person walks", "a person jumps high"], seconds=[2.0, 1.5], seed=[5, 11], num_variants=2,
                num_inference_steps=2)
    assert both.seeds == [5, 6, 11, 12]
    one = pipe(["a person jumps high"], seconds=1.5, seed=12, num_inference_steps=2)
    np.testing.assert_allclose(both.features[3, :30], one.features[0, :30], atol=1e-4)
    with pytest.raises(ValueError, match="seed has 3 entries"):
        pipe(["a", "b"], seed=[1, 2, 3], num_inference_steps=1)


def test_batch_of_two_equals_two_single_runs(pipe):
    both = pipe(["a person walks", "a person jumps high"], seconds=2.0, seed=7, num_inference_steps=3)
    one = pipe(["a person walks"], seconds=2.0, seed=7, num_inference_steps=3)
    two = pipe(["a person jumps high"], seconds=2.0, seed=7, num_inference_steps=3)
    np.testing.assert_allclose(both.features[0], one.features[0], atol=1e-4)
    np.testing.assert_allclose(both.features[1], two.features[0], atol=1e-4)


def test_two_step_ddim_matches_pinned_numbers(pipe):
    out = pipe(["a person walks forward"], seconds=1.0, seed=0, num_inference_steps=2, guidance_scale=2.0,
               repair=False)  # the sampler alone; tests/test_repair.py covers the repairs
    got = out.features[0, :3, :4]
    pinned = np.array(PINNED_2STEP, np.float32)
    np.testing.assert_allclose(got, pinned, atol=2e-4)


PINNED_2STEP = [
    [0.022416, 0.019698, 0.014354, 0.899592],
    [0.015406, 0.017994, 0.017982, 0.915462],
    [0.004282, 0.014834, 0.026052, 0.928584],
]


def test_guidance_scale_one_equals_conditional_prediction(pipe):
    den = pipe.denoiser
    text = pipe.text_encoder(["a person walks"])
    cond = den.condition_tokens(1, text=text)
    z = torch.randn(1, 1, 32, generator=torch.Generator().manual_seed(0))
    t = torch.tensor([pipe.scheduler.timesteps[0].item()])
    lengths = torch.tensor([40])
    with torch.no_grad():
        e_c = den(z, t, cond, lengths)
        e_u = den(z, t, den.null_tokens(1), lengths)
        guided = e_u + 1.0 * (e_c - e_u)
    assert torch.allclose(guided, e_c, atol=1e-6)
    a = pipe(["a person walks"], seconds=2.0, seed=1, num_inference_steps=2, guidance_scale=1.0)
    b = pipe(["a person walks"], seconds=2.0, seed=1, num_inference_steps=2, guidance_scale=3.0)
    assert not np.allclose(a.features, b.features)


def test_callback_reports_progress_and_cancels(pipe):
    seen = []
    pipe(["a person walks"], seconds=1.0, num_inference_steps=3, callback=lambda k, n: seen.append((k, n)))
    assert seen == [(1, 3), (2, 3), (3, 3)]
    with pytest.raises(Cancelled):
        pipe(["a person walks"], seconds=1.0, num_inference_steps=3, callback=lambda k, n: k < 2)


def test_pipeline_rejects_bad_input(pipe):
    with pytest.raises(ValueError, match="empty prompt"):
        pipe(["  "], seconds=2.0)
    with pytest.raises(ValueError, match="seconds"):
        pipe(["walk"], seconds=100.0)
    with pytest.raises(ValueError, match="seconds"):
        pipe(["walk"], seconds=float("nan"))


def test_unconditional_and_prior_sampling(pipe):
    out = pipe(["", ""], seconds=1.5, unconditional=True, num_inference_steps=2)
    assert out.features.shape == (2, 30, 263)
    prior = pipe.sample_prior(seconds=2.0, num=2, seed=0)
    assert prior.joints.shape == (2, 40, 22, 3) and np.isfinite(prior.joints).all()


def test_reconstruction_decodes_the_vae_mean_whatever_the_latent_normalisation(tmp_path):
    p = tiny_pipeline(tmp_path, seed=2)
    p.config.latent_scale, p.config.latent_mean = 1.7, -0.3  # a trained model's diffusion-space normalisation
    rng = np.random.default_rng(0)
    clips = [p.denormalize(rng.normal(size=(n, 263)).astype(np.float32)) for n in (30, 22)]
    z, lengths = p.features_to_latents(clips)  # (2, n, d), (2,)
    assert lengths.tolist() == [30, 22]
    recon = p.latents_to_features(z, lengths)  # (2, 30, 263)
    with torch.inference_mode():
        for i, f in enumerate(clips):
            mu, _ = p.vae.encode(torch.from_numpy(p.normalize(f))[None], torch.tensor([len(f)]))  # (1, n, d)
            direct = p.denormalize(p.vae.decode(mu, torch.tensor([len(f)])).numpy())[0]  # (T, F)
            np.testing.assert_allclose(recon[i, : len(f)], direct, atol=1e-4)  # batch equals single, mean kept
    assert not recon[1, 22:].any()


def test_action_conditioned_pipeline(tmp_path):
    p = tiny_pipeline(tmp_path, cond="action")
    out = p([], actions=["walk", "wave"], seconds=1.0, num_inference_steps=2)
    assert out.features.shape == (2, 20, 263)
    with pytest.raises(ValueError, match="unknown action"):
        p([], actions=["fly"], seconds=1.0)


def test_save_load_gives_identical_output(tmp_path):
    a = tiny_pipeline(tmp_path / "a", seed=5)
    b = MLDPipeline.from_pretrained(tmp_path / "a")
    x = a(["a person runs"], seconds=1.0, num_inference_steps=2)
    y = b(["a person runs"], seconds=1.0, num_inference_steps=2)
    np.testing.assert_array_equal(x.features, y.features)


def test_missing_or_corrupt_checkpoint_files_are_named(tmp_path):
    d = tiny_model(tmp_path / "m")
    (d / "denoiser.safetensors").write_bytes(b"not a safetensors file")
    with pytest.raises(CheckpointError, match="denoiser.safetensors"):
        MLDPipeline.from_pretrained(d)
    (d / "denoiser.safetensors").unlink()
    with pytest.raises(CheckpointError, match="missing weights file.*denoiser.safetensors"):
        MLDPipeline.from_pretrained(d)
    (d / "config.json").write_text("{ not json")
    with pytest.raises(CheckpointError, match="config.json"):
        MLDPipeline.from_pretrained(d)
    with pytest.raises(CheckpointError, match="not found"):
        MLDPipeline.from_pretrained(tmp_path / "nowhere")


def test_config_json_round_trips(tmp_path):
    d = tiny_model(tmp_path / "m", cond="action")
    data = json.loads((d / "config.json").read_text())
    assert data["format"] == "mld-core-model"
    assert data["denoiser"]["cond"] == "action" and data["vae"]["encoder"]["layers"] == 1
    assert len(data["mean"]) == 263


# -- CPU inference paths --------------------------------------------------------------------------------------
def _skip_stack(seed=0):
    torch.manual_seed(seed)
    return SkipTransformer(TransformerConfig(dim=32, heads=2, ff_dim=64, layers=3, dropout=0.0)).eval()


def test_inference_layer_and_packed_weights_equal_the_torch_layers():
    """The written-out encoder layer (no grad, eval, no padding mask), with and without oneDNN-prepacked weights,
    computes what nn.TransformerEncoderLayer computes; training drops the packed snapshot."""
    net = _skip_stack()
    x = torch.randn(2, 7, 32)
    reference = net(x)  # grad enabled: PyTorch's own layers
    with torch.no_grad():
        plain = net(x)
        packed_ok = net.pack_for_cpu_inference()
        packed = net(x)
    torch.testing.assert_close(plain, reference, atol=1e-5, rtol=0)
    torch.testing.assert_close(packed, reference, atol=1e-4, rtol=0)
    if torch.backends.mkldnn.is_available():
        assert packed_ok and len(net._packed) == 3
    # Weights change during training: the snapshot must not survive train().
    net.train()
    assert net._packed == {}
    with torch.no_grad():
        for p in net.parameters():
            p.mul_(1.5)
    net.eval()
    changed = net(x)
    with torch.no_grad():
        assert torch.allclose(net(x), changed, atol=1e-5) and not torch.allclose(changed, reference, atol=1e-3)


def test_bf16_pipeline_is_close_to_float32(tmp_path):
    full = tiny_pipeline(tmp_path / "a", seed=0)
    half = MLDPipeline.from_pretrained(tmp_path / "a", precision="bf16")
    assert {p.dtype for p in half.denoiser.parameters()} == {torch.bfloat16}
    assert {p.dtype for p in half.vae.parameters()} == {torch.float32}
    a = full(["a person walks", "a person waves"], seconds=2.0, seed=1, num_inference_steps=2)
    b = half(["a person walks", "a person waves"], seconds=2.0, seed=1, num_inference_steps=2)
    assert b.features.dtype == np.float32 and np.isfinite(b.features).all()
    scale = np.abs(a.features).max()
    assert np.abs(a.features - b.features).max() < 0.05 * scale  # bfloat16 keeps ~3 significant digits
    assert not np.array_equal(a.features, b.features)
    with pytest.raises(ValueError, match="precision"):
        MLDPipeline.from_pretrained(tmp_path / "a", precision="fp8")


def test_a_dtype_onednn_cannot_pack_here_runs_unpacked_instead_of_failing(monkeypatch):
    """On a CPU whose oneDNN packs no bfloat16 (AVX2 only), packing a bf16 stack is declined and its layers run as
    they are, giving the same output as a stack that was never packed."""
    import mld_core.models.transformer as transformer

    torch.manual_seed(0)
    net = SkipTransformer(TransformerConfig(dim=16, heads=2, ff_dim=32, layers=3, dropout=0.0)).eval()
    x = torch.randn(2, 5, 16)
    with torch.no_grad():
        reference = net(x)
    real_packs_in = transformer.packs_in
    monkeypatch.setattr(transformer, "packs_in", lambda dtype: False)
    assert net.pack_for_cpu_inference(torch.bfloat16) is False and not net._packed
    with torch.no_grad():
        assert torch.equal(net(x), reference)
    if transformer.packing_available():
        assert real_packs_in(torch.float32)  # float32 packs wherever oneDNN does
