"""The pipeline's takes do not change when its code is reorganised: the bundled model's takes on every path of
``MLDPipeline.__call__`` (Final, stepped or not, Draft, a side redraw, directed, ranked, a sequence, unconditional, an
action model) equal, bit for bit, the ones recorded before (scripts/record_takes.py; re-record only for an intended
change of output, and say so)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "scripts"))
from record_takes import compare, record  # noqa: E402

REFERENCE = REPO / "tests" / "fixtures" / "takes_reference.npz"


@pytest.mark.slow
def test_takes_equal_the_recorded_ones_bit_for_bit():
    with np.load(REFERENCE) as data:
        reference = {k: data[k] for k in data.files}
    takes = record()
    if str(takes["machine"]) != str(reference["machine"]):
        pytest.skip(f"takes were recorded on {reference['machine']} and compare bit for bit only there (this machine: "
                    f"{takes['machine']}); record a reference here with scripts/record_takes.py --out before a change")
    verdicts = compare(takes, reference)
    assert len(verdicts) == 10
    assert {case: v for case, v in verdicts.items() if v != "same"} == {}


def test_the_recording_covers_every_path():
    with np.load(REFERENCE) as data:
        assert int(data["sided_redrawn/draws"][0]) >= 1  # a side redraw was kept
        assert data["ranked_variants/seeds"].tolist() == [7, 6]  # ranking reordered the variants
        assert data["directed_stepped/residuals"].shape == (1, 3)  # pose keys, a root path, a loop
        assert data["sequence/seams"].shape == (1, 1)
        assert data["final/features"].dtype == np.float32


def test_the_comparison_sees_a_one_bit_change():
    reference = {"a/joints": np.zeros((2, 3), np.float32), "a/draws": np.zeros(1, np.int64),
                 "b/joints": np.ones(2, np.float32)}
    assert compare(dict(reference), reference) == {"a": "same", "b": "same"}
    nudged = np.nextafter(np.float32(1.0), np.float32(2.0))  # one bit above 1
    changed = {"a/joints": np.zeros((2, 3), np.float32), "b/joints": np.array([1.0, nudged], np.float32)}
    assert compare(changed, reference) == {"a": "draws missing", "b": "joints differs by up to 1.19e-07"}
    assert compare({**reference, "a/joints": np.zeros((2, 4), np.float32)}, reference)["a"] == \
        "joints float32[2, 4] vs recorded float32[2, 3]"
