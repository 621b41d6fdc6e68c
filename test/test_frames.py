"""The IMU frames on /tf_static: transform content from the description, without ROS's tf2 (not on PyPI)."""

from __future__ import annotations

import sys
import types

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from conftest import ARRAY32, REPO
from imu_array_ros.io.kalibr import kalibr_transform
from imu_array_ros.model.description import load_description
from imu_array_ros.model.frames import quaternion_from_matrix, static_frames
from imu_array_ros.model.layouts import make_description

#: half turns about the axes and a diagonal (w = 0: the sign convention's edge), identity, a quarter turn
SPECIAL = [np.eye(3), np.diag([1.0, -1, -1]), np.diag([-1.0, 1, -1]), np.diag([-1.0, -1, 1]),
           Rotation.from_rotvec(np.pi * np.array([1.0, 1, 0]) / np.sqrt(2)).as_matrix(),
           Rotation.from_euler("z", 90, degrees=True).as_matrix()]


def _rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """v rotated by the unit quaternion q = (x, y, z, w): q v q*, written out (not through a matrix)."""
    u, w = q[:3], q[3]
    return v + 2.0 * np.cross(u, np.cross(u, v) + w * v)


def _random_array(seed: int):
    rng = np.random.default_rng(seed)
    k = int(rng.integers(1, 40))
    orientations = Rotation.random(k, random_state=seed).as_matrix()
    orientations[: min(k, len(SPECIAL))] = SPECIAL[: min(k, len(SPECIAL))]
    positions = rng.normal(scale=rng.uniform(1e-3, 0.5), size=(k, 3))
    return make_description(positions, orientations, frame_id=f"array_{seed}")


def _check(desc, frames, prefix=""):
    assert len(frames) == len(desc.imus)
    for f, imu in zip(frames, desc.imus):
        assert f.parent == desc.frame_id and f.child == prefix + imu.name
        np.testing.assert_array_equal(f.translation, imu.position)
        q = np.array(f.quaternion)
        assert abs(np.linalg.norm(q) - 1.0) < 1e-12 and q[3] >= 0.0
        v = np.random.default_rng(len(imu.name)).normal(size=(5, 3))
        for x in v:  # rotating a sensor-frame vector by q gives it in the array frame
            np.testing.assert_allclose(_rotate(q, x), imu.orientation @ x, atol=1e-12)
        # the transform parent -> child maps a point of the IMU frame into the array frame: the inverse of T_i_b
        pose = np.eye(4)
        pose[:3, :3], pose[:3, 3] = Rotation.from_quat(q).as_matrix(), f.translation
        np.testing.assert_allclose(pose @ kalibr_transform(imu.orientation.T, imu.position), np.eye(4), atol=1e-12)


@pytest.mark.parametrize("seed", range(6))
def test_static_frames_equal_the_description(seed):
    desc = _random_array(seed)
    _check(desc, static_frames(desc))
    _check(desc, static_frames(desc, "rig/"), "rig/")


@pytest.mark.parametrize("path", [ARRAY32, REPO / "config" / "mimu4444bt_corners.yaml"])
def test_static_frames_of_shipped_descriptions(path):
    desc = load_description(path)
    _check(desc, static_frames(desc))


def test_quaternion_is_scipys_up_to_sign_and_has_w_nonnegative():
    mats = np.concatenate([Rotation.random(500, random_state=11).as_matrix(), SPECIAL])
    for r in mats:
        q = quaternion_from_matrix(r)
        want = Rotation.from_matrix(r).as_quat()
        assert q[3] >= 0.0
        np.testing.assert_allclose(q, want if np.dot(q, want) > 0 else -want, atol=1e-12)


def test_transform_messages_carry_the_frames():
    from builtin_interfaces.msg import Time

    from imu_array_ros.nodes.frames import transform_messages

    desc = _random_array(3)
    msgs = transform_messages(desc, Time(sec=12, nanosec=5), "p_")
    for m, f in zip(msgs, static_frames(desc, "p_"), strict=True):
        assert (m.header.stamp.sec, m.header.stamp.nanosec) == (12, 5)
        assert m.header.frame_id == desc.frame_id and m.child_frame_id == f.child
        t, r = m.transform.translation, m.transform.rotation
        assert (t.x, t.y, t.z) == f.translation and (r.x, r.y, r.z, r.w) == f.quaternion


