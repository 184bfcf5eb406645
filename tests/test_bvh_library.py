"""``data prepare bvh``: any BVH folder with captions -> a HumanML3D-format folder (mld_core.data.bvh_library)."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from mld_core.cli import main
from mld_core.data import terms
from mld_core.data import bvh_library as bl
from mld_core.data.bandai import PrepareError, clip_joints
from mld_core.rig.bone_maps import detect_bone_map

WALK = "dataset-2_walk-turn-left_normal_027"
WAVE = "dataset-2_wave-right-hand_normal_026"


@pytest.fixture
def library(fixtures, tmp_path):
    src = tmp_path / "lib"
    (src / "walks").mkdir(parents=True)
    shutil.copy(fixtures / "bandai" / f"{WALK}.bvh", src / "walks" / "turning_walk.bvh")
    shutil.copy(fixtures / "bandai" / f"{WAVE}.bvh", src / "wave.bvh")
    (src / "wave.txt").write_text("a person waves the right hand\nsomeone waves with the right hand\n")
    (src / "broken.bvh").write_text("HIERARCHY\nROOT Thing\n{\n OFFSET 0 0 0\n CHANNELS 3 Xposition Yposition "
                                    "Zposition\n End Site\n {\n OFFSET 0 1 0\n }\n}\nMOTION\nFrames: 1\n"
                                    "Frame Time: 0.0333333\n0 0 0\n")
    return src


def _run(src, out, *extra):
    return main(["data", "prepare", "bvh", str(src), "--out", str(out), *map(str, extra)])


def test_a_library_becomes_a_training_folder(library, tmp_path, capsys):
    out = tmp_path / "out"
    assert _run(library, out, "--caption-template", "a person {name}") == 0
    assert "2 of 3 files mapped (1 skipped" in capsys.readouterr().out
    report = json.loads((out / "prepare_report.json").read_text())
    by_file = {f["file"]: f for f in report["files"]}
    assert "cannot map the skeleton" in by_file["broken.bvh"]["error"]
    walk = by_file["walks/turning_walk.bvh"]
    assert (walk["skeleton"], walk["units"], walk["up"], walk["fps"]) == ("bandai", "cm", "y", 30.0)
    wave = by_file["wave.bvh"]
    texts = (out / "texts" / f"{wave['segments'][0]['id']}.txt").read_text().splitlines()
    assert [t.split("#")[0] for t in texts] == ["a person waves the right hand", "someone waves with the right hand"]
    mirrored = (out / "texts" / f"M{wave['segments'][0]['id']}.txt").read_text()
    assert "waves the left hand" in mirrored
    walk_text = (out / "texts" / f"{walk['segments'][0]['id']}.txt").read_text()
    assert walk_text.startswith("a person turning walk#")
    ids = (out / "all.txt").read_text().split()
    assert len(ids) == 4 and all((out / "new_joint_vecs" / f"{i}.npy").is_file() for i in ids)
    features = np.load(out / "new_joint_vecs" / f"{walk['segments'][0]['id']}.npy")
    reference = clip_joints((library / "walks" / "turning_walk.bvh").read_bytes())
    assert features.shape == (len(reference) - 1, 263)  # the same frames as the Bandai reader gives
    assert json.loads((out / "actions.json").read_text())["clips"][walk["segments"][0]["id"]] == "walks"
    assert terms.of_folder(out) == [{"name": f"BVH folder {library.name}", "licence": "its owner's",
                                     "commercial": None}]


def test_a_library_records_the_terms_its_owner_gives(library, tmp_path, capsys):
    out = tmp_path / "out"
    assert _run(library, out, "--caption-template", "a person {name}", "--licence", "Studio X, all rights reserved",
                "--commercial-use", "yes") == 0
    assert terms.of_folder(out) == [{"name": f"BVH folder {library.name}", "licence": "Studio X, all rights reserved",
                                     "commercial": True}]
    assert terms.commercial_use(terms.of_folder(out)) is True
    capsys.readouterr()
    assert _run(library, tmp_path / "bad", "--caption-template", "a person {name}", "--licence", " ") == 2
    err = capsys.readouterr().err
    assert "--licence" in err and len(err.strip().splitlines()) == 1 and not (tmp_path / "bad").exists()
    for bad in (bl.LibraryOptions(caption_template="a person {name}", licence=""),  # the library's own API too
                bl.LibraryOptions(caption_template="a person {name}", commercial="yes")):
        with pytest.raises(PrepareError):
            bl.prepare_bvh(library, tmp_path / "bad", bad)
        assert not (tmp_path / "bad").exists()


def test_caption_table_spans_cut_segments(library, tmp_path):
    table = tmp_path / "captions.tsv"
    table.write_text("file\tcaption\tstart_s\tend_s\nwalks/turning_walk.bvh\ta person walks and turns left\t0\t2.5\n"
                     "turning_walk\tsomeone turns to the left while walking\t0\t2.5\nwave.bvh\ta wave\t\t\n")
    out = tmp_path / "out"
    assert _run(library, out, "--captions", table) == 0
    report = {f["file"]: f for f in json.loads((out / "prepare_report.json").read_text())["files"]}
    segs = report["walks/turning_walk.bvh"]["segments"]
    assert [(s["start"], s["end"]) for s in segs] == [(0, 40)]  # 2.5 s asked; the clip has 40 frames at 20 fps
    assert segs[0]["captions"] == ["a person walks and turns left", "someone turns to the left while walking"]


def test_bad_input_is_one_line_and_writes_nothing(library, tmp_path, capsys):
    from test_reliability import refused

    out = tmp_path / "out"
    bad = tmp_path / "bad.csv"
    bad.write_text("wave.bvh,a wave,soon,later\n")
    prepare = ["data", "prepare", "bvh"]
    refused(prepare + [library, "--out", out, "--captions", bad], tmp_path, capsys, "must be numbers")
    refused(prepare + [library, "--out", out, "--units", "furlongs"], tmp_path, capsys, "--units must be")
    refused(prepare + [library, "--out", out, "--units", "inf"], tmp_path, capsys, "--units must be")
    refused(prepare + [library, "--out", out, "--captions", tmp_path / "none.csv"], tmp_path, capsys,
            "cannot read --captions")
    refused(prepare + [library, "--out", out, "--captions", library], tmp_path, capsys, "cannot read --captions")
    refused(prepare + [library, "--out", out, "--bone-map", tmp_path / "none.json", "--caption-template", "x {name}"],
            tmp_path, capsys, "cannot use --bone-map")
    refused(prepare + [library / "walks", "--out", out], tmp_path, capsys, "no caption")
    refused(prepare + [library, "--out", library / "inside", "--caption-template", "x {name}"], tmp_path, capsys,
            "must not be inside")


def test_up_axis_units_and_tpose(fixtures):
    joints = clip_joints((fixtures / "bandai" / f"{WALK}.bvh").read_bytes())  # (T, 22, 3) metres, Y up
    z_up = np.stack([joints[..., 0], -joints[..., 2], joints[..., 1]], axis=-1)
    assert bl.detect_up(joints) == "y" and bl.detect_up(z_up) == "z"
    np.testing.assert_allclose(bl.to_y_up(z_up, "z"), joints, atol=1e-12)
    for unit in ("m", "cm", "mm", "in"):
        assert bl.detect_units(joints / bl.UNITS[unit]) == (unit, bl.UNITS[unit])
    name, scale = bl.detect_units(joints / 0.0564)  # CMU ASF units: no named unit fits
    assert abs(scale - 0.0564) < 0.01 and "from the leg length" in name
    tpose = joints[0].copy()
    for side, sign in (("left", 1), ("right", -1)):
        s, e, w = (bl._J[f"{side}_{j}"] for j in ("shoulder", "elbow", "wrist"))
        tpose[e] = tpose[s] + [sign * 0.26, 0, 0]
        tpose[w] = tpose[s] + [sign * 0.53, 0, 0]
    assert bl.is_tpose(tpose) and not bl.is_tpose(joints[0])
    assert bl.leading_tpose_frames(np.concatenate([tpose[None], tpose[None], joints]), 30) == 2
    assert bl.leading_tpose_frames(joints, 30) == 0


def test_a_rest_frame_before_the_motion_is_trimmed_and_the_take_stands_on_the_floor(fixtures, tmp_path):
    """A first frame in another place and pose (the skeleton's rest pose) jumps into frame 1 faster than a body can move:
    it is dropped, and the floor is the take's own."""
    text = (fixtures / "bandai" / f"{WALK}.bvh").read_text()
    head, motion = text.split("MOTION")
    lines = motion.strip().splitlines()
    first = lines[2].split()
    rest = " ".join([first[0], str(float(first[1]) + 300.0), first[2]] + ["0"] * (len(first) - 3))  # 3 m up
    frames = int(lines[0].split()[1])
    src = tmp_path / "lib"
    src.mkdir()
    (src / "walk.bvh").write_text(head + "MOTION\n" + f"Frames: {frames + 1}\n" + lines[1] + "\n" + rest + "\n"
                                  + "\n".join(lines[2:]) + "\n")
    summary = bl.prepare_bvh(src, tmp_path / "out", bl.LibraryOptions(caption_template="a person walks", up="y"))
    assert summary["leading_frames_trimmed"] == {"walk.bvh": 1}
    feet = np.load(next((tmp_path / "out" / "new_joints").glob("walk*.npy")))[:, [7, 8, 10, 11], 1].min(axis=1)
    assert np.median(feet) < 0.05  # standing on its own floor, not 3 m below a stray frame's


def test_segments_are_at_most_the_model_length():
    cap = bl.Caption("x")
    assert bl.segments(500, cap, 20, 2.0, 9.8) == [(0, 167), (167, 333), (333, 500)]
    assert bl.segments(30, cap, 20, 2.0, 9.8) == []
    assert bl.segments(500, bl.Caption("x", 1.0, 4.0), 20, 2.0, 9.8) == [(20, 80)]


def test_iclone_and_cmu_asf_skeletons_map():
    iclone = {"CC_Base_BoneRoot": None, "CC_Base_Hip": "CC_Base_BoneRoot", "CC_Base_Pelvis": "CC_Base_Hip",
              "CC_Base_Waist": "CC_Base_Hip", "CC_Base_Spine01": "CC_Base_Waist",
              "CC_Base_Spine02": "CC_Base_Spine01", "CC_Base_NeckTwist01": "CC_Base_Spine02",
              "CC_Base_Head": "CC_Base_NeckTwist01"}
    for s in ("L", "R"):
        iclone.update({f"CC_Base_{s}_Thigh": "CC_Base_Pelvis", f"CC_Base_{s}_Calf": f"CC_Base_{s}_Thigh",
                       f"CC_Base_{s}_Foot": f"CC_Base_{s}_Calf", f"CC_Base_{s}_ToeBaseShareBone": f"CC_Base_{s}_Foot",
                       f"CC_Base_{s}_ToeBase": f"CC_Base_{s}_Foot", f"CC_Base_{s}_Clavicle": "CC_Base_Spine02",
                       f"CC_Base_{s}_Upperarm": f"CC_Base_{s}_Clavicle",
                       f"CC_Base_{s}_Forearm": f"CC_Base_{s}_Upperarm", f"CC_Base_{s}_Hand": f"CC_Base_{s}_Forearm"})
    found = detect_bone_map(list(iclone), list(iclone.values()))
    assert not found.missing
    j = found.bone_map.joints
    assert (j["pelvis"], j["spine1"], j["spine3"], j["head"]) == ("CC_Base_Pelvis", "CC_Base_Waist",
                                                                  "CC_Base_Spine02", "CC_Base_Head")
    assert j["left_foot"] == "CC_Base_L_ToeBase"
    asf = ["hip", "lhipjoint", "lfemur", "ltibia", "lfoot", "ltoes", "rhipjoint", "rfemur", "rtibia", "rfoot",
           "rtoes", "lowerback", "upperback", "thorax", "lowerneck", "upperneck", "head", "lclavicle", "lhumerus",
           "lradius", "lwrist", "rclavicle", "rhumerus", "rradius", "rwrist"]
    found = detect_bone_map(asf)
    assert found.source == "cmu_asf" and not found.missing


def test_the_cmu_subsets_prepare(shared, tmp_path):
    import tarfile

    archive = shared / "datasets" / "cmu-subsets.tar.xz"
    if not archive.is_file():
        pytest.skip(f"needs {archive}")
    with tarfile.open(archive) as tar:
        tar.extractall(tmp_path, filter="data")
    summary = bl.prepare_bvh(tmp_path / "cmu-subsets", tmp_path / "out",
                             bl.LibraryOptions(caption_template="a person moves {folder}"))
    assert summary["files"] == 163 and summary["mapped"] >= 145
    assert all("shorter than" in why or "implausible" in why for why in summary["skipped"].values())
    # Many clips start with a rest or calibration frame that jumps into the motion: trimmed and counted per file.
    assert len(summary["leading_frames_trimmed"]) >= 50
    # Nothing implausible is written (the floor from a stray frame once left whole takes floating above it).
    from mld_core.data.take_checks import implausible

    for cid in (tmp_path / "out" / "all.txt").read_text().split():
        assert implausible(np.load(tmp_path / "out" / "new_joints" / f"{cid}.npy"), 20) is None, cid


def _blender_take(fixtures, name="Walk_Tired.001", drop=("spine2", "left_collar", "right_collar")):
    from mld_core.data.action_export import Take

    joints = np.load(fixtures / "rigs" / "source_takes.npz")[f"{WALK}_joints"].astype(np.float64)  # model axes
    joints = np.concatenate([joints, joints[::-1]])  # 4 s: there and back again, continuous
    blender = np.stack([joints[..., 0], -joints[..., 2], joints[..., 1]], axis=-1)  # Z up, facing -Y
    for joint in drop:  # joints the rig's bone map does not have
        blender[:, bl._J[joint]] = np.nan
    return Take(name, blender, 20.0), joints


def test_actions_export_as_a_library_that_prepares(fixtures, tmp_path, capsys):
    from mld_core.data.action_export import Take, export_takes
    from mld_core.motion.features import canonical_joints

    take, joints = _blender_take(fixtures, drop=())
    short = Take("Blink", take.joints[:20], 20.0)
    noname = Take("123", take.joints, 20.0)
    result = export_takes([take, short, noname, Take("Wave", take.joints, 20.0, ["a person waves\n", " "])],
                          tmp_path / "lib")
    assert result["written"] == ["Walk_Tired_001.bvh", "Wave.bvh"]
    assert "shorter than 2 s" in result["skipped"]["Blink"] and "no caption" in result["skipped"]["123"]
    rows = (tmp_path / "lib" / "captions.csv").read_text().splitlines()
    assert rows == ["file,caption", "Walk_Tired_001.bvh,a person walk tired", "Wave.bvh,a person waves"]
    assert _run(tmp_path / "lib", tmp_path / "out", "--captions", tmp_path / "lib" / "captions.csv") == 0
    report = {f["file"]: f for f in json.loads((tmp_path / "out" / "prepare_report.json").read_text())["files"]}
    assert report["Walk_Tired_001.bvh"]["skeleton"] == "canonical"
    seg = report["Walk_Tired_001.bvh"]["segments"][0]["id"]
    back = np.load(tmp_path / "out" / "new_joints" / f"{seg}.npy")
    expected = canonical_joints(joints)[:len(back)]  # two feature extractions: one frame fewer each
    assert np.abs(back - expected).max() < 0.01  # the take comes back within 1 cm
    (tmp_path / "a_file").write_text("x")
    with pytest.raises(Exception, match="is a file"):
        export_takes([take], tmp_path / "a_file")
    before = sorted(p.name for p in (tmp_path / "lib").iterdir())
    with pytest.raises(Exception, match="already exists"):
        export_takes([take], tmp_path / "lib")
    assert sorted(p.name for p in (tmp_path / "lib").iterdir()) == before


def test_joints_a_bone_map_lacks_are_filled_in(fixtures, tmp_path):
    from mld_core.data.action_export import export_takes

    take, joints = _blender_take(fixtures)  # no spine2, no collars
    export_takes([take], tmp_path / "lib")
    assert _run(tmp_path / "lib", tmp_path / "out", "--captions", tmp_path / "lib" / "captions.csv") == 0
    back = np.load(next((tmp_path / "out" / "new_joints").glob("W*.npy")))
    legs = [bl._J[n] for n in ("pelvis", "left_knee", "right_knee", "left_ankle", "right_ankle", "left_foot")]
    from mld_core.motion.features import canonical_joints

    assert np.abs(back[:, legs] - canonical_joints(joints)[:len(back), legs]).max() < 0.02
    spine2 = back[:, bl._J["spine2"]]
    between = 0.5 * (back[:, bl._J["spine1"]] + back[:, bl._J["spine3"]])
    assert np.linalg.norm(spine2 - between, axis=-1).max() < 0.05  # filled halfway up the spine
