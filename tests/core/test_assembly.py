"""Assembling a simulation from configuration files (slicersim.assembly): MLA configurations."""
import pytest


def test_mla_configuration_sets_its_cross_dispersion_strip(tmp_path):
    """A kind = "mla" configuration's [spectrograph.psf.detector] xdisp_sigma(_spectral) and
    [extraction] xdisp_width_insigma were ignored (the defaults 0.9, 0.3, 10: 19 px per spaxel
    whatever the file said), so the MLA's detector pixels per cell — its read noise, dark and full
    well in the ETC, the cubes and solve_many — could not be configured."""
    import math

    from slicersim.assembly import build_simulation
    from slicersim.errors import ConfigError
    toml = tmp_path / "mla.toml"
    toml.write_text('[spectrograph]\nkind = "mla"\n[spectrograph.psf.detector]\nxdisp_sigma = 2.0\n'
                    'xdisp_sigma_spectral = 0.1\n[extraction]\nxdisp_width_insigma = 3\n')
    expected = math.ceil(2 * 3 * math.hypot(0.1, 2.0))                  # 13 px at 1 µm
    for conv in ("physical", "slicersim-1.0"):
        sim = build_simulation(["cbe", str(toml)], "narrow", conventions=conv)
        spec = sim.spectrograph
        assert (spec.xdisp_sigma, spec.xdisp_sigma_spectral, spec.xdisp_width_insigma) == (2.0, 0.1, 3.0)
        assert sim.detector_pixels_per_cell == spec.pixels_per_cell == expected
    plain = tmp_path / "mla_defaults.toml"
    plain.write_text('[spectrograph]\nkind = "mla"\n')
    assert build_simulation(["cbe", str(plain)], "narrow").detector_pixels_per_cell == 19   # cbe: 0.9, 0.3, 10
    assert build_simulation("cbe", "narrow").detector_pixels_per_cell == 1                  # the slicer ignores them
    for bad in ('xdisp_sigma = -1.0', 'xdisp_sigma = nan', 'xdisp_profile = "airy"'):
        toml.write_text(f'[spectrograph]\nkind = "mla"\n[spectrograph.psf.detector]\n{bad}\n')
        with pytest.raises(ConfigError, match="xdisp"):
            build_simulation(["cbe", str(toml)], "narrow")
