"""`quicknav export`: a trained policy as `policy.onnx` + `policy.json`, to run without JAX."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from quicknav_cli.common import console, enable_compilation_cache, fail


def export_cmd(
    run: Annotated[
        Path | None,
        typer.Argument(help="Run folder (or its checkpoint folder) from quicknav train."),
    ] = None,
    job: Annotated[
        str | None,
        typer.Option("--job", help="A succeeded train job of the service instead of a run folder"
                     " (its policy.onnx and policy.json are downloaded)."),
    ] = None,
    fmt: Annotated[str, typer.Option("--format", help="Model format: onnx.")] = "onnx",
    out: Annotated[Path, typer.Option("--out", help="Folder for policy.onnx and policy.json.")] = Path(
        "policy"
    ),
    url: Annotated[
        str, typer.Option(envvar="QUICKNAV_URL", help="The service's base URL (with --job).")
    ] = "http://127.0.0.1:8000",
    token: Annotated[
        str | None,
        typer.Option(envvar="QUICKNAV_API_TOKEN", help="Bearer token, if the service wants one."),
    ] = None,
    on_map: Annotated[
        Path | None,
        typer.Option("--map", help="A map the robot drives (map_server .yaml): written with the"
                     " policy at its cell size (map.npz) with its frame, for the SDK's Navigator."),
    ] = None,
) -> None:
    """Export a trained policy: policy.onnx (deterministic action, recurrent state as inputs and
    outputs, dynamic batch) and policy.json (observation layout, beam angles, action units, state,
    env, provenance, held-out success)."""
    if fmt != "onnx":
        fail(f"--format {fmt!r}: allowed values are onnx")
    if (run is None) == (job is None):
        fail("give either a run folder or --job ID")
    if job is not None and on_map is not None:
        fail("--map: export the run folder (quicknav jobs download) to ship a map with its policy")
    if job is not None:
        try:
            from quicknav_client import QuickNavClient, QuickNavError
        except ImportError:
            fail("the QuickNav SDK is not installed: pip install 'quicknav[service]' (or ./clients)")
        try:
            with QuickNavClient(url, token=token) as client:
                folder = client.download_policy(job, out)
        except QuickNavError as e:
            fail(str(e), code=1)
        console.print(f"wrote {folder}/policy.onnx and {folder}/policy.json", highlight=False)
        return
    try:
        import jax2onnx  # noqa: F401
    except ImportError:
        fail("exporting needs the export extra: pip install 'quicknav[export]'")
    from quicknav_core.export import check_robot_map, export_run
    from quicknav_core.layout import RunFolder

    run_dir = RunFolder.of(run).path
    if not run_dir.is_dir():
        fail(f"run folder {run_dir} does not exist")
    enable_compilation_cache()
    from quicknav_core.env.maps import MapError

    if on_map is not None:
        try:  # before the minute of tracing is announced
            check_robot_map(on_map)
        except MapError as e:
            fail(str(e))
    # tracing to ONNX and checking the model against the JAX policy takes tens of seconds: say so
    # first (a line, not a spinner, so that a log or a pipe shows it too)
    console.print(f"exporting {run_dir} (tracing the policy to ONNX and checking it against JAX;"
                  " about a minute)", highlight=False)  # fmt: skip
    try:
        doc = export_run(run_dir, out, map_path=on_map)
    except (FileNotFoundError, MapError) as e:
        fail(str(e))
    state = ", ".join(f"{s['input']} {s['shape']}" for s in doc["state"]) or "none"
    held = doc["held_out"]
    success = (f"held-out success {held['success_rate']:.2f} ({held['episodes']} episodes)"
               if held else "no held-out evaluation yet (quicknav eval RUN_DIR, then export again)")  # fmt: skip
    console.print(
        f"wrote {out}/policy.onnx and {out}/policy.json: {doc['network']['kind']} policy,"
        f" obs {doc['observation']['size']}, state: {state}; {success}",
        highlight=False,
    )
    if doc.get("map"):
        m = doc["map"]
        rows, cols = m["grid"]
        console.print(f"wrote {out}/map.npz: {m['source']} on a grid of {rows} x {cols} cells (rows x"
                      f" cols) of {m['cell_m']:g} m ({m['free_kept']:.0%} of its free space kept)",
                      highlight=False)  # fmt: skip
