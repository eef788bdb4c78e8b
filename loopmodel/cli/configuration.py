"""``loopmodel config``: the effective configuration."""

from __future__ import annotations

import sys

from loopmodel.cli.common import (
    ConfigOption,
    config_app,
)
from loopmodel.config import dump_config, load_config


@config_app.command("dump")
def config_dump(config: ConfigOption = None) -> None:
    """Print the effective configuration (defaults overridden by --config) as YAML."""
    sys.stdout.write(dump_config(load_config(config)))
