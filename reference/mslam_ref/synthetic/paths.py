"""Synthetic data — named camera paths through the procedural room (camera-to-world poses).

Cameras use the OpenCV convention (x right, y down, z forward); the world has z up. Every
path stays in the free central region of the room (see ``scene.make_scene``) at 1.2–1.6 m
height and moves a few centimetres and a few degrees per frame at 60–100 frames, so that
consecutive frames overlap strongly.

* ``loop``: an ellipse around the room centre, looking half outward; frame n would coincide
  with frame 0, so the end of the sequence revisits its start (loop closure).
* ``jump``: the kidnapped camera. An arc turning by 92° (frames ``0..j-1``, ``j = n // 2``;
  wider than the 70° field of view, so its last frames share no surface point with its
  first), then at frame ``j`` the camera is carried back to the arc's start, 3 cm higher and
  turned 1.7° away from the arc's end, and sweeps the first 60 % of the arc again, more
  slowly. Frame ``j`` sees nothing of the last keyframe's view (tracking is lost) and almost
  exactly what frame 0 saw, so relocalisation can succeed at once; every later frame overlaps
  the map. ``jump_indices`` gives ``(j,)``.
* ``detour``: an arc (first half), a sudden relocation to the opposite side of the room
  looking the other way (third quarter), then a jump back that retraces the arc in reverse
  (last quarter). The detour's frames see nothing mapped before it, so a single-map system
  can pose at most 75 % of the frames: it is the case for multi-map SLAM (a second map,
  merged when the camera returns). Tracking is lost at the first jump and relocalisation can
  succeed at the return frame; ``detour_indices`` gives the two jump frames.
* ``rotation``: a fixed camera centre, yaw and pitch oscillate (pure rotation).
* ``forward``: forward motion along +x with a gentle sway.

Public names, in reading order:
    PATHS, look_at, camera_path, jump_indices, detour_indices
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from mslam_ref import sim3, so3
from mslam_ref.conventions import FloatArray

__all__ = ["PATHS", "camera_path", "detour_indices", "jump_indices", "look_at"]

#: Names of the camera paths, in the order the documentation lists them.
PATHS = ("loop", "jump", "detour", "rotation", "forward")

#: Seed stream of each path's random variations. ``detour`` shares ``jump``'s, so both start with
#: the same arc.
_SEED_KEY = {"loop": 0, "jump": 1, "detour": 1, "rotation": 2, "forward": 3}


def look_at(
    position: FloatArray, yaw: ArrayLike, pitch: ArrayLike, roll: ArrayLike = 0.0
) -> FloatArray:
    """Camera-to-world poses looking along heading ``yaw`` (about world z) and ``pitch``.

    The optical axis is ``f = [cos p cos y, cos p sin y, sin p]``; the camera x axis is
    ``normalize(f × z_W)`` (right), y = z × x (down); ``roll`` rotates about the optical axis.

    Args:
        position: (N, 3) camera centres; yaw, pitch, roll: (N,) radians (broadcast).

    Returns:
        (N, 8) Sim(3) poses with s = 1.
    """
    position = np.asarray(position, dtype=np.float64).reshape(-1, 3)
    n = len(position)
    yaw, pitch, roll = (
        np.broadcast_to(np.asarray(a, np.float64), (n,)) for a in (yaw, pitch, roll)
    )
    f = np.stack([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)], -1)
    x = np.cross(f, np.array([0.0, 0.0, 1.0]))
    x /= np.linalg.norm(x, axis=-1, keepdims=True)
    y = np.cross(f, x)
    R = np.stack([x, y, f], axis=-1)
    q = so3.from_matrix(R)
    q = so3.mul(q, so3.exp(np.stack([np.zeros(n), np.zeros(n), roll], -1)))
    return np.concatenate([position, q, np.ones((n, 1))], axis=-1)


def jump_indices(n_frames: int) -> tuple[int]:
    """Frame indices where the ``jump`` path relocates the camera: the 1-tuple ``(n // 2,)``.

    A tuple, like :func:`detour_indices`, so callers can treat "the frames where the camera
    teleports" alike for both paths (``synth.json`` lists them as ``jump_indices``).
    """
    return (n_frames // 2,)


def detour_indices(n_frames: int) -> tuple[int, int]:
    """Frame indices of the two relocations of the ``detour`` path: ``(n // 2, 3n // 4)``."""
    return n_frames // 2, (3 * n_frames) // 4


def _loop(s: FloatArray, rng: np.random.Generator) -> FloatArray:
    a, b = rng.uniform(1.1, 1.3), rng.uniform(0.8, 0.95)
    th = 2 * np.pi * s + rng.uniform(0, 2 * np.pi)
    pos = np.stack([a * np.cos(th), b * np.sin(th), 1.35 + 0.1 * np.sin(2 * th)], -1)
    return look_at(pos, th + 0.9, -0.12 + 0.08 * np.sin(3 * th), 0.03 * np.sin(5 * th))


def _arc(
    s: FloatArray, yaw0: float, rise: float = 0.0, turn: float = 0.0, sweep: float = 0.9
) -> FloatArray:
    """The arc at parameters ``s`` in [0, 1]: heading ``yaw0`` turning by ``sweep`` radians,
    raised by ``rise`` metres and turned by ``turn`` radians."""
    pos = np.stack([-1.0 + 0.8 * s, -0.6 + 0.3 * np.sin(np.pi * s), 1.35 + 0.05 * s + rise], -1)
    return look_at(pos, yaw0 + sweep * s + turn, -0.1 + 0.05 * np.sin(2 * np.pi * s))


#: ``jump``: yaw swept by its arc (rad; 92° > the 70° field of view), the kidnapped camera's
#: rise (m) and turn (rad) from the arc's first pose, and the share of the arc swept again.
_JUMP_SWEEP, _KIDNAP_RISE, _KIDNAP_TURN, _RETRACE = 1.6, 0.03, -0.03, 0.6


def _jump(n: int, rng: np.random.Generator) -> FloatArray:
    (j,) = jump_indices(n)
    yaw0 = rng.uniform(-0.4, 0.0)
    i = np.arange(n, dtype=np.float64)
    out = np.empty((n, 8))
    out[:j] = _arc(i[:j] / max(j - 1, 1), yaw0, sweep=_JUMP_SWEEP)
    # Kidnapped back to the arc's start: sweep its first 60 % again, slower than the first time.
    s = _RETRACE * (i[j:] - j) / max(n - j - 1, 1)
    out[j:] = _arc(s, yaw0, _KIDNAP_RISE, _KIDNAP_TURN, _JUMP_SWEEP)
    return out


def _detour(n: int, rng: np.random.Generator) -> FloatArray:
    j1, j2 = detour_indices(n)
    yaw0 = rng.uniform(-0.4, 0.0)
    i = np.arange(n, dtype=np.float64)
    out = np.empty((n, 8))
    out[:j1] = _arc(i[:j1] / max(j1 - 1, 1), yaw0)
    sb = (i[j1:j2] - j1) / max(j2 - j1, 1)
    pos_b = np.stack([1.0 - 0.3 * sb, 0.7 + 0.1 * np.sin(np.pi * sb), 1.4 + 0 * sb], -1)
    out[j1:j2] = look_at(pos_b, np.pi + yaw0 + 0.4 * sb, -0.15)
    # Retrace the arc backwards, slightly raised and turned, from its end towards its middle.
    sc = 1.0 - 0.6 * (i[j2:] - j2) / max(n - j2 - 1, 1)
    out[j2:] = _arc(sc, yaw0 + 0.05, rise=0.04)
    return out


def _rotation(s: FloatArray, rng: np.random.Generator) -> FloatArray:
    pos = np.broadcast_to(np.array([0.3, -0.2, 1.4]), (len(s), 3))
    yaw0 = rng.uniform(0, 2 * np.pi)
    return look_at(
        pos,
        yaw0 + 0.9 * np.sin(2 * np.pi * s),
        -0.1 + 0.15 * np.sin(4 * np.pi * s),
        0.05 * np.sin(6 * np.pi * s),
    )


def _forward(s: FloatArray, rng: np.random.Generator) -> FloatArray:
    y0 = rng.uniform(-0.3, 0.3)
    pos = np.stack(
        [-1.6 + 3.0 * s, y0 + 0.2 * np.sin(2 * np.pi * s), 1.3 + 0.05 * np.sin(4 * np.pi * s)],
        -1,
    )
    return look_at(pos, 0.12 * np.sin(2 * np.pi * s), -0.08)


def camera_path(name: str, n_frames: int, seed: int = 0) -> FloatArray:
    """Ground-truth camera-to-world poses of a named path.

    Args:
        name: one of :data:`PATHS`.
        n_frames: number of poses (>= 2).
        seed: random seed for the path's small random variations (phase, radii, heading).

    Returns:
        (n_frames, 8) Sim(3) poses (s = 1).
    """
    if name not in PATHS:
        raise ValueError(f"name: unknown synthetic path {name!r}; choose one of {', '.join(PATHS)}")
    if int(n_frames) < 2:
        raise ValueError(f"n_frames: need at least 2 frames, got {n_frames}")
    n = int(n_frames)
    rng = np.random.default_rng([int(seed), _SEED_KEY[name], 104729])
    s = np.arange(n, dtype=np.float64) / n
    if name == "loop":
        T = _loop(s, rng)
    elif name == "jump":
        T = _jump(n, rng)
    elif name == "detour":
        T = _detour(n, rng)
    elif name == "rotation":
        T = _rotation(s, rng)
    else:
        T = _forward(np.arange(n, dtype=np.float64) / (n - 1), rng)
    # Canonical quaternion sign (w >= 0) for reproducible files.
    return sim3.from_matrix(sim3.to_matrix(T))
