r"""Bundle adjustment — normal equations in blocks, Schur complement, reduced solve, back-substitution.

With camera unknowns ``dc`` (M blocks of d = 6 or 9) and point unknowns ``dl`` (P blocks of 3),
residual Jacobians ``J = [J_c, J_p]`` and IRLS weights ``w_e = omega_e rho'(s_e)``, the damped
normal equations have the arrow shape

    +-------------------+----------------------+   +----+     +----+
    | U + lam I  (M d)  |  W         (Md x 3P) |   | dc |     | bc |
    | block-diagonal    |  one d x 3 block per |   |    |  =  |    |
    |                   |  observation         |   |    |     |    |
    +-------------------+----------------------+   +----+     +----+
    | W^T               |  V + lam I  (3P)     |   | dl |     | bl |
    |                   |  block-diagonal 3x3  |   |    |     |    |
    +-------------------+----------------------+   +----+     +----+

    U_i  = sum_{e in cam i}   J_c,e^T w_e J_c,e            (d x d)      normal_blocks
    V_j  = sum_{e in point j} J_p,e^T w_e J_p,e            (3 x 3)      normal_blocks
    W_e  = J_c,e^T w_e J_p,e                               (d x 3)      normal_blocks
    bc_i = -sum_{e in cam i}   J_c,e^T w_e r_e,   bl_j = -sum_{e in j} J_p,e^T w_e r_e

Because V is block-diagonal it is inverted block by block and the points are eliminated:

    S    = (U + lam I) - W (V + lam I)^-1 W^T                               schur_complement
         block (a, b) -= sum over point j seen by a and b of Y_ea W_eb^T,  Y_e = W_e V_j^-1
    rhs  = bc - W (V + lam I)^-1 bl,    rhs_i = bc_i - sum_{e in cam i} Y_e bl_{j(e)}
    S dc = rhs                         (Cholesky, dense or sparse)          solve_reduced
    dl_j = V_j^-1 (bl_j - sum_{e in j} W_e^T dc_{i(e)})                     back_substitute

S is stored as its upper-triangular d x d blocks in the pattern of :class:`BlockStructure`
(``block_row <= block_col``); the "product list" of (e_a, e_b) observation pairs that feed each
block is built once per problem by :func:`build_structure`, as cuda-bundle-adjustment builds it
once per ``optimize()`` call. Unknowns that are fixed or unobserved get identity blocks and a
zero right-hand side (their step is exactly 0), which keeps every block shape static.

Public names, in reading order:
    BlockStructure, build_structure, normal_blocks, jacobi_scale, pin_fixed, scaled_normal_blocks,
    schur_complement,
    dense_reduced, solve_reduced, back_substitute

Shapes: M cameras, P points, O observations, d camera DoF, B blocks of S, Q observation pairs.

Upstream: cuda-bundle-adjustment src/cuda_block_solver.cu (constructQuadraticForm, computeBschure,
computeHschure, schurComplementPost), src/sparse_block_matrix.cpp (the Hsc pattern and the
product list); g2o core/block_solver.hpp (BlockSolver::buildSystem, solve).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import scipy.linalg
import scipy.sparse
import scipy.sparse.linalg

from mslam_ref.conventions import BoolArray, FloatArray, IntArray

__all__ = [
    "DENSE_MAX",
    "BlockStructure",
    "back_substitute",
    "build_structure",
    "dense_reduced",
    "jacobi_scale",
    "normal_blocks",
    "pin_fixed",
    "scaled_normal_blocks",
    "schur_complement",
    "solve_reduced",
]

#: Largest reduced system (M d unknowns) solved with a dense Cholesky; above it, sparse LU.
DENSE_MAX = 3000


@dataclasses.dataclass(frozen=True, eq=False)
class BlockStructure:
    """Symbolic structure of the block system, built once per problem.

    Attributes:
        n_cams, n_points, cam_dof: M, P, d.
        obs_cam, obs_pt: (O,) camera and point of each observation.
        cam_ptr, cam_obs: CSR of observations by camera, (M+1,) and (O,).
        pt_ptr, pt_obs: CSR of observations by point, (P+1,) and (O,).
        block_row, block_col: (B,) block coordinates of S's upper triangle (row <= col),
            sorted row-major; every diagonal block is present.
        diag_block: (M,) index of block (i, i).
        pair_ptr, pair_a, pair_b: CSR of observation pairs per block, (B+1,), (Q,), (Q,):
            ``S[b] -= sum_q Y[pair_a[q]] W[pair_b[q]]^T``.
    """

    n_cams: int
    n_points: int
    cam_dof: int
    obs_cam: IntArray
    obs_pt: IntArray
    cam_ptr: IntArray
    cam_obs: IntArray
    pt_ptr: IntArray
    pt_obs: IntArray
    block_row: IntArray
    block_col: IntArray
    diag_block: IntArray
    pair_ptr: IntArray
    pair_a: IntArray
    pair_b: IntArray


def _csr(keys: IntArray, n: int) -> tuple[IntArray, IntArray]:
    order = np.argsort(keys, kind="stable")
    ptr = np.zeros(n + 1, np.int64)
    np.cumsum(np.bincount(keys, minlength=n), out=ptr[1:])
    return ptr, order.astype(np.int64)


def build_structure(
    obs_cam: IntArray, obs_pt: IntArray, n_cams: int, n_points: int, cam_dof: int
) -> BlockStructure:
    """Build the CSR maps, S's block pattern and the product list (observation pairs per block).

    Upstream: sparse_block_matrix.cpp (Hsc pattern from the per-landmark pose lists) and
    cuda_block_solver.cu (makeHschureProductList). Pairs (a, b) of observations of the same
    point are kept when ``cam(a) < cam(b)``, or ``cam(a) == cam(b)`` (both orders, so repeated
    observations of one pair are handled exactly).

    Args:
        obs_cam, obs_pt: (O,) int.
        n_cams, n_points, cam_dof: M, P, d.

    Returns:
        The :class:`BlockStructure`.
    """
    obs_cam = np.asarray(obs_cam, np.int64)
    obs_pt = np.asarray(obs_pt, np.int64)
    cam_ptr, cam_obs = _csr(obs_cam, n_cams)
    pt_ptr, pt_obs = _csr(obs_pt, n_points)
    # all ordered pairs of observations of the same point
    cnt = np.diff(pt_ptr)
    n_of = cnt[obs_pt[pt_obs]]  # count of the point of each sorted observation
    a_pos = np.repeat(np.arange(len(pt_obs)), n_of)
    first = pt_ptr[obs_pt[pt_obs]]  # start of its point's run
    run_start = np.repeat(np.cumsum(n_of) - n_of, n_of)
    b_pos = np.repeat(first, n_of) + (np.arange(len(a_pos)) - run_start)
    a, b = pt_obs[a_pos], pt_obs[b_pos]
    ca, cb = obs_cam[a], obs_cam[b]
    keep = ca <= cb
    a, b, pair_key = a[keep], b[keep], ca[keep] * n_cams + cb[keep]
    # one stable sort groups the pairs by block; the blocks are the distinct keys plus every
    # diagonal block (empty for a camera without observations)
    order = np.argsort(pair_key, kind="stable")
    pair_key = pair_key[order]
    diag = np.arange(n_cams) * (n_cams + 1)
    keys = np.union1d(pair_key[np.diff(pair_key, prepend=-1) != 0], diag)
    pair_ptr = np.searchsorted(pair_key, np.r_[keys, n_cams * n_cams])
    return BlockStructure(
        n_cams=n_cams, n_points=n_points, cam_dof=cam_dof, obs_cam=obs_cam, obs_pt=obs_pt,
        cam_ptr=cam_ptr, cam_obs=cam_obs, pt_ptr=pt_ptr, pt_obs=pt_obs,
        block_row=keys // n_cams, block_col=keys % n_cams,
        diag_block=np.searchsorted(keys, diag),
        pair_ptr=np.asarray(pair_ptr, np.int64), pair_a=a[order], pair_b=b[order],
    )  # fmt: skip


def _segment_sum(values: FloatArray, order: IntArray, ptr: IntArray) -> FloatArray:
    """Sum ``values[order]`` over the CSR segments ``ptr`` (empty segments give 0)."""
    n = len(ptr) - 1
    out = np.zeros((n, *values.shape[1:]))
    nonempty = np.flatnonzero(np.diff(ptr) > 0)
    if len(nonempty) and len(order):
        out[nonempty] = np.add.reduceat(values[order], ptr[nonempty], axis=0)
    return out


def normal_blocks(
    r: FloatArray,
    J_cam: FloatArray,
    J_pt: FloatArray,
    weight: FloatArray,
    structure: BlockStructure,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """Assemble the block normal equations (undamped).

    Upstream: cuda_block_solver.cu::constructQuadraticFormKernel; g2o BlockSolver::buildSystem.

        U_i = sum J_c^T w J_c,  V_j = sum J_p^T w J_p,  W_e = J_c^T w J_p,
        bc_i = -sum J_c^T w r,  bl_j = -sum J_p^T w r

    Args:
        r: (O, k) residuals; J_cam: (O, k, d); J_pt: (O, k, 3).
        weight: (O,) effective information ``omega rho'(s)``.
        structure: the block structure.

    Returns:
        U (M, d, d), V (P, 3, 3), W (O, d, 3), bc (M, d), bl (P, 3).
    """
    s = structure
    wJc = (J_cam * weight[:, None, None]).transpose(0, 2, 1)  # (O, d, k)
    U = _segment_sum(wJc @ J_cam, s.cam_obs, s.cam_ptr)
    wJp = (J_pt * weight[:, None, None]).transpose(0, 2, 1)
    V = _segment_sum(wJp @ J_pt, s.pt_obs, s.pt_ptr)
    W = wJc @ J_pt
    bc = -_segment_sum(np.einsum("oik,ok->oi", wJc, r), s.cam_obs, s.cam_ptr)
    bl = -_segment_sum(np.einsum("oik,ok->oi", wJp, r), s.pt_obs, s.pt_ptr)
    return U, V, W, bc, bl


def jacobi_scale(
    U: FloatArray,
    V: FloatArray,
    W: FloatArray,
    bc: FloatArray,
    bl: FloatArray,
    structure: BlockStructure,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """Ceres' Jacobi scaling of the blocks: ``H <- D H D``, ``b <- D b``, ``D = 1 / (1 + sqrt(diag H))``.

    Solving the scaled system and multiplying the step by D turns the damping ``lam I`` into
    Marquardt's ``lam D^-2`` (``mslam_ref.ba.lm.LMConfig.jacobi_scaling``).

    Args:
        U, V, W, bc, bl: from :func:`normal_blocks` (not modified).
        structure: the block structure.

    Returns:
        The scaled U (M, d, d), V (P, 3, 3), W (O, d, 3), bc (M, d), bl (P, 3), and
        Dc (M, d), Dp (P, 3).
    """
    s = structure
    Dc = 1.0 / (1.0 + np.sqrt(np.diagonal(U, axis1=1, axis2=2)))
    Dp = 1.0 / (1.0 + np.sqrt(np.diagonal(V, axis1=1, axis2=2)))
    Ws = W * Dc[s.obs_cam][:, :, None] * Dp[s.obs_pt][:, None, :]
    Us = U * (Dc[:, :, None] * Dc[:, None, :])
    Vs = V * (Dp[:, :, None] * Dp[:, None, :])
    return Us, Vs, Ws, bc * Dc, bl * Dp, Dc, Dp


def pin_fixed(
    U: FloatArray, V: FloatArray, bc: FloatArray, bl: FloatArray,
    cam_free: BoolArray, point_free: BoolArray,
) -> None:  # fmt: skip
    """Give every unknown that is not free an identity block and a zero right-hand side, in
    place (its step is then exactly 0): U (M, d, d) and bc (M, d) where ``cam_free`` (M,) is
    False, V (P, 3, 3) and bl (P, 3) where ``point_free`` (P,) is False."""
    U[~cam_free], bc[~cam_free] = np.eye(U.shape[-1]), 0.0
    V[~point_free], bl[~point_free] = np.eye(3), 0.0


def scaled_normal_blocks(
    r: FloatArray,
    J_cam: FloatArray,
    J_pt: FloatArray,
    weight: FloatArray,
    cam_free: BoolArray,
    point_free: BoolArray,
    structure: BlockStructure,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """:func:`normal_blocks`, :func:`pin_fixed`, then :func:`jacobi_scale`: the LM driver's
    scaled system in one call.

    Args:
        r, J_cam, J_pt, weight, structure: as :func:`normal_blocks`.
        cam_free: (M,) bool, point_free: (P,) bool.

    Returns:
        As :func:`jacobi_scale`: scaled U, V, W, bc, bl, and Dc (M, d), Dp (P, 3).
    """
    U, V, W, bc, bl = normal_blocks(r, J_cam, J_pt, weight, structure)
    pin_fixed(U, V, bc, bl, cam_free, point_free)
    return jacobi_scale(U, V, W, bc, bl, structure)


def schur_complement(
    U: FloatArray,
    V: FloatArray,
    W: FloatArray,
    bc: FloatArray,
    bl: FloatArray,
    lam: float,
    structure: BlockStructure,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Damp, invert the 3x3 point blocks and form the reduced camera system.

    Upstream: cuda_block_solver.cu::computeBschureKernel (V^-1, Y = W V^-1, rhs) and
    computeHschureKernel (S -= Y W^T over the product list); g2o BlockSolver::solve.

        S = (U + lam I) - sum Y_a W_b^T,  rhs = bc - sum Y_e bl_j,  Y_e = W_e (V_j + lam I)^-1

    Args:
        U: (M, d, d), V: (P, 3, 3), W: (O, d, 3), bc: (M, d), bl: (P, 3) from
            :func:`normal_blocks`.
        lam: LM damping added to every diagonal entry of U and V.
        structure: the block structure.

    Returns:
        S (B, d, d) upper-triangular blocks, rhs (M, d), Vinv (P, 3, 3) of the damped V.
        A singular damped V_j gives ``inf`` entries in Vinv (the solve then fails).
    """
    s = structure
    eye3 = np.eye(3)
    Vd = V + lam * eye3
    det = np.linalg.det(Vd)
    ok = np.abs(det) > 0.0
    Vinv = np.full_like(Vd, np.inf)
    Vinv[ok] = np.linalg.inv(Vd[ok])
    Y = W @ Vinv[s.obs_pt]  # (O, d, 3)
    rhs = bc - _segment_sum(np.einsum("oik,ok->oi", Y, bl[s.obs_pt]), s.cam_obs, s.cam_ptr)
    d = s.cam_dof
    S = np.zeros((len(s.block_row), d, d))
    pair_block = np.repeat(np.arange(len(S)), np.diff(s.pair_ptr))
    chunk = 1 << 15
    for lo in range(0, len(s.pair_a), chunk):  # chunked to bound the (Q, d, d) temporary
        hi = min(lo + chunk, len(s.pair_a))
        prod = Y[s.pair_a[lo:hi]] @ W[s.pair_b[lo:hi]].transpose(0, 2, 1)
        blk = pair_block[lo:hi]
        starts = np.flatnonzero(np.r_[True, blk[1:] != blk[:-1]])
        S[blk[starts]] -= np.add.reduceat(prod, starts, axis=0)
    S[s.diag_block] += U + lam * np.eye(d)
    return S, rhs, Vinv


