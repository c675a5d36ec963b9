"""reduce_exposure's options object (ReduceOptions): the keyword form and the options form give the
same products; bad option values are refused, naming the option, when the object is built (before
any data are read); the other reduction option objects (RectifyOptions, ForwardOptions) likewise."""
import warnings

import astropy.units as u
import numpy as np
import pytest
from conftest import SMALL_EDGES, small_raw_ramps
from conftest import small_slicer_mapper

from slicersim.errors import ParameterError, SlicersimError
from slicersim.reduction.options import ForwardOptions, PixelNoise, ReduceOptions
from slicersim.reduction.rectify_checks import RectifyOptions
import h5py
from slicersim.reduction.spectra import propagate_variance

EDGES = np.linspace(9050.0, 9950.0, 13)      # 12 bins of 5 px on the small layout
NCOL = 24


@pytest.fixture(scope="module")
def small():
    return small_slicer_mapper()


@pytest.fixture(scope="module")
def raw(small, tmp_path_factory):
    """A short ramp of a point source + background on the small layout, and its PSF cube."""
    from slicersim.physics.psf import gaussian_psf_cells
    from slicersim.products.ramps import simulate
    lbda = 0.5 * (EDGES[1:] + EDGES[:-1])
    ny, nx = 58, NCOL
    sig = 1.2 + 0.6 * (lbda - lbda[0]) / (lbda[-1] - lbda[0])
    iy, ix = np.indices((ny, nx)).reshape(2, -1)
    psf = gaussian_psf_cells(sig, 0.8 * sig, (ny, nx), (1.3, -2.7), (iy, ix)).reshape(-1, ny, nx)
    cube = 1000.0 * psf + 0.4
    img = small.project_fields(lbda, EDGES, narrow=cube)
    path = tmp_path_factory.mktemp("raw") / "raw.h5"
    simulate(img, (6, 2, 0), seed=21, out=str(path), ron=5.0, dark=0.0, roic_glow=0.0)
    return str(path), psf


@pytest.mark.slow
def test_keyword_and_options_forms_give_the_same_products(small, raw, tmp_path):
    from slicersim.reduction.pipeline import reduce_exposure
    path, psf = raw
    kw = dict(mapper=small, lbda_edges=EDGES, ncol=NCOL, psf=psf, weights="data")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        a = reduce_exposure(path, out=str(tmp_path / "a.h5"), **kw)
        opts = ReduceOptions(**kw)
        b = reduce_exposure(path, opts, out=str(tmp_path / "b.h5"))
        # keywords replace fields of a given options object
        c = reduce_exposure(path, ReduceOptions(mapper=small, lbda_edges=EDGES, ncol=58, psf=psf), ncol=NCOL,
                            weights="data")
        # λ edges as an astropy Quantity in another length unit
        d = reduce_exposure(path, **dict(kw, lbda_edges=(EDGES / 10.0) * u.nm))
    # (nm → Å through astropy is exact to ~2e-16: the products agree to float precision)
    np.testing.assert_allclose(d["spectra"]["narrow"].flux, a["spectra"]["narrow"].flux, rtol=1e-9)
    np.testing.assert_allclose(d["cubes"]["narrow"].lbda_edges, EDGES, rtol=1e-15)
    for other in (b, c):
        np.testing.assert_array_equal(a["spectra"]["narrow"].flux, other["spectra"]["narrow"].flux)
        np.testing.assert_array_equal(a["spectra"]["narrow"].variance, other["spectra"]["narrow"].variance)
        np.testing.assert_array_equal(a["cubes"]["narrow"].flux, other["cubes"]["narrow"].flux)
        assert a["weights"] == other["weights"] == "data" and a["dark_kind"] == other["dark_kind"]
    assert a["path"].endswith("a.h5") and b["path"].endswith("b.h5")


