"""The inputs of the conformance golden set: small, deterministic, edges included.

Every kernel of ``mslam.conformance.kernels.KERNELS`` gets a few cases: a generic one, the
edges its maths has (identity, rotation angles near 0 and near pi, scale log sigma on both
sides of the 1e-6 series threshold, at the +-1.5 bound of the test strategies and just below
the cap |sigma| < 690, float64 only as e^689 overflows float32; pixels on the image border and
outside it, points at zero, behind the camera, NaN/inf, all-invalid masks) and an empty batch.
Images are 32x24 or smaller, so the whole set is about 2.6 MB.
Scenes are written from the maths (a wavy wall seen by nearby cameras, random Fourier-feature
descriptors), seeded, so export is reproducible.

Public names, in reading order:
    Case, build_cases
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from typing import Any

import numpy as np

from mslam_ref import backend, fusion, matching, sim3, tracking
from mslam_ref.ba import cameras, schur, synthetic
from mslam_ref.ba.robust import RobustKernel
from mslam_ref.conventions import SIM3_SIGMA_MAX
from mslam_ref.pointmap import backproject

__all__ = ["Case", "build_cases"]

H, W, F = 24, 32, 16
K_CAM = np.array([[26.0, 0.0, 15.5], [0.0, 27.0, 11.5], [0.0, 0.0, 1.0]])
#: (theta, sigma) edges: identity, pure scale, tiny angle/scale, just above the series
#: threshold, near pi, scale log at the strategies' bound.
EDGES = ((0.0, 0.0), (0.0, 0.4), (1e-7, 1e-7), (1e-5, 1e-7), (3e-3, 2e-6), (1e-6, -1e-6),
         (np.pi - 1e-9, 0.5), (1.0, 1.5), (2.0, -1.5))  # fmt: skip
#: Log-scales just below the cap of ``mslam_ref.conventions.SIM3_SIGMA_MAX`` (s up to 1e299).
SIGMA_CAP = (689.0, -689.0, 600.0)
_AXIS = np.array([1.0, 2.0, -0.5]) / np.linalg.norm([1.0, 2.0, -0.5])


@dataclasses.dataclass(frozen=True)
class Case:
    """One case: a kernel's inputs (arrays by name, scalars and config in ``params``)."""

    kernel: str
    name: str
    note: str
    inputs: dict[str, np.ndarray]
    params: dict[str, Any] = dataclasses.field(default_factory=dict)
    precisions: tuple[str, ...] = ("f64", "f32")


def _rng(seed: int) -> np.random.Generator:
    return np.random.default_rng(seed)


# --- Sim(3) ----------------------------------------------------------------------------------


def _edge_tangents() -> np.ndarray:
    """(E, 7) tangents ``[tau, theta axis, sigma]`` for every (theta, sigma) of EDGES."""
    tau = np.array([0.3, -1.2, 2.0])
    return np.stack([np.r_[tau, th * _AXIS, sg] for th, sg in EDGES])


def _random_tangents(n: int, seed: int) -> np.ndarray:
    rng = _rng(seed)
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    phi = axis * rng.uniform(0.0, np.pi - 1e-3, (n, 1))
    return np.concatenate([rng.uniform(-5, 5, (n, 3)), phi, rng.uniform(-1.5, 1.5, (n, 1))], 1)


def _sim3_sets() -> Iterator[tuple[str, str, np.ndarray, np.ndarray, np.ndarray]]:
    """(name, note, tangents, second tangents, points): edges, sigma cap, random, empty."""
    e = _edge_tangents()
    pts = np.tile([0.7, -0.4, 2.5], (len(e), 1))
    pts[0] = 0.0
    yield "edges", "identity, pure scale, angles 0/1e-7/1e-5/3e-3/pi-1e-9, sigma +-1e-6 and +-1.5", \
        e, e[::-1].copy(), pts  # fmt: skip
    cap = np.stack([np.r_[0.3, -1.2, 2.0, 0.7 * _AXIS, sg] for sg in SIGMA_CAP])
    yield (
        "sigma_cap",
        f"sigma {SIGMA_CAP} below the cap |sigma| < {SIM3_SIGMA_MAX:g} (f64 only)",
        cap,
        cap[::-1] * [1, 1, 1, 1, 1, 1, 1e-3],
        np.tile([0.7, -0.4, 2.5], (len(cap), 1)),
    )
    r = _random_tangents(24, 1)
    yield "random", "24 random elements, angles up to pi - 1e-3, points up to 10", \
        r, _random_tangents(24, 2), _rng(3).uniform(-10, 10, (24, 3))  # fmt: skip
    yield "empty", "empty batch (0,)", np.zeros((0, 7)), np.zeros((0, 7)), np.zeros((0, 3))


