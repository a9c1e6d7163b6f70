"""The learning benchmark keeps seeds recorded in a committed report when their run folders are gone."""

from __future__ import annotations

import json

from quicknav_core.bench.learning import run_learning_bench


def _metrics(success: float) -> dict:
    return {
        "episodes": 100, "success_rate": success, "success_ci95": [0.0, 1.0],
        "steps_to_goal_successes": {"mean": 60.0, "std": 5.0},
        "steps_to_goal_failures_as_limit": {"mean": 70.0, "std": 9.0},
        "return": {"mean": 90.0, "std": 3.0}, "collisions_per_episode": 0.5, "timeout_rate": 0.0,
        "spl": 0.9, "path_length_successes": {"mean": 5.0, "std": 1.0},
        "reference_length": {"mean": 5.0, "std": 1.0}, "steps_lower_bound": {"mean": 50.0, "std": 1.0},
    }  # fmt: skip


def test_bench_learning__keeps_committed_seeds_without_their_run_folders(tmp_path):
    out, runs = tmp_path / "results", tmp_path / "runs"
    for name in ("oracle-table1", "random-table1", "oracle-table2", "random-table2"):
        policy, table = name.split("-")
        d = runs / f"baseline-{policy}-{table}"
        d.mkdir(parents=True)
        (d / "eval.json").write_text(
            json.dumps({"metrics": _metrics(1.0 if policy == "oracle" else 0.0)})
        )
    out.mkdir()
    kept = [{"metrics": _metrics(0.98 + 0.01 * s), "training": {"seed": s, "minutes": 4.0,
             "env_steps": 20_000_000, "stopped_by_time_cap": False}} for s in range(3)]  # fmt: skip
    (out / "report.json").write_text(json.dumps({"rows": {"paper-ppo": {"runs": kept}}}))
    markdown, data = run_learning_bench(out, runs, rows=["none-selected"], seeds=3)
    runs_ppo = data["rows"]["paper-ppo"]["runs"]
    assert [r["training"]["seed"] for r in runs_ppo] == [0, 1, 2]
    assert "| PPO (MLP 2x128) | paper | 3/3 |" in markdown
    target = next(t for t in data["targets"] if "PPO" in t["target"])
    assert target["met"]
    # nothing was trained: no run folder appeared
    assert sorted(p.name for p in runs.iterdir() if not p.name.startswith("baseline")) == []


def _run(success: float, steps: float, minutes: float, seed: int) -> dict:
    m = _metrics(success)
    m["steps_to_goal_failures_as_limit"] = {"mean": steps, "std": 1.0}
    return {"metrics": m, "training": {"seed": seed, "minutes": minutes}}


def test_build_report__table2_target_needs_steps_success_and_time():
    from quicknav_core.bench.learning import build_report

    def target(success, steps, minutes):
        rows = {"paper-lstm": [_run(success, steps, minutes, s) for s in range(3)],
                "paper-gtrxl": [_run(0.0, 300.0, 5.0, s) for s in range(3)]}  # fmt: skip
        _, data = build_report(rows, {}, 3)
        t = next(t for t in data["targets"] if "Table 2" in t["target"])
        assert t["measured"]["preset"] == "paper-lstm"  # the fewest steps, not the fastest run
        return t["met"]

    assert target(0.92, 95.0, 30.0)
    assert not target(0.92, 105.0, 30.0)  # too many steps
    assert not target(0.85, 95.0, 30.0)  # too few successes
    assert not target(0.92, 95.0, 61.0)  # trained too long


