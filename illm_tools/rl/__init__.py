"""PPO for iLLM: configuration, networks, rollout storage, the trainer and run-dir checkpoints."""

from illm_tools.rl.checkpoint import load_checkpoint, load_policy
from illm_tools.rl.config import TrainConfig
from illm_tools.rl.networks import GridMissionNet, MissionVocab
from illm_tools.rl.ppo import Trainer, make_pool
from illm_tools.rl.storage import Rollout, gae, two_stream_advantages

__all__ = [
    "GridMissionNet", "MissionVocab", "Rollout", "TrainConfig", "Trainer", "gae", "load_checkpoint",
    "load_policy", "make_pool", "two_stream_advantages",
]
