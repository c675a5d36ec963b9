"""band_variance_table: OpenCL kernel vs NumPy twin vs a plain-Python reference.

Tolerances
----------
* NumPy twin vs plain-Python loop reference: rtol 1e-13.  Both evaluate the
  same correctly rounded IEEE operations; only the order of the sum over the
  (<= 10) aperture cells differs, so the relative difference is a few ulp
  (~1e-15).  All inputs are positive, so there is no cancellation.
* OpenCL vs NumPy: rtol 1e-12 (the required agreement).  OpenCL fp64
  division is correctly rounded and no fast-math options are used; the
  kernel may contract ``A + B*Q`` into an FMA and sums cells sequentially,
  so differences are again a few ulp times the number of terms (< 1e-14).
* Chunking: each (target, candidate) value is computed by the same
  operations in the same order whatever the chunk size, so the results
  must be bit-identical (exact equality).
* nvalid and the positions of +inf / exact zeros are compared exactly.
"""

import math

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from slicersim.backends import band_variance as compute
from slicersim.backends.dispatch import resolve_backend

from conftest import have_opencl

BACKENDS = ["numpy", pytest.param("opencl", marks=pytest.mark.needs_opencl)]


def reference(Q, P2, A, B, Qsat, band):
    """Literal transcription of the definition (slow; small inputs only)."""
    N, nlbda, ncell = Q.shape
    K = len(A)
    vs = np.zeros((N, K))
    nv = np.zeros((N, K), np.int32)
    for t in range(N):
        for k in range(K):
            for i in range(band[t, 0], band[t, 1]):
                w = 0.0
                for c in range(ncell):
                    q = Q[t, i, c]
                    if q > Qsat[k]:
                        continue
                    w += P2[i, c] / (A[k] + B[k] * q)
                v = math.inf if w == 0 else 1.0 / w  # NaN w -> NaN v
                if math.isnan(v):
                    continue
                vs[t, k] += v
                nv[t, k] += 1
    return vs, nv


def random_case(seed, N=11, nlbda=19, ncell=7, K=13):
    """Odd sizes with NaN bins, saturated cells, a fully saturated bin, empty bands."""
    rng = np.random.default_rng(seed)
    Q = rng.uniform(0.5, 100.0, (N, nlbda, ncell))
    P2 = rng.uniform(0.0, 1.0, (nlbda, ncell))
    A = rng.uniform(1.0, 50.0, K)
    B = rng.uniform(0.5, 3.0, K)
    Qsat = rng.uniform(60.0, 150.0, K)
    Qsat[0] = np.inf  # no saturation
    Q[0, 2, 3] = np.nan  # one NaN cell invalidates bin 2 of target 0
    Q[1, :, :] = np.where(rng.random((nlbda, ncell)) < 0.2, np.nan, Q[1])
    Q[2, 4, :] = 1e6  # every cell saturated (finite Qsat) -> bin variance +inf
    band = np.sort(rng.integers(0, nlbda + 1, (N, 2)), axis=1)
    band[0] = (0, nlbda)
    band[2] = (3, 6)
    band[3] = (5, 5)  # empty band
    return Q, P2, A, B, Qsat, band


def assert_same(got, want, rtol):
    (vs, nv), (rvs, rnv) = got, want
    assert vs.shape == rvs.shape and vs.dtype == np.float64
    assert nv.shape == rnv.shape and nv.dtype == np.int32
    np.testing.assert_array_equal(nv, rnv)
    np.testing.assert_array_equal(np.isinf(vs), np.isinf(rvs))
    np.testing.assert_allclose(vs, rvs, rtol=rtol, atol=0)


