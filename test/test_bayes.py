"""Bayesian position calibration (carlsson2021): the likelihood, the sampler, its runners, the command."""

from __future__ import annotations

import dataclasses
import sys

import numpy as np
import pytest
import yaml
from scipy.stats import ks_2samp

from conftest import START, assert_user_error, cli
from imu_array_ros.calibration import bayes
from imu_array_ros.calibration.bayes import sampler as bayes_sampler
from imu_array_ros.calibration.selection import MIN_EXCITATION, select_rotating
from imu_array_ros.errors import CalibrationError
from imu_array_ros.model.description import load_description, save_description
from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.model.kinematics import skew
from imu_array_ros.model.layouts import grid_array32, tetrahedron4
from imu_array_ros.simulation.simulator import simulate_gaussian


def _unclipped(desc) -> SensorModel:
    return dataclasses.replace(SensorModel.from_description(desc), acc_clip=np.inf, gyro_clip=np.inf)


def _problem(seed=0, t=30, desc=None, true_offset=2e-4, **kw):
    """(problem, laplace, samples, true positions, nominal model) for a tetrahedron of 4 IMUs."""
    nominal = _unclipped(desc or tetrahedron4())
    rng = np.random.default_rng(seed)
    pos = nominal.positions.copy()
    pos[1:] += rng.normal(size=pos[1:].shape) * true_offset
    s, truth = simulate_gaussian(nominal.with_terms(position=pos), t, rng)
    p = bayes.build_problem(s, nominal, **kw)
    return p, bayes.laplace(p, s, nominal), s, truth, pos, nominal


# --------------------------------------------------------------------------- the likelihood


def test_rao_blackwellised_likelihood_matches_the_dense_formula_with_a_calibrated_model():
    """eq. 22-25 with S formed densely, in the raw sensor frames with gains, misalignments and biases:
    the compensated, factorised likelihood differs from it by a theta-independent constant only."""
    desc = tetrahedron4()
    nominal = _unclipped(desc)
    rng = np.random.default_rng(4)
    k = nominal.n_imus
    model = nominal.with_terms(accelerometer_gain=1 + 0.02 * rng.normal(size=(k, 3)),
                               accelerometer_misalignment=0.01 * rng.normal(size=(k, 3)),
                               accelerometer_bias=0.1 * rng.normal(size=(k, 3)),
                               gyroscope_gain=1 + 0.01 * rng.normal(size=(k, 3)))
    s, truth = simulate_gaussian(model, 12, rng)
    p = bayes.build_problem(s, model)
    m_acc, o_acc, _, _ = bayes.affine_model(model, s.stamps)
    sigma = np.diag(np.tile(model.acc_std[0] ** 2, k))
    om = np.linalg.inv(sigma)
    mbig = np.zeros((3 * k, 3 * k))
    for i in range(k):
        mbig[3 * i:3 * i + 3, 3 * i:3 * i + 3] = m_acc[i]

    def dense(theta):
        r = p.full_positions(theta)
        h = mbig @ np.concatenate([np.concatenate([-skew(r[i]), np.eye(3)], 1) for i in range(k)])
        g = h.T @ om @ h
        smat = om - om @ h @ np.linalg.solve(g, h.T @ om)
        total = 0.0
        for t in range(len(s.stamps)):
            w = skew(truth.omega[t])
            pred = mbig @ np.concatenate([w @ w @ r[i] for i in range(k)])
            d = (s.accel[t] - o_acc[t]).reshape(-1) - pred
            total += -0.5 * d @ smat @ d
        return total - 0.5 * len(s.stamps) * np.linalg.slogdet(g)[1]

    th0 = p.theta_of(model.positions)
    th1 = th0 + 1e-3 * rng.normal(size=p.dim)
    ours = p.exact_loglik(th1, truth.omega) - p.exact_loglik(th0, truth.omega)
    assert ours == pytest.approx(dense(th1) - dense(th0), rel=1e-8, abs=1e-6)
    assert abs(ours) > 10  # the comparison is not between two zeros


