"""PPO with a plug-in intrinsic bonus: rollout, LLM targets, intrinsic rewards, GAE, clipped update.

Reads top to bottom like CleanRL's ppo.py, but as an importable `Trainer` over an env pool
(`illm_tools.envs.pool.EnvPool` interface) and an optional `TargetProvider`. The run's method
(`cfg.method`) names a bonus in `illm_tools.intrinsic.registry`; the trainer knows bonuses only
through `IntrinsicBonus` (base.py documents the tensors it hands them and the hooks). Per update:
  1. rollout: T steps of N envs, actions sampled from the policy, `bonus.observe` after each step,
     per-step `StateRecord`s kept when the bonus needs LLM targets;
  2. targets: the provider answers for every step of the rollout at once (cache + live fallback);
  3. bonus: `bonus.compute_rewards` on the whole rollout (iLLM: f^a / f^hc vs the targets);
  4. advantages: extrinsic GAE + intrinsic GAE on the bonus (two value heads, RND-style);
  5. update: epochs x minibatches of clipped PPO loss + value losses + the bonus's `aux_loss`;
     then `bonus.update` trains the bonus's own model (RND's predictor).
The trainer never prints: metrics go to run_dir/metrics.jsonl, TensorBoard, and `on_metrics`.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np
import torch
from torch import nn

from illm_tools.errors import OutputExistsError, UsageError
from illm_tools.folders import refuse_foreign
from illm_tools.intrinsic.base import BonusContext, BonusRewards, TargetProvider
from illm_tools.intrinsic.registry import get_method
from illm_tools.rl.bonus_schedule import BonusSchedule
from illm_tools.rl.checkpoint import CHECKPOINT_NAME, CheckpointWriter
from illm_tools.rl.config import TrainConfig
from illm_tools.rl.declared import check_resumable
from illm_tools.rl.metrics_log import Means, MetricsLog
from illm_tools.rl.policy import policy_network
from illm_tools.rl.saved import read_run, write_config
from illm_tools.rl.states import make_observers, make_states
from illm_tools.rl.storage import Advantages, Rollout, target_extras, two_stream_advantages
from illm_tools.rl.threads import frozen_heap
from illm_tools.tasks.state import StateRecord


class Trainer:
    """One training run. `train()` runs to `cfg.total_steps`; the steps are public for tests."""

    def __init__(self, cfg: TrainConfig, pool, provider: TargetProvider | None = None,
                 on_metrics: Callable[[dict], None] | None = None, checkpoint: dict | None = None):
        self.method = method = get_method(cfg.method)
        if method.needs_targets and provider is None:
            raise UsageError(f"mode {cfg.method} needs LLM targets (an annotation cache); "
                             "pass one or train with mode ppo")
        if pool.num_envs != cfg.num_envs:
            raise UsageError(f"the pool has {pool.num_envs} envs, the config asks for {cfg.num_envs}")
        if cfg.device == "auto":  # the run's (`run.train`) comes resolved; one made by hand: its choices made here
            raise UsageError("a Trainer takes a resolved config (`cfg.resolved()`: the machine's device and dtypes)")
        self.cfg, self.pool, self.on_metrics = cfg, pool, on_metrics
        self.device = torch.device(cfg.device)
        self.suite = pool.suite
        self.provider = provider if method.needs_targets else None
        self.action_names = list(pool.action_names)
        self.vocab = self.suite.mission_vocab(cfg.mission_max_len)

        # --- seeding: everything random in the run derives from cfg.seed (episode seeds too:
        # run.make_pool gives the pool cfg.seed); no global RNG is read or changed ------------------
        with torch.random.fork_rng(devices=[]):  # network init without touching global RNG state
            torch.manual_seed(cfg.seed)
            self.obs = pool.reset()
            self.image_shape = tuple(self.obs.images.shape[1:])
            self.image_dtype = torch.as_tensor(self.obs.images[:1]).dtype
            # what the run tracks beside the policy: each step's LLM state (and hop's Z_h), visit counts
            self.observers = make_observers(self.obs)
            self.states = make_states(cfg, self.suite, self.image_shape, self.action_names,
                                      needs_records=self.provider is not None, device=self.device)
            self.net = policy_network(cfg, method, len(self.action_names), image_shape=self.image_shape,
                                      vocab_size=len(self.vocab), context_dim=self.states.context_dim,
                                      ).to(self.device)  # initialised on the CPU: the same weights on any device
        self.generator = torch.Generator().manual_seed(cfg.seed + 1)  # action sampling
        self.np_rng = np.random.default_rng(cfg.seed + 2)             # minibatch order

        # fused: one kernel over every parameter (CPU and CUDA alike); iLLM's heads are 90% of the
        # parameters, and the default per-tensor step cost 1.8 ms a minibatch on them against 0.7
        self.optimizer = torch.optim.AdamW(self.net.parameters(), lr=cfg.ppo.learning_rate, eps=1e-5, fused=True)
        ctx = BonusContext(num_envs=cfg.num_envs, num_steps=cfg.num_steps, image_shape=self.image_shape,
                           num_actions=len(self.action_names), feature_dim=self.net.feature_dim,
                           int_gamma=cfg.bonus.int_gamma, seed=cfg.seed + 3,
                           observation=self.suite.observation(cfg.env_id))
        with torch.random.fork_rng(devices=[]):  # the bonus's own models: their own seeded stream
            torch.manual_seed(ctx.seed)
            self.bonus = method.build({"illm": cfg.illm}, cfg.bonus_options, ctx).to(self.device)
        if self.provider is not None:  # a bonus may read more of its provider than the stored targets (ELLM's goals)
            self.bonus.use_provider(self.provider)
        self.schedule = BonusSchedule(cfg.bonus.bonus_schedule, cfg.num_updates)  # the intrinsic advantage's weight
        self.global_step, self.update_idx = 0, 0
        self.checkpoints = CheckpointWriter(cfg.run_dir)
        self._open_run_dir(checkpoint)

    # --- run directory ----------------------------------------------------------------------
    def _open_run_dir(self, checkpoint: dict | None = None) -> None:
        cfg, run_dir = self.cfg, self.cfg.run_dir
        refuse_foreign(run_dir, "training run", "--out")
        run_dir.mkdir(parents=True, exist_ok=True)
        if cfg.resume:  # the checkpoint the run already read (`run.train`), or read here (a trainer made by hand)
            self._restore(checkpoint if checkpoint is not None else read_run(run_dir).checkpoint)
        elif (run_dir / CHECKPOINT_NAME).exists():
            raise OutputExistsError(f"{run_dir} already holds a run; pass --resume to continue it "
                                    "or choose another run dir")
        write_config(run_dir, cfg.to_dict())
        from illm_tools import provenance

        provenance.append(run_dir, from_frame=self.global_step)  # the code and command of this start
        self.log = MetricsLog(run_dir, tensorboard=cfg.tensorboard,
                              keep_until_update=self.update_idx if cfg.resume else 0)

    def state_dict(self) -> dict:
        return {
            "config": self.cfg.to_dict(), "global_step": self.global_step, "update": self.update_idx,
            "action_names": self.action_names, "image_shape": list(self.image_shape),
            "model": self.net.state_dict(), "optimizer": self.optimizer.state_dict(),
            "bonus": self.bonus.state_dict(), "bonus_schedule": self.schedule.state_dict(),
            **{observer.name: observer.state_dict() for observer in self.observers},
            "rng": {"torch": self.generator.get_state(), "numpy": self.np_rng.bit_generator.state},
        }

    def save(self, wait: bool = True) -> None:
        """Write the checkpoint (and the observers' files); `wait=False` leaves the checkpoint's
        write to finish beside the training (`CheckpointWriter`; `train` waits for it before it returns)."""
        self.checkpoints.save(self.state_dict(), wait=wait)
        for observer in self.observers:
            observer.save(self.cfg.run_dir)

    def _restore(self, state: dict) -> None:
        check_resumable(state, self.cfg, self.action_names)
        self.net.load_state_dict(state["model"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.bonus.load_state_dict(state["bonus"])
        self.schedule.load_state_dict(state.get("bonus_schedule", {}))  # a checkpoint from before: constant
        for observer in self.observers:
            if observer.name in state:
                observer.load_state_dict(state[observer.name])
        self.generator.set_state(state["rng"]["torch"])
        self.np_rng.bit_generator.state = state["rng"]["numpy"]
        self.global_step, self.update_idx = int(state["global_step"]), int(state["update"])
        # environments restart: episodes in flight at the checkpoint are not restored

    # --- 1. rollout -------------------------------------------------------------------------
    def _policy_inputs(self, obs) -> tuple[torch.Tensor, torch.Tensor]:
        return (torch.as_tensor(obs.images).to(self.device),
                torch.as_tensor(self.vocab.encode(obs.missions)).to(self.device))

    @torch.no_grad()
    def collect_rollout(self) -> tuple[Rollout, list[StateRecord], list, tuple[torch.Tensor, torch.Tensor]]:
        """T steps of every env. Returns (rollout, records t-major, the episodes that ended
        (`EpisodeStats`), next values)."""
        cfg = self.cfg
        extras = {}
        if self.states.context_dim:
            extras["contexts"] = ((self.states.context_dim,), torch.float32)
        if self.provider is not None:
            extras.update(target_extras(len(self.action_names), cfg.embedding_dim * len(cfg.text_tasks)))
        ro = Rollout.empty(cfg.num_steps, cfg.num_envs, self.image_shape, cfg.mission_max_len,
                           feature_dim=self.net.feature_dim, image_dtype=self.image_dtype, extras=extras,
                           device=self.device)
        records: list[StateRecord] = []
        episodes: list = []
        obs = self.obs
        images, missions = self._policy_inputs(obs)
        ro.observations[0], ro.mission_ids[0] = images, missions
        for t in range(cfg.num_steps):
            step_records, context = self.states.current(obs)
            if context is not None:
                ro.contexts[t] = context
            out = self.net(images, missions, context)
            logp_all = out.logits.log_softmax(-1)
            # sampled on the CPU from the run's seeded generator (the envs need the actions there anyway)
            action = torch.multinomial(logp_all.exp().cpu(), 1, generator=self.generator).squeeze(-1)
            on_device = action.to(self.device)
            if self.provider is not None:
                records.extend(step_records)
            step = self.pool.step(action.numpy())
            ends = np.logical_or(step.terminated, step.truncated)
            for observer in self.observers:
                observer.observe(step.obs)
            self.states.advance(obs, action.tolist(), ends.tolist(), step.obs)
            ro.actions[t] = on_device
            ro.logprobs[t] = logp_all.gather(1, on_device[:, None]).squeeze(1)
            ro.values_ext[t], ro.values_int[t] = out.value_ext, out.value_int
            ro.features[t] = out.features  # the bonus is computed before the update, with these same weights
            ro.rewards[t] = torch.as_tensor(step.rewards, dtype=torch.float32)
            ro.ends[t] = torch.as_tensor(ends, dtype=torch.float32)
            next_images, next_missions = self._policy_inputs(step.obs)
            ro.observations[t + 1], ro.mission_ids[t + 1] = next_images, next_missions
            self.bonus.observe({"images": images, "missions": missions, "actions": on_device, "ends": ro.ends[t],
                                "next_images": next_images, "next_missions": next_missions,
                                "features": out.features})
            episodes.extend(step.episodes)
            obs, images, missions = step.obs, next_images, next_missions
        self.obs = obs
        self.global_step += cfg.batch_size
        last = self.net(images, missions, self.states.current(obs)[1])
        return ro, records, episodes, (last.value_ext, last.value_int)

    # --- 2. targets -------------------------------------------------------------------------
    def attach_targets(self, ro: Rollout, records: list[StateRecord]) -> dict:
        """Ask the provider for every step's LLM targets and store them in the rollout."""
        if self.provider is None:
            return {"cache_hit_rate": 0.0, "target_coverage": 0.0, "live_annotations": 0.0}
        probs, emb, mask = self.provider.targets(records)
        t, n, a = ro.target_probs.shape
        d = ro.target_emb.shape[2]
        if np.shape(probs) != (t * n, a) or np.shape(emb) != (t * n, d) or np.shape(mask) != (t * n,):
            raise UsageError(f"target provider answered shapes {np.shape(probs)}, {np.shape(emb)}, "
                             f"{np.shape(mask)}; expected ({t * n}, {a}), ({t * n}, {d}), ({t * n},): "
                             "check the cache's action space and embedding dimension")
        ro.target_probs[:] = torch.as_tensor(np.asarray(probs, dtype=np.float32)).view(t, n, a)
        ro.target_emb[:] = torch.as_tensor(np.asarray(emb, dtype=np.float32)).view(t, n, d)
        ro.target_mask[:] = torch.as_tensor(np.asarray(mask, dtype=bool)).view(t, n)
        # the provider's own figures (cache hits, live annotations, its live annotator's queue) as it names them
        return {"cache_hit_rate": 0.0, "live_annotations": 0.0,
                **{k: float(v) for k, v in self.provider.stats().items()},
                "target_coverage": float(ro.target_mask.float().mean())}

    # --- 3. intrinsic rewards ---------------------------------------------------------------
    def bonus_batch(self, ro: Rollout, rows: torch.Tensor | None = None,
                    features: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """What the bonus reads (base.py): the whole rollout [T, N, ...], or flat rows `rows` [B, ...]
        with `features` (the minibatch's, with gradient) in place of the stored ones; the LLM
        targets are among the rollout's extras when the run has them, and the bonus adds what it
        reads of the policy network (`policy_outputs`: iLLM's heads)."""
        batch = ro.bonus_batch(rows, self.bonus.reads)
        if features is not None:
            batch["features"] = features
        batch.update(self.bonus.policy_outputs(self.net, batch))
        return batch

    @torch.no_grad()
    def intrinsic_rewards(self, ro: Rollout, batch: dict[str, torch.Tensor] | None = None) -> BonusRewards:
        """The bonus for every step of the rollout (iLLM: the heads' current outputs vs the stored
        targets), from `batch` = `bonus_batch(ro)` when given. Called between the rollout and the
        update, so the features stored while acting are current."""
        return self.bonus.compute_rewards(self.bonus_batch(ro) if batch is None else batch)

    # --- 4. advantages ----------------------------------------------------------------------
    def bonus_weight(self) -> float:
        """This update's factor on int_coef (`cfg.bonus.bonus_schedule`)."""
        return self.schedule.weight(max(self.update_idx, 1))

    def advantages(self, ro: Rollout, int_rewards: torch.Tensor | None,
                   next_values: tuple[torch.Tensor, torch.Tensor]) -> Advantages:
        cfg = self.cfg
        bonus = cfg.bonus
        return two_stream_advantages(ro, int_rewards, *next_values, gamma=cfg.ppo.gamma, int_gamma=bonus.int_gamma,
                                     lam=cfg.ppo.gae_lambda, ext_coef=bonus.ext_coef,
                                     int_coef=bonus.int_coef * self.bonus_weight(), int_episodic=bonus.int_episodic,
                                     streams=bonus.reward_streams, int_ext_cap=bonus.int_ext_cap)

    # --- 5. update --------------------------------------------------------------------------
    def _value_loss(self, new: torch.Tensor, old: torch.Tensor, ret: torch.Tensor) -> torch.Tensor:
        if not self.cfg.ppo.clip_vloss:
            return 0.5 * (new - ret).pow(2).mean()
        clipped = old + (new - old).clamp(-self.cfg.ppo.clip_coef, self.cfg.ppo.clip_coef)
        return 0.5 * torch.max((new - ret).pow(2), (clipped - ret).pow(2)).mean()

    def _ppo_loss(self, b: dict[str, torch.Tensor], mb: torch.Tensor, int_stream: bool):
        """(the minibatch `mb`'s PPO loss: clipped surrogate, entropy bonus, both values' losses; the
        network's outputs; its logs), as CleanRL's ppo.py computes them."""
        ppo = self.cfg.ppo
        out = self.net(b["images"][mb], b["missions"][mb], b["contexts"][mb] if "contexts" in b else None)
        logp_all = out.logits.log_softmax(-1)
        newlogprob = logp_all.gather(1, b["actions"][mb, None]).squeeze(1)
        entropy = -(logp_all.exp() * logp_all).sum(-1).mean()
        logratio = newlogprob - b["logprobs"][mb]
        ratio = logratio.exp()
        with torch.no_grad():
            approx_kl = ((ratio - 1) - logratio).mean()
            clipfrac = ((ratio - 1.0).abs() > ppo.clip_coef).float().mean()
        mb_adv = b["advantages"][mb]
        if ppo.norm_adv:
            mb_adv = (mb_adv - mb_adv.mean()) / (mb_adv.std() + 1e-8)
        pg_loss = torch.max(-mb_adv * ratio, -mb_adv * ratio.clamp(1 - ppo.clip_coef, 1 + ppo.clip_coef)).mean()
        v_loss = self._value_loss(out.value_ext, b["values_ext"][mb], b["returns_ext"][mb])
        v_loss_int = (self._value_loss(out.value_int, b["values_int"][mb], b["returns_int"][mb])
                      if int_stream else torch.zeros((), device=self.device))
        loss = pg_loss - ppo.ent_coef * entropy + ppo.vf_coef * (v_loss + v_loss_int)
        logs = {"policy_loss": pg_loss.detach(), "value_loss": v_loss.detach(), "value_loss_int": v_loss_int.detach(),
                "entropy": entropy.detach(), "approx_kl": approx_kl, "clipfrac": clipfrac}
        return loss, out, logs

    def update(self, ro: Rollout, adv: Advantages) -> dict:
        """`update_epochs` passes over the rollout in shuffled minibatches: the PPO loss, plus the
        bonus's auxiliary loss (iLLM: the heads' distillation) in the first `distill_epochs`, one
        clipped optimiser step each; early stop on the approximate KL (`target_kl`). Returns the
        losses' means over the minibatches and the extrinsic value's explained variance."""
        cfg = self.cfg
        # the rollout flattened: one row per (step, env)
        b = {name: ro.flat(name) for name in ("images", "missions", "actions", "logprobs", "values_ext", "values_int")}
        if "contexts" in ro.extras:
            b["contexts"] = ro.flat("contexts")
        b.update(advantages=adv.advantages.reshape(-1), returns_ext=adv.returns_ext.reshape(-1),
                 returns_int=adv.returns_int.reshape(-1))
        logged = Means()  # stays tensors until the update ends: on a GPU, one wait for the device per update
        inds = np.arange(cfg.batch_size)
        for epoch in range(cfg.ppo.update_epochs):
            self.np_rng.shuffle(inds)
            for start in range(0, cfg.batch_size, cfg.minibatch_size):
                mb = torch.as_tensor(inds[start:start + cfg.minibatch_size]).to(self.device)
                loss, out, logs = self._ppo_loss(b, mb, adv.int_stream)
                if self.bonus.uses_aux_loss and epoch < cfg.bonus.distill_epochs:  # the heads learn the targets
                    aux, aux_logs = self.bonus.aux_loss(self.bonus_batch(ro, mb, out.features))
                    loss = loss + cfg.bonus.distill_coef * aux
                    logs.update(aux_logs)
                self.optimizer.zero_grad()
                loss.backward()
                nn.utils.clip_grad_norm_(self.net.parameters(), cfg.ppo.max_grad_norm)
                self.optimizer.step()
                logged.add(logs)
            if cfg.ppo.target_kl is not None and float(logs["approx_kl"]) > cfg.ppo.target_kl:
                break
        # bookkeeping: the means, and how much of the return the extrinsic value explains
        result = {f"losses/{k}": v for k, v in logged.means().items()}
        y_pred, y_true = b["values_ext"].cpu().numpy(), b["returns_ext"].cpu().numpy()
        var_y = np.var(y_true)
        if var_y > 0:  # undefined for a constant return (e.g. no reward yet); left out then
            result["losses/explained_variance"] = float(1 - np.var(y_true - y_pred) / var_y)
        return result

    # --- the loop ---------------------------------------------------------------------------
    def train_one_update(self) -> dict:
        cfg = self.cfg
        self.update_idx += 1
        if cfg.ppo.anneal_lr:
            frac = 1.0 - (self.update_idx - 1.0) / cfg.num_updates
            self.optimizer.param_groups[0]["lr"] = max(frac, 0.0) * cfg.ppo.learning_rate
        t0 = time.perf_counter()
        ro, records, episodes, next_values = self.collect_rollout()
        t1 = time.perf_counter()
        target_logs = self.attach_targets(ro, records)
        t2 = time.perf_counter()
        with torch.no_grad():
            batch = self.bonus_batch(ro)
        bonus = self.intrinsic_rewards(ro, batch)
        adv = self.advantages(ro, bonus.reward if self.bonus.pays_reward else None, next_values)
        paid = (bonus.reward * (self.cfg.bonus.int_coef * self.bonus_weight())).cpu().numpy() \
            if self.bonus.pays_reward and self.observers else None
        for observer in self.observers:  # where the bonus was paid (the weighted reward, as it entered)
            observer.paid(paid)
        loss_logs = self.update(ro, adv)
        # the bonus's own model learns from the same batch (its head outputs: from before the update)
        loss_logs.update({f"losses/{k}": v for k, v in self.bonus.update(batch).items()})
        t3 = time.perf_counter()
        metrics = {"global_step": self.global_step, "update": self.update_idx,
                   "charts/learning_rate": self.optimizer.param_groups[0]["lr"],
                   "charts/bonus_weight": self.bonus_weight() if self.bonus.pays_reward else 0.0,
                   "charts/episodes": len(episodes),
                   "time/rollout_s": t1 - t0, "time/targets_s": t2 - t1, "time/update_s": t3 - t2}
        if episodes:
            metrics["charts/episodic_return"] = float(np.mean([e.episode_return for e in episodes]))
            metrics["charts/episodic_length"] = float(np.mean([e.length for e in episodes]))
            suite_figures = self.suite.episode_metrics(episodes)  # success rate, score, achievements
            metrics.update({f"charts/{k}": v for k, v in suite_figures.items() if not np.isnan(v)})
            self.schedule.observe(suite_figures.get("success_rate"))  # the next update's weight reads it
        metrics.update({f"charts/{k}": v for k, v in {**target_logs, **bonus.logs}.items()})
        metrics.update(loss_logs)
        metrics.update({f"charts/{k}": v for k, v in adv.scale_logs().items()})
        return metrics

    def train(self, should_stop: Callable[[], bool] | None = None) -> dict:
        """Run the remaining updates; returns the last update's metrics. When `should_stop()` says
        so after an update (a signal: SIGINT, SIGTERM), a checkpoint is written and the run
        returns early, its metrics marked `stopped`; `--resume` continues it."""
        cfg, metrics = self.cfg, {}
        start_step, start_time = self.global_step, time.perf_counter()
        if self.update_idx >= cfg.num_updates:
            self.log.close()
            return {"global_step": self.global_step, "already_done": True}
        saved_at = time.monotonic()
        with frozen_heap():  # the objects the run was built with: out of the collector's passes
            try:
                while self.update_idx < cfg.num_updates:
                    if should_stop is not None and should_stop():
                        if self.update_idx:
                            self.save()
                        metrics = {**metrics, "stopped": True, "global_step": self.global_step}
                        break
                    metrics = self.train_one_update()
                    metrics["charts/sps"] = (self.global_step - start_step) / (time.perf_counter() - start_time)
                    self.log.write(metrics)
                    if self.on_metrics is not None:
                        self.on_metrics(metrics)
                    last = self.update_idx == cfg.num_updates
                    due = (cfg.checkpoint_every and self.update_idx % cfg.checkpoint_every == 0) or \
                        time.monotonic() - saved_at >= 60 * cfg.checkpoint_minutes
                    if last or due or self.update_idx == 1:  # the first too: a run killed early can resume
                        self.save(wait=False)
                        saved_at = time.monotonic()
            finally:
                try:
                    self.checkpoints.wait()
                finally:
                    self.log.close()
        return metrics
