"""BVH reading, forward kinematics, writing, and clear errors on malformed files."""

from __future__ import annotations

import numpy as np
import pytest

from mld_core.motion.bvh import (
    BVHError,
    euler_to_matrix,
    matrix_to_euler,
    parse_bvh,
    quat_to_matrix,
    read_bvh,
    write_bvh,
)

# A 3-joint chain: root at its channel position, a child 10 along X, a grandchild 5 along X.
CHAIN = """HIERARCHY
ROOT root
{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
  JOINT mid
  {
    OFFSET 10 0 0
    CHANNELS 3 Zrotation Xrotation Yrotation
    JOINT tip
    {
      OFFSET 5 0 0
      CHANNELS 3 Zrotation Xrotation Yrotation
      End Site
      {
        OFFSET 1 0 0
      }
    }
  }
}
MOTION
Frames: 2
Frame Time: 0.05
0 0 0 0 0 0 0 0 0 0 0 0
1 2 3 90 0 0 0 0 90 0 0 0
"""


def test_fk_hand_computed_chain():
    bvh = parse_bvh(CHAIN)
    assert bvh.names == ["root", "mid", "tip"]
    assert bvh.parents.tolist() == [-1, 0, 1]
    assert bvh.num_frames == 2 and bvh.fps == pytest.approx(20.0)
    assert np.allclose(bvh.end_sites[2], [1, 0, 0])
    pos = bvh.joint_positions()
    assert pos.shape == (2, 3, 3)
    # Frame 0: rest pose along +X.
    np.testing.assert_allclose(pos[0], [[0, 0, 0], [10, 0, 0], [15, 0, 0]], atol=1e-12)
    # Frame 1: root at (1,2,3) turned 90 deg about Z: +X -> +Y, so mid = (1, 12, 3).
    # mid turns 90 deg about its local Y; in root space local +X -> -Z, then root's Rz keeps Z: tip = mid + (0,0,-5).
    np.testing.assert_allclose(pos[1], [[1, 2, 3], [1, 12, 3], [1, 12, -2]], atol=1e-12)


def test_rotation_order_follows_channel_order():
    # ZXY means R = Rz @ Rx @ Ry: check against explicit products.
    a = np.array([30.0, -20.0, 50.0])
    r = euler_to_matrix(a, "ZXY")
    rz, rx, ry = (euler_to_matrix(np.array([v]), ax) for v, ax in zip(a, "ZXY"))
    np.testing.assert_allclose(r, rz @ rx @ ry, atol=1e-12)
    # A quarter turn about Z takes +X to +Y (right-handed).
    np.testing.assert_allclose(euler_to_matrix(np.array([90.0]), "Z") @ [1, 0, 0], [0, 1, 0], atol=1e-12)


@pytest.mark.parametrize("order", ["XYZ", "XZY", "YXZ", "YZX", "ZXY", "ZYX"])
def test_matrix_to_euler_round_trip(order):
    rng = np.random.default_rng(1)
    angles = rng.uniform(-179, 179, size=(200, 3))
    angles[:, 1] = rng.uniform(-89, 89, size=200)
    angles[:3, 1] = [90, -90, 90]  # gimbal lock: angles differ, the matrix must not
    m = euler_to_matrix(angles, order)
    back = matrix_to_euler(m, order)
    np.testing.assert_allclose(euler_to_matrix(back, order), m, atol=1e-9)
    np.testing.assert_allclose(back[3:], angles[3:], atol=1e-9)


def _random_skeleton(rng, F=7):
    names = ["hips", "spine", "head", "l_leg", "l_foot", "r_leg"]
    parents = np.array([-1, 0, 1, 0, 3, 0])
    offsets = rng.normal(size=(6, 3)) * 10
    root = rng.normal(size=(F, 3)) * 50
    quats = rng.normal(size=(F, 6, 4))
    return names, parents, offsets, root, quats


