"""Named training presets: the paper's tuned settings (its appendix) and a fast demo.

The paper (Table 1) trains memoryless 2 x 128 MLPs with the goal observed, using its tuned PPO, SAC
and TD3; for Table 2 it hides the goal and trains PPO with a memory MLP (1 x 256 + memory 32), an
LSTM (2 layers x 15) and a GTrXL (embedding 8, head size 4, 2 layers, 2 heads, memory 32), each
with its own tuned reward weights. Values the paper does not give (number of envs, epochs, total
steps, TD3's gamma) are QuickNav's choices and say so in ``notes``.
"""

from __future__ import annotations

from typing import Any

from quicknav_core.config.train import TrainConfig, with_trainer_defaults

_PAPER_PPO = {
    "name": "ppo", "learning_rate": 4e-4, "num_minibatches": 256, "num_steps": 512,
    "gae_lambda": 0.93, "ent_coef": 0.0095, "clip_eps": 0.146, "gamma": 0.96, "num_epochs": 2,
}  # fmt: skip
_TABLE2_ENV = {"observe_goal": False}
# Recurrent PPO replays whole per-env sequences: the paper's 512-step rollouts in 8 minibatches gave
# 16 gradient steps per 131k env steps and no Table 2 agent left the random policy. 64-step rollouts
# (the carry still flows across them), 16 minibatches and 4 epochs give one gradient step per 256 env
# steps, as in the Table 1 PPO; with them the paper's rewards train (LSTM: 0 -> 83 % training
# success in 13M steps).
_TABLE2_PPO = {
    **_PAPER_PPO,
    "num_steps": 64,
    "num_minibatches": 16,
    "num_epochs": 4,
}
_TABLE2_NOTE = (
    "num_steps 64, num_minibatches 16 (whole env sequences), num_epochs 4 and num_envs 256 are "
    "QuickNav's: with the paper's 512-step rollouts the recurrent agents never left the random policy"
)

_PAPER_TD3 = {
    "name": "td3",
    "learning_rate": 5e-4,
    "exploration_noise": 0.44,
    "buffer_size": 50_000,
    "batch_size": 256,
    "polyak": 0.97,
    "target_noise": 0.16,
    "policy_delay": 1,
}
# the paper's tuned reward weights of each Table 2 network
_LSTM_ENV = {
    **_TABLE2_ENV,
    "reward": {"step_penalty": 0.370, "progress_reward": 0.443, "cycle_penalty": 0.203},
}
_GTRXL_ENV = {
    **_TABLE2_ENV,
    "reward": {"step_penalty": 0.232, "progress_reward": 0.291, "cycle_penalty": 0.276},
}
_PAPER_GTRXL = {
    "kind": "gtrxl", "embed_size": 8, "head_size": 4, "num_layers": 2, "num_heads": 2,
    "memory_length": 32,
}

# The building preset's env: what a robot in a real building meets, in generated floor plans only
_BUILDING_ENV = {
    "rooms": "floorplan", "grid_size": 24, "room_size": 12.0, "train_rooms": 1024,
    "test_rooms": 256, "lidar_beams": 64, "max_steps": 300,
    # a 4 m lidar range (a real scanner reaches farther; the policy reads 4 m of it): in 12 m
    # plans a 10 m beam nearly always meets a wall, so a policy trained so met open floors of real
    # buildings (beams with no return all round) as something never seen and stopped in them:
    # 10 timeouts of 13 failures in Nav2's depot at 10 m, 87 % success; 97 % at 4 m
    "lidar_max_range": 4.0,
    # doors of 1-2 cells (0.5-1 m) and 2-cell corridors: a map's 1 m door can land on a single
    # 0.5 m cell, so the policy learns the narrow doors too
    "floorplan": {"door_width": 1, "door_width_max": 2, "corridor_width": 2},
    # the robot's frame only: its pose and the goal's position in a room's frame do not carry to
    # another building; the plan's waypoints and the path left do
    "observe_pose": False, "observe_goal": False, "observe_plan": True,
    "plan_lookahead": 1, "plan_waypoints": 3,
    "obstacles": {"static": 6, "moving": 3},
    # a collision ends the episode, as it ends a robot's run; the proximity penalty keeps it off
    # walls and people before it touches them
    "end_on_collision": True,
    "reward": {"progress": "path", "collision_penalty": 3.0, "proximity_penalty": 1.0},
}  # fmt: skip