def _sim3_cases() -> Iterator[Case]:
    for name, note, xi, xi2, X in _sim3_sets():
        T, T2 = sim3.exp(xi), sim3.exp(xi2)
        args = {
            "exp": {"xi": xi}, "log": {"T": T}, "mul": {"A": T, "B": T2}, "inv": {"T": T},
            "act": {"T": T, "X": X}, "act_and_jacobian": {"T": T, "X": X},
            "adjoint": {"T": T}, "adjoint_inv_apply": {"T": T, "J": xi2},
            "retract": {"T": T, "xi": xi2}, "to_matrix": {"T": T},
        }  # fmt: skip
        fps = ("f64",) if name == "sigma_cap" else ("f64", "f32")  # e^689 overflows float32
        for fn, ins in args.items():
            yield Case(f"sim3.{fn}", name, note, ins, precisions=fps)
    T = sim3.exp(_random_tangents(6, 4)).reshape(3, 1, 2, 8)
    yield Case("sim3.act", "batch_3x1x2", "leading batch axes (3, 1, 2), broadcast points",
               {"T": T, "X": _rng(5).normal(size=(2, 3))})  # fmt: skip


# --- matching --------------------------------------------------------------------------------


def wavy_pair(seed: int = 0) -> tuple[np.ndarray, ...]:
    """X11, X21 (H, W, 3) and unit descriptors D11, D21 (H, W, F) of a wavy wall, two views."""
    rng = _rng(seed)
    v, u = np.mgrid[0:H, 0:W]
    X11 = backproject(2.0 + 0.3 * np.sin(u / 5.0 + seed) + 0.2 * np.cos(v / 4.0), K_CAM)
    T = sim3.exp(np.r_[rng.normal(0, 0.03, 3), rng.normal(0, 0.02, 3), 0.0])
    X21 = sim3.act(T, X11) + rng.normal(0, 0.002, X11.shape)
    Om, ph = rng.normal(0, 20.0, (F, 3)), rng.uniform(0, 2 * np.pi, F)

    def desc(X: np.ndarray) -> np.ndarray:
        D = np.sin(X @ Om.T + ph)
        return D / np.linalg.norm(D, axis=-1, keepdims=True)

    return X11, X21, desc(X11), desc(X21)


