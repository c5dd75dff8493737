"""Device-resident arrays for the per-frame chain: matching → tracking's solve → fusion.

The twins of ``mslam_ref`` take and return NumPy arrays (the pairing contract). On CUDA, Taichi
copies every NumPy argument to the GPU and back at each kernel call, so a frame that runs
matching, ten tracking iterations and fusion moves the same keyframe arrays across the bus many
times. This module is the additional entry that keeps them on the device:

* :func:`to_device` uploads a checked, converted host array once (a ``ti.ndarray`` on CUDA;
  on the CPU, where device memory is host memory, the array itself) and counts the upload
  (:func:`uploads`); :func:`to_host` brings a result back.
* :class:`Kept` holds the device copy of one host array while the caller passes the same
  read-only object again: a keyframe's arrays are uploaded once per keyframe, not per frame.
* :class:`ResidentMatcher` is ``mslam_fast.matching.match`` with the keyframe's descriptors
  (``D21``, the second image of the pair (frame, keyframe)) kept on the device as the kernel's
  zero-padded rows, and the last ``idx`` kept there as the next call's ``idx_init``.
* :class:`ResidentFusion` is ``mslam_fast.fusion.update_pointmap`` with the keyframe's fused
  pointmap kept on the device between frames (re-uploaded when someone else replaced it).

``mslam_fast.tracking.solve`` uploads its converted inputs once per solve through
:func:`to_device`, so its iterations do not copy them again.

Identity is only trusted for read-only arrays (``flags.writeable`` false, as the priors' cached
per-frame arrays are; their owner promises they do not change): a writable array is uploaded at
every call, since it may have changed in place. Every upload is checked on the host, where the data already is (finite values), once;
nothing is read back from the device to check it.

The results equal the NumPy entries' bit for bit: the same kernels run on the same values.
:func:`ndarrays_on_cpu` makes the CPU take CUDA's code path (``ti.ndarray`` storage, explicit
uploads and downloads) so that tests check it without a GPU.

Public names, in reading order:
    uploads, reset_uploads, storage, ndarrays_on_cpu, to_device, to_host, Kept,
    ResidentMatcher, ResidentFusion
"""

from __future__ import annotations

from typing import Any

import numpy as np

from mslam_fast import _matching_host as host
from mslam_fast import fusion as _fusion
from mslam_fast import matching as _matching
from mslam_fast._device import (
    Kept,
    empty,
    ndarrays_on_cpu,
    reset_uploads,
    storage,
    to_device,
    to_host,
    uploads,
)
from mslam_fast._runtime import ensure_init, generation
from mslam_ref import fusion as ref_fusion
from mslam_ref.fusion import FusionConfig, PointmapState
from mslam_ref.matching import MatchingConfig

__all__ = [
    "Kept",
    "ResidentFusion",
    "ResidentMatcher",
    "ndarrays_on_cpu",
    "reset_uploads",
    "storage",
    "to_device",
    "to_host",
    "uploads",
]

Array = np.ndarray[Any, Any]

#: Positions of the host arrays among ``_match_k``'s arguments that are uploaded per call
#: (X11, X21, D11), of ``idx_init`` and of the two outputs.
_FRAME_ARGS = {0: "matching.X11", 1: "matching.X21", 2: "matching.D11"}
_IDX0, _IDX, _VALID = 6, 9, 10


