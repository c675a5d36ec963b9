"""Cube builder (slicersim.cube.build_cube): physics, reference cubes, chunking, noise, paths.

Tolerances: against ``Simulation.get_cube`` 1e-12 of the peak (the builder
applies the LSF to the point-source and uniform parts separately, which only
changes the rounding, ~1e-16); against the slicersim 1.0.0 reference cubes
1e-6 of the peak (as tests/test_reference_cases.py; measured ~2e-8, set by the
reference's rounded h c).  Chunked and unchunked cubes must be bit-identical.
"""
import copy
import math

import numpy as np
import pytest
from scipy import stats

from conftest import reference_case_ids, reference_target
from cube_oracle import cube_numpy
from slicersim.backends.dispatch import resolve_backend
from slicersim.errors import ParameterError
from slicersim.products.cube import PATH_ABSENT, PATH_POINT, PATH_UNIFORM, build_cube, lsf_halo
from slicersim.errors import SpectrumError
from slicersim.sources.extended import Host
from slicersim.sources.scene import Scene
from slicersim.sources.spectra import PointSource
from slicersim.simulation import Simulation
from slicersim.targets import LazuliTarget

LBDA_IN = np.arange(3000.0, 20000.0, 10.0)
READOUT = {"nmd": (16, 8, 0), "nramps": 2}
BACKENDS = ["numpy", pytest.param("opencl", marks=pytest.mark.needs_opencl)]


def _target(mag=21.0, position=(0.0, 0.0), field="narrow"):
    flux = 1.0 + 0.3 * np.sin(LBDA_IN / 700.0)               # structured, positive spectrum
    return LazuliTarget(LBDA_IN, flux, mag=mag, band="bessellb", position=position, field=field)


@pytest.fixture(scope="module")
def sim():
    return _target(position=(1.3, -0.6)).simulation


@pytest.fixture(scope="module")
def narrow_band_sim():
    """9000–11000 Å only (47 bins): keeps the host integrations and convolutions fast."""
    sim = _target().simulation
    sim.update(spectral_range=(9000.0, 11000.0))
    return sim


@pytest.fixture(scope="module")
def cube(sim):
    return build_cube(sim, **READOUT, seed=2024, progress=False)


def _peak_err(got, ref):
    assert np.array_equal(np.isnan(got), np.isnan(ref))
    return np.nanmax(np.abs(got - ref)) / np.nanmax(np.abs(ref))


def test_equals_simulation_get_cube(sim, cube):
    signal, variance = cube_numpy(sim, **READOUT)
    assert cube.signal.shape == (sim.lbda.size, *sim.spectrograph.shape)
    assert _peak_err(cube.signal, signal) < 1e-12
    assert _peak_err(cube.variance, variance) < 1e-12
    assert np.array_equal(cube.lbda, sim.lbda)


@pytest.mark.parametrize("backend", BACKENDS)
def test_flux_conservation_and_ramps(sim, backend):
    """Σ_cells (signal − uniform level) = r·LSF[F f2p QE]·t_int·g (the true spectrum) to 1 %:
    the Gaussian PSF loses < 1e-6 outside the field; the LSF is applied before QE in the cube and
    after QE in the spectrum (reference §2.7), a small difference where QE varies."""
    cube = build_cube(sim, **READOUT, progress=False, backend=backend)
    uniform_level = cube.signal[:, 0, 0]                       # corner cell: PSF wing ≈ exp(−300)
    point_sum = (cube.signal - uniform_level[:, None, None]).sum(axis=(1, 2))
    _, true_signal, _ = sim.get_spectrum(**READOUT)
    inner = slice(10, -10)
    assert np.allclose(point_sum[inner], true_signal[inner], rtol=1e-2)
    one = build_cube(sim, nmd=READOUT["nmd"], nramps=1, progress=False, backend=backend)
    assert np.allclose(cube.signal, 2 * one.signal, rtol=1e-14)
    assert np.allclose(cube.variance, 2 * one.variance, rtol=1e-14)


