"""Every node parameter, declared in one place with its descriptor, and checked at start.

A node calls :func:`declare` with its table; a value of the wrong type, outside
its range or not among its choices stops the node with one line naming the
parameter (:class:`~imu_array_ros.errors.ConfigError`), before anything opens.
A parameter given to the node that is in neither its table nor ROS's own
(``use_sim_time``, ``start_type_description_service``, ``qos_overrides.*``) stops it
the same way, naming the parameter and the nearest known name (a misspelling
would otherwise run with the default).  The nodes are created with
``automatically_declare_parameters_from_overrides=True`` (:data:`NODE_OPTIONS`) so
that every name given is visible through ``get_parameters_by_prefix('')``.
The tables are also the source of the parameter tables in the README and of the
example files ``config/<node>.params.yaml`` (a test checks they agree).
"""

from __future__ import annotations

from dataclasses import dataclass
from types import SimpleNamespace
from typing import Any

from imu_array_ros.calibration.geometry import DEFAULT_METHOD, METHODS, MIN_EXCITATION
from imu_array_ros.errors import ConfigError
from imu_array_ros.util.names import did_you_mean

__all__ = ["Param", "DRIVER_PARAMS", "FUSION_PARAMS", "CALIBRATION_PARAMS", "declare", "NODE_PARAMS", "NODE_OPTIONS",
           "ROS_PARAMS", "unknown_parameters"]

#: keyword arguments of ``rclpy.node.Node`` for a node that checks its parameter names with :func:`declare`
NODE_OPTIONS = {"automatically_declare_parameters_from_overrides": True}

#: parameters of ROS itself, allowed on every node (and names starting with ``qos_overrides.``)
ROS_PARAMS = ("use_sim_time", "start_type_description_service")


@dataclass(frozen=True)
class Param:
    """One parameter: name, default (its type is the parameter's type), description,
    optional numeric range [low, high], optional choices, required (non-empty string)."""

    name: str
    default: Any
    description: str
    low: float | None = None
    high: float | None = None
    choices: tuple = ()
    required: bool = False
    read_only: bool = True


_COMMON = (
    Param("array_config", "", "array description YAML (IMU names, positions, noise)", required=True),
    Param("topic_prefix", "/imu_array", "topics are <topic_prefix>/<imu name>/data_raw and <topic_prefix>/fused/..."),
    Param("frame_prefix", "", "raw messages carry header.frame_id = <frame_prefix><imu name>"),
    Param("reliable", False, "raw IMU topics reliable throughout: the serial driver publishes reliable (keeping "
          "the last 1000), the fusion and calibration nodes subscribe reliable keep-all (a best-effort publisher "
          "then cannot connect); false: serial publishes sensor-data (best effort, depth 5), replay reliable, and "
          "the subscriptions start reliable keep-all and switch a topic to best effort (keeping the last 1000) "
          "when a best-effort publisher appears on it"),
)

DRIVER_PARAMS = _COMMON + (
    Param("mode", "serial", "'serial': an OpenShoe array on 'port'; 'replay': the recording 'bag'",
          choices=("serial", "replay")),
    Param("port", "/dev/ttyUSB0", "serial port of the array (or the path 'imu-array fake-device' prints)"),
    Param("baud", 115200, "serial baud rate (ignored by USB/Bluetooth virtual ports)", 1200, 4_000_000),
    Param("imu_mask", 0, "IMUs to stream, bit k = IMU k; 0 = the lowest K bits for the K IMUs of array_config",
          0, 2**32 - 1),
    Param("rate_divider", 5, "OpenShoe output rate 1000 Hz / 2**(d-1): 1 = 1 kHz ... 5 = 62.5 Hz ... 7", 1, 7),
    Param("bag", "", "replay: recording to play (rosbag2 directory or .mcap file)"),
    Param("rate", 1.0, "replay speed factor; 0 = as fast as possible without loss (reliable, keep-all QoS)",
          0.0, 1000.0),
    Param("loop", False, "replay: start again at the end (stamps keep increasing)"),
    Param("restamp", False, "replay: stamp samples with the time they are published instead of the recorded time"),
    Param("wait_for_subscribers", -1, "wait until every IMU topic has this many subscribers (at most "
          "'wait_timeout') before starting the replay / the serial stream; -1 = 1 in replay, 0 in serial", -1, 1000),
    Param("wait_timeout", 10.0, "seconds to wait for the subscribers of 'wait_for_subscribers' before starting "
          "anyway (logged); 0 = wait forever", 0.0, 3600.0),
    Param("start_delay", -1.0, "seconds between the subscribers of 'wait_for_subscribers' matching and the "
          "first sample, so that the fusion node's own subscribers (yours of the fused topics) have matched it "
          "too; -1 = 2 s in replay when waiting for subscribers, else 0", -1.0, 60.0),
    Param("exit_at_end", False, "replay: exit when the recording has been played (and acknowledged)"),
    Param("poll_period", 0.002, "seconds between reads of the port / replay steps", 0.0005, 1.0),
    Param("publish_clock", True, "replay: publish /clock (rosgraph_msgs/Clock) with the time of the replayed stamps "
          "(the recording's; with 'restamp' the publish time), paced with the replay and ahead of the samples of that "
          "time, for nodes run with use_sim_time:=true (the driver itself stays on the system clock); ignored in "
          "serial mode"),
    Param("publish_frames", True, "publish the IMU frames of array_config on /tf_static at start (array frame_id -> "
          "<frame_prefix><imu name>; needs tf2_msgs, a full ROS install); false when another node publishes them, "
          "e.g. the fusion node with a calibration_file"),
)

