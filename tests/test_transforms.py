"""Static transforms: matrices, quaternions, tf2's two forms, configuration errors, the frame tree."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from racecar_hw.base.errors import ConfigError
from racecar_hw.base.messages import TransformStamped
from racecar_hw.base.transforms import (
    SEED_CAMERA_TRANSFORMS,
    StaticTransform,
    StaticTransformParams,
    TfTree,
    TransformNotFound,
    apply,
    build_static_transform,
    build_static_transforms,
    compose,
    default_static_transforms,
    from_quaternion,
    from_transform_stamped,
    from_ypr,
    invert,
    parse_static_transform_args,
    quaternion_from_ypr,
    rotation_from_ypr,
    to_quaternion,
    to_static_transform_args,
    to_transform_stamped,
    translation_of,
    yaw_of,
    ypr_from_rotation,
)

pytestmark = pytest.mark.quiet  # may run beside an alone test (tests/conftest.py, PaceLock)

finite = st.floats(min_value=-50.0, max_value=50.0, allow_nan=False, allow_infinity=False)
angles = st.floats(min_value=-math.pi, max_value=math.pi, allow_nan=False)
xyz = st.tuples(finite, finite, finite)


@st.composite
def unit_quaternions(draw: st.DrawFn) -> tuple[float, float, float, float]:
    v = draw(st.tuples(*[st.floats(-1.0, 1.0, allow_nan=False)] * 4).filter(
        lambda q: sum(c * c for c in q) > 1e-2))
    n = math.sqrt(sum(c * c for c in v))
    return (v[0] / n, v[1] / n, v[2] / n, v[3] / n)


@st.composite
def rigid_transforms(draw: st.DrawFn) -> np.ndarray:
    return from_quaternion(draw(xyz), draw(unit_quaternions()))


def argv(text: str) -> list[str]:
    return text.split()


def same_rotation(q1: tuple[float, ...], q2: tuple[float, ...]) -> bool:
    """q and -q are the same rotation."""
    return abs(abs(float(np.dot(q1, q2))) - 1.0) < 1e-9


# --- known rotations --------------------------------------------------------------------------


def test_yaw_quarter_turn_maps_forward_to_left() -> None:
    m = from_ypr((1.0, 2.0, 3.0), yaw=math.pi / 2)
    np.testing.assert_allclose(apply(m, np.array([1.0, 0.0, 0.0])), [1.0, 3.0, 3.0], atol=1e-12)
    assert yaw_of(m) == pytest.approx(math.pi / 2)


def test_pitch_quarter_turn_maps_forward_to_down() -> None:
    # Ry(+90 deg) turns x into -z (right-handed, about y)
    np.testing.assert_allclose(rotation_from_ypr(0.0, math.pi / 2, 0.0) @ [1, 0, 0], [0, 0, -1], atol=1e-12)


def test_roll_quarter_turn_maps_left_to_up() -> None:
    np.testing.assert_allclose(rotation_from_ypr(0.0, 0.0, math.pi / 2) @ [0, 1, 0], [0, 0, 1], atol=1e-12)


def test_ypr_order_is_z_then_y_then_x() -> None:
    yaw, pitch, roll = 0.3, -0.4, 0.5
    rz = rotation_from_ypr(yaw, 0, 0)
    ry = rotation_from_ypr(0, pitch, 0)
    rx = rotation_from_ypr(0, 0, roll)
    np.testing.assert_allclose(rotation_from_ypr(yaw, pitch, roll), rz @ ry @ rx, atol=1e-12)


def test_known_quaternions() -> None:
    half = math.sqrt(0.5)
    assert quaternion_from_ypr(0, 0, 0) == pytest.approx((0, 0, 0, 1))
    assert quaternion_from_ypr(math.pi / 2, 0, 0) == pytest.approx((0, 0, half, half))
    assert quaternion_from_ypr(0, 0, math.pi / 2) == pytest.approx((half, 0, 0, half))
    assert quaternion_from_ypr(0, math.pi / 2, 0) == pytest.approx((0, half, 0, half))
    # a half turn about z: the trace is -1, the branch Shepperd's method guards
    assert same_rotation(quaternion_from_ypr(math.pi, 0, 0), (0, 0, 1, 0))


def test_both_static_forms_give_the_same_matrix() -> None:
    half = math.sqrt(0.5)
    by_ypr = parse_static_transform_args(argv("0.1 0.2 0.3 1.5707963267948966 0 0 base_link laser"))
    by_quat = parse_static_transform_args(f"0.1 0.2 0.3 0 0 {half} {half} base_link laser".split())
    np.testing.assert_allclose(by_ypr.matrix(), by_quat.matrix(), atol=1e-12)
    assert by_ypr.frame_id == "base_link" and by_ypr.child_frame_id == "laser"


@settings(deadline=None)
@given(xyz, angles, st.floats(-1.5, 1.5), angles)
def test_ypr_and_its_quaternion_give_the_same_matrix(t: tuple[float, float, float], yaw: float,
                                                      pitch: float, roll: float) -> None:
    q = quaternion_from_ypr(yaw, pitch, roll)
    by_ypr = StaticTransformParams(xyz=t, ypr=(yaw, pitch, roll)).matrix()
    by_quat = StaticTransformParams(xyz=t, quaternion=q).matrix()
    np.testing.assert_allclose(by_ypr, by_quat, atol=1e-9)


def test_named_flag_form_matches_positional_form() -> None:
    flags = parse_static_transform_args(
        ["--x", "0.2", "--yaw", "0.5", "--frame-id", "base_link", "--child-frame-id", "laser"])
    positional = parse_static_transform_args(argv("0.2 0 0 0.5 0 0 base_link laser"))
    np.testing.assert_allclose(flags.matrix(), positional.matrix())
    quat = parse_static_transform_args(["--qz", "1", "--qw", "0", "--frame-id", "a",
                                        "--child-frame-id", "b"])
    assert yaw_of(quat.matrix()) == pytest.approx(math.pi)


# --- round trips and identities ---------------------------------------------------------------


@settings(deadline=None)
@given(unit_quaternions())
def test_quaternion_round_trip(q: tuple[float, float, float, float]) -> None:
    assert same_rotation(to_quaternion(from_quaternion((0, 0, 0), q)), q)
    assert to_quaternion(from_quaternion((0, 0, 0), q))[3] >= 0.0


@settings(deadline=None)
@given(angles, st.floats(-1.5, 1.5), angles)
def test_ypr_round_trip(yaw: float, pitch: float, roll: float) -> None:
    r = rotation_from_ypr(yaw, pitch, roll)
    np.testing.assert_allclose(rotation_from_ypr(*ypr_from_rotation(r)), r, atol=1e-9)


def test_ypr_at_gimbal_lock_still_rebuilds_the_rotation() -> None:
    r = rotation_from_ypr(0.7, math.pi / 2, 0.2)
    np.testing.assert_allclose(rotation_from_ypr(*ypr_from_rotation(r)), r, atol=1e-9)


@settings(deadline=None)
@given(rigid_transforms())
def test_invert_is_inverse(m: np.ndarray) -> None:
    np.testing.assert_allclose(compose(m, invert(m)), np.eye(4), atol=1e-9)
    np.testing.assert_allclose(compose(invert(m), m), np.eye(4), atol=1e-9)
    np.testing.assert_allclose(invert(m), np.linalg.inv(m), atol=1e-9)


@settings(deadline=None)
@given(rigid_transforms(), rigid_transforms(), rigid_transforms())
def test_compose_is_associative_and_inverts_in_reverse(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> None:
    np.testing.assert_allclose(compose(compose(a, b), c), compose(a, compose(b, c)), atol=1e-7)
    np.testing.assert_allclose(invert(compose(a, b)), compose(invert(b), invert(a)), atol=1e-7)
    np.testing.assert_allclose(compose(), np.eye(4))


@settings(deadline=None)
@given(rigid_transforms(), st.lists(st.tuples(finite, finite, finite), min_size=1, max_size=20))
def test_apply_matches_homogeneous_product(m: np.ndarray, pts: list[tuple[float, float, float]]) -> None:
    p = np.array(pts)
    homogeneous = (m @ np.hstack([p, np.ones((len(p), 1))]).T).T[:, :3]
    np.testing.assert_allclose(apply(m, p), homogeneous, atol=1e-9)
    np.testing.assert_allclose(apply(invert(m), apply(m, p)), p, atol=1e-7)


def test_apply_2d_points_on_the_floor_plane() -> None:
    m = from_ypr((0.25, 0.0, 0.1), yaw=math.pi)
    np.testing.assert_allclose(apply(m, np.array([[1.0, 0.0], [0.0, 2.0]])), [[-0.75, 0.0], [0.25, -2.0]],
                               atol=1e-12)
    with pytest.raises(ValueError):
        apply(m, np.zeros((3, 4)))


@settings(deadline=None)
@given(rigid_transforms(), st.integers(0, 2**62))
def test_transform_stamped_round_trip(m: np.ndarray, stamp_ns: int) -> None:
    msg = to_transform_stamped(m, "base_link", "laser", stamp_ns)
    assert isinstance(msg, TransformStamped)
    assert msg.header.frame_id == "base_link" and msg.child_frame_id == "laser"
    assert msg.header.stamp.to_ns() == stamp_ns
    np.testing.assert_allclose(from_transform_stamped(msg), m, atol=1e-9)
    back = StaticTransform.from_msg(msg)
    assert (back.frame_id, back.child_frame_id) == ("base_link", "laser")


def test_translation_and_yaw_extraction() -> None:
    m = from_ypr((1.0, -2.0, 0.5), yaw=-2.5)
    assert translation_of(m) == pytest.approx((1.0, -2.0, 0.5))
    assert yaw_of(m) == pytest.approx(-2.5)


# --- static_transform_publisher arguments -----------------------------------------------------


@settings(deadline=None, max_examples=200)
@given(xyz, st.one_of(st.none(), st.tuples(angles, angles, angles)), unit_quaternions(),
       st.booleans(), st.from_regex(r"[a-z][a-z0-9_]{0,12}", fullmatch=True))
def test_static_args_round_trip(t: tuple[float, float, float], ypr: tuple[float, float, float] | None,
                                q: tuple[float, float, float, float], use_quat: bool, child: str) -> None:
    p = StaticTransformParams("base_link", f"c_{child}", t, None if use_quat else ypr,
                              q if use_quat else None)
    back = parse_static_transform_args(to_static_transform_args(p))
    if p.ypr is None and p.quaternion is None:
        assert back.ypr == (0.0, 0.0, 0.0)
    else:
        assert back == p
    np.testing.assert_allclose(back.matrix(), p.matrix(), atol=1e-12)


@settings(deadline=None)
@given(st.lists(st.text(max_size=8), max_size=12))
def test_static_args_parser_only_raises_config_error(tokens: list[str]) -> None:
    try:
        p = parse_static_transform_args(tokens)
    except ConfigError:
        return
    assert np.all(np.isfinite(p.matrix()))


@pytest.mark.parametrize(("args", "key"), [
    ("0 0 0 0 0 0 base_link", "args"),
    ("0 0 zero 0 0 0 base_link laser", "z"),
    ("0 0 0 0 0 0 2 base_link laser", "quaternion"),
    ("0 0 0 nan 0 0 base_link laser", "yaw"),
    ("0 0 0 0 0 0 base_link base_link", "child_frame_id"),
    ("--x 1 --frame-id a", "--child-frame-id"),
    ("--yaw 1 --qw 1 --frame-id a --child-frame-id b", "--qx"),
    ("--speed 1 --frame-id a --child-frame-id b", "--speed"),
    ("--x", "--x"),
])
def test_bad_static_args_name_the_argument(args: str, key: str) -> None:
    with pytest.raises(ConfigError) as info:
        parse_static_transform_args(args.split())
    assert info.value.key == key


# --- configuration ----------------------------------------------------------------------------


def test_params_defaults_are_base_link_to_laser_identity() -> None:
    p = build_static_transform({})
    assert (p.frame_id, p.child_frame_id) == ("base_link", "laser")
    np.testing.assert_allclose(p.matrix(), np.eye(4))


def test_params_from_yaml_mapping() -> None:
    p = build_static_transform({"xyz": [0.275, 0, 0.1], "ypr": [math.pi, 0, 0]}, "transforms[0]")
    np.testing.assert_allclose(apply(p.matrix(), np.array([1.0, 0.0, 0.0])), [-0.725, 0, 0.1], atol=1e-12)


@pytest.mark.parametrize(("data", "key"), [
    ({"ypr": [0, 0, 0], "quaternion": [0, 0, 0, 1]}, "car.tf.quaternion"),
    ({"quaternion": [0, 0, 0, 2]}, "car.tf.quaternion"),
    ({"quaternion": [0, 0, 0, 0]}, "car.tf.quaternion"),
    ({"quaternion": [0, 0, 1]}, "car.tf.quaternion"),
    ({"xyz": [0, 0, float("inf")]}, "car.tf.xyz"),
    ({"xyz": [0, "up", 0]}, "car.tf.xyz[1]"),
    ({"frame_id": "laser"}, "car.tf.child_frame_id"),
    ({"child_frame_id": ""}, "car.tf.child_frame_id"),
    ({"rotation": [0, 0, 0]}, "car.tf.rotation"),
])
def test_bad_config_names_the_key(data: dict[str, object], key: str) -> None:
    with pytest.raises(ConfigError) as info:
        build_static_transform(data, "car.tf")
    assert info.value.key == key
    assert str(info.value).startswith(key + ":")


def test_build_list_names_the_index() -> None:
    items = build_static_transforms([{"child_frame_id": "a"}, {"quaternion": [0, 0, 0.6, 0.8]}])
    assert [i.child_frame_id for i in items] == ["a", "laser"]
    with pytest.raises(ConfigError) as info:
        build_static_transforms([{}, {"quaternion": [1, 1, 1, 1]}], "tf")
    assert info.value.key == "tf[1].quaternion"
    with pytest.raises(ConfigError):
        build_static_transforms({"frame_id": "a"}, "tf")
    assert build_static_transforms(None) == []


def test_direct_construction_refuses_both_rotations() -> None:
    with pytest.raises(ConfigError) as info:
        StaticTransformParams(ypr=(0, 0, 0), quaternion=(0, 0, 0, 1))
    assert info.value.key == "quaternion"


# --- the frame tree ---------------------------------------------------------------------------


def test_seed_cameras_are_five_centimetres_either_side() -> None:
    tree = TfTree.from_params(SEED_CAMERA_TRANSFORMS)
    np.testing.assert_allclose(tree.lookup("base_link", "left_cam")[:3, 3], [0, 0.05, 0])
    np.testing.assert_allclose(tree.lookup("base_link", "right_cam")[:3, 3], [0, -0.05, 0])
    # the lab's "right camera relative to the left camera": 0.10 m to the right
    np.testing.assert_allclose(tree.lookup("left_cam", "right_cam"), from_ypr((0, -0.1, 0)), atol=1e-12)
    np.testing.assert_allclose(tree.lookup("right_cam", "left_cam"), from_ypr((0, 0.1, 0)), atol=1e-12)


def test_laser_points_into_base_link_through_a_chain() -> None:
    tree = TfTree([
        StaticTransform("base_link", "mount", from_ypr((0.2, 0.0, 0.05))),
        StaticTransform("mount", "laser", from_ypr((0.05, 0.0, 0.05), yaw=math.pi)),
        *(StaticTransform.from_params(p) for p in SEED_CAMERA_TRANSFORMS),
    ])
    t_base_laser = tree.lookup("base_link", "laser")
    # an obstacle 1 m ahead of an upside-down-mounted (yawed half turn) laser is behind the mount
    np.testing.assert_allclose(apply(t_base_laser, np.array([1.0, 0.0])), [-0.75, 0.0], atol=1e-12)
    np.testing.assert_allclose(tree.lookup("laser", "base_link"), invert(t_base_laser), atol=1e-12)
    np.testing.assert_allclose(tree.lookup("left_cam", "laser"),
                               compose(invert(tree.lookup("base_link", "left_cam")), t_base_laser),
                               atol=1e-12)
    np.testing.assert_allclose(tree.lookup("laser", "laser"), np.eye(4))
    assert tree.can_transform("left_cam", "laser")


def test_lookup_unknown_or_disconnected_frames() -> None:
    tree = TfTree([StaticTransform("base_link", "laser", np.eye(4)),
                   StaticTransform("map", "odom", np.eye(4))])
    with pytest.raises(TransformNotFound):
        tree.lookup("base_link", "camera")
    with pytest.raises(TransformNotFound):
        tree.lookup("odom", "laser")
    assert not tree.can_transform("odom", "laser")
    assert tree.frames() == {"base_link", "laser", "map", "odom"}


def test_tree_refuses_second_parent_and_cycles_and_replaces_same_edge() -> None:
    tree = TfTree([StaticTransform("base_link", "laser", np.eye(4)),
                   StaticTransform("laser", "lens", np.eye(4))])
    with pytest.raises(ConfigError):
        tree.add(StaticTransform("odom", "laser", np.eye(4)))
    with pytest.raises(ConfigError):
        tree.add(StaticTransform("lens", "base_link", np.eye(4)))
    tree.add(StaticTransform("base_link", "laser", from_ypr((0.3, 0, 0))))
    np.testing.assert_allclose(tree.lookup("base_link", "lens")[:3, 3], [0.3, 0, 0])
    assert len(tree.transforms()) == 2


def test_default_static_transforms_as_tf_static_message() -> None:
    tree = TfTree.from_params(default_static_transforms())
    msg = tree.to_tf_message(stamp_ns=1_700_000_000_123_456_789)
    assert [(t.header.frame_id, t.child_frame_id) for t in msg.transforms] == [
        ("base_link", "laser"), ("base_link", "left_cam"), ("base_link", "right_cam")]
    assert msg.transforms[1].transform.translation.y == pytest.approx(0.05)
    assert msg.transforms[0].header.stamp.sec == 1_700_000_000
