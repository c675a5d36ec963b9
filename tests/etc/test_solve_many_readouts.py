"""The batch ETC's speed-ups keep its answers: readouts pinned before them (extraction weights below
1e-16 of their bin's largest skipped, chunks of targets sized to their bands, the reference walk's
SNRs computed on demand), and the weight cutoff's effect on the band SNR bounded."""
import numpy as np
import pytest

from slicersim.backends.precision import SINGLE_PRECISION_ERRORS
from slicersim.etc.solve import solve_many
from slicersim.snr.search import candidate_readouts
from slicersim.snr.snr_table import WEIGHT_CUTOFF, band_snr_table_for_models, extraction_weights, template_psf
from slicersim.targets import LazuliTarget

from model_state import LBDA, sloped  # the λ grid [Å] and λ^-1.5 spectrum shared with other tests

#: 12 redshifts × 3 levels [erg/s/cm²/Å at 1 µm] of a λ^-1.5 spectrum, SNR 20 per resolution element in
#: [4000, 6800](1+z) Å, built-in CBE configuration: bright (walk on n), medium and faint (walk on ramps)
Z = np.round(np.linspace(0.1, 1.5, 12), 4)
LEVELS = (3e-17, 3e-18, 3e-19)
FLUXES = np.array([sloped(level) for z in Z for level in LEVELS])
RANGES = np.array([(4000.0 * (1 + z), 6800.0 * (1 + z)) for z in Z for level in LEVELS])

# (n, m, d, nramps, snr_per_bin) of each target, computed before the speed-ups (float64 kernel; the
# NumPy twin gave the same readouts, and precision="single" too)
PINNED_REFERENCE = [
    (25, 1, 0, 1, 12.826381512936763),
    (24, 8, 0, 1, 13.569206004324496),
    (64, 8, 0, 5, 12.97026633177934),
    (20, 1, 0, 1, 13.271024289667615),
    (35, 4, 0, 1, 13.615370738523989),
    (54, 8, 0, 4, 13.121821976395259),
    (17, 1, 0, 1, 13.577666054348882),
    (27, 4, 0, 1, 13.32894558743212),
    (54, 8, 0, 3, 13.336687965566998),
    (14, 1, 0, 1, 12.719015939163365),
    (23, 4, 0, 1, 13.304471061232858),
    (64, 8, 0, 2, 13.422939587754831),
    (13, 1, 0, 1, 12.90930587654391),
    (20, 4, 0, 1, 13.03189690806916),
    (54, 8, 0, 2, 13.19724771990927),
    (13, 1, 0, 1, 13.675104550879416),
    (19, 4, 0, 1, 13.248374786240696),
    (51, 8, 0, 2, 13.464507599403717),
    (12, 1, 0, 1, 12.967894271920851),
    (18, 4, 0, 1, 13.134142978737472),
    (47, 8, 0, 2, 13.246124372381107),
    (12, 1, 0, 1, 13.091059723383571),
    (17, 4, 0, 1, 12.734469531592014),
    (47, 8, 0, 2, 13.448129162971457),
    (12, 1, 0, 1, 12.970440513737762),
    (17, 4, 0, 1, 12.721583708344314),
    (47, 8, 0, 2, 13.445578586858815),
    (13, 1, 0, 1, 13.844519544231108),
    (18, 4, 0, 1, 13.18001569968796),
    (47, 8, 0, 2, 13.29220543813115),
    (13, 1, 0, 1, 13.386896968604956),
    (19, 4, 0, 1, 13.484230715626156),
    (51, 8, 0, 2, 13.66519137547531),
    (13, 1, 0, 1, 12.792654648326968),
    (20, 4, 0, 1, 13.630684936683947),
    (54, 8, 0, 2, 13.648892370680729),
]
PINNED_EXACT = [
    (26, 1, 0, 1, 13.280125230009208),
    (23, 8, 0, 1, 13.217868350329736),
    (57, 8, 0, 6, 13.249072868098603),
    (20, 1, 0, 1, 13.271024289667615),
    (17, 8, 0, 1, 13.3524387957153),
    (55, 8, 0, 4, 13.267833811882241),
    (17, 1, 0, 1, 13.577666054348882),
    (27, 4, 0, 1, 13.32894558743212),
    (53, 8, 0, 3, 13.189464554208211),
    (15, 1, 0, 1, 13.630379318687178),
    (23, 4, 0, 1, 13.304471061232858),
    (63, 8, 0, 2, 13.304293196815225),
    (14, 1, 0, 1, 13.92398668210941),
    (21, 4, 0, 1, 13.517973182270795),
    (54, 8, 0, 2, 13.19724771990927),
    (13, 1, 0, 1, 13.675104550879416),
    (19, 4, 0, 1, 13.248374786240696),
    (50, 8, 0, 2, 13.3078718072684),
    (13, 1, 0, 1, 14.112100530818703),
    (19, 4, 0, 1, 13.705035278244658),
    (47, 8, 0, 2, 13.246124372381107),
    (13, 1, 0, 1, 14.25820577517463),
    (9, 8, 0, 1, 13.308749389508892),
    (46, 8, 0, 2, 13.273150927889915),
    (13, 1, 0, 1, 14.144028084329406),
    (9, 8, 0, 1, 13.304297712267573),
    (46, 8, 0, 2, 13.269352571787485),
    (13, 1, 0, 1, 13.844519544231108),
    (19, 4, 0, 1, 13.779155606798568),
    (47, 8, 0, 2, 13.29220543813115),
    (13, 1, 0, 1, 13.386896968604956),
    (19, 4, 0, 1, 13.484230715626156),
    (49, 8, 0, 2, 13.335205321701793),
    (14, 1, 0, 1, 13.890913043540952),
    (10, 8, 0, 1, 13.602273774914236),
    (52, 8, 0, 2, 13.34047794848883),
]


