"""Cube builder: signal, variance and noisy cubes (λ, y, x) computing only what the scene needs.

Photon cube (reference §2.9), ph/s per cell:

    C = LSF_λ[ F f2p P  +  H ]  +  LSF_λ[ B f2p s² + N_th ]
        point source     host       uniform (1-D spectrum, broadcast)

* point source: PSF(λ, y, x) × spectrum — no 2-D convolution;
* background and dispersed thermal light: one 1-D spectrum, LSF'd once and
  broadcast over the cells — no spatial work;
* host (extended): f2p × (host flux per cell ⊛ PSF(λ)), a 2-D convolution per
  wavelength (``slicersim.backends.convolution``).

Detector (§2.10–2.12), per ramp then × r ramps: electrons = C·QE,
signal = electrons·t_int·g [ADU] (NaN where saturated), variance from
``Simulation.cell_variance`` [ADU²] (+inf where saturated, and only there).
All physics comes from the :class:`~slicersim.simulation.Simulation` methods.

Backends: on OpenCL with the Rauscher07 variance (linear in the electron rate,
V = A + B e), LSF, QE, signal and variance of a chunk are one fused kernel
(:func:`slicersim.backends.cube.detector_block`) fed with small inputs: the
Gaussian PSF as its two erf factors (nλ × (ny + nx) values), or the Airy PSF
block, the spectrum G = F f2p, the host block if any, U, QE and the LSF taps;
the product cube G·P is never stored.  ``backend="numpy"`` and a non-linear variance
(Kubik16, through :class:`CellVarianceReadout`) run the kernel's NumPy twin, the one NumPy
cube path; the two agree to ~1e-15 of the peak.  The independent oracle of the tests
(``tests/cube_oracle.py``: the whole photon cube, scipy LSF, ``cell_variance``) agrees to 1e-12.

``switch_off`` (:mod:`slicersim.products.components`) drops scene components from the photon
cube and detector terms from the variance.  :func:`build_scene_cubes` returns the noise-free
components separately (their sum in ADU is the signal cube, to rounding).

The cube is built in wavelength chunks within a memory budget.  The LSF mixes
±h = int(4σ + ½) bins, so each chunk is computed on [i0 − h, i1 + h) (clipped
to the grid: the LSF reflects only at the true grid ends) and the halo is
dropped; a host is convolved in groups of :data:`HOST_PLANE_GROUP` planes aligned on the grid
(the batched FFT's rounding depends on the planes transformed together) and a user cube is
resampled plane by plane alike (:mod:`slicersim.sources.pixels`): the chunked cube equals the
unchunked one bit for bit, hosts included.  The noisy
realisation (:func:`slicersim.backends.noise.noisy_cube`) is keyed by the seed
and the voxel's flat index in the full cube, so it does not depend on the
chunking either.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from slicersim.backends.convolution import choose_convolution_method, convolve_cube
from slicersim.backends.cube import DetectorChunk, ReadoutConstants, detector_chunk
from slicersim.backends.precision import resolve_precision, storage_dtype
from slicersim.backends.noise import noisy_cube, seed_from
from slicersim.physics.lsf import lsf_weights
from slicersim.errors import ParameterError
from slicersim.physics.readout import cell_variance_coefficients
from slicersim.products.components import SCENE_COMPONENTS, check_switch_off
from slicersim.products.psf_profiles import PSF_PROFILES, get_psf_profile

__all__ = ["CubeResult", "build_cube", "build_scene_cubes", "scene_photon_rates", "readout_constants",
           "PSF_PROFILES", "PATH_POINT", "PATH_UNIFORM", "PATH_ABSENT", "PATH_OFF", "FUSED_KERNEL",
           "SCENE_CUBE_UNITS", "SceneCubes"]

PATH_POINT = "psf x spectrum (no 2-D convolution)"
PATH_UNIFORM = "uniform: no spatial work"
PATH_ABSENT = "absent: not in the scene"
PATH_OFF = "switched off"
#: units of :func:`build_scene_cubes`
SCENE_CUBE_UNITS = ("adu", "electron", "photon", "flambda")
#: unit aliases of :func:`build_scene_cubes` (slicersim 1.4.2's "default", "ph", "photons")
SCENE_CUBE_UNIT_ALIASES = {"default": "adu", "ph": "photon", "photons": "photon", "electrons": "electron",
                           "e-": "electron"}
#: slicersim 1.4.2's names of the scene cubes (``get_scene_cubes`` keys)
SCENE_CUBE_KEY_ALIASES = {"host_cube": "host", "thermal_cube": "thermal"}
#: λ planes of the host convolved together: groups start at multiples of this bin index whatever
#: the chunk, so every plane goes through the same arithmetic (chunked == unchunked bit for bit)
HOST_PLANE_GROUP = 64
#: a cube's progress bar appears only once the cube has taken this long [s] (long runs only)
PROGRESS_DELAY_S = 2.0
FUSED_KERNEL = "fused OpenCL kernel (LSF, QE, signal, variance)"
HOST_CONV_METHOD = "auto"
#: float64 temporaries per voxel of a chunk (PSF, point, LSF output, electrons, variance, signal, noise, host)
_TEMPORARIES_PER_VOXEL = 8
_NOISE_BYTES_PER_VOXEL = 160           # NumPy noise draw: ~20 float64 temporaries per voxel


@dataclass
class CubeResult:
    """Output of :func:`build_cube`; cubes are (nλ, ny, nx), summed over the ramps.

    signal [ADU] (NaN where saturated), variance [ADU²] (+inf where saturated, and only there),
    noisy [ADU] (None without seed; NaN where saturated), paths: component →
    computation path (and "precision": "double" or "single", of the kernels that ran), chunks: number of λ chunks; ``saturated``: bool cube (variance = +inf).
    """
    signal: np.ndarray
    variance: np.ndarray
    noisy: np.ndarray | None
    paths: dict
    chunks: int
    lbda: np.ndarray = field(repr=False, default=None)
    psf_profile: str = "gaussian"
    seed: int | None = None

    @cached_property
    def saturated(self):
        """Saturated voxels: exactly those with variance = +inf (NaN fluxes give NaN, not inf)."""
        return np.isposinf(self.variance)

    def __iter__(self):
        """Unpack like ``Simulation.get_cube``: (signal, variance[, noisy])."""
        return iter((self.signal, self.variance) if self.noisy is None
                    else (self.signal, self.variance, self.noisy))


class SceneCubes(dict):
    """The scene-component cubes, keyed by :data:`~slicersim.products.components.SCENE_COMPONENTS`;
    slicersim 1.4.2's keys (:data:`SCENE_CUBE_KEY_ALIASES`: ``host_cube``, ``thermal_cube``) read
    the same arrays (iteration and ``keys()`` give the canonical names only)."""

    def __getitem__(self, key):
        return super().__getitem__(SCENE_CUBE_KEY_ALIASES.get(key, key))

    def __contains__(self, key):
        return super().__contains__(SCENE_CUBE_KEY_ALIASES.get(key, key))

    def get(self, key, default=None):
        return super().get(SCENE_CUBE_KEY_ALIASES.get(key, key), default)

    def stack(self):
        """(4, nλ, ny, nx) array in the order of SCENE_COMPONENTS (1.4.2's ``as_dict=False``)."""
        return np.stack([self[name] for name in SCENE_COMPONENTS])


def lsf_halo(sim):
    """Half width h [bins] of the LSF: output bin i depends on input bins i − h … i + h."""
    return int(lsf_weights(sim.spectrograph.lsf_sigma)[0][-1])


def psf_block(sim, profile, lo, hi, shape=None, position=None, backend="auto", options=None, on_device=False,
              precision="auto"):
    """PSF fractions P[λ, y, x] for bins lo … hi − 1 of a registered profile (name or
    :class:`~slicersim.products.psf_profiles.PSFProfile`; shape/position default to the field's;
    ``options``: extra keywords of ``backends.psf.psf_cube``, e.g. {"grid": "reference"}).
    ``on_device``: leave a block computed by OpenCL on the device (``backends.psf.DevicePSF``)."""
    shape = sim.spectrograph.shape if shape is None else shape
    position = sim.position if position is None else position
    return get_psf_profile(profile).block(sim, lo, hi, shape, position, backend, options, on_device,
                                          precision=precision)


def host_kernel_shape(sim, profile):
    """Odd (ky, kx) of the PSF kernels convolving the host ((0, 0) is the central cell)."""
    return get_psf_profile(profile).kernel_shape(sim)


def host_photons_block(sim, profile, lo, hi, method="auto", backend="auto", psf_options=None, groups=None,
                       precision="auto"):
    """Host photons per cell before LSF, f2p · (F_host ⊛ PSF) [ph/s/cell], for bins lo … hi − 1.

    Needs ``host.flux_cube(lbda, shape, spatial_scale)`` → F_host [erg/s/cm²/Å per cell]
    (:class:`slicersim.sources.extended.Host`) and ``slicersim.backends.convolution.convolve_cube``.
    The convolution runs over whole groups of :data:`HOST_PLANE_GROUP` planes aligned on the grid
    (the batched FFT's rounding depends on the planes transformed together: so a plane is always
    convolved with the same ones, whatever ``lo`` / ``hi``).  ``groups``: a dict kept by the caller
    across consecutive blocks (the cube builder's chunks): convolved groups are reused from it,
    and groups ending before ``lo`` dropped.  ``precision``: of the PSF and convolution kernels.
    """
    host, spec = sim.scene.host, sim.spectrograph
    if not callable(getattr(host, "flux_cube", None)):
        raise NotImplementedError(f"host light needs a host with flux_cube(lbda, shape, spatial_scale) "
                                  f"(slicersim.sources.extended.Host); got {type(host).__module__}.{type(host).__name__}")
    g, nl = HOST_PLANE_GROUP, sim.lbda.size
    g0, g1 = lo - lo % g, min(nl, -(-hi // g) * g)
    groups = {} if groups is None else groups
    for start in [k for k in groups if k + g <= lo]:
        del groups[start]
    missing = [a for a in range(g0, g1, g) if a not in groups]
    if missing:
        m0, m1 = missing[0], min(nl, missing[-1] + g)
        kernels = psf_block(sim, profile, m0, m1, shape=host_kernel_shape(sim, profile), position=(0.0, 0.0),
                            backend=backend, options=psf_options, precision=precision)
        flux = np.asarray(host.flux_cube(sim.lbda[m0:m1], spec.shape, spec.spatial_scale), dtype=float)
        for a in missing:
            b = min(m1, a + g)
            part = flux[a - m0:b - m0]
            # convolve O(1) numbers (erg units are ~1e-17): scale by an exact power of two
            peak = float(np.max(np.abs(part))) if part.size else 0.0
            scale = np.ldexp(1.0, int(np.frexp(peak)[1])) if np.isfinite(peak) and peak > 0 else 1.0
            conv = convolve_cube(part / scale, kernels[a - m0:b - m0], method=method, backend=backend,
                                 precision=precision) * scale
            if part.size and part.min() >= 0:       # light ⊛ PSF ≥ 0: FFT round-off (~1e-17 of the peak) clipped
                np.maximum(conv, 0.0, out=conv)
            groups[a] = conv
        del flux, kernels
    blurred = np.concatenate([groups[a] for a in range(g0, g1, g)]) if g1 > g0 else \
        np.zeros((0,) + tuple(spec.shape))
    return sim.flambda_to_photon[lo:hi, None, None] * blurred[lo - g0:hi - g0]


def readout_constants(sim, nmd, nramps, off=frozenset()):
    """:class:`slicersim.backends.cube.ReadoutConstants` of a readout: Rauscher07 cell variance
    V = A + B e [ADU²] (:func:`slicersim.etc.readout_variance_coefficients`) and the saturation
    test of ``Simulation.cell_variance``; detector terms in ``off`` (frozenset) removed."""
    det = sim.detector
    dark = sim.effective_dark(off)
    var_a, var_b, _ = cell_variance_coefficients(nmd, det.tframe, sim.read_noise(off), dark, det.gain,
                                                 det.saturation, sim.detector_pixels_per_cell,
                                                 sim.conventions)
    tint = sim.get_times(nmd, nramps)["integration_time_per_ramp"]
    return ReadoutConstants(tint=float(tint), gain=det.gain, nramps=int(nramps), var_a=float(var_a),
                            var_b=float(var_b), pixels_per_cell=float(sim.detector_pixels_per_cell),
                            dark=float(dark), saturation=float(det.saturation))


def _linear_variance(sim):
    """True for the Rauscher07 variance, linear in the electron rate (V = A + B e)."""
    return sim.detector.variance_model.lower().startswith("rauscher")


def _use_fused_kernel(sim, backend):
    """The fused kernel serves the Rauscher07 (linear) variance on an OpenCL backend (``backend``
    as resolved with the precision: a device without fp64 runs it in single precision)."""
    return backend == "opencl" and _linear_variance(sim)


def _chunk_bins(nl, ny, nx, halo, max_bytes):
    per_bin = 8 * _TEMPORARIES_PER_VOXEL * ny * nx
    return int(min(nl, max(1, max_bytes // per_bin - 2 * halo)))


def _progress_bar(progress, nchunks):
    """tqdm bar of the chunks: ``progress=True`` shows it at once, None (default) only when stderr is
    a terminal (:func:`~slicersim.io.row_blocks.show_progress`) and for a long run (it appears after
    :data:`PROGRESS_DELAY_S` seconds; a short cube prints nothing), False never."""
    from slicersim.io.row_blocks import show_progress
    if not show_progress(progress) or nchunks < 2:
        return None
    from tqdm import tqdm
    return tqdm(total=nchunks, desc="cube", unit="chunk", leave=False,
                delay=0.0 if progress else PROGRESS_DELAY_S)


@dataclass(frozen=True)
class CellVarianceReadout:
    """Detector stage of the NumPy cube for any variance model (e.g. Kubik16, not linear in the
    electron rate): ``Simulation.cell_variance`` of readout ``nmd``, r = ``nramps`` ramps summed,
    integration time ``tint`` [s] per ramp, detector terms in ``off`` removed."""
    sim: object
    nmd: tuple
    nramps: int
    tint: float
    off: frozenset = frozenset()

    def signal_variance(self, electrons):
        """(signal [ADU] (NaN where saturated), variance [ADU²]) of r ramps for e [e-/s/cell]."""
        var1, sat = self.sim.cell_variance(electrons, self.nmd, self.off)              # ADU² per ramp
        signal = np.where(sat, np.nan, electrons * self.tint * self.sim.detector.gain) * self.nramps
        return signal, var1 * self.nramps


@dataclass
class _CubePlan:
    """What :func:`build_cube` computes, resolved once: readout, scene components, kernels, paths."""
    nmd: tuple
    nramps: int
    tint: float
    off: frozenset
    profile: object
    dtype: np.dtype
    seed: int | None
    backend: str                       # as asked ("auto", "opencl", "numpy"): PSF, host and noise hooks
    fused_backend: str                 # the cube kernel's, resolved with the precision
    precision: str
    noise_kw: dict
    has_point: bool
    has_host: bool
    host_method: str | None
    psf_options: dict | None
    paths: dict


def _check_uncovered(sim):
    """Warn when the point-source spectrum does not cover the grid (those bins are NaN)."""
    uncovered = np.isnan(sim.pointsource_flambda)
    if uncovered.any():
        ps = sim.scene.pointsource
        warnings.warn(f"the point-source spectrum covers {ps.lbda_in[0]:.0f}–{ps.lbda_in[-1]:.0f} Å only: "
                      f"{int(uncovered.sum())} of {uncovered.size} bins (and their LSF neighbours) are NaN "
                      "in the cube", RuntimeWarning, stacklevel=3)


def _component_paths(sim, plan):
    """Computation path of each scene component (and the precision of the arithmetic)."""
    scene = sim.scene
    paths = {"pointsource": PATH_POINT if plan.has_point else PATH_ABSENT,
             "background": PATH_UNIFORM if scene.background is not None else PATH_ABSENT,
             "thermal": PATH_UNIFORM,
             "host": f"2-D convolution ({plan.host_method})" if plan.has_host else PATH_ABSENT}
    if plan.has_point and plan.profile.name != "gaussian":
        paths["pointsource"] = f"{PATH_POINT}, {plan.profile.name} PSF"
    paths.update({name: PATH_OFF for name in SCENE_COMPONENTS if name in plan.off})
    paths["precision"] = "double"             # of the arithmetic; the kernels' below when they run
    if plan.seed is not None:
        paths["noise_precision"] = plan.noise_kw["precision"]
    return paths


def _plan_cube(sim, nmd, nramps, psf_profile, seed, backend, dtype, switch_off, precision, psf_options):
    """Check the arguments of :func:`build_cube` and resolve its readout, backends and paths
    (the noise draw's precision is refused now, e.g. "double" without fp64, not after the cube)."""
    off = check_switch_off(switch_off)
    noise_backend, noise_precision = (resolve_precision(precision, backend, "noise") if seed is not None
                                      else (None, None))
    fused_backend, precision = resolve_precision(precision, backend, "cube")
    profile = get_psf_profile(psf_profile)
    dtype = storage_dtype(dtype)
    times = sim.get_times(nmd, nramps)
    scene = sim.scene
    has_point = scene.pointsource is not None and "pointsource" not in off
    has_host = scene.host is not None and "host" not in off
    if has_point:
        _check_uncovered(sim)
    host_method = HOST_CONV_METHOD if has_host else None
    if host_method == "auto":
        host_method = choose_convolution_method(sim.spectrograph.shape, host_kernel_shape(sim, profile), backend)
    plan = _CubePlan(times["nmd"], times["nramps"], times["integration_time_per_ramp"], off, profile, dtype,
                     None if seed is None else seed_from(seed), backend, fused_backend, precision,
                     {"backend": noise_backend, "precision": noise_precision}, has_point, has_host, host_method,
                     psf_options, {})
    plan.paths.update(_component_paths(sim, plan))
    return plan


def _detector_readout(sim, plan, fused):
    """The detector stage: :class:`ReadoutConstants` (linear Rauscher07 variance: the fused kernel
    and its NumPy twin) or :class:`CellVarianceReadout` (any other model, NumPy)."""
    if fused or _linear_variance(sim):
        return readout_constants(sim, plan.nmd, plan.nramps, plan.off)
    return CellVarianceReadout(sim, plan.nmd, plan.nramps, float(plan.tint), plan.off)


def _draw_noise(plan, cube, bins, max_bytes):
    """Noisy planes i0 … i1 − 1 of ``cube`` = (signal, variance, noisy), keyed by the seed and the
    voxel's flat index in the full cube; drawn straight into ``noisy`` where its dtype allows."""
    signal, variance, noisy = cube
    (i0, i1), (ny, nx) = bins, signal.shape[1:]
    in_place = plan.dtype in ((np.float64, np.float32) if plan.noise_kw["precision"] == "single" else (np.float64,))
    drawn = noisy_cube(signal[i0:i1], variance[i0:i1], plan.seed,
                       max_bytes=max(max_bytes, _NOISE_BYTES_PER_VOXEL * ny * nx), first_index=i0 * ny * nx,
                       out=noisy[i0:i1] if in_place else None, **plan.noise_kw)
    if not in_place:
        noisy[i0:i1] = drawn


def _uniform_cube(sim, plan, uniform_ph, cube):
    """A scene without point source or host: one 1-D spectrum [ph/s/cell] broadcast over the field."""
    signal, variance, _ = cube
    electrons = uniform_ph * sim.qe
    var1, sat1 = sim.cell_variance(electrons, plan.nmd, plan.off)
    signal[...] = (np.where(sat1, np.nan, electrons * plan.tint * sim.detector.gain) * plan.nramps)[:, None, None]
    variance[...] = (var1 * plan.nramps)[:, None, None]
    plan.paths["detector"] = "1-D spectrum, broadcast"


def _chunk_inputs(sim, plan, spectra, bins, host_groups, fused):
    """:class:`~slicersim.backends.cube.DetectorChunk` of output bins ``bins`` = (i0, i1): the PSF
    (the kernel's form when ``fused``, else the full block) and host photons of the input bins
    lo … hi − 1 (the LSF halo, clipped to the grid)."""
    taps, flux_ph, uniform_ph = spectra
    (i0, i1), nl, halo = bins, sim.lbda.size, taps.size // 2
    lo, hi = max(0, i0 - halo), min(nl, i1 + halo)
    psf, host = None, None
    if plan.has_point:
        psf = (plan.profile.fused(sim, lo, hi, plan.backend, plan.psf_options, plan.precision) if fused else
               psf_block(sim, plan.profile, lo, hi, backend=plan.backend, options=plan.psf_options,
                         precision=plan.precision))
    if plan.has_host:
        host = host_photons_block(sim, plan.profile, lo, hi, plan.host_method, plan.backend, plan.psf_options,
                                  host_groups, plan.precision)
    return DetectorChunk(taps, flux_ph[lo:hi] if plan.has_point else None, uniform_ph[i0:i1], sim.qe[i0:i1],
                         (i0, i1), nl, lo, psf, host)


def _chunked_cube(sim, plan, uniform_ph, cube, max_bytes, progress):
    """Point source and host: λ chunks within ``max_bytes``, each through the fused kernel (OpenCL,
    linear variance) or its NumPy twin; → the number of chunks."""
    nl, (ny, nx) = sim.lbda.size, sim.spectrograph.shape
    taps = lsf_weights(sim.spectrograph.lsf_sigma)[1]
    flux_ph = sim.pointsource_flambda * sim.flambda_to_photon if plan.has_point else None    # ph/s
    step = _chunk_bins(nl, ny, nx, taps.size // 2, max_bytes)
    starts = range(0, nl, step)
    fused = _use_fused_kernel(sim, plan.fused_backend)
    readout = _detector_readout(sim, plan, fused)
    plan.paths["detector"] = FUSED_KERNEL if fused else "NumPy (LSF, QE, signal, variance)"
    plan.paths["precision"] = plan.precision     # of the kernels (fused, or the PSF and host convolution of
                                                 # the NumPy path, whose LSF, QE and variance are float64)
    bar = _progress_bar(progress, len(starts))
    host_groups = {}                    # convolved host planes shared by consecutive chunks
    try:
        for i0 in starts:
            i1 = min(nl, i0 + step)
            chunk = _chunk_inputs(sim, plan, (taps, flux_ph, uniform_ph), (i0, i1), host_groups, fused)
            detector_chunk(chunk, readout, out=(cube[0][i0:i1], cube[1][i0:i1]), dtype=plan.dtype,
                           backend="opencl" if fused else "numpy", precision=plan.precision)
            del chunk
            if plan.seed is not None:
                _draw_noise(plan, cube, (i0, i1), max_bytes)
            if bar is not None:
                bar.update(1)
    finally:
        if bar is not None:
            bar.close()
    return len(starts)


def build_cube(sim, nmd=None, nramps=None, psf_profile="gaussian", seed=None, max_bytes=300 * 2**20,
               progress=None, backend="auto", psf_options=None, dtype=np.float64, switch_off=None,
               precision="auto"):
    """Signal [ADU], variance [ADU²] and optional noisy cube of ``sim`` (all ramps summed).

    Parameters
    ----------
    sim : Simulation
    nmd, nramps : readout (n, m, d) and ramps (default: the simulation's)
    psf_profile : "gaussian" (erf-integrated, = Simulation.get_psf) or "airy" (slicersim.backends.psf)
    seed : None (no noisy cube), int in [0, 2⁶⁴) or numpy Generator
    max_bytes : working-memory budget of one λ chunk [bytes] (the three output cubes come on top)
    progress : None (a tqdm bar when stderr is a terminal, for long runs only: shown once the cube has
        taken :data:`PROGRESS_DELAY_S`), True (at once) or False
    backend : "auto" | "opencl" | "numpy".  OpenCL with the Rauscher07 variance: LSF, QE, signal,
        variance and saturation in one fused kernel (:mod:`slicersim.backends.cube`), else its NumPy
        twin (any variance model); also the backend of the noise draw and the Airy/host hooks
    psf_options : dict of extra ``compute_psf.psf_cube`` keywords for non-Gaussian profiles
        (e.g. {"grid": "reference", "oversampling": 3} for slicersim 1.0's Airy sampling)
    dtype : float64 (default) or float32 storage of the signal, variance and noisy cubes
        (computed in float64 either way; the noise is drawn from the stored values)
    switch_off : None, a name or names (:mod:`slicersim.products.components`): scene components
        leave signal and variance, detector terms (dark, roic_glow, thermal_dark, ron) the variance
    precision : "auto" (default), "double" or "single": of the PSF, host convolution and fused cube
        kernels (:mod:`slicersim.backends.precision`; single: ≤ 1e-5 of the signal peak against
        double, measured 2e-7 on the Lazuli Airy cube) and of the noise draw (product "noise": within
        1e-3 σ of the double draw, measured 8e-5 σ on the Lazuli cube).  "auto" is double on CPUs and
        GPUs with fast fp64 (results unchanged), single on devices without (fast) fp64.  The NumPy
        path stays double.  ``paths["precision"]`` records the cube kernels', ``paths["noise_precision"]``
        (with a seed) the noise draw's.
    """
    plan = _plan_cube(sim, nmd, nramps, psf_profile, seed, backend, dtype, switch_off, precision, psf_options)
    shape = (sim.lbda.size, *sim.spectrograph.shape)
    cube = (np.empty(shape, plan.dtype), np.empty(shape, plan.dtype),
            None if plan.seed is None else np.empty(shape, plan.dtype))
    background_ph, thermal_ph = sim.uniform_photons(plan.off)
    uniform_ph = sim.spectrograph.apply_lsf(background_ph + thermal_ph)              # ph/s/cell, (nλ,)
    if plan.has_point or plan.has_host:
        nchunks = _chunked_cube(sim, plan, uniform_ph, cube, max_bytes, progress)
    else:
        _uniform_cube(sim, plan, uniform_ph, cube)
        nchunks = 1
        if plan.seed is not None:
            _draw_noise(plan, cube, (0, shape[0]), max_bytes)
    return CubeResult(*cube, plan.paths, nchunks, sim.lbda.copy(), plan.profile.name, plan.seed)


def scene_photon_rates(sim, off=frozenset(), psf_profile="gaussian", backend="auto", psf_options=None):
    """LSF'd photon rate of each scene component [ph/s/cell]: ``pointsource`` and ``host``
    (nλ, ny, nx) cubes or None (absent or in ``off``), ``background`` and ``thermal`` (nλ,)
    spectra, uniform over the field (zeros when switched off)."""
    scene, lsf, nl = sim.scene, sim.spectrograph.apply_lsf, sim.lbda.size
    rates = dict.fromkeys(SCENE_COMPONENTS)
    if scene.pointsource is not None and "pointsource" not in off:
        flux_ph = sim.pointsource_flambda * sim.flambda_to_photon                       # ph/s
        psf = psf_block(sim, psf_profile, 0, nl, backend=backend, options=psf_options)   # may be cached
        rates["pointsource"] = lsf(flux_ph[:, None, None] * psf, axis=0)
        del psf
    if scene.host is not None and "host" not in off:
        rates["host"] = lsf(host_photons_block(sim, psf_profile, 0, nl, backend=backend,
                                               psf_options=psf_options), axis=0)
    background, thermal = sim.uniform_photons(off)
    rates["background"], rates["thermal"] = lsf(background), lsf(thermal)
    return rates


def build_scene_cubes(sim, unit="adu", nmd=None, nramps=None, per_ramp=False, psf_profile="gaussian",
                      switch_off=None, backend="auto", psf_options=None):
    """Noise-free (nλ, ny, nx) cube of each scene component (dict keyed by
    :data:`~slicersim.products.components.SCENE_COMPONENTS`; zeros when absent or switched off).

    ``unit``: ``"adu"`` = photons × QE × t_int × g [ADU] per ramp (``per_ramp``) or summed over
    the ramps; ``"electron"`` = photons × QE [e-/s/cell]; ``"photon"`` [ph/s/cell]; ``"flambda"`` =
    photons / f2p [erg/s/cm²/Å per cell] (1.4.2 aliases: :data:`SCENE_CUBE_UNIT_ALIASES`).  No
    saturation: these are expectations.  The dict (:class:`SceneCubes`) also answers to
    1.4.2's keys ``host_cube`` and ``thermal_cube``."""
    off = check_switch_off(switch_off)
    unit = unit.lower() if isinstance(unit, str) else unit
    unit = SCENE_CUBE_UNIT_ALIASES.get(unit, unit)
    if unit not in SCENE_CUBE_UNITS:
        raise ParameterError(f"unit must be one of {', '.join(SCENE_CUBE_UNITS)} (aliases: "
                             f"{', '.join(SCENE_CUBE_UNIT_ALIASES)}), got {unit!r}")
    times = sim.get_times(nmd, nramps)                      # validates the readout
    get_psf_profile(psf_profile)
    factor = np.ones_like(sim.lbda)                         # per λ: photons → unit
    if unit in ("adu", "electron"):
        factor = sim.qe.copy()
    if unit == "adu":
        factor *= times["integration_time_per_ramp"] * sim.detector.gain * (1 if per_ramp else times["nramps"])
    elif unit == "flambda":
        factor = 1.0 / sim.flambda_to_photon
    shape = (sim.lbda.size, *sim.spectrograph.shape)
    cubes = SceneCubes()
    for name, rate in scene_photon_rates(sim, off, psf_profile, backend, psf_options).items():
        if rate is None:
            cubes[name] = np.zeros(shape)
        elif rate.ndim == 1:
            cubes[name] = np.broadcast_to((rate * factor)[:, None, None], shape).copy()
        else:
            cubes[name] = rate * factor[:, None, None]
    return cubes
