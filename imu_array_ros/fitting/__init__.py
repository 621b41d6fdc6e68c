"""The one fitting engine: maximum likelihood of sensor-model terms jointly with the motion.

Problem
-------
Sample n (n = 1..N) of IMU k reads six axes r = [acc x, y, z, gyro x, y, z]::

    y_nkr = h_kr(x_n, theta_k) + e_nkr,    e_nkr ~ N(0, sigma_kr^2) white,

with h the sensor model (:class:`~imu_array_ros.model.sensor_model.SensorModel`),
x_n = [omega, omega_dot, s] (9) the motion of sample n and theta_k the free
terms' parameters of IMU k (IMU k's parameters move only IMU k's readings).
Saturated and missing axes carry no information and get weight 0, as in the
fusion.  Maximum likelihood of (theta, x_1..x_N) is weighted least squares of
the normalised residuals r = w (y - h), w = 1/sigma (0 on masked axes).

Gauss-Newton with J_x = w dh/dx (per sample) and J_t = w dh/dtheta has
block-arrow normal equations, one 9x9 block per sample coupled only through theta::

    [ A_1            B_1 ] [dx_1 ]   [gx_1]      A_n = J_x^T J_x      (9 x 9)
    [      ...       ... ] [ ... ] = [ ...]      B_n = J_x^T J_t      (9 x dim theta)
    [            A_N B_N ] [dx_N ]   [gx_N]      C   = sum_n J_t^T J_t (block diagonal by IMU)
    [ B_1^T .. B_N^T  C  ] [dth  ]   [ gt ]      g   = J^T r

Eliminating every dx_n (Schur complement), with A_n = L_n L_n^T (Cholesky),
G_n = L_n^-1 B_n and h_n = L_n^-1 gx_n::

    S dth = g_red,     S = C - sum_n G_n^T G_n,     g_red = gt - sum_n G_n^T h_n,
    dx_n = L_n^-T (h_n - G_n dth).

Per chunk of samples the G_n are stacked into one (9 n, dim theta) matrix and
``S -= G^T G`` is one matrix product, so a step costs O(N) in the samples with
no per-sample Python loop; a dim-theta system is solved per step
(Levenberg-Marquardt damping on S's diagonal, accepted when the cost drops; a
trial whose back-substituted dx_n raises the cost is judged again after one
Gauss-Newton step of each sample's motion alone at the new theta, since the
motion can respond to theta far from linearly: time offsets x omega_dot).
The initial motion is self-contained: the gyroscopes (and accelerometers)
mapped to the array frame and averaged, refined by the same machinery with no
free parameters (batched 9x9 Gauss-Newton steps).

Cramér-Rao bound
----------------
J^T J is the Fisher information of the joint problem (theta, x_1..x_N); the
information about theta with the motion unknown is its Schur complement, S.
The covariance returned is S^-1 at the estimate (in the gauge chosen below):
the Cramér-Rao bound of the joint problem that carlsson2017 Sec. VI leaves open.

Misfit-robust covariance
------------------------
The CRB holds only when the model is exact and the noise white.  Beside it the
engine returns the sandwich S^-1 B S^-1 (``covariance_robust``, ``std_robust``),
B the long-run covariance of the per-sample profiled scores
u_n = J_t,n^T r_n - G_n^T h_n (sum_n u_n = g_red), estimated from sums over
time blocks whose length is chosen from the data (:mod:`.robust`).  It equals
the CRB to within its sampling noise when the model is exact, and is the
estimate's spread over recordings when the residuals are time-correlated misfit;
the calibrations write it as ``_std``.

Gauge
-----
Some parameter combinations change no reading when the motion changes with
them: a common shift of every position (s absorbs it: s + C (p + d) = s' + C p
with s' = s + C d), of every time offset (the time base), accelerometer biases
forming a rigid-body field b + c x p_k (s and omega_dot absorb it), a common
gyroscope scale traded against the scale of the positions (omega (1 + e),
omega_dot (1 + e)^2, p / (1 + e)^2), ...  They are found as the null space of
the Jacobi-scaled S (eigenvalues below ``NULL_RTOL``), computed at the
*structural point* (the model with every term but the positions at its identity
value, so that a small known time offset cannot fake information through the
approximation below).  With ``gauge="reference"`` they are fixed by holding
parameters of the reference IMU, tried in the order ``GAUGE_ORDER`` then every
other free term, and, for what is left (e.g. the rotational part of the bias
field), of the other fitted IMUs in turn.  A parameter is held only when that
removes a null direction which also involves other IMUs (a *collective*
direction, a gauge freedom; an unidentifiable parameter of one IMU alone is not
one).  With ``gauge="mean"`` the same directions are instead fixed by keeping
the parameters' component along each of them (in SI units: e.g. the centroid
of the positions, the mean time offset) at its initial value.

Identifiability
---------------
Null directions left after that are not identifiable from the recording.
Motion that is missing (e.g. angular acceleration about x and y when the array
turns about z only) is not exactly missing at the estimated motion: there it is
replaced by the estimate's noise, which fakes a little information.  So the
information F that the motion noise alone produces (S rebuilt from the change
of the parameter Jacobian under one draw of that noise) is compared with S:
directions with more than ``NOISE_SHARE`` of their information from the noise
are not identified either.  Both raise :class:`CalibrationError` naming the
parameters involved and the motion that would identify them (``Term.hint``);
nothing is regularised silently.

Approximation
-------------
The timing terms (time offsets, sample clocks, stamp clocks) evaluate every reading at its true sample
time along the motion near its sample: local quartics through the current motion estimate
(:func:`~imu_array_ros.model.trajectory.timing_context` with ``ENGINE_DEGREE``: the fusion compensates along
cubics, whose smoothing biased fitted time offsets on fast motion; see :mod:`imu_array_ros.model.trajectory`),
held fixed
through an optimisation round, in the predictions, the Jacobians and the cost of the trial steps, and rebuilt
from the motion found between rounds until the fixed point (:mod:`.rounds`: a Gauss-Newton step on the motion's
own trajectory moves no parameter by 0.05 std; ``converged`` False when the round cap comes first); their
Jacobians are first order in the delay (d y / d theta = dx/dt d delay / d theta, the slopes of the same quartics;
a gyroscope's rate of change is that of the angular-rate estimates, not the omega_dot state, which a bias
field's gauge may shift).  The dependence of sample n's readings on its neighbours' motion through the quartics is
neglected (keeps the normal equations block-arrow), and the iteration converges to the point that is optimal for
the trajectory of its own motion.  The effect is second order in the delay (milliseconds) times the noise of the
motion estimate.

Modules
-------
:mod:`.engine` the entry points (:func:`fit_terms`, :func:`fit_motion`,
:class:`FitResult`); :mod:`.problem` readings, weights, parameter layout and
the Schur-complemented linearisation; :mod:`.schur` the batched algebra of the
Schur step; :mod:`.gauge` null space and gauge fixing; :mod:`.identifiability`
the noise-share check and the one-line messages; :mod:`.optimiser`
Levenberg-Marquardt; :mod:`.rounds` the trajectory rounds of fits with timing terms; :mod:`.robust` the
sandwich covariance and Huber reweighting; :mod:`.score` discovery's score test
(:func:`score_blocks`); :mod:`.motion_models` how each sample's motion is
parametrised (any rigid motion, static poses on gravity).
"""

from imu_array_ros.fitting.engine import (
    GAUGE_ORDER,
    NOISE_SHARE,
    FitResult,
    ScoreBlocks,
    check_terms,
    fit_motion,
    fit_terms,
    score_blocks,
)
from imu_array_ros.fitting.motion_models import RigidMotion, StaticMotion

__all__ = ["FitResult", "ScoreBlocks", "fit_terms", "fit_motion", "score_blocks", "check_terms", "GAUGE_ORDER",
           "NOISE_SHARE", "RigidMotion", "StaticMotion"]
