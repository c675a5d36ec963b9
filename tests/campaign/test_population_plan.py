"""Populations (distributions, SN Ia spectra vs sncosmo, dust, hosts, catalogs) and survey plans.

Statistical tests use N draws and bounds of 5 standard errors (false-alarm ≈ 6e-7 each).
"""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from astropy.table import Table

from slicersim.errors import ConfigError, ParameterError
import signal
import time

from conftest import one_line_error, run_cli

LBDA = np.arange(3000.0, 20000.0, 10.0)
BIN = Path(sys.executable).parent


def _pop(**kw):
    from slicersim.campaign.population import SNIaPopulation
    kw.setdefault("redshift", {"distribution": "uniform", "min": 0.1, "max": 1.2})
    return SNIaPopulation(kw.pop("n", 2000), **kw)


# --------------------------------------------------------------------------- distributions
def test_uniform_redshifts_moments_and_independence_of_n():
    pop = _pop(n=20000)
    z = np.asarray(pop.draw(5)["redshift"])
    assert z.min() > 0.1 and z.max() < 1.2
    se = 1.1 / np.sqrt(12 * z.size)
    assert abs(z.mean() - 0.65) < 5 * se
    # a target's parameters depend only on (seed, target id): not on n
    small = _pop(n=50).draw(5)
    assert np.array_equal(np.asarray(small["redshift"]), z[:50])
    assert not np.array_equal(np.asarray(_pop(n=50).draw(6)["redshift"]), z[:50])


def test_volumetric_redshifts_follow_rate_times_volume():
    """KS distance to the CDF of (1+z)^1.5 dV/dz/(1+z) computed independently with quad."""
    from astropy.cosmology import Planck18
    from scipy.integrate import quad
    pop = _pop(n=20000, redshift={"distribution": "volumetric", "min": 0.05, "max": 1.5})
    z = np.sort(np.asarray(pop.draw(1)["redshift"]))

    def dens(x):
        return (1 + x) ** 0.5 * Planck18.differential_comoving_volume(x).value
    norm = quad(dens, 0.05, 1.5)[0]
    probe = np.linspace(0.1, 1.45, 12)
    cdf = np.array([quad(dens, 0.05, p)[0] / norm for p in probe])
    emp = np.searchsorted(z, probe) / z.size
    # DKW: P(sup|F_n − F| > ε) ≤ 2 exp(−2 n ε²); ε = 0.015 at n = 20000 → 2e-4
    assert np.max(np.abs(emp - cdf)) < 0.015
    # more SNe at high z than a uniform draw would give (volume grows)
    assert np.median(z) > 0.9


def test_table_redshift_distribution(tmp_path):
    path = tmp_path / "nz.csv"
    Table({"z": [0.2, 0.4, 0.6], "weight": [0.0, 1.0, 0.0]}).write(path)
    pop = _pop(n=20000, redshift={"distribution": "table", "file": str(path)})
    z = np.asarray(pop.draw(2)["redshift"])
    assert 0.2 <= z.min() and z.max() <= 0.6
    # triangular density on [0.2, 0.6]: mean 0.4, variance (0.2²)/6
    assert abs(z.mean() - 0.4) < 5 * np.sqrt(0.04 / 6 / z.size)
    assert abs(z.var() - 0.04 / 6) < 0.1 * 0.04 / 6


@pytest.mark.parametrize("spec, message", [
    ({"distribution": "uniform", "min": 1.2, "max": 0.3},
     r"population.redshift.min \(1.2\) must be < population.redshift.max \(0.3\)$"),
    ({"distribution": "uniform", "min": -0.3, "max": 1.0},
     r"population.redshift.min must be in \[0, 10\] \(redshifts cannot be negative\), got -0.3$"),
    ({"distribution": "uniform", "min": 0.5, "max": 0.5}, "min"),
    ({"distribution": "uniform", "min": 0.1, "max": 30}, r"population.redshift.max must be in \[0, 10\] \(redshifts "
                                                          r"above 10 are outside any SN Ia model\), got 30$"),
    ({"distribution": "gauss", "min": 0.1, "max": 1}, "distribution"),
    ({"distribution": "uniform", "min": 0.1, "mx": 1}, "'mx'"),
    ({"distribution": "uniform", "min": float("nan"), "max": 1}, "finite"),
    ({"distribution": "uniform", "min": True, "max": 1}, "a number"),
    ({"distribution": "volumetric", "min": 0.1, "max": 1, "rate_index": 50}, "rate_index"),
    (0.0, "> 0"),
])
def test_bad_redshift_distributions(spec, message):
    with pytest.raises(ConfigError, match=message):
        _pop(n=3, redshift=spec)


def test_bad_population_values():
    for kw, msg in [({"n": 0}, "n"), ({"n": 2.5}, "integer"), ({"n": True}, "integer"),
                    ({"x1": 1.0}, "SALT"), ({"cosmology": "Planck99"}, "Planck18"),
                    ({"phase": {"distribution": "uniform", "min": -50, "max": 0}}, "phase"),
                    ({"mw_dust": {"ebv": -0.1}}, "ebv"), ({"host_dust": {"ebv": 0.1, "rv": 3}}, "'rv'"),
                    ({"band": "nosuchband"}, "band"), ({"colour": 1}, "'colour'"),
                    ({"hosts": {"sersic": 1}}, "'sersic'")]:
        with pytest.raises(ConfigError, match=msg):
            _pop(**{"n": 3, **kw})


