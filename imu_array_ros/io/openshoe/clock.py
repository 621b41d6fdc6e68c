"""Device clock -> host clock: stamps that follow the device's clock drift without the transport jitter.

The board stamps each packet with its own 64 MHz clock (unwrapped to ns by
:class:`~imu_array_ros.io.openshoe.framing.TickUnwrapper`).  The host only
knows when a batch of packets *arrived*.  Model, with ``d`` the device time of
a sample and ``h`` host time (both ns)::

    h_generated(d) = d + offset(d),      offset(d) = b + s * d   (s: skew, tens of ppm)
    h_received     = h_generated + latency,  latency >= 0 (USB/Bluetooth, OS, polling)

Every batch gives one observation ``y = host_receive_ns - d_last`` (its last
sample is the freshest, so it gives the tightest bound) with ``y >= offset(d_last)``:
observations lie *above* the offset line, and their lower envelope is the line
plus the minimum latency.  :class:`DeviceClock` estimates that envelope:

1. the device timeline is cut into windows (``window_ns``, default 1 s); each
   window keeps its lowest observation (robust minimum-delay filter: one
   packet with little delay per window suffices);
2. a line is fitted to the minima of the last ``windows`` windows (default
   60, i.e. one minute) plus the current one (:func:`minimum_delay_line`):
   least-squares slope (the skew), refitted without windows far above the
   line (delayed throughout, e.g. a radio stall), then lowered until it
   touches the lowest minimum, so that stamps are not later than the arrivals seen.
   Minimum-delay skew estimation as in V. Paxson, "On calibrating
   measurements of packet transit times", ACM SIGMETRICS 1998, and S. B.
   Moon, P. Skelly, D. Towsley, "Estimation and removal of clock skew from
   network delay measurements", IEEE INFOCOM 1999.  The slope is limited to
   ``max_skew`` (default 1000 ppm);
3. the offset applied to the stamps moves towards that line with a bounded
   slew (``max_slew``, default 1 %: 10 ms per second), continuously, so a new
   minimum shifts the stamps smoothly instead of as a step.

Hence: stamps are strictly increasing in device time (each interval is the
device interval times ``1 ± max_slew``, and almost always ``1 + skew`` once the
estimate settles), one device time always maps to one stamp, and stamps track
``generation time + minimum latency`` within the minimum-delay noise: at 62.5 Hz
with 0-20 ms of latency jitter and 5 ms polling, typically 0.2-0.5 ms and at
most about 1.5 ms once 30 s of history are in (test_openshoe_serial.py).
Until then stamps slew from the first batch's latency down to the minimum
latency, and the skew estimate needs a few windows.

:meth:`DeviceClock.reset` forgets everything (call it on reconnect, device
restart, or a host clock jump).  The clock re-anchors itself (counted in
``reanchors``) when the device time goes backwards or when the fitted line
and the applied offset differ by more than ``reanchor_ns`` (default 1 s: the
host clock stepped back, or the first batches were stuck for > 1 s); only then
may stamps step.
"""

from __future__ import annotations

from collections import deque

import numpy as np

__all__ = ["DeviceClock", "minimum_delay_line"]


def minimum_delay_line(x: np.ndarray, y: np.ndarray, max_slope: float = np.inf) -> tuple[float, float]:
    """Line ``y = a + b x`` under per-window minimum delays: robust slope, lowered to touch the lowest point.

    x, y : (P,) float (device ns since the anchor; observed offset, ns).  The
    slope is the least-squares slope of the points, refitted twice without
    the points more than 4 robust standard deviations (1.4826 MAD) above the
    line (windows delayed throughout, e.g. a radio stall), then clipped to
    ``[-max_slope, max_slope]``; fewer than 3 points give b = 0.  The
    intercept puts the line under every point, through the lowest residual.
    Returns (a, b).
    """
    x = np.asarray(x, float)
    y = np.asarray(y, float)
    b = 0.0
    if len(x) >= 3:
        keep = np.ones(len(x), bool)
        for _ in range(3):
            xc = x[keep] - x[keep].mean()
            if not np.any(xc):
                break
            b = float(np.dot(xc, y[keep]) / np.dot(xc, xc))
            r = y - b * x
            med = float(np.median(r[keep]))
            keep = r <= med + 4 * 1.4826 * float(np.median(np.abs(r[keep] - med))) + 1.0
        b = float(np.clip(b, -max_slope, max_slope))
    return float(np.min(y - b * x)), b