def test_bench_learning__report_written_mid_row_keeps_finished_seeds(tmp_path, monkeypatch):
    """A session cut off while a row trains must not lose that row's committed seeds."""
    import quicknav_core.bench.learning as bl

    out, runs = tmp_path / "results", tmp_path / "runs"
    monkeypatch.setattr(bl, "baselines", lambda runs_dir: {})
    out.mkdir()
    seed0 = {"metrics": _metrics(0.5), "training": {"seed": 0, "minutes": 7.0, "machine": "box A"}}
    (out / "report.json").write_text(json.dumps({"rows": {"paper-gtrxl": {"runs": [seed0]}}}))
    seen: list[list[int]] = []

    def fake_run_one(row, seed, runs_dir, scale=1.0, say=print):
        on_disk = json.loads((out / "report.json").read_text())
        seen.append([r["training"]["seed"] for r in on_disk["rows"]["paper-gtrxl"]["runs"]])
        run = _run(0.6, 90.0, 8.0, seed)
        run["training"]["machine"] = "box B"
        return run

    monkeypatch.setattr(bl, "run_one", fake_run_one)
    markdown, data = bl.run_learning_bench(out, runs, rows=["paper-gtrxl"], seeds=3)
    assert seen == [[0], [0, 1]]  # seed 0 stays in the report while seeds 1 and 2 train
    assert [r["training"]["seed"] for r in data["rows"]["paper-gtrxl"]["runs"]] == [0, 1, 2]
    assert "- box A: paper-gtrxl s0" in markdown
    assert "- box B: paper-gtrxl s1, paper-gtrxl s2" in markdown


def test_rows__shaped_and_variant_rows_resolve_to_the_configs_they_name():
    from quicknav_core.bench.learning import ROW_KEYS, ROWS
    from quicknav_core.config import get_preset, resolve_train

    assert len(set(ROW_KEYS)) == len(ROWS)  # run folders and report keys never collide
    by_key = {r.key: r for r in ROWS}
    for preset in ("paper-ppo", "paper-sac", "paper-td3", "paper-mlp", "paper-lstm", "paper-gtrxl"):
        paper = resolve_train(by_key[preset].request(1, 2_000_000))
        shaped = resolve_train(by_key[f"{preset}-shaped"].request(1, 2_000_000))
        assert paper.env.reward.progress == "sign" and paper.seed == 1
        assert shaped.env.reward.progress == "potential"
        # the shaping's γ is the trainer's discount (else the optimal policy changes)
        assert shaped.env.reward.potential_gamma == get_preset(preset).algorithm.gamma
        assert shaped.model_copy(update={"env": paper.env}) == paper  # nothing else differs
    cur = resolve_train(by_key["tuned-lstm-curriculum"].request(0, 60_000_000))
    assert cur.curriculum.enabled and not resolve_train(by_key["tuned-lstm"].request(0, 60_000_000)).curriculum.enabled
    assert by_key["tuned-lstm-curriculum"].family == "PPO + LSTM"


def test_rows__tuned_rows_answer_a_paper_row_and_change_only_the_trainer():
    from quicknav_core.bench.learning import ROWS
    from quicknav_core.config import resolve_train

    paper_names = {r.name for r in ROWS if r.key == r.preset and r.preset.startswith("paper-")}
    assert len(paper_names) == 6
    by_key = {r.key: r for r in ROWS}
    for row in ROWS:
        assert (row.family or row.name) in paper_names, row.key  # every row counts for a target
    # the tuned rows keep their paper row's env (rewards, rooms, observation): only the agent differs
    for tuned, paper in (("tuned-td3-shaped", "paper-td3-shaped"), ("tuned-gtrxl", "paper-gtrxl"),
                         ("tuned-lstm", "paper-lstm")):  # fmt: skip
        t = resolve_train(by_key[tuned].request(2, 1_000_000))
        p = resolve_train(by_key[paper].request(2, 1_000_000))
        assert t.env == p.env, tuned
        assert t.algorithm != p.algorithm or t.network != p.network, tuned
    # tuned-td3 carries the shaped reward it was tuned under (a plain `--preset tuned-td3` gets it)
    from quicknav_core.config import get_preset

    assert get_preset("tuned-td3").env == resolve_train(by_key["paper-td3-shaped"].request(0, 1_000_000)).env