#: sync_timeout -1 (by QoS): seconds while every raw topic is reliable (a message is late, not lost), and once
#: one is best effort (a missing message is lost)
SYNC_TIMEOUT_RELIABLE_S, SYNC_TIMEOUT_BEST_EFFORT_S = 5.0, 0.05


def sync_timeout_s(value: float, all_reliable: bool) -> float:
    """The ``sync_timeout`` parameter's seconds: itself when >= 0, else by QoS."""
    if value >= 0:
        return float(value)
    return SYNC_TIMEOUT_RELIABLE_S if all_reliable else SYNC_TIMEOUT_BEST_EFFORT_S


FUSION_PARAMS = _COMMON + (
    Param("calibration_file", "", "calibrated description YAML; used instead of array_config's values when "
          "present, and reloaded whenever it changes on disk", read_only=True),
    Param("sync_timeout", -1.0, "seconds an array sample waits for missing IMUs before it is fused without them; "
          "-1 = by QoS: 5 s while every raw topic is reliable (a message is late, not lost: a retransmission can "
          "take the writer's heartbeat period, up to 3 s, on a loaded machine), 0.05 s once one is best effort", -1.0, 10.0),
    Param("max_batch", 1000, "most samples per fusion call", 1, 1_000_000),
    Param("period", 0.005, "seconds between timer sweeps (fusion is event-driven: a sample is fused when its last message arrives; the timer fuses batches when behind and samples that timed out)", 0.0005, 1.0),
    Param("watch_period", 0.5, "seconds between checks of calibration_file", 0.05, 60.0),
    Param("stamps", "common", "'common': every IMU's message of an array sample carries the same stamp; 'own': "
          "the IMUs stamp their messages with their own clocks: paired onto the reference IMU's stamps, their "
          "clocks estimated live", choices=("common", "own")),
    Param("reference_imu", "", "stamps 'own': the IMU whose stamps are the grid the fused messages come on; '' = "
          "the first IMU"),
    Param("session_window", 20.0, "sample clocks or own stamps: seconds of the latest samples the session states "
          "(clock phases, common clock rate, stamp-clock offsets and skews) are estimated from (needs 2 s of "
          "motion in it)", 2.0, 600.0),
    Param("session_interval", 30.0, "seconds (of stamps) between re-estimates of the session states while the array "
          "moves", 1.0, 3600.0),
    Param("bias_tracking", True, "re-measure the gyroscope biases on every still interval of 1 s or more and fuse "
          "with them from then on (published in /diagnostics); false: the description's biases throughout"),
    Param("timed_batch", 0.05, "time-aware fusion (timing terms or own stamps): least seconds of samples fused per "
          "call (a call costs ~10 ms for 32 IMUs); adds up to this to the latency", 0.0, 1.0),
    Param("publish_frames", True, "publish the IMU frames of the description in use (calibration_file's when "
          "present) on /tf_static at start and after every calibration reload (array frame_id -> <frame_prefix><imu "
          "name>; needs tf2_msgs, a full ROS install)"),
)

