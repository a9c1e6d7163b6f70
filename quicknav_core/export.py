"""A trained policy as a file a robot runs without JAX: ``policy.onnx`` and its ``policy.json``.

The converter is jax2onnx (maintained, converts a jitted JAX function primitive by primitive,
symbolic batch axes, opset 23); writing ONNX graphs by hand would duplicate every network. What
is exported is the policy's deterministic step, the same function ``quicknav eval`` drives:

    inputs   obs (B, obs_dim) float32, [start (B,) bool, state_0, state_1, ...]   (recurrent only)
    outputs  action (B, 2) float32 in [-1, 1], [next_state_0, next_state_1, ...]

``start`` is true on an episode's first step: the network resets that env's state to its initial
value inside the graph, exactly as in training, so a caller may pass any state then. ``B`` is
dynamic. ``policy.json`` says what every slice of ``obs`` means and how it is normalised, the beam
angles, what the action means in m/s, the state's names, shapes and initial values, the env config,
the training provenance and the held-out success.

    uv run quicknav export RUN_DIR --out DIR
"""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from quicknav_core.env.constants import PATH_SCALE_M, observation_parts
from quicknav_core.layout import RUN, RunFolder
from quicknav_core.runtime import runtime_or_new

ONNX_FILE, MANIFEST_FILE = RUN.policy, RUN.manifest  # the layout's names
MAP_FILE = "map.npz"  # with --map: the map as the policy sees it
START_DOC = "bool (B,): true on an episode's first step; the network resets that env's state itself"
FORMAT_VERSION = 1
OPSET = 23


def policy_step(policy, obs_dim: int) -> tuple[Any, list[jax.ShapeDtypeStruct], list[str], list[str]]:
    """(fn, input specs with a batch of 1, input names, output names) of a ``Policy``'s
    deterministic step with its state as explicit, flat inputs and outputs."""
    leaves, treedef = jax.tree.flatten(policy.initial_carry(1))
    specs = [jax.ShapeDtypeStruct((1, obs_dim), jnp.float32)]
    names = ["obs"]
    state_names = [f"state_{i}" for i in range(len(leaves))]
    if leaves:
        specs.append(jax.ShapeDtypeStruct((1,), jnp.bool_))
        names.append("start")
        specs += [jax.ShapeDtypeStruct(leaf.shape, leaf.dtype) for leaf in leaves]
        names += state_names

    def step(obs, *rest):
        if not leaves:
            _, action = policy.act((), obs, None, None, deterministic=True)
            return action
        start, state = rest[0], jax.tree.unflatten(treedef, rest[1:])
        state, action = policy.act(state, obs, start, None, deterministic=True)
        return (action, *jax.tree.leaves(state))

    return step, specs, names, ["action"] + [f"next_{n}" for n in state_names]


# jax2onnx's plugin trees that QuickNav's policies need: flax linen networks over jax primitives
PLUGIN_TREES = ("jax", "flax")


def import_onnx_plugins() -> None:
    """Import the jax2onnx plugins a QuickNav policy's conversion uses, and only those.

    On its first conversion jax2onnx imports every module under ``jax2onnx.plugins`` (its
    ``import_all_plugins``), equinox's plugins and the examples too: ~2 s of every export on a
    2-core AMD EPYC VM, most of it in the equinox tree, none of it used here. This imports the
    ``PLUGIN_TREES`` with jax2onnx's own walker and marks the import as done. A jax2onnx without
    that walker or flag (another version) keeps its own full import. The export's parity check
    (``check_parity``) and the tests' exports of every network kind hold the conversion to the
    JAX policy, so a plugin left out would fail there, loudly."""
    try:
        from jax2onnx.plugins import plugin_system as plugins
    except ImportError:  # pragma: no cover - jax2onnx moved it: its own import runs
        return
    walk = getattr(plugins, "_import_tree", None)
    if walk is None or getattr(plugins, "_already_imported_plugins", None) is not False:
        return  # done already, or a jax2onnx this does not know
    root = Path(plugins.__file__).parent
    for tree in PLUGIN_TREES:
        walk(root / tree, f"jax2onnx.plugins.{tree}")
    plugins._already_imported_plugins = True


