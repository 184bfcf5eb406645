"""``data prepare cmu-joints``: CMU's 20 joints onto the 22, captions from KIT sentences and CMU descriptions, windows
of long trials captioned by what the detectors find, skips listed with their reasons, splits by subject, bad sources
refused in one line. The source is built here from the Bandai fixture clips in CMU's joint layout and units."""

from __future__ import annotations

import io
import itertools
import json
import tarfile
from pathlib import Path

import numpy as np
import pytest

from mld_core.cli import main
from mld_core.data import terms
from mld_core.data import cmu_captions as cc
from mld_core.data import cmu_joints as C
from mld_core.data.bandai import clip_joints
from mld_core.data.take_checks import implausible, leading_jump_frames
from mld_core.motion.skeleton import JOINT_NAMES

WALK = "dataset-2_walk-turn-left_normal_027"
WAVE = "dataset-2_wave-right-hand_normal_026"
HEADER = "\t".join(C.LABEL_COLUMNS)


def as_cmu(joints: np.ndarray, fps_out: float = 12.0) -> np.ndarray:
    """22 joints at 20 fps in metres -> CMU's 20 joints at ``fps_out`` in CMU units (hands 8 cm past the wrists)."""
    from mld_core.data.bandai import resample_joints

    j = resample_joints(joints, 20.0, fps_out)
    out = np.zeros((len(j), 20, 3))
    for name, k in C.CMU_TO_SMPL.items():
        out[:, k] = j[:, JOINT_NAMES.index(name)]
    for wrist, elbow, hand in ((6, 5, 7), (10, 9, 11)):
        out[:, hand] = out[:, wrist] + 0.08 * (out[:, wrist] - out[:, elbow]) / np.linalg.norm(
            out[:, wrist] - out[:, elbow], axis=-1, keepdims=True)
    return (out / C.CMU_UNIT_M).astype(np.float32)


def ping_pong(joints: np.ndarray, times: int = 2) -> np.ndarray:
    """A clip played forwards and backwards ``times`` times: longer, and still continuous."""
    return np.concatenate([joints] + [joints[::-1][1:], joints[1:]] * times)


@pytest.fixture
def clips(fixtures) -> dict[str, np.ndarray]:
    """A 4 s walk on planted feet (tests/test_physical.py's generator on a real standing pose) and the Bandai wave
    fixture played back and forth (6 s)."""
    from test_physical import walk

    pose = np.load(fixtures / "humanml3d" / "new_joints_012314.npy")[0].astype(np.float64)
    wave = clip_joints((fixtures / "bandai" / f"{WAVE}.bvh").read_bytes())
    return {WALK: walk(pose, (0.0, 1.2), seconds=4.0), WAVE: ping_pong(wave)}


def source(root: Path, clips: dict) -> Path:
    """A CMU joints folder: labels.tsv and joints/ with a captioned walk, a wave with a rest frame first, a long
    trial that walks then jumps, a cryptic one, a range-of-motion take, a two-subject trial, NaNs and a bad shape."""
    walk, wave = clips[WALK], clips[WAVE]
    walks = np.concatenate([walk, walk[1:] - walk[0, :1] * [1, 0, 1] + walk[-1, :1] * [1, 0, 1]])  # 8 s
    hop = np.repeat(walks[-1:], 20, axis=0)  # a still second, then three 0.3 s hops of 30 cm
    lift = np.array([0.0, 0.15, 0.3, 0.3, 0.3, 0.3, 0.15] + [0.0] * 13)[:, None, None] * [0.0, 1.0, 0.0]
    long_trial = np.concatenate([walks, hop] + [hop + lift] * 3)
    rest = as_cmu(wave)
    rest = np.concatenate([rest[:1] + np.float32(3.0 / C.CMU_UNIT_M), rest])  # a frame 3 m away: no body can do that
    trials = {
        "01_01": (as_cmu(walk), "walk, veer left", "A person walks forward and turns left."),
        "02_01": (rest, "Wave Hello", ""),
        "03_01": (as_cmu(long_trial), "walk, jump", ""),
        "04_01": (as_cmu(walk + [0.5, 0.0, 0.0]), "clean", ""),
        "05_01": (as_cmu(walk + [1.0, 0.0, 0.0]), "Range of motion", ""),
        "06_01": (as_cmu(wave), "A comforts B (2 subjects - subject B)", ""),
        "07_01": (np.full((40, 20, 3), np.nan, np.float32), "walk", ""),
        "08_01": (np.zeros((40, 19, 3), np.float32), "walk", ""),
        "09_01": (as_cmu(walk), "walk, veer left", ""),  # the same capture as 01_01
    }
    (root / "joints").mkdir(parents=True)
    rows = [HEADER]
    for name, (array, description, kit) in trials.items():
        np.save(root / "joints" / f"{name}.npy", array)
        rows.append("\t".join([name, str(len(array)), "120", "12", description, "", kit]))
    (root / "labels.tsv").write_text("\n".join(rows) + "\n", encoding="utf-8")
    return root


