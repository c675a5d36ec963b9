"""slicersim.validation: each checker converts what it accepts and refuses the rest with a
SlicersimError subclass whose message names the parameter."""
import math
import os
import warnings

import numpy as np
import pytest

from slicersim import validation as V
from slicersim.errors import EffectsError, ParameterError, ReadoutError, SlicersimError


def test_number_accepts_reals_and_quantities():
    assert V.number("gain", 2) == 2.0 and isinstance(V.number("gain", np.float32(1.5)), float)
    assert V.number("x", np.array(3.0)) == 3.0
    u = pytest.importorskip("astropy.units")
    assert V.number("tframe", 2830 * u.ms, unit="s") == pytest.approx(2.83)
    with pytest.raises(ParameterError, match=r"tframe must be in units convertible to s, got 3.0 m"):
        V.number("tframe", 3 * u.m, unit="s")
    with pytest.raises(ParameterError, match="gain is a plain number"):
        V.number("gain", 3 * u.m)


@pytest.mark.parametrize("bad", [True, "3", None, [1.0], np.array([1.0, 2.0]), math.nan, math.inf, 1 + 2j])
def test_number_refuses_non_numbers(bad):
    with pytest.raises(ParameterError, match="dark"):
        V.number("dark", bad)


def test_number_bounds_open_and_closed():
    assert V.number("f", 0.0, low=0.0) == 0.0
    with pytest.raises(ParameterError, match=r"gain must be > 0, got 0"):
        V.number("gain", 0, low=0.0, low_open=True)
    with pytest.raises(ParameterError, match=r"in \[0, 1\]"):
        V.number("f", 1.5, low=0, high=1)
    with pytest.raises(EffectsError, match="rate"):
        V.number("rate", -1, low=0, error=EffectsError)


def test_integer_refuses_fractions_instead_of_truncating():
    assert V.integer("n", 3.0) == 3 and V.integer("n", np.int16(4)) == 4
    for bad in (2.7, "2", True, math.nan, None):
        with pytest.raises(ParameterError, match="n must be an integer"):
            V.integer("n", bad)
    with pytest.raises(ParameterError, match=r"workers must be an integer ≥ 1, got 0"):
        V.positive_int("workers", 0)


def test_readout_refuses_non_integer_groups_and_bounds_frames():
    assert V.readout((16, 8, 0)) == (16, 8, 0)
    assert V.readout(np.array([4.0, 1.0, 2.0])) == (4, 1, 2)
    with pytest.raises(ReadoutError, match=r"nmd\[0\] \(n, groups per ramp\) must be an integer.*2\.7"):
        V.readout((2.7, 1, 0))
    with pytest.raises(ReadoutError, match=r"nmd\[2\]"):
        V.readout((4, 1, 1e9))
    with pytest.raises(ReadoutError, match=r"≤ 10|in \[2, 10\]"):
        V.readout((11, 1, 0), max_group=10)
    with pytest.raises(ReadoutError, match="frames per ramp"):
        V.readout((4000, 16, 16))
    for bad in ("16,8,0", (16, 8), None, 5):
        with pytest.raises(ReadoutError, match="nmd must be a triple"):
            V.readout(bad)


def test_seed_types_and_generator_deprecation():
    assert V.seed(None) is None and V.seed(np.uint64(2**64 - 1)) == 2**64 - 1
    for bad in (1.5, "1", True, -1, 2**64):
        with pytest.raises(ParameterError, match="seed"):
            V.seed(bad)
    with pytest.raises(ParameterError, match="seed must be an integer"):
        V.seed(None, allow_none=False)
    with pytest.warns(DeprecationWarning, match="Generator is deprecated"):
        s = V.seed(np.random.default_rng(3))
    assert s == np.random.default_rng(3).integers(0, 2**63)
    draws = {V.new_seed() for _ in range(8)}
    assert len(draws) == 8 and all(0 <= s < 2**63 for s in draws)


def test_choice_lists_valid_names_and_suggests():
    assert V.choice("backend", "numpy", ("auto", "numpy", "opencl")) == "numpy"
    with pytest.raises(ParameterError, match=r"unknown backend 'numpi' \(did you mean 'numpy'\?\); "
                                             r"valid: 'auto', 'numpy', 'opencl'"):
        V.choice("backend", "numpi", ("auto", "numpy", "opencl"))
    with pytest.raises(ParameterError, match=r"did you mean 'silver'"):
        V.choice("noptics key", "Silver", ("silver", "gold"))
    with pytest.raises(ParameterError, match=r"unknown backend \[1\]; valid"):
        V.choice("backend", [1], ("numpy",))