@pytest.mark.parametrize("order", ["ZXY", "XYZ", "YZX"])
def test_write_read_write_round_trip(tmp_path, order):
    rng = np.random.default_rng(0)
    names, parents, offsets, root, quats = _random_skeleton(rng)
    path = tmp_path / "a.bvh"
    write_bvh(path, names, parents, offsets, root, quats, 1 / 30, order=order, end_sites={2: np.array([0, 7.0, 0])})
    bvh = read_bvh(path)
    assert bvh.names == names
    assert bvh.parents.tolist() == parents.tolist()
    assert bvh.frame_time == pytest.approx(1 / 30)
    assert bvh.channels[0][3:] == tuple(f"{a}rotation" for a in order)
    np.testing.assert_allclose(bvh.offsets, offsets, atol=1e-6)
    np.testing.assert_allclose(bvh.root_positions(), root, atol=1e-6)
    np.testing.assert_allclose(bvh.local_rotations(), quat_to_matrix(quats), atol=1e-6)
    np.testing.assert_allclose(bvh.end_sites[2], [0, 7, 0])
    assert sorted(bvh.end_sites) == [2, 4, 5]
    # Writing what was read gives a file that reads back to the same values.
    path2 = tmp_path / "b.bvh"
    write_bvh(path2, bvh.names, bvh.parents, bvh.offsets, bvh.root_positions(), bvh.local_rotations(),
              bvh.frame_time, order=order, end_sites=bvh.end_sites)
    again = read_bvh(path2)
    np.testing.assert_allclose(again.motion, bvh.motion, atol=2e-6)
    np.testing.assert_allclose(again.joint_positions(), bvh.joint_positions(), atol=1e-4)
    assert not list(tmp_path.glob("*.tmp"))


def test_write_rejects_bad_input(tmp_path):
    rng = np.random.default_rng(0)
    names, parents, offsets, root, quats = _random_skeleton(rng)
    with pytest.raises(ValueError):
        write_bvh(tmp_path / "x.bvh", names, parents, offsets, root[:-1], quats, 1 / 30)
    with pytest.raises(ValueError):
        write_bvh(tmp_path / "x.bvh", names, parents, offsets, root, quats, 1 / 30, order="XXY")
    bad = quats.copy()
    bad[0, 0, 0] = np.nan
    with pytest.raises(ValueError):
        write_bvh(tmp_path / "x.bvh", names, parents, offsets, root, bad, 1 / 30)
    assert not list(tmp_path.iterdir())


def test_crlf_tabs_scientific_and_three_channels():
    text = (
        "HIERARCHY\r\n"
        "ROOT\tHips\r\n{\r\n\tOFFSET\t0\t0\t0\r\n"
        "\tCHANNELS 6 Xposition Yposition Zposition Xrotation Yrotation Zrotation\r\n"
        "\tJOINT Leg{\r\n\t\tOFFSET 0 -1.5e+1 0\r\n\t\tCHANNELS 3 Xrotation Yrotation Zrotation\r\n"
        "\t\tEnd Site\r\n\t\t{\r\n\t\t\tOFFSET 0 -1E1 0\r\n\t\t}\r\n\t}\r\n}\r\n"
        "MOTION\r\nFrames:\t2\r\nFrame Time:\t3.3333e-02\r\n"
        "1.0e0\t2E+0 3 0 0 0\t90 0 0\r\n"
        "0 0 0 0 0 0 0 0 0\r\n"
    )
    bvh = parse_bvh(text)
    assert bvh.names == ["Hips", "Leg"]
    assert bvh.channels[1] == ("Xrotation", "Yrotation", "Zrotation")
    assert bvh.frame_time == pytest.approx(0.033333)
    np.testing.assert_allclose(bvh.offsets[1], [0, -15, 0])
    pos = bvh.joint_positions()
    np.testing.assert_allclose(pos[0], [[1, 2, 3], [1, -13, 3]], atol=1e-12)


GOOD_MOTION = CHAIN.split("MOTION")[0]


