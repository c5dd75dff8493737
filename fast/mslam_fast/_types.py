"""Taichi parameter annotations, with the types the type checker sees.

Taichi reads a kernel's parameter annotations at run time and needs its own objects there
(``ti.types.ndarray()``, ``ti.template()``, ``ti.f64``); they are values, not types. For mypy an
ndarray or template argument is ``Any`` (Taichi indexes it inside a kernel with its own rules,
which ``numpy.typing`` cannot express) and an ``f64`` scalar is a ``float``.
"""

from typing import TYPE_CHECKING, Any, TypeAlias

import taichi as ti

if TYPE_CHECKING:
    nd: TypeAlias = Any
    template: TypeAlias = Any
    f64: TypeAlias = float
else:
    #: A ``ti.types.ndarray()`` kernel parameter (any dtype and number of dimensions).
    nd = ti.types.ndarray()
    #: A ``ti.template()`` parameter: compiled per value (a ``ti.static`` size, a field, a func).
    template = ti.template()
    #: A scalar kernel parameter in float64.
    f64 = ti.f64
