"""iLLM(hop): language-driven exploration for observations without text (paper Algorithm 1, B.1,
D.7). Observations are not described in words but translated into the LLM's token-embedding space
by a frozen Hopfield layer (`translate.FrozenHopfield`, after HELM's FrozenHopfield), and the LLM
reads the translated steps as input embeddings (`context.HopContext`):

- the policy sees concat(torso(o_t), Z_h), Z_h the LLM's last hidden state after reading the last
  K translated steps (computed in the rollout, every step);
- the language tasks (B.2's prompts) read the same translated steps spliced in place of the
  written history (`illm_tools.annotate.engine`'s hop path), so the cache answers with the LLM's
  next-action ranking and 64-token summary exactly as in text mode;
- cache keys hash what determines the translation: the window's raw observation bytes and
  previous actions, the projection's seed, beta, the window and the model (`illm_tools.tasks.annotation_setup.hop_renderer`).
"""
