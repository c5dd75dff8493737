r"""Bundle adjustment — the reduced camera system: symbolic analysis once, numeric Cholesky per trial.

The Schur complement ``S`` (M d x M d, symmetric positive definite) has the block pattern of
the camera co-visibility graph: block (a, b) is non-zero when a point is seen by cameras a and
b. That pattern is fixed for a problem, so it is analysed once (cuda-bundle-adjustment's
"symbolic decomposition") and every LM trial only refills the numbers and refactors
("numerical decomposition"):

    analyse (once)        order the cameras by reverse Cuthill–McKee on the co-visibility
                          graph (scipy.sparse.csgraph), which packs the non-zeros of P S P^T
                          into a band of half-width kd = d (max |p(a) - p(b)| + 1) - 1; a band
                          Cholesky has no fill outside the band.  Then choose the storage:
                          "banded" (LAPACK dpbtrf, n kd^2 flops) when the band is narrow,
                          else "dense" (dpotrf, n^3 / 3); and precompute the scatter map from
                          the blocks of S to that storage.
    factor_solve (trial)  scatter S into the storage with the map, factor, solve
                          P S P^T y = P rhs, return P^T y; None when S is not positive
                          definite (LM counts the trial as failed).

A forward-moving camera whose points are seen by runs of consecutive views (visual odometry,
the KITTI graphs) gives a band of a dozen cameras whatever M is, so the factorisation is linear
in M; a graph whose ordering leaves a wide band falls back to the dense factorisation.

Public names, in reading order: BANDED_MAX_FILL, ReducedSymbolic, analyse, factor_solve.

Shapes: M cameras, d camera DoF, n = M d unknowns, B blocks of S (upper triangle), kd the band
half-width.

Upstream: cuda-bundle-adjustment src/cuda_linear_solver.cpp (ordering and csrcholAnalysis once
per optimize(), csrcholFactor and csrcholSolve per trial).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import scipy.linalg
import scipy.sparse
from scipy.sparse.csgraph import reverse_cuthill_mckee

from mslam_ref.conventions import FloatArray, IntArray

__all__ = ["BANDED_MAX_FILL", "ReducedSymbolic", "analyse", "factor_solve"]

#: The band storage is used when its size (kd + 1) n is at most this share of the dense n^2.
BANDED_MAX_FILL = 0.25


@dataclasses.dataclass(frozen=True, eq=False)
class ReducedSymbolic:
    """The analysed pattern of S: ordering, storage and scatter map.

    Attributes:
        n: M d unknowns.
        cam_dof: d.
        perm: (M,) camera order: camera ``perm[k]`` is the k-th block of P S P^T.
        inv_perm: (M,) position of each camera in that order.
        kind: "banded" or "dense".
        kd: band half-width (scalar), ``n - 1`` for "dense".
        src: (E,) flat indices into ``S.ravel()`` of the upper-triangle entries that are kept.
        dst: (E,) their flat indices into the storage: LAPACK upper band form
            ``ab[kd + i - j, j] = A[i, j]`` (i <= j), shape (kd + 1, n), or the dense (n, n).
    """

    n: int
    cam_dof: int
    perm: IntArray
    inv_perm: IntArray
    kind: str
    kd: int
    src: IntArray
    dst: IntArray

    @property
    def shape(self) -> tuple[int, int]:
        """Shape of the storage that ``dst`` indexes."""
        return (self.kd + 1, self.n) if self.kind == "banded" else (self.n, self.n)


def _ordering(block_row: IntArray, block_col: IntArray, n_cams: int) -> IntArray:
    """Reverse Cuthill–McKee order of the co-visibility graph (M,)."""
    g = scipy.sparse.coo_matrix(
        (np.ones(2 * len(block_row)), (np.r_[block_row, block_col], np.r_[block_col, block_row])),
        shape=(n_cams, n_cams),
    ).tocsr()
    return np.asarray(reverse_cuthill_mckee(g, symmetric_mode=True), np.int64)


def analyse(structure) -> ReducedSymbolic:
    """Order, choose the storage and build the scatter map of S (once per problem).

    Args:
        structure: the ``mslam_ref.ba.schur.BlockStructure`` (block_row <= block_col, B blocks).

    Returns:
        The :class:`ReducedSymbolic`.
    """
    s, d = structure, structure.cam_dof
    M, n = s.n_cams, s.n_cams * structure.cam_dof
    perm = _ordering(s.block_row, s.block_col, M)
    inv = np.empty(M, np.int64)
    inv[perm] = np.arange(M)
    pr, pc = inv[s.block_row], inv[s.block_col]
    kd = int(d * (np.abs(pr - pc).max(initial=0) + 1) - 1)
    kind = "banded" if (kd + 1) * n <= BANDED_MAX_FILL * n * n else "dense"
    # scalar coordinates of every block entry in the permuted matrix
    ii, jj = np.meshgrid(np.arange(d), np.arange(d), indexing="ij")
    R = pr[:, None, None] * d + ii
    C = pc[:, None, None] * d + jj
    lo, hi = np.minimum(R, C).ravel(), np.maximum(R, C).ravel()
    keep = (s.block_row[:, None, None] != s.block_col[:, None, None]) | (ii <= jj)[None]
    src = np.flatnonzero(np.broadcast_to(keep, R.shape).ravel())
    lo, hi = lo[src], hi[src]
    if kind == "banded":
        kd = max(kd, 0)
        dst = (kd + lo - hi) * n + hi
    else:
        kd = n - 1
        dst = lo * n + hi
    return ReducedSymbolic(n=n, cam_dof=d, perm=perm, inv_perm=inv, kind=kind, kd=kd,
                           src=src.astype(np.int64), dst=dst.astype(np.int64))  # fmt: skip


def factor_solve(symbolic: ReducedSymbolic, S: FloatArray, rhs: FloatArray) -> FloatArray | None:
    """Refill, factor and solve ``S dc = rhs``; None when S is not positive definite.

    Args:
        symbolic: from :func:`analyse` on the same structure.
        S: (B, d, d) upper-triangular blocks of the reduced matrix.
        rhs: (M, d).

    Returns:
        dc (M, d), or None (non-finite input, a non-positive pivot, or a non-finite solution).
    """
    sym, d = symbolic, symbolic.cam_dof
    if not (np.all(np.isfinite(S)) and np.all(np.isfinite(rhs))):
        return None
    A = np.zeros(sym.shape)
    A.ravel()[sym.dst] = np.asarray(S, np.float64).ravel()[sym.src]
    b = np.asarray(rhs, np.float64)[sym.perm].reshape(-1)
    try:
        if sym.kind == "banded":
            c = scipy.linalg.cholesky_banded(A, lower=False, check_finite=False)
            y = scipy.linalg.cho_solve_banded((c, False), b, check_finite=False)
        else:
            cf = scipy.linalg.cho_factor(A, lower=False, check_finite=False)
            y = scipy.linalg.cho_solve(cf, b, check_finite=False)
    except np.linalg.LinAlgError:
        return None
    if not np.all(np.isfinite(y)):
        return None
    return y.reshape(-1, d)[sym.inv_perm]
