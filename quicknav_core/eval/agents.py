"""What evaluation drives: the ``Agent`` interface and a trained policy as an agent.

An agent has per-episode state (a recurrent carry, an oracle's plan) and acts on a batch of
observations (and, for scripted agents, the env states). ``payload`` is its traced data (network
parameters); everything else is static and named by ``static_key()``, so agents that differ only
in payload share one compiled evaluation. The baselines live in ``scripted``.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

from quicknav_core.config import EnvConfig


class Agent:
    """What evaluation needs from a policy: per-episode state and a batched act."""

    name = "agent"

    @property
    def payload(self) -> Any:
        return ()

    def static_key(self) -> Any:
        return (type(self).__name__,)

    def init(self, env, params, states, payload) -> Any:
        return ()

    def act(self, agent_state, obs, states, start, key, deterministic: bool, payload):
        raise NotImplementedError


class PolicyAgent(Agent):
    """A trained policy (``quicknav_core.train.Policy``)."""

    def __init__(self, policy, name: str = "policy"):
        self.policy = policy
        self.name = name

    @property
    def payload(self):
        return self.policy.params

    def static_key(self):
        return ("policy", self.policy.kind, self.policy.module)

    def _policy(self, payload):
        return dataclasses.replace(self.policy, params=payload)

    def init(self, env, params, states, payload):
        return self.policy.initial_carry(states.pos.shape[0])

    def act(self, carry, obs, states, start, key, deterministic, payload):
        return self._policy(payload).act(carry, obs, start, key, deterministic)


def agent_from_run(path: Path) -> tuple[Agent, EnvConfig, dict[str, Any]]:
    """The trained policy of a run folder (or its checkpoint folder), with the run's env config."""
    from quicknav_core.layout import RunFolder
    from quicknav_core.train.run import load_policy

    run_dir = RunFolder.of(path).path
    config, policy, meta = load_policy(run_dir)  # the network and its parameters: no trainer
    return (
        # a run folder named by a job id is shown by its first 8 characters, as the CLI shows ids
        PolicyAgent(policy, name=f"{config.trainer_kind}:{run_dir.name[:16]}"),
        config.env,
        meta,
    )
