"""A reconnecting, non-blocking serial link to an OpenShoe/MIMU array (ROS-free side of ``driver_node``).

:class:`SerialArrayLink` spawns no thread and never blocks: its owner (the node's
timer, a test loop) calls :meth:`~SerialArrayLink.poll`, which reads what the port
holds, frames it with :class:`~imu_array_ros.io.openshoe.framing.OpenShoeFramer`,
unwraps the ticks and maps them to host time with a
:class:`~imu_array_ros.io.openshoe.clock.DeviceClock`.  Only framer-accepted
packets (size byte and checksum valid) come out: never a corrupt sample.

States (``stats.state``): ``disconnected`` -(open, start command sent)->
``waiting_ack`` -(``A0 28 00 C8``)-> ``streaming``; any ``SerialException`` /
``OSError`` (port vanished) -> ``disconnected``.

* **Data before the start acknowledgement is discarded** (``stats.packets_before_ack``):
  it may come from an earlier session with another IMU mask or rate, which would
  frame fine with the same IMU count yet carry other sensors.  Without an ack
  within ``ack_timeout`` the start command is re-sent (``stats.start_retries``).
* After a failure, opening is retried on later polls, waiting ``backoff[0]``
  doubling up to ``backoff[1]`` seconds (back to ``backoff[0]`` once streaming);
  each connection gets a new framer and tick unwrapper, a clock reset and the
  start command.  A packet counter stepping backwards (by more than half its
  range) is a device restart: unwrapper and clock start again there.
* :meth:`~SerialArrayLink.close` sends the stop command ``22 00 22`` (errors ignored).
  Timeouts use ``time.monotonic``; stamps use ``now`` (the node passes the ROS clock).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, replace
from typing import Callable

import numpy as np
import serial

from imu_array_ros.io.openshoe.clock import DeviceClock
from imu_array_ros.io.openshoe.framing import OpenShoeFramer, ParsedPackets, TickUnwrapper, counts_to_si
from imu_array_ros.io.openshoe.protocol import (START_ACK, STOP_COMMAND, default_imu_mask, mask_bits,
                                                output_rate_hz, start_command)

__all__ = ["LinkBatch", "LinkStats", "SerialArrayLink"]

_FRAMER_COUNTS = ("packets", "bad_checksums", "garbage_bytes", "counter_gaps", "counter_backsteps", "acks", "bytes_in")


@dataclass
class LinkBatch:
    """Samples from one :meth:`SerialArrayLink.poll`, in stream order (M may be 0).

    stamps_ns (M,) int64 host time, ns (DeviceClock); device_ns (M,) int64 unwrapped device
    time, ns (starts again on reconnect/device restart); counter (M,) uint16; raw (M, K, 6)
    int16 counts; accel (M, K, 3) m/s^2; gyro (M, K, 3) rad/s; sensor axes.
    """

    stamps_ns: np.ndarray
    device_ns: np.ndarray
    counter: np.ndarray
    raw: np.ndarray
    accel: np.ndarray
    gyro: np.ndarray

    @classmethod
    def empty(cls, n_imus: int) -> "LinkBatch":
        z = np.zeros(0, np.int64)
        return cls(z, z.copy(), np.zeros(0, np.uint16), np.zeros((0, n_imus, 6), np.int16),
                   np.zeros((0, n_imus, 3)), np.zeros((0, n_imus, 3)))

    def __len__(self) -> int:
        return len(self.stamps_ns)


@dataclass
class LinkStats:
    """Link counters, summed over connections.  reconnects: successful opens after the first;
    packets ... bytes_in: as in :class:`~imu_array_ros.io.openshoe.framing.FramerStats`
    (packets includes packets_before_ack); last_error: last port error ('' if none)."""

    state: str = "disconnected"
    connects: int = 0
    reconnects: int = 0
    start_retries: int = 0
    packets: int = 0
    bad_checksums: int = 0
    garbage_bytes: int = 0
    counter_gaps: int = 0
    counter_backsteps: int = 0
    acks: int = 0
    bytes_in: int = 0
    packets_before_ack: int = 0
    device_restarts: int = 0
    last_error: str = ""

    def as_dict(self) -> dict:
        """Field name -> value (e.g. for diagnostics key/values)."""
        return asdict(self)


class SerialArrayLink:
    """Non-blocking OpenShoe link on ``port`` for ``n_imus`` IMUs (see module docstring).

    port: device path or pyserial URL (``serial.serial_for_url``).  n_imus: K, IMUs
    per packet, = bits set in ``imu_mask`` (default: the lowest K bits).  baud:
    ignored by pseudo-terminals and most USB bridges.  rate_divider: output rate
    1000 Hz / 2**(d-1), d = 1..7 (default 5: 62.5 Hz).  ack_timeout: seconds
    before the start command is re-sent.  backoff: (first, longest) wait between
    reopen attempts, s.  clock: a :class:`DeviceClock` (default a new one).
    now: host clock for the stamps, () -> ns (default ``time.time_ns``).
    require_next_header: passed to the framer (stronger resync, one packet later).
    """

    def __init__(self, port: str, n_imus: int, *, baud: int = 115200, imu_mask: int | None = None,
                 rate_divider: int = 5, ack_timeout: float = 1.0, backoff: tuple[float, float] = (0.2, 5.0),
                 clock: DeviceClock | None = None, now: Callable[[], int] = time.time_ns,
                 require_next_header: bool = False) -> None:
        self.imu_mask = default_imu_mask(n_imus) if imu_mask is None else imu_mask
        if len(mask_bits(self.imu_mask)) != n_imus:
            raise ValueError(f"imu_mask 0x{self.imu_mask:08X} selects {len(mask_bits(self.imu_mask))} IMUs, "
                             f"but n_imus is {n_imus}")
        self.rate_hz = output_rate_hz(rate_divider)
        if ack_timeout <= 0 or not 0 < backoff[0] <= backoff[1]:
            raise ValueError(f"ack_timeout must be > 0 and backoff (min, max) with 0 < min <= max, "
                             f"got {ack_timeout}, {backoff}")
        self.port, self.n_imus, self.baud = str(port), int(n_imus), int(baud)
        self.start = start_command(self.imu_mask, rate_divider)
        self.ack_timeout, self.backoff = float(ack_timeout), (float(backoff[0]), float(backoff[1]))
        self.clock = DeviceClock() if clock is None else clock
        self._now, self._require_next_header = now, bool(require_next_header)
        self._stats, self._done = LinkStats(), dict.fromkeys(_FRAMER_COUNTS, 0)  # _done: closed connections
        self._ser, self._framer = None, None
        self._wait, self._next_open, self._ack_deadline = self.backoff[0], 0.0, 0.0  # s, time.monotonic
        self._carry = b""  # last 3 bytes while waiting for the ack (an ack split over reads)
        self._unwrapper, self._last_counter = TickUnwrapper(), None

    @property
    def stats(self) -> LinkStats:
        """A snapshot of the counters (framer counts summed over connections)."""
        s = replace(self._stats)
        for k in _FRAMER_COUNTS:
            setattr(s, k, self._done[k] + (getattr(self._framer.stats, k) if self._framer else 0))
        return s

    @property
    def state(self) -> str:
        """'disconnected', 'waiting_ack' or 'streaming'."""
        return self._stats.state

    def poll(self, max_bytes: int = 1 << 16) -> LinkBatch:
        """Do what is due (open, re-send start), read up to ``max_bytes``; the new samples (never blocks)."""
        mono = time.monotonic()
        if self._ser is None:
            if mono < self._next_open:
                return LinkBatch.empty(self.n_imus)
            self._open(mono)
            if self._ser is None:
                return LinkBatch.empty(self.n_imus)
        try:
            if self._stats.state == "waiting_ack" and mono >= self._ack_deadline:
                self._ser.write(self.start)
                self._stats.start_retries += 1
                self._ack_deadline = mono + self.ack_timeout
            data = self._ser.read(max_bytes)
        except (serial.SerialException, OSError) as err:
            self._lost(err, mono)
            return LinkBatch.empty(self.n_imus)
        if self._stats.state == "waiting_ack":
            data = self._skip_to_ack(data)
        return self._decode(self._framer.feed(data)) if data else LinkBatch.empty(self.n_imus)

    def close(self) -> None:
        """Send the stop command if the port is open (errors ignored) and close it."""
        if self._ser is not None:
            try:
                self._ser.write(STOP_COMMAND)
            except (serial.SerialException, OSError):
                pass
            self._drop_port()
        self._stats.state = "disconnected"

    def __enter__(self) -> "SerialArrayLink":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _open(self, mono: float) -> None:
        try:
            self._ser = serial.serial_for_url(self.port, baudrate=self.baud, timeout=0, write_timeout=0)
            self._ser.write(self.start)
        except (serial.SerialException, OSError, ValueError) as err:
            self._lost(err, mono)
            return
        self._stats.connects += 1
        self._stats.reconnects += self._stats.connects > 1
        self._framer = OpenShoeFramer(self.n_imus, require_next_header=self._require_next_header)
        self._unwrapper, self._last_counter, self._carry = TickUnwrapper(), None, b""
        self.clock.reset()
        self._stats.state, self._ack_deadline = "waiting_ack", mono + self.ack_timeout

    def _lost(self, err: Exception, mono: float) -> None:
        """Port failed (open, read or write): close, schedule the next attempt with backoff."""
        self._stats.last_error, self._stats.state = f"{self.port}: {err}", "disconnected"
        self._drop_port()
        self._next_open, self._wait = mono + self._wait, min(2 * self._wait, self.backoff[1])

    def _drop_port(self) -> None:
        if self._framer is not None:
            for k in _FRAMER_COUNTS:
                self._done[k] += getattr(self._framer.stats, k)
            self._framer = None
        if self._ser is not None:
            try:
                self._ser.close()
            except (serial.SerialException, OSError):
                pass
            self._ser = None

    def _skip_to_ack(self, data: bytes) -> bytes:
        """Feed the framer up to and including the start ack (packets discarded); the bytes after it."""
        i = (self._carry + data).find(START_ACK)
        if i < 0:
            self._stats.packets_before_ack += len(self._framer.feed(data))
            self._carry = (self._carry + data)[-(len(START_ACK) - 1):]
            return b""
        end = i + len(START_ACK) - len(self._carry)  # ack end within data (>= 1)
        self._stats.packets_before_ack += len(self._framer.feed(data[:end]))
        self._stats.state, self._wait = "streaming", self.backoff[0]
        return data[end:]

    def _decode(self, p: ParsedPackets) -> LinkBatch:
        if len(p) == 0:
            return LinkBatch.empty(self.n_imus)
        host_ns = int(self._now())
        c = p.counter.astype(np.int64)
        prev = c[0] if self._last_counter is None else self._last_counter
        back = np.flatnonzero((np.diff(np.concatenate([[prev], c])) % 65536) > 32768)  # device restarts
        self._last_counter = int(c[-1])
        device_ns, stamps = np.empty(len(c), np.int64), np.empty(len(c), np.int64)
        cuts = np.concatenate([[0], back, [len(c)]])
        for j in range(len(cuts) - 1):  # one segment per device restart (rare)
            lo, hi = int(cuts[j]), int(cuts[j + 1])
            if j > 0:
                self._stats.device_restarts += 1
                self._unwrapper = TickUnwrapper()
                self.clock.reset()
            if hi > lo:
                device_ns[lo:hi] = self._unwrapper.to_ns(p.ticks[lo:hi])
                stamps[lo:hi] = self.clock.map(device_ns[lo:hi], host_ns)
        accel, gyro = counts_to_si(p.raw)
        return LinkBatch(stamps, device_ns, p.counter, p.raw, accel, gyro)