def test_short_repr_summarises_arrays_and_long_values():
    assert V.short_repr(np.zeros((300, 2))) == "an array of shape (300, 2) and dtype float64"
    long = V.short_repr("x" * 500)
    assert len(long) == 60 and long.endswith("…")
    with pytest.raises(ParameterError) as err:
        V.number("qe", np.linspace(0, 1, 1000))
    assert len(str(err.value)) < 120 and "shape (1000,)" in str(err.value)


def test_array_refuses_complex_structured_and_nonfinite():
    assert V.array("rate", [[1, 2], [3, 4]], ndim=2).dtype == np.float64
    for bad, pattern in ((np.zeros(3, complex), "real numbers"), (np.zeros(3, [("a", "f8")]), "real numbers"),
                         (np.array(["a"]), "real numbers"), (np.array([1.0, np.nan]), "1 non-finite"),
                         (np.zeros((2, 2, 2)), "dimension")):
        with pytest.raises(ParameterError, match=f"rate.*{pattern}|rate must have"):
            V.array("rate", bad, ndim=2 if pattern == "dimension" else None)
    with pytest.raises(ParameterError, match="rate must be ≥ 0"):
        V.array("rate", [-1.0, 2.0], low=0)


def test_regular_file_refuses_directories_fifos_and_missing(tmp_path):
    f = tmp_path / "a.npy"
    f.write_bytes(b"12345")
    assert V.regular_file("rate", f) == str(f)
    with pytest.raises(ParameterError, match="is a directory"):
        V.regular_file("rate", tmp_path)
    with pytest.raises(ParameterError, match="No such file"):
        V.regular_file("rate", tmp_path / "missing")
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    with pytest.raises(ParameterError, match="not a regular file"):
        V.regular_file("rate", fifo)
    with pytest.raises(ParameterError, match="more than the 4"):
        V.regular_file("rate", f, max_bytes=4)


def test_renamed_keyword_warns_and_refuses_both():
    kw = {"memory_budget": 10}
    with pytest.warns(DeprecationWarning, match="'memory_budget' is deprecated, use 'max_bytes'"):
        V.renamed_keyword(kw, "memory_budget", "max_bytes", "fit_ramps")
    assert kw == {"max_bytes": 10}
    with pytest.raises(ParameterError, match="give 'max_bytes' only"):
        V.renamed_keyword({"memory_budget": 1, "max_bytes": 2}, "memory_budget", "max_bytes", "fit_ramps")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert V.renamed_keyword({"max_bytes": 1}, "memory_budget", "max_bytes", "x") == {"max_bytes": 1}


def test_every_checker_error_is_a_slicersim_error():
    for call in (lambda: V.flag("overwrite", 1), lambda: V.shape("shape", (0, 4)), lambda: V.fraction("f", 2),
                 lambda: V.nramps(0)):
        with pytest.raises(SlicersimError):
            call()


def test_flag_names_show_a_parameter_by_its_flag_inside_the_block_only():
    """The CLI runs each command inside flag_names({dest: --flag}): a checker then names the flag."""
    with V.flag_names({"nramps": "--nramps", "lbda_range": "--lbda-range"}):
        with pytest.raises(ReadoutError, match=r"^--nramps must be an integer in \[1, 2147483647\], got 0$"):
            V.nramps(0)
        with pytest.raises(ParameterError, match=r"^--lbda-range\[0\] must be finite"):
            V.number(f"{V.shown('lbda_range')}[0]", math.nan)
        with V.flag_names({"seed": "--seed"}):                # nested blocks add names
            assert (V.shown("seed"), V.shown("nramps"), V.shown("other")) == ("--seed", "--nramps", "other")
        assert V.shown("seed") == "seed"
    with pytest.raises(ReadoutError, match=r"^nramps must be"):
        V.nramps(0)
def test_redshift_has_a_physical_upper_bound_and_short_messages():
    """A redshift of 1e300 (or a 301-digit integer) is refused by a range check, printed short."""
    assert V.redshift("z", 0.05) == 0.05 and V.redshift("z", 1.5) == 1.5 and V.redshift("z", 20) == 20.0
    assert V.redshift("z", V.MAX_REDSHIFT) == V.MAX_REDSHIFT and V.redshift("z", 0, allow_zero=True) == 0.0
    for huge in (float("1" + "0" * 300), 10**300, 10**400, 51.0):
        shown = r"(1e\+300|an integer of 401 digits|51.0)"
        with pytest.raises(ParameterError, match=rf"^z must be ≤ 50, got {shown} \(beyond z ≈ 21") as info:
            V.redshift("z", huge)
        assert len(str(info.value)) < 200 and "0000000000" not in str(info.value)
    with pytest.raises(ParameterError, match=r"z must be in \(0, 50\], got 0"):
        V.redshift("z", 0)


