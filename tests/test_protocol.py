"""The OSC wire API: decoding, validation with drop reasons, encoding."""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest
from pythonosc.osc_bundle_builder import IMMEDIATELY, OscBundleBuilder
from pythonosc.osc_message import OscMessage
from pythonosc.osc_message_builder import OscMessageBuilder

from stage.joints import JOINTS, HandState
from stage.sensors.protocol import (DROP_REASONS, HandStateMsg, JointCoordinates, LostUser,
                                    NewUser, RegisterDevice, RegisterView, StatsQuery,
                                    decode_datagram, encode_bundle, encode_client_joints,
                                    encode_message, encode_view_hand_state, encode_view_joints)


def build(address: str, *args) -> bytes:
    b = OscMessageBuilder(address)
    for a in args:
        b.add_arg(a)
    return b.build().dgram


def skeleton_args(n: int = 25, value: float = 0.5):
    out = []
    for name in JOINTS[:n]:
        out += [name, value, value, value, 1.0]
    return out


def only_message(data: bytes):
    d = decode_datagram(data, "1.2.3.4:5")
    assert d.drops == []
    assert len(d.messages) == 1
    return d.messages[0]


def only_drop(data: bytes) -> tuple[str, str]:
    d = decode_datagram(data, "1.2.3.4:5")
    assert d.messages == []
    assert len(d.drops) == 1
    assert d.drops[0][1] in DROP_REASONS
    return d.drops[0]


def test_every_client_message_decodes_as_the_paper_defines_it():
    msg, tt = only_message(build("/registerDevice", "10.0.0.7", "kinect2"))
    assert msg == RegisterDevice("10.0.0.7", "kinect2") and tt is None
    msg, _ = only_message(build("/newUser", "10.0.0.7", 3, 0.1, 0.2, 2.5))
    assert isinstance(msg, NewUser) and msg.user == 3
    np.testing.assert_allclose(msg.position, [0.1, 0.2, 2.5], atol=1e-6)
    msg, _ = only_message(build("/lostUser", "10.0.0.7", 3))
    assert msg == LostUser("10.0.0.7", 3)
    msg, _ = only_message(build("/handState", "10.0.0.7", 3, "right", "lasso"))
    assert msg == HandStateMsg("10.0.0.7", 3, 1, HandState.LASSO)
    msg, _ = only_message(build("/handState", "10.0.0.7", 3, "left", 3))  # codes too
    assert msg.state == HandState.CLOSED and msg.hand == 0
    msg, _ = only_message(build("/registerView", "127.0.0.1", 9001))
    assert msg == RegisterView("127.0.0.1", 9001)
    # stage addition: a trailing rate in Hz asks for a fixed output rate
    msg, _ = only_message(build("/registerView", "127.0.0.1", 9001, 60.0))
    assert msg == RegisterView("127.0.0.1", 9001, True, 60.0)
    msg, _ = only_message(build("/registerView", "127.0.0.1", 9001, 25))
    assert msg.rate_hz == 25.0
    msg, _ = only_message(build("/stage/stats"))
    assert msg == StatsQuery(None)


def test_joint_coordinates_fill_named_joints_and_leave_the_rest_at_confidence_zero():
    data = build("/jointCoordinates", "k", 0, "Head", 0.1, 1.6, 2.0, 1.0,
                 "HandLeft", -0.3, 1.0, 1.9, 0.5)
    msg, _ = only_message(data)
    assert isinstance(msg, JointCoordinates)
    assert msg.conf[3] == 1.0 and msg.conf[7] == 0.5
    assert (msg.conf > 0).sum() == 2
    np.testing.assert_allclose(msg.joints[3], [0.1, 1.6, 2.0], atol=1e-6)


def test_integer_client_ids_are_accepted_as_text():
    msg, _ = only_message(build("/lostUser", 4, 1))
    assert msg.client == "4"