def test_chunked_equals_unchunked(sim, cube, capsys, monkeypatch):
    import slicersim.products.cube as cube_module
    monkeypatch.setattr(cube_module, "PROGRESS_DELAY_S", 1e9)   # a "short" run, whatever the machine's speed
    ny, nx = sim.spectrograph.shape
    halo = lsf_halo(sim)
    assert halo == int(4 * sim.spectrograph.lsf_sigma + 0.5)
    for max_bytes, expected_chunks in ((1, sim.lbda.size), (8 * 8 * ny * nx * (7 + 2 * halo), None)):
        got = build_cube(sim, **READOUT, seed=2024, max_bytes=max_bytes, progress=None)
        if expected_chunks is None:                            # 7 bins per chunk + halo fit the budget
            expected_chunks = math.ceil(sim.lbda.size / 7)
        assert got.chunks == expected_chunks > 1
        assert np.array_equal(got.signal, cube.signal, equal_nan=True)
        assert np.array_equal(got.variance, cube.variance)
        assert np.array_equal(got.noisy, cube.noisy, equal_nan=True)
    assert cube.chunks == 1                                    # default budget: one chunk
    assert "cube" not in capsys.readouterr().err               # short runs: no bar (only after PROGRESS_DELAY_S)
    build_cube(sim, **READOUT, max_bytes=1, progress=True)
    assert "cube" in capsys.readouterr().err                   # progress=True: at once


def test_noisy_cube(sim, cube):
    again = build_cube(sim, **READOUT, seed=2024, progress=False)
    assert np.array_equal(again.noisy, cube.noisy)
    other = build_cube(sim, **READOUT, seed=2025, progress=False)
    assert np.count_nonzero(other.noisy != cube.noisy) > 0.999 * cube.noisy.size
    assert build_cube(sim, **READOUT, progress=False).noisy is None
    pull = ((cube.noisy - cube.signal) / np.sqrt(cube.variance)).ravel()
    n = pull.size
    assert abs(pull.mean()) < 4 / np.sqrt(n)
    assert abs(pull.var() - 1) < 4 * np.sqrt(2.0 / n)
    assert stats.kstest(pull[::7], "norm").pvalue > 1e-3
    assert len(tuple(cube)) == 3                              # unpacks like get_cube


def test_paths_reported(cube):
    assert cube.paths["pointsource"] == PATH_POINT == "psf x spectrum (no 2-D convolution)"
    assert "convolution" in cube.paths["pointsource"] and "no 2-D" in cube.paths["pointsource"]
    assert cube.paths["background"] == cube.paths["thermal"] == PATH_UNIFORM
    assert cube.paths["host"] == PATH_ABSENT


def test_uniform_scene_needs_no_spatial_work(sim):
    bare = Simulation(Scene(None, sim.scene.background, None), sim.telescope, sim.spectrograph, sim.detector)
    res = build_cube(bare, **READOUT, seed=1, max_bytes=1, progress=False)
    assert res.paths["pointsource"] == PATH_ABSENT and res.paths["background"] == PATH_UNIFORM
    assert res.chunks == 1
    assert np.all(res.signal == res.signal[:, :1, :1])         # flat over the field
    signal, variance = cube_numpy(bare, **READOUT)
    assert _peak_err(res.signal, signal) < 1e-12 and _peak_err(res.variance, variance) < 1e-12


def test_nan_only_where_saturated(sim, cube):
    assert not np.isnan(cube.signal).any() and np.isfinite(cube.variance).all() and not cube.saturated.any()
    bright = build_cube(_target(mag=11.0).simulation, **READOUT, seed=3, progress=False)
    sat = bright.saturated
    assert 0 < sat.sum() < sat.size / 100                       # only the PSF core saturates
    assert np.array_equal(np.isnan(bright.signal), sat) and np.array_equal(np.isinf(bright.variance), sat)
    assert np.array_equal(np.isnan(bright.noisy), sat)
    # invalid spectra never reach the cube
    with pytest.raises(SpectrumError):
        PointSource(LBDA_IN, np.where(LBDA_IN > 9000, np.nan, 1.0))
    with pytest.raises(SpectrumError):
        PointSource(LBDA_IN, -np.ones_like(LBDA_IN))