def prepare(src, out, capsys, *extra) -> tuple[int, str]:
    code = main(["data", "prepare", "cmu-joints", str(src), "--out", str(out), "--quiet", *extra])
    return code, capsys.readouterr().err


def test_trials_become_a_training_folder_with_every_skip_explained(clips, tmp_path, capsys):
    src, out = source(tmp_path / "cmu", clips), tmp_path / "data"
    code, err = prepare(src, out, capsys)
    assert code == 0, err
    report = json.loads((out / "prepare_report.json").read_text())
    by_trial = {t["trial"]: t for t in report["trials"]}
    assert set(by_trial) == {f"0{k}_01" for k in range(1, 10)}  # every trial prepared or listed
    reasons = {t: r.get("error", "") for t, r in by_trial.items()}
    assert "range-of-motion" in reasons["05_01"] and "subject B" in reasons["06_01"]
    assert "NaN" in reasons["07_01"] and "(40, 19, 3)" in reasons["08_01"]
    assert "the same capture as 01_01" in reasons["09_01"]
    assert all(f"skipped {t}" in err for t in ("05_01", "06_01", "07_01", "08_01"))
    # captions: the KIT sentence and the description as a sentence; a cryptic description leaves it uncaptioned
    walk_id = by_trial["01_01"]["windows"][0]["id"]
    texts = (out / "texts" / f"{walk_id}.txt").read_text().splitlines()
    assert [t.split("#")[0] for t in texts] == ["A person walks forward and turns left.",
                                               "a person walks and veers left"]
    assert "right" in (out / "texts" / f"M{walk_id}.txt").read_text()  # the mirror's caption is mirrored too
    uncaptioned = (out / "uncaptioned.txt").read_text().split()
    assert uncaptioned == sorted([w["id"] for w in by_trial["04_01"]["windows"]] +
                                 ["M" + w["id"] for w in by_trial["04_01"]["windows"]])
    # the rest frame 3 m away is dropped; what is written is plausible motion
    assert by_trial["02_01"]["leading_frames_trimmed"] == 1
    for cid in (out / "all.txt").read_text().split():
        joints = np.load(out / "new_joints" / f"{cid}.npy")
        assert implausible(joints, 20) is None, cid
        assert np.isfinite(np.load(out / "new_joint_vecs" / f"{cid}.npy")).all()
    # the long trial "walk, jump": each window is captioned with what the detectors find in it
    long_windows = by_trial["03_01"]["windows"]
    assert len(long_windows) == 2
    assert long_windows[0]["captions"] == ["a person walks"]
    assert long_windows[1]["captions"] == ["a person jumps"]  # 2 s of walking, 4 s of standing and hopping
    # splits are by subject: no subject in two splits
    subjects = {sp: {i.lstrip("M").split("_")[0] for i in (out / f"{sp}.txt").read_text().split()}
                for sp in ("train", "val", "test")}
    assert not (subjects["train"] & subjects["test"]) and not (subjects["train"] & subjects["val"])
    assert (out / "LICENSE").read_text().count("mocap.cs.cmu.edu") == 2