@pytest.mark.parametrize(
    "text, line, words",
    [
        ("hello world\nthis is not a bvh\n", 1, "not a BVH"),
        ("", 1, "not a BVH"),
        (GOOD_MOTION, 21, "no MOTION"),
        (GOOD_MOTION + "MOTION\nFrames: 3\nFrame Time: 0.05\n" + "0 " * 12 + "\n" + "0 " * 12 + "\n", 25, "truncated"),
        (GOOD_MOTION + "MOTION\nFrames: 2\nFrame Time: 0.05\n" + "0 " * 12 + "\n" + "0 " * 11 + "\n", 25, "11 values"),
        (GOOD_MOTION + "MOTION\nFrames: 2\nFrame Time: 0.05\n" + "0 " * 12 + "\n" + "0 " * 13 + "\n", 25, "13 values"),
        (GOOD_MOTION + "MOTION\nFrames: 2\nFrame Time: 0.05\n" + "0 " * 12 + "\n" + "0 " * 11 + "nan\n", 25, "non-finite"),
        (GOOD_MOTION + "MOTION\nFrames: 2\nFrame Time: 0.05\n" + "0 " * 11 + "inf\n" + "0 " * 12 + "\n", 24, "non-finite"),
        (GOOD_MOTION + "MOTION\nFrames: 2\nFrame Time: 0.05\n" + "0 " * 11 + "1.2.3\n" + "0 " * 12 + "\n", 24, "unreadable"),
        (GOOD_MOTION + "MOTION\nFrames: 0\nFrame Time: 0.05\n", 22, "no frames"),
        (GOOD_MOTION + "MOTION\nFrames: two\nFrame Time: 0.05\n", 22, "frame count"),
        (GOOD_MOTION + "MOTION\nFrames: 1\nFrame Time: -1\n" + "0 " * 12 + "\n", 23, "frame time"),
        (GOOD_MOTION + "MOTION\nFrames: 1\n", 23, "Frame Time"),
        (GOOD_MOTION + "MOTION\nFrames: 1\nFrame Time: 0.05\n" + "0 " * 12 + "\n" + "0 " * 12 + "\n", 25, "more frame"),
        (CHAIN.replace("OFFSET 10 0 0", "OFFSET 10 zero 0"), 8, "unreadable number"),
        (CHAIN.replace("CHANNELS 3 Zrotation Xrotation Yrotation\n    JOINT", "CHANNELS 3 Zrotation Wrotation Yrotation\n    JOINT"), 9, "unknown channel"),
        (CHAIN.replace("      End Site", "      End Sight"), 14, "End Site"),
        (CHAIN.replace("  }\n}\nMOTION", "  }\nMOTION"), 19, "unexpected end"),
        (CHAIN.replace("JOINT mid", "BONE mid"), 6, "unexpected 'BONE'"),
    ],
)
def test_malformed_files_raise_bvherror_with_line(text, line, words):
    with pytest.raises(BVHError) as info:
        parse_bvh(text, source="bad.bvh")
    err = info.value
    assert isinstance(err, ValueError)
    assert err.line == line, str(err)
    assert words.lower() in str(err).lower()
    assert f"bad.bvh:{line}" in str(err)


def test_read_bvh_names_the_file(tmp_path):
    p = tmp_path / "broken.bvh"
    p.write_bytes(b"\x00\x01\x02 binary junk")
    with pytest.raises(BVHError, match="broken.bvh:1"):
        read_bvh(p)


def test_real_bandai_fixture_parses(fixtures):
    files = sorted((fixtures / "bandai").rglob("*.bvh"))
    if not files:
        pytest.skip("no Bandai fixture files")
    for f in files:
        bvh = read_bvh(f)
        assert len(bvh.names) == 22 and all(len(c) == 6 for c in bvh.channels)
        pos = bvh.joint_positions()
        hips = pos[:, bvh.index("Hips")]
        head = pos[:, bvh.index("Head")]
        # Centimetres, Y up: the head is well above the hips for a standing performer.
        assert np.all(head[:, 1] - hips[:, 1] > 30)
        assert 60 < np.median(hips[:, 1]) < 120


def test_deep_nesting_is_a_bvherror():
    depth = 5000
    text = "HIERARCHY\n" + "".join(f"{'ROOT' if i == 0 else 'JOINT'} j{i}\n{{\nOFFSET 0 1 0\n" for i in range(depth))
    text += "}\n" * depth + "MOTION\nFrames: 1\nFrame Time: 0.1\n\n"
    with pytest.raises(BVHError) as info:
        parse_bvh(text)
    assert info.value.line is not None


def test_random_corruptions_raise_only_bvherror_with_a_line():
    """Seeded fuzzing: deletions, insertions and replacements anywhere in a valid file."""
    rng = np.random.default_rng(1234)
    pieces = ["{", "}", "\n", " ", "nan", "1e999", "-", ".", "x", "JOINT", "End Site", "MOTION\n", "\t", "\r",
              "\x00", "9" * 30, "CHANNELS 7", "Frames: 5", "OFFSET"]
    parsed = failed = 0
    for _ in range(400):
        text = list(CHAIN)
        for _ in range(int(rng.integers(1, 5))):
            k = int(rng.integers(len(text)))
            op = rng.random()
            if op < 0.3:
                del text[k : k + int(rng.integers(1, 20))]
            elif op < 0.6:
                text.insert(k, pieces[int(rng.integers(len(pieces)))])
            else:
                text[k] = "{} \n0123456789.-eEx"[int(rng.integers(18))]
        try:
            bvh = parse_bvh("".join(text))
        except BVHError as exc:
            assert exc.line is not None and exc.line >= 1
            failed += 1
        else:
            assert np.isfinite(bvh.joint_positions()).all()
            parsed += 1
    assert failed > 100 and parsed > 10  # both outcomes were exercised