def test_hand_computed_case():
    # 1 target, 2 bins, 2 cells, 2 candidates.
    Q = np.array([[[1.0, 3.0], [2.0, np.nan]]])
    P2 = np.array([[0.5, 0.25], [1.0, 1.0]])
    A = np.array([1.0, 2.0])
    B = np.array([1.0, 0.5])
    Qsat = np.array([np.inf, 2.0])
    band = np.array([[0, 2]])
    # bin 1 has a NaN cell -> skipped for both candidates.
    # k=0, bin 0: V = (2, 4) -> w = 0.5/2 + 0.25/4 = 0.3125 -> v = 3.2
    # k=1, bin 0: V = (2.5, -) , cell 1 saturated (3 > 2) -> w = 0.5/2.5 = 0.2 -> v = 5
    for backend in ("numpy", "opencl") if have_opencl() else ("numpy",):
        vs, nv = compute.band_variance_table(Q, P2, A, B, Qsat, band, backend=backend)
        np.testing.assert_allclose(vs, [[3.2, 5.0]], rtol=1e-15)
        np.testing.assert_array_equal(nv, [[1, 1]])
    # all cells saturated in the only bin -> +inf, still counted as valid
    vs, nv = compute.band_variance_table(Q, P2, A, B, [0.5, 0.5], [[0, 1]], backend="numpy")
    assert np.all(np.isinf(vs)) and np.all(nv == 1)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_matches_reference(backend, seed):
    Q, P2, A, B, Qsat, band = random_case(seed)
    want = reference(Q, P2, A, B, Qsat, band)
    got = compute.band_variance_table(Q, P2, A, B, Qsat, band, backend=backend)
    assert_same(got, want, rtol=1e-13 if backend == "numpy" else 1e-12)
    vs, nv = got
    assert np.isinf(vs[2, 1:]).all() and np.isfinite(vs[2, 0])  # saturated bin 4
    assert (nv[3] == 0).all() and (vs[3] == 0).all()  # empty band
    assert (nv[0] == Q.shape[1] - 1).all()  # one NaN bin skipped


@pytest.mark.needs_opencl
@pytest.mark.parametrize("vector_width", [None, 1, 2, 4, 8, 16])
def test_opencl_matches_numpy(vector_width):
    Q, P2, A, B, Qsat, band = random_case(7, N=53, nlbda=41, ncell=9, K=37)
    Q = Q.astype(np.float32).astype(np.float64)  # also exercise dtype handling below
    want = compute.band_variance_table(Q, P2, A, B, Qsat, band, backend="numpy")
    got = compute.band_variance_table(Q.astype(np.float32), P2, A, B, Qsat, band,
                                      backend="opencl", vector_width=vector_width)
    assert_same(got, want, rtol=1e-12)


@pytest.mark.parametrize("backend", BACKENDS)
def test_chunking_is_invariant(backend):
    Q, P2, A, B, Qsat, band = random_case(3, N=29, nlbda=23, ncell=5, K=11)
    full = compute.band_variance_table(Q, P2, A, B, Qsat, band, backend=backend)
    for max_bytes in (1, 5000):  # one target per chunk; a few targets per chunk
        part = compute.band_variance_table(Q, P2, A, B, Qsat, band, backend=backend, max_bytes=max_bytes)
        np.testing.assert_array_equal(part[0], full[0])
        np.testing.assert_array_equal(part[1], full[1])


@pytest.mark.parametrize("backend", BACKENDS)
def test_degenerate_sizes(backend):
    Q, P2, A, B, Qsat, band = random_case(4, N=4, nlbda=6, ncell=4, K=1)
    Q, P2 = Q[:, :, :1], P2[:, :1]  # single cell (and a non-contiguous Q view)
    assert_same(compute.band_variance_table(Q, P2, A, B, Qsat, band, backend=backend),
                reference(Q, P2, A, B, Qsat, band), rtol=1e-12)
    vs, nv = compute.band_variance_table(Q[:0], P2, A, B, Qsat, band[:0], backend=backend)
    assert vs.shape == nv.shape == (0, 1)
    vs, nv = compute.band_variance_table(Q, P2, A[:0], B[:0], Qsat[:0], band, backend=backend)
    assert vs.shape == nv.shape == (4, 0)
    empty = np.zeros_like(band)
    vs, nv = compute.band_variance_table(Q, P2, A, B, Qsat, empty, backend=backend)
    assert (vs == 0).all() and (nv == 0).all()


