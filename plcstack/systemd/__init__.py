"""Running as a systemd service: the notify protocol, the watchdog, the unit file.

``plcstack poll`` (and every long-running command) tells systemd when it is ready, what it is
doing and that it is alive when systemd started it as a ``Type=notify`` service
(``NOTIFY_SOCKET`` set); without it nothing here does anything. ``plcstack systemd-unit
CONFIG`` prints the unit for a configuration file (docs/systemd.md).

- :mod:`.notify` - the sd_notify(3) datagrams (``READY=1``, ``STATUS=``, ``WATCHDOG=1``,
  ``RELOADING=1``, ``STOPPING=1``) to ``NOTIFY_SOCKET``;
- :mod:`.service` - when a command sends them: readiness after the first scans, the status
  line, the watchdog pings only while the loop and the scans go on;
- :mod:`.unit` - the hardened unit file, filled in for a configuration file.
"""
