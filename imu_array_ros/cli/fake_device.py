"""``imu-array fake-device``: a simulated OpenShoe array on a pseudo-terminal, for use without hardware.

Prints the port path (a symlink that stays valid across a simulated unplug)
as the only line on stdout, so a script can read it and start the driver on
it; progress and the final summary go to stderr (``-q`` silences them).  The
data plays once a host sends the start command; the command runs until Ctrl-C
or SIGTERM (exit 0, symlink removed) or, without ``--loop``, until all data
was sent and read.

``--speed`` other than 1 (and 0) plays the data faster or slower while the device
clock keeps real time: the packets' device timestamps are rescaled by 1/speed (as
a device sampling ``speed`` x faster), so the driver's stamps follow the host
clock.  (A device clock running at ``speed`` x real time made the driver's clock
filter re-anchor again and again, stepping stamps back: the fusion node dropped
most messages as "backwards".)  A capture is then re-encoded, not byte for byte.
"""

from __future__ import annotations

import argparse
import signal
import threading
from pathlib import Path

import numpy as np

from imu_array_ros import workflows
from imu_array_ros.cli.options import MAX_SIMULATED_SAMPLES, non_negative_float, non_negative_int, positive_float
from imu_array_ros.cli.progress import info
from imu_array_ros.errors import ImuArrayError

__all__ = ["add_parser", "run", "probability", "openshoe_rate", "real_time_ticks"]

_DRAIN_S = 2.0  # after the last byte: how long the host may take to read what is buffered


def probability(text: str) -> float:
    """A number in [0, 1) (a per-bit or per-byte fault rate)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not 0 <= value < 1:
        raise argparse.ArgumentTypeError(f"must lie in [0, 1), got {text!r}")
    return value


def openshoe_rate(text: str) -> float:
    """A rate an OpenShoe device streams at: 1000, 500, 250, 125, 62.5, 31.25 or 15.625 Hz."""
    from imu_array_ros.io.openshoe.protocol import output_rate_hz, rate_divider_for

    try:
        return output_rate_hz(rate_divider_for(float(text)))
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err).replace(f"got {float(text)!r}", f"got {text!r}")) from None


def real_time_ticks(ticks, speed: float) -> np.ndarray:
    """Device timestamps (uint32, 64 MHz) rescaled by 1/``speed`` from the first: played at ``speed`` x
    the data's own pace, they advance in real time.  (N,) uint32."""
    from imu_array_ros.io.openshoe.framing import TickUnwrapper

    t = TickUnwrapper().unwrap(np.asarray(ticks).astype(np.uint32))
    scaled = t[0] + np.round((t - t[0]) / float(speed)).astype(np.int64)
    return (scaled % (1 << 32)).astype(np.uint32)


