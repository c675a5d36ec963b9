"""The summary of a campaign against its truth (summary.ecsv, report.md, figures).

The band comparison is checked on synthetic spectra with known noise; the report on a fake campaign
(conftest.fake_campaign: real Lazuli SN Ia truths, spectra = truth + Gaussian noise of the ETC
variance, written without simulating ramps).  The real chain (ramps → reduce --spectra → summary) is
tested in test_reduce_dataset.py on the small layout.
"""
from __future__ import annotations

import numpy as np
import pytest
from astropy.table import Table

from slicersim.errors import DatasetError
from slicersim.io.target_truth import TargetTruth
from slicersim.reduction.summary import band_overlap, compare_band, rebin, redshift_bins

from conftest import fake_campaign


def _flat_truth(n=200, rate=50.0, var=4.0):
    lbda = 5000.0 + 10.0 * np.arange(n)
    return TargetTruth({"redshift": 0.5}, lbda, np.full(n, 10.0), np.full(n, 1e-17), np.full(n, rate),
                       etc_variance=np.full(n, var))


def test_rebin_conserves_the_integral_and_band_overlap_counts_partial_bins():
    edges = np.linspace(0.0, 10.0, 11)
    values = np.arange(10.0)
    coarse = rebin(edges, values, np.array([0.0, 2.5, 7.5, 10.0]))
    assert coarse.sum() == pytest.approx(values.sum())
    assert coarse[0] == pytest.approx(0 + 1 + 0.5 * 2)                 # half of bin [2, 3]
    assert band_overlap(edges, 2.5, 4.0).tolist() == [0, 0, 0.5, 1, 0, 0, 0, 0, 0, 0]


def test_compare_band_is_unbiased_with_unit_pulls_and_chi2():
    truth = _flat_truth()
    edges = truth.edges()[::4]                                          # 4 native bins per output bin
    true = rebin(truth.edges(), truth.rate, edges)
    var = rebin(truth.edges(), truth.etc_variance, edges)
    rng = np.random.default_rng(1)
    res = [compare_band(edges, true + rng.normal(size=true.size) * np.sqrt(var), var, truth, (5115.0, 6515.0))
           for _ in range(400)]
    ratio = np.array([r["band_flux_ratio"] for r in res])
    pull = np.array([r["pull"] for r in res])
    chi2 = np.array([r["chi2"] for r in res])
    err = res[0]["band_flux_ratio_error"]
    # band 1400 Å: 140 native bins of 50 e-/s, σ² = 140 × 4 → error √560 / 7000
    assert err == pytest.approx(np.sqrt(560.0) / 7000.0, rel=1e-9)
    assert abs(ratio.mean() - 1) < 5 * err / np.sqrt(ratio.size)
    assert abs(pull.std() - 1) < 0.1 and abs(pull.mean()) < 5 / np.sqrt(pull.size)
    assert abs(chi2.mean() - 1) < 0.05
    assert res[0]["snr_etc"] == pytest.approx(7000.0 / np.sqrt(560.0))
    assert not res[0]["partial"]
    # a spectrum 2 % high: ratio 1.02, pulls of 0.02 / err
    high = compare_band(edges, 1.02 * true, var, truth, (5115.0, 6515.0))
    assert high["band_flux_ratio"] == pytest.approx(1.02) and high["pull"] == pytest.approx(0.02 / err)
    # a band reaching past the spectrum is partial
    assert compare_band(edges, true, var, truth, (4900.0, 6515.0))["partial"]


def test_redshift_bins_mean_and_error():
    z = np.array([0.1, 0.2, 0.3, 0.9, 1.0, 1.1, np.nan])
    v = np.array([1.0, 2.0, 3.0, 10.0, 10.0, 10.0, 5.0])
    b = redshift_bins(z, v, nbins=2)
    assert b["n"].tolist() == [3, 3] and b["mean"].tolist() == [2.0, 10.0]
    assert b["error"][0] == pytest.approx(1.0 / np.sqrt(3)) and b["error"][1] == 0.0


@pytest.fixture(scope="module")
def reduced_campaign(tmp_path_factory):
    """The fake campaign (4 SNe Ia, z 0.3–1.05), its reduction and their report."""
    from slicersim.reduction.report import campaign_report
    root = tmp_path_factory.mktemp("fake")
    dataset, red, truths = fake_campaign(root)
    return root, truths, campaign_report(dataset, root / "rep", reduced=red)


