"""The systemd unit of one configuration file: ``plcstack systemd-unit CONFIG``.

The template (``plcstack.service`` beside this module, shipped in the package) is a hardened
``Type=notify`` service; what depends on the file is filled in here, from the loaded
configuration, so the unit grants exactly what that file needs:

- write access only where the file's paths point (``[mqtt] buffer_path`` and ``state_path``,
  ``[influx] buffer_path``, ``[audit] path``, ...): a directory under ``/var/lib`` becomes a
  ``StateDirectory=`` (systemd creates it, owned by the service's user), one under ``/var/log``
  a ``LogsDirectory=``, any other a ``ReadWritePaths=`` entry (it must exist);
- the serial ports of ``as511:///dev/...`` PLCs (``DeviceAllow=``, the ``dialout`` group);
  without one, no devices at all;
- ``CAP_NET_BIND_SERVICE`` only when a face listens on a port below 1024 (Modbus on 502);
- ``ProtectHome=read-only`` instead of ``yes`` when the interpreter, the file or a path lives
  under a home directory;
- the start timeout from the PLCs' deadlines (the first scan of each must end within it).

``ExecStart`` runs this interpreter (``sys.executable``, the one plcstack is installed in) with
``-m plcstack poll --format none``: samples go to the configured faces, not to the journal.
"""

from __future__ import annotations

import math
import os
import shlex
import sys
from importlib import resources
from pathlib import PurePosixPath

from plcstack.north.config import NorthConfig
from plcstack.poll.config import PollConfig
from plcstack.systemd.service import stall_limit
from plcstack.url import parse_url

__all__ = ["DEFAULT_USER", "DEFAULT_WATCHDOG", "listen_ports", "render_unit", "written_paths"]

#: the service's user unless ``--user`` says otherwise
DEFAULT_USER = "plcstack"
#: ``WatchdogSec=`` unless ``--watchdog`` says otherwise (0: none)
DEFAULT_WATCHDOG = 30.0
#: seconds the start may take beyond the PLCs' first scans (imports, faces starting)
START_MARGIN = 30.0
_HOMES = (PurePosixPath("/home"), PurePosixPath("/root"), PurePosixPath("/run/user"))
_MANAGED = {PurePosixPath("/var/lib"): "StateDirectory", PurePosixPath("/var/log"): "LogsDirectory"}


def written_paths(north: NorthConfig) -> list[str]:
    """Every file the configuration has plcstack write (absolute: the loader resolved relative
    ones against the file's directory), in a stable order."""
    paths: list[str | None] = []
    if north.mqtt is not None:
        paths += [north.mqtt.buffer_path, north.mqtt.state_path]
    if north.audit is not None:
        paths.append(north.audit.path)
    if north.history is not None:
        paths.append(str(north.history.path))
    if north.influx.url is not None:
        paths.append(north.influx.buffer_path)
    return list(dict.fromkeys(p for p in paths if p))


def listen_ports(north: NorthConfig) -> list[int]:
    """The TCP ports the configuration's faces listen on."""
    ports: list[int] = []
    if north.metrics is not None:
        ports.append(north.metrics.port)
    if north.web is not None:
        ports.append(north.web.port)
    if north.modbus is not None:
        ports.append(north.modbus.port)
    if north.opcua is not None:
        ports.append(north.opcua.port)
    return ports


def _installation(python: str) -> list[PurePosixPath]:
    """Where the interpreter and plcstack live: the command, the file its links lead to, the
    environment's prefixes and plcstack's package (an editable install: the source tree)."""
    places = [python, os.path.realpath(python), sys.prefix, sys.base_prefix]
    places.append(os.path.dirname(os.path.dirname(os.path.realpath(__file__))))
    return [PurePosixPath(p) for p in places]