def test_truncated_normal_and_exponential_draws():
    from slicersim import rng
    from slicersim.campaign.distributions import Distribution
    u = rng.uniform(3, np.arange(40000, dtype=np.uint64), stream=9)
    x = Distribution.parse({"distribution": "normal", "mean": 0, "sigma": 1, "min": 0}, "x").draw(u)
    assert x.min() >= 0
    assert abs(x.mean() - np.sqrt(2 / np.pi)) < 5 * np.sqrt((1 - 2 / np.pi) / x.size)   # half-normal
    e = Distribution.parse({"distribution": "exponential", "scale": 0.1}, "e").draw(u[:, 1])
    assert abs(e.mean() - 0.1) < 5 * 0.1 / np.sqrt(e.size)
    e2 = Distribution.parse({"distribution": "exponential", "scale": 0.1, "max": 0.05}, "e").draw(u[:, 1])
    assert e2.max() <= 0.05 and e2.min() >= 0


# --------------------------------------------------------------------------- SN Ia spectra
def test_snia_fluxes_equal_sncosmo_model_with_dust_and_rest_frame_phase():
    import sncosmo
    from astropy.cosmology import Planck18

    from slicersim.campaign.population import snia_fluxes
    z = np.array([0.3, 0.9, 1.4])
    phase = np.array([-5.0, 0.0, 12.0])            # rest-frame days
    absmag = np.array([-19.3, -19.1, -19.5])
    mwebv, hostebv = np.array([0.02, 0.1, 0.0]), np.array([0.0, 0.2, 0.05])
    ours = snia_fluxes(LBDA, z, phase, absmag, mwebv=mwebv, mw_rv=3.1, hostebv=hostebv, host_rv=2.5)
    for i in range(z.size):
        model = sncosmo.Model("hsiao-subsampled", effects=[sncosmo.CCM89Dust(), sncosmo.F99Dust()],
                              effect_names=["host", "mw"], effect_frames=["rest", "obs"])
        model.set(z=z[i], t0=0.0, hostebv=hostebv[i], hostr_v=2.5, mwebv=mwebv[i])
        model.set_source_peakabsmag(absmag[i], "bessellb", "ab", cosmo=Planck18)
        ok = np.isfinite(ours[i])
        ref = model.flux(phase[i] * (1 + z[i]), LBDA[ok])
        np.testing.assert_allclose(ours[i, ok], ref, rtol=1e-12)
        # coverage: hsiao rest 1000–25000 Å → NaN only where λ/(1+z) leaves it
        assert np.array_equal(ok, (LBDA / (1 + z[i]) >= 1000) & (LBDA / (1 + z[i]) <= 25000))


def test_population_spectrum_of_a_row_equals_the_batch():
    pop = _pop(n=5, mw_dust={"ebv": 0.03}, host_dust={"ebv": {"distribution": "exponential", "scale": 0.1}},
               phase={"distribution": "uniform", "min": -10, "max": 20}, mag_scatter=0.1)
    tab = pop.draw(4)
    batch = pop.spectra(tab, LBDA)
    for row in tab:
        lb, f = pop.spectrum({k: row[k] for k in tab.colnames}, LBDA)
        ok = np.isfinite(batch[int(row["target_id"])])
        assert np.array_equal(lb, LBDA[ok]) and np.array_equal(f, batch[int(row["target_id"])][ok])
    # switching dust on leaves the other parameters' draws unchanged (one stream each)
    plain = _pop(n=5, phase={"distribution": "uniform", "min": -10, "max": 20}, mag_scatter=0.1).draw(4)
    for col in ("redshift", "phase", "peak_absmag"):
        assert np.array_equal(np.asarray(plain[col]), np.asarray(tab[col]))
    # the dust dims the SN: host + MW extinction < 1 everywhere
    undimmed = _pop(n=5, phase={"distribution": "uniform", "min": -10, "max": 20}, mag_scatter=0.1).spectra(plain, LBDA)
    ok = np.isfinite(batch)
    assert np.all(batch[ok] < undimmed[ok])


def test_salt_offline_error_names_what_is_missing(monkeypatch, tmp_path):
    from slicersim.campaign import snia_model
    from slicersim.errors import SpectrumError
    monkeypatch.setenv("SNCOSMO_DATA_DIR", str(tmp_path))
    snia_model._SOURCES.pop("salt3-nonexistent", None)
    with pytest.raises(SpectrumError, match="salt3-nonexistent.*available offline: hsiao-subsampled"):
        snia_model._source("salt3-nonexistent")


# --------------------------------------------------------------------------- hosts
def test_hosts_follow_size_luminosity_and_light_profile():
    from scipy.special import gammainc

    from slicersim.campaign.population import shen03_radius_kpc
    from slicersim.sources.extended import sersic_bn
    # Shen et al. 2003 late types: at M = M0 = −20.52 the median R50 is
    # 10^(0.0840·20.52·... ) — evaluated by hand: log R = 0.084·20.52 + 0.32·log10(2) − 1.31
    assert shen03_radius_kpc(-20.52, 0.5) == pytest.approx(10 ** (0.084 * 20.52 + 0.32 * np.log10(2) - 1.31),
                                                           rel=1e-12)
    pop = _pop(n=6000, hosts={"sersic_index": 1.0, "axis_ratio": 1.0, "max_radius": 8.0},
               redshift={"distribution": "fixed", "value": 0.5})
    tab = pop.draw(3)
    r = np.hypot(tab["host_offset_x"], tab["host_offset_y"]) / tab["host_r_eff"]
    # SN radii follow the exponential disc's light: half within r_e (truncation at 8 r_e: 0.9997)
    bn = sersic_bn(1.0)
    expect = gammainc(2, bn * 1.0) / gammainc(2, bn * 8.0)
    frac = np.mean(r < 1)
    assert abs(frac - expect) < 5 * np.sqrt(0.25 / r.size)
    assert r.max() <= 8.0 + 1e-9
    # r_eff in arcsec = R50[kpc] × arcsec/kpc at z = 0.5 (Planck18)
    from astropy.cosmology import Planck18
    med_kpc = np.median(np.asarray(tab["host_r_eff"]) / Planck18.arcsec_per_kpc_proper(0.5).value)
    assert 1.0 < med_kpc < 8.0