def test_captions_from_cmu_alone_leave_the_kit_sentences_out(clips, tmp_path, capsys):
    src = source(tmp_path / "cmu", clips)
    code, err = prepare(src, tmp_path / "all", capsys)
    assert code == 0, err
    code, err = prepare(src, tmp_path / "cmu_only", capsys, "--captions", "cmu")
    assert code == 0, err
    for name, kit_lines in (("all", 1), ("cmu_only", 0)):
        out = tmp_path / name
        walk_id = json.loads((out / "prepare_report.json").read_text())["trials"][0]["windows"][0]["id"]
        texts = [t.split("#")[0] for t in (out / "texts" / f"{walk_id}.txt").read_text().splitlines()]
        assert texts == ["A person walks forward and turns left."] * kit_lines + ["a person walks and veers left"]
        assert ("Plappert" in (out / "LICENSE").read_text()) == bool(kit_lines)
        readme = (out / "README.md").read_text()
        assert ("KIT Motion-Language sentences" in readme) == bool(kit_lines)
        assert json.loads((out / C.MANIFEST).read_text())["captions"] == ("all" if kit_lines else "cmu")
        # whose terms weights trained on it carry: CMU's alone allow commercial products; the KIT sentences' unknown
        assert terms.of_folder(out) == ([terms.CMU, terms.KIT] if kit_lines else [terms.CMU])
        assert terms.commercial_use(terms.of_folder(out)) is (None if kit_lines else True)
    # the same windows and splits either way: only the captions differ
    assert (tmp_path / "all" / "all.txt").read_text() == (tmp_path / "cmu_only" / "all.txt").read_text()


def test_the_archive_reads_like_the_folder(clips, tmp_path, capsys):
    src = source(tmp_path / "cmu-mocap-joints", clips)
    archive = tmp_path / "cmu.tar.xz"
    with tarfile.open(archive, "w:xz") as tar:
        tar.add(src, arcname="cmu-mocap-joints")
    assert prepare(src, tmp_path / "a", capsys)[0] == 0
    assert prepare(archive, tmp_path / "b", capsys)[0] == 0
    for cid in (tmp_path / "a" / "all.txt").read_text().split():
        a = np.load(tmp_path / "a" / "new_joint_vecs" / f"{cid}.npy")
        assert np.array_equal(a, np.load(tmp_path / "b" / "new_joint_vecs" / f"{cid}.npy"))
    assert (tmp_path / "a" / "train.txt").read_text() == (tmp_path / "b" / "train.txt").read_text()


