"""``plcstack systemd-unit CONFIG``: the systemd service unit that polls CONFIG, on stdout.

The unit runs ``plcstack poll --format none CONFIG`` with this installation's Python as a
hardened Type=notify service: ready once its faces listen and every PLC had its first scan, a
watchdog that restarts it when its scans stop, reloaded with ``systemctl reload``, restarted on
failure, and writable nowhere but where CONFIG's paths point. Install it with:

  plcstack systemd-unit /etc/plcstack/plant.toml > plcstack-plant.service
  sudo cp plcstack-plant.service /etc/systemd/system/
  sudo systemctl daemon-reload && sudo systemctl enable --now plcstack-plant

The whole walkthrough (user, credentials, status, logs, reload): plcstack docs systemd.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from plcstack.cli import UsageError, plain_text
from plcstack.config import load_config
from plcstack.systemd.unit import DEFAULT_USER, DEFAULT_WATCHDOG, render_unit


def register(subparsers: Any) -> None:
    unit = subparsers.add_parser(
        "systemd-unit",
        help="print the systemd service unit that polls a TOML config",
        description=plain_text(__doc__),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    unit.add_argument("config", help="the TOML file the service polls (made absolute)")
    unit.add_argument(
        "--user",
        default=DEFAULT_USER,
        help=f"the user the service runs as (default {DEFAULT_USER}); it must exist",
    )
    unit.add_argument(
        "--watchdog",
        type=float,
        default=DEFAULT_WATCHDOG,
        metavar="SECONDS",
        help=f"WatchdogSec: restart when no ping came for this long (default {DEFAULT_WATCHDOG:g};"
        " 0: no watchdog)",
    )
    unit.set_defaults(func=run_unit)


async def run_unit(args: argparse.Namespace) -> int:
    sys.stdout.write(unit_text(args.config, user=args.user, watchdog=args.watchdog))
    return 0


def unit_text(config: str, *, user: str, watchdog: float) -> str:
    """The unit for the file ``config`` (a file that does not load: its FILE:LINE error)."""
    path = str(Path(config).absolute())
    whole = load_config(path)
    poll, north = whole.poll, whole.north
    try:
        return render_unit(path, poll, north, user=user, watchdog=watchdog)
    except ValueError as exc:
        raise UsageError(f"systemd-unit: {exc}") from None
