"""How ``loopmodel --help`` reads (issue 35 item 6): commands in the user's flow, panels, one example each.

The commands register in their own modules; :func:`document` runs once they all have and sets each
command's help panel and example (typer's ``rich_help_panel`` and ``epilog``). :class:`FlowGroup`
lists them in the order a user meets them: simulate → info → run → eval → mesh → map → batch, then
calibration, then the research tools.
"""

from __future__ import annotations

from typing import Any

import typer
from typer import rich_utils
from typer.core import TyperGroup, TyperOption

WORKFLOW = "Workflow"
CALIBRATION = "Calibration"
RESEARCH = "Research tools"
SETTINGS = "Settings"

#: Top-level commands in the user's flow, with their help panel.
FLOW: tuple[tuple[str, str], ...] = (
    ("simulate", WORKFLOW),
    ("info", WORKFLOW),
    ("convert", WORKFLOW),
    ("run", WORKFLOW),
    ("eval", WORKFLOW),
    ("mesh", WORKFLOW),
    ("map", WORKFLOW),
    ("view", WORKFLOW),
    ("batch", WORKFLOW),
    ("calibrate", CALIBRATION),
    ("turntable", CALIBRATION),
    ("config", SETTINGS),
    ("loop", RESEARCH),
    ("bound", RESEARCH),
    ("givens-sim", RESEARCH),
    ("depth", RESEARCH),
    ("vvs", RESEARCH),
)

#: One example per command (the README's data where it has one).
EXAMPLES: dict[str, str] = {
    "simulate": "loopmodel simulate scan --preset orbit --frames 60 -o scan.mcap",
    "simulate scan": "loopmodel simulate scan --preset orbit --frames 60 -o scan.mcap",
    "info": "loopmodel info scan.mcap",
    "convert": "loopmodel convert ../shared/data/kitti_clip kitti.bag",
    "run": "loopmodel run scan.mcap -o results --rerun scan.rrd",
    "eval": "loopmodel eval results/scan --plot-mode xz",
    "mesh": "loopmodel mesh results/scan --format obj",
    "map": "loopmodel map info results/scan",
    "map info": "loopmodel map info results/scan",
    "map merge": "loopmodel map merge results/scan results/scan2 -o merged_map",
    "view": "loopmodel view results/scan -o scan.rrd",
    "batch": "loopmodel batch plan.yaml -o results/plan",
    "batch run": "loopmodel batch run plan.yaml -o results/plan",
    "batch status": "loopmodel batch status results/plan",
    "calibrate": "loopmodel calibrate stereo left/ right/ --board 9x6 --square-m 0.025 -o calib.yaml",
    "calibrate stereo": "loopmodel calibrate stereo left/ right/ --board 9x6 --square-m 0.025 -o calib.yaml",
    "calibrate laser": "loopmodel calibrate laser laser/ --intrinsics calib_left.yaml -o plane.yaml",
    "turntable": "loopmodel turntable scan ../shared/data/turntable_laser",
    "turntable scan": "loopmodel turntable scan ../shared/data/turntable_laser",
    "turntable convert": "loopmodel turntable convert ../shared/data/turntable_laser turntable.mcap",
    "config": "loopmodel config dump -c configs/kitti.yaml",
    "config dump": "loopmodel config dump -c configs/kitti.yaml -c mine.yaml",
    "loop": "loopmodel loop detect ../shared/data/loop_images",
    "loop detect": "loopmodel loop detect ../shared/data/loop_images",
    "loop vocabulary": "loopmodel loop vocabulary images/ vocabulary.npz",
    "bound": "loopmodel bound --out results/bound --distance-m 0.5",
    "givens-sim": "loopmodel givens-sim --frames 88 --blunders 0.02",
    "depth": "loopmodel depth simulate --out results/depth_sim",
    "depth simulate": "loopmodel depth simulate --out results/depth_sim",
    "depth track": "loopmodel depth track ../shared/data/kitti_clip --out results/depth_track",
    "vvs": "loopmodel vvs simulate",
    "vvs simulate": "loopmodel vvs simulate",
    "vvs calibrate": "loopmodel vvs calibrate",
    "vvs render": "loopmodel vvs render -o vvs_scene",
    "vvs track": "loopmodel vvs track vvs_scene/images --rig vvs_scene/rig.yaml --model vvs_scene/model.yaml "
    "--init vvs_scene/init.txt -o vvs_out",
}


class FlowGroup(TyperGroup):
    """The top-level group: commands listed in the user's flow (:data:`FLOW`), others after them."""

    def list_commands(self, ctx: Any) -> list[str]:  # ctx: typer's vendored click Context
        order = {name: k for k, (name, _) in enumerate(FLOW)}
        names = super().list_commands(ctx)
        return sorted(names, key=lambda n: (order.get(n, len(order)), names.index(n)))


def _example(path: str) -> str | None:
    text = EXAMPLES.get(path)
    return f"Example: {text}" if text else None


def _document_typer(app: typer.Typer, prefix: str) -> None:
    for cmd in app.registered_commands:
        name = cmd.name or (cmd.callback.__name__.replace("_", "-") if cmd.callback else "")
        path = f"{prefix} {name}".strip()
        if cmd.epilog is None:
            cmd.epilog = _example(path)
        if not prefix:
            cmd.rich_help_panel = dict(FLOW).get(name, cmd.rich_help_panel)
    for group in app.registered_groups:
        name = str(group.name)
        path = f"{prefix} {name}".strip()
        if group.typer_instance is not None:
            _document_typer(group.typer_instance, path)
            info = group.typer_instance.info
            if not isinstance(info.epilog, str):
                info.epilog = _example(path)
        if not prefix:
            group.rich_help_panel = dict(FLOW).get(name, WORKFLOW)


def document(app: typer.Typer) -> None:
    """Set every command's help panel and example; call once all commands are registered."""
    _document_typer(app, "")


def _flag_type(self: TyperOption, ctx: Any) -> str | None:
    """No ``<bool>`` beside a flag: ``--json`` takes no value (``--json true`` fails)."""
    if self.is_flag:
        return None
    return _PLAIN_DISPLAY_TYPE(self, ctx)


# typer 0.29 shows the type of every option, flags included; a flag's "<bool>" reads as if it
# took a value. Pinned typer range: pyproject.toml.
_PLAIN_DISPLAY_TYPE = TyperOption.display_type_rich
TyperOption.display_type_rich = _flag_type  # type: ignore[method-assign]


def _plain_help_text(*, text: str, style: str = "", markup_mode: Any) -> Any:
    """Help text as written: ``[m]`` is a unit, not rich markup; a paragraph's line breaks are spaces."""
    if markup_mode == "rich":
        import inspect
        import re

        from rich.markup import escape

        text = re.sub(r"(?<!\n)\n(?!\n)", " ", inspect.cleandoc(text))
        text = escape(text)
    return _RICH_TEXT(text=text, style=style, markup_mode=markup_mode)


# typer's rich mode parses help as rich markup: "Distance R [m]" showed as "Distance R". The
# docstrings are wrapped at 100 columns, so single line breaks inside a paragraph are joined.
_RICH_TEXT = rich_utils._make_rich_text
rich_utils._make_rich_text = _plain_help_text
