"""A candidate whose evidence is mostly a change of the earlier findings' values (it trades with them) is not
reported as physics; a true partner of an earlier finding is, even when its refit moves that finding by many of
its standard errors (:mod:`imu_array_ros.discovery.trading`).  Linear-Gaussian simulations of the two
terms' columns (what the exact refit's information is, to first order); discovery keeping a true pair on two
IMUs: test_discovery_scopes.py::test_time_offset_and_position_pair_both_found."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np

from imu_array_ros.discovery.confirm import TRADES
from imu_array_ros.discovery.trading import trading, traded_share
from imu_array_ros.model.description import load_description
from imu_array_ros.model.sensor_model import SensorModel

ROOT = Path(__file__).resolve().parents[1]
CORNERS = str(ROOT / "config" / "mimu4444bt_corners.yaml")


def _design(rng, n=4000):
    """Columns of an earlier finding A (a1, a2) and a candidate B (b1, b2): b1 is 0.98 a1 plus a little of its
    own (canonical correlation ~0.98, rho^2 0.96 >= 0.9), b2 correlates 0.6 with a2 (rho^2 0.36)."""
    a1, a2, u1, u2 = rng.normal(size=(4, n))
    b1 = 0.98 * a1 + np.sqrt(1 - 0.98 ** 2) * u1
    b2 = 0.6 * a2 + 0.8 * u2
    return np.stack([b1, b2, a1, a2], axis=1), u1  # the candidate first, as traded_share reads it


def _fits(x, y):
    """(joint estimate, covariance) with unit noise, and A's estimate alone."""
    cov = np.linalg.inv(x.T @ x)
    joint = cov @ x.T @ y
    alone = np.linalg.lstsq(x[:, 2:], y, rcond=None)[0]
    return joint, cov, alone


def test_a_proxy_that_trades_with_the_earlier_finding_is_flagged():
    """What neither term has (w: the candidate's own part u1 of b1, as a missing effect would leave) is fitted
    by the candidate only by moving A along a1: the candidate's estimate lies on its confounded direction."""
    rng = np.random.default_rng(7)
    x, u1 = _design(rng)
    y = x[:, 2:] @ np.array([3.0, -2.0]) + 0.3 * u1 + rng.normal(size=len(u1))
    joint, cov, _ = _fits(x, y)
    share, evidence, rho2, _, parts = traded_share(cov, joint[:2], [2])
    assert evidence > 100  # the candidate is wanted (Wald given A)
    assert rho2.max() > 0.9 and share > 0.9, (share, rho2)


def test_a_true_partner_is_kept_though_it_moves_the_earlier_finding_by_many_sigmas():
    """B truly present on b2 (partly correlated with a2): A's a2 estimate alone was biased by B's absence, and the
    joint refit moves it back by ~10 of its standard errors (a shift in sigma units would reject B), but B's
    evidence is on a direction A's terms cannot produce: kept."""
    rng = np.random.default_rng(8)
    x, _ = _design(rng)
    y = x @ np.array([0.0, 0.5, 3.0, -2.0]) + rng.normal(size=len(x))
    joint, cov, alone = _fits(x, y)
    shift_sigma = np.abs(joint[2:] - alone) / np.sqrt(np.diag(cov)[2:])
    assert shift_sigma.max() > 5
    share, evidence, rho2, _, _ = traded_share(cov, joint[:2], [2])
    assert rho2.max() > 0.9  # it has a confounded direction, but its evidence is not there
    assert evidence > 100 and share < 0.1, (share, evidence)


def test_noise_on_a_confounded_direction_adds_its_chi_square_not_its_inflation():
    """A weak true partner (evidence ~30 on b2) with b1 at zero: the b1 direction's noise (VIF 25) adds ~1 to the
    traded part, so the share stays small in every one of 200 draws."""
    rng = np.random.default_rng(9)
    shares = []
    for _ in range(200):
        x, _ = _design(rng, n=400)
        y = x @ np.array([0.0, 0.35, 3.0, -2.0]) + rng.normal(size=len(x))
        joint, cov, _ = _fits(x, y)
        shares.append(traded_share(cov, joint[:2], [2])[0])
    shares = np.array(shares)
    assert np.mean(shares >= 0.5) < 0.05 and np.median(shares) < 0.1, np.quantile(shares, [0.5, 0.9, 0.99])


def test_trading_names_the_partner_from_a_fit():
    """trading() on a fit-like object: indexes by term and IMU, the change from the starting model, the partner
    named when the candidate trades."""
    rng = np.random.default_rng(7)
    x, u1 = _design(rng)
    y = x[:, 2:] @ np.array([3.0, -2.0]) + 0.3 * u1 + rng.normal(size=len(u1))
    joint, cov, _ = _fits(x, y)
    nominal = SensorModel.from_description(load_description(CORNERS))
    # a fit of gyroscope_gain (3) and accelerometer_bias (3) on imu_1: candidate b -> gain[0:2], A -> bias[0:2]
    theta = np.zeros(6)
    full = np.zeros((6, 6))
    order = [3, 4, 0, 1]  # gain x, y; bias x, y (free order: bias, gain)
    full[np.ix_(order, order)] = cov
    theta[order] = joint
    theta[3:] += nominal.terms["gyroscope_gain"].values[0]
    fit = SimpleNamespace(covariance=full, theta=theta, free=("accelerometer_bias", "gyroscope_gain"),
                          imus=(nominal.names[0],), model=nominal)
    earlier = [SimpleNamespace(effect="accelerometer_bias", imus=(0,), sensor="imu_1")]
    t = trading(fit, nominal, earlier, "gyroscope_gain", (0,))
    assert t.traded and t.partners == [("accelerometer_bias", "imu_1")] and t.dims == 2
    assert t.reason().startswith(TRADES)