@pytest.mark.parametrize("data, reason", [
    (build("/jointCoordinates", "k", 0, "Head", float("nan"), 1.0, 2.0, 1.0), "non_finite"),
    (build("/jointCoordinates", "k", 0, "Head", 0.0, float("inf"), 2.0, 1.0), "non_finite"),
    (build("/jointCoordinates", "k", 0, "Head", 0.0, 1.0, 25.0, 1.0), "out_of_range"),
    (build("/jointCoordinates", "k", 0, "Head", 0.0, 1.0, 2.0, 1.5), "out_of_range"),
    (build("/jointCoordinates", "k", 0, "Handleft", 0.0, 1.0, 2.0, 1.0), "unknown_joint"),
    (build("/jointCoordinates", "k", 0, "Head", 0.0, 1.0, 2.0, 1.0,
           "Head", 0.0, 1.0, 2.0, 1.0), "duplicate_joint"),
    (build("/jointCoordinates", "k", 6, "Head", 0.0, 1.0, 2.0, 1.0), "bad_user_id"),
    (build("/jointCoordinates", "k", -1, "Head", 0.0, 1.0, 2.0, 1.0), "bad_user_id"),
    (build("/jointCoordinates", "k", 0, "Head", 0.0, 1.0, 2.0), "bad_arity"),
    (build("/jointCoordinates", "k", 0, "Head", "x", 1.0, 2.0, 1.0), "bad_types"),
    (build("/jointCoordinates", "k", 0, *skeleton_args(25), "Head", 0.0, 0.0, 0.0, 1.0),
     "bad_arity"),
    (build("/newUser", "k", 0, 1.0, 2.0), "bad_arity"),
    (build("/handState", "k", 0, "middle", "open"), "bad_hand"),
    (build("/handState", "k", 0, "left", "waving"), "bad_hand_state"),
    (build("/handState", "k", 0, "left", 9), "bad_hand_state"),
    (build("/registerView", "127.0.0.1", 70000), "out_of_range"),
    (build("/registerView", 5, 9000), "bad_types"),
    (build("/registerView", "127.0.0.1", 9000, 0.0), "out_of_range"),
    (build("/registerView", "127.0.0.1", 9000, "fast"), "bad_types"),
    (build("/registerView", "127.0.0.1", 9000, 60.0, 1), "bad_arity"),
    (build("/kinect/skeleton", "k", 0), "unknown_address"),
])
def test_bad_messages_are_dropped_with_their_reason(data, reason):
    client, got = only_drop(data)
    assert got == reason
    if data.startswith(b"/jointCoordinates") or data.startswith(b"/handState"):
        assert client == "k"  # counted against the client that sent it


@pytest.mark.parametrize("data", [
    b"", b"\x00\x01\x02", b"hello world", b"/jointCoordinates\x00\x00\x00,sisffff",
    build("/jointCoordinates", "k", 0, *skeleton_args(3))[:-7],  # truncated mid-float
    b"#bundle\x00\x00\x00",                                    # truncated bundle header
    b"#bundle\x00" + b"\x00" * 8 + struct.pack(">i", 400) + b"/x\x00\x00,\x00\x00\x00",
])
def test_malformed_datagrams_are_counted_against_the_source(data):
    client, reason = only_drop(data)
    assert reason == "malformed"
    assert client == "1.2.3.4:5"


def test_random_bytes_never_raise_and_never_yield_invalid_frames():
    rng = np.random.default_rng(7)
    good = build("/jointCoordinates", "k", 0, *skeleton_args(25))
    n_frames = 0
    for k in range(3000):
        if k % 2:
            data = rng.integers(0, 256, size=int(rng.integers(0, 200)), dtype=np.uint8).tobytes()
        else:  # flip bytes of a valid message: the nastiest inputs are nearly right
            arr = np.frombuffer(good, dtype=np.uint8).copy()
            for i in rng.integers(0, len(arr), size=int(rng.integers(1, 6))):
                arr[i] = rng.integers(0, 256)
            data = arr.tobytes()
        decoded = decode_datagram(data, "x:1")
        for msg, _ in decoded.messages:
            if isinstance(msg, JointCoordinates):
                n_frames += 1
                assert np.isfinite(msg.joints).all() and (np.abs(msg.joints) <= 20).all()
                assert ((msg.conf >= 0) & (msg.conf <= 1)).all()
                assert 0 <= msg.user <= 5
        assert all(reason in DROP_REASONS for _, reason in decoded.drops)
    assert n_frames > 0  # some flips land in values and still make valid frames


def test_bundles_carry_the_capture_timetag_and_may_nest():
    inner = OscBundleBuilder(1_700_000_000.25)
    inner.add_content(OscMessage(build("/lostUser", "k", 1)))
    outer = OscBundleBuilder(1_700_000_000.5)
    outer.add_content(OscMessage(build("/lostUser", "k", 2)))
    outer.add_content(inner.build())
    d = decode_datagram(outer.build().dgram)
    assert d.drops == []
    times = {msg.user: tt for msg, tt in d.messages}
    assert times[2] == pytest.approx(1_700_000_000.5, abs=1e-6)
    assert times[1] == pytest.approx(1_700_000_000.25, abs=1e-6)


def test_an_immediate_bundle_has_no_timetag():
    b = OscBundleBuilder(IMMEDIATELY)
    b.add_content(OscMessage(build("/lostUser", "k", 1)))
    (msg, tt), = decode_datagram(b.build().dgram).messages
    assert tt is None


