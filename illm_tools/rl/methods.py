"""The training methods this layer brings to the method registry (`illm_tools.intrinsic.registry.METHODS`).

`chibit` is a policy network (`illm_tools.rl.chibit.ChibiTNet`), not a bonus, so it registers from
the layer that owns the networks rather than naming that layer from below. Light: the network is
named "module:Class" and imported on first use, so `illm train --help` lists the method without
torch. `illm_tools.rl` imports this module first thing (rl/__init__.py), so every user of the
trainer, its config or the command line sees the method.
"""

from __future__ import annotations

from illm_tools.intrinsic.registry import Method, register

CHIBIT = register(Method("chibit", "policy torso from the LLM's pretrained blocks, no bonus", None, pays_reward=False,
                         network="illm_tools.rl.chibit:ChibiTNet"))
