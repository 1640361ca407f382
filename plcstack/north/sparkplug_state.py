"""The Sparkplug edge node's ``bdSeq`` kept on disk, so a restarted poller continues the sequence.

Why: a Sparkplug host application pairs the ``bdSeq`` metric of an NDEATH (the MQTT Will, which
the broker may deliver late, after the node's next NBIRTH) with the NBIRTH of the same session.
The specification (3.0, "bdSeq number MUST start at zero and increment by one on every new MQTT
CONNECT packet", 0..255 then 0 again) counts CONNECTs of the edge node, not of one process: a
restart that began again at 0 lets a late Will of the old session carry the number of the new
one, and the host marks a live node offline.

What is stored: the ``bdSeq`` of the most recent CONNECT, written *before* that CONNECT is sent
(a crash right after it still counts it), with the group and edge node id it belongs to::

    {"group_id": "plant1", "edge_node_id": "line1", "bdSeq": 17}

Written atomically: a temporary file in the same directory, flushed and fsynced, then renamed
over the old one, so a power cut leaves the old or the new number, never half a file. A missing
file means a node that never connected (start at 0); an unreadable or corrupt one, or one of
another edge node, starts at 0 too, with a warning: the node must keep publishing, and a host
that sees bdSeq 0 again treats it as a new session, which is the safe side. A corrupt or
foreign file is moved aside first (``sparkplug.corrupt-TIME.json``, one WARNING naming both
paths), never overwritten: it may be the only record of what happened.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import tempfile
from pathlib import Path

from plcstack.statefiles import fsync_directory, move_aside

__all__ = ["BdSeqStore", "default_state_path"]

log = logging.getLogger("plcstack.north.sparkplug")


def default_state_path(buffer_path: str | None) -> str | None:
    """Next to the store-and-forward file: ``/var/lib/plcstack/mqtt.sqlite`` ->
    ``/var/lib/plcstack/mqtt.sparkplug.json`` (None without a buffer file)."""
    if buffer_path is None:
        return None
    path = Path(buffer_path)
    return str(path.with_name(f"{path.stem}.sparkplug.json"))


class BdSeqStore:
    """Loads and saves the last ``bdSeq`` of one edge node (``group_id``/``edge_node_id``)."""

    def __init__(self, path: str | os.PathLike[str], group_id: str, edge_node_id: str) -> None:
        self.path = Path(path)
        self.group_id = group_id
        self.edge_node_id = edge_node_id
        #: the last save failed (logged once until one succeeds again)
        self.failing = False

    def load(self) -> int | None:
        """The ``bdSeq`` of the last CONNECT, or None when there was none (or it cannot be
        trusted: then a warning says why).

        A file that is not a bdSeq state file of this edge node (bytes that are not JSON, a
        number out of range, another node's file) is moved aside (see
        :mod:`plcstack.statefiles`): kept for whoever wants to look, never read again.
        """
        try:
            raw = self.path.read_bytes()
        except FileNotFoundError:
            return None
        except OSError as exc:
            log.warning(
                "sparkplug: cannot read %s (%s); bdSeq starts at 0", self.path, exc.strerror or exc
            )
            return None
        value, why = self._parse(raw)
        if why is not None:
            move_aside(
                self.path,
                why,
                what="sparkplug: bdSeq state file",
                then="bdSeq starts at 0",
                logger=log,
            )
        return value

    def _parse(self, raw: bytes) -> tuple[int | None, str | None]:
        """(the stored bdSeq, None) or (None, why the file cannot be trusted)."""
        try:
            data = json.loads(raw.decode("utf-8"))
        except UnicodeDecodeError:
            return None, "not UTF-8 text"
        except ValueError:
            return None, "not JSON" if raw.strip() else "empty"
        if not isinstance(data, dict) or not {"bdSeq", "group_id", "edge_node_id"} <= data.keys():
            return None, "not a bdSeq state file: needs group_id, edge_node_id and bdSeq"
        value = data["bdSeq"]
        if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= 255:
            return None, f"bdSeq {value!r} is not 0..255"
        owner = (data["group_id"], data["edge_node_id"])
        if owner != (self.group_id, self.edge_node_id):
            return None, (
                f"it belongs to edge node {owner[0]}/{owner[1]},"
                f" not {self.group_id}/{self.edge_node_id}"
            )
        return value, None

    def save(self, bd_seq: int) -> bool:
        """Store ``bd_seq`` atomically; False (and a warning, once) if the disk refused it.

        A failure does not stop the node: publishing matters more than the number, and the
        next CONNECT tries again.
        """
        data = {"group_id": self.group_id, "edge_node_id": self.edge_node_id, "bdSeq": bd_seq}
        tmp: str | None = None
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(
                prefix=f".{self.path.name}.", suffix=".tmp", dir=self.path.parent
            )
            with os.fdopen(fd, "w", encoding="utf-8") as f:
                json.dump(data, f)
                f.write("\n")
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, self.path)
            tmp = None
            fsync_directory(self.path.parent)
        except OSError as exc:
            if not self.failing:
                log.warning(
                    "sparkplug: cannot save bdSeq %d to %s (%s); a restart may repeat it",
                    bd_seq,
                    self.path,
                    exc,
                )
            self.failing = True
            return False
        finally:
            if tmp is not None:
                with contextlib.suppress(OSError):
                    os.unlink(tmp)
        if self.failing:
            log.warning("sparkplug: bdSeq saved to %s again", self.path)
        self.failing = False
        return True
