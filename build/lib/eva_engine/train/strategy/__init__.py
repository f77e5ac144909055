"""Adaptive density control as swappable strategies with explicit state (gsplat's design)."""

from eva_engine.train.strategy import ops
from eva_engine.train.strategy.base import Strategy
from eva_engine.train.strategy.context import ContextAwareStrategy
from eva_engine.train.strategy.default import DefaultStrategy
from eva_engine.train.strategy.kl import KLStrategy

__all__ = ["ContextAwareStrategy", "DefaultStrategy", "KLStrategy", "Strategy", "ops"]
