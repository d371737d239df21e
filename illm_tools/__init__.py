"""illm: offline LLM annotation and distillation for exploration in reinforcement learning (iLLM)."""

__version__ = "0.1.0"