def add_parser(subparsers) -> argparse.ArgumentParser:
    sp = subparsers.add_parser("fake-device", help="simulated OpenShoe array on a pseudo-terminal (no hardware needed)")
    sp.add_argument("--array", required=True, type=Path,
                    help="array description YAML: the number of IMUs per packet (and the sensor model when simulating)")
    sp.add_argument("--capture", type=Path,
                    help="raw capture to replay byte for byte (e.g. exp_1.bin; IMU order = capture order); "
                         "default: simulated hand twisting")
    sp.add_argument("--duration", type=positive_float, help="simulated seconds, > 0 (default 60)")
    sp.add_argument("--rate", type=openshoe_rate, metavar="HZ",
                    help="simulated sample rate: 1000, 500, 250, 125, 62.5, 31.25 or 15.625 Hz (default 1000; "
                         "the host's rate divider decimates it)")
    sp.add_argument("--seed", type=non_negative_int, help="seed of the simulated motion and noise and of the "
                                                          "faults, >= 0 (default 0)")
    sp.add_argument("--link", type=Path, metavar="PATH",
                    help="symlink to create for the port (default: in a new temporary directory); an existing PATH "
                         "is replaced only if it is a symlink to a pseudo-terminal")
    sp.add_argument("--speed", type=non_negative_float, default=1.0,
                    help="playback speed, x real time, >= 0; 0 = as fast as the port is read (default 1); the device "
                         "clock keeps real time (it reads as a device sampling speed x faster)")
    sp.add_argument("--loop", action="store_true", help="replay the data forever (default: stop at its end)")
    sp.add_argument("--garbage-every", type=non_negative_int, default=0, metavar="N",
                    help="insert random bytes after every N-th packet (default 0: never)")
    sp.add_argument("--bit-error-rate", type=probability, default=0.0, metavar="P",
                    help="probability of flipping each bit, 0 <= P < 1 (default 0)")
    sp.add_argument("--drop-byte-rate", type=probability, default=0.0, metavar="P",
                    help="probability of losing each byte, 0 <= P < 1 (default 0)")
    sp.add_argument("--unplug-at", type=positive_float, metavar="SECONDS",
                    help="simulate unplugging this many seconds after the port appears (the host must reconnect "
                         "and send the start command again)")
    sp.add_argument("--unplug-duration", type=non_negative_float, default=1.0, metavar="SECONDS",
                    help="seconds the device stays unplugged, >= 0 (default 1)")
    sp.add_argument("-q", "--quiet", action="store_true", help="only the port path on stdout (errors still appear)")
    sp.set_defaults(handler=run)
    return sp


class _Terminated(Exception):
    """SIGTERM, turned into an exception so the device closes cleanly."""


def run(
    *,
    array: Path,
    capture: Path | None = None,
    duration: float | None = None,
    rate: float | None = None,
    seed: int | None = None,
    link: Path | None = None,
    speed: float = 1.0,
    loop: bool = False,
    garbage_every: int = 0,
    bit_error_rate: float = 0.0,
    drop_byte_rate: float = 0.0,
    unplug_at: float | None = None,
    unplug_duration: float = 1.0,
    quiet: bool = False,
) -> int:
    """Serve ``capture`` (or simulated hand twisting: ``duration`` s at ``rate`` Hz) as a fake device.

    ``array`` gives K (IMUs per packet) and, when simulating, the sensor model.
    ``link``: symlink to create (default in a new temporary directory); an
    existing path is replaced only if it is a symlink to a pseudo-terminal.
    ``seed`` seeds the simulation and the faults.  Faults and pacing as in
    :class:`~imu_array_ros.io.openshoe.fake_device.FakeArrayDevice` (``unplug_at``:
    seconds after the port appears).
    """
    from imu_array_ros.io.openshoe.fake_device import FakeArrayDevice, check_link

    if link is not None:
        check_link(Path(link))  # before any work
    desc, _ = workflows.load_array(array)
    k = len(desc.imus)
    if k > 32:
        raise ImuArrayError(f"{array}: describes {k} IMUs, but the OpenShoe IMU mask selects at most 32")
    faults = dict(link=link, speed=speed, loop=loop, garbage_every=garbage_every, bit_error_rate=bit_error_rate,
                  drop_byte_rate=drop_byte_rate, unplug_at=unplug_at, unplug_duration=unplug_duration,
                  seed=0 if seed is None else seed, record_packets=False)
    if capture is not None:
        given = [name for name, v in (("--duration", duration), ("--rate", rate)) if v is not None]
        if given:
            raise ImuArrayError(f"{' and '.join(given)}: only for simulated data, not with --capture")
        device = _capture_device(FakeArrayDevice, Path(capture), k, faults)
        what = f"{Path(capture).name}"
    else:
        from imu_array_ros.simulation.simulator import simulate_twist

        duration = 60.0 if duration is None else duration
        rate = 1000.0 if rate is None else rate
        n = int(round(duration * rate))
        if not 1 <= n <= MAX_SIMULATED_SAMPLES:
            raise ImuArrayError(f"--duration {duration:g} s at --rate {rate:g} Hz gives {n} samples "
                                f"(need 1..{MAX_SIMULATED_SAMPLES})")
        samples, _ = simulate_twist(desc, duration, rate, np.random.default_rng(faults["seed"]))
        if speed not in (0.0, 1.0):  # the device clock keeps real time (see the module docstring)
            from imu_array_ros.io.openshoe.fake_device import samples_to_counts, stamps_to_ticks

            counts = samples_to_counts(samples.accel, samples.gyro)
            ticks = real_time_ticks(stamps_to_ticks(samples.stamps), speed)
            device = FakeArrayDevice.from_samples(counts, ticks, **{**faults, "speed": 1.0})
        else:
            device = FakeArrayDevice.from_imu_samples(samples, **faults)
        what = f"simulated twisting, {duration:g} s at {rate:g} Hz"
    old = _on_sigterm()
    try:
        print(device.port, flush=True)
        info(quiet, f"fake-device: {k} IMUs, {len(device.raw)} samples ({what}) on {device.tty} via {device.port}; "
                    f"waiting for the start command{'' if loop else ' (stops at the end of the data)'}; Ctrl-C to stop")
        seen = 0
        while not device.wait_finished(0.2, drained=False):
            seen = _say_commands(device.record, seen, quiet)
        device.wait_finished(_DRAIN_S)
    except (KeyboardInterrupt, _Terminated):
        pass
    finally:
        device.close()
        if old is not None:
            signal.signal(signal.SIGTERM, old)
    r = device.record
    info(quiet, f"fake-device: sent {r.packets_sent} packets ({r.corrupted_packets} corrupted: {r.bits_flipped} "
                f"bits flipped, {r.bytes_dropped} bytes dropped; {r.garbage_bytes} garbage bytes), "
                f"{len(r.commands)} commands ({r.bad_commands} bad), {r.unplugs} unplugs")
    if device.error is not None:
        raise ImuArrayError(f"fake-device: stopped early: {device.error}")
    return 0


