"""Paper §3.5 — the sparse normal equations of the backend over many keyframe poses.

The backend's directed blocks each give a 14x14 Hessian block ``[[H_ii, H_ij], [H_ji, H_jj]]``
and a gradient ``[g_i, g_j]`` over the two poses they connect. This module sums them into one
sparse ``7n x 7n`` system over the n free poses (blocks touching a fixed pose are dropped from
the rows and columns of that pose) and solves it for the Gauss–Newton step.

Public names, in reading order: DENSE_MAX, assemble_system, factor_solve.

Upstream: gn_kernels.cu::SparseBlock (update_lhs, update_rhs; Eigen's sparse Cholesky).
"""

from __future__ import annotations

import numpy as np
import scipy.linalg
import scipy.sparse
import scipy.sparse.linalg

from mslam_ref.conventions import FloatArray, IntArray

__all__ = ["DENSE_MAX", "assemble_system", "factor_solve"]

#: Above this many unknowns the system is factorised with sparse LU instead of dense Cholesky
#: (7 x 511, upstream's keyframe buffer of 512 with one pose fixed).
DENSE_MAX = 7 * 511


def assemble_system(
    Hs: FloatArray, gs: FloatArray, pos_i: IntArray, pos_j: IntArray, n: int
) -> tuple[scipy.sparse.csr_matrix, FloatArray]:
    """Sum the blocks into the sparse 7n x 7n matrix and the 7n right-hand side.

    Upstream: gn_kernels.cu::SparseBlock::update_lhs / update_rhs (Eigen triplets; duplicate
    entries summed; blocks touching a fixed pose, position < 0, skipped).

    Args:
        Hs: (D, 4, 7, 7); gs: (D, 2, 7).
        pos_i, pos_j: (D,) positions of the block's poses among the unknowns (-1: fixed).
        n: number of free poses.

    Returns:
        A: (7n, 7n) CSR matrix; b: (7n,).
    """
    rows, cols, vals = [], [], []
    r7 = np.arange(7)
    b = np.zeros(7 * n)
    for k, (p, q) in enumerate(((0, 0), (0, 1), (1, 0), (1, 1))):
        pa = (pos_i, pos_j)[p]
        pb = (pos_i, pos_j)[q]
        keep = (pa >= 0) & (pb >= 0)
        rr = 7 * pa[keep, None, None] + r7[None, :, None]
        cc = 7 * pb[keep, None, None] + r7[None, None, :]
        rows.append(np.broadcast_to(rr, (keep.sum(), 7, 7)).ravel())
        cols.append(np.broadcast_to(cc, (keep.sum(), 7, 7)).ravel())
        vals.append(Hs[keep, k].ravel())
    for s, pa in enumerate((pos_i, pos_j)):
        keep = pa >= 0
        np.add.at(b, (7 * pa[keep, None] + r7).ravel(), gs[keep, s].ravel())
    A = scipy.sparse.coo_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(7 * n, 7 * n)
    ).tocsr()  # duplicates summed
    return A, b


def factor_solve(A: scipy.sparse.csr_matrix, b: FloatArray) -> FloatArray | None:
    """The step ``dx = -A^-1 b`` by dense Cholesky (sparse LU above :data:`DENSE_MAX`
    unknowns); None when the factorisation fails or the step is not finite."""
    try:
        if A.shape[0] <= DENSE_MAX:
            dx = -scipy.linalg.cho_solve(scipy.linalg.cho_factor(A.toarray(), lower=True), b)
        else:
            dx = -scipy.sparse.linalg.splu(A.tocsc()).solve(b)
    except (np.linalg.LinAlgError, RuntimeError, ValueError):
        return None
    return dx if np.all(np.isfinite(dx)) else None