def test_host_is_convolved_and_conserves_flux(narrow_band_sim):
    """A Sersic host of total F = 1e-17 erg/s/cm²/Å: Σ_cells signal = (flux fraction in the field)
    · LSF[F f2p] QE t_int g, up to the PSF blur losing light over the field edges (< 2e-3)."""
    from slicersim.sources.extended import Host as SersicHost, SersicProfile
    sim = narrow_band_sim
    host = SersicHost(SersicProfile(1.0, 0.3), LBDA_IN, np.full(LBDA_IN.size, 1e-17))
    parts = {name: Simulation(Scene(None, None, h), sim.telescope, sim.spectrograph, sim.detector)
             for name, h in (("host", host), ("empty", None))}
    res = build_cube(parts["host"], nmd=(16, 8, 0), nramps=1, progress=False)
    assert res.paths["host"].startswith("2-D convolution (") and res.paths["pointsource"] == PATH_ABSENT
    empty = build_cube(parts["empty"], nmd=(16, 8, 0), nramps=1, progress=False)
    spec = sim.spectrograph
    tint = sim.get_times((16, 8, 0), 1)["integration_time_per_ramp"]
    expected = spec.apply_lsf(1e-17 * sim.flambda_to_photon) * sim.qe * tint * sim.detector.gain
    in_field = host.profile.cell_fractions(spec.shape, spec.spatial_scale).sum()
    ratio = ((res.signal - empty.signal).sum(axis=(1, 2)) / expected)[6:-6]
    assert np.all(ratio <= in_field * (1 + 1e-6)) and np.all(ratio > in_field - 2e-3)


class _BlobHost:
    """Minimal extended source for the host hook: a Gaussian blob (σ = 3 cells) × a flat 1e-17 spectrum."""

    def flux_cube(self, lbda, shape, spatial_scale):
        ny, nx = shape
        y, x = np.meshgrid(np.arange(ny) - ny / 2 + 0.5, np.arange(nx) - nx / 2 - 4.5, indexing="ij")
        blob = np.exp(-0.5 * (x**2 + y**2) / 9.0)
        return 1e-17 * np.ones(len(lbda))[:, None, None] * (blob / blob.sum())[None]


@pytest.mark.parametrize("backend", BACKENDS)
def test_host_chunking_and_device_twin(narrow_band_sim, backend):
    """Chunking does not change the host cube; the device convolution equals the NumPy twin; the
    host's flux (a 1e-17 flat spectrum, blob well inside the field) is conserved by the cube."""
    sim = narrow_band_sim
    blob = Simulation(Scene(None, None, _BlobHost()), sim.telescope, sim.spectrograph, sim.detector)
    ny, nx = sim.spectrograph.shape
    res = build_cube(blob, **READOUT, progress=False, backend=backend)
    chunked = build_cube(blob, **READOUT, progress=False, max_bytes=8 * 8 * ny * nx * 24, backend=backend)
    assert chunked.chunks > 1 and _peak_err(chunked.signal, res.signal) < 1e-13
    twin = build_cube(blob, **READOUT, progress=False, backend="numpy")
    assert _peak_err(res.signal, twin.signal) < 1e-12
    empty = build_cube(Simulation(Scene(None, None, None), sim.telescope, sim.spectrograph, sim.detector),
                       **READOUT, progress=False, backend="numpy")
    tint = sim.get_times(READOUT["nmd"], 1)["integration_time_per_ramp"]
    expected = sim.spectrograph.apply_lsf(1e-17 * sim.flambda_to_photon) * sim.qe * tint * sim.detector.gain \
        * READOUT["nramps"]
    ratio = ((res.signal - empty.signal).sum(axis=(1, 2)) / expected)[6:-6]
    assert np.allclose(ratio, 1.0, atol=1e-3)                  # σ = 3 cells blob + PSF: nothing leaves


def test_airy_profile_hook(sim, cube):
    airy = build_cube(sim, **READOUT, psf_profile="airy", progress=False)
    assert airy.paths["pointsource"].startswith(PATH_POINT) and "airy" in airy.paths["pointsource"]
    if resolve_backend("auto") == "opencl":          # the NumPy Airy cube takes ~4 s: once is enough
        ny, nx = sim.spectrograph.shape
        chunked = build_cube(sim, **READOUT, psf_profile="airy", progress=False,
                             max_bytes=8 * 8 * ny * nx * 100)
        # compute_psf batches wavelengths (BLAS contractions): chunking may change the last bits
        assert chunked.chunks > 1 and _peak_err(chunked.signal, airy.signal) < 1e-13
    # same photons, different spatial distribution: totals agree to the Airy wings lost outside the field
    ratio = airy.signal.sum(axis=(1, 2)) / cube.signal.sum(axis=(1, 2))
    assert np.all(np.abs(ratio - 1) < 0.03)


