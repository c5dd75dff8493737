"""The kernels a conformance golden set covers, and how each is called from a case's arrays.

A kernel is named ``MODULE.FUNCTION`` after the reference (``sim3.act`` is
``mslam_ref.sim3.act``, ``ba.schur.normal_blocks`` is ``mslam_ref.ba.schur.normal_blocks``). A
case stores the kernel's array arguments as ``in.NAME`` and its results as ``out.NAME``;
scalars and configurations sit in the case's ``params`` in ``index.json``. :func:`call` turns
those into the reference's call (building ``PoseGraph``, ``PointmapState``,
``BlockStructure`` and the config dataclasses) and the result back into named arrays, so
export (with ``mslam_ref``) and check (with any implementation) share one code path.

Public names, in reading order:
    Kernel, KERNELS, call
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import numpy as np

__all__ = ["KERNELS", "Kernel", "call"]

Arrays = dict[str, Any]


@dataclasses.dataclass(frozen=True)
class Kernel:
    """One kernel of the golden set.

    Attributes:
        name: ``MODULE.FUNCTION`` (module path below ``mslam_ref``).
        group: tolerance group (``mslam.conformance.tolerances.TOLERANCES``).
        signature: the call with shapes, as shown in ``index.json``.
        outputs: output name -> measure (``allclose``, ``scaled``, ``exact``, ``share_*``);
            a ``pose`` measure is ``allclose`` with the solved-pose tolerance.
        invoke: ``(fn, ins, params) -> result`` for the reference signature.
    """

    name: str
    group: str
    signature: str
    outputs: dict[str, str]
    invoke: Callable[[Callable[..., Any], Arrays, dict[str, Any]], Any]

    @property
    def module(self) -> str:
        """Module path below the package, e.g. ``ba.schur``."""
        return self.name.rsplit(".", 1)[0]

    @property
    def function(self) -> str:
        """Function name, e.g. ``normal_blocks``."""
        return self.name.rsplit(".", 1)[1]


def _cfg(module: str, params: dict[str, Any]) -> Any:
    """The config dataclass of ``module`` built from ``params["cfg"]`` (all fields stored)."""
    from mslam_ref import backend, fusion, matching, tracking

    cls = {
        "matching": matching.MatchingConfig,
        "tracking": tracking.TrackingConfig,
        "fusion": fusion.FusionConfig,
        "backend": backend.BackendConfig,
    }[module]
    return cls(**params["cfg"])


def _graph(ins: Arrays) -> Any:
    """``mslam_ref.backend.PoseGraph`` from the case's ``X, C, ii, jj, idx, valid, Q``."""
    from mslam_ref.backend import pose_graph

    names = ("X", "C", "ii", "jj", "idx", "valid", "Q", "K_cam", "pixels")
    return pose_graph(*(ins.get(n) for n in names))


def _structure(ins: Arrays, params: dict[str, Any]) -> Any:
    """``mslam_ref.ba.schur.BlockStructure`` from the stored ``structure.*`` arrays."""
    from mslam_ref.ba.schur import BlockStructure

    kw: dict[str, Any] = {k: int(params[k]) for k in ("n_cams", "n_points", "cam_dof")}
    for f in dataclasses.fields(BlockStructure):
        if f.name not in kw:
            kw[f.name] = ins[f"structure.{f.name}"]
    return BlockStructure(**kw)


def _state(ins: Arrays, params: dict[str, Any]) -> Any:
    """``mslam_ref.fusion.PointmapState`` from ``state.X_canon``, ``state.C`` and params."""
    from mslam_ref.fusion import PointmapState

    return PointmapState(
        ins["state.X_canon"], ins["state.C"], int(params["state_N"]),
        int(params["state_N_updates"]), float(params["state_score"]),
    )  # fmt: skip


def _args(*names: str) -> Callable[[Callable[..., Any], Arrays, dict[str, Any]], Any]:
    """Invoke ``fn`` with the named arrays as positional arguments."""
    return lambda fn, ins, params: fn(*(ins[n] for n in names))


def _sim3(fn: str, ins: tuple[str, ...], outs: tuple[str, ...], sig: str) -> Kernel:
    return Kernel(f"sim3.{fn}", "sim3", sig, dict.fromkeys(outs, "allclose"), _args(*ins))