def test_host_spectrum_has_the_drawn_absolute_magnitude():
    """Round trip: the observed host spectrum, moved back to 10 pc in the rest frame, has
    the drawn rest-frame bessellr AB absolute magnitude."""
    import sncosmo
    from astropy.cosmology import Planck18
    pop = _pop(n=3, hosts={}, redshift={"distribution": "fixed", "value": 0.3})
    row = {k: v for k, v in zip(pop.draw(1).colnames, pop.draw(1)[1])}
    host = pop.host(row)
    lb, f = host.lbda_in, host.flux_in
    dl = Planck18.luminosity_distance(0.3).to_value("pc")
    rest = sncosmo.Spectrum(lb / 1.3, f * 1.3 * (dl / 10) ** 2)
    assert rest.bandmag("bessellr", "ab") == pytest.approx(row["host_absmag"], abs=2e-3)
    assert host.profile.r_eff == pytest.approx(row["host_r_eff"])


# --------------------------------------------------------------------------- catalogs
@pytest.mark.parametrize("fmt", ["ecsv", "csv", "parquet"])
def test_catalog_population_formats_and_user_spectra(tmp_path, fmt):
    from slicersim.campaign.population import population_from_spec
    spec_file = tmp_path / "flat.ecsv"
    Table({"lbda": [3000.0, 20000.0], "flux": [1e-17, 1e-17]}).write(spec_file)
    tab = Table({"target_id": [7, 3], "redshift": [0.5, 0.0], "spectrum_file": ["", "flat.ecsv"],
                 "survey_tag": ["a", "b"]})
    path = tmp_path / f"targets.{fmt}"
    tab.write(path, format={"ecsv": "ascii.ecsv", "csv": "ascii.csv", "parquet": "parquet"}[fmt])
    pop = population_from_spec({"kind": "catalog", "file": path.name}, base_dir=str(tmp_path))
    drawn = pop.draw(1)
    assert list(drawn["target_id"]) == [7, 3] and list(drawn["survey_tag"]) == ["a", "b"]
    flux = pop.spectra(drawn, LBDA)
    np.testing.assert_allclose(flux[1], 1e-17)                                # the user's spectrum
    ref = _pop(n=1).spectra(Table({"redshift": [0.5], "phase": [0.0], "peak_absmag": [-19.3]}), LBDA)[0]
    ok = np.isfinite(ref)
    np.testing.assert_array_equal(flux[0][ok], ref[ok])                      # the SN Ia model


@pytest.mark.parametrize("table, message", [
    ({"redshift": []}, "no rows"),
    ({"z": [0.5]}, "'redshift'"),
    ({"redshift": [-0.5]}, "negative"),
    ({"redshift": [0.5, 0.6], "target_id": [1, 1]}, "unique"),
    ({"redshift": [0.5], "target_id": [-1]}, "unique"),
    ({"redshift": [0.5], "nramps": [3]}, "computed by the campaign"),
    ({"redshift": [0.0]}, "> 0"),
])
def test_bad_catalogs(tmp_path, table, message):
    from slicersim.campaign.population import population_from_spec
    path = tmp_path / "t.ecsv"
    Table({k: np.asarray(v, dtype=float if k == "redshift" else None) for k, v in table.items()}).write(path)
    with pytest.raises(ConfigError, match=message):
        population_from_spec({"kind": "catalog", "file": str(path)})


def test_catalog_missing_file_and_unknown_kind(tmp_path):
    from slicersim.campaign.population import population_from_spec
    with pytest.raises(ConfigError, match="no such file"):
        population_from_spec({"kind": "catalog", "file": "nope.ecsv"}, base_dir=str(tmp_path))
    with pytest.raises(ConfigError, match="snia, catalog"):
        population_from_spec({"kind": "galaxies", "n": 3})


# --------------------------------------------------------------------------- plans
@pytest.fixture(scope="module")
def small_plan():
    from slicersim.campaign.plan import plan_survey
    pop = _pop(n=40, redshift={"distribution": "uniform", "min": 0.1, "max": 1.5})
    tab = pop.draw(1)
    flux = np.nan_to_num(pop.spectra(tab, LBDA))
    return tab, flux, plan_survey(np.asarray(tab["redshift"]), LBDA, flux, snr=20, overhead=300.0,
                                  efficiency=0.8, compression_ratio=2.5)


