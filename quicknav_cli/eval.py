"""`quicknav eval`: a trained run or a baseline on held-out rooms: success, SPL, steps, collisions."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer

from quicknav_cli.common import (
    EnvSetOpt,
    PrintConfigOpt,
    admitted,
    console,
    enable_compilation_cache,
    env_sets,
    fail,
    print_config,
    read_json,
    resolved,
    warn,
)


def run_env(source: str):
    """The env a run folder's policy trained in (``resolve_eval``'s lookup for the CLI)."""
    from quicknav_core.config import ConfigError
    from quicknav_core.train.run import CHECKPOINT_DIR, read_config

    path = Path(source)
    run_dir = path.parent if path.name == CHECKPOINT_DIR else path
    try:
        return read_config(run_dir).env
    except FileNotFoundError as e:
        raise ConfigError.single(["run"], str(e)) from None


def eval_request(
    run: Path | None, policy: str | None, episodes: int, seed: int, deterministic: bool,
    split: str, config: Path | None, overrides: list[str] | None, robustness: bool = False,
    shield: bool = False,
) -> dict[str, Any]:  # fmt: skip
    """The eval request the flags describe (what the SDK would send, with a job for the run)."""
    if (run is None) == (policy is None):
        fail("give either a run folder or --policy random|oracle|dwa")
    if policy is not None and policy not in ("random", "oracle", "dwa"):
        fail(f"--policy {policy!r}: allowed values are random, oracle and dwa")
    env = {**(read_json(config) if config else {}), **env_sets(overrides)}
    request: dict[str, Any] = {"episodes": episodes, "seed": seed, "split": split,
                               "deterministic": deterministic, "env": env}  # fmt: skip
    if robustness:
        request["robustness"] = True
    if shield:
        request["shield"] = True
    if run is not None:
        request["run"] = str(run)
    else:
        request["policy"] = policy
    return request


def default_out(run_dir: Path | None, policy: str | None, on_map: Path | None,
                split: str = "test", deterministic: bool = True, shield: bool = False,
                sets: dict[str, Any] | None = None) -> Path:  # fmt: skip
    """Where an evaluation is written without --out: RUN/eval for a run (its held-out evaluation,
    what export reads as the policy's held-out success), eval/POLICY for a baseline; one on a
    map, on the training rooms, acting stochastically, through the safety layer or in an env that
    --set changed beside it, never over it (RUN/eval-MAP, RUN/eval-train, RUN/eval-stochastic,
    RUN/eval-shield, RUN/eval-KEY=VALUE, in that order when several; MAP the map file's name
    without its suffix; a map's ``maps.*`` reading is part of its name already)."""
    parts = [Path(on_map).stem] if on_map is not None else []
    parts += ["train"] if split == "train" else []
    parts += [] if deterministic else ["stochastic"]
    parts += ["shield"] if shield else []
    changed = {k: v for k, v in (sets or {}).items() if on_map is None or not k.startswith("maps.")}
    if changed:
        parts.append(_sets_name(changed))
    tail = "".join(f"-{p}" for p in parts)
    return run_dir / f"eval{tail}" if run_dir is not None else Path("eval") / f"{policy}{tail}"


def _sets_name(changed: dict[str, Any]) -> str:
    """A folder name for --set items: KEY=VALUE joined by '-' in the order given, characters a file
    name would trip on replaced by '_'; past 60 characters the first ones and a digest of all."""
    import hashlib
    import json
    import re

    text = "-".join(f"{k}={v if isinstance(v, str) else json.dumps(v, separators=(',', ':'))}"
                    for k, v in changed.items())  # fmt: skip
    name = re.sub(r"[^A-Za-z0-9._=+-]", "_", text)
    if len(name) > 60:
        name = f"{name[:48]}-{hashlib.sha1(text.encode()).hexdigest()[:8]}"
    return name


def map_layer(say: bool = True):
    """``resolve_eval``'s ``map_env`` for the command line: a map file (a server's ``map:<id>``
    is refused, naming where to download it), laid as every door lays it
    (``eval.map_fit.env_on_map``); ``say``: print how (not under --print-config, whose output is
    the JSON alone) and warn when the grid loses free space."""
    from quicknav_core.eval.map_fit import env_on_map

    def seen(env, fit) -> None:
        if say:
            rows, cols = fit.grid_shape
            grid = f"{rows}" if rows == cols else f"{rows} x {cols} (rows x cols)"
            console.print(f"on {fit.path}: grid {grid} of {fit.cell_m:g} m cells, step"
                          f" limit {fit.max_steps} (longest path {fit.longest_path_m:.1f} m)",
                          highlight=False, soft_wrap=True)  # fmt: skip
            if env.obstacles and (env.obstacles.static or env.obstacles.moving):
                # the policy's own env: a figure with them is not one without them (docs: Measured)
                console.print(f"among obstacles the map does not show: up to"
                              f" {env.obstacles.static} boxes and {env.obstacles.moving} people"
                              " walking (--set obstacles=null for none)", highlight=False,
                              soft_wrap=True)  # fmt: skip
        for message in fit.warnings():
            warn(message)

    return lambda env, name, reading=None: env_on_map(env, name, seen=seen, reading=reading)


def eval_cmd(
    run: Annotated[
        Path | None,
        typer.Argument(help="Run folder (or its checkpoint folder) from quicknav train."),
    ] = None,
    policy: Annotated[
        str | None, typer.Option(help="Baseline instead of a run: random, oracle (the plan, pure pursuit) or dwa (the plan, a dynamic window on the lidar).")
    ] = None,
    episodes: Annotated[
        int, typer.Option(min=1, max=100_000, help="Episodes (fixed seeds).")
    ] = 100,
    seed: Annotated[int, typer.Option(min=0, help="Episode seed: same seed, same episodes.")] = 0,
    deterministic: Annotated[
        bool, typer.Option("--deterministic/--stochastic", help="Act with the mean, or sample.")
    ] = True,
    split: Annotated[str, typer.Option(help="Room bank: test (held out) or train.")] = "test",
    config: Annotated[
        Path | None, typer.Option("--config", help="EnvConfig JSON file of a baseline's env.")
    ] = None,
    set_: EnvSetOpt = None,
    out: Annotated[
        Path | None, typer.Option(help="Folder for eval.json and pictures (default RUN/eval; with"
                                  " --map MAP, --split train, --stochastic, --shield or --set K=V"
                                  " beside it: RUN/eval-MAP, RUN/eval-train, RUN/eval-stochastic,"
                                  " RUN/eval-shield, RUN/eval-K=V; the held-out one stays).")
    ] = None,
    robustness: Annotated[
        bool,
        typer.Option("--robustness", help="Also run the episodes at fixed levels of lidar noise,"
                     " beam dropout, range bias, action latency and wheel asymmetry: success and"
                     " SPL per level (eval.json, robustness.png)."),
    ] = False,
    shield: Annotated[
        bool,
        typer.Option("--shield", help="Put the safety layer between the policy and the wheels: a"
                     " command that would bring the robot within 1 cm of a lidar return is"
                     " slowed, down to turning in place (agent '<policy>+shield')."),
    ] = False,
    on_map: Annotated[
        Path | None,
        typer.Option("--map", help="Evaluate on this map (a map_server .yaml, or a .png/.pgm with"
                     " --set maps.resolution=M_PER_PX): the grid follows the map at the policy's"
                     " cell size and the step limit its longest path (--set wins over both, but"
                     " --set grid_size/room_size give the cell size the map is laid at)."),
    ] = None,
    print_only: PrintConfigOpt = False,
) -> None:
    """Evaluate a trained run or a baseline on held-out rooms: success, SPL, steps, collisions."""
    from quicknav_core.config import resolve_eval

    if split not in ("test", "train"):
        fail(f"--split {split!r}: allowed values are test and train")
    request = eval_request(run, policy, episodes, seed, deterministic, split, config, set_,
                           robustness, shield)  # fmt: skip
    if on_map is not None:  # the library's EvalRequest.map, as the service's eval jobs take it:
        # laid over --config's env and --set (grid_size / room_size give the cells it is laid at,
        # the map how many); the step limit follows the map unless --set names one
        request["map"] = str(on_map)
        if config and "max_steps" not in env_sets(set_):
            request["env"].pop("max_steps", None)
    cfg = resolved(resolve_eval, request, flags={"map": "--map"}, trained_env=run_env,
                   map_env=map_layer(say=not print_only) if on_map is not None else None)
    if print_only:
        print_config(cfg)
        return
    from quicknav_core.eval.evaluate import run_eval
    from quicknav_core.layout import RunFolder

    run_dir = RunFolder.of(run).path if run is not None else None
    out_dir = out or default_out(run_dir, policy, on_map, split, deterministic, shield,
                                 env_sets(set_))
    from quicknav_core.runtime import Runtime

    runtime = Runtime()
    admitted(cfg, runtime)  # the env's rooms and maps, as every door checks them
    enable_compilation_cache()
    what = f"{episodes} episodes" + (" at every perturbation level" if robustness else "")
    with console.status(f"evaluating on {what}..."):
        try:
            result, _ = run_eval(cfg, out_dir, run_dir=run_dir, runtime=runtime)
        except (ValueError, FileNotFoundError) as e:
            fail(str(e))
    print_eval(result)
    for b in result["by_path_length"]:
        hi = f"{b['path_m'][1]:g}" if b["path_m"][1] is not None else "..."
        console.print(f"  oracle path {b['path_m'][0]:g}-{hi} m: {b['episodes']} episode{'s' * (b['episodes'] != 1)}, success"
                      f" {b['success_rate']:.0%}, SPL {b['spl']:.2f}")  # fmt: skip
    if result.get("robustness"):
        print_robustness(result["robustness"], result["agent"])
    written = sorted(p.name for p in Path(out_dir).iterdir() if p.is_file())
    console.print(f"wrote {out_dir}/: {', '.join(written)}")
    for message in result.get("warnings", []):
        warn(message)


def print_robustness(rows, agent: str) -> None:
    """One line per perturbation level: success (95 % CI), SPL, steps, collisions."""
    from rich.table import Table

    t = Table(title=f"{agent}: robustness ({rows[0]['episodes']} episodes per level)")
    for name, justify in (("perturbation", "left"), ("success (95% CI)", "right"),
                          ("SPL", "right"), ("steps", "right"), ("collisions", "right")):  # fmt: skip
        t.add_column(name, justify=justify)
    for r in rows:
        lo, hi = r["success_ci95"]
        t.add_row(r["label"], f"{r['success_rate']:.0%} ({lo:.0%} - {hi:.0%})", f"{r['spl']:.2f}",
                  f"{r['mean_steps']:.1f}", f"{r['collisions_per_episode']:.2f}")  # fmt: skip
    console.print(t)


def print_eval(result) -> None:
    from rich.table import Table

    m = result["metrics"]
    t = Table(title=f"{result['agent']}: {m['episodes']} held-out episodes")
    t.add_column("metric")
    t.add_column("value", justify="right")
    lo, hi = m["success_ci95"]
    t.add_row("success rate (95% CI)", f"{m['success_rate']:.1%} ({lo:.1%} - {hi:.1%})")
    t.add_row("SPL", f"{m['spl']:.3f}")
    s = m["steps_to_goal_successes"]
    # "a ± b": the mean over the episodes and their standard deviation (not an interval)
    t.add_row("steps to goal (successes), mean ± std", f"{s['mean']:.1f} ± {s['std']:.1f}")
    s = m["steps_to_goal_failures_as_limit"]
    t.add_row("steps (failures = limit), mean ± std", f"{s['mean']:.1f} ± {s['std']:.1f}")
    t.add_row("steps lower bound (oracle path)", f"{m['steps_lower_bound']['mean']:.1f}")
    t.add_row("return, mean ± std", f"{m['return']['mean']:.2f} ± {m['return']['std']:.2f}")
    t.add_row("collisions per episode", f"{m['collisions_per_episode']:.2f}")
    t.add_row("success without a collision", f"{m['collision_free_success_rate']:.1%}")
    t.add_row("timeout rate", f"{m['timeout_rate']:.1%}")
    p = m["path_length_successes"]
    t.add_row("path length, m (successes), mean ± std", f"{p['mean']:.2f} ± {p['std']:.2f}")
    console.print(t)