_SIM3 = [
    _sim3("exp", ("xi",), ("T",), "exp(xi (...,7)) -> T (...,8)"),
    _sim3("log", ("T",), ("xi",), "log(T (...,8)) -> xi (...,7)"),
    _sim3("mul", ("A", "B"), ("T",), "mul(A (...,8), B (...,8)) -> T (...,8)"),
    _sim3("inv", ("T",), ("T",), "inv(T (...,8)) -> T (...,8)"),
    _sim3("act", ("T", "X"), ("P",), "act(T (...,8), X (...,3)) -> P (...,3)"),
    _sim3("act_and_jacobian", ("T", "X"), ("P", "J"),
          "act_and_jacobian(T (...,8), X (...,3)) -> P (...,3), J (...,3,7)"),
    _sim3("adjoint", ("T",), ("Ad",), "adjoint(T (...,8)) -> Ad (...,7,7)"),
    _sim3("adjoint_inv_apply", ("T", "J"), ("out",),
          "adjoint_inv_apply(T (...,8), J (...,7)) -> out (...,7)"),
    _sim3("retract", ("T", "xi"), ("T",), "retract(T (...,8), xi (...,7)) -> T (...,8)"),
    _sim3("to_matrix", ("T",), ("M",), "to_matrix(T (...,8)) -> M (...,4,4)"),
]  # fmt: skip

_MATCHING = [
    Kernel("matching.ray_image_and_gradients", "matching",
           "ray_image_and_gradients(X11 (...,H,W,3)) -> RG (...,H,W,9)",
           {"RG": "allclose"}, _args("X11")),
    Kernel("matching.iter_proj", "matching",
           "iter_proj(rays_with_grad (...,H,W,9), X21 (...,N,3), p_init (...,N,2), cfg) "
           "-> p (...,N,2), valid (...,N)",
           {"p": "share_close", "valid": "share_equal"},
           lambda fn, i, p: fn(i["rays_with_grad"], i["X21"], i["p_init"], _cfg("matching", p))),
    Kernel("matching.refine_matches", "matching",
           "refine_matches(D11 (...,H,W,F), D21 (...,N,F), p1 (...,N,2) int, cfg) -> idx (...,N)",
           {"idx": "share_equal"},
           lambda fn, i, p: fn(i["D11"], i["D21"], i["p1"], _cfg("matching", p))),
    Kernel("matching.match", "matching",
           "match(X11 (...,H,W,3), X21 (...,H,W,3), D11 (...,H,W,F), D21 (...,H,W,F), "
           "idx_init (...,N) or absent, cfg) -> idx (...,N), valid (...,N)",
           {"idx": "share_equal", "valid": "share_equal"},
           lambda fn, i, p: fn(i["X11"], i["X21"], i["D11"], i["D21"], i.get("idx_init"),
                               _cfg("matching", p))),
]  # fmt: skip

_TRACKING = [
    Kernel("tracking.ray_dist_residual_and_jacobian", "tracking",
           "ray_dist_residual_and_jacobian(T_CkCf (8,), X_f (N,3), X_k (N,3)) "
           "-> r (N,4), J (N,4,7)",
           {"r": "scaled", "J": "scaled"}, _args("T_CkCf", "X_f", "X_k")),
    Kernel("tracking.linearize", "tracking",
           "linearize(T_CkCf (8,), X_f (N,3) or (H,W,3), X_k (like X_f), Q (N,), valid (N,), "
           "cfg, K (3,3) or absent) -> H (7,7), g (7,), cost ()",
           {"H": "scaled", "g": "scaled", "cost": "allclose"},
           lambda fn, i, p: fn(i["T_CkCf"], i["X_f"], i["X_k"], i["Q"], i["valid"],
                               _cfg("tracking", p), i.get("K"))),
    Kernel("tracking.solve", "tracking",
           "solve(X_f, X_k, Q, valid, T_CkCf_init (8,), cfg, K or absent) "
           "-> T_CkCf (8,), converged (), failed ()",
           {"T_CkCf": "pose", "converged": "exact", "failed": "exact"},
           lambda fn, i, p: fn(i["X_f"], i["X_k"], i["Q"], i["valid"], i["T_CkCf_init"],
                               _cfg("tracking", p), i.get("K"))),
]  # fmt: skip

_FUSION = [
    Kernel("fusion.update_pointmap", "fusion",
           "update_pointmap(state (X_canon (...,3), C (...), N, N_updates, score), X (...,3), "
           "C (...), cfg) -> X_canon (...,3), C (...), N (), N_updates (), score ()",
           {"X_canon": "allclose", "C": "allclose", "N": "exact", "N_updates": "exact",
            "score": "allclose"},
           lambda fn, i, p: fn(_state(i, p), i["X"], i["C"], _cfg("fusion", p))),
]  # fmt: skip

_BACKEND_SIG = (
    "(T_WC (K,8), graph = pose_graph(X (K,H,W,3), C (K,H,W), ii (D,), jj (D,), idx (D,N), "
    "valid (D,N), Q (D,N), K_cam (3,3) or absent), cfg)"
)
_BACKEND = [
    Kernel("backend.linearize", "backend",
           f"linearize{_BACKEND_SIG} -> Hs (D,4,7,7), gs (D,2,7), cost ()",
           {"Hs": "scaled", "gs": "scaled", "cost": "allclose"},
           lambda fn, i, p: fn(i["T_WC"], _graph(i), _cfg("backend", p))),
    Kernel("backend.solve", "backend", f"solve{_BACKEND_SIG} -> T_WC (K,8)",
           {"T_WC": "pose"},
           lambda fn, i, p: fn(i["T_WC"], _graph(i), _cfg("backend", p))),
]  # fmt: skip

