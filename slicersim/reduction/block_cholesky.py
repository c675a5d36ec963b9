"""Block Cholesky factor of a sparse symmetric positive-definite block-tridiagonal matrix (the normal
matrix PᵀWP of one slice in :mod:`~slicersim.reduction.rectify`), its solves, the diagonal of its
inverse and an estimate of its 1-norm condition number.

The dense diagonal and sub-diagonal blocks are read out of the sparse matrix in one scatter (no
sparse slicing per block: the rectification of a Lazuli field made 29k such calls, a third of its
time); the last block is padded with the identity, which changes nothing in the solution.
"""
from __future__ import annotations

import numpy as np
from scipy.linalg import LinAlgError
from scipy.linalg.lapack import dpotrf, dtrtri

__all__ = ["BlockCholesky"]


class BlockCholesky:
    """Cholesky factor A = L Lᵀ of a symmetric positive-definite block-tridiagonal matrix.

    Parameters
    ----------
    A : scipy.sparse matrix, (n, n)
        symmetric positive definite, with no entry farther than ``block`` from the diagonal.
    block : int
        rows per block (≥ the bandwidth of ``A``).

    Kept: the inverses of L's lower-triangular diagonal blocks, ``inv[i]`` = L_ii⁻¹, and its
    sub-diagonal blocks ``sub[i]`` = L[i+1, i] (arrays (nb, block, block) and (nb − 1, block,
    block)): solves are matrix products.  Raises :class:`scipy.linalg.LinAlgError` when ``A`` is
    not positive definite.
    """

    def __init__(self, A, block):
        n = A.shape[0]
        block = int(block)
        nb = max(-(-n // block), 1)
        self.n, self.block, self.nb = n, block, nb
        coo = A.tocoo()
        coo.sum_duplicates()
        r, c, v = coo.row.astype(np.int64), coo.col.astype(np.int64), coo.data
        bi, bj = r // block, c // block
        if coo.nnz and np.abs(bi - bj).max() > 1:
            raise ValueError("BlockCholesky: an entry lies farther than one block from the diagonal")
        D = np.zeros((nb, block, block))
        on = bi == bj
        D[bi[on], r[on] % block, c[on] % block] = v[on]
        C = np.zeros((max(nb - 1, 0), block, block))                   # A[b_{i+1}, b_i]
        low = bi == bj + 1
        C[bj[low], r[low] % block, c[low] % block] = v[low]
        pad = np.arange(n - (nb - 1) * block, block)                  # the last block's padding: identity
        D[-1, pad, pad] = 1.0
        self.inv = np.empty((nb, block, block))
        self.sub = np.empty((max(nb - 1, 0), block, block))
        S = D[0]
        for i in range(nb):
            L, info = dpotrf(S, lower=1, clean=1)                      # LAPACK, no wrapper's checks
            if info != 0:
                raise LinAlgError("the matrix is not positive definite")
            Linv, info = dtrtri(L, lower=1)                            # L⁻¹
            if info != 0:
                raise LinAlgError("singular Cholesky factor")
            self.inv[i] = Linv
            if i + 1 < nb:
                M = C[i] @ Linv.T                                       # C L⁻ᵀ
                self.sub[i] = M
                S = D[i + 1] - M @ M.T

    def solve(self, rhs):
        """A⁻¹ rhs for (n,) or (n, k) ``rhs``."""
        rhs = np.asarray(rhs, np.float64)
        vec = rhs.ndim == 1
        b = self.block
        R = np.zeros((self.nb * b, 1 if vec else rhs.shape[1]))
        R[:self.n] = rhs[:, None] if vec else rhs
        R = R.reshape(self.nb, b, -1)
        y = np.empty_like(R)
        prev = None
        for i in range(self.nb):
            r = R[i] if prev is None else R[i] - self.sub[i - 1] @ prev
            prev = y[i] = self.inv[i] @ r
        x = np.empty_like(y)
        nxt = None
        for i in range(self.nb - 1, -1, -1):
            r = y[i] if nxt is None else y[i] - self.sub[i].T @ nxt
            nxt = x[i] = self.inv[i].T @ r
        x = x.reshape(self.nb * b, -1)[:self.n]
        return x[:, 0] if vec else x

    def inverse_diagonal(self):
        """diag(A⁻¹), (n,), by the block Takahashi recursion: Z_ii = L_ii⁻ᵀL_ii⁻¹ + Tᵀ Z_{i+1} T,
        T = L[i+1, i] L_ii⁻¹."""
        out = np.empty((self.nb, self.block))
        Z = None
        for i in range(self.nb - 1, -1, -1):
            Linv = self.inv[i]
            Znew = Linv.T @ Linv
            if Z is not None:
                T = self.sub[i] @ Linv
                Znew += T.T @ (Z @ T)
            Z = Znew
            out[i] = np.diag(Z)
        return out.ravel()[:self.n]

    def inverse_norm1(self, y=None, z=None):
        """Hager's estimate of ‖A⁻¹‖₁ (a lower bound, usually exact: Higham 1988, Algorithm 2.1, for a
        symmetric A, at most two steps) from two to five solves, the first two of which the caller
        may have done already (batched with its own solves).

        Parameters
        ----------
        y : (n,) array, optional
            A⁻¹ (1/n, …, 1/n).
        z : (n,) array, optional
            A⁻¹ sign(y) (only with ``y``).

        Returns
        -------
        float
        """
        n = self.n
        x = np.full(n, 1.0 / n)
        y = self.solve(x) if y is None else np.asarray(y, float)
        est = float(np.abs(y).sum())
        for _ in range(2):
            z = self.solve(np.where(y >= 0, 1.0, -1.0)) if z is None else np.asarray(z, float)
            j = int(np.argmax(np.abs(z)))
            if abs(z[j]) <= z @ x:
                break
            x = np.zeros(n)
            x[j] = 1.0
            y, z = self.solve(x), None
            new = float(np.abs(y).sum())
            if new <= est:
                break
            est = new
        return est
