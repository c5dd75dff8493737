"""Synthetic data — a procedural textured room and exact, vectorised ray casting.

The scene is a closed axis-aligned room (world frame: x, y horizontal, z up, floor at z = 0)
with textured walls, floor and ceiling, a few axis-aligned boxes standing on the floor and a
few spheres. Every ray from inside the room hits a surface, so rendered depth is dense.
Ray casting is analytic (slabs for the room and boxes, a quadratic for spheres), so depth is
exact to float64 rounding: the geometric ground truth against which priors, matching and
tracking are tested.

The texture is a solid (3-D) procedural texture: a per-surface base colour modulated by
multi-scale value noise (cells of 0.9 m down to 4 cm), soft random colour blobs and a
0.5 m checker on the floor. It is rich enough for patch descriptors to discriminate and smooth
enough (smoothstep-interpolated noise) for projective matching to converge.

Public names, in reading order:
    Scene, make_scene, cast_rays, shade, render
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mslam_ref import sim3
from mslam_ref.conventions import FloatArray, IntArray, as_float_array
from mslam_ref.pointmap import camera_rays

__all__ = ["Scene", "cast_rays", "make_scene", "render", "shade"]

#: Ray parameters below this are ignored (self-intersection guard), in z-depth units.
T_MIN = 1e-9

#: Noise octaves: (frequency in 1/m, amplitude).
_OCTAVES = ((1.1, 0.45), (3.1, 0.3), (9.0, 0.18), (25.0, 0.1))


@dataclass(frozen=True, eq=False)
class Scene:
    """A procedural room.

    Attributes:
        room_min, room_max: (3,) opposite corners of the room (metres).
        boxes: (B, 2, 3) min and max corners of axis-aligned boxes.
        spheres: (S, 4) centre xyz and radius.
        colours: (6 + B + S, 3) base colour in [0, 1] per surface id (room faces x-, x+, y-,
            y+, floor, ceiling; then boxes; then spheres).
        blob_colours: (6 + B + S, 3) colour of the blobs on each surface.
        lattice: (G, G, G, 3) random values in [-1, 1] of the periodic value-noise lattice.
        seed: the seed the scene was made from.
    """

    room_min: FloatArray
    room_max: FloatArray
    boxes: FloatArray
    spheres: FloatArray
    colours: FloatArray
    blob_colours: FloatArray
    lattice: FloatArray
    seed: int

    @property
    def n_surfaces(self) -> int:
        """Number of surface ids (6 room faces + boxes + spheres)."""
        return 6 + len(self.boxes) + len(self.spheres)


def make_scene(seed: int = 0, n_boxes: int = 5, n_spheres: int = 3) -> Scene:
    """A random room of 6 m x 5 m x 2.6 m with boxes near the walls and spheres around the centre.

    Objects are kept out of the central region ``(x/1.6)^2 + (y/1.3)^2 < 1`` above 1.05 m, where
    the camera paths run, so no camera starts inside an object.

    Args:
        seed: random seed; the same seed gives the same scene.
        n_boxes, n_spheres: object counts.

    Returns:
        a :class:`Scene`.
    """
    rng = np.random.default_rng([int(seed), 7919])
    room_min = np.array([-3.0, -2.5, 0.0])
    room_max = np.array([3.0, 2.5, 2.6])
    boxes = []
    for _ in range(n_boxes):
        ang = rng.uniform(0, 2 * np.pi)
        r = rng.uniform(1.9, 2.3)
        c = np.array([2.4 * np.cos(ang), 1.95 * np.sin(ang)]) * r / 2.3
        half = rng.uniform([0.2, 0.2], [0.45, 0.45])
        h = rng.uniform(0.4, 1.0)
        lo = np.clip(np.r_[c - half, 0.0], room_min + 0.05, room_max - 0.05)
        hi = np.clip(np.r_[c + half, h], room_min + 0.05, room_max - 0.05)
        lo[2] = 0.0
        boxes.append(np.stack([lo, hi]))
    spheres = []
    for _ in range(n_spheres):
        ang = rng.uniform(0, 2 * np.pi)
        rad = rng.uniform(0.2, 0.4)
        c = np.array([2.0 * np.cos(ang), 1.6 * np.sin(ang), rng.uniform(0.6, 2.0)])
        spheres.append(np.r_[c, rad])
    n = 6 + n_boxes + n_spheres
    colours = rng.uniform(0.25, 0.9, size=(n, 3))
    blob_colours = rng.uniform(0.05, 1.0, size=(n, 3))
    lattice = rng.uniform(-1.0, 1.0, size=(32, 32, 32, 3))
    return Scene(
        room_min=room_min,
        room_max=room_max,
        boxes=np.array(boxes, dtype=np.float64).reshape(-1, 2, 3),
        spheres=np.array(spheres, dtype=np.float64).reshape(-1, 4),
        colours=colours,
        blob_colours=blob_colours,
        lattice=lattice,
        seed=int(seed),
    )


def _safe_inv(d: FloatArray) -> FloatArray:
    """1/d with exact zeros replaced by a huge number of positive sign (no NaN in slabs)."""
    return 1.0 / np.where(d == 0.0, 1e-300, d)


def cast_rays(scene: Scene, origin: FloatArray, dirs: FloatArray) -> tuple[FloatArray, IntArray]:
    """First intersection of rays ``o + t d`` (t > 0) with the scene.

    The direction need not be unit: with ``d = R_WC [x, y, 1]`` the returned ``t`` is the camera
    z-depth of the hit point. The origin must lie inside the room.

    Args:
        origin: (3,) or (N, 3) ray origins.
        dirs: (N, 3) ray directions.

    Returns:
        t: (N,) ray parameter of the first hit (finite: the room is closed).
        sid: (N,) surface id of the hit (see :class:`Scene`).
    """
    d = as_float_array(dirs, "dirs", 3)
    o = np.broadcast_to(as_float_array(origin, "origin", 3), d.shape)
    if np.any(o < scene.room_min) or np.any(o > scene.room_max):
        raise ValueError("origin: ray origins must lie inside the room")
    inv = _safe_inv(d)
    # Room: exit through the nearest wall along each axis.
    t_hi = (scene.room_max - o) * inv
    t_lo = (scene.room_min - o) * inv
    t_axis = np.where(d > 0, t_hi, t_lo)
    t_axis = np.where(d == 0.0, np.inf, t_axis)
    axis = np.argmin(t_axis, axis=-1)
    t = np.take_along_axis(t_axis, axis[:, None], -1)[:, 0]
    sid = 2 * axis + (np.take_along_axis(d, axis[:, None], -1)[:, 0] > 0)
    for b, (lo, hi) in enumerate(scene.boxes):
        t1 = (lo - o) * inv
        t2 = (hi - o) * inv
        tn = np.minimum(t1, t2).max(axis=-1)
        tf = np.maximum(t1, t2).min(axis=-1)
        hit = (tn <= tf) & (tn > T_MIN) & (tn < t)
        t = np.where(hit, tn, t)
        sid = np.where(hit, 6 + b, sid)
    for k, sph in enumerate(scene.spheres):
        oc = o - sph[:3]
        a = np.einsum("ni,ni->n", d, d)
        bh = np.einsum("ni,ni->n", d, oc)
        c = np.einsum("ni,ni->n", oc, oc) - sph[3] ** 2
        disc = bh * bh - a * c
        sq = np.sqrt(np.maximum(disc, 0.0))
        tn = (-bh - sq) / a
        hit = (disc >= 0) & (tn > T_MIN) & (tn < t)
        t = np.where(hit, tn, t)
        sid = np.where(hit, 6 + len(scene.boxes) + k, sid)
    return t, sid.astype(np.int64)


def _value_noise(lattice: FloatArray, p: FloatArray) -> FloatArray:
    """Smoothstep-interpolated value noise on a periodic lattice; (N, 3) -> (N, C)."""
    G = lattice.shape[0]
    flat = np.ascontiguousarray(lattice).reshape(G**3, -1)
    pf = np.floor(p)
    f = p - pf
    w1 = f * f * (3.0 - 2.0 * f)
    w0 = 1.0 - w1
    i0 = pf.astype(np.int64) % G
    i1 = (i0 + 1) % G
    out = np.zeros((len(p), flat.shape[1]))
    for ix, wx in ((i0[:, 0], w0[:, 0]), (i1[:, 0], w1[:, 0])):
        for iy, wy in ((i0[:, 1], w0[:, 1]), (i1[:, 1], w1[:, 1])):
            ixy, wxy = (ix * G + iy) * G, wx * wy
            for iz, wz in ((i0[:, 2], w0[:, 2]), (i1[:, 2], w1[:, 2])):
                out += (wxy * wz)[:, None] * flat[ixy + iz]
    return out


def shade(scene: Scene, P: FloatArray, sid: IntArray) -> FloatArray:
    """Colour of surface points (a solid procedural texture, no lighting).

    ``colour = base[sid] · (0.62 + Σ_o a_o n(f_o p + off)) `` blended with ``blob[sid]`` where a
    low-frequency noise channel exceeds a threshold, times a 0.5 m checker (0.8 / 1.0) on the floor.

    Args:
        P: (N, 3) world points; sid: (N,) surface ids.

    Returns:
        (N, 3) colours in [0, 1].
    """
    off = sid[:, None] * np.array([7.31, 3.17, 5.03])
    q = P + off
    lat3, lat1 = scene.lattice, scene.lattice[..., :1]
    n = np.zeros((len(P), 1))
    for k, (freq, amp) in enumerate(_OCTAVES):
        # Colour variation at the coarse octaves, grey detail at the fine ones (cheaper).
        n = n + amp * _value_noise(lat3 if k < 2 else lat1, q * freq + 11.0 * amp)
    grey = n.mean(axis=1, keepdims=True)
    base = scene.colours[sid] * (0.62 + 0.8 * grey) + 0.25 * (n - grey)
    blob = _value_noise(scene.lattice[..., 1:2], q * 1.7 + 3.3)
    m = np.clip((blob - 0.15) / 0.2, 0.0, 1.0)
    m = m * m * (3.0 - 2.0 * m)
    col = (1.0 - m) * base + m * scene.blob_colours[sid] * (0.7 + 0.6 * grey)
    floor = sid == 4
    checker = (np.floor(P[:, 0] / 0.5) + np.floor(P[:, 1] / 0.5)) % 2
    col[floor] *= (0.8 + 0.2 * checker[floor])[:, None]
    return np.clip(col, 0.0, 1.0)


def render(
    scene: Scene, T_WC: FloatArray, K: FloatArray, width: int, height: int
) -> tuple[np.ndarray, FloatArray, IntArray]:
    """Render RGB, z-depth and surface ids by casting one ray through every pixel centre.

    The ray of pixel (u, v) is ``o = t_WC``, ``d = s R_WC [(u - cx)/fx, (v - cy)/fy, 1]`` so the
    hit parameter equals the camera z-depth exactly.

    Args:
        T_WC: (8,) Sim(3) camera-to-world pose; K: (3, 3) intrinsics; width, height: image size.

    Returns:
        rgb: (H, W, 3) uint8; depth: (H, W) float64 metres; sid: (H, W) int64 surface ids.
    """
    M = sim3.to_matrix(as_float_array(T_WC, "T_WC", 8))
    rays = camera_rays(K, height, width).reshape(-1, 3)
    dirs = rays @ M[:3, :3].T
    t, sid = cast_rays(scene, M[:3, 3], dirs)
    P = M[:3, 3] + t[:, None] * dirs
    col = shade(scene, P, sid)
    rgb = np.round(col * 255.0).astype(np.uint8).reshape(height, width, 3)
    return rgb, t.reshape(height, width), sid.reshape(height, width)