def test_bench_learning__two_processes_sharing_a_report_keep_each_others_seeds(tmp_path, monkeypatch):
    """Rows trained by two `bench learning` processes at once: neither write drops the other's seeds."""
    import quicknav_core.bench.learning as bl

    out, runs = tmp_path / "results", tmp_path / "runs"
    monkeypatch.setattr(bl, "baselines", lambda runs_dir: {})
    out.mkdir()

    def other_process_finishes(seed: int) -> None:
        """What the other process's write leaves on disk: its own row's seed added."""
        on_disk = json.loads((out / "report.json").read_text()) if (out / "report.json").exists() else {"rows": {}}
        row = on_disk["rows"].setdefault("paper-sac-shaped", {"runs": []})
        row["runs"].append(_run(0.9, 70.0, 30.0, seed))
        (out / "report.json").write_text(json.dumps(on_disk))

    def fake_run_one(row, seed, runs_dir, scale=1.0, say=print):
        other_process_finishes(seed)  # the other process writes while this seed trains
        return _run(0.6, 90.0, 8.0, seed)

    monkeypatch.setattr(bl, "run_one", fake_run_one)
    markdown, data = bl.run_learning_bench(out, runs, rows=["paper-lstm-shaped"], seeds=3)
    on_disk = json.loads((out / "report.json").read_text())
    for report in (data, on_disk):
        assert [r["training"]["seed"] for r in report["rows"]["paper-lstm-shaped"]["runs"]] == [0, 1, 2]
        assert [r["training"]["seed"] for r in report["rows"]["paper-sac-shaped"]["runs"]] == [0, 1, 2]
    assert "| SAC (MLP 2x128), shaped reward | shaped | 3/3 |" in markdown


def test_bench_learning__rerun_scoreless_replaces_only_seeds_without_episodes(tmp_path, monkeypatch):
    """--rerun-scoreless retrains the seeds recorded without per-episode scores, nothing else, and
    the recorded seed stays in the report while its rerun trains."""
    import quicknav_core.bench.learning as bl

    out, runs = tmp_path / "results", tmp_path / "runs"
    monkeypatch.setattr(bl, "baselines", lambda runs_dir: {})
    out.mkdir()
    scored = {"metrics": _metrics(0.9), "training": {"seed": 1, "minutes": 7.0},
              "per_episode": {"success": [1, 0], "spl": [0.9, 0.0], "steps": [60, 300]}}  # fmt: skip
    old = [_run(0.5, 90.0, 8.0, 0), scored, _run(0.5, 90.0, 8.0, 2)]
    (out / "report.json").write_text(json.dumps({"rows": {"paper-mlp": {"runs": old},
                                                          "paper-lstm": {"runs": old}}}))  # fmt: skip
    trained: list[tuple[str, int]] = []

    def fake_run_one(row, seed, runs_dir, scale=1.0, say=print):
        on_disk = json.loads((out / "report.json").read_text())
        assert len(on_disk["rows"][row.key]["runs"]) == 3  # the old seed is still reported
        trained.append((row.key, seed))
        run = _run(0.95, 70.0, 9.0, seed)
        run["per_episode"] = {"success": [1, 1], "spl": [0.9, 0.8], "steps": [60, 70]}
        return run

    monkeypatch.setattr(bl, "run_one", fake_run_one)
    _, data = bl.run_learning_bench(out, runs, rows=["paper-mlp"], seeds=3, rerun_scoreless=True)
    assert trained == [("paper-mlp", 0), ("paper-mlp", 2)]  # seed 1 had scores; paper-lstm not chosen
    mlp = data["rows"]["paper-mlp"]["runs"]
    assert [r["metrics"]["success_rate"] for r in mlp] == [0.95, 0.9, 0.95]
    assert data["rows"]["paper-mlp"]["aggregate"]["seeds"] == 3
    assert [r["metrics"]["success_rate"] for r in data["rows"]["paper-lstm"]["runs"]] == [0.5, 0.9, 0.5]
    # without the flag nothing recorded is trained again
    trained.clear()
    bl.run_learning_bench(out, runs, rows=["paper-lstm"], seeds=3)
    assert trained == []


