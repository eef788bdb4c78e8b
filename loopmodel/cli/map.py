"""``loopmodel map``: describe a session map, merge two maps (issue 20)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer
from rich.table import Table

from loopmodel.cli.common import ConfigOption, app, console
from loopmodel.config import load_config

map_app = typer.Typer(help="Session maps: describe, merge.", no_args_is_help=True)

app.add_typer(map_app, name="map")

MapArgument = Annotated[Path, typer.Argument(help="Map folder (a run's RESULTS_DIR/map, or the results folder)")]


@map_app.command("info")
def map_info(
    path: MapArgument,
    as_json: Annotated[bool, typer.Option("--json", help="Print JSON instead of a table")] = False,
) -> None:
    """Describe a map: keyframes, sessions, features, vocabulary, landmarks, pose graph, stripes, size."""
    import time

    import numpy as np
    from rich.markup import escape

    from loopmodel.display import Formatter, describe_rows
    from loopmodel.io.map_file import load_session_map, map_folder, map_size_bytes

    t0 = time.perf_counter()
    smap = load_session_map(path)
    desc = {
        "map": str(map_folder(path)),
        **smap.summary(),
        "size_mib": map_size_bytes(path) / 2**20,
        "load_s": time.perf_counter() - t0,
    }
    if as_json:
        console.print_json(json.dumps(desc))
        return
    table = Table(title=str(path), show_header=False)
    rows = dict(desc)
    rows["sessions"] = ", ".join(f"session {k}: {n} keyframes" for k, n in desc["sessions"].items())
    fmt = Formatter.for_scale(float(np.linalg.norm(desc["keyframe_extent_m"])) if len(smap) else None)
    for k, v in describe_rows(rows, fmt):
        table.add_row(escape(k), escape(v))
    console.print(table)


@map_app.command("merge")
def map_merge(
    first: Annotated[Path, typer.Argument(help="Map A (its world is the merged map's)")],
    second: Annotated[Path, typer.Argument(help="Map B (moved into A's world)")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Merged map folder to write")],
    config: ConfigOption = None,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace an existing map folder at --out")] = False,
) -> None:
    """Merge map B into map A: place recognition finds where they share a view, then a joint optimisation."""
    from loopmodel.errors import InputError
    from loopmodel.io.map_file import load_session_map, save_session_map
    from loopmodel.loop.merge import merge_maps

    if out.exists() and not overwrite:  # checked before the work (an input's own map/ too)
        raise InputError(out, "exists; choose another --out or pass --overwrite")
    cfg = load_config(config)
    a, b = load_session_map(first), load_session_map(second)
    merged, report = merge_maps(a, b, cfg.loop)
    save_session_map(out, merged)
    console.print(
        f"wrote {out}: {len(merged)} keyframes ({len(a)} + {len(b)}), "
        f"{report.links} links between the maps ({report.candidates} candidates), "
        f"B moved by {report.offset_m:.3f} m / {report.offset_deg:.2f} deg"
    )
