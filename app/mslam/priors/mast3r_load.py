"""Loading the user's MASt3R network — dependencies and checkpoint checked before any frame.

Upstream builds the network with ``AsymmetricMASt3R.from_pretrained(path)``, which reads the
checkpoint (``torch.load``), instantiates the model described by its ``args.model`` string and
loads the ``model`` weights, printing both steps on stdout. :func:`load_mast3r` does the same
with every failure turned into one line (a ``ValueError``, which the CLI prints with exit 2):

1. the checkpoint file must exist;
2. torch must import, then ``mast3r.model``; a missing module is named (``einops``,
   ``huggingface_hub``, ``mast3r`` itself) and the dust3r/croco submodule check of the mast3r
   code is passed on in one line;
3. the checkpoint is read (memory-mapped when the file allows it) and must be a mapping with
   ``args`` (whose ``model`` string upstream instantiates) and ``model`` weights that include
   the local-feature (descriptor) heads, ``downstream_head{1,2}.head_local_features.*``:
   a DUSt3R checkpoint has the same backbone but no descriptors, and is refused here;
4. the network is built and moved to the device. What the mast3r code prints on stdout (at
   import and while building) is captured and discarded, so ``--quiet`` runs and JSON output
   stay clean.

Public names, in reading order:
    Mast3rUnavailable, import_torch, import_model_class, read_checkpoint, check_checkpoint,
    load_mast3r
"""

from __future__ import annotations

import contextlib
import io
from collections.abc import Mapping
from pathlib import Path
from typing import Any

__all__ = [
    "Mast3rUnavailable",
    "check_checkpoint",
    "import_model_class",
    "import_torch",
    "load_mast3r",
    "read_checkpoint",
]

INSTALL_HINT = (
    "the MASt3R prior needs torch, einops and huggingface_hub (pip install -e '.[mast3r]', "
    "CPU build pinned), the naver/mast3r code with its dust3r submodule on PYTHONPATH, and a "
    "checkpoint such as MASt3R_ViTLarge_BaseDecoder_512_catmlpdpt_metric.pth"
)

#: Weight names of MASt3R's local-feature (descriptor) heads; DUSt3R checkpoints lack them.
DESCRIPTOR_HEAD = "head_local_features"


class Mast3rUnavailable(ImportError, ValueError):
    """torch, the mast3r code or one of its modules is missing (a ValueError too, so the CLI
    prints it as one line)."""


def _one_line(text: object) -> str:
    """``str(text)`` (a message or an exception) on one line, runs of whitespace made one space."""
    return " ".join(str(text).split())


def import_torch() -> Any:
    """The torch module, or :class:`Mast3rUnavailable` naming it."""
    try:
        import torch
    except ImportError:
        raise Mast3rUnavailable(f"torch is not installed: {INSTALL_HINT}") from None
    return torch


def import_model_class() -> Any:
    """``mast3r.model.AsymmetricMASt3R``, or :class:`Mast3rUnavailable` naming what is missing.

    A missing module is named as Python reports it (``einops``, ``mast3r``, ...); the mast3r
    code's own check for its dust3r submodule (an ``ImportError`` with a message) is passed on
    in one line.
    """
    try:
        from mast3r.model import AsymmetricMASt3R
    except ModuleNotFoundError as exc:
        name = exc.name or _one_line(exc)
        if name.split(".")[0] == "mast3r":
            where = "the naver/mast3r checkout is not on PYTHONPATH"
        elif name.split(".")[0] in ("dust3r", "croco"):
            where = "run 'git submodule update --init --recursive' in the mast3r checkout"
        else:
            where = "pip install -e '.[mast3r]'"
        raise Mast3rUnavailable(
            f"mast3r cannot be imported: the Python module '{name}' is not installed ({where})"
        ) from None
    except ImportError as exc:
        raise Mast3rUnavailable(f"mast3r cannot be imported: {_one_line(exc)}") from None
    return AsymmetricMASt3R


def read_checkpoint(path: Path, torch: Any) -> Any:
    """The unpickled checkpoint (memory-mapped if the file allows it), or a one-line
    ``ValueError`` naming the file when it is not a readable PyTorch checkpoint."""
    try:
        return torch.load(str(path), map_location="cpu", weights_only=False, mmap=True)
    except Exception:  # an older format cannot be mapped: read it whole
        pass
    try:
        return torch.load(str(path), map_location="cpu", weights_only=False)
    except Exception as exc:
        raise ValueError(
            f"{path}: not a readable PyTorch checkpoint ({type(exc).__name__}: "
            f"{_one_line(exc)[:200]})"
        ) from None


def check_checkpoint(ckpt: Any, path: Path) -> None:
    """Raise a one-line ``ValueError`` unless ``ckpt`` is a MASt3R checkpoint: a mapping with
    ``args.model`` (a string) and ``model`` weights that include the descriptor heads."""
    if not isinstance(ckpt, Mapping) or "args" not in ckpt:
        raise ValueError(
            f"{path}: the checkpoint has no 'args' (the model description upstream's loader "
            "instantiates); a MASt3R checkpoint as released is needed"
        )
    if not isinstance(getattr(ckpt["args"], "model", None), str):
        raise ValueError(f"{path}: the checkpoint's 'args' has no 'model' description string")
    weights = ckpt.get("model")
    if not isinstance(weights, Mapping):
        raise ValueError(f"{path}: the checkpoint has no 'model' weights")
    if not any(DESCRIPTOR_HEAD in str(k) for k in weights):
        raise ValueError(
            f"{path}: the checkpoint has no descriptor heads ({DESCRIPTOR_HEAD} weights), as a "
            "DUSt3R checkpoint; the MASt3R prior needs a MASt3R checkpoint such as "
            "MASt3R_ViTLarge_BaseDecoder_512_catmlpdpt_metric.pth"
        )


def load_mast3r(checkpoint: str | Path, device: str = "cpu") -> Any:
    """``AsymmetricMASt3R`` from a user-given checkpoint, in eval mode on ``device``.

    Upstream: mast3r_utils.py::load_mast3r (``AsymmetricMASt3R.from_pretrained(path)``).

    Raises:
        FileNotFoundError: the checkpoint is missing. Mast3rUnavailable (an ImportError and a
        ValueError): torch, mast3r or one of its modules missing. ValueError: the file is not
        a readable checkpoint, has no ``args`` or no descriptor heads, or the network cannot
        be built from it. Nothing is printed on stdout.
    """
    path = Path(checkpoint)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: MASt3R checkpoint not found; {INSTALL_HINT}")
    torch = import_torch()
    # The mast3r code prints on stdout: a note at import (no compiled RoPE2D), the model's
    # args and the weight-key report when building it. It is discarded.
    with contextlib.redirect_stdout(io.StringIO()):
        model_class = import_model_class()
    check_checkpoint(read_checkpoint(path, torch), path)
    with contextlib.redirect_stdout(io.StringIO()):
        try:
            return model_class.from_pretrained(str(path)).to(device).eval()
        except Exception as exc:
            raise ValueError(
                f"{path}: MASt3R cannot build the network from this checkpoint on {device!r} "
                f"({type(exc).__name__}: {_one_line(exc)[:200]})"
            ) from None
