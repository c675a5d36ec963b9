"""A flat, faint LazuliTarget and a summary of its model's state, for the tests that a refused
change (``update``, ``set_*``, ``change_*``) changes nothing."""
import numpy as np
import pytest

import slicersim
from slicersim.errors import SlicersimError

#: band [Å] whose SNR enters the state
STATE_BAND = (9000.0, 12000.0)
#: wavelengths [Å] and flux [erg/s/cm²/Å] of the flat target
STATE_LBDA = np.linspace(3000.0, 20000.0, 500)
STATE_FLUX = np.full(500, 1e-18)


def flat_target(**kw):
    """A LazuliTarget of the flat spectrum (keywords as LazuliTarget's)."""
    return slicersim.LazuliTarget(STATE_LBDA, STATE_FLUX, **kw)


def model_state(t):
    """(band SNR, Σ signal, Σ variance, exposure time, readout, number of bins) of target ``t``."""
    sim = t.simulation
    _, sig, var = sim.get_spectrum()
    return (sim.get_band_snr(STATE_BAND), float(np.sum(sig)), float(np.sum(var)),
            sim.get_times()["exposure_time"], t.get_readout_config(), sim.lbda.size)


def assert_rejected_unchanged(t, func, exc=SlicersimError, match=None):
    """``func()`` raises ``exc`` (matching ``match``) and leaves the state of ``t`` as it was."""
    before = model_state(t)
    with pytest.raises(exc, match=match):
        func()
    assert repr(model_state(t)) == repr(before)


# ----------------------------------------------------------------- a fast target for detector products
#: both backends, OpenCL where a device with fp64 exists
BACKENDS = ["numpy", pytest.param("opencl", marks=pytest.mark.needs_opencl)]
#: wavelengths [Å] of the sloped spectrum
LBDA = np.arange(3000.0, 20000.0, 10.0)
#: Lazuli frame time [s] (built-in TOML)
TFRAME = 2.83


def sloped(level=1e-17):
    """A λ^-1.5 spectrum [erg/s/cm²/Å] on :data:`LBDA`, ``level`` at 1 µm."""
    return level * (LBDA / 1e4) ** -1.5


@pytest.fixture(scope="module")
def short_range_toml(tmp_path_factory):
    """Overlay TOML: the built-in CBE instrument on 9000–10000 Å only (fast detector products)."""
    path = tmp_path_factory.mktemp("cfg") / "short_range.toml"
    path.write_text("[spectrograph]\nspectral_range = [9000, 10000]\n", encoding="utf-8")
    return str(path)


@pytest.fixture(scope="module")
def short_target(short_range_toml):
    """A LazuliTarget of the sloped spectrum on the short range."""
    return slicersim.LazuliTarget(LBDA, sloped(2e-17), config=["cbe", short_range_toml])