@pytest.mark.parametrize("case, words", [
    ("missing", "does not exist"),
    ("garbage archive", "neither a folder nor a readable tar archive"),
    ("truncated archive", "cannot read the archive"),
    ("no labels", "holds no labels.tsv"),
    ("labels without columns", "expected the columns"),
    ("a bad frame rate", "a2p_fps"),
])
def test_a_bad_source_is_one_line_and_writes_nothing(clips, tmp_path, capsys, case, words):
    src = tmp_path / "src"
    if case == "garbage archive":
        src = tmp_path / "cmu.tar.xz"
        src.write_bytes(b"not an archive at all" * 10)
    elif case == "truncated archive":
        folder = source(tmp_path / "cmu", clips)
        src = tmp_path / "cmu.tar.xz"
        buf = io.BytesIO()
        with tarfile.open(fileobj=buf, mode="w:xz") as tar:
            tar.add(folder, arcname="cmu")
        src.write_bytes(buf.getvalue()[: len(buf.getvalue()) // 2])
    elif case == "no labels":
        (src / "joints").mkdir(parents=True)
    elif case == "labels without columns":
        source(src, clips)
        (src / "labels.tsv").write_text("trial\tframes\n01_01\t10\n")
    elif case == "a bad frame rate":
        source(src, clips)
        text = (src / "labels.tsv").read_text().replace("\t120\t12\t", "\t120\ttwelve\t", 1)
        (src / "labels.tsv").write_text(text)
    before = sorted(p.name for p in tmp_path.iterdir())
    code, err = prepare(src, tmp_path / "out", capsys)
    lines = [line for line in err.splitlines() if line.startswith("error:")]
    assert code == 2 and len(lines) == 1 and words in lines[0], err
    assert "Traceback" not in err
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # no output, no temporary folder


DESCRIPTIONS = [
    ("playground - climb, hang, swing", "a person climbs, hangs and swings on a playground"),
    ("Walk8", "a person walks in a figure eight"),
    ("JumpTurn", "a person jumps and turns"),
    ("bear (human subject)", "a person imitates a bear"),
    ("sit on stepstool, hands against chin, fidget, stand up", "a person sits on the stepstool and stands up"),
    ("jumping jacks, side twists, bend over, squats",
     "a person does jumping jacks, twists to the sides, bends over and squats"),
    ("A pulls B; B resists (2 subjects - subject B)", "a person resists"),
    ("walk; A catches keys thrown by B (2 subjects - subject A)", "a person walks and catches keys thrown by the other person"),
    ("Get Up From Ground Laying on Back", "a person gets up from lying on the back"),
    ("DrunkWalk", "a person walks like a drunk"),
]


@pytest.mark.parametrize("description, sentence", DESCRIPTIONS)
def test_descriptions_become_sentences(description, sentence):
    assert cc.trial_plan(description).sentences == [sentence]


@pytest.mark.parametrize("description", ["clean", "Story", "Lavish", "12.5 lbs", "360", "", "Alaskan vacation"])
def test_cryptic_descriptions_leave_the_trial_uncaptioned(description):
    plan = cc.trial_plan(description)
    assert plan.skip is None and plan.sentences == [] and plan.actions == []


@pytest.mark.parametrize("description", ["Range of motion", "rangeOfMotion_01", "T-Pose", "calibration",
                                         "A comforts B, puts one hand on B's shoulder (2 subjects - subject B)"])
def test_calibration_and_silent_subjects_are_skipped(description):
    assert cc.trial_plan(description).skip


def test_the_twenty_joints_land_on_their_places(clips):
    walk = clips[WAVE]
    back = C.to_smpl22(as_cmu(walk, fps_out=20.0).astype(np.float64))  # (T, 22, 3) metres
    for name in C.CMU_TO_SMPL:
        k = JOINT_NAMES.index(name)
        assert np.allclose(back[:, k], walk[:, k], atol=1e-5), name
    spine = [JOINT_NAMES.index(n) for n in ("pelvis", "spine1", "spine2", "spine3")]
    assert np.allclose(back[:, spine[1]], (2 * back[:, spine[0]] + back[:, spine[3]]) / 3, atol=1e-9)


def test_leading_frames_that_jump_impossibly_are_found(clips):
    walk = clips[WALK]
    assert leading_jump_frames(walk, 20.0) == 0
    glitch = np.concatenate([walk[:2] + [0.0, 2.0, 0.0], walk])
    assert leading_jump_frames(glitch, 20.0) == 2
    assert implausible(walk, 20.0) is None
    assert "body height" in implausible(walk * 3.0, 20.0)
    floating = walk.copy()
    floating[:1, :, 1] -= 0.5  # one frame 50 cm below the rest
    assert "below the floor" in implausible(floating, 20.0)
    fast = walk.copy()
    fast[10, 21] += 2.0  # a wrist 2 m away for one frame
    assert "m/s" in implausible(fast, 20.0)


def test_subject_splits_are_stable_and_disjoint():
    subjects = [str(s) for s in range(1, 145)]
    a, b = C.subject_splits(subjects), C.subject_splits(list(reversed(subjects)))
    assert a == b and set(a.values()) == {"train", "val", "test"}
    assert 10 <= sum(v == "test" for v in a.values()) <= 20


@pytest.mark.parametrize("text, verbs", [
    ("a person jumps over a puddle", ["jump"]),
    ("sit down", ["get_low"]),
    ("a person picks up an object from the ground", ["reach_floor"]),
    ("a person crawls on hands and knees", ["crawl"]),
    ("A human performs front crawl movements with her arms.", []),  # swimming
    ("a person mimes front crawl swimming", []),
    ("a person does a cartwheel", ["inverted"]),
    ("a person collapses to the ground", ["on_ground"]),
    ("someone gets up from the floor", ["stand_up"]),
    ("a person throws punches", []),  # punching, not throwing
    ("a person walks duck-footed", []),
    ("a person dances the lindy hop", []),
    ("a person walks forward and waves", []),
])
def test_verbs_in_reads_what_a_sentence_asks_for(text, verbs):
    from mld_core.data.verbs import verbs_in

    assert verbs_in(text) == verbs


def test_data_summary_counts_hours_per_source_split_and_verb(clips, tmp_path, capsys):
    from mld_core.data.summary import folder_summary

    assert prepare(source(tmp_path / "cmu", clips), tmp_path / "data", capsys)[0] == 0
    s = folder_summary(tmp_path / "data")
    frames = {sp: sum(len(np.load(tmp_path / "data" / "new_joint_vecs" / f"{i}.npy"))
                      for i in (tmp_path / "data" / f"{sp}.txt").read_text().split()) for sp in ("train", "val", "test")}
    for split, n in frames.items():
        assert sum(s["hours"][split].values()) == pytest.approx(n / 20 / 3600)
    jumps = [i for i in (tmp_path / "data" / "all.txt").read_text().split()
             if "jumps" in (tmp_path / "data" / "texts" / f"{i}.txt").read_text()]
    assert len(jumps) == 2  # the hopping window and its mirror
    assert sum(s["verbs"]["jump"].values()) == pytest.approx(
        sum(len(np.load(tmp_path / "data" / "new_joint_vecs" / f"{i}.npy")) for i in jumps) / 20 / 3600)
    assert main(["data", "summary", str(tmp_path / "data")]) == 0
    out = capsys.readouterr().out
    assert "| jump |" in out and "| train |" in out
    assert main(["data", "summary", str(tmp_path / "nothing")]) == 2
    assert capsys.readouterr().err.startswith("error: ")


def test_the_vocabulary_benchmark_reads_the_real_windows_of_the_chosen_split(clips, tmp_path, capsys, monkeypatch):
    """scripts/vocabulary.py --split: the real rate is read on that split's windows of the verb (all splits when it
    has too few), so a VAE can be checked on the clips it trained on as well as on the test clips."""
    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parents[1] / "scripts"))
    import vocabulary

    from mld_core.data.dataset import split_ids

    out = tmp_path / "data"
    assert prepare(source(tmp_path / "cmu", clips), out, capsys)[0] == 0
    whole = set(split_ids(out, "all"))  # every window counts as a whole trial here
    hop = [i for i in whole if not i.startswith("M") and "jumps" in (out / "texts" / f"{i}.txt").read_text()]
    assert len(hop) == 1
    home = next(sp for sp in ("train", "val", "test") if hop[0] in split_ids(out, sp))
    monkeypatch.setattr(vocabulary, "MIN_REAL", 0)  # no fallback to all splits
    for split in ("train", "val", "test"):
        _, real = vocabulary.prompts_for(out, "jump", whole, 2, split)
        assert [cid for cid, _ in real] == (hop if split == home else [])
    monkeypatch.setattr(vocabulary, "MIN_REAL", 8)  # too few real windows in a split: all splits'
    assert [cid for cid, _ in vocabulary.prompts_for(out, "jump", whole, 2, "train")[1]] == hop


