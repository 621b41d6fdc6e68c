"""Reports of the Bayesian position calibration: ellipses, chain plots, the diagnostics table and files."""

from __future__ import annotations

import dataclasses
import json
import struct

import numpy as np
import pytest

from imu_array_ros.calibration import bayes
from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.model.layouts import grid_array32, planar_square4
from imu_array_ros.simulation.simulator import simulate_gaussian

pytest.importorskip("matplotlib")
pytest.importorskip("arviz")

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def posterior():
    """A small real posterior (4 IMUs, 20 samples, 4 chains; a few seconds)."""
    model = dataclasses.replace(SensorModel.from_description(planar_square4()), acc_clip=np.inf, gyro_clip=np.inf)
    rng = np.random.default_rng(0)
    s, _ = simulate_gaussian(model, 20, rng)
    p = bayes.build_problem(s, model)
    lap = bayes.laplace(p, s, model)
    post = bayes.sample_posterior(p, lap, bayes.SamplerSettings(scheduler="serial", ess=100, min_warmup=500,
                                                                chunk=500))
    return post, model


def _png_size(path) -> tuple[int, int]:
    data = path.read_bytes()
    assert data[:8] == PNG_MAGIC, f"{path.name} is not a PNG"
    assert data[12:16] == b"IHDR"
    return struct.unpack(">II", data[16:24])


# --------------------------------------------------------------------------- ellipses


@pytest.mark.parametrize("level", [0.5, 0.9, 0.99])
def test_ellipse_points_lie_on_the_chi2_contour(level):
    from scipy.stats import chi2

    mean = np.array([1.5, -2.0])
    cov = np.array([[4.0, 1.2], [1.2, 0.9]])
    pts = bayes.ellipse_points(mean, cov, level, n=200)
    assert pts.shape == (200, 2)
    d = pts - mean
    maha = np.einsum("ni,ij,nj->n", d, np.linalg.inv(cov), d)
    np.testing.assert_allclose(maha, chi2.ppf(level, 2), rtol=1e-10)
    np.testing.assert_allclose(pts[0], pts[-1])  # closed
    # the polygon's area is that of the ellipse, pi r^2 sqrt(det cov)
    x, y = pts[:, 0], pts[:, 1]
    area = 0.5 * abs(np.dot(x[:-1], y[1:]) - np.dot(x[1:], y[:-1]))
    assert area == pytest.approx(np.pi * chi2.ppf(level, 2) * np.sqrt(np.linalg.det(cov)), rel=1e-3)
    # and the points go all the way round: the extreme x is mean_x +- r sqrt(cov_xx)
    assert x.max() - mean[0] == pytest.approx(np.sqrt(chi2.ppf(level, 2) * cov[0, 0]), rel=1e-3)


def test_ellipse_points_rejects_bad_input():
    with pytest.raises(ValueError):
        bayes.ellipse_points([0, 0], np.eye(2), level=1.0)
    with pytest.raises(ValueError):
        bayes.ellipse_points([0, 0], np.eye(3))
    # a singular covariance: a segment, not an error
    pts = bayes.ellipse_points([0, 0], np.diag([1.0, 0.0]))
    assert np.allclose(pts[:, 1], 0.0) and np.isfinite(pts).all()


def test_panel_layout_follows_the_board():
    """array32: 4 x 4 per side; the top side (z = +1 mm) left, x to the right, y up, a spacer between."""
    nominal = SensorModel.from_description(grid_array32()).positions
    place, rows, widths = bayes.panel_layout(nominal)
    assert rows == 4 and widths == [1.0] * 4 + [0.25] + [1.0] * 4
    assert len(set(place.values())) == 32
    xs, ys = (sorted(set(np.round(nominal[:, a], 6))) for a in (0, 1))
    for i, (r, c) in place.items():
        x, y, z = np.round(nominal[i], 6)
        assert c == (0 if z > 0 else 5) + xs.index(x)
        assert r == 3 - ys.index(y)
    # not a grid (every IMU at its own x, y, z): rows of up to 8, highest z first
    rng = np.random.default_rng(3)
    scattered = rng.normal(size=(11, 3))
    place, rows, widths = bayes.panel_layout(scattered)
    assert rows == 2 and len(widths) == 8
    first = min(place, key=lambda i: place[i])
    assert first == int(np.argmax(scattered[:, 2]))