def dense_reduced(S: FloatArray, structure: BlockStructure) -> FloatArray:
    """The full symmetric (M d, M d) matrix of the upper-triangular blocks ``S`` (B, d, d)."""
    s, d = structure, structure.cam_dof
    A = np.zeros((s.n_cams, d, s.n_cams, d))
    A[s.block_row, :, s.block_col, :] = S
    off = s.block_row != s.block_col
    A[s.block_col[off], :, s.block_row[off], :] = S[off].transpose(0, 2, 1)
    return A.reshape(s.n_cams * d, s.n_cams * d)


def solve_reduced(S: FloatArray, rhs: FloatArray, structure: BlockStructure) -> FloatArray | None:
    """Solve ``S dc = rhs`` by Cholesky; None when S is not positive definite.

    Upstream: cuda_linear_solver.cpp (cusolverSp csrchol; dense cusolverDn in the Kudan fork).
    Dense ``scipy.linalg.cho_factor`` up to ``DENSE_MAX`` unknowns, otherwise a sparse LU in
    symmetric mode with a minimum-degree ordering (SciPy has no sparse Cholesky).

    Args:
        S: (B, d, d) blocks from :func:`schur_complement`.
        rhs: (M, d).
        structure: the block structure.

    Returns:
        dc (M, d), or None on a failed factorisation (LM then counts the trial as failed).
    """
    s, d = structure, structure.cam_dof
    n = s.n_cams * d
    if not (np.all(np.isfinite(S)) and np.all(np.isfinite(rhs))):
        return None
    if n <= DENSE_MAX:
        try:
            c = scipy.linalg.cho_factor(dense_reduced(S, s), lower=False, check_finite=False)
        except np.linalg.LinAlgError:
            return None
        x = scipy.linalg.cho_solve(c, rhs.reshape(-1), check_finite=False)
    else:
        ii, jj = np.meshgrid(np.arange(d), np.arange(d), indexing="ij")
        rows = (s.block_row[:, None, None] * d + ii).ravel()
        cols = (s.block_col[:, None, None] * d + jj).ravel()
        off = np.repeat(s.block_row != s.block_col, d * d)
        A = scipy.sparse.coo_matrix(
            (np.r_[S.ravel(), S.ravel()[off]], (np.r_[rows, cols[off]], np.r_[cols, rows[off]])),
            shape=(n, n),
        ).tocsc()
        try:
            lu = scipy.sparse.linalg.splu(
                A, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                options={"SymmetricMode": True},
            )  # fmt: skip
        except RuntimeError:
            return None
        if np.any(lu.U.diagonal() <= 0.0):
            return None
        x = lu.solve(rhs.reshape(-1))
    if not np.all(np.isfinite(x)):
        return None
    return x.reshape(s.n_cams, d)


def back_substitute(
    Vinv: FloatArray, W: FloatArray, bl: FloatArray, dc: FloatArray, structure: BlockStructure
) -> FloatArray:
    """Recover the point steps.

    Upstream: cuda_block_solver.cu::schurComplementPostKernel.

        dl_j = V_j^-1 (bl_j - sum_{e in j} W_e^T dc_{i(e)})

    Args:
        Vinv: (P, 3, 3) inverse damped point blocks; W: (O, d, 3); bl: (P, 3).
        dc: (M, d) camera steps.
        structure: the block structure.

    Returns:
        dl (P, 3).
    """
    s = structure
    t = np.einsum("oij,oi->oj", W, dc[s.obs_cam])
    rhs = bl - _segment_sum(t, s.pt_obs, s.pt_ptr)
    return np.einsum("pij,pj->pi", Vinv, rhs)
