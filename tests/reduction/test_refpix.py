"""Reference pixels (mask, bias map) and the JWST-style reference-pixel correction."""
import numpy as np
import pytest

from slicersim.backends.correlated_noise import CorrelatedNoise
from slicersim.errors import EffectsError
from slicersim.physics.correlated_noise import (CorrelatedNoiseParameters, ReadoutGeometry, group_combination_variance,
                                                group_mean_variance, ols_slope_weights, picture_frame_template)
from slicersim.physics.reference_pixels import ReferencePixelParameters, bias_map, reference_pixel_mask
from slicersim.reduction.refpix import refpix_correct


def test_mask():
    m = reference_pixel_mask((4096, 4096))
    assert m[:4].all() and m[-4:].all() and m[:, :4].all() and m[:, -4:].all()
    assert not m[4:-4, 4:-4].any()
    assert m.sum() == 4096**2 - 4088**2
    assert reference_pixel_mask((16, 16), border=0).sum() == 0


def test_bias_map_statistics_and_keying():
    p = ReferencePixelParameters(n_outputs=8, output_offset=100.0, pixel_offset=50.0)
    b = bias_map(3, (256, 256), p)
    assert b.dtype == np.float32 and b.shape == (256, 256)
    np.testing.assert_array_equal(b, bias_map(3, (256, 256), p))
    assert not np.array_equal(b, bias_map(4, (256, 256), p))
    per_out = b.reshape(256, 8, 32)
    resid = per_out - per_out.mean(axis=(0, 2), keepdims=True)
    # 65536 pixels: the rms of the fixed pattern within 2 % (MC error 0.3 %)
    assert resid.std() == pytest.approx(50.0, rel=0.02)
    # the same pixel gets the same value in a bigger detector's first rows (index = pixel)
    np.testing.assert_array_equal(bias_map(3, (300, 256), p)[:256], b)