def test_estimator_variance_falls_as_one_over_n():
    """carlsson2021 Fig. 2: Var[log p_N] ~ 1/N."""
    p, lap, *_ = _problem(t=200, desc=grid_array32())
    rng = np.random.default_rng(1)
    v1 = bayes.loglik_variance(p.with_(n_draws=1), lap.mean, 200, rng)
    v16 = bayes.loglik_variance(p.with_(n_draws=16), lap.mean, 200, rng)
    assert 8 < v1 / v16 < 32, (v1, v16)


def test_a_model_with_time_offsets_is_refused_by_name():
    nominal = _unclipped(tetrahedron4())
    model = nominal.with_terms(time_offset=np.full((4, 2), 1e-3))
    s, _ = simulate_gaussian(model, 5, np.random.default_rng(0))
    with pytest.raises(CalibrationError, match="time_offset"):
        bayes.build_problem(s, model)


# --------------------------------------------------------------------------- the proposals


def _metropolis_hastings(move, logpdf, starts, n_steps, rng):
    """``n_steps`` Metropolis-Hastings steps with ``move`` alone from each start (C, d), as run_chunk makes
    them (a batch of proposals per chain, log-uniforms, the move's correction); the final states (C, d)."""
    out = np.empty_like(starts)
    for c, theta in enumerate(starts):
        batch, logu = move.draw(rng, n_steps), np.log(rng.random(n_steps))
        for i in range(n_steps):
            prop = move.propose(theta, batch[i])
            if logu[i] < logpdf(prop) - logpdf(theta) + move.log_correction(theta, prop):
                theta = prop
        out[c] = theta
    return out


@pytest.mark.parametrize("name", ["random walk", "isotropic random walk", "independence t"])
def test_each_proposal_alone_leaves_the_target_invariant(name):
    """2000 chains started from a correlated 2-d Gaussian target, 10 steps of one proposal each: their end
    points are independent draws of the target when the kernel keeps it; KS test of both marginals and of
    a diagonal.  The t proposal is off-centre and too wide, so its q(theta) / q(theta') correction matters
    (without it: p ~ 1e-40); a random walk with a drift of 0.15 sd per step fails too."""
    from scipy.stats import kstest, norm

    mean, cov = np.array([0.3, -0.2]), np.array([[1.0, 0.8], [0.8, 2.0]])
    prec, low = np.linalg.inv(cov), np.linalg.cholesky(cov)
    logpdf = lambda x: -0.5 * (x - mean) @ prec @ (x - mean)  # noqa: E731
    move = {"random walk": bayes.RandomWalk(low, 1.7),
            "isotropic random walk": bayes.RandomWalk.isotropic(2, 1.2),
            "independence t": bayes.IndependenceT(mean + np.array([1.0, -0.5]), 1.5 * low)}[name]
    rng = np.random.default_rng(20)
    starts = mean + rng.standard_normal((2000, 2)) @ low.T
    ends = _metropolis_hastings(move, logpdf, starts, 10, rng)
    assert not np.array_equal(ends, starts)
    pvals = [kstest(ends @ a, norm(a @ mean, np.sqrt(a @ cov @ a)).cdf).pvalue
             for a in (np.array([1.0, 0.0]), np.array([0.0, 1.0]), np.array([1.0, 1.0]) / np.sqrt(2))]
    assert min(pvals) > 0.001 / 3, pvals  # Bonferroni at 0.1 %


