"""Policy networks with one recurrent interface (Flax linen).

Every network is called as ``net.apply(params, carry, obs, start)`` with a batch of observations
``obs (B, obs_dim)`` and episode-start flags ``start (B,)``, and returns
``(new_carry, PolicyOutput(mean, log_std, value))``. Wherever ``start`` is true the carry is first
reset to ``net.initial_carry(B)``'s value, so a carry never leaks across an episode start.
Memoryless networks use an empty carry. ``make_network(NetworkConfig, action_dim)`` builds one.
"""

from quicknav_core.networks.common import PolicyOutput, gaussian_entropy, gaussian_log_prob
from quicknav_core.networks.factory import make_network

__all__ = [
    "PolicyOutput",
    "gaussian_entropy",
    "gaussian_log_prob",
    "make_network",
]
