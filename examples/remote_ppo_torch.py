"""A PyTorch PPO agent that trains on QuickNav envs served over gRPC (`RemoteVectorEnv`).

The learner needs no JAX: only torch, gymnasium and the QuickNav SDK. Start a server, then:

    uv run quicknav rollout-server                     # or `quicknav serve`, or docker compose
    pip install torch "quicknav-client[gym]"           # in the learner's environment
    python examples/remote_ppo_torch.py --target 127.0.0.1:50051 --steps 500000

It prints, per update, the env steps so far, the success rate and mean return of the episodes
that ended in that update, and the throughput. The defaults (an 8x8-cell room, 64 envs) learn in
a few minutes on a laptop CPU.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
from quicknav_client.gym import RemoteVectorEnv
from torch import nn


class ActorCritic(nn.Module):
    def __init__(self, obs_dim: int, hidden: int = 128):
        super().__init__()

        def mlp(out: int) -> nn.Sequential:
            return nn.Sequential(nn.Linear(obs_dim, hidden), nn.Tanh(), nn.Linear(hidden, hidden),
                                 nn.Tanh(), nn.Linear(hidden, out))  # fmt: skip

        self.pi, self.v = mlp(2), mlp(1)
        self.log_std = nn.Parameter(torch.full((2,), -0.5))

    def dist(self, obs: torch.Tensor) -> torch.distributions.Normal:
        return torch.distributions.Normal(self.pi(obs), self.log_std.exp())

    def value(self, obs: torch.Tensor) -> torch.Tensor:
        return self.v(obs).squeeze(-1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--target", default="127.0.0.1:50051")
    ap.add_argument("--token", default=None)
    ap.add_argument("--envs", type=int, default=64)
    ap.add_argument("--steps", type=int, default=500_000, help="env steps to train for")
    ap.add_argument("--grid-size", type=int, default=8)
    ap.add_argument("--rollout", type=int, default=128, help="steps per env per update")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    torch.manual_seed(args.seed)
    torch.set_num_threads(1)
    env = RemoteVectorEnv(args.target, num_envs=args.envs, seed=args.seed, token=args.token,
                          config={"grid_size": args.grid_size, "max_steps": 200})  # fmt: skip
    n, t_len = env.num_envs, args.rollout
    obs_dim = env.single_observation_space.shape[0]
    net = ActorCritic(obs_dim)
    opt = torch.optim.Adam(net.parameters(), lr=3e-4, eps=1e-5)
    gamma, lam, clip, epochs, minibatches = 0.99, 0.95, 0.2, 4, 4

    obs, _ = env.reset(seed=args.seed)
    obs = torch.as_tensor(obs)
    steps, start = 0, time.time()
    print(f"{'env steps':>10} {'success':>8} {'return':>8} {'episodes':>8} {'steps/s':>8}")
    while steps < args.steps:
        buf_obs = torch.zeros(t_len, n, obs_dim)
        buf_act, buf_logp = torch.zeros(t_len, n, 2), torch.zeros(t_len, n)
        buf_rew, buf_done, buf_val = (
            torch.zeros(t_len, n),
            torch.zeros(t_len, n),
            torch.zeros(t_len, n),
        )
        ep_ret, ended, succeeded, returns = np.zeros(n), 0, 0, []
        for t in range(t_len):
            with torch.no_grad():
                d = net.dist(obs)
                action = d.sample()
                buf_val[t] = net.value(obs)
            buf_obs[t], buf_act[t], buf_logp[t] = obs, action, d.log_prob(action).sum(-1)
            next_obs, reward, terminated, truncated, info = env.step(action.clamp(-1, 1).numpy())
            reward = torch.as_tensor(reward)
            # a truncated episode did not end in the task: bootstrap from its final observation
            if truncated.any():
                idx = np.flatnonzero(truncated)
                final = torch.as_tensor(np.stack(info["final_obs"][idx]))
                with torch.no_grad():
                    reward[idx] += gamma * net.value(final)
            done = terminated | truncated
            buf_rew[t], buf_done[t] = reward, torch.as_tensor(done, dtype=torch.float32)
            ep_ret += reward.numpy()
            for i in np.flatnonzero(done):
                ended += 1
                succeeded += int(terminated[i])
                returns.append(ep_ret[i])
                ep_ret[i] = 0.0
            obs = torch.as_tensor(next_obs)
            steps += n

        # GAE over the rollout; `done` cuts the bootstrap at episode ends (the env auto-resets)
        with torch.no_grad():
            next_value = net.value(obs)
        adv = torch.zeros(t_len, n)
        last = torch.zeros(n)
        for t in reversed(range(t_len)):
            nv = next_value if t == t_len - 1 else buf_val[t + 1]
            nonterminal = 1.0 - buf_done[t]
            delta = buf_rew[t] + gamma * nv * nonterminal - buf_val[t]
            last = delta + gamma * lam * nonterminal * last
            adv[t] = last
        ret = adv + buf_val

        b_obs, b_act = buf_obs.reshape(-1, obs_dim), buf_act.reshape(-1, 2)
        b_logp, b_adv, b_ret = buf_logp.reshape(-1), adv.reshape(-1), ret.reshape(-1)
        size = b_obs.shape[0]
        for _ in range(epochs):
            for mb in torch.randperm(size).chunk(minibatches):
                d = net.dist(b_obs[mb])
                ratio = (d.log_prob(b_act[mb]).sum(-1) - b_logp[mb]).exp()
                a = (b_adv[mb] - b_adv[mb].mean()) / (b_adv[mb].std() + 1e-8)
                pg = -torch.min(ratio * a, ratio.clamp(1 - clip, 1 + clip) * a).mean()
                vf = 0.5 * (net.value(b_obs[mb]) - b_ret[mb]).pow(2).mean()
                loss = pg + 0.5 * vf
                opt.zero_grad()
                loss.backward()
                nn.utils.clip_grad_norm_(net.parameters(), 0.5)
                opt.step()
        rate = succeeded / max(ended, 1)
        mean_ret = float(np.mean(returns)) if returns else float("nan")
        print(f"{steps:>10,} {rate:>8.2f} {mean_ret:>8.1f} {ended:>8} "
              f"{steps / (time.time() - start):>8,.0f}", flush=True)  # fmt: skip
    env.close()


if __name__ == "__main__":
    main()