def test_plan_fields_volumes_and_totals(small_plan):
    from slicersim.campaign.plan import YEAR_S
    tab, _, plan = small_plan
    t = plan.table
    z = np.asarray(t["redshift"])
    assert np.array_equal(np.asarray(t["field"]) == "wide", z >= 0.8)
    assert set(t["status"]) == {"planned"} and np.all(np.asarray(t["snr"]) >= 20 * (1 - 1e-9))
    # 16-bit groups of the 4096² H4RG, every group of every ramp kept
    vol = np.asarray(t["nramps"]) * np.asarray(t["n"]) * 4096 * 4096 * 2
    assert np.array_equal(np.asarray(t["data_volume"]), vol)
    assert np.array_equal(np.asarray(t["data_volume_compressed"]), np.round(vol / 2.5).astype(np.int64))
    # exposure = nramps · (n (m + d) − d) · t_frame
    frames = np.asarray(t["n"]) * (np.asarray(t["m"]) + np.asarray(t["d"])) - np.asarray(t["d"])
    ratio = np.asarray(t["exposure_time"]) / (np.asarray(t["nramps"]) * frames)
    assert np.allclose(ratio, ratio[0]) and 2 < ratio[0] < 4                  # one frame time (~3 s)
    tot = plan.totals
    assert tot["exposure_time"] == pytest.approx(float(np.sum(t["exposure_time"])))
    assert tot["duration"] == pytest.approx((tot["exposure_time"] + 40 * 300.0) / 0.8)
    assert tot["duration_years"] == pytest.approx(tot["duration"] / YEAR_S)
    assert tot["data_volume"] == int(vol.sum())
    # time and volume grow with redshift (same SNR, fainter targets)
    hi, lo = z > 1.2, z < 0.4
    assert np.median(np.asarray(t["exposure_time"])[hi]) > 3 * np.median(np.asarray(t["exposure_time"])[lo])
    assert "yr" in plan.summary() and "TB" in plan.summary()


def test_plan_equals_the_batch_etc_per_field(small_plan):
    """Sorting by redshift inside the plan changes no number: same as solve_many per field."""
    from slicersim.etc.solve import solve_many
    tab, flux, plan = small_plan
    z = np.asarray(tab["redshift"])
    for field in ("narrow", "wide"):
        sel = (z >= 0.8) == (field == "wide")
        ref = solve_many(LBDA, flux[sel], 20, (4000, 6800), frame="rest", redshifts=z[sel], field=field)
        for key in ("n", "m", "d", "nramps", "exposure_time", "snr"):
            assert np.array_equal(np.asarray(plan.table[key])[sel], np.asarray(ref[key])), key


def test_plan_records_unservable_targets_and_plans_the_rest(small_plan):
    from slicersim.campaign.plan import plan_survey
    tab, flux, plan = small_plan
    flux = flux[:8].copy()
    flux[3] = 0.0                                             # no signal: no readout reaches the SNR
    z = np.asarray(tab["redshift"])[:8]
    p = plan_survey(z, LBDA, flux, snr=20)
    assert list(np.asarray(p.table["status"]) == "failed") == [i == 3 for i in range(8)]
    assert "cannot reach" in p.table["error"][3]
    keep = np.arange(8) != 3
    for key in ("n", "nramps", "exposure_time"):
        assert np.array_equal(np.asarray(p.table[key])[keep], np.asarray(plan.table[key])[:8][keep])
    assert p.totals["failed"] == 1 and p.totals["planned"] == 7


@pytest.mark.parametrize("kw, message", [({"efficiency": 0}, "efficiency"), ({"efficiency": 1.5}, "efficiency"),
                                         ({"overhead": -1}, "overhead"), ({"compression_ratio": 0.5}, "compression"),
                                         ({"overhead": float("nan")}, "overhead")])
def test_plan_bad_parameters(kw, message):
    from slicersim.campaign.plan import plan_survey
    with pytest.raises(ParameterError, match=message):
        plan_survey(np.array([0.5]), LBDA, np.ones((1, LBDA.size)) * 1e-17, **kw)


@pytest.mark.parametrize("kw, message", [({"frame": "observed"}, "frame.*'rest', 'obs'"),
                                         ({"lbda_range": (6800, 4000)}, "lbda_range"),
                                         ({"snr": 0}, "snr"), ({"z_switch": -1}, "z_switch"),
                                         ({"z_switch": "high"}, "z_switch"),
                                         ({"fields": ("narrow", "wdie")}, r"fields\[1\].*did you mean 'wide'"),
                                         ({"fieldz": ("wide", "wide")}, "unknown keyword.*'fieldz'"),
                                         ({"target_ids": [7]}, "target_ids")])
def test_plan_bad_options_name_the_keyword(kw, message):
    from slicersim.campaign.plan import plan_survey
    with pytest.raises(ParameterError, match=message):
        plan_survey(np.array([0.5, 0.6]), LBDA, np.ones((2, LBDA.size)) * 1e-17, **kw)


def test_plan_refuses_duplicate_target_ids():
    """Duplicate ids made two plan rows (and later two campaign records) one target: refused, naming them."""
    from slicersim.campaign.plan import plan_survey
    z = np.array([0.3, 0.5, 0.7, 0.9])
    with pytest.raises(ParameterError, match=r"target_ids must be unique.*\(3, 8\)"):
        plan_survey(z, LBDA, np.ones((4, LBDA.size)) * 1e-17, target_ids=[3, 8, 3, 8])