@pytest.mark.parametrize("options, error, match", [
    (dict(field="all"), ParameterError, r"unknown field 'all'.*valid: 'narrow', 'wide', 'both'"),
    (dict(field="narow"), ParameterError, r"did you mean 'narrow'"),
    (dict(ncol=0), ParameterError, r"ncol must be an integer in \[1, 1024\]"),
    (dict(ncol=2.5), ParameterError, "ncol must be an integer"),
    (dict(rectify_method="lsqr"), ParameterError, r"unknown rectify_method 'lsqr' \(did you mean 'lsq'\?\)"),
    (dict(extraction="optimul"), ParameterError, r"unknown extraction .*did you mean 'optimal'"),
    (dict(extraction="gls", rectify_method="drizzle"), ParameterError, "extraction 'gls' needs an lsq cube"),
    (dict(weights="smooth"), ParameterError, "unknown weights 'smooth'"),
    (dict(weights="data", rectify_method="drizzle"), ParameterError, "weights apply to rectify_method 'lsq'"),
    (dict(position=(1.0, 2.0, 3.0)), ParameterError, "position must be"),
    (dict(position=(100.0, 0.0)), ParameterError, "position .* lies outside the field"),
    (dict(aperture=-1.0), ParameterError, r"aperture \[PSF σ\] must be"),
    (dict(background="no"), ParameterError, "background must be True or False"),
    (dict(propagate=1), ParameterError, "propagate must be True or False"),
    (dict(keep_information="yes"), ParameterError, "keep_information must be True or False"),
    (dict(ipc=True), ParameterError, "ipc must be None"),
    (dict(config=3), ParameterError, "config must be"),
    (dict(psf="gauss"), ParameterError, r"unknown psf 'gauss'"),
    (dict(dark=-1.0), ParameterError, r"dark \(dark rates\) must be finite, ≥ 0 and ≤ 1e\+06 e-/s, got -1"),
    (dict(dark="dark"), ParameterError, "dark must be 'auto', None"),
    (dict(lbda_edges=[1.0, 2.0] * u.s), ParameterError, r"lbda_edges must be wavelengths \[Å\]"),
    (dict(fit_options=[("gain", 1)]), ParameterError, "fit_options must be a dict"),
    (dict(fit_options={"weightng": "ols"}), ParameterError, r"unknown fit_ramps option 'weightng' \(did you mean "),
    (dict(fit_options={"weighting": "best"}), ParameterError, "unknown weighting 'best'"),
    (dict(fit_options={"gain": 0}), ParameterError, r"gain \[adu / electron\] must be in \[0.001, 1000\], got 0"),
])
def test_bad_options_are_refused_naming_the_option(options, error, match):
    with pytest.raises(error, match=match):
        ReduceOptions(**options)
    from slicersim.reduction.pipeline import reduce_exposure
    with pytest.raises(error, match=match):                    # refused before the (missing) file is read
        reduce_exposure("/nonexistent/raw.h5", **options)


def test_unknown_keyword_and_wrong_options_type():
    from slicersim.reduction.pipeline import reduce_exposure
    with pytest.raises(ParameterError, match=r"unknown reduce_exposure keyword 'ncols' \(did you mean 'ncol'\?\)"):
        reduce_exposure("/nonexistent/raw.h5", ncols=3)
    with pytest.raises(ParameterError, match="options must be a ReduceOptions"):
        reduce_exposure("/nonexistent/raw.h5", {"ncol": 3})
    opts = ReduceOptions(ncol=30, position=(1, 2))
    assert opts.ncol == 30 and opts.position == (1.0, 2.0)
    with pytest.raises(AttributeError):                      # frozen
        opts.ncol = 3
    assert ReduceOptions.defaults()["ncol"] == 58 and ReduceOptions.defaults()["dark"] == "auto"


def test_fit_options_renamed_keywords():
    """fit_options take the package's keyword names (ron, max_bytes) and the old ones (read_noise,
    memory_budget), passed under the name fit_ramps takes; both names at once are refused."""
    from slicersim.reduction.checks import check_fit_options
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        a = check_fit_options({"ron": 3.0})
        b = check_fit_options({"read_noise": 3.0})
    assert a == b and len(a) == 1 and list(a.values()) == [3.0]
    with pytest.raises(ParameterError, match="'ron'"):
        check_fit_options({"ron": 3.0, "read_noise": 3.0})
    with pytest.raises(ParameterError, match=r"ron \(read noise per frame\) \[electron\] must be in \[0, 10000\]"):
        check_fit_options({"ron": -1.0})


