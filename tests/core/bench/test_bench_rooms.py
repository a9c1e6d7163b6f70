"""`quicknav bench rooms` at small sizes: it runs, the JSON is complete, the figures add up."""

import json

from typer.testing import CliRunner

from quicknav_cli.main import app
from quicknav_core.bench.rooms import (
    RoomsBenchConfig,
    RoomsMeasurement,
    check_targets,
    run_rooms_bench,
    write_report,
)


def test_run_rooms_bench__builds_both_default_banks_per_grid(tmp_path):
    report = run_rooms_bench(RoomsBenchConfig(grids=(8,)))
    (row,) = report.results
    assert (row.grid, row.carver, row.train_rooms, row.test_rooms) == (8, "paper", 1024, 256)
    assert row.free_cells >= row.carve_target == 29
    assert abs(row.total_s - row.train_s - row.test_s) < 0.01 and row.train_s > 0
    data = json.loads(write_report(report, tmp_path).read_text())
    assert {"config", "machine", "results", "targets"} <= set(data)
    assert data["results"][0]["total_s"] == row.total_s and data["config"]["grids"] == [8]


def test_check_targets__slowest_grid_decides():
    def m(grid, total):
        return RoomsMeasurement(grid, "carved", 1024, 256, total, 0.0, total, 10, 10)

    (t,) = check_targets([m(16, 1.0), m(128, 9.5)])
    assert t["met"] and t["grid"] == 128 and t["measured"] == 9.5
    (t,) = check_targets([m(16, 1.0), m(128, 12.0)])
    assert not t["met"]


def test_cli_bench_rooms__prints_table_and_writes_json(tmp_path):
    result = CliRunner().invoke(app, ["bench", "rooms", "--grid", "8", "--carver", "centre",
                                      "--out", str(tmp_path)])  # fmt: skip
    assert result.exit_code == 0, result.output
    assert "8x8" in result.output and "centre" in result.output and "met" in result.output
    row = json.loads((tmp_path / "bench_rooms.json").read_text())["results"][0]
    assert row["carver"] == "centre" and row["train_rooms"] == 1024
    bad = CliRunner().invoke(app, ["bench", "rooms", "--grid", "300"])
    assert bad.exit_code != 0 and "4..256" in bad.output
    bad = CliRunner().invoke(app, ["bench", "rooms", "--carver", "fast"])
    assert bad.exit_code != 0 and "carved" in bad.output
