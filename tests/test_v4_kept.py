"""The v4 training's folders the repository carries to continue from (research/v4/README.md): the VAE and the merged
evaluator load from their folders, are stored in fp16 with a card, and give their pinned numbers on the repository's
Bandai Namco fixture clips (a change of weights or of the code that reads them moves these)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import load_file

from mld_core.checkpoint import load_config, load_weights
from mld_core.models.vae import MotionVAE
from mld_core.motion.features import features_to_joints

V4 = Path(__file__).resolve().parents[1] / "research" / "v4"
FIXTURES = sorted((Path(__file__).parent / "fixtures" / "bandai").glob("*.bvh"))
PINNED_VAE_MPJPE_MM = 33.04  # the fixture clips through research/v4/vae, root-relative (bundled VAE: 28.45)
PINNED_CMU_VAE_MPJPE_MM = 104.5  # the fixture clips through research/cmu_only/vae (it never saw Bandai's clips)
PINNED_EVALUATOR_SIMILARITY = 0.8692  # the walk-and-turn fixture's motion embedding against its wording below


def fixture_features(path: Path) -> np.ndarray:
    from mld_core.data.bandai import clip_joints
    from mld_core.motion.features import joints_to_features

    return joints_to_features(clip_joints(path.read_text())).astype(np.float32)  # (T, 263)


def fixture_recon_mpjpe_mm(folder: Path) -> float:
    """Root-relative MPJPE (mm) of the fixture clips, each encoded and decoded (the latent's mean) by ``folder``'s
    VAE, averaged over clips."""
    config = load_config(folder)
    vae = MotionVAE(config.vae).eval()
    load_weights(folder / "vae.safetensors", vae)
    mean, std = (np.asarray(a, np.float32) for a in config.mean_std)
    errors = []
    for path in FIXTURES:
        feats = fixture_features(path)[: config.max_frames]
        x = torch.from_numpy((feats - mean) / std)[None]  # (1, T, 263)
        lengths = torch.tensor([x.shape[1]])
        with torch.no_grad():
            mu, _ = vae.encode(x, lengths)
            recon = vae.decode(mu, lengths)[0].numpy() * std + mean  # (T, 263)
        real, back = features_to_joints(feats), features_to_joints(recon)  # (T, 22, 3)
        real, back = real - real[:, :1], back - back[:, :1]
        errors.append(float(np.linalg.norm(real - back, axis=-1).mean() * 1000))
    return float(np.mean(errors))


def test_the_kept_vae_is_fp16_with_its_lineage_and_gives_its_pinned_reconstruction():
    folder = V4 / "vae"
    assert {v.dtype for v in load_file(str(folder / "vae.safetensors")).values()} == {torch.float16}
    config = load_config(folder)
    assert config.denoiser is None and config.vae.feature_dim == 263
    lineage = [s["model_id"] for s in config.provenance.get("vae_lineage", [])]
    assert lineage and lineage[0] == "mld-bandai-cpu-v3.8"  # where the first sitting started
    card = (folder / "MODEL_CARD.md").read_text()
    assert "CC BY-NC 4.0" in card and "sittings below" in card
    assert fixture_recon_mpjpe_mm(folder) == pytest.approx(PINNED_VAE_MPJPE_MM, rel=1e-3)


def test_the_merged_evaluator_is_fp16_and_gives_its_pinned_similarity():
    from mld_core.eval.evaluator import Evaluator

    folder = V4 / "evaluator"
    weights = load_file(str(folder / "model.safetensors"))
    assert torch.float16 in {v.dtype for v in weights.values()}
    assert "CC BY-NC 4.0" in (folder / "EVALUATOR_CARD.md").read_text()
    evaluator = Evaluator.from_pretrained(folder)
    motion = evaluator.encode_motion([fixture_features(p) for p in FIXTURES if "walk-turn-left" in p.name])[0]
    text = evaluator.encode_text(["a person walks and turns left"])[0]
    assert float(motion @ text) == pytest.approx(PINNED_EVALUATOR_SIMILARITY, abs=1e-3)
    assert float(motion @ evaluator.encode_text(["a person kicks"])[0]) < float(motion @ text) - 0.3


def test_the_kept_text_model_is_fp16_generates_and_records_no_machine_path():
    """mld_core/weights/v4_preview: a model folder (denoiser + the VAE it trained on + a verb denoiser on its latents) that
    generates as it is, in fp16, its card and provenance free of any machine's paths; the verb denoiser guides a
    prompt naming a checked verb and leaves any other as the text denoiser alone makes it."""
    from mld_core.pipeline import MLDPipeline

    folder = V4.parents[1] / "mld_core" / "weights" / "v4_preview"
    for name in ("denoiser.safetensors", "vae.safetensors", "verb_denoiser.safetensors"):
        assert {v.dtype for v in load_file(str(folder / name)).values()} == {torch.float16}
    card, config = (folder / "MODEL_CARD.md").read_text(), (folder / "config.json").read_text()
    assert "CC BY-NC 4.0" in card and "mocap.cs.cmu.edu" in card
    assert not re.search(r'"/[A-Za-z]', config + card)  # no absolute path recorded in the provenance
    pipe = MLDPipeline.from_pretrained(folder)
    assert pipe.config.denoiser.cond == "text"
    out = pipe(["a person squats down"], seconds=2.0, seed=0, num_variants=2)
    assert out.joints.shape[0] == 2 and np.isfinite(out.joints).all()
    assert not np.allclose(out.joints[0], out.joints[1])  # two seeds, two takes
    assert pipe.verb_guide.scale == 8.0 and "## Verb guidance" in card
    assert set(pipe.verb_guide.verbs) == {"jump", "get_low", "on_ground", "crawl", "reach_floor", "inverted",
                                          "stand_up", "climb", "kick", "throw"}
    kw = dict(seconds=2.0, seed=0, num_inference_steps=5, repair=False, side_redraws=0, verb_redraws=0)
    assert pipe.config.verb_redraws == 2 and "## Verb redraws" in card
    assert pipe.config.repair.on_floor and "## On the floor" in card
    floored = pipe(["a person crawls on hands and knees"], seconds=2.0, seed=0, num_inference_steps=5)
    assert floored.joints[0, : floored.lengths[0], :, 1].min() == pytest.approx(0.0, abs=1e-5)
    guided = pipe(["a person jumps", "a person waves"], **kw).joints
    pipe.verb_guide.scale = 0.0
    plain = pipe(["a person jumps", "a person waves"], **kw).joints
    assert not np.allclose(guided[0], plain[0], atol=1e-3) and np.array_equal(guided[1], plain[1])



def test_the_preview_has_a_draft_whose_teacher_step_is_verb_guided():
    """The preview's Draft (draft.safetensors, fp16; the default's 3-layer text encoder): a Draft take of a verb
    prompt has its teacher step guided by the verb denoiser too (config draft.teacher_verb_guide), another prompt
    not; its card says how it was distilled and measured."""
    from mld_core.pipeline import MLDPipeline

    folder = V4.parents[1] / "mld_core" / "weights" / "v4_preview"
    default = V4.parents[1] / "mld_core" / "weights" / "default"
    assert {v.dtype for v in load_file(str(folder / "draft.safetensors")).values()} == {torch.float16}
    assert (folder / "draft_text.safetensors").read_bytes() == (default / "draft_text.safetensors").read_bytes()
    assert "## Draft" in (folder / "MODEL_CARD.md").read_text()
    pipe = MLDPipeline.from_pretrained(folder, draft_precision="fp32")
    d = pipe.config.draft
    assert (d.teacher_verb_guide, d.text_layers, d.teacher_steps, pipe.draft_text_layers) == (True, 3, 1, 3)
    assert pipe.config.provenance["draft_training"]["fold_verb_guide"] is True
    kw = dict(seconds=2.0, seed=0, draft=True, repair=False, side_redraws=0, verb_redraws=0)
    guided = pipe(["a person jumps", "a person waves"], **kw).joints
    d.teacher_verb_guide = False
    plain = pipe(["a person jumps", "a person waves"], **kw).joints
    assert np.isfinite(guided).all() and not np.allclose(guided[0], plain[0], atol=1e-3)
    assert np.array_equal(guided[1], plain[1])


def test_the_kept_action_model_is_fp16_generates_by_label_and_refuses_an_unknown_one():
    """research/v4/action_model: conditioned on the action labels of the merged folder (``generate --action jump``),
    in fp16 on the fourth sitting of research/v4/vae; a label it was not trained on is refused by name."""
    from mld_core.pipeline import MLDPipeline

    folder = V4 / "action_model"
    for name in ("denoiser.safetensors", "vae.safetensors"):
        assert {v.dtype for v in load_file(str(folder / name)).values()} == {torch.float16}
    card, config = (folder / "MODEL_CARD.md").read_text(), (folder / "config.json").read_text()
    assert "CC BY-NC 4.0" in card and "mocap.cs.cmu.edu" in card
    assert not re.search(r'"/[A-Za-z]', config + card)
    pipe = MLDPipeline.from_pretrained(folder)
    assert pipe.config.denoiser.cond == "action"
    assert {"jump", "kick", "walk-left", "stand_up"} <= set(pipe.config.actions)
    out = pipe(["jump", "crawl"], actions=["jump", "crawl"], seconds=2.0, seed=0)
    assert out.joints.shape[0] == 2 and np.isfinite(out.joints).all()
    assert not np.allclose(out.joints[0], out.joints[1])  # two labels, two motions from one seed
    with pytest.raises(ValueError, match="swim"):
        pipe(["swim"], actions=["swim"], seconds=2.0, seed=0)


def test_the_long_text_denoiser_is_fp16_on_the_kept_vae_and_generates():
    """research/v4/den_long: the text denoiser trained long on research/v4/vae with a verb denoiser on its latents,
    kept so its next sitting continues it (``train denoiser --init research/v4/den_long``): fp16, the kept VAE's
    weights unchanged beside it, the Bandai, CMU and KIT terms recorded, no machine path; it generates."""
    from mld_core.data import terms
    from mld_core.pipeline import MLDPipeline

    folder = V4 / "den_long"
    for name in ("denoiser.safetensors", "vae.safetensors"):
        assert {v.dtype for v in load_file(str(folder / name)).values()} == {torch.float16}
    kept_vae, its_vae = load_file(str(V4 / "vae" / "vae.safetensors")), load_file(str(folder / "vae.safetensors"))
    assert kept_vae.keys() == its_vae.keys() and all(torch.equal(kept_vae[k], its_vae[k]) for k in kept_vae)
    card, text = (folder / "MODEL_CARD.md").read_text(), (folder / "config.json").read_text()
    assert "CC BY-NC 4.0" in card and "mocap.cs.cmu.edu" in card
    assert "## Limits" in card and "24 content classes" not in card  # its own limits, not the Bandai model's
    assert not re.search(r'"/[A-Za-z]', text + card)
    config = load_config(folder)
    assert config.denoiser.cond == "text" and terms.commercial_use(terms.of_model(config)) is False
    assert {e["name"] for e in terms.of_model(config)} == {terms.BANDAI["name"], terms.CMU["name"], terms.KIT["name"]}
    pipe = MLDPipeline.from_pretrained(folder)
    out = pipe(["a person jumps"], seconds=2.0, seed=0, num_variants=2, num_inference_steps=5)
    assert out.joints.shape[0] == 2 and np.isfinite(out.joints).all()
    assert pipe.verb_guide.scale == 8.0 and "jump" in pipe.verb_guide.verbs  # its own verb denoiser, on its latents


def test_the_cmu_only_vae_is_fp16_owes_nothing_to_bandai_and_gives_its_pinned_reconstruction():
    """research/cmu_only/vae: the CMU-only model's VAE, trained from nothing on CMU's own descriptions' folder:
    its weights may go into commercial products, and it reconstructs the fixture clips (Bandai's, which it never
    saw) at its pinned error."""
    from mld_core.data import terms

    folder = V4.parent / "cmu_only" / "vae"
    assert {v.dtype for v in load_file(str(folder / "vae.safetensors")).values()} == {torch.float16}
    config = load_config(folder)
    assert config.denoiser is None and config.vae.latent_tokens == 2
    assert terms.of_model(config) == [terms.CMU] and terms.commercial_use(terms.of_model(config)) is True
    assert "may be used in commercial products" in (folder / "MODEL_CARD.md").read_text()
    assert fixture_recon_mpjpe_mm(folder) == pytest.approx(PINNED_CMU_VAE_MPJPE_MM, rel=1e-3)