CALIBRATION_PARAMS = _COMMON + (
    Param("output_file", "", "calibrated description YAML the service writes (atomically, the previous one kept as "
          "<output_file>.bak; give it to fusion_node as calibration_file); if it exists and is a description of "
          "the array, calibrations start from it", required=True),
    Param("window", 10.0, "seconds of the latest array samples (by stamp) the calibration uses", 0.1, 600.0),
    Param("window_samples", 0, "number of the latest array samples the calibration uses; 0 = those of 'window'",
          0, 1_000_000),
    Param("reference_imu", "", "IMU whose position is held (only relative positions are observable); "
          "'' = the first IMU"),
    Param("min_excitation", MIN_EXCITATION, "a sample is used when the Frobenius norm of [omega]x^2 + [omega_dot]x "
          "reaches this (rad/s^2): still samples carry no information about the positions", 0.0, 1e6),
    Param("method", DEFAULT_METHOD, "'joint': Gauss-Newton on positions and motion together; 'bcd': block "
          "coordinate descent (carlsson2017 Alg. 1)", choices=METHODS),
    Param("max_iterations", 0, "iteration cap of the solver; 0 = the solver's default", 0, 100_000),
    Param("sync_timeout", -1.0, "seconds an array sample waits for missing IMUs before it is buffered without "
          "them (the calibration skips incomplete samples); -1 = by QoS, as the fusion node: 5 s while every raw "
          "topic is reliable, 0.05 s once one is best effort", -1.0, 10.0),
    Param("period", 0.01, "seconds between buffering steps (decoding the queued messages)", 0.0005, 1.0),
)

NODE_PARAMS = {"driver_node": DRIVER_PARAMS, "fusion_node": FUSION_PARAMS, "calibration_node": CALIBRATION_PARAMS}


def _range_text(p: Param) -> str:
    return f"in [{p.low:g}, {p.high:g}]"


def unknown_parameters(given, params: tuple[Param, ...]) -> str | None:
    """The refusal for names in ``given`` that are neither in ``params`` nor ROS's own; None if all are known."""
    known = [p.name for p in params]
    unknown = sorted(n for n in given if n not in known and n not in ROS_PARAMS and not n.startswith("qos_overrides."))
    if not unknown:
        return None
    parts = []
    for name in unknown:
        near = did_you_mean(name, known)
        parts.append(f"'{name}'" + (f" (did you mean '{near}'?)" if near else ""))
    s = "s" if len(unknown) > 1 else ""
    return f"unknown parameter{s} {', '.join(parts)}"


def declare(node, params: tuple[Param, ...]) -> SimpleNamespace:
    """Declare ``params`` on an rclpy node with descriptors; return the checked values.

    Raises ConfigError (one line naming the parameter) for an unknown parameter name
    given to the node (created with :data:`NODE_OPTIONS`), a wrong type, a value out
    of range or not among the choices, or a missing required value.
    """
    from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
    from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException

    refusal = unknown_parameters(node.get_parameters_by_prefix(""), params)
    if refusal:
        raise ConfigError(refusal)
    values = {}
    for p in params:
        if node.has_parameter(p.name):  # declared from an override, untyped: declared again with its descriptor
            node.undeclare_parameter(p.name)
        desc = ParameterDescriptor(description=p.description, read_only=p.read_only)
        if p.choices:
            desc.additional_constraints = "one of: " + ", ".join(p.choices)
        if p.low is not None and isinstance(p.default, float):
            desc.floating_point_range = [FloatingPointRange(from_value=float(p.low), to_value=float(p.high))]
        elif p.low is not None and isinstance(p.default, int) and not isinstance(p.default, bool):
            desc.integer_range = [IntegerRange(from_value=int(p.low), to_value=int(p.high))]
        try:
            value = node.declare_parameter(p.name, p.default, desc).value
        except InvalidParameterTypeException as err:
            raise ConfigError(f"parameter '{p.name}': expected {type(p.default).__name__} ({err})") from None
        except InvalidParameterValueException:
            raise ConfigError(f"parameter '{p.name}': must be {_range_text(p)}") from None
        if isinstance(p.default, float) and isinstance(value, int):
            value = float(value)
        if p.choices and value not in p.choices:
            raise ConfigError(f"parameter '{p.name}': {value!r} is not one of {', '.join(p.choices)}")
        if p.low is not None and not (p.low <= value <= p.high):
            raise ConfigError(f"parameter '{p.name}': {value!r} is not {_range_text(p)}")
        if p.required and not value:
            raise ConfigError(f"parameter '{p.name}' is required ({p.description})")
        values[p.name] = value
    return SimpleNamespace(**values)