def test_the_vocabulary_benchmark_asks_an_action_model_by_its_labels(clips, tmp_path, capsys, monkeypatch):
    """scripts/vocabulary.py on an action-conditioned model: each verb is generated from its action label (one
    wording, "action", seeds x 1 takes); a verb the model has no label for is refused in one line."""
    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parents[1] / "scripts"))
    import vocabulary

    from mld_core.testing import tiny_model

    out = tmp_path / "data"
    assert prepare(source(tmp_path / "cmu", clips), out, capsys)[0] == 0
    model = tiny_model(tmp_path / "act", cond="action", actions=("jump", "walk"))
    capsys.readouterr()
    argv = ["--data", str(out), "--model", str(model), "--seeds", "2", "--seconds", "2", "--threads", "1"]
    assert vocabulary.main(argv + ["--verbs", "jump", "--json", str(tmp_path / "v.json")]) == 0
    assert "(action labels)" in capsys.readouterr().out
    rows = json.loads((tmp_path / "v.json").read_text())["rows"]
    assert [(r["verb"], r["wording"], r["prompts"], r["takes"]) for r in rows] == [("jump", "action", ["jump"], 2)]
    assert vocabulary.main(argv + ["--verbs", "jump,kick"]) == 2
    assert capsys.readouterr().err.strip() == "error: this action-conditioned model has no label kick"


