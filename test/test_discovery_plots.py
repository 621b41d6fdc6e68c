"""PNG plots of a mismatch-discovery report."""

from __future__ import annotations

import sys

import numpy as np
import pytest

matplotlib = pytest.importorskip("matplotlib")

from imu_array_ros.discovery import plots  # noqa: E402
from imu_array_ros.errors import MissingDependencyError  # noqa: E402

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
NAMES = [f"imu_{i + 1}" for i in range(8)]


@pytest.fixture
def figures(monkeypatch):
    """Every figure the plot functions close, in order (and checks they were closed)."""
    import matplotlib.pyplot as plt

    closed = []
    real_close = plt.close

    def close(fig=None):
        closed.append(fig)
        real_close(fig)

    monkeypatch.setattr(plt, "close", close)
    yield closed
    for fig in closed:
        assert fig.number not in plt.get_fignums()


def _texts(fig) -> list[str]:
    from matplotlib.text import Text

    return [t.get_text() for t in fig.findobj(Text)]


def _check_png(directory, name):
    """The directory holds exactly the PNG ``name``: non-empty, PNG signature, no temporaries."""
    assert sorted(p.name for p in directory.iterdir()) == [name]
    data = (directory / name).read_bytes()
    assert len(data) > 1000 and data[:8] == PNG_MAGIC


def _maps(rng):
    before = np.exp(rng.normal(1.0, 1.0, size=(8, 6)))
    after = np.exp(rng.normal(0.0, 0.1, size=(8, 6)))
    before[0, 0], after[0, 0] = 3.2, 1.0
    before[5, 4] = after[5, 4] = np.nan      # no data for one cell
    after[7] = np.nan                         # nor for one IMU afterwards
    return before, after


def test_residual_maps(tmp_path, figures):
    before, after = _maps(np.random.default_rng(0))
    plots.plot_residual_maps(before, after, NAMES, tmp_path / "maps.png", title="vibration of imu_3")
    _check_png(tmp_path, "maps.png")
    (fig,) = figures
    texts = _texts(fig)
    assert "3.2" in texts and "1.0" in texts and "vibration of imu_3" in texts
    assert {"imu_1", "imu_8", "acc_x", "gyr_z"} <= set(texts)
    # both maps share one logarithmic colour scale, reaching down to 0.5 and up to the largest ratio
    images = [im for ax in fig.axes for im in ax.get_images()]
    assert len(images) == 2 and images[0].norm is images[1].norm
    assert images[0].norm.vmin == pytest.approx(min(0.5, np.nanmin(before), np.nanmin(after)))
    assert images[0].norm.vmax == pytest.approx(np.nanmax(before))
    assert type(images[0].norm).__name__ == "LogNorm"


def test_residual_maps_all_nan_and_single(tmp_path, figures):
    nan = np.full((8, 6), np.nan)
    plots.plot_residual_maps(nan, nan, NAMES, tmp_path / "a.png")
    plots.plot_residual_maps(np.ones((8, 6)), None, NAMES, tmp_path / "b.png")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.png", "b.png"]
    assert all((tmp_path / n).read_bytes()[:8] == PNG_MAGIC for n in ("a.png", "b.png"))
    with pytest.raises(ValueError, match="shape"):
        plots.plot_residual_maps(np.ones((7, 6)), None, NAMES, tmp_path / "c.png")
    assert len(figures) == 2


def _spectra(rng):
    f = np.linspace(0.0, 100.0, 257)
    before = np.exp(rng.normal(0.0, 0.2, size=(8, 6, f.size)))
    before[2, 2] += 300.0 * np.exp(-0.5 * ((f - 23.0) / 0.5) ** 2)   # a mode at 23 Hz
    before[3, 0] += 20.0 / (1.0 + (f / 3.0) ** 2)                   # coloured noise
    after = before.copy()
    after[3, 0] = np.exp(rng.normal(0.0, 0.2, size=f.size))
    before[6, 5] = np.nan                                            # no data
    return f, before, after


def test_spectra_default_cells(tmp_path, figures):
    f, before, after = _spectra(np.random.default_rng(1))
    plots.plot_spectra(f, before, after, NAMES, tmp_path / "spectra.png")
    _check_png(tmp_path, "spectra.png")
    texts = _texts(figures[0])
    assert "imu_3 acc_z" in texts and "imu_4 acc_x" in texts and "Hz" in texts
    panels = [t for t in texts if t.startswith("imu_")]
    assert len(panels) == 6 and "imu_7 gyr_z" not in panels
    assert any(ax.get_yscale() == "log" for ax in figures[0].axes)