def test_rectify_and_forward_options():
    from slicersim.reduction.rectify import rectify
    assert RectifyOptions(ncol=30).ncol == 30 and RectifyOptions(oversample=[2, 1]).oversample == (2, 1)
    np.testing.assert_allclose(RectifyOptions(lbda_edges=[0.905, 0.995] * u.um).lbda_edges, [9050.0, 9950.0])
    for options, match in ((dict(field="wid"), r"unknown field 'wid' \(did you mean 'wide'\?\)"),
                           (dict(method="psf"), "unknown method 'psf'"),
                           (dict(ncol=0), "ncol must be an integer ≥ 1"),
                           (dict(oversample=(2.5, 1)), r"oversample\[0\] must be an integer"),
                           (dict(truncate=-1), "truncate"), (dict(max_bytes=0), "max_bytes"),
                           (dict(backend="cuda"), "unknown backend 'cuda'"),
                           (dict(weights_dtype="int8"), "weights_dtype must be float32 or float64")):
        with pytest.raises(ParameterError, match=match):
            RectifyOptions(**options)
        with pytest.raises(ParameterError, match=match):
            rectify(np.zeros((4, 4)), **options)
    with pytest.raises(ParameterError, match="unknown rectify keyword 'cols'"):
        rectify(np.zeros((4, 4)), cols=3)
    for options, match in ((dict(field="both"), "unknown field 'both'"),
                           (dict(position=(1.0,)), "position must be a pair"),
                           (dict(start=(np.nan, 0.0)), r"start\[0\] must be finite"),
                           (dict(cell_scale=(0.0, 1.0)), r"cell_scale\[0\] must be > 0"),
                           (dict(background=1), "background must be True or False")):
        with pytest.raises(ParameterError, match=match):
            ForwardOptions(**options)
    assert ForwardOptions(position=np.array([1, 2])).position == (1.0, 2.0)


def test_extract_forward_noise_keywords():
    """extract_forward's earlier keywords (var_rnoise, var_poisson, raw_rate, dark_rate) build its
    PixelNoise; mixing them with noise= or giving them partly is refused before any work."""
    from slicersim.reduction.forward_extraction import _forward_options
    z = np.zeros((2, 2))
    opts, noise = _forward_options(None, None, dict(var_rnoise=z, var_poisson=z, raw_rate=z, dark_rate=0.5,
                                                    field="wide"))
    assert opts.field == "wide" and isinstance(noise, PixelNoise) and noise.dark_rate == 0.5
    with pytest.raises(ParameterError, match="var_rnoise needs raw_rate"):
        _forward_options(None, None, dict(var_rnoise=z, var_poisson=z))
    with pytest.raises(ParameterError, match="not both"):
        _forward_options(None, PixelNoise(z, z, z), dict(var_rnoise=z))
    with pytest.raises(ParameterError, match="noise must be a PixelNoise"):
        _forward_options(None, {"var_rnoise": z}, {})
    # without var_rnoise the others were ignored silently (the data variance used)
    for partial in (dict(var_poisson=z), dict(raw_rate=z, dark_rate=0.5), dict(dark_rate=z)):
        with pytest.raises(ParameterError, match="need.* var_rnoise, var_poisson and raw_rate together"):
            _forward_options(None, None, dict(partial))
    assert _forward_options(None, None, dict(var_rnoise=None, dark_rate=None))[1] is None


def test_deconvolve_ipc_bad_kernel_is_a_parameter_error():
    from slicersim.reduction.ipc_correction import deconvolve_ipc
    img = np.ones((8, 8))
    with pytest.raises(ParameterError, match="kernel .* 3×3 array summing to 1"):
        deconvolve_ipc(img, img > 0, np.ones((3, 3)))
    with pytest.raises(ParameterError, match="kernel"):
        deconvolve_ipc(img, img > 0, np.ones((2, 2)) / 4)
    assert issubclass(ParameterError, SlicersimError) and issubclass(ParameterError, ValueError)