def to_onnx_model(policy, obs_dim: int):
    """The ONNX model of a policy's deterministic step, batch axis ``B`` dynamic."""
    from jax import export
    from jax2onnx import to_onnx

    import_onnx_plugins()
    step, specs, names, outputs = policy_step(policy, obs_dim)
    (batch,) = export.symbolic_shape("B")
    inputs = [jax.ShapeDtypeStruct((batch, *s.shape[1:]), s.dtype) for s in specs]
    # onnx_ir warns about untyped shape constants it leaves out of the file; nothing to act on
    quiet = logging.getLogger("onnx_ir.serde")
    level = quiet.level
    quiet.setLevel(logging.ERROR)
    try:
        return to_onnx(step, inputs, model_name="quicknav_policy", opset=OPSET,
                       input_names=names, output_names=outputs)  # fmt: skip
    finally:
        quiet.setLevel(level)


# --------------------------------------------------------------------------- the manifest
def _part_meanings(env) -> dict[str, tuple[str, str, str]]:
    """(meaning, units, normalisation) of every part ``observation_parts`` can name."""
    room, max_range = env.room_size, env.lidar_max_range
    cell = env.room_size / env.grid_size
    w, look = env.plan_waypoints, env.plan_lookahead
    return {
        "position": ("robot x, y in the room frame", "m", f"divided by room_size ({room:g} m)"),
        "heading": ("sin(theta), cos(theta) of the robot's heading in the room frame", "1", "none"),
        "ranges": ("lidar range per beam (beam_angles_rad order), capped at lidar_max_range", "m",
                   f"divided by lidar_max_range ({max_range:g} m): 1.0 = no return"),
        "wall_hits": ("1.0 where the beam's return is a wall", "1", "none"),
        "goal_hits": ("1.0 where the beam's return is the goal disc (a real lidar does not see"
                      " goals: leave 0, or draw the goal disc as OnnxPolicy does)", "1", "none"),
        "goal_position": ("goal x, y in the room frame", "m", f"divided by room_size ({room:g} m)"),
        "goal_distance": ("distance robot-goal", "m", f"divided by room_size ({room:g} m)"),
        "goal_bearing": ("sin, cos of the goal's bearing in the robot frame (counter-clockwise"
                         " from straight ahead)", "1", "none (sin 0, cos 1 at the goal)"),
        "waypoints": (f"{w} waypoint(s) of the global plan in the robot frame, (forward, left)"
                      f" each: the centre of the cell i * {look} steps down the shortest 8-connected"
                      " path of cells where the robot's disc fits (the goal itself once the path"
                      " reaches the goal's cell)", "m",
                      f"waypoint i divided by (i * {look} + 1) * sqrt(2) * cell ({cell:g} m),"
                      " clipped to [-1, 1]"),
        "path_left": ("length of that path from the robot's cell to the goal's", "m",
                      f"tanh(length / {PATH_SCALE_M:g} m)"),
    }  # fmt: skip


def observation_layout(env) -> list[dict[str, Any]]:
    """Every slice of the flat observation: name, slice, meaning, units, normalisation (in the
    order of ``constants.observation_parts``, the one description the env follows)."""
    meanings, layout, start = _part_meanings(env), [], 0
    for name, low, _ in observation_parts(env):
        meaning, units, normalisation = meanings[name]
        layout.append({"name": name, "slice": [start, start + len(low)], "meaning": meaning,
                       "units": units, "normalisation": normalisation})  # fmt: skip
        start += len(low)
    return layout