def test_the_random_walk_is_symmetric_and_the_t_proposal_corrects():
    rng = np.random.default_rng(1)
    walk = bayes.RandomWalk(np.diag([1.0, 2.0]), 0.5)
    steps = walk.draw(np.random.default_rng(3), 4)
    np.testing.assert_array_equal(steps, np.random.default_rng(3).standard_normal((4, 2)) @ walk.chol.T * 0.5)
    theta = rng.normal(size=2)
    assert walk.log_correction(theta, walk.propose(theta, steps[0])) == 0.0
    assert walk.rescaled(2.0).scale == 1.0 and walk.reshaped(np.eye(2)).scale == 0.5
    t = bayes.IndependenceT(np.zeros(2), np.eye(2))
    a, b = np.array([0.1, 0.0]), np.array([3.0, 1.0])
    assert t.propose(a, b) is b
    assert t.log_correction(a, b) == pytest.approx(t.log_density(a) - t.log_density(b))
    assert t.log_correction(a, b) > 0  # moving into the tail of q: favoured, as q proposes it rarely


# --------------------------------------------------------------------------- the sampler

FAST = dict(scheduler="serial", ess=300, min_warmup=500, chunk=500)


@pytest.fixture(scope="module")
def tetra_posterior():
    p, lap, s, truth, pos, nominal = _problem(seed=3)
    post = bayes.sample_posterior(p, lap, bayes.SamplerSettings(**FAST, seed=1))
    return p, lap, post, pos


def test_posterior_covers_the_truth_and_agrees_with_laplace(tetra_posterior):
    p, lap, post, pos = tetra_posterior
    assert post.converged and post.rhat_max <= 1.01 and post.ess_bulk_min >= 300
    z = (post.mean - p.theta_of(pos)) / np.sqrt(np.diag(post.covariance))
    assert np.all(np.abs(z) < 4), z
    chi2 = float(z @ z)
    assert chi2 < 30, chi2  # 9 coordinates: chi2(9) exceeds 30 with probability 4e-4
    agree = bayes.laplace_agreement(post)
    assert agree["agrees"], agree
    # the posterior is far narrower than the 3 mm prior: the data, not the prior, speak
    assert np.all(np.sqrt(np.diag(post.covariance)) < 0.05 * bayes.PRIOR_STD)
    assert 0.07 <= post.acceptance.min() and post.acceptance.max() <= 0.35


def test_correlated_random_numbers_keep_the_target():
    """rho 0.9 against plain PmMH (rho 0), random walk only: two-sample KS per coordinate on thinned draws."""
    p, lap, *_ = _problem(seed=5, t=40)
    runs = {}
    for rho in (0.0, 0.9):
        runs[rho] = bayes.sample_posterior(p, lap, bayes.SamplerSettings(**{**FAST, "ess": 600}, rho=rho,
                                                                         independence=0.0, n_draws=1, seed=7))
    pvals = []
    for j in range(p.dim):
        a, b = (runs[r].draws[..., j].reshape(-1) for r in (0.0, 0.9))
        thin = lambda x, post: x[::max(1, int(len(x) / post.ess_bulk_min))]  # noqa: E731
        pvals.append(ks_2samp(thin(a, runs[0.0]), thin(b, runs[0.9])).pvalue)
    assert min(pvals) > 0.001 / p.dim, pvals  # Bonferroni at 0.1 %


def test_uniform_prior_keeps_every_draw_in_the_package():
    p, lap, *_ = _problem(seed=2, t=5, true_offset=5e-4, prior_kind="uniform")
    post = bayes.sample_posterior(p, lap, bayes.SamplerSettings(**FAST, seed=2))
    lo, hi = p.prior.mean - p.prior.std, p.prior.mean + p.prior.std
    assert np.all((post.flat >= lo) & (post.flat <= hi))
    assert p.prior.std[:3] == pytest.approx(np.array(bayes.PACKAGE_SIZE) / 2)


