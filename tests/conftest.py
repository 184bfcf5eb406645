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