def test_plan_options_object_and_frame_default(small_plan, monkeypatch):
    """plan_survey(..., options=SurveyOptions(...)) is the keyword form; frame None means "rest"
    (a survey's targets have redshifts) and is recorded as such."""
    from slicersim.campaign import plan as plan_module
    tab, flux, plan = small_plan
    assert plan.totals["frame"] == "rest"
    seen = []
    monkeypatch.setattr(plan_module, "_solve_fields", lambda lbda, fluxes, z, ids, opts: seen.append(opts) or
                        ({k: np.zeros(z.size, dtype=np.int64) for k in ("n", "m", "d", "nramps", "exposure_time",
                                                                         "snr")}, {}, np.full(z.size, "narrow"),
                         {"narrow": (8, 8)}))
    opts = plan_module.SurveyOptions(snr=15, overhead=10.0, frame="obs")
    got = plan_module.plan_survey(np.array([0.5]), LBDA, np.ones((1, LBDA.size)), options=opts)
    assert seen[0].snr == 15.0 and seen[0].frame == "obs" and got.totals["overhead"] == 10.0
    assert plan_module.plan_survey(np.array([0.5]), LBDA, np.ones((1, LBDA.size)), snr=15, overhead=10.0,
                                   frame="obs").totals == got.totals
    with pytest.raises(ParameterError, match="not both"):
        plan_module.plan_survey(np.array([0.5]), LBDA, np.ones((1, LBDA.size)), options=opts, overhead=1.0)


def test_plan_figure(small_plan, tmp_path):
    from slicersim.campaign.plan import plot_time_and_volume
    path = plot_time_and_volume({"SNR 20": small_plan[2]}, tmp_path / "f.png")
    assert Path(path).stat().st_size > 10_000


# --------------------------------------------------------------------------- CLI
@pytest.mark.slow
def test_cli_survey_plan_writes_the_table_and_prints_totals(tmp_path):
    out = tmp_path / "plan.ecsv"
    proc = subprocess.run([str(BIN / "slicersim"), "survey", "plan", "--n", "30", "--zmin", "0.05", "--zmax", "1.5",
                           "--snr", "20", "--z-switch", "0.8", "--seed", "1", "--out", str(out), "--overhead", "600",
                           "--efficiency", "0.75"], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    t = Table.read(out, format="ascii.ecsv")
    for col in ("redshift", "field", "n", "m", "d", "nramps", "exposure_time", "snr", "data_volume"):
        assert col in t.colnames
    assert str(t["exposure_time"].unit) == "s" and str(t["data_volume"].unit) == "byte"
    assert set(t["field"]) == {"narrow", "wide"}
    assert "yr at 75 % observing efficiency" in proc.stdout and "TB" in proc.stdout
    assert t.meta["population_seed"] == 1 and "population seed    : 1\n" in proc.stdout
    drawn = subprocess.run([str(BIN / "slicersim"), "survey", "plan", "--n", "2", "--zmin", "0.3", "--zmax", "0.5",
                            "--out", str(tmp_path / "drawn.ecsv")], capture_output=True, text=True, timeout=300)
    assert drawn.returncode == 0, drawn.stderr                 # no --seed: a seed is drawn, printed and recorded
    seed = Table.read(tmp_path / "drawn.ecsv", format="ascii.ecsv").meta["population_seed"]
    assert f"population seed    : {seed} (drawn" in drawn.stdout
    again = subprocess.run([str(BIN / "slicersim"), "survey", "plan", "--n", "3", "--out", str(out)],
                           capture_output=True, text=True, timeout=300)
    assert again.returncode == 2 and "exists" in again.stderr


@pytest.mark.slow
@pytest.mark.parametrize("args, message", [(["--n", "0"], "n"), (["--zmin", "1.2", "--zmax", "0.3"], "min"),
                                           (["--zmin", "-0.5"], "negative"), (["--efficiency", "2"], "efficiency"),
                                           (["--seed", "-1"], "--seed")])
def test_cli_survey_plan_bad_input(tmp_path, args, message):
    out = tmp_path / "p.ecsv"
    proc = subprocess.run([str(BIN / "slicersim"), "survey", "plan", "--n", "5", *args, "--out", str(out)],
                          capture_output=True, text=True, timeout=300)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1 and lines[0].startswith("slicersim: error:"), proc.stderr
    assert message in lines[0]
    assert not out.exists()


@pytest.mark.parametrize("args, message", [
    (["--zmin", "1.2", "--zmax", "0.3"], "--zmin (1.2) must be < --zmax (0.3)"),
    (["--zmin", "0.5", "--zmax", "0.5"], "--zmin (0.5) must be < --zmax (0.5)"),
    (["--zmin=-0.5"], "--zmin must be in [0, 10] (redshifts cannot be negative), got -0.5"),
    (["--zmax", "12"], "--zmax must be in [0, 10] (redshifts above 10 are outside any SN Ia model), got 12"),
    (["--zmin", "nan"], "--zmin must be finite, got nan"),
    (["--zmax", "inf"], "--zmax must be finite, got inf"),
    (["--zmin=-inf"], "--zmin must be finite, got -inf"),
    (["--snr", "-1"], "--snr must be > 0, got -1"),
    (["--z-switch", "-1"], "--z-switch must be in [0, 50], got -1"),
    (["--compression-ratio", "0"], "--compression-ratio must be ≥ 1, got 0"),
    (["--lbda-range", "6000", "4000"], "--lbda-range must be (lo, hi) in Å with 0 < lo < hi"),
])
def test_cli_survey_plan_messages_name_the_flags(tmp_path, args, message):
    """The redshift range and the plan's options are named by their flags (--zmin, not population.redshift.min
    or zmin), one line each."""
    proc = run_cli("survey", "plan", "--n", "2", *args, "--out", tmp_path / "p.ecsv")
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1 and lines[0].startswith("slicersim: error: --"), proc.stderr
    assert message in lines[0] and "population." not in lines[0] and "z_switch" not in lines[0], lines[0]
    assert not (tmp_path / "p.ecsv").exists()


# --------------------------------------------------------------------------- campaign targets
def test_catalog_campaign_with_dust_hosts_and_user_spectrum(tmp_path):
    """A catalog campaign in-process: planned, simulated (host in the scene) and recorded;
    editing the catalog changes the dataset's identity (a changed catalog is refused)."""
    import tomllib

    import h5py

    from slicersim.campaign.products import run_target
    from slicersim.campaign.runner import plan_campaign
    from slicersim.campaign.spec import parse_spec
    from slicersim.io.dataset import Dataset
    Table({"lbda": [3000.0, 20000.0], "flux": [3e-18, 3e-18]}).write(tmp_path / "flat.ecsv")
    Table({"target_id": [10, 11], "redshift": [0.4, 0.5], "spectrum_file": ["", "flat.ecsv"],
           "program": ["snia", "flat"]}).write(tmp_path / "targets.csv")
    text = """seed = 5
[population]
kind = "catalog"
file = "targets.csv"
mw_dust = {ebv = 0.03}
host_dust = {ebv = {distribution = "exponential", scale = 0.1}}
hosts = {absmag = -19.0}
[observation]
snr = 5
[products]
spectrum = true
"""
    (tmp_path / "c.toml").write_text(text)
    spec = parse_spec(tomllib.loads(text), text=text, base_dir=str(tmp_path))
    cat, plan = plan_campaign(spec)
    assert list(cat["target_id"]) == [10, 11] and list(cat["program"]) == ["snia", "flat"]
    assert {"mwebv", "hostebv", "host_r_eff", "host_offset_x"} <= set(cat.colnames)
    assert np.all(np.asarray(cat["mwebv"]) == 0.03) and set(cat["status"]) == {"planned"}
    ds = Dataset(tmp_path / "d")
    digest = ds.initialise(spec.text, spec.canonical(), {}, False)
    for row in cat:
        rec = run_target(spec, {k: (row[k].item() if hasattr(row[k], "item") else row[k]) for k in cat.colnames},
                         ds.path, digest)
        assert rec["status"] == "done", rec.get("error")
    with h5py.File(tmp_path / "d" / "products" / "t0000011" / "spectrum.h5", "r") as f:
        np.testing.assert_allclose(f["flambda"][...], 3e-18, rtol=1e-12)       # the user's spectrum
        assert np.all(f["variance"][...] > 0)
    # the catalog's content is part of the spec's identity
    Table({"target_id": [10, 11], "redshift": [0.4, 0.6], "spectrum_file": ["", "flat.ecsv"],
           "program": ["snia", "flat"]}).write(tmp_path / "targets.csv", overwrite=True)
    changed = parse_spec(tomllib.loads(text), text=text, base_dir=str(tmp_path))
    from slicersim.errors import DatasetError
    with pytest.raises(DatasetError, match="different spec.*population.file_sha256"):
        ds.check_spec(changed.canonical())


def _cli(*args, **kw):
    """`slicersim ARGS` in this process (the real `slicersim survey plan` runs above)."""
    return run_cli(*args, **kw)


# 4, 13 ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("col, values, message", [("mwebv", [-2.0], "mwebv"), ("peak_absmag", [-40.0], "peak_absmag"),
                                                  ("phase", ["abc"], "not numeric"), ("redshift", ["x"], "not numeric"),
                                                  ("host_r_eff", [1.0], "all host columns")])