def _quoted(text: str) -> str:
    """One word of a unit file's command line or path list: ``%`` and ``$`` are specifiers
    there (doubled), and a word with a space or quote is double-quoted."""
    text = text.replace("%", "%%").replace("$", "$$")
    if any(c in text for c in " \t\"'\\"):
        return '"' + text.replace("\\", "\\\\").replace('"', '\\"') + '"'
    return text


def _under(path: PurePosixPath, roots: tuple[PurePosixPath, ...]) -> bool:
    return any(path == root or root in path.parents for root in roots)


def render_unit(
    config_path: str,
    poll: PollConfig,
    north: NorthConfig,
    *,
    user: str = DEFAULT_USER,
    watchdog: float = DEFAULT_WATCHDOG,
    python: str | None = None,
) -> str:
    """The unit text for the configuration file ``config_path`` (absolute), already loaded
    into ``poll`` and ``north``."""
    if not PurePosixPath(config_path).is_absolute():
        raise ValueError(f"the configuration's path must be absolute, not {config_path!r}")
    if not user or any(c.isspace() for c in user):
        raise ValueError(f"a user name has no spaces and is not empty: {user!r}")
    if watchdog < 0 or not math.isfinite(watchdog):
        raise ValueError(f"the watchdog is 0 (none) or a number of seconds, not {watchdog}")
    python = python or sys.executable
    config = PurePosixPath(config_path)
    directories = list(dict.fromkeys(PurePosixPath(p).parent for p in written_paths(north)))
    managed: dict[str, list[str]] = {}
    others: list[str] = []
    for directory in directories:
        for root, key in _MANAGED.items():
            if root in directory.parents:
                managed.setdefault(key, []).append(str(directory.relative_to(root)))
                break
        else:
            others.append(str(directory))
    writable = [f"{key}={' '.join(_quoted(d) for d in dirs)}" for key, dirs in managed.items()]
    if others:
        writable.append(f"ReadWritePaths={' '.join(_quoted(d) for d in others)}")
    serial = sorted(
        {
            str(url.path)
            for plc in poll.plcs
            if (url := parse_url(plc.url)).transport == "serial" and url.path
        }
    )
    if serial:
        devices = "\n".join(
            ["PrivateDevices=no", "DevicePolicy=closed"]
            + [f"DeviceAllow={_quoted(port)} rw" for port in serial]
            + ["SupplementaryGroups=dialout"]
        )
    else:
        devices = "PrivateDevices=yes"
    low = sorted({port for port in listen_ports(north) if 0 < port < 1024})
    if low:
        ports = ", ".join(str(p) for p in low)
        capabilities = (
            f"# port {ports} is below 1024: the one capability to listen there\n"
            "CapabilityBoundingSet=CAP_NET_BIND_SERVICE\nAmbientCapabilities=CAP_NET_BIND_SERVICE"
        )
    else:
        capabilities = "CapabilityBoundingSet="
    # a home directory stays readable (not writable, but for the paths above) when the
    # interpreter (or what its link points to, or its packages), the file or a written path is
    # there
    homes = [*_installation(python), config, *directories]
    protect_home = "read-only" if any(_under(p, _HOMES) for p in homes) else "yes"
    exec_start = " ".join(
        _quoted(word) for word in (python, "-m", "plcstack", "poll", "--format", "none")
    )
    exec_start += f" {_quoted(config_path)}"
    count = len(poll.plcs)
    template = resources.files("plcstack.systemd").joinpath("plcstack.service").read_text()
    return template.format(
        description=f"{count} PLC{'s' if count != 1 else ''} of {config_path}".replace("%", "%%"),
        config_arg=shlex.quote(config_path),
        unit_name=f"plcstack-{config.stem}.service",
        user=user,
        exec_start=exec_start,
        timeout_start=math.ceil(stall_limit(poll) + START_MARGIN),
        watchdog=f"WatchdogSec={watchdog:g}s" if watchdog else "# no watchdog (--watchdog 0)",
        protect_home=protect_home,
        devices=devices,
        writable="\n".join(writable) or "# nothing written: no path of the file is writable",
        capabilities=capabilities,
    )