def test_auto_backend_and_validation():
    Q, P2, A, B, Qsat, band = random_case(5)
    auto = compute.band_variance_table(Q, P2, A, B, Qsat, band)  # backend="auto"
    ref = compute.band_variance_table(Q, P2, A, B, Qsat, band, backend="numpy")
    assert_same(auto, ref, rtol=1e-12)
    assert resolve_backend("auto") == ("opencl" if have_opencl() else "numpy")
    with pytest.raises(ValueError, match="backend"):
        compute.band_variance_table(Q, P2, A, B, Qsat, band, backend="cuda")
    with pytest.raises(ValueError, match="P2"):
        compute.band_variance_table(Q, P2[1:], A, B, Qsat, band, backend="numpy")
    with pytest.raises(ValueError, match="same length"):
        compute.band_variance_table(Q, P2, A, B[1:], Qsat, band, backend="numpy")
    bad = band.copy()
    bad[0] = (3, Q.shape[1] + 1)
    with pytest.raises(ValueError, match="band"):
        compute.band_variance_table(Q, P2, A, B, Qsat, bad, backend="numpy")
    with pytest.raises(ValueError, match="band"):
        compute.band_variance_table(Q, P2, A, B, Qsat, band.astype(float), backend="numpy")


@settings(max_examples=25, deadline=None)
@given(
    N=st.integers(1, 4), nlbda=st.integers(1, 6), ncell=st.integers(1, 4), K=st.integers(1, 5),
    seed=st.integers(0, 2**32 - 1), nan_frac=st.sampled_from([0.0, 0.1, 0.5]),
)
def test_numpy_twin_property(N, nlbda, ncell, K, seed, nan_frac):
    rng = np.random.default_rng(seed)
    Q = rng.uniform(0.0, 10.0, (N, nlbda, ncell))
    Q[rng.random(Q.shape) < nan_frac] = np.nan
    P2 = rng.uniform(0.0, 1.0, (nlbda, ncell))
    A, B = rng.uniform(0.1, 5.0, K), rng.uniform(0.0, 2.0, K)
    Qsat = np.where(rng.random(K) < 0.3, np.inf, rng.uniform(0.0, 10.0, K))
    band = np.sort(rng.integers(0, nlbda + 1, (N, 2)), axis=1)
    want = reference(Q, P2, A, B, Qsat, band)
    assert_same(compute.band_variance_table(Q, P2, A, B, Qsat, band, backend="numpy"), want, rtol=1e-13)
    if have_opencl():
        assert_same(compute.band_variance_table(Q, P2, A, B, Qsat, band, backend="opencl"), want, rtol=1e-12)


@pytest.mark.needs_opencl
def test_zero_weight_cells_are_skipped_exactly():
    """The kernel skips cells of weight exactly 0 (CSR of the non-zero weights): adding
    zero-weight cells with any Q (huge, saturated) changes no bit of the result."""
    from slicersim.backends.band_variance import band_variance_table, nonzero_weights
    rng = np.random.default_rng(4)
    N, nl, nc, K = 5, 30, 12, 37
    Q = rng.uniform(0, 50, (N, nl, nc))
    Q[1, 7] = np.nan                                       # an invalid bin
    P2 = rng.uniform(0, 1, (nl, nc)) * (rng.uniform(size=(nl, nc)) > 0.4)
    P2[3] = 0.0                                            # a bin with no weight: variance +inf
    A, B = rng.uniform(1, 5, K), rng.uniform(0.5, 2, K)
    Qsat = np.full(K, 40.0)
    band = np.array([[0, nl], [2, 20], [5, 6], [0, 0], [10, 30]])
    ref = band_variance_table(Q, P2, A, B, Qsat, band, backend="opencl")
    Qx = np.concatenate([Q, rng.uniform(0, 1e9, (N, nl, 7))], axis=2)
    P2x = np.concatenate([P2, np.zeros((nl, 7))], axis=1)
    got = band_variance_table(Qx, P2x, A, B, Qsat, band, backend="opencl")
    assert np.array_equal(ref[0], got[0]) and np.array_equal(ref[1], got[1])
    assert np.isinf(ref[0][0]).all()                        # bin 3 has no weight in target 0's band
    w, c, r = nonzero_weights(P2)
    assert r[-1] == np.count_nonzero(P2) and np.array_equal(w, P2[P2 != 0]) and r[4] == r[3]
    # and the NumPy twin agrees (summation order differs: 1e-12 relative)
    num = band_variance_table(Q, P2, A, B, Qsat, band, backend="numpy")
    fin = np.isfinite(ref[0])
    np.testing.assert_allclose(ref[0][fin], num[0][fin], rtol=1e-12)
    assert np.array_equal(ref[1], num[1])