def test_catalog_parameter_columns_are_checked(tmp_path, col, values, message):
    from slicersim.campaign.population import population_from_spec
    cols = {"redshift": [0.5], col: values} if col != "redshift" else {"redshift": values}
    Table(cols).write(tmp_path / "t.ecsv")
    kw = {"hosts": {}} if col.startswith("host_") else {}
    with pytest.raises(ConfigError, match=message):
        population_from_spec({"kind": "catalog", "file": "t.ecsv", **kw}, base_dir=str(tmp_path))


# 5 -------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_sigint_interrupts_a_survey_plan_with_one_line(tmp_path):
    out = tmp_path / "p.ecsv"
    proc = subprocess.Popen([str(BIN / "slicersim"), "survey", "plan", "--n", "3000", "--out", str(out)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    time.sleep(6)                                             # inside the batch ETC (kernels running)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    last = [l for l in err.replace("\r", "\n").splitlines() if l.strip()][-1]
    assert proc.returncode == 2 and last == "slicersim: error: interrupted", err[-500:]
    assert not out.exists()


# 10, 22 --------------------------------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.parametrize("args, message", [(["--snr", "-5"], "--snr"), (["--snr", "0"], "--snr"),
                                           (["--snr", "nan"], "--snr"),
                                           (["--lbda-range", "6800", "4000"], "--lbda-range"),
                                           (["--lbda-range", "-5", "4000"], "--lbda-range"),
                                           (["--out", "plan.txt"], ".ecsv"), (["--out", "."], "directory"),
                                           (["--figure", "/nonexistent/f.png"], "not writable")])