def test_runners_give_the_same_chains_in_processes_on_dask_and_in_process():
    """Each round carries its chain's generator: where the chains run cannot change a draw."""
    pytest.importorskip("distributed")
    p, lap, *_ = _problem(seed=8, t=10)
    settings = dict(ess=50, min_warmup=200, chunk=200, max_iterations=400, chains=2, seed=3)
    serial = bayes.sample_posterior(p, lap, bayes.SamplerSettings(scheduler="serial", **settings))
    procs = bayes.sample_posterior(p, lap, bayes.SamplerSettings(scheduler=None, workers=2, **settings))
    dask = bayes.sample_posterior(p, lap, bayes.SamplerSettings(scheduler="local", workers=2, **settings))
    assert procs.runner == "processes" and dask.runner == "dask" and serial.runner == "serial"
    np.testing.assert_array_equal(serial.draws, procs.draws)
    np.testing.assert_array_equal(serial.draws, dask.draws)
    assert dask.cpu_seconds > 0


def test_settings_are_checked():
    for bad in (dict(chains=1), dict(rho=1.0), dict(proposal="hmc"), dict(independence=1.0)):
        with pytest.raises(CalibrationError):
            bayes.SamplerSettings(**bad).check()


def test_an_unreachable_scheduler_is_a_one_line_error():
    pytest.importorskip("distributed")
    p, lap, *_ = _problem(seed=8, t=5)
    with pytest.raises(CalibrationError, match="cannot connect"):
        bayes.sample_posterior(p, lap, bayes.SamplerSettings(scheduler="tcp://127.0.0.1:9", chains=2, n_draws=1))


