"""Ocean surface heights by the Longuet-Higgins sum of harmonics (the paper's eq. 38-43).

The surface is a finite sum of travelling cosines,

    eta(x, y, t) = sum_i sum_j a_ij cos(omega_i t - k_i (x cos th_j + y sin th_j) + eps_ij)     (38)

with amplitudes ``a_ij = sqrt(2 S(omega_i) phi(th_j) d_omega d_th)`` (39), deep-water dispersion
``k = omega^2 / g`` (40), the Pierson-Moskowitz spectrum ``S`` (42) and the ITTC ``cos^2`` spreading
``phi`` (43) about the mean wind direction. Directions ``th`` are measured in the ``lab`` x-y plane
from +x towards +y; a component travels towards ``th``.

``[waves] dispersion = "capillary"`` replaces (40) by the gravity-capillary relation of deep
water, ``omega^2 = g k + (sigma / rho) k^3`` (surface tension ``sigma``, density ``rho``): waves
shorter than a few centimetres are held together by surface tension as much as by gravity, so a
spectrum cut well past the peak (``omega_max_rel`` > ~5 at light wind) has longer waves than
(40) gives them, and needs a coarser mesh. The two relations agree for ``k << sqrt(rho g / sigma)``
(about 370 rad/m, wavelengths well above 1.7 cm).

Physics is done in SI units; everything public on :class:`SeaSurface` is in millimetres
(positions, heights, wavelengths), radians and seconds, matching the ``lab`` frame.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from wai_core.config import WavesConfig
from wai_core.errors import WaiInputError
from wai_core.heightfield import Heightfield

Array = NDArray[np.float64]

G_M_S2 = 9.81
"""Gravitational acceleration, m/s^2."""

PM_ALPHA = 8.1e-3
"""Phillips constant of the P-M spectrum (eq. 42), dimensionless."""

PM_BETA = 0.74
"""Exponent coefficient of the P-M spectrum (eq. 42), dimensionless."""

# S ~ w^-5 exp(-B w^-4) with B = beta (g/U)^4: d ln S / dw = -5/w + 4B/w^5 = 0 gives
# w_p^4 = 4B/5, i.e. w_p = (4 beta / 5)^(1/4) g/U = 0.877 g/U.
PM_PEAK_FACTOR = (0.8 * PM_BETA) ** 0.25
"""``omega_p U / g`` at the P-M spectral peak, derived from ``dS/domega = 0`` (about 0.877)."""

SURFACE_TENSION_N_M = 0.074
"""Surface tension of sea water against air, N/m (0.0728 for pure water at 20 C, raised by the
salt by ~1.5 %; 0.074 is the usual round value for sea water at 20 C, 35 PSU)."""

SEA_WATER_DENSITY_KG_M3 = 1025.0
"""Density of sea water near the surface (35 PSU, ~15-20 C), kg/m^3."""

DISPERSIONS = ("gravity", "capillary")
"""Dispersion relations :func:`wavenumber_rad_m` knows (``[waves].dispersion``)."""

MM_PER_M = 1000.0

# Bytes allowed for one (points x components) work array; a few of these live at once, so the
# evaluators stay well under 200 MB whatever the number of points.
_BLOCK_BYTES = 32 * 2**20


def peak_frequency_rad_s(wind_speed_m_s: float) -> float:
    """Angular frequency of the P-M spectral peak, rad/s (``inf`` for calm water).

    Parameters
    ----------
    wind_speed_m_s : float
        Wind speed ``U`` at 19.5 m above the sea, m/s.
    """
    if wind_speed_m_s <= 0:
        return float("inf")
    return PM_PEAK_FACTOR * G_M_S2 / wind_speed_m_s


def wavenumber_rad_m(omega_rad_s: ArrayLike, dispersion: str = "gravity") -> Array:
    """Deep-water wave number of angular frequencies by a dispersion relation, rad/m.

    ``"gravity"``: ``k = omega^2 / g`` (eq. 40). ``"capillary"``: the positive root of
    ``(sigma / rho) k^3 + g k - omega^2 = 0`` (with :data:`SURFACE_TENSION_N_M` and
    :data:`SEA_WATER_DENSITY_KG_M3`), the only real one since the left side increases with
    ``k``. As a depressed cubic ``k^3 + p k - q = 0`` with ``p = rho g / sigma > 0`` and
    ``q = rho omega^2 / sigma``, its root is
    ``2 sqrt(p/3) sinh(asinh(3 q / (2 p) sqrt(3 / p)) / 3)`` (the hyperbolic form of Cardano's
    formula, free of the cancellation of its cube roots at small ``omega``).

    Parameters
    ----------
    omega_rad_s : array_like, any shape
        Angular frequencies, rad/s, >= 0.
    dispersion : {"gravity", "capillary"}

    Returns
    -------
    ndarray, same shape as ``omega_rad_s``
    """
    w = np.asarray(omega_rad_s, dtype=float)
    if dispersion == "gravity":
        return w**2 / G_M_S2
    if dispersion != "capillary":
        raise WaiInputError(
            f"[waves].dispersion must be one of {', '.join(DISPERSIONS)}, not {dispersion!r}"
        )
    p = SEA_WATER_DENSITY_KG_M3 * G_M_S2 / SURFACE_TENSION_N_M
    q = SEA_WATER_DENSITY_KG_M3 * w**2 / SURFACE_TENSION_N_M
    scale = 2.0 * np.sqrt(p / 3.0)
    return scale * np.sinh(np.arcsinh(1.5 * q / p * np.sqrt(3.0 / p)) / 3.0)


def pm_spectrum(omega_rad_s: ArrayLike, wind_speed_m_s: float) -> Array:
    """Pierson-Moskowitz frequency spectrum ``S(omega)`` (eq. 42), m^2 s / rad.

    Parameters
    ----------
    omega_rad_s : array_like, any shape
        Angular frequencies, rad/s. Non-positive values give 0 (the spectrum's limit).
    wind_speed_m_s : float
        Wind speed ``U`` at 19.5 m, m/s; 0 gives a spectrum that is zero everywhere.

    Returns
    -------
    ndarray, same shape as ``omega_rad_s``
    """
    w = np.asarray(omega_rad_s, dtype=float)
    s = np.zeros(w.shape)
    pos = w > 0
    if wind_speed_m_s <= 0 or not pos.any():
        return s
    wp = w[pos]
    # In logs, so tiny omega gives exp(-inf) = 0 rather than inf * 0.
    with np.errstate(divide="ignore", over="ignore"):
        log_s = (
            np.log(PM_ALPHA * G_M_S2**2)
            - 5.0 * np.log(wp)
            - PM_BETA * (G_M_S2 / (wind_speed_m_s * wp)) ** 4
        )
    s[pos] = np.exp(log_s)
    return s


def ittc_spreading(theta_rad: ArrayLike) -> Array:
    """ITTC directional spreading ``phi(theta) = (2/pi) cos^2(theta)`` (eq. 43), 1/rad.

    Parameters
    ----------
    theta_rad : array_like, any shape
        Angle from the mean wind direction, radians; wrapped to ``[-pi, pi)`` first, and zero
        where ``|theta| > pi/2`` (no energy travels against the wind).

    Returns
    -------
    ndarray, same shape as ``theta_rad``; integrates to 1 over ``[-pi/2, pi/2]``.
    """
    th = np.asarray(theta_rad, dtype=float)
    th = np.mod(th + np.pi, 2.0 * np.pi) - np.pi
    return np.where(np.abs(th) <= np.pi / 2, (2.0 / np.pi) * np.cos(th) ** 2, 0.0)


@dataclass(frozen=True, eq=False)
class SeaSurface:
    """A frozen Longuet-Higgins sea: ``M`` frequencies times ``N`` directions of harmonics.

    Attributes
    ----------
    amplitudes_mm : (M, N) ndarray
        ``a_ij``, mm.
    omega_rad_s : (M,) ndarray
        Angular frequencies ``omega_i``, rad/s.
    k_rad_per_mm : (M,) ndarray
        Wave numbers ``k_i``, rad/mm (``omega^2 / g`` for a sea from :func:`sea_surface`).
    directions_rad : (N,) ndarray
        Absolute travel directions ``theta_j`` in the ``lab`` x-y plane, from +x towards +y.
    phases : (M, N) ndarray
        Initial phases ``eps_ij``, radians.
    omega_band_rad_s : (float, float) or None
        The sampled frequency band, rad/s, when known; it fixes :attr:`shortest_wavelength_mm`
        independently of the random jitter of the samples.
    dispersion : {"gravity", "capillary"}
        The relation between ``omega`` and ``k`` (:func:`wavenumber_rad_m`) by which
        :attr:`shortest_wavelength_mm` follows from the band.
    """

    amplitudes_mm: Array
    omega_rad_s: Array
    k_rad_per_mm: Array
    directions_rad: Array
    phases: Array
    omega_band_rad_s: tuple[float, float] | None = None
    dispersion: str = "gravity"

    def __post_init__(self) -> None:
        names = ("amplitudes_mm", "omega_rad_s", "k_rad_per_mm", "directions_rad", "phases")
        arrays = {n: np.array(getattr(self, n), dtype=float) for n in names}
        m, n = arrays["omega_rad_s"].size, arrays["directions_rad"].size
        expected = {
            "amplitudes_mm": (m, n),
            "omega_rad_s": (m,),
            "k_rad_per_mm": (m,),
            "directions_rad": (n,),
            "phases": (m, n),
        }
        for name, arr in arrays.items():
            if arr.shape != expected[name]:
                raise WaiInputError(
                    f"waves: {name} must have shape {expected[name]}, not {arr.shape}"
                )
            if not np.all(np.isfinite(arr)):
                raise WaiInputError(f"waves: {name} holds NaN or inf")
            arr.flags.writeable = False  # the dataclass is frozen; so are its arrays
            object.__setattr__(self, name, arr)
        if np.any(arrays["amplitudes_mm"] < 0):
            raise WaiInputError("waves: amplitudes_mm must be non-negative")
        if self.dispersion not in DISPERSIONS:
            raise WaiInputError(
                f"[waves].dispersion must be one of {', '.join(DISPERSIONS)}, "
                f"not {self.dispersion!r}"
            )

    @property
    def n_components(self) -> int:
        """Number of harmonics ``M * N``."""
        return int(self.amplitudes_mm.size)

    @property
    def significant_wave_height_mm(self) -> float:
        """``Hs = 4 sqrt(m0)`` of the discrete spectrum, ``m0 = sum a^2 / 2``, mm."""
        return float(4.0 * np.sqrt(0.5 * np.sum(self.amplitudes_mm**2)))

    @property
    def shortest_wavelength_mm(self) -> float:
        """Wavelength ``2 pi / k(omega_max)`` of the fastest harmonic, mm; ``inf`` when calm.

        ``omega_max`` is the top of the sampled band when known, else the largest frequency
        that carries energy; ``k`` follows :attr:`dispersion` (``2 pi g / omega_max^2`` for
        gravity waves).
        """
        if self.omega_band_rad_s is not None:
            omega_max = float(self.omega_band_rad_s[1])
        else:
            live = np.any(self.amplitudes_mm > 0, axis=1)
            if not live.any():
                return float("inf")
            omega_max = float(np.max(self.omega_rad_s[live]))
        if self.dispersion == "gravity":
            return 2.0 * np.pi * G_M_S2 / omega_max**2 * MM_PER_M
        return 2.0 * np.pi / float(wavenumber_rad_m(omega_max, self.dispersion)) * MM_PER_M

    def height_mm(self, x_mm: ArrayLike, y_mm: ArrayLike, time_s: ArrayLike = 0.0) -> Array:
        """Surface elevation ``eta`` about the mean level at points and times, mm.

        Parameters
        ----------
        x_mm, y_mm : array_like
            Point coordinates in the ``lab`` frame, mm; broadcast together with ``time_s``.
        time_s : array_like
            Time, s (a scalar, or one time per point).

        Returns
        -------
        ndarray with the broadcast shape of the inputs
        """
        a, *_ = self.harmonics()
        return self._sum_harmonics(x_mm, y_mm, time_s, np.cos, a[:, None])[..., 0]

    def slopes(
        self, x_mm: ArrayLike, y_mm: ArrayLike, time_s: ArrayLike = 0.0
    ) -> tuple[Array, Array]:
        """Exact surface slopes ``(d eta/dx, d eta/dy)`` at points and times (dimensionless).

        Parameters are as for :meth:`height_mm`; each output has the broadcast input shape.
        """
        a, kx, ky, _, _ = self.harmonics()
        # d/dx of a cos(wt - kx x - ky y + eps) is a kx sin(...).
        out = self._sum_harmonics(x_mm, y_mm, time_s, np.sin, np.stack([a * kx, a * ky], axis=1))
        return out[..., 0], out[..., 1]

    def grid(
        self, x_mm: ArrayLike, y_mm: ArrayLike, time_s: float, mean_level_mm: float = 0.0
    ) -> Heightfield:
        """The surface ``z = mean_level_mm + eta`` sampled on a rectilinear grid.

        Uses the separability of plane waves, ``eta = Re(Ey diag(A) Ex^T)`` with
        ``Ey = exp(-i ky y)``, ``Ex = exp(-i kx x)`` and ``A = a exp(i (omega t + eps))``: one
        complex matrix product instead of a cosine per grid point and harmonic.

        Parameters
        ----------
        x_mm : (n,) array_like
            Strictly increasing x samples, mm.
        y_mm : (m,) array_like
            Strictly increasing y samples, mm.
        time_s : float
            Time, s.
        mean_level_mm : float
            Height of the still water in the ``lab`` frame, mm (``h0``).

        Returns
        -------
        Heightfield
            ``z`` of shape (m, n), mm.
        """
        x = np.asarray(x_mm, dtype=float).ravel()
        y = np.asarray(y_mm, dtype=float).ravel()
        return Heightfield(x, y, mean_level_mm + self._grid_eta(x, y, float(time_s)))

    def harmonics(self) -> tuple[Array, Array, Array, Array, Array]:
        """The harmonics that carry energy as flat arrays, each (C,): amplitudes ``a`` (mm),
        wave vectors ``kx``, ``ky`` (rad/mm), ``omega`` (rad/s) and phases ``eps`` (rad), so
        that ``eta = sum a cos(omega t - kx x - ky y + eps)``."""
        m, n = self.amplitudes_mm.shape
        k = np.broadcast_to(self.k_rad_per_mm[:, None], (m, n))
        kx = k * np.cos(self.directions_rad)
        ky = k * np.sin(self.directions_rad)
        omega = np.broadcast_to(self.omega_rad_s[:, None], (m, n))
        live = self.amplitudes_mm > 0
        return self.amplitudes_mm[live], kx[live], ky[live], omega[live], self.phases[live]

    def _sum_harmonics(
        self,
        x_mm: ArrayLike,
        y_mm: ArrayLike,
        time_s: ArrayLike,
        trig: Callable[..., Array],
        weights: Array,
    ) -> Array:
        """``trig(phase) @ weights`` at points, in blocks of points to bound memory.

        ``weights`` is (C, K); returns (..., K) over the broadcast point shape.
        """
        x, y, t = np.broadcast_arrays(*(np.asarray(v, dtype=float) for v in (x_mm, y_mm, time_s)))
        _, kx, ky, omega, eps = self.harmonics()
        # phase = omega t + eps - kx x - ky y, as one (P, 3) @ (3, C) product per block.
        pts = np.stack([x.ravel(), y.ravel(), t.ravel()], axis=1)
        coeffs = np.stack([-kx, -ky, omega])
        out = np.zeros((pts.shape[0], weights.shape[1]))
        step = max(1, _BLOCK_BYTES // (8 * max(eps.size, 1)))
        if eps.size:
            for start in range(0, pts.shape[0], step):
                phase = pts[start : start + step] @ coeffs
                phase += eps
                out[start : start + step] = trig(phase, out=phase) @ weights
        return out.reshape(x.shape + (weights.shape[1],))

    def _grid_eta(self, x: Array, y: Array, time_s: float) -> Array:
        """Elevation over ``y`` (m,) by ``x`` (n,), mm, shape (m, n), by blocked matrix products."""
        a, kx, ky, omega, eps = self.harmonics()
        amp = a * np.exp(1j * (omega * time_s + eps))
        eta = np.zeros((y.size, x.size))
        if not a.size:
            return eta
        step = max(1, _BLOCK_BYTES // (16 * a.size))
        # Re(P Q^T) = [Re P, -Im P] @ [Re Q, Im Q]^T: one real product of twice the depth, half
        # the arithmetic of the complex one.
        for j0 in range(0, y.size, step):
            ey_amp = _plane_wave_factors(y[j0 : j0 + step], ky) * amp
            left = np.concatenate([ey_amp.real, -ey_amp.imag], axis=1)
            for i0 in range(0, x.size, step):
                ex = _plane_wave_factors(x[i0 : i0 + step], kx)
                right = np.concatenate([ex.real, ex.imag], axis=1)
                eta[j0 : j0 + step, i0 : i0 + step] = left @ right.T
        return eta


def _plane_wave_factors(coords_mm: Array, k_rad_per_mm: Array) -> NDArray[np.complex128]:
    """``exp(-i coords k)`` for coordinates (n,) and wave numbers (C,), shape (n, C).

    Complex exponentials dominate the grid's cost. On an evenly spaced axis the phase splits into
    a coarse and a fine step, so only about ``2 sqrt(n)`` rows need them; the rest are products.
    """

    def direct(c: Array) -> NDArray[np.complex128]:
        return np.exp(-1j * np.outer(c, k_rad_per_mm))

    n = coords_mm.size
    if n < 16:
        return direct(coords_mm)
    step = (coords_mm[-1] - coords_mm[0]) / (n - 1)
    offsets = coords_mm - (coords_mm[0] + step * np.arange(n))
    # Take the split only where treating the axis as even moves no phase by more than 1e-12 rad.
    if np.max(np.abs(offsets)) * np.max(np.abs(k_rad_per_mm), initial=0.0) > 1e-12:
        return direct(coords_mm)
    b = int(np.ceil(np.sqrt(n)))
    coarse = direct(coords_mm[0] + step * np.arange(0, n, b))
    fine = direct(step * np.arange(b))
    return (coarse[:, None, :] * fine[None, :, :]).reshape(-1, k_rad_per_mm.size)[:n]


def _frequency_samples(
    omega_p: float, waves: WavesConfig, rng: np.random.Generator
) -> tuple[Array, float]:
    """Jittered frequencies (M,), rad/s, one uniformly placed inside each of M equal bins, and
    the bin width, rad/s. Jitter breaks the common period of equally spaced frequencies."""
    lo, hi = waves.omega_min_rel * omega_p, waves.omega_max_rel * omega_p
    d_omega = (hi - lo) / waves.n_frequencies
    edges = lo + d_omega * np.arange(waves.n_frequencies)
    return edges + d_omega * rng.uniform(0.0, 1.0, waves.n_frequencies), d_omega


def _direction_samples(n_directions: int) -> tuple[Array, Array]:
    """Bin midpoints (N,) over ``[-pi/2, pi/2]`` about the wind, rad, and their weights
    ``phi(theta_j) d_theta`` (N,), which sum to 1.

    For N >= 2 the midpoint rule integrates ``cos^2`` exactly, so the rescaling only matters for
    N = 1, where it keeps the continuous energy instead of doubling it.
    """
    d_theta = np.pi / n_directions
    theta = -np.pi / 2 + d_theta * (np.arange(n_directions) + 0.5)
    weights = ittc_spreading(theta) * d_theta
    return theta, weights / weights.sum()


def sea_surface(waves: WavesConfig) -> SeaSurface:
    """The sea described by a ``[waves]`` configuration (eq. 38-43).

    Frequencies: ``n_frequencies`` equal bins over ``[omega_min_rel, omega_max_rel] * omega_p``,
    one sample jittered uniformly inside each bin. Directions: ``n_directions`` bin midpoints over
    ``+-90 deg`` about ``wind_direction_deg``. Phases uniform in ``[0, 2 pi)``. All randomness comes
    from ``numpy.random.default_rng(seed)`` (frequency jitter first, then phases), so a seed fixes
    the surface. Wave numbers follow ``dispersion`` (:func:`wavenumber_rad_m`); the amplitudes,
    a frequency spectrum, do not depend on it; ``height_scale`` multiplies them. ``time_s`` of
    the config is not used: time is passed to the evaluators.

    Calm water (``wind_speed_m_s == 0``) gives all amplitudes, frequencies and wave numbers zero:
    a flat surface.

    Parameters
    ----------
    waves : WavesConfig

    Returns
    -------
    SeaSurface
        ``n_frequencies x n_directions`` harmonics.
    """
    if waves.wind_speed_m_s < 0 or waves.n_frequencies < 1 or waves.n_directions < 1:
        raise WaiInputError("waves: needs wind_speed_m_s >= 0 and at least one component")
    if not 0 < waves.omega_min_rel < waves.omega_max_rel:
        raise WaiInputError("waves: needs 0 < omega_min_rel < omega_max_rel")
    rng = np.random.default_rng(waves.seed)
    m, n = waves.n_frequencies, waves.n_directions
    theta_rel, dir_weights = _direction_samples(n)
    directions = np.deg2rad(waves.wind_direction_deg) + theta_rel
    omega_p = peak_frequency_rad_s(waves.wind_speed_m_s)
    if np.isinf(omega_p):
        rng.uniform(0.0, 1.0, m)  # same draws as a windy sea, so phases match across U
        zeros = np.zeros(m)
        phases = rng.uniform(0.0, 2.0 * np.pi, (m, n))
        return SeaSurface(np.zeros((m, n)), zeros, zeros, directions, phases)
    omega, d_omega = _frequency_samples(omega_p, waves, rng)
    phases = rng.uniform(0.0, 2.0 * np.pi, (m, n))
    # eq. 39 with the direction weights phi(theta_j) d_theta; metres -> mm.
    energy_m2 = 2.0 * pm_spectrum(omega, waves.wind_speed_m_s)[:, None] * d_omega * dir_weights
    band = (waves.omega_min_rel * omega_p, waves.omega_max_rel * omega_p)
    return SeaSurface(
        amplitudes_mm=np.sqrt(energy_m2) * MM_PER_M * float(waves.height_scale),
        omega_rad_s=omega,
        k_rad_per_mm=wavenumber_rad_m(omega, waves.dispersion) / MM_PER_M,
        directions_rad=directions,
        phases=phases,
        omega_band_rad_s=band,
        dispersion=waves.dispersion,
    )


def mesh_spacing_mm(
    surface: SeaSurface, points_per_wavelength: float, extent_mm: float = 660.0
) -> float:
    """Vertex spacing that resolves the shortest wave present, mm.

    Parameters
    ----------
    surface : SeaSurface
    points_per_wavelength : float
        Samples per shortest wavelength (``mesh_points_per_wavelength``), > 0.
    extent_mm : float
        Side of the modelled water patch, mm (default: the paper's 660 mm). Used only for calm
        water, which has no wavelength: a flat surface needs no resolution, so the spacing is
        ``extent_mm / 4``, the 5 samples a side that a :class:`Heightfield` accepts.

    Returns
    -------
    float
    """
    if points_per_wavelength <= 0:
        raise WaiInputError("waves: points_per_wavelength must be positive")
    wavelength = surface.shortest_wavelength_mm
    if not np.isfinite(wavelength):
        return extent_mm / 4.0
    return wavelength / points_per_wavelength
