"""The array's IMU frames on ``/tf_static`` (the transforms of :mod:`imu_array_ros.model.frames`).

:class:`StaticFramePublisher` publishes one ``tf2_msgs/TFMessage`` of ``geometry_msgs/TransformStamped``
(array frame -> each IMU's sensor frame) on ``/tf_static`` with the topic's QoS convention
(reliable, transient local, depth 1: a late subscriber such as RViz still gets the last message).
Call :meth:`~StaticFramePublisher.publish` at start and again after a calibration reload (the
transforms replace the previous ones: tf2 keeps the latest static transform per child frame).

``tf2_msgs`` comes with a full ROS install, not with the ROS packages on PyPI: without it the node
says so once in its log and publishes nothing.  :func:`transform_messages` (the message content) needs
``geometry_msgs`` only.
"""

from __future__ import annotations

from imu_array_ros.model.description import ArrayDescription
from imu_array_ros.model.frames import static_frames

__all__ = ["StaticFramePublisher", "transform_messages", "TF_STATIC", "NO_TF_MESSAGE"]

TF_STATIC = "/tf_static"
NO_TF_MESSAGE = "tf2_msgs not available: IMU frames not published on /tf_static"


def transform_messages(description: ArrayDescription, stamp, frame_prefix: str = "") -> list:
    """``geometry_msgs/TransformStamped`` per IMU of ``description`` (array frame -> IMU frame
    ``frame_prefix + name``), stamped ``stamp`` (``builtin_interfaces/Time``)."""
    from geometry_msgs.msg import TransformStamped

    out = []
    for f in static_frames(description, frame_prefix):
        t = TransformStamped()
        t.header.stamp = stamp
        t.header.frame_id = f.parent
        t.child_frame_id = f.child
        t.transform.translation.x, t.transform.translation.y, t.transform.translation.z = f.translation
        (t.transform.rotation.x, t.transform.rotation.y, t.transform.rotation.z,
         t.transform.rotation.w) = f.quaternion
        out.append(t)
    return out


def static_qos():
    """The ``/tf_static`` convention: reliable, transient local, keep last 1."""
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    return QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL)


class StaticFramePublisher:
    """Publishes a description's IMU frames on ``/tf_static`` (module docstring); ``frame_prefix`` as
    the node's raw messages use it."""

    def __init__(self, node, frame_prefix: str = "") -> None:
        self.node, self.frame_prefix = node, frame_prefix
        self.published = 0  # messages sent
        try:
            from tf2_msgs.msg import TFMessage
        except ImportError:
            self._type, self._pub = None, None
            node.get_logger().info(NO_TF_MESSAGE)
            return
        self._type = TFMessage
        self._pub = node.create_publisher(TFMessage, TF_STATIC, static_qos())

    @property
    def available(self) -> bool:
        return self._pub is not None

    def publish(self, description: ArrayDescription) -> int:
        """Send the frames of ``description``; the number of transforms sent (0 without tf2_msgs)."""
        if self._pub is None:
            return 0
        transforms = transform_messages(description, self.node.get_clock().now().to_msg(), self.frame_prefix)
        self._pub.publish(self._type(transforms=transforms))
        self.published += 1
        return len(transforms)