def test_importing_bayes_loads_no_optional_dependency():
    """The package imports numpy and the core only; ArviZ, Dask, h5netcdf ([bayes]) and matplotlib
    ([plots]) are loaded when a function needs them."""
    import subprocess
    import sys

    code = ("import sys; import imu_array_ros.calibration.bayes as b; "
            "print(sorted(m for m in ('arviz', 'dask', 'distributed', 'h5netcdf', 'matplotlib', 'xarray') "
            "if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stdout


def test_a_missing_extra_is_a_one_line_error_naming_it(monkeypatch):
    from imu_array_ros.errors import MissingDependencyError

    monkeypatch.setitem(sys.modules, "arviz", None)  # import arviz raises ImportError
    with pytest.raises(MissingDependencyError, match=r"arviz.*imu_array_ros\[bayes\]"):
        bayes.chain_diagnostics(np.zeros((2, 10, 3)))
    monkeypatch.setitem(sys.modules, "distributed", None)
    with pytest.raises(MissingDependencyError, match=r"distributed.*imu_array_ros\[bayes\]"):
        with bayes.dask_client("local", 1):
            pass


# --------------------------------------------------------------------------- the command


@pytest.fixture(scope="module")
def bayes_recording(tmp_path_factory):
    """A 2 s twist of a tetrahedron with seeded 0.3 mm position errors (imu_00 at nominal)."""
    from imu_array_ros.cli import main

    d = tmp_path_factory.mktemp("bayes")
    desc = tetrahedron4()
    save_description(desc, d / "array.yaml")
    model = SensorModel.from_description(desc)
    pos = model.positions.copy()
    pos[1:] += np.random.default_rng(5).normal(0, 3e-4, (3, 3))
    save_description(model.with_terms(position=pos).to_description(desc), d / "true.yaml")
    assert main(["simulate", "--array", str(d / "array.yaml"), "--true-array", str(d / "true.yaml"), "--out",
                 str(d / "twist"), "--duration", "2", "--rate", "200", "--seed", "3", "--start-time", START,
                 "-q"]) == 0
    return d, pos


def test_calibrate_bayes_writes_the_posterior_and_the_report(bayes_recording, capsys):
    d, pos = bayes_recording
    out, rep = d / "bayes.yaml", d / "report"
    code, stdout, err = cli(capsys, "calibrate", "bayes", d / "twist", "--array", d / "array.yaml", "--out", out,
                            "--samples", "40", "--chains", "2", "--scheduler", "serial", "--ess", "200",
                            "--report", rep)
    assert code == 0 and stdout == "", err
    assert "ESS bulk" in err and "warm-up" in err and f"wrote {out}" in err
    desc = load_description(out)
    mean = np.array([imu.position for imu in desc.imus])
    std = np.array([imu.stds["position"] for imu in desc.imus[1:]])
    assert np.all(std > 0) and np.all(std < 1e-3)
    assert np.all(np.abs(mean[1:] - pos[1:]) < 5 * std), (mean - pos, std)
    record = yaml.safe_load(out.read_text())["calibration"]
    assert record["samples"] == 40 and record["chains"] == 2 and record["converged"]
    cov = np.array(record["position_covariance"]["imu_01"])
    assert cov.shape == (3, 3) and np.allclose(np.sqrt(np.diag(cov)), std[0], rtol=1e-6)
    assert set(p.name for p in rep.iterdir()) >= {"diagnostics.json", "diagnostics.md", "ellipses.png", "trace.png",
                                                  "autocorr.png", "manifest.json"}
    # again without --force: refused, nothing touched
    before = out.read_bytes()
    assert_user_error(cli(capsys, "calibrate", "bayes", d / "twist", "--array", d / "array.yaml", "--out", out,
                          "-q"), str(out))
    assert out.read_bytes() == before


@pytest.mark.parametrize("args, fragment", [
    (["--chains", "1"], "chains"),
    (["--rho", "1"], "rho"),
    (["--reference", "nope"], "nope"),
    (["--samples", "0"], "--samples"),
])
def test_calibrate_bayes_bad_options_are_one_line_errors(bayes_recording, capsys, tmp_path, args, fragment):
    d, _ = bayes_recording
    out = tmp_path / "c.yaml"
    assert_user_error(cli(capsys, "calibrate", "bayes", d / "twist", "--array", d / "array.yaml", "--out", out,
                          "--scheduler", "serial", "-q", *args), fragment)
    assert not out.exists()


def test_calibrate_bayes_report_must_be_a_directory(bayes_recording, capsys, tmp_path):
    d, _ = bayes_recording
    (tmp_path / "file").write_text("x")
    assert_user_error(cli(capsys, "calibrate", "bayes", d / "twist", "--array", d / "array.yaml", "--out",
                          tmp_path / "c.yaml", "--report", tmp_path / "file", "-q"), "must be a directory")
    assert not (tmp_path / "c.yaml").exists()


def test_calibrate_bayes_report_follows_the_report_directory_rule(bayes_recording, capsys, tmp_path):
    """--report as for calibrate all and discover: a directory holding an input or other files is refused, even
    with --force, before any work; nothing is written."""
    d, _ = bayes_recording
    other = tmp_path / "other"
    other.mkdir()
    (other / "notes.txt").write_text("mine")
    for rep in (d, other):
        before = sorted(p.name for p in rep.iterdir())
        assert_user_error(cli(capsys, "calibrate", "bayes", d / "twist", "--array", d / "array.yaml", "--out",
                              tmp_path / "c.yaml", "--report", rep, "--force", "-q"), str(rep))
        assert sorted(p.name for p in rep.iterdir()) == before and not (tmp_path / "c.yaml").exists()


def test_still_recording_is_a_clear_error(capsys, tmp_path):
    from imu_array_ros.cli import main

    desc = tetrahedron4()
    save_description(desc, tmp_path / "a.yaml")
    assert main(["simulate", "--array", str(tmp_path / "a.yaml"), "--out", str(tmp_path / "still"), "--duration",
                 "1", "--rate", "100", "--rms-rate", "0.01", "--start-time", START, "-q"]) == 0
    assert_user_error(cli(capsys, "calibrate", "bayes", tmp_path / "still", "--array", tmp_path / "a.yaml", "--out",
                          tmp_path / "c.yaml", "--scheduler", "serial", "-q"), "rotation")


# --------------------------------------------------------------------------- review fixes


def test_still_samples_with_accelerometer_biases_are_not_taken_for_rotation():
    """Uncalibrated accelerometer biases make a still array's fused omega_dot large (the geometry test
    passes it as rotation); the gyroscopes say it is still, and select_samples drops it."""
    from imu_array_ros.model.samples import MotionTruth
    from imu_array_ros.simulation.simulator import simulate_measurements

    nominal = _unclipped(tetrahedron4())
    rng = np.random.default_rng(11)
    n = 200
    truth = simulate_gaussian(nominal, n, rng)[1]
    still = np.arange(n) < n // 2
    omega, omega_dot, force = truth.omega.copy(), truth.omega_dot.copy(), truth.specific_force.copy()
    omega[still], omega_dot[still], force[still] = 0.0, 0.0, [0.0, 0.0, 9.81]
    truth = MotionTruth(stamps=(np.arange(n) * 1e7).astype(np.int64), omega=omega, omega_dot=omega_dot,
                        specific_force=force)  # 100 Hz
    biased = nominal.with_terms(accelerometer_bias=0.3 * rng.normal(size=(4, 3)))
    s = simulate_measurements(biased, truth, rng, saturate=False)
    used = select_rotating(s, nominal, MIN_EXCITATION).used
    assert used[still].sum() > 80  # the accelerometer-based test alone lets the still samples through
    idx, dropped, usable = bayes.select_samples(s, nominal, None)
    # the last still sample's central difference reaches into the motion: a transition, not still
    assert set(np.flatnonzero(still[idx])) <= {0}, np.flatnonzero(still[idx])
    assert dropped["still_by_gyroscopes"] >= used[still].sum() - 1
    assert usable >= 0.9 * (~still).sum()  # the moving samples stay


def test_sample_covariance_laplace_has_the_likelihoods_information_about_omega():
    """eq. 30 uses the spread of single gyroscopes as omega's covariance (not of their mean, as the paper
    writes): K times the model's sigma^2 / K. The Laplace approximation's equivalent gyroscope std must
    carry that information: sqrt(K) times the simulated gyroscopes' std."""
    p, lap, s, *_ , nominal = _problem(seed=6, t=60, desc=grid_array32(), omega_covariance="sample")
    ratio = bayes.sample_gyro_std(p) / nominal.gyro_std / np.sqrt(nominal.n_imus)
    assert np.all((ratio > 0.85) & (ratio < 1.15)), ratio


def test_a_log_likelihood_too_noisy_to_sample_is_a_clear_error(monkeypatch):
    """Accelerometer noise 100x too small for the data: no N up to the cap makes the estimate usable."""
    p, lap, s, *_ , nominal = _problem(seed=9, t=40, accel_std=1e-4)
    monkeypatch.setattr(bayes_sampler, "MAX_DRAWS", 8)  # the module choose_draws reads it from
    with pytest.raises(CalibrationError, match="too noisy to sample.*n_draws"):
        bayes.sample_posterior(p, lap, bayes.SamplerSettings(scheduler="serial", seed=0))
    n, table = bayes.choose_draws(p, lap.mean, 0.1, np.random.default_rng(0))
    assert n == 8 and table[-1][1] > 10 * 0.1


def test_sampling_rounds_grow_geometrically_when_only_rhat_is_missing():
    """When the ESS is met but R-hat cannot be (target 1.0001), the rounds still grow geometrically
    (they fell back to one chunk each, re-running the diagnostics on all draws: 55 rounds here)."""
    p, lap, *_ = _problem(seed=3, t=30)
    lines = []
    post = bayes.sample_posterior(p, lap, bayes.SamplerSettings(scheduler="serial", independence=0.0, n_draws=1,
                                                                seed=4, chunk=500, min_warmup=1000,
                                                                max_warmup=30000, rhat=1.0001, max_iterations=30000),
                                  progress=lines.append)
    assert post.warmup < 15000, post.warmup
    rounds = [x for x in lines if x.startswith("sampling:")]
    assert post.draws.shape[1] == 30000 and len(rounds) <= 12, rounds  # one-chunk rounds: 60