def test_survey_plan_refuses_impossible_requests(tmp_path, args, message):
    proc = _cli("survey", "plan", "--n", "3", *args, cwd=tmp_path)
    one_line_error(proc, message)
    assert not list(tmp_path.iterdir())


@pytest.mark.slow
def test_survey_plan_exits_1_when_targets_cannot_be_planned(tmp_path):
    proc = _cli("survey", "plan", "--n", "3", "--snr", "1e6", "--out", tmp_path / "p.ecsv")
    assert proc.returncode == 1 and "could not be planned" in proc.stdout
    t = Table.read(tmp_path / "p.ecsv")
    assert set(t["status"]) == {"failed"}
    # 11: each error names its own target id, not its position in the ETC batch
    for tid, err in zip(t["target_id"], t["error"]):
        assert f"target {tid}:" in err


# 23 ------------------------------------------------------------------------------------------
def test_population_too_large_for_memory_is_refused_before_drawing():
    from slicersim.campaign.plan import check_client_memory
    from slicersim.errors import ParameterError
    with pytest.raises(ParameterError, match="split the population"):
        check_client_memory(10_000_000, 1700)
    check_client_memory(8000, 1700)


def test_survey_plan_out_fifo_is_refused_even_with_overwrite(tmp_path):
    """--overwrite replaces only regular files: a FIFO (or a link to one) given as --out is refused, untouched."""
    import os
    import stat
    os.mkfifo(tmp_path / "p.ecsv")
    (tmp_path / "f.png").symlink_to(tmp_path / "p.ecsv")
    for args, words in ((["--out", "p.ecsv"], ("--out:", "p.ecsv is a FIFO")),
                        (["--figure", "f.png"], ("--figure:", "FIFO", "symbolic link"))):
        one_line_error(_cli("survey", "plan", "--n", "3", "--overwrite", *args, cwd=tmp_path), *words)
    assert stat.S_ISFIFO(os.lstat(tmp_path / "p.ecsv").st_mode) and sorted(os.listdir(tmp_path)) == ["f.png", "p.ecsv"]


def test_survey_redshifts_beyond_the_physical_bound_are_refused_short():
    """Populations, plans and switch redshifts of 1e300 are range errors printed short."""
    from slicersim.campaign.plan import plan_survey
    with pytest.raises(ConfigError, match=r"population.redshift.max must be in \[0, 10\] \(redshifts above 10 .*got 1e\+300$"):
        _pop(n=3, redshift={"distribution": "uniform", "min": 0.1, "max": 10**300})
    with pytest.raises(ParameterError, match=r"redshift must be ≤ 50, its maximum is 1e\+300"):
        plan_survey(np.array([0.5, 1e300]), LBDA, np.ones((2, LBDA.size)) * 1e-17)
    with pytest.raises(ParameterError, match=r"z_switch must be ≤ 50, got 1e\+300"):
        plan_survey(np.array([0.5]), LBDA, np.ones((1, LBDA.size)) * 1e-17, z_switch=10**300)


# --------------------------------------------------------------------------- one SN model
def test_single_target_population_and_campaign_agree_on_flux_and_readout(tmp_path):
    """``phase`` is rest-frame days in every path: a LazuliSupernova, a population row and a catalog
    campaign of the same SN give the same F_λ and the same ETC readout at phases −10 … +30 d
    (they were 1.6–2.9× apart when the single target read its phase in the observer frame)."""
    import tomllib

    from slicersim.campaign.runner import plan_campaign
    from slicersim.campaign.spec import parse_spec
    from slicersim.targets import LazuliSupernova
    z, phases = 0.6, [-10.0, 0.0, 15.0, 30.0]
    Table({"target_id": [0, 1, 2, 3], "redshift": [z] * 4, "phase": phases}).write(tmp_path / "sne.ecsv")
    text = '[population]\nkind = "catalog"\nfile = "sne.ecsv"\n[observation]\nsnr = 10\nfield = "narrow"\n'
    spec = parse_spec(tomllib.loads(text), text=text, base_dir=str(tmp_path))
    cat, _ = plan_campaign(spec)
    flux_pop = spec.population.spectra(cat, LBDA)
    for i, phase in enumerate(phases):
        sn = LazuliSupernova(z, phase=phase)
        lbda, flux = sn.pointsource.lbda_in, sn.pointsource.flux_in
        pop = np.interp(lbda, LBDA, flux_pop[i])
        np.testing.assert_allclose(flux, pop, rtol=1e-12)
        etc = sn.setup_to_snr(10)
        assert (tuple(etc["nmd"]), etc["nramps"]) == ((int(cat["n"][i]), int(cat["m"][i]), int(cat["d"][i])),
                                                       int(cat["nramps"][i])), phase
    # the old meaning stays available: slicersim 1.0 read the same number in the observer frame
    old = LazuliSupernova(z, phase=15.0, conventions="slicersim-1.0").pointsource.flux_in
    rest = LazuliSupernova(z, phase=15.0 / (1 + z)).pointsource.flux_in
    np.testing.assert_allclose(old, rest, rtol=1e-12)
    assert not np.allclose(old, LazuliSupernova(z, phase=15.0).pointsource.flux_in, rtol=0.05, atol=0)


