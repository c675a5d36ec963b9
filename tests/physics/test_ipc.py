"""IPC (physics/ipc.py): kernel, flux conservation, α from the autocorrelation of a flat."""
import math

import numpy as np
import pytest

from slicersim.errors import EffectsError
from slicersim.physics import ipc


def test_default_kernel():
    k = ipc.ipc_kernel()
    assert k.shape == (3, 3) and k.dtype == np.float64
    assert k[1, 1] == pytest.approx(1 - 4 * 0.016 - 4 * 0.002)
    assert k[0, 1] == k[1, 0] == k[1, 2] == k[2, 1] == 0.016
    assert k[0, 0] == k[2, 2] == 0.002
    assert k.sum() == pytest.approx(1.0, abs=1e-15)


def test_flux_conservation_and_stencil_orientation():
    g = np.random.default_rng(0)
    img = np.zeros((40, 50))
    img[1:-1, 1:-1] = g.uniform(0, 1000, (38, 48))          # nothing on the edge pixels
    k = ipc.ipc_kernel()
    out = ipc.apply_ipc(img, k)
    assert out.sum() == pytest.approx(img.sum(), rel=1e-13)
    # an asymmetric user kernel: charge of a point moves by the kernel offsets
    user = np.zeros((3, 3))
    user[1, 1], user[2, 1], user[1, 0] = 0.9, 0.05, 0.03     # 5 % down (+y), 3 % left (−x)
    point = np.zeros((5, 5))
    point[2, 2] = 100.0
    out = ipc.apply_ipc(point, user)
    assert out[2, 2] == pytest.approx(90.0) and out[3, 2] == pytest.approx(5.0) and out[2, 1] == pytest.approx(3.0)
    assert out.sum() == pytest.approx(98.0)                   # Σ K < 1 loses charge
    # zero outside the image: a corner pixel keeps only the in-image shares
    corner = np.zeros((4, 4))
    corner[0, 0] = 1.0
    assert ipc.apply_ipc(corner, k).sum() == pytest.approx(k[1:, 1:].sum())
    # batched images (..., ny, nx) equal image by image
    stack = g.normal(size=(3, 16, 16))
    np.testing.assert_allclose(ipc.apply_ipc(stack, k)[1], ipc.apply_ipc(stack[1], k))


def test_alpha_recovered_from_poisson_flat():
    """A Poisson flat (10⁴ e-) through the default kernel: the autocorrelation estimator gives α
    and α_d back within 3σ of its Monte Carlo error σ_α ≈ (c/2)/√(2N) (lag-1 sample
    correlations of N pairs have variance 1/N; two axes averaged; dα/dr ≈ c/2, c = K centre)."""
    g = np.random.default_rng(42)
    n = 2048
    flat = g.poisson(1e4, (n, n)).astype(float)
    k = ipc.ipc_kernel(0.016, 0.002)
    alpha, alpha_d = ipc.ipc_alpha_from_autocorrelation(ipc.apply_ipc(flat, k))
    sigma = k[1, 1] / 2 / math.sqrt(2 * (n - 2) ** 2)
    assert abs(alpha - 0.016) < 3 * sigma
    assert abs(alpha_d - 0.002) < 3 * sigma
    # no IPC: α ≈ 0
    a0, _ = ipc.ipc_alpha_from_autocorrelation(flat)
    assert a0 < 3 * sigma
    # read noise added after IPC dilutes the correlation unless its variance is given
    noisy = ipc.apply_ipc(flat, k) + g.normal(0, 50.0, flat.shape)
    a_biased, _ = ipc.ipc_alpha_from_autocorrelation(noisy)
    a_fixed, _ = ipc.ipc_alpha_from_autocorrelation(noisy, noise_variance=2500.0)
    assert a_biased < 0.016 * 0.9 and abs(a_fixed - 0.016) < 4 * sigma


def test_kernel_autocorrelation_matches_brute_force():
    from scipy.signal import correlate2d
    for a, ad in ((0.01, 0.0), (0.02, 0.003), (0.03, 0.001)):
        k = ipc.ipc_kernel(a, ad)
        full = correlate2d(k, k)                               # 5×5, zero lag at [2, 2]
        near, diag = ipc.kernel_autocorrelation(k)
        assert near == pytest.approx(full[2, 3] / full[2, 2], rel=1e-12)
        assert diag == pytest.approx(full[3, 3] / full[2, 2], rel=1e-12)


@pytest.mark.parametrize("kernel", [np.ones((2, 2)) / 8, np.full((3, 3), 0.12),
                                    [[0, 0, 0], [0, 1.0, -0.01], [0, 0, 0]],
                                    [[0, 0, 0], [0, float("nan"), 0], [0, 0, 0]], "abc"])
def test_bad_kernels_rejected(kernel):
    with pytest.raises(EffectsError):
        ipc.ipc_kernel(kernel=kernel)


def test_bad_alpha_rejected():
    for a, ad in ((-0.01, 0.0), (0.2, 0.1), (0.0, float("inf"))):
        with pytest.raises(EffectsError, match="alpha"):
            ipc.ipc_kernel(a, ad)
    assert ipc.ipc_kernel(kernel=np.eye(3) / 3).sum() == pytest.approx(1.0)
    user = ipc.IPCParameters(kernel=(np.eye(3) / 3).tolist())
    np.testing.assert_array_equal(user.matrix(), np.eye(3) / 3)
