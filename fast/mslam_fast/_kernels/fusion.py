"""``@ti.func`` pieces of pointmap fusion; the maths is in ``mslam_ref.fusion``."""

import taichi as ti


@ti.func
def to_spherical(X):
    """(r, atan2(y, x), acos(z/r)); the origin maps to (0, 0, 0)."""
    r = X.norm()
    ct = 1.0
    if r > 0.0:
        ct = ti.min(ti.max(X[2] / r, -1.0), 1.0)
    return ti.Vector([r, ti.atan2(X[1], X[0]), ti.acos(ct)])


@ti.func
def from_spherical(S):
    st = ti.sin(S[2])
    return ti.Vector([S[0] * st * ti.cos(S[1]), S[0] * st * ti.sin(S[1]), S[0] * ti.cos(S[2])])