_BAL = ("cameras", "points", "obs_cam", "obs_pt", "obs")
_PIN = ("poses", "intrinsics", "points", "obs_cam", "obs_pt", "meas", "is_stereo")
_BA = [
    Kernel("ba.cameras.bal_residuals", "ba",
           "bal_residuals(cameras (M,9), points (P,3), obs_cam (O,), obs_pt (O,), obs (O,2)) "
           "-> r (O,2)", {"r": "scaled"}, _args(*_BAL)),
    Kernel("ba.cameras.bal_linearize", "ba",
           "bal_linearize(same as bal_residuals) -> r (O,2), J_cam (O,2,9), J_pt (O,2,3)",
           {"r": "scaled", "J_cam": "scaled", "J_pt": "scaled"}, _args(*_BAL)),
    Kernel("ba.cameras.pinhole_residuals", "ba",
           "pinhole_residuals(poses (M,7), intrinsics (M,5), points (P,3), obs_cam (O,), "
           "obs_pt (O,), meas (O,3), is_stereo (O,)) -> r (O,3)", {"r": "scaled"}, _args(*_PIN)),
    Kernel("ba.cameras.pinhole_linearize", "ba",
           "pinhole_linearize(same as pinhole_residuals) -> r (O,3), J_cam (O,3,6), J_pt (O,3,3)",
           {"r": "scaled", "J_cam": "scaled", "J_pt": "scaled"}, _args(*_PIN)),
    Kernel("ba.schur.normal_blocks", "ba",
           "normal_blocks(r (O,k), J_cam (O,k,d), J_pt (O,k,3), weight (O,), structure) "
           "-> U (M,d,d), V (P,3,3), W (O,d,3), bc (M,d), bl (P,3)",
           dict.fromkeys(("U", "V", "W", "bc", "bl"), "scaled"),
           lambda fn, i, p: fn(i["r"], i["J_cam"], i["J_pt"], i["weight"], _structure(i, p))),
    Kernel("ba.schur.schur_complement", "ba",
           "schur_complement(U, V, W, bc, bl, lam, structure) "
           "-> S (B,d,d), rhs (M,d), Vinv (P,3,3)",
           dict.fromkeys(("S", "rhs", "Vinv"), "scaled"),
           lambda fn, i, p: fn(i["U"], i["V"], i["W"], i["bc"], i["bl"], float(p["lam"]),
                               _structure(i, p))),
    Kernel("ba.schur.back_substitute", "ba",
           "back_substitute(Vinv (P,3,3), W (O,d,3), bl (P,3), dc (M,d), structure) -> dl (P,3)",
           {"dl": "scaled"},
           lambda fn, i, p: fn(i["Vinv"], i["W"], i["bl"], i["dc"], _structure(i, p))),
]  # fmt: skip

#: Every kernel of the golden set, by name, in reading order.
KERNELS: dict[str, Kernel] = {k.name: k for k in _SIM3 + _MATCHING + _TRACKING + _FUSION +
                              _BACKEND + _BA}  # fmt: skip


def _as_outputs(kernel: Kernel, result: Any) -> dict[str, np.ndarray]:
    """Name the parts of a kernel's result (tuples, result dataclasses) after its outputs."""
    names = list(kernel.outputs)
    if kernel.name == "fusion.update_pointmap":
        parts = [getattr(result, n) for n in names]
    elif kernel.name == "tracking.solve":
        T, info = result
        parts = [T, bool(np.all(info.converged)), bool(np.all(info.failed))]
    elif kernel.name == "backend.solve":
        parts = [result[0]]
    elif len(names) == 1:
        parts = [result]
    else:
        parts = list(result)
    if len(parts) != len(names):
        raise ValueError(f"{kernel.name}: expected {len(names)} results, got {len(parts)}")
    return {n: np.asarray(v) for n, v in zip(names, parts, strict=True)}


def call(
    kernel: Kernel, fn: Callable[..., Any], ins: Arrays, params: dict[str, Any]
) -> dict[str, np.ndarray]:
    """Run ``fn`` (with the reference's signature) on one case; its outputs by name.

    Args:
        kernel: the kernel.
        fn: the implementation's function.
        ins: the case's input arrays without the ``in.`` prefix (optional ones may be absent).
        params: the case's ``params`` from ``index.json``.

    Returns:
        ``{output name: array}`` in the order of ``kernel.outputs``.
    """
    return _as_outputs(kernel, kernel.invoke(fn, ins, params))