def test_spectra_without_after_and_nan_cell(tmp_path, figures):
    f, before, _ = _spectra(np.random.default_rng(2))
    plots.plot_spectra(f, before, None, NAMES, tmp_path / "s.png", cells=[(2, 2), (6, 5)])
    _check_png(tmp_path, "s.png")
    texts = _texts(figures[0])
    assert "imu_3 acc_z" in texts and "imu_7 gyr_z: no data" in texts and "after" not in texts


def _candidates():
    return [
        {"effect": "vibration", "sensors": ["imu_3"], "delta_loglik": 5400.0, "accepted": True, "step": 1},
        {"effect": "colored_noise", "sensors": ["imu_4"], "delta_loglik": 310.0, "accepted": True, "step": 2},
        {"effect": "time_offset", "sensors": ["imu_2"], "delta_loglik": 3.1, "accepted": False, "step": 3},
        {"effect": "position", "sensors": ["imu_1", "imu_5"], "delta_loglik": -2.0, "accepted": False, "step": 3},
        {"effect": "gyroscope_bias", "sensors": [], "delta_loglik": float("nan"), "accepted": False, "step": 3},
    ] + [{"effect": f"term_{i}", "sensors": ["imu_6"], "delta_loglik": 0.01 * i, "accepted": False, "step": 3}
         for i in range(40)]


def test_evidence(tmp_path, figures):
    plots.plot_evidence(_candidates(), tmp_path / "evidence.png", threshold=12.5, top=10)
    _check_png(tmp_path, "evidence.png")
    (fig,) = figures
    texts = _texts(fig)
    assert "vibration @ imu_3" in texts and "colored_noise @ imu_4" in texts and "time_offset @ imu_2" in texts
    assert "gyroscope_bias" not in texts  # NaN sorts last, beyond the top 10
    ax = fig.axes[0]
    labels = [t.get_text() for _, t in sorted(zip(ax.get_yticks(), ax.get_yticklabels()), key=lambda p: -p[0])]
    assert len(labels) == 10 and labels[:3] == ["vibration @ imu_3", "colored_noise @ imu_4", "time_offset @ imu_2"]
    assert ax.get_xscale() == "log"
    assert any(t.startswith("threshold") for t in texts) and "accepted" in texts
    colors = {tuple(np.round(p.get_facecolor(), 3)) for p in ax.patches}
    assert len(colors) == 2


def test_evidence_empty_and_no_threshold(tmp_path, figures):
    plots.plot_evidence([], tmp_path / "empty.png")
    _check_png(tmp_path, "empty.png")
    assert "no candidates" in _texts(figures[0])
    plots.plot_evidence(_candidates()[:5], tmp_path / "few.png")
    assert (tmp_path / "few.png").read_bytes()[:8] == PNG_MAGIC
    assert "position @ imu_1, imu_5" in _texts(figures[1]) and "gyroscope_bias" in _texts(figures[1])


def test_time(tmp_path, figures):
    t = np.arange(0.0, 60.0, 2.0)
    before = np.exp(np.random.default_rng(3).normal(1.0, 0.5, t.size))
    after = np.ones_like(t)
    before[4] = np.nan
    plots.plot_time(t, before, after, tmp_path / "time.png", spans=[(10.0, 20.0, "twisting"), (40.0, 45.0)])
    _check_png(tmp_path, "time.png")
    texts = _texts(figures[0])
    assert "twisting" in texts and "time (s)" in texts
    assert figures[0].axes[0].get_yscale() == "log"
    plots.plot_time(t, np.full(t.size, np.nan), None, tmp_path / "nan.png")
    assert "no data" in _texts(figures[1])


def test_failed_write_leaves_nothing(tmp_path, figures, monkeypatch):
    from matplotlib.figure import Figure

    def broken(self, *args, **kwargs):
        raise RuntimeError("disk full")

    monkeypatch.setattr(Figure, "savefig", broken)
    with pytest.raises(RuntimeError, match="disk full"):
        plots.plot_evidence(_candidates(), tmp_path / "evidence.png")
    assert list(tmp_path.iterdir()) == [] and len(figures) == 1


def test_without_matplotlib(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib raises ImportError
    with pytest.raises(MissingDependencyError, match=r"matplotlib.*imu_array_ros\[plots\]"):
        plots.plot_time([0.0, 1.0], [1.0, 2.0], None, tmp_path / "t.png")
    assert list(tmp_path.iterdir()) == []
