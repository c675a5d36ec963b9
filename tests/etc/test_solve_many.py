"""The batch ETC (slicersim.etc.solve.solve_many) against the single-target ETC: reference
search and the Kubik16 variance model."""
import math

import numpy as np
import pytest

from slicersim.etc.solve import solve_many
from slicersim.targets import LazuliTarget

from model_state import LBDA, sloped  # the λ grid [Å] and λ^-1.5 spectrum shared with other tests


def flat(level=1e-17):
    return np.full(LBDA.size, level)


@pytest.fixture(scope="module")
def kubik_toml(tmp_path_factory):
    path = tmp_path_factory.mktemp("cfg") / "kubik.toml"
    path.write_text('[detector]\nvariance_model = "Kubik16"\n', encoding="utf-8")
    return str(path)


BATCH = [(flat(1e-17), (8000.0, 11000.0)), (flat(3e-18), (8000.0, 11000.0)),
         (sloped(5e-17), (5000.0, 7000.0)), (sloped(2e-18), (12000.0, 15000.0))]


def test_solve_many_reference_search_equals_single_target_reference_search():
    fluxes = np.array([f for f, _ in BATCH])
    ranges = np.array([r for _, r in BATCH])
    table = solve_many(LBDA, fluxes, 20.0, ranges, search="reference")
    assert table.meta["search"] == "reference" and len(table) == len(BATCH)
    for i, (flux, band) in enumerate(BATCH):
        target = LazuliTarget(LBDA, flux)
        res = target.setup_to_snr(20.0, lbda_range=band, search="reference")
        assert (table["n"][i], table["m"][i], table["d"][i]) == tuple(res["nmd"]), i
        assert table["nramps"][i] == res["nramps"], i
        assert table["exposure_time"][i] == pytest.approx(res["exposure_time"], rel=1e-12)
        assert table["snr_per_bin"][i] == pytest.approx(res["snr"], rel=1e-9)
        # the SNR reached, re-evaluated independently at the chosen readout
        nmd = (int(table["n"][i]), int(table["m"][i]), int(table["d"][i]))
        again = target.simulation.get_band_snr(band, nmd=nmd, nramps=int(table["nramps"][i]))
        assert again == pytest.approx(table["snr_per_bin"][i], rel=1e-9)


def test_solve_many_kubik16_equals_single_target_exact_search(kubik_toml):
    cfg = ["cbe", kubik_toml]
    fluxes = np.array([f for f, _ in BATCH])
    ranges = np.array([r for _, r in BATCH])
    table = solve_many(LBDA, fluxes, 20.0, ranges, config=cfg, search="exact")
    rauscher = solve_many(LBDA, fluxes, 20.0, ranges, search="exact")
    tau = 20.0 / math.sqrt(2.3)
    differs = False
    for i, (flux, band) in enumerate(BATCH):
        target = LazuliTarget(LBDA, flux, config=cfg)
        sim = target.simulation
        assert sim.detector.variance_model == "Kubik16"
        res = target.setup_to_snr(20.0, lbda_range=band, search="exact")
        nmd = (int(table["n"][i]), int(table["m"][i]), int(table["d"][i]))
        r = int(table["nramps"][i])
        assert nmd == tuple(res["nmd"]) and r == res["nramps"], i
        assert table["exposure_time"][i] == pytest.approx(res["exposure_time"], rel=1e-12)
        # minimal: reaches the target, one group less / one ramp less does not
        reached = sim.get_band_snr(band, nmd=nmd, nramps=r)
        assert reached >= tau * (1 - 1e-12) and reached == pytest.approx(table["snr_per_bin"][i], rel=1e-9)
        if nmd[0] > sim.detector.min_group:
            assert sim.get_band_snr(band, nmd=(nmd[0] - 1, nmd[1], nmd[2]), nramps=r) < tau
        if r > 1:
            assert sim.get_band_snr(band, nmd=nmd, nramps=r - 1) < tau
        differs |= (table["snr_per_bin"][i] != rauscher["snr_per_bin"][i])
    assert differs                                # the variance model reached the batch ETC


def test_absurd_fluxes_are_refused_and_no_signal_says_what_was_found():
    """Fluxes of 1e100 erg/s/cm²/Å reported 'no signal in the band'; a zero spectrum did not say what it held."""
    from slicersim.errors import ETCError, SpectrumError
    lbda = np.linspace(3000.0, 20000.0, 200)
    fluxes = np.full((3, 200), 1e-17)
    fluxes[2] = 1e100
    with pytest.raises(SpectrumError, match=r"fluxes of target\(s\) \[2\] \(first\): F_λ reaches 1e\+100 "
                                            r"erg/s/cm²/Å, above 1000 \(5× the Sun's F_λ at Earth"):
        solve_many(lbda, fluxes, 10.0, (9000.0, 10000.0))
    fluxes[2] = 0.0
    with pytest.raises(ETCError, match=r"target\(s\) \[2\] cannot reach their SNR: no signal in the band \(target 2, "
                                       r"band 9000–10000 Å observer frame: its F_λ there is at most 0 erg/s/cm²/Å\)"):
        solve_many(lbda, fluxes, 10.0, (9000.0, 10000.0))
    fluxes[2] = 1.0                              # saturates every cell: it said "no signal in the band"
    with pytest.raises(ETCError, match=r"target\(s\) \[2\] cannot reach their SNR: a signal that saturates the "
                                       r"detector even in the shortest readout"):
        solve_many(lbda, fluxes, 10.0, (8000.0, 13600.0))


def test_quantities_are_converted_or_refused_never_their_unit_dropped():
    """fluxes in Jy (an F_ν) or bands in µm were read as plain F_λ [erg/s/cm²/Å] and Å without a word."""
    import astropy.units as u
    from slicersim.errors import ETCError, SpectrumError
    fluxes = np.stack([flat(1e-17), sloped(3e-18)])
    plain = solve_many(LBDA, fluxes, 20, (8000.0, 11000.0))
    flam = (fluxes * u.erg / u.s / u.cm**2 / u.AA).to(u.W / u.m**2 / u.um)
    same = solve_many((LBDA * u.AA).to(u.um), flam, 20, (0.8, 1.1) * u.um)
    assert list(same["exposure_time"]) == pytest.approx(list(plain["exposure_time"]))
    with pytest.raises(SpectrumError, match=r"fluxes must be in units convertible to erg / \(s cm2 Angstrom\), got Jy"):
        solve_many(LBDA, fluxes * u.Jy, 20, (8000.0, 11000.0))
    with pytest.raises(ETCError, match=r"lbda_ranges must be in units convertible to Angstrom, got s"):
        solve_many(LBDA, fluxes, 20, (8000.0, 11000.0) * u.s)


def test_snr_of_another_length_than_the_targets_is_an_etc_error():
    """snr=[20, 30] for 3 targets was NumPy's broadcast ValueError."""
    from slicersim.errors import ETCError
    fluxes = np.stack([flat(1e-17)] * 3)
    with pytest.raises(ETCError, match=r"snr must be one value or one per target \(3\), got shape \(2,\)"):
        solve_many(LBDA, fluxes, [20, 30], (8000.0, 11000.0))
    assert list(solve_many(LBDA, fluxes, [20, 20, 20], (8000.0, 11000.0))["nramps"]) == [1, 1, 1]