def test_deconvolve_ipc_fills_unusable_pixels_with_the_median_of_their_neighbours():
    """Unusable pixels enter the deconvolution as scipy's 3×3 median filter (edges repeated, unusable
    neighbours as 0) would give them, computed at those pixels only; they are 0 in the result."""
    from scipy import fft
    from scipy.ndimage import median_filter
    from slicersim.physics.ipc import ipc_kernel
    from slicersim.reduction.ipc_correction import deconvolve_ipc
    rng = np.random.default_rng(3)
    img = rng.normal(10, 2, (24, 40))
    usable = rng.random(img.shape) > 0.2
    usable[0, 0] = usable[-1, 5] = False                      # edges
    k = ipc_kernel(0.016, 0.002)
    zero = np.where(usable, img, 0.0)
    filled = np.where(usable, img, median_filter(zero, size=3, mode="nearest"))
    pad = np.roll(np.pad(k, ((0, 21), (0, 37))), (-1, -1), axis=(0, 1))
    expect = fft.irfft2(fft.rfft2(filled) / fft.rfft2(pad), s=img.shape)
    out = deconvolve_ipc(img, usable, k)
    np.testing.assert_allclose(out[usable], expect[usable], rtol=0, atol=1e-12)
    assert (out[~usable] == 0).all()


@pytest.mark.parametrize("rows", [1, 2, 3])
def test_deconvolve_ipc_of_one_or_two_rows(rows):
    """A row range of a ramp of some rows may be 1 or 2 rows high: the kernel wraps as in any image (the
    IPC of the result, periodic, is the input), instead of a broadcasting error."""
    from slicersim.physics.ipc import ipc_kernel
    from slicersim.reduction.ipc_correction import deconvolve_ipc
    k = ipc_kernel(0.016, 0.002)
    img = np.random.default_rng(4).normal(10, 2, (rows, 16))
    out = deconvolve_ipc(img, np.ones(img.shape, bool), k)
    back = sum(k[1 + dy, 1 + dx] * np.roll(out, (dy, dx), axis=(0, 1)) for dy in (-1, 0, 1) for dx in (-1, 0, 1))
    np.testing.assert_allclose(back, img, rtol=0, atol=1e-12)


def test_check_spectra_options_names_and_units():
    """check_spectra_options (reduce_file, reduce_dataset and the CLI check with it): an unknown option is
    refused with a "did you mean"; λ edges given as a Quantity are taken in Å."""
    from slicersim.reduction.checks import check_spectra_options
    with pytest.raises(ParameterError, match=r"unknown reduction option 'ncols' \(did you mean 'ncol'\?\)"):
        check_spectra_options(ncols=3)
    edges = check_spectra_options(lbda_edges=np.linspace(905.0, 995.0, 13) * u.nm)["lbda_edges"]
    np.testing.assert_allclose(edges, np.linspace(9050.0, 9950.0, 13), rtol=1e-15)


@pytest.mark.parametrize("key, value, match", [("GAIN", 1e-300, "keyword GAIN = 1e-300 is outside"),
                                               ("DARK", float("nan"), "keyword DARK = nan is not finite"),
                                               ("EFFECTS", "{oops", "keyword EFFECTS")])
def test_raw_keywords_out_of_range_are_refused_before_the_fit(small, raw, tmp_path, key, value, match):
    """Issue 26: reduce_exposure on a file (the Python API, no check_ramp_file before it) names
    the keyword; a gain given by the caller replaces the file's."""
    import shutil

    import h5py

    from slicersim.errors import RampFileError
    from slicersim.reduction.pipeline import reduce_exposure
    bad = tmp_path / "bad.h5"
    shutil.copy(raw[0], bad)
    with h5py.File(bad, "r+") as fh:
        fh.attrs[key] = value
    with pytest.raises(RampFileError, match=match):
        reduce_exposure(str(bad), mapper=small, lbda_edges=EDGES, ncol=NCOL)
    if key == "GAIN":
        from slicersim.reduction.pipeline import _plan
        plan = _plan(str(bad), ReduceOptions(mapper=small, lbda_edges=EDGES, ncol=NCOL, fit_options={"gain": 1.0}),
                     None, False)
        assert plan.raw_attrs["GAIN"] == 1e-300


EDGES_RAW = SMALL_EDGES                          # 12 bins on the small test layout


@pytest.fixture(scope="module")
def small_raw(tmp_path_factory):
    """Raw ramps of a point source in the narrow field of the small test layout (660 × 600)."""
    return small_raw_ramps(tmp_path_factory.mktemp("small") / "raw.h5")[:2]