def test_options_and_hooks(sim):
    with pytest.raises(ValueError, match="psf_profile"):
        build_cube(sim, psf_profile="moffat")
    from slicersim.errors import ParameterError
    with pytest.raises(ParameterError, match="host must provide flux_cube"):
        Scene(sim.scene.pointsource, sim.scene.background, object())
    with pytest.raises(ValueError):
        build_cube(sim, nmd=(1, 8, 0))


# --------------------------------------------------------------------------- reference cubes
CASES = reference_case_ids()


def _reference_case(refdir, reference_case, case):
    meta, arr = reference_case(case)
    return meta, arr, reference_target(refdir, meta, arr)


def _check_reference_cube(meta, arr, res, prof):
    ref, idx = meta["cube"][prof], meta["cube"]["slice_indices"]
    assert res.signal.shape == tuple(ref["shape"])
    assert np.count_nonzero(~np.isfinite(res.signal)) == ref["n_nonfinite"]
    for got, name in ((res.signal.sum(axis=(1, 2)), f"cube_{prof}_signal_sum_adu"),
                      (res.variance.sum(axis=(1, 2)), f"cube_{prof}_variance_sum_adu2"),
                      (res.signal[idx], f"cube_{prof}_signal_slices_adu"),
                      (res.variance[idx], f"cube_{prof}_variance_slices_adu2")):
        assert _peak_err(got, arr[name]) < 1e-6, name
    assert res.signal.sum() == pytest.approx(ref["sum_signal_adu"], rel=1e-6)
    assert np.nanmax(res.signal) == pytest.approx(ref["max_signal_adu"], rel=1e-6)


@pytest.mark.reference
@pytest.mark.parametrize("case", CASES or ["none"])
def test_reference_gaussian_cube(refdir, reference_case, case):
    meta, arr, target = _reference_case(refdir, reference_case, case)
    readout = meta["cube"]["readout"]
    res = build_cube(target.simulation, nmd=tuple(readout["nmd"]), nramps=readout["nramps"], progress=False)
    _check_reference_cube(meta, arr, res, "default")


@pytest.mark.slow
@pytest.mark.reference
def test_reference_airy_cube_through_the_hook(refdir, reference_case):
    """psf_options reach compute_psf: its slicersim-1.0 sampling reproduces the reference Airy cube."""
    meta, arr, target = _reference_case(refdir, reference_case, "sn_z1.00_cbe_wide_snr20")
    readout = meta["cube"]["readout"]
    res = build_cube(target.simulation, nmd=tuple(readout["nmd"]), nramps=readout["nramps"], progress=False,
                     psf_profile="airy", psf_options={"grid": "reference"})
    _check_reference_cube(meta, arr, res, "airy")


# --------------------------------------------------------------------------- fused kernel (compute_cube)
# Tolerances: kernel vs NumPy twin 1e-13 of the peak (measured ~5e-16: summation order and FMA
# contraction only); chunked vs unchunked kernel output must be bit-identical.
from scipy.ndimage import correlate1d  # noqa: E402

from slicersim.backends.cube import (GaussianPSF, ReadoutConstants, default_vector_width,  # noqa: E402
                                    detector_block, reflect_indices)
from slicersim.products.cube import FUSED_KERNEL, readout_constants  # noqa: E402
from slicersim.physics.lsf import lsf_index_weights, lsf_weights  # noqa: E402
from slicersim.targets import LazuliSupernova
import slicersim.products.cube as cube_module

RO = ReadoutConstants(tint=181.1, gain=1.3, nramps=3, var_a=41.0, var_b=0.62, pixels_per_cell=2.0,
                      dark=0.011, saturation=3.0e5)