def test_the_vocabulary_benchmark_measures_with_the_verb_redraws_it_is_given(clips, tmp_path, capsys, monkeypatch):
    """scripts/vocabulary.py --verb-redraws N: each take records its draw, the JSON the count and the share drawn
    again; 0 is the model alone (every take its seed's first draw); a count out of range is one line, exit 2."""
    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parents[1] / "scripts"))
    import vocabulary

    from mld_core.eval import physical
    from mld_core.testing import tiny_model

    out = tmp_path / "data"
    assert prepare(source(tmp_path / "cmu", clips), out, capsys)[0] == 0
    model = tiny_model(tmp_path / "text")
    argv = ["--data", str(out), "--model", str(model), "--seeds", "2", "--seconds", "2", "--threads", "1",
            "--verbs", "jump"]
    calls = itertools.count()
    # per prompt, 2 seeds: the two first draws miss the jump, the two redraws (draw 3: after 2 side redraws) show it,
    # and so do the two takes then scored
    monkeypatch.setattr(physical, "shows", lambda joints, verb, fps=20.0, result=None: next(calls) % 6 >= 2)
    assert vocabulary.main(argv + ["--verb-redraws", "2", "--json", str(tmp_path / "v.json")]) == 0
    report = json.loads((tmp_path / "v.json").read_text())
    assert report["verb_redraws"] == 2 and report["redrawn"] == 1.0 and report["redraw_s"] > 0
    assert {t["draw"] for t in report["takes"]} == {3} and all(r["pass"] == 1.0 for r in report["rows"] if r["takes"])
    assert report["capped_cells"] == 0.0  # no real rate for this tiny folder's jumps: no cell counts
    rows = [{"ratio": 1.5}, {"ratio": 0.25}, {"ratio": float("nan")}, {"ratio": 0.5}]  # capped, kept, uncounted, kept
    assert vocabulary.capped_cells(rows) == pytest.approx(1.75)
    assert "verb redraws 2" in capsys.readouterr().out
    monkeypatch.setattr(physical, "shows", lambda joints, verb, fps=20.0, result=None: False)
    assert vocabulary.main(argv + ["--verb-redraws", "0", "--json", str(tmp_path / "v.json")]) == 0
    report = json.loads((tmp_path / "v.json").read_text())
    assert report["verb_redraws"] == 0 and {t["draw"] for t in report["takes"]} == {0} and report["redraw_s"] == 0
    assert "the 3 cells, each capped at 1: 0.00" in capsys.readouterr().out
    assert vocabulary.main(argv + ["--verb-redraws", "9"]) == 2
    assert capsys.readouterr().err.strip() == "error: --verb-redraws must be between 0 and 8, got 9"


def test_the_vocabulary_benchmark_reports_how_far_takes_sink_or_hover(clips, tmp_path, capsys, monkeypatch):
    """scripts/vocabulary.py: each take's lowest joint (cm) and each row's median, beside the real windows' median;
    a model whose repair puts takes on the floor has every take's lowest joint at 0."""
    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parents[1] / "scripts"))
    import vocabulary

    from mld_core.data.dataset import split_ids
    from mld_core.testing import tiny_model

    out = tmp_path / "data"
    assert prepare(source(tmp_path / "cmu", clips), out, capsys)[0] == 0
    model = tiny_model(tmp_path / "text")
    argv = ["--data", str(out), "--model", str(model), "--seeds", "3", "--seconds", "2", "--threads", "1",
            "--verbs", "jump", "--json", str(tmp_path / "v.json")]
    lows = {}
    for on_floor in (False, True):
        config = json.loads((model / "config.json").read_text())
        config["repair"]["on_floor"] = on_floor
        (model / "config.json").write_text(json.dumps(config))
        assert vocabulary.main(argv) == 0
        report = json.loads((tmp_path / "v.json").read_text())
        lows[on_floor] = [t["lowest_cm"] for t in report["takes"]]
        for row in (r for r in report["rows"] if r["takes"]):
            mine = [t["lowest_cm"] for t in report["takes"] if t["wording"] == row["wording"]]
            assert row["lowest_cm"] == pytest.approx(np.median(mine), abs=0.01)
            floats = [t["float"] for t in report["takes"] if t["wording"] == row["wording"]]
            assert row["float"] == pytest.approx(np.mean(floats), abs=1e-3) and 0.0 <= row["float"] <= 1.0
            assert np.isfinite(row["real_lowest_cm"]) == (row["real_windows"] > 0)
    assert lows[True] == pytest.approx([0.0] * len(lows[True]), abs=0.01)
    assert max(abs(v) for v in lows[False]) > 1.0  # the tiny model's noise is nowhere near the floor
    assert "low cm" in capsys.readouterr().out
    real = [(cid, []) for cid in split_ids(out, "all")]  # the prepared clips: each one's lowest joint on the floor
    low, flt = vocabulary.real_floor(vocabulary.real_joints(out, real))
    assert low == pytest.approx(0.0, abs=0.01) and 0.0 <= flt <= 1.0
    assert all(np.isnan(vocabulary.real_floor([])))