def test_plot_ellipses_with_truth_and_several_labels(tmp_path):
    model = SensorModel.from_description(grid_array32())
    nominal, names = model.positions, list(model.names)
    k = len(names)
    rng = np.random.default_rng(7)
    truth = nominal + rng.normal(0.0, 0.3e-3, nominal.shape)
    a = rng.normal(size=(k, 3, 3))
    cov = (a @ a.transpose(0, 2, 1) + np.eye(3)) * 1e-8
    estimates = {lab: (truth + rng.normal(0.0, 1e-4, nominal.shape), cov * f)
                 for lab, f in (("MCMC", 1.0), ("Laplace", 1.3), ("BCD", 0.7))}
    big = tmp_path / "ellipses32.png"
    place = bayes.plot_ellipses(big, names, nominal, estimates, prior_std=np.full((k, 3), 1e-3), truth=truth,
                                reference=names[0], colors={"BCD": "k"})
    assert place["imu_00"] == (3, 0) and place["imu_15"] == (0, 3) and place["imu_16"] == (3, 5)
    w32, h32 = _png_size(big)
    small = tmp_path / "ellipses4.png"
    model4 = SensorModel.from_description(planar_square4())
    bayes.plot_ellipses(small, model4.names, model4.positions,
                        {"one": (model4.positions, np.tile(np.eye(3) * 1e-10, (4, 1, 1)))}, package=None)
    w4, h4 = _png_size(small)
    assert w32 > 1.8 * w4 and h32 > h4  # the figure grows with the count
    assert not list(tmp_path.glob(".*"))  # no temporary left behind
    with pytest.raises(ValueError):
        bayes.plot_ellipses(tmp_path / "bad.png", names, nominal, {"x": (nominal[:3], cov)})
    with pytest.raises(ValueError):
        bayes.plot_ellipses(tmp_path / "bad.png", names, nominal, estimates, reference="nope")
    assert not (tmp_path / "bad.png").exists()


# --------------------------------------------------------------------------- the posterior's report


def test_lowest_ess_coords_match_the_summary(posterior):
    post, _ = posterior
    coords = bayes.lowest_ess_coords(post, 4)
    ess = post.summary["ess_bulk"]
    expected = [lab for lab in ess.sort_values().index[:4]]
    assert [f"position[{i}, {a}]" for i, a in coords] == expected
    assert len(bayes.lowest_ess_coords(post, 100)) == post.draws.shape[-1]


def test_diagnostics_table_values(posterior):
    post, _ = posterior
    rows = bayes.diagnostics_table(post)
    d = post.draws.shape[-1]
    assert len(rows) == d
    assert [(r["imu"], r["axis"]) for r in rows] == [(n, a) for n in post.free_names for a in "xyz"]
    nominal = post.problem.theta_of(post.problem.positions)
    lap_sd = np.sqrt(np.diag(post.laplace.covariance))
    for j, r in enumerate(rows):
        assert r["mean_um"] == pytest.approx((post.mean[j] - nominal[j]) * 1e6)
        assert r["sd_um"] == pytest.approx(post.flat[:, j].std(ddof=1) * 1e6)
        assert r["laplace_mean_um"] == pytest.approx((post.laplace.mean[j] - nominal[j]) * 1e6)
        assert r["laplace_sd_um"] == pytest.approx(lap_sd[j] * 1e6)
        assert r["z"] == pytest.approx((r["mean_um"] - r["laplace_mean_um"]) / r["sd_um"])
        assert r["sd_ratio"] == pytest.approx(r["laplace_sd_um"] / r["sd_um"])
        label = f"position[{r['imu']}, {r['axis']}]"
        assert r["ess_bulk"] == pytest.approx(post.summary.loc[label, "ess_bulk"])
        assert r["r_hat"] == pytest.approx(post.summary.loc[label, "r_hat"])
        assert r["hdi_low_um"] < r["mean_um"] < r["hdi_high_um"]
        assert r["mcse_mean_um"] < r["sd_um"]
    # this posterior is nearly Gaussian: the Laplace approximation matches it
    assert max(abs(r["z"]) for r in rows) < 1.0
    assert all(0.8 < r["sd_ratio"] < 1.25 for r in rows)


def test_disagreements_name_the_coordinates():
    rows = [{"imu": "a", "axis": "x", "z": 0.5, "sd_ratio": 1.0},
            {"imu": "a", "axis": "y", "z": -2.5, "sd_ratio": 1.0},
            {"imu": "b", "axis": "z", "z": 0.1, "sd_ratio": 0.5},
            {"imu": "b", "axis": "x", "z": float("nan"), "sd_ratio": 1.3}]
    dis = bayes.disagreements(rows)
    assert [(d["imu"], d["axis"]) for d in dis] == [("a", "y"), ("b", "z"), ("b", "x")]
    assert "z = -2.50" in dis[0]["why"] and "sd ratio 0.50" in dis[1]["why"]


