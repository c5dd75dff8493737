"""Bundle adjustment — the per-stage time profile, kept apart from the LM loop.

cuda-bundle-adjustment reports eight stages (``timeProfile()``): initialize, build_structure,
compute_error, build_system, schur_complement, symbolic_decomposition,
numerical_decomposition, update_solution. The LM driver marks each stage with
``with clock("stage"):``; a :class:`StageClock` sums the seconds per stage.

Public names: StageClock.
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Iterator
from contextlib import contextmanager

__all__ = ["StageClock"]


class StageClock:
    """Seconds per named stage, summed over every ``with clock(name):`` block.

    Args:
        stages: the stage names, reported in this order (all start at 0.0).
    """

    def __init__(self, stages: Iterable[str]) -> None:
        self.totals: dict[str, float] = dict.fromkeys(stages, 0.0)

    @contextmanager
    def __call__(self, stage: str) -> Iterator[None]:
        if stage not in self.totals:
            raise KeyError(f"stage: unknown stage {stage!r}; expected one of {list(self.totals)}")
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.totals[stage] += time.perf_counter() - t0