def test_one_bad_message_in_a_bundle_does_not_lose_the_good_ones():
    data = encode_bundle([build("/lostUser", "k", 1), build("/lostUser", "k", 9)], 1.7e9)
    d = decode_datagram(data)
    assert [m.user for m, _ in d.messages] == [1]
    assert d.drops == [("k", "bad_user_id")]


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_fast_encoders_are_read_back_by_python_osc(seed):
    # several seeds: several joint sets, each with its own cached layout
    rng = np.random.default_rng(seed)
    joints = rng.uniform(-3, 3, size=(25, 3))
    conf = rng.choice([0.0, 0.5, 1.0], size=25)
    msg = OscMessage(encode_view_joints(12, joints, conf))
    assert msg.address == "/jointCoordinates"
    params = msg.params
    assert params[0] == 12
    sent = np.flatnonzero(conf > 0)
    assert len(params) == 1 + 5 * len(sent)
    for k, j in enumerate(sent):
        name, x, y, z, c = params[1 + 5 * k: 6 + 5 * k]
        assert name == JOINTS[j]
        np.testing.assert_allclose([x, y, z, c], [*joints[j], conf[j]], rtol=1e-6)
    # the client-side encoder round-trips through our own decoder
    data = encode_client_joints("kin-1", 2, joints, conf)
    back, _ = only_message(data)
    assert back.client == "kin-1" and back.user == 2
    np.testing.assert_allclose(back.joints[sent], joints[sent], rtol=1e-6)
    np.testing.assert_allclose(back.conf, conf)


def test_message_encoder_types_match_python_osc():
    data = encode_message("/handState", 3, "left", "open")
    assert data == build("/handState", 3, "left", "open")
    assert OscMessage(encode_view_hand_state(3, 1, HandState.CLOSED)).params == [3, "right", "closed"]
    assert OscMessage(encode_message("/x", 1.5)).params[0] == pytest.approx(1.5)
    with pytest.raises(TypeError):
        encode_message("/x", True)
    assert math.isclose(OscMessage(encode_message("/x", -2.25)).params[0], -2.25)


def test_floor_plane_extension_is_normalised_and_validated():
    from stage.sensors.protocol import FloorPlane
    msg, _ = only_message(build("/floorPlane", "k", 0.0, 2.0, 0.0, 1.6))
    assert isinstance(msg, FloorPlane)
    np.testing.assert_allclose(msg.plane, [0, 1, 0, 0.8])
    assert only_drop(build("/floorPlane", "k", 0.0, 0.0, 0.0, 1.0))[1] == "out_of_range"
    assert only_drop(build("/floorPlane", "k", 0.0, 1.0, 0.0))[1] == "bad_arity"


def test_fast_path_agrees_with_the_general_decoder():
    """The hot-path decoder accepts exactly what the general one accepts, with equal values."""
    rng = np.random.default_rng(11)
    fast_hits = 0
    for k in range(600):
        n = int(rng.integers(1, 26))
        names = list(rng.choice(JOINTS, size=n, replace=False))
        if k % 7 == 0:
            names[0] = "Nose"                                 # unknown joint
        if k % 11 == 0 and n > 1:
            names[1] = names[0]                               # duplicate
        args = ["kin" if k % 3 else 3, int(rng.integers(-1, 8))]
        for name in names:
            xyz = rng.normal(0, 8 if k % 5 == 0 else 1, size=3)
            c = float(rng.choice([0.0, 0.5, 1.0, 1.2]) if k % 13 == 0 else rng.choice([0.5, 1.0]))
            if k % 17 == 0:
                xyz[0] = np.nan
            args += [str(name), *map(float, xyz), c]
        data = build("/jointCoordinates", *args)
        if k % 19 == 0:
            data = data[:-4]
        general, fast = _decode_both_ways(data)
        if fast is None:
            continue
        fast_hits += 1
        _assert_same_skeleton(general, fast)
    assert fast_hits > 100


def test_fast_path_in_kinect_order_agrees_with_the_general_decoder():
    """All 25 joints in JOINTS order (what Kinect clients send) take a shortcut in the fast
    path; it accepts exactly what the general decoder accepts, with equal values."""
    rng = np.random.default_rng(12)
    fast_hits = 0
    for k in range(300):
        names = list(JOINTS)
        if k % 7 == 0:
            names[3] = "Nose"                                 # unknown joint, same slot
        if k % 11 == 0:
            names[5], names[6] = names[6], names[5]           # another order
        args = ["kin" if k % 3 else 3, int(rng.integers(-1, 8))]
        for n, name in enumerate(names):
            xyz = rng.normal(0, 8 if k % 5 == 0 else 1, size=3)
            c = float(rng.choice([0.0, 0.5, 1.0, 1.2]) if k % 13 == 0 else rng.choice([0.5, 1.0]))
            if k % 17 == 0 and n == 24:
                xyz[2] = np.inf
            args += [str(name), *map(float, xyz), c]
        data = build("/jointCoordinates", *args)
        if k % 19 == 0:
            data = data[:-4]
        general, fast = _decode_both_ways(data)
        if fast is None:
            assert general.drops or k % 11 == 0
            continue
        fast_hits += 1
        _assert_same_skeleton(general, fast)
    assert fast_hits > 100


