"""research/v4/latent_use.py: the posterior's spread per latent dimension, on a tiny model."""
import importlib.util
from pathlib import Path

from mld_core.testing import tiny_model
from test_reliability import _h3d_folder

SCRIPT = Path(__file__).resolve().parents[1] / "research" / "v4" / "latent_use.py"


def _script():
    spec = importlib.util.spec_from_file_location("latent_use", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_latent_use_counts_the_dimensions_whose_posterior_is_narrow(tmp_path, capsys):
    """An encoder whose log-variance is pushed down (sigma e^-2 on every dimension) reports every dimension active,
    pushed up (sigma e^2) none; a label no clip has is one error line."""
    from mld_core.pipeline import MLDPipeline

    latent_use = _script()
    model = tiny_model(tmp_path / "tiny")
    data = _h3d_folder(tmp_path / "data")
    pipe = MLDPipeline.from_pretrained(model)
    ids = latent_use.clip_ids(data, set(), 8)
    mu, sigma = latent_use.posterior(pipe, data, ids)
    assert mu.shape == sigma.shape == (len(ids), pipe.config.vae.latent_tokens, pipe.config.vae.latent_dim)
    n = pipe.config.vae.latent_tokens
    encode = pipe.vae.encode
    for shift, active in ((-1e3, True), (1e3, False)):
        pipe.vae.encode = _shifted(encode, shift)
        _, sigma = latent_use.posterior(pipe, data, ids)
        assert bool((sigma < 0.3).all()) is active and bool((sigma > 0.9).all()) is not active
    assert latent_use.main([str(model), "--data", str(data)]) == 0
    out = capsys.readouterr().out
    assert f"latent ({n}, {pipe.config.vae.latent_dim})" in out and "active dims" in out
    (data / "actions.json").write_text('{"clips": {}}')
    assert latent_use.main([str(model), "--data", str(data), "--labels", "no-such-label"]) == 2
    assert "no train clips" in capsys.readouterr().err


def _shifted(encode, shift):
    def run(x, lengths):
        mu, logvar = encode(x, lengths)
        return mu, (logvar + shift).clamp(-4.0, 4.0)
    return run
