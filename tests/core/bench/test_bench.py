"""The bench module itself at tiny sizes: it runs, the JSON is complete, figures are consistent."""

import json

import pytest
from typer.testing import CliRunner

from quicknav_cli.main import app
from quicknav_core.bench.env import BenchConfig, check_targets, run_bench, write_outputs


@pytest.mark.slow  # the whole env benchmark on tiny sizes: ~26 s on 2 cores
def test_bench__tiny_run_is_complete_and_consistent(tmp_path):
    cfg = BenchConfig(grids=(4, 8), batches=(8,), beams=4, steps=400, repeats=3, budget_s=10)
    report = run_bench(cfg)
    impls = {(r.grid, r.impl) for r in report.results}
    for g in (4, 8):
        assert {(g, "numpy"), (g, "jax-b1-py"), (g, "jax-b1-scan"), (g, "jax-b8")} <= impls
    for r in report.results:
        assert r.steps_per_s > 0 and r.time_for_steps_s > 0
        assert len(r.seconds) == 3 and all(s > 0 for s in r.seconds)
        # the rate and the time for `steps` steps are the same figure
        assert abs(r.time_for_steps_s * r.steps_per_s - cfg.steps) < 1e-6 * cfg.steps
        if r.impl != "numpy":
            assert r.compile_s is not None and r.compile_s > 0
        if r.impl.startswith("jax-b") and r.impl != "jax-b1-py":
            assert r.steps_timed >= cfg.steps  # scan length covers the requested steps
    m = report.machine
    assert m["cores"] >= 1 and m["jax_backend"] in ("cpu", "gpu", "tpu") and m["jax"]
    paths = write_outputs(report, tmp_path)
    data = json.loads(paths["json"].read_text())
    assert {"config", "machine", "results", "targets"} <= set(data)
    row = data["results"][0]
    for key in ("grid", "impl", "batch", "steps_per_s", "time_for_steps_s", "compile_s",
                "peak_memory_bytes", "seconds", "steps_timed"):  # fmt: skip
        assert key in row
    assert paths["time_png"].stat().st_size > 5000 and paths["batch_png"].stat().st_size > 5000
    # a picture that fails is told and left out; the figures are written all the same
    told = []
    broken = type(report)(**{**report.__dict__, "config": {**report.config, "grids": None}})
    again = write_outputs(broken, tmp_path / "broken", warn=told.append)
    assert set(again) == {"json"} and again["json"].is_file(), again
    assert [t.split(" ")[0] for t in told] == ["bench_time_100k.png", "bench_batch.png"], told


def test_check_targets__reads_the_right_rows():
    from quicknav_core.bench.env import Measurement

    def m(grid, impl, rate, compile_s=None):
        return Measurement(grid, impl, 4096 if impl == "jax-b4096" else 1, 1, 3, [1, 1, 1], rate,
                           100_000 / rate, compile_s)  # fmt: skip

    rows = [m(16, "jax-b4096", 1.2e6, 3.0), m(16, "numpy", 5e3), m(4, "jax-b4096", 1.5e6, 2.0)]
    t = {x["target"]: x for x in check_targets(rows, BenchConfig())}
    assert len(t) == 4
    assert all(x["met"] for x in t.values())
    rows[0] = m(16, "jax-b4096", 0.4e6, 12.0)
    t = {x["target"]: x for x in check_targets(rows, BenchConfig())}
    assert not any(x["met"] for x in t.values())


def test_cli_bench__prints_table_and_writes_files(tmp_path):
    result = CliRunner().invoke(
        app,
        [
            "bench",
            "--grid",
            "4",
            "--batch",
            "4",
            "--beams",
            "4",
            "--steps",
            "200",
            "--budget-s",
            "10",
            "--out",
            str(tmp_path),
        ],
    )
    assert result.exit_code == 0, result.output
    assert "jax-b4" in result.output and "numpy" in result.output
    assert (tmp_path / "bench.json").exists() and (tmp_path / "bench_batch.png").exists()
    bad = CliRunner().invoke(app, ["bench", "--grid", "2"])
    assert bad.exit_code != 0 and "4..256" in bad.output