def _inputs(rng, nl=29, ny=7, nx=19, halo=4, e_peak=2.0e4):
    """Random block: odd sizes, photon rates reaching above saturation (RO: 2548 e-/s/cell)."""
    taps = rng.random(2 * halo + 1) + 0.2
    taps /= taps.sum()
    fy, fx = rng.random((nl, ny)), rng.random((nl, nx))
    rate = e_peak * (0.2 + rng.random(nl))
    return dict(taps=taps, rate=rate, uniform=rng.random(nl), qe=0.3 + 0.7 * rng.random(nl),
                fy=fy, fx=fx, full=0.5 * rng.random((nl, ny, nx)), host=50.0 * rng.random((nl, ny, nx)),
                gauss=GaussianPSF(0.3 + 0.4 * rng.random(nl), 0.3 + rng.random(nl), (1.0, -1.0), (ny, nx)))


def _run(d, psf_kind, with_host=False, bins=None, lo=0, backend="numpy", **kw):
    nl = d["rate"].size
    i0, i1 = bins or (0, nl)
    hi = min(nl, i1 + d["taps"].size // 2) if bins else nl
    sl = slice(lo, hi)
    psf = {"factors": lambda: (d["fy"][sl], d["fx"][sl]), "full": lambda: d["full"][sl], "none": lambda: None,
           "gauss": lambda: GaussianPSF(d["gauss"].sig_y[sl], d["gauss"].sig_x[sl], d["gauss"].position,
                                        d["gauss"].shape)}[psf_kind]()
    return detector_block(d["taps"], None if psf is None else d["rate"][sl], d["uniform"][i0:i1], d["qe"][i0:i1],
                          RO, bins=(i0, i1), nl=nl, lo=lo, psf=psf,
                          host=d["host"][sl] if with_host else None, backend=backend, **kw)


def test_twin_lsf_reflect_and_readout_physics():
    """NumPy twin against independent oracles: scipy's reflect LSF (also for a grid shorter than the
    LSF, several mirror images), the reflect indices of spectrograph.lsf_index_weights, signal =
    e t_int g r, variance = r (A + B e), saturation at e_sat, NaN (not inf) for a NaN flux."""
    rng = np.random.default_rng(7)
    for nl, halo in ((29, 3), (3, 4)):
        d = _inputs(rng, nl=nl, halo=halo)
        assert np.array_equal(reflect_indices((0, nl), nl, halo), lsf_index_weights(nl, halo / 4.0)[0])
        signal, variance = _run(d, "full")
        e = (correlate1d(d["rate"][:, None, None] * d["full"], d["taps"], axis=0, mode="reflect")
             + d["uniform"][:, None, None]) * d["qe"][:, None, None]
        sat = e > RO.saturation_rate
        assert 0 < sat.mean() < 0.9 and RO.saturation_rate == pytest.approx(
            2.0 * (3.0e5 / (181.1 * 1.3) - 0.011))
        assert np.array_equal(np.isnan(signal), sat) and np.array_equal(np.isposinf(variance), sat)
        ok = ~sat
        assert np.allclose(signal[ok], (e * 181.1 * 1.3 * 3)[ok], rtol=1e-14, atol=0)
        assert np.allclose(variance[ok], (3 * (41.0 + 0.62 * e))[ok], rtol=1e-14, atol=0)
    # a flat spectrum through a flat PSF block is unchanged by the (normalised, reflecting) LSF
    d = _inputs(rng)
    d["rate"][:] = 1.0
    d["full"][:] = d["full"][0]
    signal, _ = _run(d, "full")
    e = (d["full"][0] + d["uniform"][:, None, None]) * d["qe"][:, None, None]
    assert np.allclose(signal, e * RO.signal_scale, rtol=1e-14, equal_nan=True)
    d["rate"][5] = np.nan                                          # NaN flux: NaN, never "saturated"
    signal, variance = _run(d, "full")
    reach = np.unique(np.nonzero(reflect_indices((0, 29), 29, 4) == 5)[0])
    assert np.isnan(signal[reach]).all() and np.isnan(variance[reach]).all()
    assert not np.isinf(variance[reach]).any()


@pytest.mark.needs_opencl
@pytest.mark.parametrize("psf_kind,with_host", [("gauss", False), ("factors", False), ("full", False),
                                                 ("factors", True), ("none", True)])
def test_fused_kernel_matches_twin(psf_kind, with_host):
    rng = np.random.default_rng(11)
    d = _inputs(rng)
    twin = _run(d, psf_kind, with_host)
    widths = {default_vector_width()} | ({1, 2} if psf_kind == "factors" and not with_host else set())
    for vw in sorted(widths):              # nx = 19: partial last vector for vw > 1; vw = 1 as on GPUs
        signal, variance = _run(d, psf_kind, with_host, backend="opencl", vector_width=vw,
                                row_per_item=vw != 1)
        assert _peak_err(signal, twin[0]) < 1e-13
        assert np.array_equal(np.isposinf(variance), np.isposinf(twin[1]))
        assert np.isposinf(variance).any() == (psf_kind != "none")       # the host alone stays faint
        fin = np.isfinite(twin[1])
        assert np.max(np.abs(variance[fin] - twin[1][fin])) < 1e-13 * np.max(twin[1][fin])


@pytest.mark.needs_opencl
def test_fused_kernel_chunking_float32_and_checks():
    """Chunks with their LSF halos (grid ends included) are bit-identical to one launch; float32
    storage is the float64 result rounded; inputs that miss the halo are refused."""
    rng = np.random.default_rng(3)
    d = _inputs(rng, nl=31, halo=4)
    whole = _run(d, "gauss", backend="opencl")
    for i0, i1 in ((0, 5), (5, 17), (17, 26), (26, 31), (3, 4)):
        lo = max(0, i0 - 4)
        part = _run(d, "gauss", bins=(i0, i1), lo=lo, backend="opencl")
        assert np.array_equal(part[0], whole[0][i0:i1], equal_nan=True)
        assert np.array_equal(part[1], whole[1][i0:i1])
    single = _run(d, "gauss", backend="opencl", dtype=np.float32)
    assert single[0].dtype == np.float32
    assert np.array_equal(single[0], whole[0].astype(np.float32), equal_nan=True)
    assert np.array_equal(single[1], whole[1].astype(np.float32))
    with pytest.raises(ValueError, match="reaches"):
        _run(d, "gauss", bins=(10, 20), lo=7, backend="opencl")
    with pytest.raises(ValueError, match="odd"):
        detector_block(np.ones(4), None, [1.0], [1.0], RO, bins=(0, 1), nl=1, lo=0, host=np.ones((1, 2, 2)))


@pytest.mark.needs_opencl
def test_fused_kernel_airy_block(narrow_band_sim):
    """A real Airy PSF block (non-separable) through the kernel and its twin; build_cube's fused
    path against its NumPy path (1e-12: compute_psf's two backends differ by ~1e-14)."""
    from slicersim.products.cube import psf_block
    sim = narrow_band_sim
    nl, halo = sim.lbda.size, lsf_halo(sim)
    psf = psf_block(sim, "airy", 0, nl)
    taps = lsf_weights(sim.spectrograph.lsf_sigma)[1]
    args = (taps, sim.pointsource_flambda * sim.flambda_to_photon, np.zeros(nl), sim.qe,
            readout_constants(sim, (16, 8, 0), 2))
    kern = detector_block(*args, bins=(0, nl), nl=nl, lo=0, psf=psf, backend="opencl")
    twin = detector_block(*args, bins=(0, nl), nl=nl, lo=0, psf=psf, backend="numpy")
    assert _peak_err(kern[0], twin[0]) < 1e-13 and _peak_err(kern[1], twin[1]) < 1e-13
    assert halo == taps.size // 2
    fused = build_cube(sim, **READOUT, psf_profile="airy", progress=False)
    oracle = build_cube(sim, **READOUT, psf_profile="airy", progress=False, backend="numpy")
    assert fused.paths["detector"] == FUSED_KERNEL != oracle.paths["detector"]
    assert _peak_err(fused.signal, oracle.signal) < 1e-12 and _peak_err(fused.variance, oracle.variance) < 1e-12


@pytest.mark.needs_opencl
def test_fused_kernel_device_resident_psf(narrow_band_sim):
    """The Airy block left on the device (no host round trip) gives the same cube, bit for bit, as
    the host block, in the kernel and in its twin; the zero-copy outputs are the caller's arrays."""
    from slicersim.backends import opencl
    from slicersim.backends.psf import DevicePSF
    from slicersim.products.cube import psf_block
    sim = narrow_band_sim
    nl = sim.lbda.size
    host_psf = psf_block(sim, "airy", 0, nl)
    dev_psf = psf_block(sim, "airy", 0, nl, on_device=True)
    assert isinstance(dev_psf, DevicePSF) and np.array_equal(dev_psf.to_host(), host_psf)
    taps = lsf_weights(sim.spectrograph.lsf_sigma)[1]
    args = (taps, sim.pointsource_flambda * sim.flambda_to_photon, np.zeros(nl), sim.qe,
            readout_constants(sim, (16, 8, 0), 2))
    out = (np.full(host_psf.shape, -1.0), np.full(host_psf.shape, -1.0))
    got = detector_block(*args, bins=(0, nl), nl=nl, lo=0, psf=dev_psf, out=out, backend="opencl")
    assert got[0] is out[0] and got[1] is out[1]
    ref = detector_block(*args, bins=(0, nl), nl=nl, lo=0, psf=host_psf, backend="opencl")
    assert np.array_equal(out[0], ref[0], equal_nan=True) and np.array_equal(out[1], ref[1])
    assert np.all(out[1] > 0)                                  # every voxel written (variance > 0)
    twin = detector_block(*args, bins=(0, nl), nl=nl, lo=0, psf=dev_psf, backend="numpy")
    assert _peak_err(twin[0], ref[0]) < 1e-13
    with pytest.raises(ValueError, match="contiguous"):
        opencl.host_buffer(np.zeros((4, 6))[:, ::2])


def test_paths_kubik_and_float32(sim, cube):
    """Kubik16 (non-linear variance) keeps the NumPy path; float32 storage rounds the float64 cube."""
    assert cube.paths["detector"] == (FUSED_KERNEL if resolve_backend("auto") == "opencl"
                                      else "NumPy (LSF, QE, signal, variance)")
    detector = copy.deepcopy(sim.detector)
    detector.update(variance_model="Kubik16")
    kubik = Simulation(sim.scene, sim.telescope, sim.spectrograph, detector)
    res = build_cube(kubik, **READOUT, progress=False)
    assert res.paths["detector"].startswith("NumPy")
    signal, variance = cube_numpy(kubik, **READOUT)
    assert _peak_err(res.signal, signal) < 1e-12 and _peak_err(res.variance, variance) < 1e-12
    assert _peak_err(res.variance, cube.variance) > 1e-3                  # a different variance model
    single = build_cube(sim, **READOUT, progress=False, dtype=np.float32, seed=2024)
    assert single.signal.dtype == single.variance.dtype == single.noisy.dtype == np.float32
    assert np.allclose(single.signal, cube.signal, rtol=1e-7, atol=0)
    assert np.allclose(single.variance, cube.variance, rtol=1e-7, atol=0)
    with pytest.raises(ParameterError, match="dtype"):
        build_cube(sim, dtype=np.int32)
    with pytest.raises(ParameterError, match="dtype"):
        build_cube(sim, dtype="not a dtype")


def test_gaussian_factors_bit_identical_to_psf_module():
    """GaussianPSF.factors skips erf where |z| ≥ 6 (erf = ±1 exactly): P = fy fx must equal
    slicersim.physics.psf.gaussian_psf_fractions bit for bit, and hold the flux inside the field."""
    from slicersim.physics.psf import gaussian_psf_fractions
    rng = np.random.default_rng(5)
    sig_y, sig_x = 0.05 + 3 * rng.random(40), 0.05 + 3 * rng.random(40)
    for shape, position in (((58, 116), (0.0, 0.0)), ((7, 19), (1.37, -2.6)), ((9, 4), (30.0, 0.2))):
        fy, fx = GaussianPSF(sig_y, sig_x, position, shape).factors()
        assert np.array_equal(fy[:, :, None] * fx[:, None, :], gaussian_psf_fractions(sig_y, sig_x, shape, position))
    fy, fx = GaussianPSF(sig_y, sig_x, (0.0, 0.0), (58, 116)).factors()
    assert np.allclose(fy.sum(1) * fx.sum(1), 1.0, atol=1e-12)        # σ ≤ 3 cells: nothing lost


def test_zero_and_partial_spectra():
    """A zero spectrum gives the source-free cube (no NaN); a partial one warns about its NaN bins."""
    zero = LazuliTarget(LBDA_IN, np.zeros_like(LBDA_IN)).simulation
    none = LazuliTarget(LBDA_IN, np.zeros_like(LBDA_IN)).simulation
    none.scene.pointsource = None
    none._cache.clear()
    a = build_cube(zero, **READOUT, progress=False)
    b = build_cube(none, **READOUT, progress=False)
    assert np.isfinite(a.signal).all() and np.array_equal(a.signal, b.signal)
    part = LazuliTarget(LBDA_IN[LBDA_IN < 12000], np.ones(np.count_nonzero(LBDA_IN < 12000)) * 1e-17)
    with pytest.warns(RuntimeWarning, match="NaN"):
        res = build_cube(part.simulation, **READOUT, progress=False)
    assert np.isnan(res.signal[-1]).all() and np.isfinite(res.signal[0]).all()


def test_one_numpy_cube_path(sim, monkeypatch):
    """build_cube's NumPy backend (linear Rauscher07 variance) and any non-linear variance model (Kubik16, on
    every backend) run the fused kernel's NumPy twin: there is one NumPy cube path, whose detector stage is
    ReadoutConstants (the kernel's) or CellVarianceReadout (Simulation.cell_variance)."""
    import slicersim.backends.cube as backend_cube
    from slicersim.products.cube import CellVarianceReadout
    seen = []
    twin = backend_cube._detector_block_numpy
    monkeypatch.setattr(backend_cube, "_detector_block_numpy",
                        lambda chunk, kind, readout, out: seen.append(type(readout)) or twin(chunk, kind, readout, out))
    build_cube(sim, **READOUT, progress=False, backend="numpy")
    detector = copy.deepcopy(sim.detector)
    detector.update(variance_model="Kubik16")
    build_cube(Simulation(sim.scene, sim.telescope, sim.spectrograph, detector), **READOUT, progress=False)
    assert seen == [backend_cube.ReadoutConstants, CellVarianceReadout]


def test_get_cube_seed_is_recorded_and_generator_deprecated(narrow_band_sim):
    """seed: an int in [0, 2**64) or None (noiseless pair); the seed is recorded on the result
    (CubeTuple.seed); a numpy Generator still works for one release, with a DeprecationWarning,
    and the integer drawn from it is recorded so the draw can be repeated."""
    from slicersim.errors import ParameterError
    sim = narrow_band_sim
    plain = sim.get_cube(nmd=(4, 1, 0), backend="numpy")
    assert len(plain) == 2 and plain.seed is None
    noisy = sim.get_cube(nmd=(4, 1, 0), seed=7, backend="numpy")
    assert len(noisy) == 3 and noisy.seed == 7
    with pytest.warns(DeprecationWarning, match="seed"):
        drawn = sim.get_cube(nmd=(4, 1, 0), seed=np.random.default_rng(3), backend="numpy")
    assert isinstance(drawn.seed, int)
    again = sim.get_cube(nmd=(4, 1, 0), seed=drawn.seed, backend="numpy")
    np.testing.assert_array_equal(again[2], drawn[2])
    for bad in (1.5, -1, "3", True):
        with pytest.raises(ParameterError, match="seed"):
            sim.get_cube(nmd=(4, 1, 0), seed=bad, backend="numpy")


@pytest.fixture(scope="module")
def sn_host():
    return LazuliSupernova(0.5, host="sersic")


def test_host_cubes_bit_identical_across_chunkings_no_bar_for_short_runs(sn_host, capfd, monkeypatch):
    monkeypatch.setattr(cube_module, "PROGRESS_DELAY_S", 1e9)        # a "short" run on any machine
    full = cube_module.build_cube(sn_host.simulation, progress=False)
    chunked = cube_module.build_cube(sn_host.simulation, max_bytes=2 * 10**7)   # 15 chunks, progress=None
    assert chunked.chunks > 4
    assert "cube" not in capfd.readouterr().err
    assert np.array_equal(chunked.signal, full.signal, equal_nan=True)
    assert np.array_equal(chunked.variance, full.variance)
