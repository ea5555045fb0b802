"""Every bus message survives msgpack and JSON round trips; key expressions are well formed."""

from __future__ import annotations

import msgspec
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from messages import ALL_MESSAGES, ALL_REPLIES, topics
from messages.codec import codec
from messages.types import Pose2


def _strategy(t: msgspec.inspect.Type) -> st.SearchStrategy:
    """A hypothesis strategy for a msgspec type description (finite floats: NaN != NaN)."""
    mi = msgspec.inspect
    if isinstance(t, mi.FloatType):
        return st.floats(allow_nan=False, allow_infinity=False, width=64)
    if isinstance(t, mi.IntType):
        return st.integers(min_value=-(2**63), max_value=2**63 - 1)
    if isinstance(t, mi.BoolType):
        return st.booleans()
    if isinstance(t, mi.BytesType):
        return st.binary(max_size=20)
    if isinstance(t, mi.StrType):
        return st.text(max_size=20)
    if isinstance(t, mi.NoneType):
        return st.none()
    if isinstance(t, mi.UnionType):
        return st.one_of([_strategy(x) for x in t.types])
    if isinstance(t, mi.ListType):
        return st.lists(_strategy(t.item_type), max_size=5)
    if isinstance(t, mi.DictType):
        return st.dictionaries(_strategy(t.key_type), _strategy(t.value_type), max_size=4)
    if isinstance(t, mi.StructType):
        return st.builds(t.cls, **{f.name: _strategy(f.type) for f in t.fields})
    raise TypeError(f"no strategy for {t!r}")


def message_strategy(cls: type) -> st.SearchStrategy:
    return _strategy(msgspec.inspect.type_info(cls))


@pytest.mark.parametrize("cls", ALL_MESSAGES + ALL_REPLIES, ids=lambda c: c.__name__)
@settings(max_examples=40, deadline=None)
@given(data=st.data())
def test_round_trip(cls, data):
    msg = data.draw(message_strategy(cls))
    c = codec(cls)
    assert c.decode(c.encode(msg)) == msg
    assert c.decode_json(c.encode_json(msg)) == msg


@pytest.mark.parametrize("cls", ALL_MESSAGES, ids=lambda c: c.__name__)
def test_messages_are_frozen_tagged_and_stamped(cls):
    info = msgspec.inspect.type_info(cls)
    names = {f.name for f in info.fields}
    assert {"stamp", "seq"} <= names
    assert cls.__struct_config__.frozen
    assert info.tag == cls.__name__


def test_wrong_type_is_rejected():
    from messages.types import CompassReading, OdometryStep

    data = codec(OdometryStep).encode(OdometryStep(stamp=1.0, seq=0, distance_m=0.1, rotation_rad=0.0, dt_s=0.1))
    with pytest.raises(msgspec.ValidationError):
        codec(CompassReading).decode(data)
    with pytest.raises(msgspec.DecodeError):
        codec(CompassReading).decode(b"\xc1\x00garbage")


def test_new_field_with_default_is_backward_compatible():
    """The schema rule: a newer publisher's extra field is ignored; an older one's missing field defaults."""
    from messages.types import DeadReckonedPose

    class DeadReckonedPoseV2(DeadReckonedPose, frozen=True, kw_only=True, tag="DeadReckonedPose"):
        extra_m: float = 0.0

    p = Pose2(x_m=1.0, y_m=2.0, heading_rad=0.5)
    new = DeadReckonedPoseV2(stamp=0.0, seq=1, compass=p, raw=p, steps=3, path_length_m=0.3, extra_m=9.0)
    old = codec(DeadReckonedPose).decode(codec(DeadReckonedPoseV2).encode(new))
    assert old.steps == 3 and old.gaps == 0
    back = codec(DeadReckonedPoseV2).decode(codec(DeadReckonedPose).encode(old))
    assert back.extra_m == 0.0


def test_topics():
    keys = topics.all_topics("r2")
    assert len(set(keys.values())) == len(keys)
    assert all(k.startswith("relaxmap/r2/") for k in keys.values())
    assert topics.odometry() == "relaxmap/robot0/sensors/odometry"
    assert topics.map_place("robot0", 12) == "relaxmap/robot0/map/place/12"
    with pytest.raises(ValueError):
        topics.odometry("a/b")


def test_schema_command(capsys):
    from services.cli import main

    assert main(["schema"]) == 0
    doc = msgspec.json.decode(capsys.readouterr().out)
    assert {c.__name__ for c in ALL_MESSAGES + ALL_REPLIES} <= set(doc["$defs"])