class ResidentMatcher:
    """``mslam_fast.matching.match`` with the second image's descriptors kept on the device.

    In the tracking pair (frame, keyframe), ``D21`` is the keyframe's descriptors: the same
    read-only array for every frame tracked against it, so it is checked and uploaded once per
    keyframe (:attr:`D21_uploads`). ``X11``, ``X21`` and ``D11`` are uploaded once per call.
    The returned ``idx`` stays on the device too: passed back as ``idx_init`` (the same object),
    the next call uses the device copy.

    Same parameters and results as ``mslam_fast.matching.match``, bit for bit.
    """

    def __init__(self) -> None:
        self._D21 = Kept()
        self._idx = Kept()

    @property
    def D21_uploads(self) -> int:
        """How many times ``D21`` was checked and uploaded."""
        return self._D21.made

    def match(
        self,
        X11: Any,
        X21: Any,
        D11: Any,
        D21: Any,
        idx_init: Any = None,
        cfg: MatchingConfig = MatchingConfig(),  # noqa: B008 (frozen, immutable)
    ) -> tuple[Array, Array]:
        """Matches of image 2's pixels in image 1 (see ``mslam_ref.matching.match``).

        Returns:
            idx: (N,) or (B, N) int64, valid: (N,) or (B, N) bool, host arrays.
        """

        def kept(flat: Array) -> Any:
            upload = lambda _: to_device(host.descriptors(flat, "D21"), "matching.D21")
            return self._D21.get(D21, upload)

        args, batched = _matching._match_args(X11, X21, D11, D21, idx_init, cfg, kept)
        dev = list(args)
        for i, label in _FRAME_ARGS.items():
            dev[i] = to_device(args[i], label)
        if idx_init is not None:
            upload = lambda _: to_device(args[_IDX0], "matching.idx_init")
            dev[_IDX0] = self._idx.get(idx_init, upload)
        dev[_IDX] = empty(args[_IDX].shape, np.int64)
        dev[_VALID] = empty(args[_VALID].shape, np.uint8)
        if args[_IDX].shape[0] > 0:
            _matching._match_k(*dev)
        idx_all, valid_all = to_host(dev[_IDX]), host.flags(to_host(dev[_VALID]))
        idx = idx_all if batched else idx_all[0]
        idx.setflags(write=False)  # kept as the next call's idx_init
        self._idx.get(idx, lambda _: dev[_IDX])
        return idx, (valid_all if batched else valid_all[0])

    def clear(self) -> None:
        """Forget the kept arrays (the next call uploads everything)."""
        self._D21.clear()
        self._idx.clear()


class ResidentFusion:
    """``mslam_fast.fusion.update_pointmap`` with the fused pointmap kept on the device.

    The state it returns is remembered with its device arrays: passed back as ``state`` (the
    same object), the next update reads the device copy, so a keyframe's ``X_canon`` and ``C``
    are uploaded once per keyframe (or when someone else replaced the state), not per frame
    (:attr:`state_uploads`). The frame's ``X`` and ``C`` are uploaded once per call.
    Modes without a kernel (``recent``, ``first``, ``best_score``) run the reference.

    Same parameters and results as ``mslam_fast.fusion.update_pointmap``, bit for bit.
    """

    def __init__(self) -> None:
        self._state: PointmapState | None = None
        self._key: tuple[Any, ...] = ()
        self._dev: tuple[Any, Any] = (None, None)
        self.state_uploads = 0

    def update_pointmap(
        self,
        state: PointmapState,
        X: Any,
        C: Any,
        cfg: FusionConfig = FusionConfig(),  # noqa: B008 (frozen, immutable)
    ) -> PointmapState:
        """The fused state (see ``mslam_ref.fusion.update_pointmap``)."""
        mode = cfg.filtering_mode
        if state.N == 0 or mode not in _fusion._KERNEL_MODES:
            return ref_fusion.update_pointmap(state, X, C, cfg)
        X, C = ref_fusion.check_pointmap(X, C)
        if X.shape != state.X_canon.shape:
            raise ValueError(f"X: expected shape {state.X_canon.shape}, got {X.shape}")
        n = C.size
        if n == 0:
            return ref_fusion.update_pointmap(state, X, C, cfg)
        rt = ensure_init()
        dtype = rt.dtype
        c = lambda a, s: np.ascontiguousarray(np.reshape(a, s), dtype=dtype)
        key = (rt.arch, rt.fp, storage(), generation())
        if state is self._state and key == self._key:
            Xs, Cs = self._dev
        else:
            self.state_uploads += 1
            Xs = to_device(c(state.X_canon, (n, 3)), "fusion.X_canon")
            Cs = to_device(c(state.C, (n,)), "fusion.C")
        Xf, Cf = to_device(c(X, (n, 3)), "fusion.X"), to_device(c(C, (n,)), "fusion.C_frame")
        Xo, Co = empty((n, 3), dtype), empty((n,), dtype)
        _fusion._fuse_k(Xs, Cs, Xf, Cf, Xo, Co, _fusion._KERNEL_MODES[mode])
        N = 1 if mode == "indep_conf" else state.N + 1
        X_canon, C_out = to_host(Xo).reshape(X.shape), to_host(Co).reshape(C.shape)
        for a in (X_canon, C_out):
            a.setflags(write=False)  # the device copy stands for them
        out = PointmapState(X_canon, C_out, N, state.N_updates + 1, state.score)
        self._state, self._key, self._dev = out, key, (Xo, Co)
        return out

    def clear(self) -> None:
        """Forget the kept state."""
        self._state, self._key, self._dev = None, (), (None, None)
