"""Reports of a Bayesian position calibration (:class:`~imu_array_ros.calibration.bayes.posterior.BayesPosterior`).

:mod:`.ellipses` and :mod:`.chains` draw (matplotlib, the ``[plots]`` extra, imported only when drawing),
:mod:`.tables` computes the rows and the markdown, :mod:`.files` writes them all into a directory.
"""

from imu_array_ros.calibration.bayes.report.chains import plot_autocorr, plot_trace
from imu_array_ros.calibration.bayes.report.ellipses import ESTIMATE_COLORS, PRIOR_COLOR, ellipse_points, \
    ellipse_radius, panel_layout, plot_ellipses
from imu_array_ros.calibration.bayes.report.files import BAYES_REPORT_NETCDF, BAYES_REPORT_PNGS, \
    BAYES_REPORT_TEXT, write_report
from imu_array_ros.calibration.bayes.report.tables import SD_RATIO_RANGE, Z_LIMIT, diagnostics_table, \
    disagreements, lowest_ess_coords

__all__ = ["ellipse_points", "ellipse_radius", "plot_ellipses", "panel_layout", "plot_trace", "plot_autocorr",
           "lowest_ess_coords", "diagnostics_table", "disagreements", "write_report", "Z_LIMIT", "SD_RATIO_RANGE",
           "PRIOR_COLOR", "ESTIMATE_COLORS", "BAYES_REPORT_TEXT", "BAYES_REPORT_PNGS", "BAYES_REPORT_NETCDF"]
