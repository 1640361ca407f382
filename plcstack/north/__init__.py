"""The north side: where the poller's samples go and where writes from other systems come in.

Each server or sink takes samples from the :class:`~plcstack.poll.Poller` and sends writes back
only through its single-flight ``write_tag``, so a write from any north-side client obeys the same
rules as one from Python. Modules that need an optional dependency (``opcua``: asyncua) import it
themselves; importing this package needs nothing beyond plcstack.
"""