def test_reduce_exposure_writes_the_truth_rate(small_raw, tmp_path):
    """Known item (b): reduce_exposure(out=..., fit_options={"with_truth": True}) dropped the truth
    (only reduce_file added it afterwards)."""
    from slicersim.reduction.pipeline import reduce_exposure
    path, mapper = small_raw
    out = tmp_path / "red.h5"
    res = reduce_exposure(path, mapper=mapper, lbda_edges=EDGES_RAW, ncol=NCOL, rectify_method="drizzle",
                          fit_options={"with_truth": True, "progress": False}, out=out)
    with h5py.File(out, "r") as fh:
        assert np.array_equal(fh["rates/TRUTH_RATE"][...], res["rates"].truth_rate)
    out2 = tmp_path / "red2.h5"
    reduce_exposure(path, mapper=mapper, lbda_edges=EDGES_RAW, ncol=NCOL, rectify_method="drizzle",
                    fit_options={"progress": False}, out=out2)
    with h5py.File(out2, "r") as fh:
        assert "TRUTH_RATE" not in fh["rates"]


@pytest.mark.slow
def test_reduce_exposure_propagates_the_sandwich_for_optimal_extraction(tmp_path):
    """reduce_exposure(weights="model", extraction="optimal"): the propagated variance is the
    sandwich with the ramp fit's variance (it was N⁻¹ of the model weights); with weights="data"
    (W = Σ⁻¹) there is nothing to correct."""
    from conftest import small_point_source

    from slicersim.products.ramps import simulate
    from slicersim.reduction.pipeline import reduce_exposure
    mapper, edges, psf, image = small_point_source()
    path = simulate(image, (8, 4, 0), seed=2, out=tmp_path / "r.h5", ron=5.0, dark=0.0, roic_glow=0.0, progress=False)
    opts = dict(mapper=mapper, lbda_edges=edges, ncol=NCOL, psf=psf, extraction="optimal")
    res = reduce_exposure(path, **opts)
    spec, cube, B = res["spectra"]["narrow"], res["cubes"]["narrow"], res["noise_information"]["narrow"]
    assert "sandwich" in spec.diagnostics["variance_model"]
    np.testing.assert_array_equal(spec.variance, propagate_variance(spec, cube, noise_information=B))
    assert not np.allclose(spec.variance, propagate_variance(spec, cube), rtol=1e-3)
    data = reduce_exposure(path, weights="data", **opts)
    assert data["noise_information"] == {} and "sandwich" not in data["spectra"]["narrow"].diagnostics["variance_model"]


@pytest.mark.parametrize("options, match", [
    (dict(aperture=2.0), "aperture applies to the 'optimal' and 'aperture' extractions"),
    (dict(aperture=2.0, extraction="gls"), "aperture applies"),
    (dict(propagate=False), "propagate applies"),
    (dict(propagate=True, rectify_method="drizzle"), "propagate applies"),
    (dict(propagate=False, rectify_method="drizzle", extraction="aperture"), "propagate applies"),
    (dict(cubes=False, extraction="gls"), "works on the cube"),
    (dict(cubes=False, rectify_method="drizzle", extraction="forward"), "rectify_method shapes the cube"),
    (dict(cubes=False, weights="model", extraction="forward"), "weights shape the cube"),
    (dict(cubes="yes"), "cubes"),
])
def test_options_that_would_do_nothing_are_refused(options, match):
    """Review finding: --aperture with the gls extraction (every cell is fitted) and --no-propagate with
    gls or drizzle did nothing, silently (the CLI refuses options that do not apply)."""
    from slicersim.reduction.checks import check_spectra_options
    with pytest.raises(ParameterError, match=match):
        check_spectra_options(**options)
    # where they apply they pass
    assert check_spectra_options(aperture=2.0, extraction="aperture")["aperture"] == 2.0
    assert check_spectra_options(aperture=2.0, rectify_method="drizzle")["aperture"] == 2.0    # optimal
    assert check_spectra_options(propagate=False, extraction="optimal")["propagate"] is False


def test_keep_information_without_cubes_is_refused():
    """Adversarial finding: cubes=False with keep_information=True (a cube option) was accepted and
    silently did nothing, while rectify_method and weights with cubes=False are refused."""
    from slicersim.reduction.options import ReduceOptions
    with pytest.raises(ParameterError, match="keep_information .* cubes=False"):
        ReduceOptions(cubes=False, keep_information=True)
    assert ReduceOptions(cubes=True, keep_information=True).resolved_cubes("forward")
    assert ReduceOptions(keep_information=True).resolved_cubes("forward")