def manifest(config, policy, meta: dict[str, Any], provenance: dict[str, Any],
             success: dict[str, Any] | None) -> dict[str, Any]:  # fmt: skip
    """What a robot's code needs to feed ``policy.onnx`` and to read its answer."""
    from quicknav_core.env.constants import beam_angles

    env = config.env
    _, specs, names, outputs = policy_step(policy, env.obs_dim)
    initial = jax.tree.leaves(policy.initial_carry(1))
    state = [{"input": n, "output": f"next_{n}", "shape": ["B", *s.shape[1:]],
              "dtype": str(np.dtype(s.dtype)), "initial": _initial_value(v)}
             for n, s, v in zip(names[2:], specs[2:], initial, strict=True)]  # fmt: skip
    angles = [float(a) for a in np.asarray(beam_angles(env.lidar_beams, env.lidar_fov_deg))]
    return {
        "format": "quicknav-policy", "format_version": FORMAT_VERSION,
        "onnx": {"file": ONNX_FILE, "opset": OPSET, "inputs": names, "outputs": outputs,
                 "batch_axis": "B (dynamic)"},
        "network": config.network.model_dump(mode="json"),
        "trainer": config.trainer_kind,
        "observation": {"size": env.obs_dim, "dtype": "float32", "layout": observation_layout(env)},
        "lidar": {"beams": env.lidar_beams, "beam_angles_rad": angles,
                  "angles_measured": "counter-clockwise from the robot's heading",
                  "fov_deg": env.lidar_fov_deg, "max_range_m": env.lidar_max_range},
        "action": {"size": 2, "names": ["left_wheel", "right_wheel"], "range": [-1.0, 1.0],
                   "meaning": "wheel speed / max_wheel_speed, deterministic (the policy's mean),"
                   " already clipped to [-1, 1]",
                   "to_mps": f"multiply by max_wheel_speed = {env.max_wheel_speed:g} m/s",
                   "max_wheel_speed_mps": env.max_wheel_speed, "wheel_base_m": env.wheel_base,
                   "control_period_s": env.dt},
        "recurrent": bool(state),
        "start": START_DOC if state else None,
        "state": state,
        "env": env.model_dump(mode="json"),
        "provenance": provenance,
        "held_out": success,
        "meta": {k: meta[k] for k in ("env_steps", "updates") if k in meta},
    }  # fmt: skip


def _initial_value(value) -> Any:
    """An initial state described without shipping it: every entry is this one value."""
    arr = np.asarray(value)
    first = arr.reshape(-1)[0].item() if arr.size else 0
    if not np.all(arr == first):
        raise ValueError("a state whose initial value is not one constant cannot be described")
    return bool(first) if arr.dtype == bool else float(first)


# --------------------------------------------------------------------------- a run folder
def check_robot_map(map_path: str | Path) -> None:
    """MapError unless ``map_path`` is a map a robot localises in: a map_server YAML (its origin
    is the map frame of poses and goals, which a picture alone does not have)."""
    from quicknav_core.env.maps import YAML_SUFFIXES, MapError

    if Path(map_path).suffix.lower() not in YAML_SUFFIXES:
        raise MapError(f"{map_path}: export --map takes the map_server .yaml the robot localises in:"
                       " its origin is the map frame poses and goals are given in, which a picture"
                       " alone does not have; write one naming the picture (image, resolution,"
                       " origin, mode), or export the map_server pair the robot uses")  # fmt: skip


def export_run(run_dir: Path, out_dir: Path, provenance: dict[str, Any] | None = None,
               map_path: str | Path | None = None) -> dict[str, Any]:
    """Write ``policy.onnx`` and ``policy.json`` of a run folder's last checkpoint into ``out_dir``
    (checked by onnxruntime against the JAX policy on random observations before returning).
    The policy is read from the checkpoint without building the run's trainer (``load_policy``).
    ``map_path``: a map the robot drives, written as the policy sees it (``map.npz``, and the
    manifest's ``map``: its frame) for ``quicknav_client.navigate.Navigator``."""
    from quicknav_core.train.run import load_policy

    if map_path is not None:
        check_robot_map(map_path)
    run_dir, out_dir = Path(run_dir), Path(out_dir)
    config, policy, meta = load_policy(run_dir)
    fit = None
    if map_path is not None:
        from quicknav_core.eval.map_fit import fit_map

        fit = fit_map(config.env, map_path)  # before the model: a map that cannot be driven fails fast
    model = to_onnx_model(policy, config.env.obs_dim)
    out_dir.mkdir(parents=True, exist_ok=True)
    tmp = out_dir / (ONNX_FILE + ".tmp")
    tmp.write_bytes(model.SerializeToString())
    worst = check_parity(policy, tmp, config.env.obs_dim, samples=1000)
    if not worst <= 1e-5:
        tmp.unlink(missing_ok=True)
        raise RuntimeError(f"the exported policy differs from the JAX one by {worst:.2e} (> 1e-5)")
    tmp.replace(out_dir / ONNX_FILE)
    success = _held_out(run_dir, config.env.model_dump(mode="json"))
    info = {"run": run_dir.name, **(provenance or {}),
            "env_steps": meta.get("env_steps"), "seed": config.seed}  # fmt: skip
    doc = manifest(config, policy, meta, info, success)
    if fit is not None:
        np.savez_compressed(out_dir / MAP_FILE, walls=fit.walls)
        doc["map"] = map_entry(fit)
    else:
        (out_dir / MAP_FILE).unlink(missing_ok=True)
    (out_dir / MANIFEST_FILE).write_text(json.dumps(doc, indent=2))
    return doc


