"""A simulated OpenShoe/MIMU array on a pseudo-terminal, for users and tests without hardware.

:class:`FakeArrayDevice` opens a pseudo-terminal (``os.openpty``, slave in raw
mode) and exposes it through a symlink at a stable path (``link``; default a
new temporary directory), which survives a simulated unplug.  A background
thread answers the host commands of :mod:`~imu_array_ros.io.openshoe.protocol`
(start ``0x28`` -> ack, then packets with the selected IMUs at the requested
rate; stop ``0x22`` -> ack, stop; bad checksums ignored) and streams packets
in real time, paced by their device timestamps (``speed`` x real time;
``speed=0``: as fast as the pseudo-terminal accepts).

Sources:

* :meth:`FakeArrayDevice.from_capture`: a real capture, played **byte for
  byte** (the file's leading acknowledgement is skipped: the device sends its
  own) when the host selects all of the capture's IMUs at the capture's rate;
* :meth:`FakeArrayDevice.from_samples` / :meth:`FakeArrayDevice.from_imu_samples`:
  packets built with :func:`~imu_array_ros.io.openshoe.framing.encode_packets`
  (e.g. from the simulator, via :func:`samples_to_counts`).

A start selecting a subset of the IMUs (mask bits = ``imu_bits``, default
0..K-1), or a lower rate (the source is decimated by ``round(source rate /
requested rate)``; a higher rate than the source is served at the source
rate), or a later pass of ``loop`` re-encodes the packets, numbered
consecutively from the first one's counter (loops continue ticks and counters).
A start while streaming switches to the new selection at the next packet; a
stop keeps the position for the next start.

Faults: ``garbage_every`` N (random 1..L bytes after every N-th packet),
``bit_error_rate`` (independent bit flips), ``drop_byte_rate`` (bytes lost),
``unplug_at`` seconds after creation (pseudo-terminal and symlink removed for
``unplug_duration`` s, then a new one behind the same symlink; the device has
forgotten the start, so the host must send it again), ``ignore_commands`` N
(the first N valid commands get no answer).  :attr:`FakeArrayDevice.record`
says what was sent and which packets were corrupted, so a test can check that
everything a host delivered was sent intact.
"""

from __future__ import annotations

import fcntl
import os
import select
import tempfile
import termios
import threading
import time
import tty
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from imu_array_ros.errors import CaptureError, OutputError
from imu_array_ros.io.openshoe.capture import guess_imu_count
from imu_array_ros.io.openshoe.framing import (
    ACC_SCALE, GYRO_SCALE, TICK_HZ, ParsedPackets, TickUnwrapper, encode_packets, packet_length, parse_buffer)
from imu_array_ros.io.openshoe.protocol import (
    START_RAW_IMU, STOP_OUTPUT, Command, CommandParser, ack_for, output_rate_hz)

__all__ = ["DeviceRecord", "FakeArrayDevice", "check_link", "samples_to_counts", "stamps_to_ticks"]

_PTY_PREFIXES = ("/dev/pts/", "/dev/ttys", "/dev/pty")
_OUT_HIGH = 1 << 16  # speed 0: generate more packets when fewer bytes than this wait


def samples_to_counts(accel: np.ndarray, gyro: np.ndarray) -> np.ndarray:
    """Inverse of :func:`~imu_array_ros.io.openshoe.framing.counts_to_si`: (N, K, 3) m/s^2 and rad/s ->
    (N, K, 6) int16 counts, rounded and clipped to the int16 range (NaN -> 0)."""
    c = np.concatenate([np.asarray(accel) / ACC_SCALE, np.asarray(gyro) / GYRO_SCALE], axis=-1)
    return np.clip(np.round(np.nan_to_num(c)), -32768, 32767).astype(np.int16)