PRESETS: dict[str, dict[str, Any]] = {
    "demo": {
        "description": "Fast demo: PPO, 2x64 MLP, default 16x16 rooms with the goal observed; "
        "goes from ~0 to >90% success in about a minute on 2 CPU cores.",
        "config": {
            "env": {"train_rooms": 512, "test_rooms": 128},
            "algorithm": {
                "name": "ppo",
                "learning_rate": 1e-3,
                "num_steps": 64,
                "num_minibatches": 8,
                "num_epochs": 4,
                "gamma": 0.97,
                "ent_coef": 0.005,
            },
            "network": {"kind": "mlp", "hidden_sizes": [64, 64]},
            "num_envs": 64,
            # 367 whole updates of 64 envs x 64 steps: what 1.5M always rounded up to, now named
            # (a demo job no longer carries a "not a whole number of updates" note)
            "total_steps": 1_503_232,
            "chunk_steps": 32_768,
        },
    },
    "building": {
        "description": "Drive a building: a learned local planner (PPO, 2x128 MLP reading the last"
        " two scans) that follows the map's global plan (waypoints in the robot's frame) and"
        " avoids, by its lidar, what the map does not show (boxes, people walking). Trained on"
        " generated floor plans only: its figures on real maps are those of a building it never"
        " saw. 11 min on 2 CPU cores of an AMD EPYC or an Intel Xeon VM with AVX-512 (a slower"
        " 2-core VM took 3x as long); start here for your own building (docs: Drive a building).",
        "notes": "Everything is QuickNav's (not in the paper): the plan in the observation, the"
        " path-progress reward, the obstacles and the training budget.",
        "config": {
            "env": _BUILDING_ENV,
            "algorithm": {
                "name": "ppo", "implementation": "quicknav", "learning_rate": 3e-4,
                "num_steps": 64, "num_minibatches": 8, "num_epochs": 4, "gamma": 0.98,
                "ent_coef": 0.005,
            },
            # two frames: the scan before this one beside it, so that the policy reads how people
            # move (one frame: 88-93 % with people walking in three maps where DWA reached 94-99)
            "network": {"kind": "mlp", "hidden_sizes": [128, 128], "frames": 2},
            "num_envs": 256,
            "total_steps": 33_554_432,
            "chunk_steps": 1_048_576,
        },
    },
    "paper-ppo": {
        "description": "Table 1: PPO with the paper's tuned values, 2x128 MLP, goal observed.",
        "notes": "num_envs (256), num_epochs (2) and total_steps are QuickNav's choices (not in the paper).",
        "config": {
            "algorithm": _PAPER_PPO,
            "network": {"kind": "mlp", "hidden_sizes": [128, 128]},
            "num_envs": 256,
            "total_steps": 20_000_000,
            "chunk_steps": 1_048_576,
        },
    },
    "paper-ppo-robust": {
        "description": "paper-ppo trained for a real robot's sensor and wheels: every episode draws"
        " lidar noise, range bias, beam dropout, per-wheel speed scales and an action latency"
        " (EnvConfig.randomize).",
        "notes": "The ranges are QuickNav's choice, a margin around the levels of `quicknav eval"
        " --robustness` (noise up to 10 % of the range plus 2 cm, dropout up to 10 %, bias +-5 cm,"
        " wheels 0.9-1.1 of their command, 0-2 steps of latency); everything else is paper-ppo.",
        "config": {
            "env": {
                "randomize": {
                    "lidar_noise_frac": [0.0, 0.1],
                    "lidar_noise_m": [0.0, 0.02],
                    "lidar_bias_m": [-0.05, 0.05],
                    "beam_dropout": [0.0, 0.1],
                    "wheel_scale_left": [0.9, 1.1],
                    "wheel_scale_right": [0.9, 1.1],
                    "latency_steps": [0, 2],
                },
            },
            "algorithm": _PAPER_PPO,
            "network": {"kind": "mlp", "hidden_sizes": [128, 128]},
            "num_envs": 256,
            "total_steps": 20_000_000,
            "chunk_steps": 1_048_576,
        },
    },
    "fast-ppo": {
        "description": "Table 1 for wall-clock time: PPO, 2x128 MLP, goal observed (paper-ppo's env "
        "and network) with 64-step rollouts of 64 envs: many small updates instead of few large ones.",
        "notes": "For `quicknav bench time-to-target`: the paper's values collect 131,072 env steps per"
        " update (256 envs x 512 steps) and need about ten times the samples; the algorithm values are"
        " the demo preset's (chosen on the train bank).",
        "config": {
            "algorithm": {
                "name": "ppo",
                "learning_rate": 1e-3,
                "num_steps": 64,
                "num_minibatches": 8,
                "num_epochs": 4,
                "gamma": 0.97,
                "ent_coef": 0.005,
            },
            "network": {"kind": "mlp", "hidden_sizes": [128, 128]},
            "num_envs": 64,
            "total_steps": 3_002_368,  # 733 whole updates of 64 envs x 64 steps
            "chunk_steps": 65_536,
        },
    },
    "paper-sac": {
        "description": "Table 1: SAC with the paper's tuned values, 2x128 MLP, goal observed.",
        "notes": "num_envs and total_steps are QuickNav's choices.",
        "config": {
            "algorithm": {
                "name": "sac",
                "learning_rate": 9e-4,
                "batch_size": 512,
                "buffer_size": 500_000,
                "polyak": 0.90,
                "target_entropy_ratio": 0.82,
                "target_update_freq": 3,
                "gamma": 0.96,
            },
            "network": {"kind": "mlp", "hidden_sizes": [128, 128]},
            "num_envs": 16,
            "total_steps": 2_000_000,
            "chunk_steps": 100_000,
        },
    },
    "paper-td3": {
        "description": "Table 1: TD3 with the paper's tuned values, 2x128 MLP, goal observed.",
        "notes": "gamma (not in the paper) kept at 0.99; num_envs and total_steps are QuickNav's.",
        "config": {
            "algorithm": _PAPER_TD3,
            "network": {"kind": "mlp", "hidden_sizes": [128, 128]},
            "num_envs": 16,
            "total_steps": 2_000_000,
            "chunk_steps": 100_000,
        },
    },
    "tuned-td3": {
        "description": "Table 1, tuned: TD3 with policy delay 2, 2x128 MLP, goal observed, "
        "potential-based shaped reward (reward.progress=potential, γ 0.99).",
        "notes": "Tuned on the train bank only, under the shaped reward (benchmarks/sweeps/td3_shaped.json,"
        " trials of 3M steps, objective steps to goal with failures as the limit; stopped after its"
        " first finished trial for time): policy delay 2 (TD3's usual value; the paper's is 1),"
        " learning rate 3.5e-4, exploration noise 0.39 reached 88 % train-bank success at 3M steps."
        " Other values are paper-td3's; the reward is the one it was tuned under.",
        "config": {
            "env": {"reward": {"progress": "potential", "potential_gamma": 0.99}},
            "algorithm": {
                **_PAPER_TD3, "learning_rate": 3.54e-4, "exploration_noise": 0.386, "policy_delay": 2,
            },
            "network": {"kind": "mlp", "hidden_sizes": [128, 128]},
            "num_envs": 16,
            "total_steps": 6_000_000,
            "chunk_steps": 100_000,
        },
    },
    "paper-mlp": {
        "description": "Table 2: PPO, MLP 1x256 with memory head 32, goal hidden, tuned rewards.",
        "notes": _TABLE2_NOTE + "; dropout 0.5 of the paper not used (it breaks PPO's ratio).",
        "config": {
            "env": {
                **_TABLE2_ENV,
                "reward": {"step_penalty": 0.191, "progress_reward": 0.611, "cycle_penalty": 0.352},
            },
            "algorithm": _TABLE2_PPO,
            "network": {"kind": "mlp", "hidden_sizes": [256], "memory_size": 32},
            "num_envs": 256,
            "total_steps": 20_000_000,
            "chunk_steps": 1_048_576,
        },
    },
    "paper-lstm": {
        "description": "Table 2: PPO, LSTM 2 layers x 15, goal hidden, tuned rewards.",
        "notes": _TABLE2_NOTE + ".",
        "config": {
            "env": _LSTM_ENV,
            "algorithm": _TABLE2_PPO,
            "network": {"kind": "lstm", "num_layers": 2, "hidden_size": 15},
            "num_envs": 256,
            "total_steps": 20_000_000,
            "chunk_steps": 1_048_576,
        },
    },
    "tuned-lstm": {
        "description": "Table 2, tuned: PPO, LSTM 1 layer x 32, goal hidden, the paper-lstm rewards.",
        "notes": "Tuned on the train bank only (benchmarks/sweeps/lstm.json: 8 trials of 10M steps,"
        " objective steps to goal with failures as the limit); the best trial (1 x 32, learning"
        " rate 5.7e-4, ent_coef 0.0088) reached 89 % train-bank success at 10M steps, where no"
        " 2 x 15 or 1 x 15 trial left 0 %. " + _TABLE2_NOTE + ".",
        "config": {
            "env": _LSTM_ENV,
            "algorithm": {**_TABLE2_PPO, "learning_rate": 5.75e-4, "ent_coef": 0.00875},
            "network": {"kind": "lstm", "num_layers": 1, "hidden_size": 32},
            "num_envs": 256,
            "total_steps": 60_000_000,
            "chunk_steps": 1_048_576,
        },
    },
    "paper-gtrxl": {
        "description": "Table 2: PPO, GTrXL (embedding 8, head size 4, 2 layers, 2 heads, memory 32), goal hidden.",
        "notes": _TABLE2_NOTE + ".",
        "config": {
            "env": _GTRXL_ENV,
            "algorithm": _TABLE2_PPO,
            "network": _PAPER_GTRXL,
            "num_envs": 256,
            "total_steps": 20_000_000,
            "chunk_steps": 1_048_576,
        },
    },
    "tuned-gtrxl": {
        "description": "Table 2, tuned: PPO, GTrXL embedding 16 (head size 4, 2 layers, 2 heads, "
        "memory 32), goal hidden, the paper-gtrxl rewards.",
        "notes": "Tuned on the train bank only (benchmarks/sweeps/gtrxl.json, trials of 10M steps,"
        " objective steps to goal with failures as the limit; stopped after 2 finished trials for"
        " time): embedding 16 with learning rate 1.17e-3 and ent_coef 0.0096 reached 74 % train-bank"
        " success at 10M steps where the paper's embedding 8 (lr 5.3e-4) stayed at 0 %. "
        + _TABLE2_NOTE + ".",
        "config": {
            "env": _GTRXL_ENV,
            "algorithm": {**_TABLE2_PPO, "learning_rate": 1.17e-3, "ent_coef": 0.0096},
            "network": {**_PAPER_GTRXL, "embed_size": 16},
            "num_envs": 256,
            "total_steps": 20_000_000,
            "chunk_steps": 1_048_576,
        },
    },
}


def get_preset(name: str) -> TrainConfig:
    """The TrainConfig of a preset; unknown names raise ValueError listing the known ones."""
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; known presets: {', '.join(PRESETS)}")
    return TrainConfig.model_validate(PRESETS[name]["config"])


def preset_summaries() -> dict[str, dict[str, Any]]:
    """Every preset's description, notes, config (as written: what differs from the defaults) and
    ``resolved`` (the whole TrainConfig it gives); what ``GET /presets`` and the CLI list."""
    out = {}
    for name, p in PRESETS.items():
        out[name] = {k: p[k] for k in ("description", "notes", "config") if k in p}
        out[name]["resolved"] = with_trainer_defaults(get_preset(name)).model_dump(mode="json")
    return out