def test_report_of_a_reduced_campaign(reduced_campaign):
    from slicersim.reduction.report import FIGURES
    tmp_path, truths, res = reduced_campaign
    table = Table.read(res["summary"], format="ascii.ecsv")
    assert len(table) == 4 and list(table["target_id"]) == [0, 1, 2, 3]
    assert table["position_error"].unit == "arcsec" and table["t_reduce"].unit == "s"
    for row in table:
        truth = truths[int(row["target_id"])]
        assert row["redshift"] == pytest.approx(truth.attrs["redshift"]) and row["phase"] == 2.0
        assert abs(row["band_flux_ratio"] - 1) < 5 * row["band_flux_ratio_error"]
        assert 0 < row["band_flux_ratio_error"] < 0.05
        assert abs(row["pull"] - (row["band_flux_ratio"] - 1) / row["band_flux_ratio_error"]) < 1e-9
        assert 0.6 < row["chi2"] < 1.5 and row["chi2_fit"] == 1.01
        # errors that are the ETC's: reported SNR = ETC SNR; measured within the χ² scatter
        assert row["snr_reported"] == pytest.approx(row["snr_etc"], rel=0.05)
        assert row["snr_measured"] == pytest.approx(row["snr_etc"], rel=0.3)
        assert row["position_error"] == pytest.approx(0.5 * truth.attrs["cell_scale"])
        assert row["t_simulate"] == 10.0 + row["target_id"] and row["t_reduce"] == 5.0
        assert row["band_lo"] == pytest.approx(4000 * (1 + row["redshift"]))
        assert "simulated" not in row["flags"]
    for name in FIGURES:
        assert (tmp_path / "rep" / name).stat().st_size > 10_000
    text = (tmp_path / "rep" / "report.md").read_text()
    assert "bias_vs_redshift.png" in text and "| z bin |" in text and "band flux / input: mean" in text


def test_report_without_a_reduction_uses_the_simulated_spectra(tmp_path):
    from slicersim.reduction.report import campaign_report
    dataset, _, _ = fake_campaign(tmp_path, redshifts=(0.4, 1.0), reduced=False)
    table = campaign_report(dataset, tmp_path / "rep")["table"]
    assert all("simulated" in f for f in table["flags"])
    assert np.all(np.abs(table["pull"]) < 5) and np.all(np.abs(np.asarray(table["band_flux_ratio"]) - 1) < 0.1)
    etc = np.asarray(table["snr_etc"], float)                  # the simulation's own errors: ETC SNR ± noise
    assert np.all(np.abs(np.asarray(table["snr_reported"]) / etc - 1) < 5 / etc)


def test_bad_inputs_are_refused(tmp_path):
    from slicersim.reduction.report import campaign_report
    dataset, red, _ = fake_campaign(tmp_path, redshifts=(0.5,))
    with pytest.raises(DatasetError, match="not a reduction directory"):
        campaign_report(dataset, tmp_path / "rep", reduced=dataset)
    with pytest.raises(DatasetError, match="reduction directory: give the campaign"):
        campaign_report(red, tmp_path / "rep")
    with pytest.raises(DatasetError, match="no such dataset directory"):
        campaign_report(tmp_path / "nowhere", tmp_path / "rep")
    with pytest.raises(DatasetError, match="does not exist"):
        campaign_report(dataset, tmp_path / "a" / "b")
    (tmp_path / "file").write_text("x")
    with pytest.raises(DatasetError, match="is a file"):
        campaign_report(dataset, tmp_path / "file")


def test_a_damaged_reduced_file_is_flagged_and_the_others_reported(tmp_path):
    from slicersim.reduction.summary import summarize
    dataset, red, _ = fake_campaign(tmp_path, redshifts=(0.5, 0.9))
    (red / "products" / "t0000001" / "reduced.h5").write_bytes(b"not hdf5")
    table = summarize(dataset, red)
    assert table["flags"][1] == "unreadable" and np.isnan(table["band_flux_ratio"][1])
    assert np.isfinite(table["band_flux_ratio"][0]) and table["flags"][0] == ""


def test_report_of_a_streaming_campaign_reads_its_own_reduced_products(tmp_path):
    """A streaming campaign (`[products] reduce = true`) holds each target's reduced.h5 in its own products:
    `campaign report DATASET` (no --reduced) compares those, not the simulated spectra."""
    import shutil

    from slicersim.io.dataset import Dataset
    from slicersim.reduction.report import campaign_report
    dataset, red, truths = fake_campaign(tmp_path, redshifts=(0.4, 0.9))
    cat = Table.read(dataset / "catalog.ecsv", format="ascii.ecsv")
    cat["reduced_product"] = [f"products/t{tid:07d}/reduced.h5" for tid in cat["target_id"]]
    for tid in cat["target_id"]:                       # the reduction moved into the dataset, as streaming writes it
        shutil.copy(red / f"products/t{tid:07d}/reduced.h5", dataset / f"products/t{tid:07d}/reduced.h5")
    Dataset(dataset).write_catalog(cat)
    table = Table.read(campaign_report(dataset, tmp_path / "rep")["summary"], format="ascii.ecsv")
    for row in table:
        assert "simulated" not in row["flags"] and row["chi2_fit"] == 1.01, row["flags"]
        assert abs(row["band_flux_ratio"] - 1) < 5 * row["band_flux_ratio_error"]