def test_bench_learning__rerun_before_retrains_seeds_of_older_versions_only(tmp_path, monkeypatch):
    """--rerun-before 0.2.0 retrains the chosen rows' seeds stamped older (or not stamped), and
    their stale run folders; seeds stamped 0.2.0 and rows not chosen stay."""
    import quicknav_core.bench.learning as bl

    out, runs = tmp_path / "results", tmp_path / "runs"
    monkeypatch.setattr(bl, "baselines", lambda runs_dir: {})
    out.mkdir()
    new = _run(0.9, 70.0, 8.0, 1)
    new["training"]["quicknav"] = "0.2.0"
    old = [_run(0.5, 90.0, 8.0, 0), new, _run(0.5, 90.0, 8.0, 2)]
    (out / "report.json").write_text(json.dumps({"rows": {"paper-sac": {"runs": old},
                                                          "paper-td3": {"runs": old}}}))  # fmt: skip
    stale = runs / "paper-sac-s2" / "eval"
    stale.mkdir(parents=True)
    (stale / "eval.json").write_text(json.dumps(_run(0.4, 95.0, 8.0, 2)))  # an unstamped run folder
    trained: list[tuple[str, int]] = []

    def fake_run_one(row, seed, runs_dir, scale=1.0, say=print):
        assert not (runs_dir / f"{row.key}-s{seed}").exists()  # the stale folder went first
        trained.append((row.key, seed))
        run = _run(0.97, 66.0, 8.0, seed)
        run["training"]["quicknav"] = "0.2.0"
        return run

    monkeypatch.setattr(bl, "run_one", fake_run_one)
    _, data = bl.run_learning_bench(out, runs, rows=["paper-sac"], seeds=3, rerun_before="0.2.0")
    assert trained == [("paper-sac", 0), ("paper-sac", 2)]
    assert [r["metrics"]["success_rate"] for r in data["rows"]["paper-sac"]["runs"]] == [0.97, 0.9, 0.97]
    assert [r["metrics"]["success_rate"] for r in data["rows"]["paper-td3"]["runs"]] == [0.5, 0.9, 0.5]
    assert bl._older_than({"training": {"quicknav": "0.1.9"}}, "0.2.0")
    assert not bl._older_than({"training": {"quicknav": "0.10.0"}}, "0.2.0")


def test_bench_learning__a_seed_another_process_replaced_is_not_written_back_stale(tmp_path, monkeypatch):
    """Process A started with an old seed of row X; process B reran it meanwhile. A's writes keep B's."""
    import quicknav_core.bench.learning as bl

    out, runs = tmp_path / "results", tmp_path / "runs"
    monkeypatch.setattr(bl, "baselines", lambda runs_dir: {})
    out.mkdir()
    (out / "report.json").write_text(json.dumps({"rows": {"paper-mlp": {"runs": [_run(0.5, 90.0, 8.0, 0)]}}}))

    def fake_run_one(row, seed, runs_dir, scale=1.0, say=print):
        on_disk = json.loads((out / "report.json").read_text())
        on_disk["rows"]["paper-mlp"]["runs"] = [_run(0.97, 60.0, 9.0, 0)]  # B's rerun lands
        (out / "report.json").write_text(json.dumps(on_disk))
        return _run(0.6, 90.0, 8.0, seed)

    monkeypatch.setattr(bl, "run_one", fake_run_one)
    _, data = bl.run_learning_bench(out, runs, rows=["paper-lstm-shaped"], seeds=1)
    assert data["rows"]["paper-mlp"]["runs"][0]["metrics"]["success_rate"] == 0.97
    on_disk = json.loads((out / "report.json").read_text())
    assert on_disk["rows"]["paper-mlp"]["runs"][0]["metrics"]["success_rate"] == 0.97
    assert not list(out.glob(".*.tmp"))  # atomic writes leave no temporary file behind


def test_build_report__a_baseline_with_no_successes_prints_a_dash():
    """The random baseline's steps over successes is undefined: NaN when just measured, null once
    read back from report.json. Either way the report is written (a read-back null once crashed
    the writer after a 10-minute training)."""
    from quicknav_core.bench.learning import build_report

    for undefined in (None, float("nan")):
        random = _metrics(0.0)
        random["steps_to_goal_successes"] = {"mean": undefined, "std": undefined}
        markdown, _ = build_report({}, {"random-table1": {"metrics": random}}, 3)
        line = next(x for x in markdown.splitlines() if x.startswith("| random (baseline)"))
        assert "| 0 | 0.9 | - | 70 |" in line, line