def map_entry(fit) -> dict[str, Any]:
    """The manifest's ``map``: the exported grid and how its frame sits in the map's."""
    return {
        "file": MAP_FILE, "source": Path(fit.path).name,
        "walls": "map.npz['walls']: (rows, cols) bool, True = wall; row r spans y in [r, r+1) * cell_m"
                 " of the grid frame, column c spans x",
        "cell_m": fit.cell_m, "grid": list(fit.grid_shape),
        "origin": list(fit.origin),
        "grid_corner_in_map": list(fit.grid_corner_in_map),
        "frame": "poses and goals in the map frame (the YAML's origin frame, as tf2 gives map ->"
                 " base_link) minus grid_corner_in_map are the grid frame the policy drives in",
        "free_kept": round(fit.free_kept, 4), "longest_path_m": round(fit.longest_path_m, 2),
        "max_steps": fit.max_steps,
    }  # fmt: skip


HELD_OUT_FIELDS = ("episodes", "success_rate", "success_ci95", "spl")


def _held_out(run_dir: Path, env: dict[str, Any]) -> dict[str, Any] | None:
    """The run's held-out evaluation by ``quicknav eval`` (RUN/eval/eval.json), if it was made
    deterministically on the test bank of the env the policy trained in."""
    path = RunFolder(run_dir).eval_result
    if not path.exists():
        return None
    result = json.loads(path.read_text())
    cfg = result.get("eval_config", {})
    if cfg.get("split") != "test" or not cfg.get("deterministic") or result.get("env_config") != env:
        return None
    return {"source": str(path.relative_to(run_dir)), **{
        k: result["metrics"][k] for k in HELD_OUT_FIELDS if k in result.get("metrics", {})}}


def record_held_out(run_dir: Path, metrics: dict[str, Any], source: dict[str, Any],
                    env: dict[str, Any]) -> bool:  # fmt: skip
    """Put a held-out evaluation into an exported policy's manifest (when the evaluation ran in
    the env the policy trained in); whether it did."""
    path = Path(run_dir) / MANIFEST_FILE
    if not path.exists():
        return False
    doc = json.loads(path.read_text())
    if doc.get("env") != env:
        return False
    doc["held_out"] = {**source, **{k: metrics[k] for k in HELD_OUT_FIELDS if k in metrics}}
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(doc, indent=2))
    tmp.replace(path)
    return True


# --------------------------------------------------------------------------- parity
def random_observations(env_config, n: int, seed: int = 0) -> np.ndarray:
    """Observations drawn inside the env's exact bounds (flags as 0/1)."""
    from quicknav_core.env.constants import observation_bounds

    low, high = observation_bounds(env_config)
    rng = np.random.default_rng(seed)
    obs = rng.uniform(low, high, size=(n, low.size)).astype(np.float32)
    b = env_config.lidar_beams
    obs[:, 4 + b:4 + 3 * b] = (obs[:, 4 + b:4 + 3 * b] > 0.5 * (low[4 + b] + high[4 + b])).astype(np.float32)
    return obs


def onnx_session(path: Path):
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.log_severity_level = 3
    return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])


