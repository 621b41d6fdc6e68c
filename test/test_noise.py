"""Noise characterisation (``calibrate noise``): Allan deviation estimates against simulated truth, the
description's per-IMU noise fields, per-IMU noise reaching the fusion, and the command line."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import yaml

from imu_array_ros.calibration.noise import characterise_noise, noise_calibration
from imu_array_ros.errors import ConfigError
from imu_array_ros.fusion.ml_fusion import fuse
from imu_array_ros.model.description import description_from_dict, description_to_dict, dump_description, \
    load_description
from imu_array_ros.model.linear import LinearArrayModel
from imu_array_ros.model.samples import ImuSamples
from imu_array_ros.model.sensor_model import SensorModel
from imu_array_ros.simulation.simulator import simulate_twist

from conftest import REPO, START, assert_user_error, cli

pytest.importorskip("allantools")

MIMU = REPO / "config" / "mimu4444bt_corners.yaml"
NILSSON14 = REPO / "config" / "nilsson14.yaml"
RATE = 62.5


def still_recording(desc, seconds: float, white: np.ndarray, walk: np.ndarray, seed: int,
                    gaps: int = 0) -> ImuSamples:
    """The array resting flat for ``seconds`` at RATE: each reading gravity (or 0) + white noise of std
    ``white`` (2, K, 3) per sample + a bias random walk of ``walk`` (2, K, 3) unit/sqrt(s), simulated directly;
    ``gaps`` missing readings (NaN) per IMU at random samples (the data then come in segments)."""
    rng = np.random.default_rng(seed)
    model = SensorModel.from_description(desc)
    n, k = int(seconds * RATE), len(desc.imus)
    g = np.einsum("kji,j->ki", model.rotations, [0.0, 0.0, 9.80665])  # R_k^T s: specific force in sensor frames
    out = []
    for j, base in enumerate((g, np.zeros((k, 3)))):
        x = base + white[j] * rng.normal(size=(n, k, 3))
        x += np.cumsum(rng.normal(size=(n, k, 3)), axis=0) * walk[j] * np.sqrt(1 / RATE)
        out.append(x)
    for kk in range(k):
        i = rng.integers(n, size=gaps)
        out[0][i, kk] = out[1][i, kk] = np.nan
    stamps = np.arange(n, dtype=np.int64) * int(round(1e9 / RATE))
    return ImuSamples(stamps, out[0], out[1], desc.names)


def per_imu_white(k: int) -> np.ndarray:
    """(2, K, 3) per-sample white-noise stds: accelerometers 0.03-0.06 m/s^2, gyroscopes 0.002-0.006 rad/s."""
    f = np.linspace(1.0, 2.0, 3 * k).reshape(k, 3)
    return np.stack([0.03 * f, 0.002 * f[::-1] * 1.5])


@pytest.fixture(scope="module")
def mimu():
    return load_description(MIMU)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_white_noise_and_random_walk_are_recovered_within_their_stated_uncertainty(mimu, seed):
    """10 minutes still, with gaps (the data come in segments, pooled); the white noise within 3 % and within
    ~1.5x its stated std (the fit treats octave taus as independent: errors 1.2-1.6 stated std RMS); the
    random walk, where seen (the +1/2 slope up to tau 33-66 s), within a factor 2 and ~1.5x its stated std."""
    k = len(mimu.imus)
    white = per_imu_white(k)
    walk = np.stack([np.full((k, 3), 4e-4), np.full((k, 3), 4e-5)])  # m/s^2/sqrt(s), rad/s/sqrt(s)
    samples = still_recording(mimu, 600.0, white, walk, seed, gaps=5)
    result = characterise_noise(samples, SensorModel.from_description(mimu))
    z_n, z_k, ratio_k = [], [], []
    for j, sensor in enumerate(("accelerometer", "gyroscope")):
        for kk, s in enumerate(result.sensors[sensor]):
            assert s.segments > 1  # the gaps split the interval: pooled over segments
            assert s.tau_range[1] >= 32.0
            np.testing.assert_allclose(s.noise_std, white[j, kk], rtol=0.03)
            z_n.extend((s.noise_std - white[j, kk]) / s.noise_std_std)
            seen = np.isfinite(s.random_walk)
            z_k.extend(((s.random_walk - walk[j, kk]) / s.random_walk_std)[seen])
            ratio_k.extend((s.random_walk / walk[j, kk])[seen])
    z_n, z_k, ratio_k = np.array(z_n), np.array(z_k), np.array(ratio_k)
    print(f"\nN: z RMS {np.sqrt(np.mean(z_n**2)):.2f} max {np.abs(z_n).max():.2f}; K seen on {len(z_k)} of 48 axes, "
          f"z RMS {np.sqrt(np.mean(z_k**2)):.2f} max {np.abs(z_k).max():.2f}, ratio {ratio_k.min():.2f}-{ratio_k.max():.2f}")
    assert np.abs(z_n).max() < 5.0 and 0.5 < np.sqrt(np.mean(z_n ** 2)) < 1.8
    assert len(z_k) >= 10
    assert np.abs(z_k).max() < 5.0 and np.sqrt(np.mean(z_k ** 2)) < 1.8
    assert np.all(np.abs(np.log(ratio_k)) < np.log(2.0))  # stated relative std 0.15-0.3: 3 sigma ~ a factor 2


def test_no_random_walk_is_invented_where_the_rests_are_too_short(mimu):
    """20 rests of 22 s (tau up to ~8 s) with a random walk too small to show there: not written (NaN), and
    the record says null; white noise alone likewise."""
    k = len(mimu.imus)
    white = per_imu_white(k)
    for seed, walk in ((4, np.stack([np.full((k, 3), 2e-4), np.full((k, 3), 2e-5)])), (5, np.zeros((2, k, 3)))):
        samples = still_recording(mimu, 22.0, white, walk, seed)
        cal = noise_calibration(samples, SensorModel.from_description(mimu))
        seen = sum(int(np.isfinite(s.random_walk).sum()) for per in cal.details.sensors.values() for s in per)
        assert seen <= 2, seen  # at most a chance 2-sigma significance on 48 axes
        hi = max(s.tau_range[1] for s in cal.details.sensors["gyroscope"])
        assert 4.0 <= hi <= 11.0
        record = cal.record["imus"][mimu.names[0]]["gyroscope"]
        assert len(record["bias_random_walk"]) == 3 and record["tau_range_s"][1] == hi


def test_a_random_walk_looked_for_and_not_seen_is_written_null_and_export_kalibr_says_so(mimu, tmp_path, capsys):
    """calibrate noise on rests too short for the random walk: the file says it was measured (all-null
    bias_random_walk), and export kalibr says the noise calibration saw none instead of "run calibrate noise";
    so does a file written before (the figure left out, the noise calibration's record beside it)."""
    k = len(mimu.imus)
    cal = noise_calibration(still_recording(mimu, 22.0, per_imu_white(k), np.zeros((2, k, 3)), 5),
                            SensorModel.from_description(mimu))
    first = cal.details.sensors["accelerometer"][0]
    assert first is not None and not np.isfinite(first.random_walk).any()  # imu_1's accelerometer: none seen
    written = tmp_path / "noise.yaml"
    written.write_text(dump_description(cal.apply(mimu)))
    doc = yaml.safe_load(written.read_text())
    assert doc["imu_array"]["imus"][0]["accelerometer"]["bias_random_walk"] == [None, None, None]
    assert np.isnan(load_description(written).imus[0].noise["accelerometer.bias_random_walk"]).all()
    for imu in doc["imu_array"]["imus"]:  # as calibrate noise wrote them before: all-null figures left out
        for sensor in ("accelerometer", "gyroscope"):
            for leaf in ("bias_random_walk", "bias_instability"):
                if imu[sensor].get(leaf) == [None, None, None]:
                    del imu[sensor][leaf]
    old = tmp_path / "old.yaml"
    old.write_text(yaml.safe_dump(doc, sort_keys=False))
    for path in (written, old):
        line = assert_user_error(cli(capsys, "export", "kalibr", path, "--out", tmp_path / "k.yaml", "--rate", RATE),
                                 f"{path}: Kalibr requires a bias_random_walk", "the accelerometer (imu 'imu_1'",
                                 "the noise calibration it holds did not see one", "--random-walk-accel")
        assert "run 'imu-array calibrate noise'" not in line
    assert not (tmp_path / "k.yaml").exists()


def test_description_round_trip_of_the_noise_fields(mimu):
    imus = list(mimu.imus)
    imus[0] = imus[0].with_noise({"accelerometer.noise_std": [0.03, 0.04, 0.05],
                                  "accelerometer.bias_random_walk": [1e-4, np.nan, 2e-4],
                                  "gyroscope.bias_instability": [np.nan, np.nan, 3e-5]})
    imus[3] = imus[3].with_noise({"gyroscope.noise_std": [0.002, 0.003, 0.004]})
    desc = mimu.with_imus(imus)
    text = dump_description(desc)
    assert "bias_random_walk: [0.0001, null, 0.0002]" in text
    back = description_from_dict(yaml.safe_load(text))
    for a, b in zip(desc.imus, back.imus):
        assert set(a.noise) == set(b.noise)
        for key in a.noise:
            np.testing.assert_array_equal(a.noise[key], b.noise[key])
    assert dump_description(back) == text
    model = SensorModel.from_description(back)
    np.testing.assert_array_equal(model.acc_std[0], [0.03, 0.04, 0.05])
    np.testing.assert_array_equal(model.gyro_std[3], [0.002, 0.003, 0.004])
    assert np.all(model.acc_std[1:] == mimu.accelerometer_noise_std)  # the pooled figure holds elsewhere
    assert np.all(np.delete(model.gyro_std, 3, axis=0) == mimu.gyroscope_noise_std)
    raw = description_to_dict(back)
    for bad, what in (([0.03, 0.0, 0.05], "must be > 0"), ([0.03, 0.04], "list of 3"), ([0.03, None, 0.05], "number")):
        doc = yaml.safe_load(yaml.safe_dump(raw))
        doc["imu_array"]["imus"][0]["accelerometer"]["noise_std"] = bad
        with pytest.raises(ConfigError, match=what):
            description_from_dict(doc, source="x.yaml")
    doc = yaml.safe_load(yaml.safe_dump(raw))
    doc["imu_array"]["imus"][0]["accelerometer"]["bias_random_walk"] = [-1e-4, None, 1e-4]
    with pytest.raises(ConfigError, match=r"imu 'imu_1'.accelerometer.bias_random_walk: must be >= 0"):
        description_from_dict(doc, source="x.yaml")


def test_per_imu_noise_reaches_the_fusion_covariance_and_the_simulator():
    """An array whose IMUs differ in noise (some 3x the others), simulated from its per-IMU description: fused
    with that description the NEES is ~3 per triad; with the pooled figure (the mean) it is not, and the fused
    covariance differs."""
    desc = load_description(NILSSON14)
    k = len(desc.imus)
    factor = np.where(np.arange(k) % 3 == 0, 3.0, 1.0)
    imus = [imu.with_noise({"accelerometer.noise_std": np.full(3, desc.accelerometer_noise_std * f),
                            "gyroscope.noise_std": np.full(3, desc.gyroscope_noise_std * f)})
            for imu, f in zip(desc.imus, factor)]
    per_imu = desc.with_imus(imus)
    pooled = replace(desc, accelerometer_noise_std=float(desc.accelerometer_noise_std * factor.mean()),
                     gyroscope_noise_std=float(desc.gyroscope_noise_std * factor.mean()))
    model = SensorModel.from_description(per_imu)
    np.testing.assert_allclose(model.gyro_std[:, 0], desc.gyroscope_noise_std * factor)
    samples, truth = simulate_twist(per_imu, duration=4.0, rate_hz=500.0, rng=np.random.default_rng(7))
    resid = samples.gyro - np.einsum("kji,nj->nki", model.rotations, truth.omega)  # gyroscopes: no position term
    np.testing.assert_allclose(resid.std(axis=(0, 2)), desc.gyroscope_noise_std * factor, rtol=0.05)

    def nees(d):
        fused, _ = fuse(samples, LinearArrayModel.from_description(d))
        e = fused.omega - truth.omega
        return fused.covariance[:, :3, :3], np.mean(np.einsum("ni,nij,nj->n", e, np.linalg.inv(fused.covariance[:, :3, :3]), e))

    cov_i, nees_i = nees(per_imu)
    cov_p, nees_p = nees(pooled)
    n = len(samples)
    print(f"\nNEES per-IMU {nees_i:.3f}, pooled {nees_p:.3f}")
    assert abs(nees_i - 3) < 4 * np.sqrt(6 / n)
    assert abs(nees_p - 3) > 10 * np.sqrt(6 / n)
    assert not np.allclose(cov_i, cov_p, rtol=0.05)


# --------------------------------------------------------------------------- the command line


@pytest.fixture(scope="module")
def recordings(tmp_path_factory):
    """The MIMU4444BT corners on the 20 faces at 62.5 Hz: 3 s rests (too short) and 8 s rests, from a per-IMU
    noise description (imu_1 with twice the noise)."""
    from imu_array_ros.cli import main

    d = tmp_path_factory.mktemp("noise")
    desc = load_description(MIMU)
    imus = list(desc.imus)
    imus[0] = imus[0].with_noise({"accelerometer.noise_std": np.full(3, 2 * desc.accelerometer_noise_std),
                                  "gyroscope.noise_std": np.full(3, 2 * desc.gyroscope_noise_std)})
    (d / "truth.yaml").write_text(dump_description(desc.with_imus(imus)))
    for name, still in (("short", "3"), ("long", "8")):
        assert main(["simulate", "--array", str(d / "truth.yaml"), "--out", str(d / name), "--motion", "icosahedron",
                     "--still-seconds", still, "--transition-seconds", "1", "--twist-seconds", "1", "--rate", "62.5",
                     "--seed", "3", "--start-time", START, "-q"]) == 0
    return d


def test_cli_refuses_without_a_long_enough_still_interval_and_writes_nothing(recordings, capsys):
    out, plot = recordings / "refused.yaml", recordings / "refused.png"
    line = assert_user_error(cli(capsys, "calibrate", "noise", recordings / "short", "--array", MIMU,
                                 "--out", out, "--plot", plot, "-q"),
                             "no still interval of 5 s or more", "6.5 s or more")
    assert "short" in line
    assert not out.exists() and not plot.exists()


def test_cli_writes_per_imu_noise_and_a_plot(recordings, capsys):
    out, plot = recordings / "noise.yaml", recordings / "noise.png"
    code, stdout, err = cli(capsys, "calibrate", "noise", recordings / "long", "--array", MIMU,
                            "--out", out, "--plot", plot)
    assert code == 0 and stdout == "", err
    assert "still intervals: 20 of 5 s" in err and f"wrote {out}" in err and f"wrote {plot}" in err
    assert plot.stat().st_size > 10000
    doc = yaml.safe_load(out.read_text())
    record = doc["calibration"]
    assert record["method"].startswith("noise") and record["still_intervals"] == 20
    assert record["imus"]["imu_1"]["still_seconds"] > 100
    cal = load_description(out)
    model = SensorModel.from_description(cal)
    nominal = load_description(MIMU)
    truth = np.full(len(cal.imus), nominal.gyroscope_noise_std)
    truth[0] *= 2
    sd = np.array([record["imus"][n]["gyroscope"]["noise_std_std"] for n in cal.names])
    z = (model.gyro_std - truth[:, None]) / sd
    assert np.abs(z).max() < 4.5, z
    acc_truth = np.full(len(cal.imus), nominal.accelerometer_noise_std)
    acc_truth[0] *= 2
    np.testing.assert_allclose(model.acc_std, np.repeat(acc_truth[:, None], 3, axis=1), rtol=0.05)
    # again: the previous file is kept as .bak
    code, _, err = cli(capsys, "calibrate", "noise", recordings / "long", "--array", MIMU, "--out", out,
                       "--force", "-q")
    assert code == 0 and err == "" and (recordings / "noise.yaml.bak").exists()


def test_raw_imu_messages_carry_each_imus_own_noise(mimu):
    """The driver's and the recordings' raw Imu messages: covariance = diag(noise_std^2) of that IMU (its own
    figures where the description has them, the pooled ones elsewhere)."""
    from imu_array_ros.io.messages import concat_payloads, raw_imu_payloads
    from imu_array_ros.io.rosbag.cdr_columns import decode_imu

    imus = list(mimu.imus)
    imus[2] = imus[2].with_noise({"accelerometer.noise_std": [0.03, 0.04, 0.05],
                                  "gyroscope.noise_std": [0.002, 0.003, 0.004]})
    desc = mimu.with_imus(imus)
    k = len(desc.imus)
    samples = ImuSamples(np.array([1, 2], dtype=np.int64), np.zeros((2, k, 3)), np.zeros((2, k, 3)), desc.names)
    for i, (rows, payload) in enumerate(raw_imu_payloads(samples, desc)):
        buf, off, length = concat_payloads(list(payload))
        cols = decode_imu(buf, off, length)
        acc = np.asarray(cols["linear_acceleration_covariance"]).reshape(-1, 3, 3)
        gyr = np.asarray(cols["angular_velocity_covariance"]).reshape(-1, 3, 3)
        want_a = [0.03, 0.04, 0.05] if i == 2 else [mimu.accelerometer_noise_std] * 3
        want_g = [0.002, 0.003, 0.004] if i == 2 else [mimu.gyroscope_noise_std] * 3
        np.testing.assert_allclose(acc[0], np.diag(np.square(want_a)))
        np.testing.assert_allclose(gyr[1], np.diag(np.square(want_g)))
