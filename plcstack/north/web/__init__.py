"""The web console and REST API of a poller (``[web]``; the ``web`` extra: aiohttp).

- :mod:`.settings` - the ``[web]`` table (no aiohttp needed to check it).
- :mod:`.state` - what the console knows: latest sample per tag, PLC health, trend rings.
- :mod:`.events` - server-sent events: changes only, bounded per client, slow clients dropped.
- :mod:`.pages` - the HTML pages and the SVG trend chart, every name and value escaped.
- :mod:`.api` - the REST handlers: ``/api/plcs``, ``/api/tags``, writes with a bearer token.
- :mod:`.server` - :class:`~.server.WebConsole`: the aiohttp application on the poller's loop.

This package's ``__init__`` imports nothing, so the config loader can check ``[web]`` on an
install without aiohttp.
"""