def test_short_repr_and_number_print_huge_integers_short():
    assert V.short_repr(10**300) == "1e+300" and V.short_repr(-(10**20)) == "-1e+20"
    assert V.short_repr(10**400) == "an integer of 401 digits" and V.short_repr(12345) == "12345"
    with pytest.raises(ParameterError, match=r"^x must be ≤ 10, got an integer of 401 digits$"):
        V.number("x", 10**400, high=10)
    with pytest.raises(ParameterError, match=r"^z must be ≤ 50, its maximum is 1e\+300$"):
        V.array("z", [0.5, 1e300], high=50)
    assert V.array("z", [0.5, np.nan], high=50, finite=False).shape == (2,)


OPTION_CLASSES = [
    ("slicersim.physics.ramp", "RampParameters", {"nmd": (4, 1, 0)}, "tframe", ParameterError),
    ("slicersim.products.ramps", "RampIO", {}, "overwrite", ParameterError),
    ("slicersim.products.ramps", "RunOptions", {}, "max_bytes", ParameterError),
    ("slicersim.products.ramps", "DetectorMaps", {}, "pixeldq", ParameterError),
    ("slicersim.campaign.runner", "RunOptions", {"workers": 1}, "window", ParameterError),
    ("slicersim.reduction.ramp_fit", "FitOptions", {}, "weighting", ParameterError),
    ("slicersim.reduction.options", "ReduceOptions", {}, "ncol", ParameterError),
    ("slicersim.reduction.options", "ForwardOptions", {}, "field", ParameterError),
    ("slicersim.reduction.rectify_checks", "RectifyOptions", {}, "method", ParameterError),
    ("slicersim.etc.solve", "SolveOptions", {}, "search", ParameterError),
    ("slicersim.campaign.plan", "SurveyOptions", {}, "efficiency", ParameterError),
    ("slicersim.io.uncal", "UncalOptions", {}, "substrt", ParameterError),
    ("slicersim.physics.cosmic_rays", "CosmicRayParameters", {}, "rate", EffectsError),
]


@pytest.mark.parametrize("module, name, required, field, error", OPTION_CLASSES)
def test_option_classes_name_an_unknown_field_with_did_you_mean(module, name, required, field, error):
    """FitOptions(weightin=...) was Python's 'TypeError: __init__() got an unexpected keyword argument'."""
    import dataclasses
    import importlib
    cls = getattr(importlib.import_module(module), name)
    misspelt = field[:-1]
    with pytest.raises(error, match=rf"unknown field of {name} '{misspelt}' \(did you mean '{field}'\?\); "
                                    rf"valid: .*'{field}'") as info:
        cls(**required, **{misspelt: 1})
    for f in dataclasses.fields(cls):
        if f.init:
            assert repr(f.name) in str(info.value)
    cls(**required)                                           # the defaults still build


def test_option_classes_name_a_field_of_the_wrong_type():
    from slicersim.physics.ramp import RampParameters
    from slicersim.products.ramps import DetectorMaps, RunOptions
    from slicersim.reduction.ramp_fit import FitOptions
    from slicersim.reduction.rectify_checks import RectifyOptions
    from slicersim.campaign.plan import SurveyOptions
    cases = [(lambda: FitOptions(with_truth="yes"), r"FitOptions.with_truth must be True or False, got 'yes'"),
             (lambda: FitOptions(jump_threshold="4"), r"FitOptions.jump_threshold must be a number or None"),
             (lambda: FitOptions(work_group="64"), r"FitOptions.work_group must be an integer or None"),
             (lambda: FitOptions(saturation="3"), r"saturation must be a number of DN > 0"),   # the class's words
             (lambda: SurveyOptions(detector_shape=4096), r"SurveyOptions.detector_shape must be a sequence or None"),
             (lambda: RectifyOptions(truncate="4"), r"truncate"),
             (lambda: RectifyOptions(weights_dtype="zzz"), r"weights_dtype must be float32 or float64, got 'zzz'"),
             (lambda: RunOptions(progress="no"), r"progress"),
             (lambda: RampParameters(), r"RampParameters: missing a required argument: 'nmd'; its fields: nmd, "),
             (lambda: DetectorMaps(dead_pixels=np.zeros(3), bogus=1), r"unknown field of DetectorMaps 'bogus'")]
    for make, message in cases:
        with pytest.raises(ParameterError, match=message):
            make()
    assert FitOptions(with_truth=np.bool_(True), jump_threshold=np.float32(4), work_group=np.int64(64)).with_truth
    u = pytest.importorskip("astropy.units")
    assert FitOptions(ron=5 * u.electron).ron == 5.0