def test_the_vocabulary_benchmark_reads_real_windows_through_a_vae(clips, tmp_path, capsys, monkeypatch):
    """scripts/vocabulary.py --vae-recon: per verb, the real windows' pass rate and median check value, before and
    after the model's VAE (the ceiling of a denoiser on it); a VAE-only folder is enough."""
    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parents[1] / "scripts"))
    import vocabulary

    from mld_core.data.dataset import split_ids
    from mld_core.eval import physical
    from mld_core.testing import tiny_model

    out = tmp_path / "data"
    assert prepare(source(tmp_path / "cmu", clips), out, capsys)[0] == 0
    model = tiny_model(tmp_path / "tiny")
    monkeypatch.setattr(vocabulary, "whole_trial_windows", lambda data: split_ids(data, "all"))  # every window
    capsys.readouterr()
    argv = ["--data", str(out), "--model", str(model), "--vae-recon", "--verbs", "jump", "--threads", "1"]
    assert vocabulary.main(argv + ["--json", str(tmp_path / "v.json")]) == 0
    assert "median value" in capsys.readouterr().out
    (row,) = json.loads((tmp_path / "v.json").read_text())["rows"]
    hop = [i for i in (out / "all.txt").read_text().split()
           if not i.startswith("M") and "jumps" in (out / "texts" / f"{i}.txt").read_text()]
    assert row["real_windows"] == len(hop) == 1  # too few in the test split: all splits'
    real_ok, real_value = physical.verb_result(np.load(out / "new_joints" / f"{hop[0]}.npy"), "jump")
    assert real_ok and real_value > 0  # the hop flies
    assert (row["real"], row["real_median_value"]) == (1.0, pytest.approx(real_value))
    assert row["vae_recon"] in (0.0, 1.0) and np.isfinite(row["vae_recon_median_value"])


def test_the_vocabulary_benchmark_measures_a_draft_with_its_own_verb_redraws(clips, tmp_path, capsys, monkeypatch):
    """scripts/vocabulary.py --draft without --verb-redraws: the Draft's own count (config draft.verb_redraws), not
    the Final's."""
    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parents[1] / "scripts"))
    import vocabulary

    from mld_core.eval import physical
    from mld_core.testing import tiny_model

    out = tmp_path / "data"
    assert prepare(source(tmp_path / "cmu", clips), out, capsys)[0] == 0
    model = tiny_model(tmp_path / "text", draft=True)
    config = json.loads((model / "config.json").read_text())
    config["verb_redraws"], config["draft"]["verb_redraws"] = 0, 1
    (model / "config.json").write_text(json.dumps(config))
    argv = ["--data", str(out), "--model", str(model), "--seeds", "2", "--seconds", "2", "--threads", "1",
            "--verbs", "jump", "--json", str(tmp_path / "v.json")]
    monkeypatch.setattr(physical, "shows", lambda joints, verb, fps=20.0, result=None: False)  # every draw misses
    assert vocabulary.main(argv + ["--draft"]) == 0
    report = json.loads((tmp_path / "v.json").read_text())
    assert report["verb_redraws"] == 1 and report["redraw_s"] > 0
    assert "(Draft)" in capsys.readouterr().out
    assert vocabulary.main(argv) == 0  # the Final: the model's 0
    report = json.loads((tmp_path / "v.json").read_text())
    assert report["verb_redraws"] == 0 and report["redraw_s"] == 0
