"""Backend and precision state of the Taichi kernels, and the wrapper helpers every module uses.

The pairing contract (DEV_NOTES.md): a fast public function takes and returns NumPy arrays with
the same shapes as its ``mslam_ref`` twin. Its wrapper coerces the dtype to the runtime's float
type, flattens leading batch axes, makes arrays contiguous, allocates outputs, calls the kernel
and reshapes back. It never mutates its inputs.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import math
from collections.abc import Callable
from typing import Any

import numpy as np
import numpy.typing as npt

from mslam_ref.conventions import as_float_array

_ARCHS = ("cpu", "cuda")
_FPS: dict[str, type[np.floating[Any]]] = {"f64": np.float64, "f32": np.float32}


@dataclasses.dataclass(frozen=True)
class Runtime:
    """The initialised backend: ``arch`` in {"cpu", "cuda"}, ``fp`` in {"f64", "f32"}."""

    arch: str
    fp: str

    @property
    def dtype(self) -> type[np.floating[Any]]:
        """NumPy float type that wrappers coerce inputs to."""
        return _FPS[self.fp]


_current: Runtime | None = None
#: How many times Taichi was (re)initialised: arrays allocated by Taichi (``ti.ndarray``) are
#: freed by ``ti.reset`` and must not outlive the initialisation they came from.
_generation = 0


def _normalise_fp(default_fp: Any) -> str:
    if default_fp is None:
        return "f64"
    if isinstance(default_fp, str):
        key = default_fp.lower().replace("float", "f")
    else:
        numpy_key = {np.float64: "f64", np.float32: "f32"}.get(default_fp)  # numpy types
        if numpy_key is not None:
            key = numpy_key
        else:
            key = {"f64": "f64", "f32": "f32"}.get(str(default_fp).split(".")[-1].lower(), "")
    if key not in _FPS:
        raise ValueError(f"default_fp: expected 'f64' or 'f32', got {default_fp!r}")
    return key


def init(arch: str = "cpu", default_fp: Any = None) -> Runtime:
    """Initialise Taichi for the fast kernels (idempotent for an unchanged setting).

    Args:
        arch: "cpu" or "cuda".
        default_fp: "f64" (default) or "f32"; also accepts np.float64/np.float32 or ti.f64/ti.f32.

    Returns:
        The active :class:`Runtime`.

    Raises:
        ValueError: on an unknown arch or precision.
        RuntimeError: when CUDA is requested and no usable GPU exists (no silent fallback); the
            runtime chosen before (arch and precision) stays active.
    """
    global _current
    if arch not in _ARCHS:
        raise ValueError(f"arch: expected one of {_ARCHS}, got {arch!r}")
    rt = Runtime(arch=arch, fp=_normalise_fp(default_fp))
    if rt == _current:
        return rt
    import taichi as ti

    previous = _current
    if previous is not None:
        ti.reset()
    try:
        _ti_init(ti, rt)
    except RuntimeError as exc:
        # A failed switch (e.g. CUDA without a GPU) keeps the earlier choice, f32 included.
        _current = None
        if previous is not None:
            _ti_init(ti, previous)
            _current = previous
        raise RuntimeError(f"mslam_fast.init: arch={arch!r} is not available here ({exc})") from exc
    _current = rt
    return rt


def generation() -> int:
    """The number of Taichi initialisations so far (see ``_generation``)."""
    return _generation


def _ti_init(ti: Any, rt: Runtime) -> None:
    global _generation
    _generation += 1
    # ti.init prints "[Taichi] Starting on arch=..." unconditionally; keep stdout clean for
    # commands that print JSON.
    ti_fp = ti.f64 if rt.fp == "f64" else ti.f32
    ti_arch = ti.cpu if rt.arch == "cpu" else ti.cuda
    with contextlib.redirect_stdout(io.StringIO()):
        ti.init(arch=ti_arch, default_fp=ti_fp, enable_fallback=False, log_level=ti.WARN)


def current() -> Runtime | None:
    """The active runtime, or None before the first ``init`` or kernel call."""
    return _current


def ensure_init() -> Runtime:
    """Return the active runtime, initialising the CPU float64 default on first use."""
    return _current if _current is not None else init()


def prepare(x: Any, name: str, trailing: int | tuple[int, ...] | None) -> npt.NDArray[Any]:
    """Check ``x`` like the reference does, then coerce it to the runtime's float dtype.

    Returns a C-contiguous array of the runtime dtype (float64 or float32).
    """
    arr = as_float_array(x, name, trailing)
    return np.ascontiguousarray(arr, dtype=ensure_init().dtype)


def coerce(x: Any, name: str, trailing: int | tuple[int, ...] | None) -> npt.NDArray[Any]:
    """:func:`prepare` without the finiteness scan, for twins whose reference computes on any
    value (the bundle adjuster's block arrays, where a scan would read every entry once more).

    Raises:
        ValueError: on a wrong trailing shape, naming ``name``.
    """
    arr = np.ascontiguousarray(x, dtype=ensure_init().dtype)
    if trailing is not None:
        tr = (trailing,) if isinstance(trailing, int) else tuple(trailing)
        if arr.ndim < len(tr) or arr.shape[arr.ndim - len(tr) :] != tr:
            raise ValueError(f"{name}: expected trailing shape {tr}, got shape {arr.shape}")
    return arr


def flat(x: npt.NDArray[Any], batch: tuple[int, ...], k: int | tuple[int, ...]) -> npt.NDArray[Any]:
    """Broadcast ``x`` to ``(*batch, *k)`` and return it as a contiguous ``(B, *k)`` array."""
    kk = (k,) if isinstance(k, int) else tuple(k)
    full = np.broadcast_to(x, (*batch, *kk))
    return np.ascontiguousarray(full.reshape(-1, *kk))


def run_batch(
    kernel: Callable[..., Any],
    inputs: list[tuple[npt.NDArray[Any], int]],
    out_tail: tuple[int, ...],
) -> npt.NDArray[Any]:
    """Run an element-wise batch kernel over broadcast inputs.

    Broadcasts ``inputs`` (prepared array, element size) over their leading batch axes, flattens
    them to ``(B, k)``, allocates the ``(*batch, *out_tail)`` output in the runtime dtype and calls
    ``kernel(*inputs, out)`` unless the batch is empty.
    """
    batch = np.broadcast_shapes(*(a.shape[:-1] for a, _ in inputs))
    out = np.empty((*batch, *out_tail), dtype=ensure_init().dtype)
    if math.prod(batch) > 0:
        kernel(*(flat(a, batch, k) for a, k in inputs), out.reshape(-1, *out_tail))
    return out