# --------------------------------------------------------------------------- the paper's units
def test_every_parameter_of_the_papers_table_accepts_the_papers_unit_as_a_quantity():
    """dark in e-/s/pix, read noise in e-, frame time in s, gain in ADU/e-, saturation in ADU, slice width in mas,
    dispersion resolution in px, diameters in m, guiding in mas, mirror temperatures in K (or °C): each gives
    the simulation the bare number in the documented unit does."""
    import astropy.units as u
    from slicersim.targets import LazuliSupernova
    plain, quantity = LazuliSupernova(0.5), LazuliSupernova(0.5)
    plain.update(dark=2.8e-3, ron=10.0, tframe=2.83, gain=1.0, saturation=65535.0, spatial_scale=0.04,
                 dispersion_resolution=2.3, diameter_ext=3.0, diameter_int=0.0, guiding_sigma=0.010,
                 temperature=293.0)
    quantity.update(dark=2.8e-3 * u.electron / u.s / u.pix, ron=10 * u.electron, tframe=2830 * u.ms,
                    gain=1.0 * u.adu / u.electron, saturation=65535 * u.adu, spatial_scale=40 * u.mas,
                    dispersion_resolution=2.3 * u.pix, diameter_ext=300 * u.cm, diameter_int=0 * u.m,
                    guiding_sigma=10 * u.mas, temperature=(293.0 - 273.15) * u.deg_C)
    assert quantity.simulation.telescope.temperature == pytest.approx(293.0, rel=1e-12)
    assert quantity.get_band_snr() == pytest.approx(plain.get_band_snr(), rel=1e-9)
    with pytest.raises(ParameterError, match="guiding_sigma must be in units convertible to arcsec"):
        quantity.update(guiding_sigma=10 * u.s)


@pytest.mark.parametrize("name, value, unit", [("guiding_sigma", 10, "arcsec"), ("spatial_scale", 40, "arcsec"),
                                               ("diameter_ext", 300, "m"), ("pixel_size", 1e-5, "um"),
                                               ("tframe", 2830, "s")])
def test_a_bare_number_implausible_in_its_unit_warns_naming_the_unit(name, value, unit):
    """update(guiding_sigma=10) (the paper's 10 mas typed as a number) gave SNR 0.002 silently."""
    import astropy.units as u
    from slicersim.errors import ImplausibleValueWarning
    from slicersim.targets import LazuliSupernova
    sn = LazuliSupernova(0.5)
    with pytest.warns(ImplausibleValueWarning, match=rf"{name} = {value:g} {unit} is implausible.*read in {unit}"):
        try:
            sn.update(**{name: value})
        except ParameterError as exc:   # 40″ slices, a 300 m mirror: no cell left in the aperture, refused
            assert "aperture" in str(exc)
    import warnings
    meant = {"guiding_sigma": 10 * u.mas, "spatial_scale": 40 * u.mas, "diameter_ext": 300 * u.cm,
             "pixel_size": 10 * u.um, "tframe": 2830 * u.ms}[name]
    with warnings.catch_warnings():
        warnings.simplefilter("error", ImplausibleValueWarning)   # a Quantity is explicit: no warning
        LazuliSupernova(0.5).update(**{name: meant})
        LazuliSupernova(0.5, config="eol")                         # nor any built-in configuration


def test_a_seed_of_exactly_2_to_the_64_and_an_infinite_number_are_named_as_such():
    """A seed of 2**64 was shown as "got 1.84467e+19"; inf as "must be > 0, got inf" (inf is > 0)."""
    from slicersim import validation
    with pytest.raises(ParameterError, match=r"got 18446744073709551616 \(2\*\*64 itself is one too many: the largest "
                                             r"seed is 2\*\*64 - 1\)"):
        validation.seed(2**64)
    assert validation.seed(2**64 - 1) == 2**64 - 1
    with pytest.raises(ParameterError, match=r"^snr must be finite and > 0, got inf$"):
        validation.number("snr", float("inf"), low=0, low_open=True)
    with pytest.raises(ParameterError, match=r"^x must be finite, got nan$"):
        validation.number("x", float("nan"))
