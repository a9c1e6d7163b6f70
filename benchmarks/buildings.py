"""Drive a building: the learned local planner against the planners that do not learn.

Rows: the `building` preset's learned local planner, `paper-ppo` (the paper's agent, as a user
would pick it), the oracle's plan followed by pure pursuit (`--policy oracle`: blind to what the
map does not show) and the same plan followed by a dynamic window approach on the lidar
(`--policy dwa`, as ROS 2 Navigation's DWB controller), and the building preset's policy through
the safety layer (`building+shield`: `quicknav eval --shield`, as a collision monitor between a
controller and the wheels; the same training). Columns: held-out generated floor plans
(the building preset's test bank), the maps drawn for QuickNav that the policy never trained on
(`examples/maps`: the office, the warehouse) and real SLAM maps that robots built with their lidar
(`examples/maps/slam`: Nav2's depot and warehouse, AWS RoboMaker's small warehouse; their
licences in that folder's README), each with no unmapped obstacles, with static ones, with
moving ones, and with both at once (the building preset's own mix: what an evaluation of its policy
on a map meets by default); a collision ends an episode, a failure, for every row (the rule the
building preset trains under; the paper's env lets the robot slide on). Every figure is a `quicknav eval` of the same episodes (seed 0) in a fresh
process, as a user runs it: success, SPL, collisions per episode, time to goal (successes).
Trainings are reused when their run folder already holds the whole budget (`--retrain` trains
again), and evaluations when their folder holds one of the same command (`--fresh` runs them
again). `--where`, `--rows` and `--obstacles` evaluate only the maps, policies and obstacle settings they
name and keep the other cells of the results file (a map added later needs no rerun of the rest).

    uv run python benchmarks/buildings.py [--episodes 100] [--runs runs/buildings] [--where "depot (SLAM)"]

Prints a Markdown table (a row per map and obstacles, a column per policy) and writes
benchmarks/results/buildings.json.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != ROOT / "benchmarks"]
sys.path.insert(0, str(ROOT))

from benchmarks.cli_runs import run, trained  # noqa: E402
from quicknav_core.bench.machine import machine_info, machine_line  # noqa: E402

PRESETS = ("building", "paper-ppo")
BASELINES = ("oracle", "dwa")
SHIELDED = ("building+shield",)  # the building training, evaluated with --shield
# where: the flags that put a policy there (its own env otherwise)
WHERE = {
    "floor plans": [],
    "office map": ["--map", "examples/maps/office.yaml"],
    "warehouse map": ["--map", "examples/maps/warehouse.yaml"],
    "depot (SLAM)": ["--map", "examples/maps/slam/depot.yaml"],
    "small warehouse (SLAM)": ["--map", "examples/maps/slam/small_warehouse.yaml"],
    "warehouse 30 x 50 m (SLAM)": ["--map", "examples/maps/slam/warehouse.yaml"],
}
# the building preset's test bank, for the agents that did not train on it
FLOORPLANS = ["--set", "rooms=floorplan", "--set", "grid_size=24", "--set", "room_size=12",
              "--set", "floorplan.door_width=1", "--set", "floorplan.door_width_max=2",
              "--set", "floorplan.corridor_width=2"]  # fmt: skip
# one rule for every row: a collision ends the episode, a failure (the building preset trains so)
RULES = ["--set", "end_on_collision=true"]
OBSTACLES = {
    "none": ["--set", "obstacles=null"],
    "static": ["--set", 'obstacles={"static": 6, "moving": 0}'],
    "moving": ["--set", 'obstacles={"static": 0, "moving": 3}'],
    # the building preset's own mix, boxes and people at once: what `quicknav eval --map` of its
    # policy drives among by default (the env it trained in)
    "both": ["--set", 'obstacles={"static": 6, "moving": 3}'],
}


def evaluate(who: list[str], where: list[str], out: Path, episodes: int, fresh: bool) -> dict:
    command = ["uv", "run", "quicknav", "eval", *who, "--episodes", str(episodes), *where, "--out", str(out)]
    asked = out / "command.json"  # an evaluation of this very command is reused (--fresh: not)
    done = json.loads(asked.read_text()) if asked.exists() else {}
    if fresh or done.get("command") != command:
        done = {"command": command, "seconds": run(command), "machine": machine_line()}
        asked.write_text(json.dumps(done))
    seconds = done["seconds"]
    doc = json.loads((out / "eval.json").read_text())
    m, env = doc["metrics"], doc["env_config"]
    steps = m["steps_to_goal_successes"]["mean"]
    return {"machine": done.setdefault("machine", machine_line()),
            "seconds": seconds and round(seconds, 1), "success_rate": m["success_rate"],
            "success_ci95": m["success_ci95"], "spl": m["spl"],
            "collisions_per_episode": m["collisions_per_episode"],
            "time_to_goal_s": None if steps is None else round(steps * env["dt"], 1)}  # fmt: skip


def cell(r: dict) -> str:
    t = "-" if r["time_to_goal_s"] is None else f"{r['time_to_goal_s']:g} s"
    return (f"{100 * r['success_rate']:.0f} %, SPL {r['spl']:.2f},"
            f" {r['collisions_per_episode']:.2f} coll., {t}")  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--episodes", type=int, default=100)
    ap.add_argument("--runs", type=Path, default=ROOT / "runs" / "buildings")
    ap.add_argument("--retrain", action="store_true")
    ap.add_argument("--fresh", action="store_true", help="evaluate again cells already evaluated")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "buildings.json")
    ap.add_argument("--where", action="append", choices=list(WHERE),
                    help="evaluate only these columns (repeat it); the results file keeps the rest")
    ap.add_argument("--rows", action="append", choices=[*PRESETS, *BASELINES, *SHIELDED],
                    help="evaluate only these rows (repeat it); the results file keeps the rest")
    ap.add_argument("--obstacles", action="append", choices=list(OBSTACLES),
                    help="evaluate only these obstacle settings (repeat it); the results file keeps"
                    " the rest")
    args = ap.parse_args()
    settings = {o: OBSTACLES[o] for o in (args.obstacles or OBSTACLES)}
    wheres, wanted = args.where or list(WHERE), args.rows or [*PRESETS, *BASELINES, *SHIELDED]
    env_file = args.runs / "building-env.json"
    rows: dict[str, dict] = {}
    for preset in PRESETS:
        run_dir = args.runs / preset
        train_s = None
        if preset in wanted and (args.retrain or not trained(run_dir, preset)):
            train_s = run(["uv", "run", "quicknav", "train", "--preset", preset, "--out", str(run_dir)])
        if preset == "building" and "building+shield" in wanted and not trained(run_dir, preset):
            sys.exit(f"{run_dir} holds no building training: run with --rows building first")
        if preset == "building":  # the baselines drive in its env (a training writes it first)
            if not (run_dir / "config.json").exists():
                sys.exit(f"{run_dir} holds no building training: run with --rows building first")
            env = json.loads((run_dir / "config.json").read_text())["env"]
            env_file.write_text(json.dumps(env))
        if preset in wanted:
            rows[preset] = {"train_s": train_s and round(train_s), "who": [str(run_dir)],
                            "floor plans": [] if preset == "building" else FLOORPLANS}  # fmt: skip
    if "building+shield" in wanted:
        rows["building+shield"] = {"train_s": None, "who": [str(args.runs / "building"), "--shield"],
                                   "floor plans": []}  # fmt: skip
    for baseline in (b for b in BASELINES if b in wanted):  # in the building preset's env
        rows[baseline] = {"train_s": None, "who": ["--policy", baseline, "--config", str(env_file)],
                          "floor plans": []}  # fmt: skip
    partial = args.where or args.rows or args.obstacles
    kept = {}
    if partial and args.out.exists():
        doc = json.loads(args.out.read_text())
        kept, was = doc["results"], doc["machine"]
        for row in kept.values():  # cells from before cells named their machine: the file's
            for c in row["cells"].values():
                c.setdefault("machine", f"{was['cpu']}, {was['cores']} cores, {was['device_kind']}")
    results: dict[str, dict] = {name: kept[name] for name in kept if name not in rows}
    for name, row in rows.items():
        before = kept.get(name, {})
        results[name] = {"train_s": row["train_s"] or before.get("train_s"),
                         "cells": dict(before.get("cells", {}))}  # fmt: skip
        for where in wheres:
            flags = WHERE[where]
            base = row["floor plans"] if where == "floor plans" else flags
            for obstacles, sets in settings.items():
                key = f"{where}, {obstacles}"
                out = args.runs / "eval" / name / re.sub(r"[^a-z0-9]+", "-", key.lower()).strip("-")
                r = evaluate(row["who"], [*base, *sets, *RULES], out, args.episodes, args.fresh)
                results[name]["cells"][key] = r
                print(f"{name} on {key}: {cell(r)} ({r['seconds']} s)", flush=True)
    names = [n for n in (*PRESETS, *BASELINES, *SHIELDED) if n in results]
    lines = ["| map | obstacles | " + " | ".join(names) + " |", "|---" * (len(names) + 2) + "|"]
    for w in WHERE:
        for o in OBSTACLES:
            k = f"{w}, {o}"
            if any(k in results[n]["cells"] for n in names):
                shown = [cell(results[n]["cells"][k]) if k in results[n]["cells"] else "-" for n in names]
                lines.append(f"| {w} | {o} | " + " | ".join(shown) + " |")
    machines = sorted({c["machine"] for r in results.values() for c in r["cells"].values()})
    lines += ["", f"{args.episodes} episodes per cell (seed 0); cells: success, SPL, collisions per"
              " episode, time to goal of the successes. Machines: " + "; ".join(machines)
              + " (each cell's in the JSON)."]  # fmt: skip
    text = "\n".join(lines)
    print(text)
    args.out.write_text(json.dumps({"machine": machine_info(), "episodes": args.episodes,
                                    "results": results, "table": text}, indent=1))  # fmt: skip
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