def check_parity(policy, onnx_path: Path, obs_dim: int, samples: int = 10_000, seed: int = 0,
                 env_config=None) -> float:  # fmt: skip
    """Largest |action_onnx - action_jax| over random observations, every row its own episode
    start (recurrent state from the initial value) and then a second step carrying the state."""
    session = onnx_session(onnx_path)
    if env_config is not None:
        obs = random_observations(env_config, samples, seed)
    else:
        obs = np.random.default_rng(seed).uniform(-1.5, 1.5, (samples, obs_dim)).astype(np.float32)
    carry = policy.initial_carry(samples)
    worst = 0.0
    feeds_state = [np.asarray(x) for x in jax.tree.leaves(carry)]
    for start in (True, False):
        jax_carry, jax_action = policy.act(carry, jnp.asarray(obs), jnp.full((samples,), start),
                                           None, deterministic=True)  # fmt: skip
        feed = {"obs": obs}
        if feeds_state:
            feed["start"] = np.full((samples,), start)
            feed.update({f"state_{i}": s for i, s in enumerate(feeds_state)})
        out = session.run(None, feed)
        worst = max(worst, float(np.max(np.abs(out[0] - np.asarray(jax_action)))))
        for a, b in zip(out[1:], jax.tree.leaves(jax_carry), strict=True):
            b = np.asarray(b)
            diff = np.abs(a.astype(np.float64) - b.astype(np.float64))
            worst = max(worst, float(np.max(diff)) if diff.size else 0.0)
        carry, feeds_state = jax_carry, out[1:]
        obs = obs[::-1].copy()
    return worst if math.isfinite(worst) else float("inf")


def check_episodes(policy, onnx_path: Path, env_config, episodes: int = 20, seed: int = 0,
                   split: str = "test", runtime=None) -> dict[str, Any]:  # fmt: skip
    """The JAX policy and the ONNX model along the same held-out episodes.

    Teacher-forced: one batch of envs is driven by the JAX policy, and the ONNX model is fed the
    very same observations (and ``start`` flags) with its own recurrent state carried from step
    to step; ``max_action_diff`` is the largest difference of the two actions over every step of
    every episode. Free-running: a second copy of the same episodes is driven by the ONNX model
    alone; each episode's outcome (success, steps) is compared with the JAX side's. Trajectories
    agree to float rounding until a contact amplifies a difference of ~1e-7 in an action, so the
    free-running comparison is by outcome, not by position."""
    from quicknav_core.env.batch import BatchedEnv

    session = onnx_session(onnx_path)
    act = jax.jit(lambda c, o, s: policy.act(c, o, s, None, True))
    recurrent = bool(jax.tree.leaves(policy.initial_carry(1)))

    def onnx_step(obs, start, state):
        feed = {"obs": obs}
        if recurrent:
            feed["start"] = start.copy()
            feed.update({f"state_{i}": s for i, s in enumerate(state)})
        action, *state = session.run(None, feed)
        return action, state

    runtime = runtime_or_new(runtime)
    envs = [BatchedEnv(env_config, episodes, seed=seed, split=split, runtime=runtime) for _ in range(2)]
    obs = [e.reset() for e in envs]
    carry = policy.initial_carry(episodes)
    forced = [np.asarray(x) for x in jax.tree.leaves(carry)]
    free = list(forced)
    start = [np.ones(episodes, bool), np.ones(episodes, bool)]
    outcome = [np.zeros((episodes, 2), np.int64), np.zeros((episodes, 2), np.int64)]  # success, steps
    open_ = [np.ones(episodes, bool), np.ones(episodes, bool)]
    worst = 0.0
    steps = 0
    while open_[0].any() or open_[1].any():
        carry, a_jax = act(carry, jnp.asarray(obs[0]), jnp.asarray(start[0]))
        a_jax = np.asarray(a_jax)
        a_forced, forced = onnx_step(obs[0], start[0], forced)
        worst = max(worst, float(np.max(np.abs(a_jax - a_forced)[open_[0]]))) if open_[0].any() else worst
        a_free, free = onnx_step(obs[1], start[1], free)
        steps += 1
        for side, (env, action) in enumerate(((envs[0], a_jax), (envs[1], a_free))):
            r = env.step(action)
            ended = r.terminated | r.truncated
            first = open_[side] & ended
            outcome[side][first] = np.stack([r.terminated[first], np.full(first.sum(), steps)], axis=1)
            open_[side] &= ~ended
            obs[side], start[side] = r.obs, ended
    agree = (outcome[0] == outcome[1]).all(axis=1)
    return {"episodes": episodes, "steps": steps, "max_action_diff": worst,
            "success_jax": int(outcome[0][:, 0].sum()), "success_onnx": int(outcome[1][:, 0].sum()),
            "same_outcome": int(agree.sum())}  # fmt: skip