def _say_commands(record, seen: int, quiet: bool) -> int:
    """One console line per start or stop the host sent since the ``seen`` first commands; the new count.
    A real device keeps running when its host stops, so the fake one waits for the next start: say so."""
    from imu_array_ros.io.openshoe.protocol import START_RAW_IMU, STOP_OUTPUT

    for cmd in record.commands[seen:]:
        if cmd.code == START_RAW_IMU:
            info(quiet, "fake-device: the host started the stream")
        elif cmd.code == STOP_OUTPUT:
            info(quiet, f"fake-device: the host stopped the stream ({record.packets_sent} packets sent so far); "
                        "waiting for the next start, as a device would (Ctrl-C to stop)")
    return len(record.commands)


def _capture_device(device_class, capture: Path, k: int, faults: dict):
    """The device for a capture; with a speed other than 0 and 1 its timestamps rescaled to real time."""
    speed = faults["speed"]
    if speed in (0.0, 1.0):
        return device_class.from_capture(capture, k, **faults)
    from imu_array_ros.io.openshoe.framing import packet_length, parse_buffer

    try:
        data = capture.read_bytes()
    except OSError:
        return device_class.from_capture(capture, k, **faults)  # its one-line error
    p, _ = parse_buffer(data, k)
    if len(p) * packet_length(k) < 0.5 * len(data):
        return device_class.from_capture(capture, k, **faults)  # its one-line error
    return device_class(p.counter, real_time_ticks(p.ticks, speed), p.raw, **{**faults, "speed": 1.0})


def _on_sigterm():
    """SIGTERM -> :class:`_Terminated` in the main thread (a clean exit); the previous handler, or None."""
    if threading.current_thread() is not threading.main_thread():
        return None

    def handler(signum, frame):
        raise _Terminated()

    return signal.signal(signal.SIGTERM, handler)