def _rows(table):
    return [(int(r["n"]), int(r["m"]), int(r["d"]), int(r["nramps"])) for r in table]


def _check_pinned(table, pinned, rtol):
    assert _rows(table) == [p[:4] for p in pinned]
    np.testing.assert_allclose(table["snr_per_bin"], [p[4] for p in pinned], rtol=rtol, atol=0)


@pytest.mark.parametrize("search, pinned", [("reference", PINNED_REFERENCE), ("exact", PINNED_EXACT)])
def test_readouts_identical_to_those_before_the_speed_ups(search, pinned):
    table = solve_many(LBDA, FLUXES, 20.0, RANGES, search=search, precision="double")
    _check_pinned(table, pinned, rtol=1e-12)        # measured: 4.4e-16 (the weights skipped)


@pytest.mark.slow
@pytest.mark.parametrize("search, pinned", [("reference", PINNED_REFERENCE), ("exact", PINNED_EXACT)])
def test_numpy_twin_readouts_identical_to_those_before_the_speed_ups(search, pinned):
    table = solve_many(LBDA, FLUXES, 20.0, RANGES, search=search, backend="numpy")
    _check_pinned(table, pinned, rtol=1e-12)


@pytest.mark.needs_opencl_device
@pytest.mark.parametrize("search, pinned", [("reference", PINNED_REFERENCE), ("exact", PINNED_EXACT)])
def test_single_precision_same_readouts_snr_within_the_dial_tolerance(search, pinned):
    table = solve_many(LBDA, FLUXES, 20.0, RANGES, search=search, precision="single")
    assert table.meta["precision"] == "single"
    # the dial's tolerance is on the band variance; the SNR moves by half of it (measured 8e-8)
    _check_pinned(table, pinned, rtol=SINGLE_PRECISION_ERRORS["batch_etc"].tolerance / 2)


@pytest.mark.parametrize("search", ["reference", "exact"])
def test_target_order_and_chunk_size_do_not_change_the_answers(search):
    """Chunks group targets by band (any input order) and fit ``max_bytes``: a shuffled batch and
    one target per chunk give the same table row for row."""
    order = np.random.default_rng(7).permutation(len(FLUXES))[:12]
    whole = solve_many(LBDA, FLUXES[order], 20.0, RANGES[order], search=search, precision="double")
    pinned = PINNED_REFERENCE if search == "reference" else PINNED_EXACT
    _check_pinned(whole, [pinned[i] for i in order], rtol=1e-12)
    one_by_one = solve_many(LBDA, FLUXES[order], 20.0, RANGES[order], search=search, precision="double",
                            max_bytes=1)
    assert _rows(one_by_one) == _rows(whole)
    np.testing.assert_array_equal(one_by_one["snr_per_bin"], whole["snr_per_bin"])


# ----------------------------------------------------------------------------- the weight cutoff
@pytest.fixture(scope="module")
def bright_and_faint():
    """Single-target simulations of a bright (near the shortest readouts) and a faint source."""
    sims = []
    for level in (3e-16, 3e-19):
        t = LazuliTarget(LBDA, sloped(level))
        sims.append(t.simulation)
    return sims


def test_extraction_weights_zero_only_the_negligible_ones(bright_and_faint):
    psf = template_psf(bright_and_faint[0])
    full, cut = psf ** 2, extraction_weights(psf)
    rowmax = full.max(axis=1, keepdims=True)
    dropped = (cut == 0) & (full != 0)
    assert dropped.any()                                        # the red bins keep most cells, the blue few
    assert np.all(full[dropped] < WEIGHT_CUTOFF * np.broadcast_to(rowmax, full.shape)[dropped])
    np.testing.assert_array_equal(cut[~dropped], full[~dropped])      # the others untouched, bit for bit
    # what a bin loses: at most ncell × 1e-16 of its largest weight
    assert np.all((full - cut).sum(axis=1) <= psf.shape[1] * WEIGHT_CUTOFF * rowmax[:, 0])
    assert extraction_weights(np.zeros((2, 3))).tolist() == [[0.0] * 3] * 2


def _snr_tables(sim, band, psf2):
    model = sim.extraction_model
    cand = candidate_readouts(sim.detector.min_group, sim.detector.max_group or 64, sim.detector.nmd[2])
    return band_snr_table_for_models(sim, [model], np.array([band]), cand, backend="numpy", psf2=psf2)


@pytest.mark.parametrize("which", [0, 1], ids=["bright", "faint"])
def test_weight_cutoff_changes_the_band_snr_by_less_than_1e_13(bright_and_faint, which):
    """Every readout's single-ramp band SNR with the weights skipped against all weights; a cutoff that
    drops weight that matters (1e-6 of a bin's largest) moves it far beyond the bound."""
    sim = bright_and_faint[which]
    psf = np.sqrt(sim.extraction_model.psf2)
    grid = sim.lbda
    band = [int(np.searchsorted(grid, 5000.0)), int(np.searchsorted(grid, 15000.0))]
    full = _snr_tables(sim, band, psf ** 2)
    ok = np.isfinite(full) & (full > 0)
    assert ok.sum() > 100
    rel = np.abs(_snr_tables(sim, band, extraction_weights(psf)) / full - 1)[ok]
    assert rel.max() < 1e-13
    coarse = np.abs(_snr_tables(sim, band, extraction_weights(psf, rel_cutoff=1e-6)) / full - 1)[ok]
    assert coarse.max() > 1e-10                               # the bound has teeth