def test_write_report_writes_every_file(posterior, tmp_path):
    post, model = posterior
    out = tmp_path / "report" / "bayes"  # created, parents too
    paths = bayes.write_report(post, out, truth=model.positions, extra={"recording": "sim", "seed": 0})
    names = {p.name for p in paths}
    assert names == {"diagnostics.json", "diagnostics.md", "ellipses.png", "trace.png", "autocorr.png",
                     "posterior.nc"}
    assert all(p.parent == out and p.stat().st_size > 0 for p in paths)
    assert not list(out.glob(".*"))  # no temporary left behind
    for name in ("ellipses.png", "trace.png", "autocorr.png"):
        w, h = _png_size(out / name)
        assert w > 400 and h > 300

    doc = json.loads((out / "diagnostics.json").read_text(), parse_constant=lambda c: pytest.fail(c))
    assert doc["recording"] == "sim" and doc["seed"] == 0
    assert doc["settings"] == json.loads(json.dumps(dataclasses.asdict(post.settings)))
    run = doc["run"]
    c, m, d = post.draws.shape
    assert (run["chains"], run["draws_per_chain"], run["warmup_per_chain"]) == (c, m, post.warmup)
    assert run["n_draws"] == post.n_draws
    assert [(v["n_draws"], v["variance"]) for v in run["var_loglik"]] == [(n, v) for n, v in post.var_loglik]
    assert run["converged"] is bool(post.converged)
    assert run["ess_bulk_min"] == pytest.approx(post.ess_bulk_min)
    rows = doc["rows"]
    assert len(rows) == d == 3 * len(post.free_names)
    table = bayes.diagnostics_table(post)
    for r, t in zip(rows, table):
        assert r["imu"] == t["imu"] and r["mean_um"] == pytest.approx(t["mean_um"])
        assert r["truth_um"] == pytest.approx(0.0)  # simulated at the nominal positions
        assert r["z_truth"] == pytest.approx(r["mean_um"] / r["sd_um"])
    assert doc["disagreements"] == bayes.disagreements(table)

    md = (out / "diagnostics.md").read_text()
    assert "**MCMC vs Laplace:**" in md
    assert ("agree everywhere" in md) == (not doc["disagreements"])
    assert "| N | Var[log-likelihood estimate] |" in md
    assert sum(line.startswith(f"| {n} |") for n in post.free_names for line in md.splitlines()) == d

    from imu_array_ros.calibration.bayes import arviz

    idata = arviz().from_netcdf(str(out / "posterior.nc"))
    np.testing.assert_allclose(idata.posterior["position"].values.reshape(c, m, d), post.draws)


def test_write_report_without_plots_and_with_a_disagreement(posterior, tmp_path):
    post, _ = posterior
    # shift the Laplace mean of one coordinate by 3 posterior sds: the report must say so
    lap = post.laplace
    mean = lap.mean.copy()
    mean[4] += 3.0 * post.flat[:, 4].std(ddof=1)
    shifted = dataclasses.replace(post, laplace=dataclasses.replace(lap, mean=mean))
    paths = bayes.write_report(shifted, tmp_path, plots=False)
    assert {p.name for p in paths} == {"diagnostics.json", "diagnostics.md", "posterior.nc"}
    assert not list(tmp_path.glob("*.png"))
    imu, axis = post.free_names[1], "y"
    md = (tmp_path / "diagnostics.md").read_text()
    line = next(x for x in md.splitlines() if x.startswith("**MCMC vs Laplace:**"))
    assert "disagree at" in line and f"{imu} {axis} (z = -" in line
    doc = json.loads((tmp_path / "diagnostics.json").read_text())
    assert [(x["imu"], x["axis"]) for x in doc["disagreements"]] == [(imu, axis)]


def test_write_report_survives_a_failing_netcdf(posterior, tmp_path, monkeypatch):
    post, _ = posterior

    class Broken:
        def to_netcdf(self, *a, **k):
            raise OSError("no engine")

    monkeypatch.setattr(type(post), "inference_data", lambda self: Broken())
    paths = bayes.write_report(post, tmp_path, plots=False)
    assert {p.name for p in paths} == {"diagnostics.json", "diagnostics.md"}
    assert not (tmp_path / "posterior.nc").exists()
    assert not list(tmp_path.glob(".*"))
    assert "posterior.nc not written" in (tmp_path / "diagnostics.md").read_text()
    assert "no engine" in json.loads((tmp_path / "diagnostics.json").read_text())["netcdf_error"]


def test_trace_and_autocorr_of_chosen_coordinates(posterior, tmp_path):
    post, _ = posterior
    name = post.free_names[0]
    shown = bayes.plot_trace(tmp_path / "t.png", post, coords=[(name, "z"), f"position[{post.free_names[2]}, x]"])
    assert shown == [(name, "z"), (post.free_names[2], "x")]
    assert bayes.plot_autocorr(tmp_path / "a.png", post, max_coords=2) == bayes.lowest_ess_coords(post, 2)
    bayes.plot_trace(tmp_path / "t4.png", post, max_coords=4)
    assert _png_size(tmp_path / "t.png")[1] < _png_size(tmp_path / "t4.png")[1]  # a row per coordinate
    assert _png_size(tmp_path / "a.png")[0] > 0
    with pytest.raises(ValueError):
        bayes.plot_trace(tmp_path / "bad.png", post, coords=[(post.names[post.problem.reference], "x")])
