"""Shared test set-up: small, seeded, single-threaded; ../shared is optional."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
FIXTURES = REPO / "tests" / "fixtures"
SHARED = Path(os.environ.get("MLD_SHARED", REPO.parent / "shared"))


def pytest_configure(config):
    try:
        import torch

        torch.set_num_threads(1)
    except ImportError:  # pragma: no cover - torch is a hard dependency
        pass


@pytest.fixture
def fixtures() -> Path:
    return FIXTURES


@pytest.fixture
def shared() -> Path:
    """The developer/CI-only ../shared folder; tests that need it skip with a reason when absent."""
    if not SHARED.is_dir():
        pytest.skip(f"needs the shared folder {SHARED} (developer and CI machines only)")
    return SHARED


@pytest.fixture(scope="module")
def minilm():
    """The real all-MiniLM-L6-v2 sentence encoder (skips where its weights package is not installed)."""
    from mld_core.models.text_encoder import TextEncoderError, load_text_encoder

    try:
        return load_text_encoder({"kind": "minilm"})
    except (TextEncoderError, ImportError) as exc:
        pytest.skip(f"needs the MiniLM weights package: {exc}")