def test_hand_state_fast_path_agrees_with_the_general_decoder():
    from stage.sensors.protocol import Decoded, _decode_message, _fast_hand_state, _parse_message
    hits = 0
    for client in ("k", "kinect-12345", "x" * 70):
        for user in (-1, 0, 5, 6):
            for hand in ("left", "right", "Left", "middle"):
                for state in ("open", "closed", "lasso", "notTracked", "unknown", "OPEN", "x"):
                    data = build("/handState", client, user, hand, state)
                    general = Decoded()
                    _decode_message(_parse_message(data), None, general, "s")
                    fast = _fast_hand_state(data)
                    if fast is not None:
                        hits += 1
                        assert general.messages[0][0] == fast
    assert hits == 2 * 2 * 2 * 5


def _decode_both_ways(data: bytes):
    """``data`` through the general decoder (a parse failure counted as one malformed drop)
    and through the joint-coordinates fast path (None: the fast path declined)."""
    from stage.sensors.protocol import (Decoded, _decode_message, _fast_joint_coordinates,
                                        _parse_message)
    general = Decoded()
    try:
        _decode_message(_parse_message(data), None, general, "x:1")
    except Exception:
        general.drops.append(("x:1", "malformed"))
    return general, _fast_joint_coordinates(data)


def _assert_same_skeleton(general, fast) -> None:
    """The fast path's skeleton is the one message the general decoder produced, value for value."""
    assert general.drops == [] and len(general.messages) == 1
    slow = general.messages[0][0]
    assert (fast.client, fast.user) == (slow.client, slow.user)
    assert np.array_equal(fast.joints, slow.joints) and np.array_equal(fast.conf, slow.conf)


def test_a_bundles_kinect_order_skeletons_decoded_together_as_each_alone():
    """The Kinect-order skeletons of one bundle are checked and converted together; the result
    is what decoding each element alone gives (python-osc's general path for the odd ones):
    the same messages in the same order, the same drops, nested bundles included."""
    from pythonosc.osc_bundle_builder import OscBundleBuilder as Builder
    from pythonosc.osc_message import OscMessage as Msg
    from stage.sensors.protocol import Decoded, _decode_element, decode_datagram
    rng = np.random.default_rng(5)
    for trial in range(40):
        elements = []
        for k in range(int(rng.integers(1, 8))):
            args = ["kin", int(rng.integers(0, 6))]
            names = list(JOINTS)
            kind = rng.integers(0, 6)
            if kind == 1:
                names[4], names[5] = names[5], names[4]            # another order
            for n, name in enumerate(names):
                xyz = rng.normal(0.0, 1.0, 3)
                c = 1.0
                if kind == 2 and n == 7:
                    xyz[1] = np.nan                                # invalid value: a drop
                if kind == 3 and n == 0:
                    c = 1.5                                        # confidence out of range
                args += [name, *map(float, xyz), c]
            elements.append(build("/jointCoordinates", *args))
            if kind == 4:
                elements.append(build("/handState", "kin", 1, "left", "open"))
        outer = Builder(IMMEDIATELY)
        inner = Builder(IMMEDIATELY)
        for k, e in enumerate(elements):
            (inner if trial % 2 and k % 2 else outer).add_content(Msg(e))
        if trial % 2:
            outer.add_content(inner.build())
        got = decode_datagram(outer.build().dgram, "x:1")
        alone = Decoded()
        for e in [e for k, e in enumerate(elements) if not (trial % 2 and k % 2)] + \
                [e for k, e in enumerate(elements) if trial % 2 and k % 2]:
            _decode_element(e, None, alone, "x:1")
        assert sorted(got.drops) == sorted(alone.drops)
        assert len(got.messages) == len(alone.messages)
        for (m, _), (a, _) in zip(got.messages, alone.messages):
            assert type(m) is type(a) and m.client == a.client and m.user == a.user
            if isinstance(m, JointCoordinates):
                assert np.array_equal(m.joints, a.joints) and np.array_equal(m.conf, a.conf)