@pytest.fixture(scope="module")
def small_exposure():
    from conftest import small_slicer_mapper
    return small_slicer_mapper()


@pytest.fixture
def no_ramp_fit(monkeypatch):
    """Fail loudly if reduce_exposure reads any data."""
    from slicersim.reduction import ramp_fit

    def boom(*a, **k):
        raise AssertionError("fit_ramps called: options must be refused before any data are read")
    monkeypatch.setattr(ramp_fit, "fit_ramps", boom)


@pytest.mark.parametrize("bad", [
    dict(extraction="bogus"),
    dict(extraction="optimal", aperture=-1.0),
    dict(extraction="optimal", psf=np.ones((12, 12, 58, NCOL))),      # a template: GLS only
    dict(psf=np.ones((5, 58, NCOL))),                                  # wrong nλ
    dict(psf=np.zeros((12, 58, NCOL))),                                # no PSF light at all
    dict(position=(1e9, 0.0)),
    dict(rectify_method="drizzle", weights="forward"),                 # drizzle has no weights
    dict(psf="bogus"),
])
def test_options_refused_before_any_data_are_read(small_exposure, no_ramp_fit, bad):
    """F1, F6: reduce_exposure checked extraction options only after the ramp fit and two
    rectifications (20–26 s on the small_exposure layout, minutes on the detector); drizzle silently ignored
    explicit weights."""
    from slicersim.errors import ParameterError
    from slicersim.reduction import pipeline
    with pytest.raises(ParameterError):
        pipeline.reduce_exposure("unused.h5", mapper=small_exposure, lbda_edges=EDGES, ncol=NCOL, **bad)


@pytest.mark.parametrize("weights", [np.array(["model", "forward"]), np.array(["forward"]), ("forward",)])
def test_array_weights_are_a_parameter_error(small_exposure, no_ramp_fit, weights):
    """F2: an array of weights gave NumPy's ambiguous-truth error or was accepted."""
    from slicersim.errors import ParameterError
    from slicersim.reduction import pipeline
    with pytest.raises(ParameterError, match="weights"):
        pipeline.reduce_exposure("unused.h5", mapper=small_exposure, lbda_edges=EDGES, ncol=NCOL, weights=weights)


@pytest.mark.slow
def test_reduced_file_records_the_weights(small_exposure, tmp_path):
    """F3: a reduced exposure did not say how its cubes were weighted, nor keep the pixel variance
    a template must be built with."""
    import h5py

    from slicersim.products.ramps import simulate
    from slicersim.reduction import pipeline
    from test_closed_loop import _scene
    lbda, cube, psf, F, B = _scene()
    img = small_exposure.project_fields(lbda, EDGES, narrow=cube * 20)
    raw = tmp_path / "raw.h5"
    simulate(img, (4, 2, 0), seed=1, out=str(raw), ron=5.0, dark=0.0, roic_glow=0.0)
    out = tmp_path / "red.h5"
    res = pipeline.reduce_exposure(str(raw), mapper=small_exposure, lbda_edges=EDGES, ncol=NCOL, psf=psf, out=str(out))
    with h5py.File(out) as f:
        assert f.attrs["WEIGHTS"] == "forward" and f.attrs["RECTIFY_METHOD"] == "lsq"
        np.testing.assert_allclose(f["rates/RECTIFY_VAR"][()], res["variance"].astype(np.float32))


@pytest.mark.parametrize("options, extraction, cubes", [
    ({}, "forward", False),                                   # the default: the spectrum needs no cube
    ({}, "gls", True),                                        # a cube extraction needs it
    ({}, "optimal", True),
    (dict(cubes=True), "forward", True),
    (dict(rectify_method="lsq"), "forward", True),            # a cube option asks for the cube
    (dict(rectify_method="drizzle"), "forward", True),
    (dict(weights="data"), "forward", True),
    (dict(keep_information=True), "forward", True),
    (dict(cubes=False), "forward", False),
])
def test_the_cube_is_made_when_the_extraction_needs_it_or_it_is_asked_for(options, extraction, cubes):
    """Issue 30: beside the forward extraction the lsq cube cost ~30 % of a full-detector reduction and
    played no part in the spectrum; it is made when asked (cubes=True, --cubes, or a cube option)."""
    from slicersim.reduction.options import ReduceOptions
    assert ReduceOptions(**options).resolved_cubes(extraction) is cubes