class _FakeNode:
    """What StaticFramePublisher uses of an rclpy node: logger, publisher factory, clock."""

    def __init__(self):
        self.lines, self.created, self.sent = [], [], []
        node = self

        class Logger:
            def info(self, text):
                node.lines.append(text)

            warning = info

        class Pub:
            def publish(self, msg):
                node.sent.append(msg)

        class Clock:
            def now(self):
                from rclpy.time import Time
                return Time(nanoseconds=1_500_000_000)

        self._logger, self._pub, self._clock = Logger(), Pub(), Clock()

    def get_logger(self):
        return self._logger

    def get_clock(self):
        return self._clock

    def create_publisher(self, msg_type, topic, qos):
        self.created.append((msg_type, topic, qos))
        return self._pub


def test_without_tf2_msgs_says_so_once_and_publishes_nothing(monkeypatch):
    from imu_array_ros.nodes.frames import NO_TF_MESSAGE, StaticFramePublisher

    monkeypatch.setitem(sys.modules, "tf2_msgs", None)  # import fails, as on a PyPI-only ROS
    monkeypatch.setitem(sys.modules, "tf2_msgs.msg", None)
    node = _FakeNode()
    frames = StaticFramePublisher(node)
    desc = load_description(ARRAY32)
    assert frames.publish(desc) == 0 and frames.publish(desc) == 0
    assert node.lines == [NO_TF_MESSAGE] and not node.created and not node.sent and not frames.available


def test_with_tf2_msgs_publishes_every_frame_again_after_a_reload(monkeypatch):
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, ReliabilityPolicy

    from imu_array_ros.nodes.frames import TF_STATIC, StaticFramePublisher

    class TFMessage:  # tf2_msgs/TFMessage: one field, transforms
        def __init__(self, transforms=()):
            self.transforms = list(transforms)

    package, module = types.ModuleType("tf2_msgs"), types.ModuleType("tf2_msgs.msg")
    module.TFMessage, package.msg = TFMessage, module
    monkeypatch.setitem(sys.modules, "tf2_msgs", package)
    monkeypatch.setitem(sys.modules, "tf2_msgs.msg", module)
    node = _FakeNode()
    frames = StaticFramePublisher(node, "x_")
    ((msg_type, topic, qos),) = node.created
    assert msg_type is TFMessage and topic == TF_STATIC == "/tf_static" and not node.lines
    assert (qos.reliability, qos.durability, qos.history, qos.depth) == (
        ReliabilityPolicy.RELIABLE, DurabilityPolicy.TRANSIENT_LOCAL, HistoryPolicy.KEEP_LAST, 1)
    desc = load_description(ARRAY32)
    moved = desc.with_imus([imu.with_values({"position": imu.position + 0.001}) for imu in desc.imus])
    assert frames.publish(desc) == len(desc.imus) and frames.publish(moved) == len(desc.imus)
    for msg, d in zip(node.sent, (desc, moved), strict=True):
        assert [t.child_frame_id for t in msg.transforms] == [f"x_{n}" for n in d.names]
        got = np.array([[t.transform.translation.x, t.transform.translation.y, t.transform.translation.z]
                        for t in msg.transforms])
        np.testing.assert_array_equal(got, d.positions)
        assert all((t.header.stamp.sec, t.header.stamp.nanosec) == (1, 500_000_000) for t in msg.transforms)


@pytest.mark.parametrize("publish", [True, False])
def test_fusion_node_publishes_the_frames_in_use_at_start(dds, monkeypatch, publish):
    """The fusion node hands its description to the frame publisher at start (publish_frames:=true), with
    its frame_prefix; publish_frames:=false makes no publisher."""
    import rclpy

    from imu_array_ros.nodes import fusion_node

    made = []

    class Recorder:
        def __init__(self, node, prefix=""):
            self.prefix, self.published = prefix, []
            made.append(self)

        def publish(self, desc):
            self.published.append(desc)
            return len(desc.imus)

    monkeypatch.setattr(fusion_node, "StaticFramePublisher", Recorder)
    rclpy.init(args=["--ros-args", "-p", f"array_config:={ARRAY32}", "-p", "frame_prefix:=arr/",
                     "-p", f"publish_frames:={str(publish).lower()}", "-p", "bias_tracking:=false"])
    try:
        node = fusion_node.FusionNode()
        node.destroy_node()
    finally:
        rclpy.try_shutdown()
    if not publish:
        assert made == []
        return
    ((frames,),) = [made]
    assert frames.prefix == "arr/" and len(frames.published) == 1
    assert list(frames.published[0].names) == list(load_description(ARRAY32).names)