def stamps_to_ticks(stamps_ns: np.ndarray) -> np.ndarray:
    """(N,) ns stamps -> (N,) uint32 64 MHz ticks counted from the first stamp (wrapping)."""
    s = np.asarray(stamps_ns, np.int64)
    return (((s - s[:1]) * 8 + 62) // 125 % (1 << 32)).astype(np.uint32)


@dataclass
class DeviceRecord:
    """What a :class:`FakeArrayDevice` received and sent (a copy: see :attr:`FakeArrayDevice.record`).

    streams: packets of each started stream (as encoded, before faults); sent /
    corrupted: per stream, indices of the packets written / of those with a
    flipped or dropped byte.  Counts: commands (valid, in order), bad_commands
    (bad checksum or invalid start), ignored_commands, acks_sent, packets_sent,
    corrupted_packets, garbage_bytes, bits_flipped, bytes_dropped, bytes_sent, unplugs.
    """

    commands: list[Command] = field(default_factory=list)
    bad_commands: int = 0
    ignored_commands: int = 0
    acks_sent: int = 0
    streams: list[ParsedPackets] = field(default_factory=list)
    sent: list[list[np.ndarray]] = field(default_factory=list)
    corrupted: list[list[np.ndarray]] = field(default_factory=list)
    packets_sent: int = 0
    corrupted_packets: int = 0
    garbage_bytes: int = 0
    bits_flipped: int = 0
    bytes_dropped: int = 0
    bytes_sent: int = 0
    unplugs: int = 0

    def sent_packets(self, stream: int, intact: bool = True) -> ParsedPackets:
        """Packets of ``stream`` that were written, only the uncorrupted ones if ``intact``."""
        p = self.streams[stream]
        idx = np.concatenate(self.sent[stream] or [np.zeros(0, np.int64)])
        if intact:
            idx = np.setdiff1d(idx, np.concatenate(self.corrupted[stream] or [np.zeros(0, np.int64)]))
        return ParsedPackets(p.counter[idx], p.ticks[idx], p.raw[idx], p.offsets[idx])


class FakeArrayDevice:
    """Simulated array behind a pseudo-terminal (see module docstring); starts at once, stop with :meth:`close`.

    counter (N,), ticks (N,) uint32 64 MHz, raw (N, K, 6) int16: the source
    packets.  data, offsets: for byte-exact replay, the stream bytes and (N+1,)
    offsets of each packet in it (last = len(data)).  imu_bits: mask bit of each
    source IMU (default 0..K-1).  Faults and pacing as in the module docstring;
    seed: random faults.  record_packets: keep every stream's packets and the
    sent/corrupted indices in :attr:`record` (set False for endless runs: the
    counts are kept either way).  With ``speed`` other than 1 the device clock
    runs at ``speed`` x real time, so host-mapped stamps are not meaningful.
    """

    def __init__(self, counter, ticks, raw, *, data: bytes | None = None, offsets=None, imu_bits=None,
                 link: str | Path | None = None, speed: float = 1.0, loop: bool = False, garbage_every: int = 0,
                 bit_error_rate: float = 0.0, drop_byte_rate: float = 0.0, unplug_at: float | None = None,
                 unplug_duration: float = 1.0, ignore_commands: int = 0, seed: int = 0,
                 record_packets: bool = True) -> None:
        self.raw = np.asarray(raw, np.int16)
        n, k = self.raw.shape[:2]
        if n < 1 or self.raw.shape[2:] != (6,):
            raise ValueError(f"raw must have shape (N >= 1, K, 6), got {self.raw.shape}")
        self.counter = np.asarray(counter).astype(np.uint16)
        self.ticks = np.asarray(ticks).astype(np.uint32)
        t = TickUnwrapper().unwrap(self.ticks)
        self.times = (t - t[0]) / TICK_HZ  # s
        self.period_ticks = int(t[-1] - t[0]) + (int(np.median(np.diff(t))) if n > 1 else TICK_HZ // 1000)
        self.rate_hz = TICK_HZ / (self.period_ticks / n)
        self.imu_bits = list(range(k)) if imu_bits is None else [int(b) for b in imu_bits]
        if len(self.imu_bits) != k:
            raise ValueError(f"imu_bits has {len(self.imu_bits)} entries for {k} IMUs")
        self._data, self._offsets = data, (None if offsets is None else np.asarray(offsets, np.int64))
        for name, p in (("bit_error_rate", bit_error_rate), ("drop_byte_rate", drop_byte_rate)):
            if not 0 <= p < 1:
                raise ValueError(f"{name} must lie in [0, 1), got {p}")
        if speed < 0 or garbage_every < 0:
            raise ValueError(f"speed and garbage_every must be >= 0, got {speed}, {garbage_every}")
        self.speed, self.loop, self.garbage_every = float(speed), bool(loop), int(garbage_every)
        self.bit_error_rate, self.drop_byte_rate = float(bit_error_rate), float(drop_byte_rate)
        self.unplug_at, self.unplug_duration = unplug_at, float(unplug_duration)
        self._ignore, self._keep = int(ignore_commands), bool(record_packets)
        self._rng = np.random.default_rng(seed)
        self._lock = threading.Lock()
        self._record = DeviceRecord()
        self._stop = threading.Event()
        self._finished = threading.Event()
        self._src_next, self._pass = 0, 0  # next source packet, loop pass
        self._streaming = False
        self._config: tuple[list[int], int] | None = None  # (source columns, decimation)
        self._out = b""
        self.error: Exception | None = None
        self._own_dir = None
        if link is None:
            self._own_dir = tempfile.mkdtemp(prefix="imu-array-fake-")
            link = os.path.join(self._own_dir, "tty")
        self.link = Path(link)
        check_link(self.link)
        self._t_created = time.monotonic()
        self._open_pty()
        self._thread = threading.Thread(target=self._run, name="FakeArrayDevice", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ constructors

    @classmethod
    def from_samples(cls, raw, ticks, counter=None, **kw) -> "FakeArrayDevice":
        """Packets from counts (N, K, 6) int16 and ticks (N,) uint32; counter default 0, 1, ... (mod 65536)."""
        counter = np.arange(len(raw)) % 65536 if counter is None else counter
        return cls(counter, ticks, raw, **kw)

    @classmethod
    def from_imu_samples(cls, samples, **kw) -> "FakeArrayDevice":
        """Packets from an :class:`~imu_array_ros.model.samples.ImuSamples` (counts clipped to int16)."""
        return cls.from_samples(samples_to_counts(samples.accel, samples.gyro), stamps_to_ticks(samples.stamps), **kw)

    @classmethod
    def from_capture(cls, path: str | Path, n_imus: int, **kw) -> "FakeArrayDevice":
        """Replay a raw capture of ``n_imus``-IMU packets (CaptureError if unreadable or not framing)."""
        path = Path(path)
        try:
            data = path.read_bytes()
        except OSError as err:
            raise CaptureError(f"{path}: cannot read capture: {err.strerror or err}") from None
        p, _ = parse_buffer(data, n_imus)
        if len(p) * packet_length(n_imus) < 0.5 * len(data):
            hint = guess_imu_count(data[: 1 << 16])
            also = f" (it frames as {hint[0]}-IMU packets)" if hint else " (not an OpenShoe raw-IMU capture?)"
            raise CaptureError(f"{path}: no valid {n_imus}-IMU packets cover half of its {len(data)} bytes; "
                               f"wrong array description?{also}")
        offsets = np.append(p.offsets, len(data))
        return cls(p.counter, p.ticks, p.raw, data=data, offsets=offsets, **kw)

    # ------------------------------------------------------------------ public

    @property
    def port(self) -> str:
        """The stable port path to open (the symlink)."""
        return str(self.link)

    @property
    def record(self) -> DeviceRecord:
        """A consistent copy of what was received and sent so far."""
        with self._lock:
            r = self._record
            return replace(r, commands=list(r.commands), streams=list(r.streams),
                           sent=[list(s) for s in r.sent], corrupted=[list(c) for c in r.corrupted])

    @property
    def finished(self) -> bool:
        """All data written to the pseudo-terminal (never with ``loop``)."""
        return self._finished.is_set() and not self._out

    def wait_finished(self, timeout: float | None = None, drained: bool = True) -> bool:
        """Wait until all data is written and, if ``drained``, read by the host; False on timeout."""
        end = None if timeout is None else time.monotonic() + timeout
        if not self._finished.wait(timeout):
            return False
        while not self.finished or (drained and self._unread() > 0):
            if (end is not None and time.monotonic() > end) or not self._thread.is_alive():
                return False
            time.sleep(0.01)
        return True

    def close(self) -> None:
        """Stop the thread, close the pseudo-terminal, remove the symlink (and the temporary directory)."""
        self._stop.set()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join()
        self._close_pty()
        if self._own_dir is not None:
            try:
                os.rmdir(self._own_dir)
            except OSError:
                pass
            self._own_dir = None

    def __enter__(self) -> "FakeArrayDevice":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------ pseudo-terminal

    def _open_pty(self) -> None:
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        os.set_blocking(self._master, False)
        self.tty = os.ttyname(self._slave)
        tmp = self.link.with_name(f".{self.link.name}.{os.getpid()}.tmp")
        try:
            os.symlink(self.tty, tmp)
            os.replace(tmp, self.link)
        except OSError as err:
            os.close(self._master)
            os.close(self._slave)
            raise OutputError(f"{self.link}: cannot create the port symlink: {err.strerror or err}") from None
        self._parser = CommandParser()

    def _close_pty(self) -> None:
        if self._master is None:
            return
        try:
            if os.readlink(self.link) == self.tty:  # still ours
                os.unlink(self.link)
        except OSError:
            pass
        for fd in (self._master, self._slave):
            os.close(fd)
        self._master = self._slave = None

    def _unread(self) -> int:
        """Bytes written to the pseudo-terminal that the host has not read yet."""
        try:
            return int.from_bytes(fcntl.ioctl(self._slave, termios.FIONREAD, b"\0\0\0\0"), "little")
        except (OSError, TypeError):  # unplugged (closed) meanwhile
            return 0

    # ------------------------------------------------------------------ device thread

    def _run(self) -> None:
        try:
            self._loop()
        except (OSError, OutputError) as err:  # e.g. the symlink's directory vanished during an unplug
            self.error = err

    def _loop(self) -> None:
        unplugged = self.unplug_at is None
        while not self._stop.is_set():
            if not unplugged and time.monotonic() - self._t_created >= self.unplug_at:
                unplugged = True
                self._unplug()
                continue
            due = self._generate()
            wl = [self._master] if self._out else []
            r, w, _ = select.select([self._master], wl, [], 0.02 if due is None else max(0.0, min(due, 0.02)))
            if r:
                try:
                    self._commands(os.read(self._master, 4096))
                except BlockingIOError:
                    pass
            if w:
                try:
                    self._out = self._out[os.write(self._master, self._out[:_OUT_HIGH]):]
                except BlockingIOError:
                    pass

    def _unplug(self) -> None:
        with self._lock:
            self._record.unplugs += 1
        self._stop_stream()
        self._streaming, self._out = False, b""
        self._close_pty()
        if not self._stop.wait(self.unplug_duration):
            self._open_pty()

    def _commands(self, data: bytes) -> None:
        before = self._parser.stats.bad_checksums
        cmds = self._parser.feed(data)
        with self._lock:
            self._record.bad_commands += self._parser.stats.bad_checksums - before
        for cmd in cmds:
            with self._lock:
                self._record.commands.append(cmd)
            if self._ignore > 0:
                self._ignore -= 1
                with self._lock:
                    self._record.ignored_commands += 1
                continue
            if cmd.code == START_RAW_IMU:
                cols = [j for j, b in enumerate(self.imu_bits) if cmd.imu_mask >> b & 1]
                try:
                    rate = output_rate_hz(cmd.rate_divider)
                except ValueError:
                    cols = []
                if not cols:
                    with self._lock:
                        self._record.bad_commands += 1
                    continue
                self._stop_stream()
                self._config = (cols, max(1, round(self.rate_hz / rate)))
                self._streaming = True
                self._new_stream()
            elif cmd.code == STOP_OUTPUT:
                self._stop_stream()
                self._streaming = False
            self._out += ack_for(cmd.code)
            with self._lock:
                self._record.acks_sent += 1

    def _stop_stream(self) -> None:
        """Remember where the current stream stopped (next start resumes there)."""
        if self._streaming:
            self._src_next = int(self._idx[self._pos]) if self._pos < len(self._idx) else len(self.raw)

    def _new_stream(self) -> None:
        """Encode the packets from the current source position for the current config; pacing restarts now."""
        cols, f = self._config
        n = len(self.raw)
        if self._src_next >= n:
            if not self.loop:
                self._streaming = False
                self._finished.set()
                return
            self._src_next, self._pass = 0, self._pass + 1
        self._idx = np.arange(self._src_next, n, f)
        if self._data is not None and self._pass == 0 and f == 1 and len(cols) == len(self.imu_bits):
            base = self._offsets[self._src_next]
            self._bytes, self._starts = self._data[base:], self._offsets[self._src_next:] - base
            p = ParsedPackets(self.counter[self._idx], self.ticks[self._idx], self.raw[self._idx], self._starts[:-1])
        else:
            m = len(self._idx)
            counter = (int(self.counter[self._idx[0]]) + self._pass * ((n + f - 1) // f) + np.arange(m)) % 65536
            ticks = (self.ticks[self._idx].astype(np.int64) + self._pass * self.period_ticks) % (1 << 32)
            raw = self.raw[self._idx][:, cols]
            self._bytes = encode_packets(counter, ticks, raw)
            self._starts = np.arange(m + 1, dtype=np.int64) * packet_length(len(cols))
            p = ParsedPackets(counter.astype(np.uint16), ticks.astype(np.uint32), raw, self._starts[:-1])
        self._times = self.times[self._idx]
        self._pos = 0
        self._t0 = time.monotonic()
        if self._keep:
            with self._lock:
                self._record.streams.append(p)
                self._record.sent.append([])
                self._record.corrupted.append([])

    def _generate(self) -> float | None:
        """Queue the packets that are due; seconds until the next one (None: nothing scheduled)."""
        if not self._streaming:
            return None
        m = len(self._idx)
        if self.speed == 0:
            hi = min(m, self._pos + 256) if len(self._out) < _OUT_HIGH else self._pos
        else:
            elapsed = (time.monotonic() - self._t0) * self.speed
            hi = int(np.searchsorted(self._times, self._times[0] + elapsed, side="right"))
        if hi > self._pos:
            self._emit(self._pos, hi)
            self._pos = hi
        if self._pos >= m:
            self._src_next = len(self.raw)
            self._new_stream()
            if not self._streaming:
                return None
        if self.speed == 0:
            return 0.0 if len(self._out) < _OUT_HIGH else None
        return (self._times[self._pos] - self._times[0]) / self.speed - (time.monotonic() - self._t0)

    def _emit(self, lo: int, hi: int) -> None:
        """Append packets lo..hi-1 of the stream to the output, with the configured faults."""
        s = self._starts
        buf = np.frombuffer(self._bytes, np.uint8, count=int(s[hi] - s[lo]), offset=int(s[lo])).copy()
        rel = s[lo:hi + 1] - s[lo]
        L = packet_length(len(self._config[0]))
        bad = np.zeros(hi - lo, bool)
        nbits = 0
        if self.bit_error_rate:
            nbits = int(self._rng.binomial(8 * len(buf), self.bit_error_rate))
            bits = np.unique(self._rng.integers(0, 8 * len(buf), nbits))
            nbits = len(bits)
            np.bitwise_xor.at(buf, bits // 8, (1 << (bits % 8)).astype(np.uint8))
            self._mark(bad, rel, bits // 8, L)
        keep = np.ones(len(buf), bool)
        if self.drop_byte_rate:
            keep = self._rng.random(len(buf)) >= self.drop_byte_rate
            self._mark(bad, rel, np.flatnonzero(~keep), L)
        ends = np.cumsum(keep)[rel[1:] - 1]  # packet ends after the drops
        buf = buf[keep]
        n_garbage = 0
        if self.garbage_every:
            with self._lock:
                done = self._record.packets_sent
            after = np.flatnonzero((done + np.arange(1, hi - lo + 1)) % self.garbage_every == 0)
            lengths = self._rng.integers(1, L + 1, len(after))
            n_garbage = int(lengths.sum())
            buf = np.insert(buf, np.repeat(ends[after], lengths), self._rng.integers(0, 256, n_garbage, np.uint8))
        self._out += buf.tobytes()
        with self._lock:
            r = self._record
            if self._keep:
                r.sent[-1].append(np.arange(lo, hi))
                r.corrupted[-1].append(lo + np.flatnonzero(bad))
            r.packets_sent += hi - lo
            r.corrupted_packets += int(bad.sum())
            r.bits_flipped += nbits
            r.bytes_dropped += int(len(keep) - keep.sum())
            r.garbage_bytes += n_garbage
            r.bytes_sent += len(buf)

    @staticmethod
    def _mark(bad: np.ndarray, rel: np.ndarray, byte_idx: np.ndarray, L: int) -> None:
        """Flag the packets whose first L bytes (the packet proper) contain one of ``byte_idx``."""
        j = np.searchsorted(rel, byte_idx, side="right") - 1
        bad[j[byte_idx - rel[j] < L]] = True


def check_link(link: Path) -> None:
    """Refuse a link path that exists and is not a symlink to a pseudo-terminal (never replace a user's file)."""
    if not link.parent.is_dir():
        raise OutputError(f"{link}: directory {link.parent} does not exist")
    if os.path.lexists(link):
        if not link.is_symlink():
            raise OutputError(f"{link}: exists and is not a symlink; refusing to replace it (choose another --link)")
        if not os.readlink(link).startswith(_PTY_PREFIXES):
            raise OutputError(f"{link}: is a symlink to {os.readlink(link)}, not to a pseudo-terminal; "
                              f"refusing to replace it")
