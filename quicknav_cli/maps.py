"""`quicknav maps`: building maps on a running service (upload, list, show, delete), via the SDK."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console

from quicknav_cli.common import console
from quicknav_cli.jobs import jobs_main, service_client

app = typer.Typer(
    help="Maps of your buildings on a QuickNav service: upload, list, show, delete. A config names"
    " an uploaded map as map:<id> (--set env.rooms=maps --set env.maps.train='[\"map:<id>\"]').",
    no_args_is_help=True,
)
app.callback()(jobs_main)

MapRef = Annotated[str, typer.Argument(help="The map's id (or map:<id>).")]


def _describe(m: dict) -> str:
    env = m["suggested_env"]
    sets = (f"--set env.rooms=maps --set env.maps.train='[\"{m['ref']}\"]'"
            f" --set env.grid_size={env['grid_size']} --set env.room_size={env['room_size']:g}")  # fmt: skip
    for key in ("grid_rows", "grid_cols"):  # a non-square map's grid
        if env.get(key):
            sets += f" --set env.{key}={env[key]}"
    if env.get("max_steps"):
        sets += f" --set env.max_steps={env['max_steps']}"
    notes = "".join(f"\n  note: {n}" for n in m.get("notes", []))
    return (f"map {m['id']} ({m['name']}): {m['width_px']} x {m['height_px']} pixels at"
            f" {m['resolution']:g} m, {m['width_m']:g} m x {m['height_m']:g} m, free"
            f" {100 * m['free_fraction']:.0f} %, unknown {100 * m['unknown_fraction']:.0f} %\n"
            f"  in a config: {m['ref']}\n  at 0.5 m cells: {sets}{notes}")  # fmt: skip


@app.command("upload")
def maps_upload(
    ctx: typer.Context,
    path: Annotated[Path, typer.Argument(help="A map_server .yaml (its image goes with it), or a .png/.pgm.")],
    resolution: Annotated[float | None, typer.Option(help="Metres per pixel (plain images only).")] = None,
    name: Annotated[str | None, typer.Option(help="A label (default: the image's name).")] = None,
    negate: Annotated[bool | None, typer.Option("--negate/--no-negate", help="Plain images: white is occupied.")] = None,
    occupied_thresh: Annotated[float | None, typer.Option(help="Plain images: occupied above (0.65).")] = None,
    free_thresh: Annotated[float | None, typer.Option(help="Plain images: free below (0.196).")] = None,
) -> None:  # fmt: skip
    """Upload a map; the server reads it as a job will and refuses a file it cannot use."""
    with service_client(ctx) as client:
        try:
            m = client.upload_map(path, name=name, resolution=resolution, negate=negate,
                                  occupied_thresh=occupied_thresh, free_thresh=free_thresh)  # fmt: skip
        except (FileNotFoundError, ValueError) as e:
            from quicknav_cli.common import fail

            fail(str(e))
    console.print(_describe(m), highlight=False, soft_wrap=True)


@app.command("list")
def maps_list(ctx: typer.Context) -> None:
    """Every uploaded map, newest first."""
    from rich.table import Table

    with service_client(ctx) as client:
        found = client.maps()
    table = Table(title=f"{len(found)} maps")
    for col in ("id", "name", "pixels", "m/pixel", "size", "free", "in use by"):
        table.add_column(col, no_wrap=True)
    for m in found:
        table.add_row(m["id"], m["name"], f"{m['width_px']} x {m['height_px']}", f"{m['resolution']:g}",
                      f"{m['width_m']:g} x {m['height_m']:g} m", f"{100 * m['free_fraction']:.0f} %",
                      ", ".join(j[:8] for j in m["used_by"]) or "-")  # fmt: skip
    Console(width=max(console.width, 110), markup=False, emoji=False).print(table)


@app.command("show")
def maps_show(
    ctx: typer.Context,
    ref: MapRef,
    preview: Annotated[Path | None, typer.Option(help="Write the map's picture to this PNG file.")] = None,
    download: Annotated[Path | None, typer.Option(help="Write map.yaml and its image into this folder.")] = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print the map's JSON.")] = False,
) -> None:  # fmt: skip
    """One map: size, resolution, free space, the env fields that hold it, the jobs using it."""
    with service_client(ctx) as client:
        m = client.map(ref)
        if as_json:
            print(json.dumps(m, indent=1))
        else:
            console.print(_describe(m), highlight=False, soft_wrap=True)
            if m["used_by"]:
                console.print(f"  used by queued or running jobs: {', '.join(m['used_by'])}", highlight=False)
        if preview is not None:
            console.print(f"wrote {client.map_preview(ref, preview)}", highlight=False)
        if download is not None:
            console.print(f"wrote {client.download_map(ref, download)} and its image", highlight=False)


@app.command("delete")
def maps_delete(ctx: typer.Context, ref: MapRef) -> None:
    """Delete a map (refused while a queued or running job uses it)."""
    with service_client(ctx) as client:
        client.delete_map(ref)
    console.print(f"deleted map {ref.removeprefix('map:')}", highlight=False)