def test_pedestal_removed_exactly():
    """A per-output, per-group offset and a row-common drift are removed to float precision."""
    rng = np.random.default_rng(0)
    ny, nx, nout = 64, 128, 4
    sci = np.zeros((1, 3, ny, nx))
    sci += np.repeat(rng.normal(0, 10, (3, nout)), nx // nout, axis=1)[None, :, None, :]
    out = refpix_correct(sci, n_outputs=nout)
    assert np.abs(out).max() < 1e-9
    slope = np.linspace(-5, 5, ny)[None, None, :, None] * np.ones((1, 3, ny, nx))
    out = refpix_correct(slope, n_outputs=nout, use_side_ref_pixels=True)
    inner = out[..., 8:-8, :]                      # the running median is exact on a linear ramp
    assert np.abs(inner).max() < 1e-9


@pytest.mark.slow
def test_removes_correlated_noise():
    """Full H4RG-10 geometry (32 outputs, τ = 4.93 µs), NGHXRG default amplitudes, MACC(2,8,0)
    groups.  Expected removed fraction 1 − E[after]/E[before], E[before] from the model
    (group_mean_variance, exact) and E[after] from two ramps (stable: ±1 %; the removable slow
    part fluctuates by ±40 % from ramp to ramp, so a per-ramp ratio is not used).

    Measured: E[after] = 0.98 e-² of E[before] = 5.70 e-²: 83 % removed in group means, short of
    the issue's 90 % (in slopes: test_removes_correlated_noise_in_slopes).  Reference quantity
    (an estimate, not a strict bound): the side reference pixels are read at the first 4 pixel
    times of every row, so the common 1/f above the row-sampling Nyquist frequency 1/(2 t_row) =
    724 Hz aliases (0.44 e-² in a group mean), and each output's own noise (u_pink + ACN: 0.45 e-²)
    reaches only that output's top and bottom reference rows (its slow part is removed there:
    36 ± 1 % of it in group means, benchmarks/refpix_slopes.py --own-only), giving 84.3 % if
    none of the own noise were removed.  Asserted as a regression: that estimate is < 90 % and
    the correction reaches ≥ 97 % of it."""
    from slicersim.physics.correlated_noise import _integral, pink_psd
    shape = (4096, 4096)
    mask = reference_pixel_mask(shape)
    p = CorrelatedNoiseParameters()
    g = ReadoutGeometry.from_params(p, shape, 2.83)
    after = []
    for ramp in range(2):
        b = CorrelatedNoise(p, shape, (2, 8, 0), 2.83, 21).block(ramp, 0, 4096)
        c = refpix_correct(b[None])[0]
        after.append(float(np.mean(c[:, ~mask] ** 2)))
    before = group_mean_variance(8, p, g)
    assert before == pytest.approx(5.70, rel=0.01)
    invisible = group_mean_variance(8, p, g, "own")
    aliased = _integral(lambda f: pink_psd(f, p.c_pink, g, p.f_min), 0.5 / g.row_time, g.f_nyquist, 4000, True) / 8
    bound = 1 - (invisible + aliased) / before
    removed = 1 - np.mean(after) / before
    assert bound < 0.90, bound
    assert removed >= 0.97 * bound, (removed, bound, after)


@pytest.mark.slow
def test_removes_correlated_noise_in_slopes():
    """The same correction judged on what a pipeline delivers: the OLS slope of the group means
    against group time (the rate image), MACC(16,8,0), full H4RG-10 geometry, NGHXRG default
    amplitudes, light-sensitive pixels.  E[before] from the model (group_combination_variance
    with ols_slope_weights: 6.119e-5 (e-/s)², converged to 1e-4; 240 ramps of the generator,
    rows 2000:2016, give 6.12 ± 0.39e-5), E[after] from ramps (per-ramp scatter 7 %).

    Measured (ramps 0–9, `benchmarks/refpix_slopes.py --groups 16 --ramps 10`): E[after] =
    5.79 ± 0.13e-6 (e-/s)²: **90.5 ± 0.2 % removed** in slopes, while the group means of the same
    ramps lose 82.6 ± 0.05 % (E[after] 0.992 of 5.701 e-²).  The slow common drift dominates the
    slope noise and is what the reference pixels see; the fast part that none sees averages down.
    At MACC(64,8,0) (ramps 0–3) only 79.7 ± 0.7 % goes (E[after] 9.41 ± 0.34e-8 of 4.641e-7):
    the model's 1/f stops at f_min = 1 mHz, so a 24-min ramp sees less slow drift (a 100-ramp
    generator check gives 5.25 ± 0.37e-7, 1.6 σ above the model).

    This test: ramps 0–2 (54 s on a shared 2-core VM), 90.4 % in slopes, 82.6 % in group means;
    asserted within 3 σ of the 10-ramp values (σ of a 3-ramp mean: 0.38 % in slopes, 0.1 % in
    group means).
    The model is checked against group_mean_variance (w = (1,)) on the way.  The read-domain
    "bound" of the test above is no bound: on own noise alone the correction removes 36 ± 1 % of
    the group-mean and 69 ± 6 % of the slope variance (`--own-only`; the top/bottom reference
    rows see the slow part of each output's own noise)."""
    shape, nmd, tframe = (4096, 4096), (16, 8, 0), 2.83
    inner = ~reference_pixel_mask(shape)
    p = CorrelatedNoiseParameters()
    g = ReadoutGeometry.from_params(p, shape, tframe)
    assert group_combination_variance([1.0], (1, 8, 0), p, g) == pytest.approx(group_mean_variance(8, p, g), rel=1e-3)
    ey, ex = picture_frame_template(shape)
    pf_ms = float(np.mean((ey[4:-4, None] + ex[None, 4:-4]) ** 2))      # picture frame on the inner pixels
    w = ols_slope_weights(nmd, tframe)
    slope_before = group_combination_variance(w, nmd, p, g, picture_frame_ms=pf_ms)
    mean_before = group_combination_variance([1.0], (1, 8, 0), p, g, picture_frame_ms=pf_ms)
    assert slope_before == pytest.approx(6.119e-5, rel=1e-3)
    gen = CorrelatedNoise(p, shape, nmd, tframe, 21)
    slope_after, mean_after = [], []
    for ramp in range(3):
        b = gen.block(ramp, 0, shape[0])
        slope = np.zeros(shape)
        for k in range(nmd[0]):
            c = refpix_correct(b[None, k:k + 1])[0, 0]
            slope += w[k] * c
            mean_after.append(float(np.mean(c[inner] ** 2)))
        slope_after.append(float(np.mean(slope[inner] ** 2)))
        del b
    removed_slope = 1 - np.mean(slope_after) / slope_before
    removed_mean = 1 - np.mean(mean_after) / mean_before
    assert removed_slope == pytest.approx(0.905, abs=0.012), (removed_slope, slope_after)
    assert removed_mean == pytest.approx(0.826, abs=0.003), (removed_mean, mean_after)


def test_bad_input():
    with pytest.raises(EffectsError, match="4-D"):
        refpix_correct(np.zeros((3, 64, 64)))
    with pytest.raises(EffectsError, match="divisible"):
        refpix_correct(np.zeros((1, 1, 64, 100)), n_outputs=32)
    with pytest.raises(EffectsError, match="pixel_offset"):
        ReferencePixelParameters(pixel_offset=-1.0)
    with pytest.raises(EffectsError, match="border"):
        ReferencePixelParameters(border=-2)
    with pytest.raises(EffectsError, match="too small"):
        reference_pixel_mask((6, 6), border=4)


def _loop_refpix(frame, n_outputs, border, side_smoothing_length):
    """JWST's two steps written out pixel by pixel (the documentation's order), for one frame."""
    from scipy.ndimage import median_filter
    out = np.array(frame, np.float64)
    ny, nx = out.shape
    ncol = nx // n_outputs
    ref = np.concatenate([out[:border], out[-border:]])
    for o in range(n_outputs):
        for par in (0, 1):
            cols = [x for x in range(o * ncol, (o + 1) * ncol) if x % 2 == par]
            out[:, cols] -= ref[:, cols].mean()
    side = np.concatenate([out[:, :border], out[:, -border:]], axis=1).mean(axis=1)
    return out - median_filter(side, size=side_smoothing_length, mode="nearest")[:, None]


def test_the_fit_s_reference_terms_come_from_the_reference_pixels_alone():
    """Issue 30: the ramp fit computed its reference-pixel terms by correcting every full frame in float64
    (16 CPU-s of a 38-group Lazuli ramp); it now reads them off the border pixels (refpix_offsets).  On
    random frames with a superbias map: frame − bias − terms equals the documented algorithm to 1e-9 DN."""
    from slicersim.reduction.ramp_fit import _refpix_terms
    from slicersim.reduction.refpix import refpix_offsets
    rng = np.random.default_rng(3)
    ny, nx, n = 40, 64, 3
    sci = rng.normal(1000, 30, (1, n, ny, nx)) + rng.normal(0, 5, (1, n, 1, nx))
    bias = rng.normal(200, 10, (ny, nx))

    class Source:
        shape = sci.shape
        rows = None                      # every row (a file of some rows lists its ranges)

        def frame(self, i, g, y0=0, y1=None):
            return sci[i, g, y0:y1]
    kw = dict(n_outputs=4, border=4, side_smoothing_length=5)
    col, row = _refpix_terms(Source(), bias, kw)
    for g in range(n):
        want = _loop_refpix(sci[0, g] - bias, 4, 4, 5)
        np.testing.assert_allclose(sci[0, g] - bias - col[0, g][None, :] - row[0, g][:, None], want, atol=1e-9)
        np.testing.assert_allclose(refpix_correct(sci[:, g:g + 1] - bias, **kw)[0, 0], want, atol=1e-9)
    with pytest.raises(EffectsError, match="not divisible"):
        _refpix_terms(Source(), None, dict(n_outputs=5))
    c, r = refpix_offsets(np.zeros((8, nx)), np.ones((ny, 8)), n_outputs=4, use_side_ref_pixels=False)
    assert not c.any() and not r.any()
