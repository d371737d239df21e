"""A trained run's policy for other stages (`illm eval`, `illm collect --policy`): its network
rebuilt from the saved run (`illm_tools.rl.saved.read_run`) and acting on a pool's observations;
`policy_network` is the one place a run's network is made, for training and for loading.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from illm_tools.errors import UsageError


def policy_network(cfg, method, num_actions: int, *, image_shape: tuple, vocab_size: int, context_dim: int,
                   embedding_dim: int | None = None):
    """The network of a run of `cfg` with the method `method` (its torso and heads; `embedding_dim`:
    the text heads' width, default the run's LLM's), on the CPU."""
    from illm_tools.rl.networks import make_network

    return make_network(method, cfg.env_id, num_actions, image_shape=image_shape, vocab_size=vocab_size,
                        network_options=cfg.network_options,
                        embedding_dim=(embedding_dim or cfg.embedding_dim) if method.policy_heads else None,
                        head_hidden=cfg.bonus.head_hidden, heads_bf16=cfg.bonus.heads_bf16,
                        context_dim=context_dim, tasks=cfg.illm.tasks)


class TrainedPolicy:
    """A trained run's actor, acting on the pool's `PoolObs` (sampled, or greedy)."""

    def __init__(self, net, vocab, *, name: str, greedy: bool = False, seed: int = 0, frames: int = 0,
                 states=None):
        self.net, self.vocab, self.name, self.greedy = net.eval(), vocab, name, greedy
        self.frames = frames
        """Frames the policy was trained for."""
        self.generator = torch.Generator().manual_seed(seed)
        self.states = states
        """The run's state source (`illm_tools.rl.states`) where its network reads a context (hop's Z_h)."""
        self._last: tuple | None = None  # (observations, actions) of the last call

    @torch.no_grad()
    def act(self, obs) -> np.ndarray:
        images = torch.as_tensor(obs.images)
        missions = torch.as_tensor(self.vocab.encode(obs.missions))
        context = None
        if self.states is not None:  # the windows follow the episodes: a state with step 0 began a new one
            if self._last is not None:
                self.states.advance(self._last[0], self._last[1].tolist(), (np.asarray(obs.steps) == 0).tolist(), obs)
            context = self.states.current(obs)[1]
        logits = self.net(images, missions, context).logits
        if self.greedy:
            actions = logits.argmax(-1).numpy()
        else:
            actions = torch.multinomial(logits.softmax(-1), 1, generator=self.generator).squeeze(-1).numpy()
        self._last = obs, actions
        return actions


def load_policy(run, pool, *, greedy: bool = False, seed: int = 0) -> TrainedPolicy:
    """Rebuild a saved run's network (`run`: its folder, or its `illm_tools.rl.saved.SavedRun`) for
    `pool` (whose action list must match) and load its weights."""
    from illm_tools.intrinsic.registry import get_method
    from illm_tools.rl.saved import SavedRun, read_run
    from illm_tools.rl.states import make_states
    from illm_tools.tasks.registry import get_task

    saved = run if isinstance(run, SavedRun) else read_run(Path(run))
    cfg, state, run_dir = saved.config, saved.checkpoint, Path(saved.run_dir)
    names = list(pool.action_names)
    if state["action_names"] != names:
        raise UsageError(f"the run was trained with actions {state['action_names']}, "
                         f"the environment offers {names}; use the same --action-space")
    vocab = pool.suite.mission_vocab(cfg.mission_max_len)
    method = get_method(cfg.method)
    text_heads = [get_task(t).head for t in cfg.text_tasks]  # the iLLM heads the method's bonus put on the network
    dim = state["model"][f"{text_heads[0]}.2.weight"].shape[0] if text_heads else cfg.embedding_dim
    states = make_states(cfg, pool.suite, tuple(state["image_shape"]), names, needs_records=False,
                         num_envs=pool.num_envs)
    net = policy_network(cfg, method, len(names), image_shape=tuple(state["image_shape"]), vocab_size=len(vocab),
                         context_dim=states.context_dim, embedding_dim=dim)  # heads_bf16 as trained: no probe
    net.load_state_dict(state["model"])
    return TrainedPolicy(net, vocab, name=f"run:{run_dir.name}@{state['global_step']}",
                         greedy=greedy, seed=seed, frames=int(state["global_step"]),
                         states=states if states.context_dim else None)