class DeviceClock:
    """Map unwrapped device time (ns) to host time (ns) along the lower envelope of the arrivals.

    Parameters
    ----------
    window_ns : int
        Length of a minimum-delay window in device time, ns (default 1 s).
    windows : int
        Completed windows the line is fitted to (default 60): the history, and
        how fast a change of skew is followed.
    max_slew : float
        Largest rate of change of the applied offset, ns per device ns (default
        0.01); bounds how much one interval can be stretched or squeezed.
    max_skew : float
        Largest accepted skew, dimensionless (default 1e-3 = 1000 ppm).
    reanchor_ns : int
        Re-anchor when the fitted line and the applied offset differ by more
        than this, ns (default 1 s).
    """

    def __init__(self, *, window_ns: int = 1_000_000_000, windows: int = 60, max_slew: float = 0.01,
                 max_skew: float = 1e-3, reanchor_ns: int = 1_000_000_000) -> None:
        if window_ns <= 0 or windows < 1:
            raise ValueError(f"window_ns and windows must be positive, got {window_ns}, {windows}")
        if not 0 < max_slew < 1:
            raise ValueError(f"max_slew must lie in (0, 1), got {max_slew}")
        if not 0 <= max_skew < max_slew:
            raise ValueError(f"max_skew must lie in [0, max_slew), got {max_skew}")
        self.window_ns = int(window_ns)
        self.max_slew = float(max_slew)
        self.max_skew = float(max_skew)
        self.reanchor_ns = int(reanchor_ns)
        self._history: deque[tuple[float, float]] = deque(maxlen=int(windows))
        self.reanchors = 0
        self.reset()

    def reset(self) -> None:
        """Forget the estimate and the last stamp (reconnect, device restart, host clock jump)."""
        self._history.clear()
        self._d0: int | None = None  # anchor: device ns and observation of the first batch
        self._y0 = 0
        self._window = -1  # index of the current window
        self._current: tuple[float, float] | None = None  # (x, y) minimum of the current window
        self._line: tuple[float, float] | None = None  # (a, b) cached fit
        self._last: tuple[int, float] | None = None  # (device ns, applied offset) of the last mapped sample

    @property
    def skew(self) -> float:
        """Current skew estimate (host ns per device ns, minus 1); 0 before two windows."""
        return self._line[1] if self._line is not None else 0.0

    @property
    def offset_ns(self) -> int | None:
        """Applied offset (stamp - device time) at the last mapped sample, ns; None before any."""
        return None if self._last is None else self._y0 + round(self._last[1])

    def map(self, device_ns: np.ndarray, host_ns: int) -> np.ndarray:
        """Stamps (M,) int64 ns (host clock) of samples at ``device_ns`` (M,) int64, received by ``host_ns``.

        ``device_ns`` must be non-decreasing and continue the previous batch (since
        the last :meth:`reset`); an empty batch returns an empty array and teaches nothing.
        """
        d = np.asarray(device_ns, dtype=np.int64)
        if len(d) == 0:
            return np.zeros(0, np.int64)
        if self._last is not None and int(d[0]) < self._last[0]:
            self._reanchor()  # device time went backwards: device restarted without reset()
        if self._d0 is None:
            self._d0, self._y0 = int(d[0]), int(host_ns) - int(d[-1])
        self._observe(float(d[-1] - self._d0), float(int(host_ns) - int(d[-1]) - self._y0))
        a, b = self._line
        x = (d - self._d0).astype(np.float64)
        target = a + b * x
        if self._last is None:
            applied = target
        else:
            dx = x - float(self._last[0] - self._d0)
            lo = self._last[1] - self.max_slew * dx
            hi = self._last[1] + self.max_slew * dx
            applied = np.minimum(np.maximum(target, lo), hi)  # continuous, slope within +-max_slew
            if abs(float(target[-1] - applied[-1])) > self.reanchor_ns:
                self._reanchor()
                return self.map(d, host_ns)
        self._last = (int(d[-1]), float(applied[-1]))
        return d + self._y0 + np.round(applied).astype(np.int64)

    def _reanchor(self) -> None:
        self.reanchors += 1
        self.reset()

    def _observe(self, x: float, y: float) -> None:
        """Add one observation (x: device ns since anchor, y: host - device ns minus the anchor's)."""
        w = int(x // self.window_ns)
        if w != self._window:
            if self._current is not None:
                self._history.append(self._current)
            self._window, self._current = w, (x, y)
            self._line = None
        elif y < self._current[1]:
            self._current = (x, y)
            self._line = None
        if self._line is None:
            pts = list(self._history) + [self._current]
            xs = np.array([p[0] for p in pts])
            ys = np.array([p[1] for p in pts])
            self._line = minimum_delay_line(xs, ys, self.max_skew)
