"""Densification strategies: `3dgs`, `absgs` (gsplat's DefaultStrategy) and `promptgs`."""

from .default import STRATEGY_NAMES, DefaultSchedule, ResettingDefaultStrategy, make_default_strategy

__all__ = ["STRATEGY_NAMES", "DefaultSchedule", "ResettingDefaultStrategy", "make_default_strategy"]
