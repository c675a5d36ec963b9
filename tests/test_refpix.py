"""Reference pixels (mask, bias map) and the JWST-style reference-pixel correction."""
import numpy as np
import pytest

from slicersim.backends.correlated_noise import CorrelatedNoise
from slicersim.errors import EffectsError
from slicersim.physics.correlated_noise import CorrelatedNoiseParameters, ReadoutGeometry, group_mean_variance
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


def test_removes_correlated_noise():
    """Full H4RG-10 geometry (32 outputs, τ = 4.93 µs), NGHXRG default amplitudes, MACC(2,8,0)
    groups.  Expected removed fraction 1 − E[after]/E[before], E[before] from the model
    (group_mean_variance, exact) and E[after] from two ramps (stable: ±1 %; the removable slow
    part fluctuates by ±40 % from ramp to ramp, so a per-ramp ratio is not used).

    Measured: E[after] = 0.98 e-² of E[before] = 5.70 e-²: 83 % removed, short of the issue's
    90 %.  The bound below shows no reference-pixel correction can reach 90 % here: the side
    reference pixels are read at the first 4 pixel times of every row (every output starts its
    row with them), so (1) each output's own noise (u_pink + ACN: 0.45 e-²) is seen by no
    reference pixel, and (2) the common 1/f above the row-sampling Nyquist frequency
    1/(2 t_row) = 724 Hz aliases (0.44 e-² in a group mean): at most 84.3 % is removable.
    Asserted: the bound is < 90 % (if the model changes so that 90 % becomes reachable, this
    fails and the goal must be met) and the correction reaches ≥ 97 % of the bound."""
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