def _matching_cases() -> Iterator[Case]:
    cfg = dataclasses.asdict(matching.MatchingConfig())
    X11, X21, D11, D21 = wavy_pair()
    bad = X11.copy()
    bad[1, 2], bad[3, 4], bad[0, :] = 0.0, np.nan, [0.0, 0.0, -1.0]
    yield Case("matching.ray_image_and_gradients", "wavy", "32x24 wavy wall", {"X11": X11})
    yield Case("matching.ray_image_and_gradients", "bad_points",
               "a zero point, a NaN point, a row behind the camera", {"X11": bad})  # fmt: skip
    n = np.arange(H * W)
    grid = np.stack([n % W, n // W], -1).astype(float)
    p0 = grid + _rng(0).uniform(-3, 3, grid.shape)
    p0[:4] = [[-5.0, -5.0], [W + 3.0, 0.0], [0.0, H - 1.0], [W - 1.0, H - 1.0]]
    RG = matching.ray_image_and_gradients(X11)
    yield Case("matching.iter_proj", "wavy",
               "starts jittered by +-3 px; four start outside or on the image corners",
               {"rays_with_grad": RG, "X21": X21.reshape(-1, 3), "p_init": p0},
               {"cfg": cfg})  # fmt: skip
    p, _ = matching.iter_proj(RG, X21.reshape(-1, 3), grid)
    p1 = p.astype(np.int64)
    p1[:3] = [[0, 0], [W - 1, H - 1], [W - 1, 0]]  # windows clipped at the border
    for radius, dil in ((3, 5), (2, 3)):
        c = dict(cfg, radius=radius, dilation_max=dil)
        yield Case("matching.refine_matches", f"radius{radius}",
                   f"radius {radius}, dilation_max {dil}; three matches on image corners",
                   {"D11": D11, "D21": D21.reshape(-1, F), "p1": p1}, {"cfg": c})  # fmt: skip
    pair = {"X11": X11, "X21": X21, "D11": D11, "D21": D21}
    yield Case("matching.match", "radius0", "projective matching only", pair,
               {"cfg": dict(cfg, radius=0)})  # fmt: skip
    yield Case("matching.match", "radius3", "with descriptor refinement", pair, {"cfg": cfg})
    idx0 = np.clip(np.arange(H * W) + 2 * (1 + W), 0, H * W - 1)
    yield Case("matching.match", "idx_init", "initial matches shifted by (2, 2) pixels",
               dict(pair, idx_init=idx0), {"cfg": cfg})  # fmt: skip
    X21b = X21.copy()
    X21b[3, 4:7] = [[0.0, 0.0, 0.0], [np.inf, 1.0, 1.0], [np.nan, 0.0, 1.0]]
    yield Case("matching.match", "bad_points", "zero, inf and NaN points in both maps",
               dict(pair, X11=bad, X21=X21b), {"cfg": cfg})  # fmt: skip
    empty = {k: v[None][:0] for k, v in pair.items()}
    yield Case("matching.match", "empty", "empty batch (0, H, W)", empty, {"cfg": cfg})


# --- tracking and fusion ---------------------------------------------------------------------


def _tracking_problem(seed: int) -> dict[str, np.ndarray]:
    """Frame and keyframe pointmaps (H, W, 3) related by a Sim(3), with outliers and points
    behind the camera; ``T`` the truth and ``T1`` a perturbed estimate."""
    rng = _rng(seed)
    v, u = np.mgrid[0:H, 0:W]
    X_k = backproject(2.0 + 0.4 * np.sin(u / 5.0 + seed) + 0.3 * np.cos(v / 4.0), K_CAM)
    T = sim3.exp(np.r_[rng.normal(0, 0.1, 3), rng.normal(0, 0.05, 3), rng.normal(0, 0.05)])
    X_f = sim3.act(sim3.inv(T), X_k.reshape(-1, 3)) + rng.normal(0, 0.01, (H * W, 3))
    X_f[rng.random(H * W) < 0.03] += 1.0
    X_f[:5] = sim3.act(sim3.inv(T), np.array([0.0, 0.0, -1.0]))
    return {
        "X_f": X_f.reshape(H, W, 3), "X_k": X_k, "Q": rng.uniform(0.5, 4.0, H * W),
        "valid": rng.random(H * W) < 0.9, "T": T, "T1": sim3.retract(T, rng.normal(0, 0.02, 7)),
    }  # fmt: skip


def _tracking_cases() -> Iterator[Case]:
    cfg = {"cfg": dataclasses.asdict(tracking.TrackingConfig())}
    P = _tracking_problem(0)
    base = {k: P[k] for k in ("X_f", "X_k", "Q", "valid")}
    for mode, K in (("ray_dist", {}), ("calibrated", {"K": K_CAM})):
        note = "ray + distance residuals" if not K else "calibrated: pixel + log-depth residuals"
        yield Case("tracking.linearize", mode, note, dict(base, T_CkCf=P["T1"], **K), cfg)
        yield Case("tracking.solve", mode, note + ", from the identity",
                   dict(base, T_CkCf_init=sim3.identity(), **K), cfg)  # fmt: skip
    pts = {"T_CkCf": P["T1"], "X_f": P["X_f"].reshape(-1, 3).copy(), "X_k": P["X_k"].reshape(-1, 3)}
    pts["X_f"][5] = 0.0  # a point at the origin: ray 0, distance 0, zero Jacobian
    yield Case("tracking.ray_dist_residual_and_jacobian", "ray_dist",
               "Eq. 6 residual and its 4x7 Jacobian; points behind the camera and at the origin",
               pts)  # fmt: skip
    none = dict(base, valid=np.zeros(H * W, bool))
    yield Case("tracking.linearize", "all_invalid", "no valid match: H = 0, g = 0, cost 0",
               dict(none, T_CkCf=P["T1"]), cfg)  # fmt: skip
    yield Case("tracking.solve", "all_invalid", "no valid match: fails, returns the start",
               dict(none, T_CkCf_init=P["T1"]), cfg)  # fmt: skip
    empty = {"X_f": np.zeros((0, 3)), "X_k": np.zeros((0, 3)), "Q": np.zeros(0),
             "valid": np.zeros(0, bool), "T_CkCf": sim3.identity()}  # fmt: skip
    yield Case("tracking.linearize", "empty", "N = 0 pixels", empty, cfg)
    yield Case("tracking.ray_dist_residual_and_jacobian", "empty", "N = 0 points",
               {k: empty[k] for k in ("T_CkCf", "X_f", "X_k")})  # fmt: skip


def _fusion_cases() -> Iterator[Case]:
    for shape, tag in (((6, 5), ""), ((0,), "_empty")):
        rng = _rng(0)
        X = [rng.normal(0, 1, (*shape, 3)) + np.array([0.0, 0.0, 2.0]) for _ in range(3)]
        C = [rng.uniform(1.0, 3.0, shape) for _ in range(3)]
        for mode in fusion.FILTERING_MODES:
            cfg = fusion.FusionConfig(mode)
            s = fusion.update_pointmap(fusion.init_pointmap(X[0], C[0], cfg), X[1], C[1], cfg)
            params = {"cfg": dataclasses.asdict(cfg), "state_N": s.N,
                      "state_N_updates": s.N_updates, "state_score": s.score}  # fmt: skip
            ins = {"state.X_canon": s.X_canon, "state.C": s.C, "X": X[2], "C": C[2]}
            yield Case("fusion.update_pointmap", f"{mode}{tag}",
                       f"third update in mode {mode}, shape {shape}", ins, params)  # fmt: skip


# --- backend ---------------------------------------------------------------------------------


def _backend_graph(seed: int, KF: int = 3) -> dict[str, np.ndarray]:
    """3 keyframes of a wavy wall, random matches with noise, invalid entries, low qualities
    and confidences, a few points behind the camera."""
    rng = _rng(seed)
    h, w = 12, 16
    Kc = np.array([[13.0, 0.0, 7.5], [0.0, 13.5, 5.5], [0.0, 0.0, 1.0]])
    v, u = np.mgrid[0:h, 0:w]
    X = np.stack([backproject(2.0 + 0.3 * np.sin(u / 3.0 + k) + 0.2 * np.cos(v / 2.0), Kc)
                  for k in range(KF)])  # fmt: skip
    X = X + rng.normal(0, 0.01, X.shape)
    X[0, 0, :3, 2] = -1.0
    ii, jj = np.array([0, 1, 1, 2]), np.array([1, 0, 2, 1])
    N = h * w
    return {
        "T_WC": sim3.exp(np.concatenate([rng.normal(0, 0.1, (KF, 6)),
                                         rng.normal(0, 0.05, (KF, 1))], 1)),
        "X": X, "C": rng.uniform(0.0, 3.0, (KF, h, w)), "ii": ii, "jj": jj,
        "idx": np.clip(np.arange(N)[None] + rng.integers(-20, 20, (4, N)), 0, N - 1),
        "valid": rng.random((4, N)) < 0.9, "Q": rng.uniform(1.0, 4.0, (4, N)), "K_cam": Kc,
    }  # fmt: skip


def _backend_cases() -> Iterator[Case]:
    G = _backend_graph(0)
    Kc = G.pop("K_cam")
    for mode, extra in (("ray_dist", {}), ("calibrated", {"K_cam": Kc})):
        ins = dict(G, **extra)
        if extra:  # store the pointmaps constrained to their rays, as the kernel sees them
            ins["X"] = backend.pose_graph(ins["X"], ins["C"], ins["ii"], ins["jj"], ins["idx"],
                                          ins["valid"], ins["Q"], Kc).X  # fmt: skip
        cfg = dataclasses.asdict(backend.BackendConfig())
        yield Case("backend.linearize", mode, f"4 directed blocks, {mode}", ins, {"cfg": cfg})
        yield Case("backend.solve", mode, f"3 Gauss-Newton iterations, {mode}, first pinned",
                   ins, {"cfg": dict(cfg, max_iters=3)})  # fmt: skip
    e = {k: G[k][:0] for k in ("ii", "jj", "idx", "valid", "Q")}
    yield Case("backend.linearize", "empty", "no blocks (D = 0)", dict(G, **e),
               {"cfg": dataclasses.asdict(backend.BackendConfig())})  # fmt: skip


# --- bundle adjustment -----------------------------------------------------------------------


def _ba_problems() -> Iterator[tuple[str, Any]]:
    pin, _ = synthetic.make_pinhole_problem(n_cams=4, n_points=20, stereo_fraction=0.4, seed=11,
                                            kernel=RobustKernel("huber", 2.0))  # fmt: skip
    yield "pinhole", pin
    bal, _ = synthetic.make_bal_problem(n_cams=4, n_points=20, seed=12)
    yield "bal", bal


def _ba_cases() -> Iterator[Case]:
    for kind, p in _ba_problems():
        cams, pts = p.params()
        if kind == "bal":
            ins = {"cameras": cams, "points": pts, "obs_cam": p.obs_cam, "obs_pt": p.obs_pt,
                   "obs": p.obs}  # fmt: skip
            lin = cameras.bal_linearize(**ins)
        else:
            ins = {"poses": cams, "intrinsics": p.intrinsics, "points": pts,
                   "obs_cam": p.obs_cam, "obs_pt": p.obs_pt, "meas": p.meas,
                   "is_stereo": p.is_stereo.astype(float)}  # fmt: skip
            lin = cameras.pinhole_linearize(**ins)
        for fn in ("residuals", "linearize"):
            yield Case(f"ba.cameras.{kind}_{fn}", "ring", f"4 cameras, 20 points, {kind}", ins)
        e = {k: (v[:0] if k in ("obs_cam", "obs_pt", "obs", "meas", "is_stereo") else v)
             for k, v in ins.items()}  # fmt: skip
        yield Case(f"ba.cameras.{kind}_residuals", "empty", "no observations (O = 0)", e)
        yield from _schur_cases(kind, p, len(cams), len(pts), lin)


def _schur_cases(kind: str, p: Any, M: int, P: int, lin: tuple[np.ndarray, ...]):
    st = schur.build_structure(p.obs_cam, p.obs_pt, M, P, p.cam_dof)
    prm = {"n_cams": M, "n_points": P, "cam_dof": p.cam_dof}
    sins = {f"structure.{f.name}": getattr(st, f.name) for f in dataclasses.fields(st)
            if f.name not in prm}  # fmt: skip
    r, Jc, Jp = lin
    wgt = _rng(0).uniform(0.5, 1.5, len(r))
    yield Case("ba.schur.normal_blocks", kind, f"{kind} ring, random weights",
               dict(sins, r=r, J_cam=Jc, J_pt=Jp, weight=wgt), prm)  # fmt: skip
    U, V, Wb, bc, bl = schur.normal_blocks(r, Jc, Jp, wgt, st)
    lam = 1e-2 * max(np.abs(U).max(), np.abs(V).max())
    yield Case("ba.schur.schur_complement", kind, f"{kind} ring, lambda = 1e-2 max|diag block|",
               dict(sins, U=U, V=V, W=Wb, bc=bc, bl=bl), dict(prm, lam=float(lam)))  # fmt: skip
    S, rhs, Vinv = schur.schur_complement(U, V, Wb, bc, bl, lam, st)
    dc = schur.solve_reduced(S, rhs, st)
    if dc is None:
        raise RuntimeError(f"{kind} ring: the reduced camera system is not positive definite")
    yield Case("ba.schur.back_substitute", kind, f"{kind} ring, dc from the reduced system",
               dict(sins, Vinv=Vinv, W=Wb, bl=bl, dc=dc), prm)  # fmt: skip


def build_cases() -> list[Case]:
    """Every case of the golden set, grouped by kernel in the order of ``KERNELS``."""
    from mslam.conformance.kernels import KERNELS

    found = [*_sim3_cases(), *_matching_cases(), *_tracking_cases(), *_fusion_cases(),
             *_backend_cases(), *_ba_cases()]  # fmt: skip
    order = {name: k for k, name in enumerate(KERNELS)}
    return sorted(found, key=lambda c: order[c.kernel])