def test_salt_models_load_offline_from_the_installed_template_files():
    """salt2 / salt3 need no download where jax-bandflux's data files are installed (make installs
    them); the population draws x1 and c for them, and x1 changes the spectrum as SALT says."""
    from slicersim.sources.salt_files import offline_model_dir, offline_salt_source
    from slicersim.sources.spectra import snia_spectrum
    if offline_model_dir("salt3") is None:
        pytest.skip("jax-bandflux (SALT template files) not installed")   # make test installs it
    src = offline_salt_source("salt3")
    assert (src.name, src.version) == ("salt3", "2.0") and offline_salt_source("SALT3") is src
    assert offline_salt_source("salt2").version == "T23" and offline_salt_source("hsiao") is None
    lbda, slow = snia_spectrum(0.5, 10.0, "salt3", x1=-2.0)
    _, fast = snia_spectrum(0.5, 10.0, "salt3", x1=2.0)
    # same peak B magnitude (Tripp-free here: peak_absmag fixed); a broader SN is brighter 10 d later
    band = (lbda > 4000 * 1.5) & (lbda < 5000 * 1.5)
    assert fast[band].sum() > 1.05 * slow[band].sum()
    table = _pop(n=400, source="salt3").draw(3)
    x1, c = np.asarray(table["x1"]), np.asarray(table["c"])
    assert abs(x1.mean()) < 5 * 1.0 / 20 and 0.8 < x1.std() < 1.2 and abs(c.mean()) < 5 * 0.1 / 20


def test_a_cadence_observes_each_sn_at_several_epochs():
    """``population.cadence`` = observer-frame days of the visits: each SN becomes one exposure per visit,
    the same SN (redshift, x1, c, magnitude, host) with its rest-frame phase advanced by Δt / (1 + z)."""
    import tomllib

    from slicersim.campaign.runner import plan_campaign
    from slicersim.campaign.spec import parse_spec
    text = """seed = 3
[population]
kind = "snia"
n = 4
redshift = {distribution = "uniform", min = 0.3, max = 0.9}
phase = {distribution = "uniform", min = -8, max = 0}
mag_scatter = 0.1
cadence = [0, 6, 15]
[observation]
snr = 5
field = "narrow"
"""
    spec = parse_spec(tomllib.loads(text), text=text)
    cat, _ = plan_campaign(spec)
    assert len(cat) == 12 and cat.meta["phase_frame"] == "rest" and str(cat["phase"].unit) == "d"
    assert list(cat["target_id"]) == list(range(12)) and len(set(cat["seed"])) == 12
    first = cat[cat["visit"] == 0]
    no_cadence = parse_spec(tomllib.loads(text.replace("cadence = [0, 6, 15]\n", "")), text=text)
    plain = no_cadence.population.draw(3)
    for col in ("redshift", "phase", "peak_absmag"):         # visit 0 is the SN drawn without a cadence
        np.testing.assert_array_equal(np.asarray(first[col]), np.asarray(plain[col]))
    for visit, day in ((1, 6.0), (2, 15.0)):
        later = cat[cat["visit"] == visit]
        np.testing.assert_array_equal(later["sn_id"], first["sn_id"])
        np.testing.assert_array_equal(later["peak_absmag"], first["peak_absmag"])
        np.testing.assert_allclose(np.asarray(later["phase"]) - np.asarray(first["phase"]),
                                   day / (1 + np.asarray(first["redshift"])), rtol=1e-12)
    assert "cadence" in spec.canonical()["population"] and "cadence" not in no_cadence.canonical()["population"]
    # each visit is the single-target SN at its own phase
    from slicersim.targets import LazuliSupernova
    row = cat[cat["visit"] == 2][0]
    sn = LazuliSupernova(float(row["redshift"]), phase=float(row["phase"]), peak_absmag=float(row["peak_absmag"]))
    flux = spec.population.spectra(cat[cat["visit"] == 2][:1], LBDA)[0]
    np.testing.assert_allclose(np.interp(sn.pointsource.lbda_in, LBDA, flux), sn.pointsource.flux_in, rtol=1e-12)


@pytest.mark.parametrize("cadence, message", [([5, 10], "start at 0"), ([0, 10, 10], "increase strictly"),
                                              ("weekly", "list of 1 to"), ([0, -3], "cadence\\[1\\]"),
                                              ([0, "x"], "cadence\\[1\\]")])
def test_bad_cadences_are_refused_naming_the_key(cadence, message):
    with pytest.raises(ConfigError, match=message):
        _pop(n=3, cadence=cadence)


def test_a_redshift_table_weight_that_is_not_a_number_names_its_line(tmp_path):
    """A z-table weight "abc" was an internal error (NumPy's 'could not convert string to float')."""
    (tmp_path / "zt.csv").write_text("z,weight\n0.1,1\n0.5,abc\n")
    with pytest.raises(ConfigError, match=r"population.redshift.file: .*zt.csv, line 3: weight = 'abc' is not a number"):
        _pop(n=3, redshift={"distribution": "table", "file": str(tmp_path / "zt.csv")})


def test_a_parquet_catalog_with_a_list_column_is_refused_naming_it(tmp_path):
    """A Parquet list column was an internal error further down."""
    import pyarrow as pa
    import pyarrow.parquet as pq
    from slicersim.campaign.population import population_from_spec
    pq.write_table(pa.table({"redshift": [0.3, 0.5], "tags": [[1, 2], [3]]}), tmp_path / "cat.parquet")
    with pytest.raises(ConfigError, match=r"cat.parquet: column tags \(list<.*\) is not a column of numbers or text"):
        population_from_spec({"kind": "catalog", "file": str(tmp_path / "cat.parquet")})
