"""The ``[[gateway]]`` faces of a run changed while it runs (a reload): an unchanged face keeps
listening and keeps its clients, a changed entry restarts alone (its clients see their
connection closed, said once), a removed one closes, a new one starts, a face of a PLC the
poller connected anew starts again on the new connection; a port taken is said and the rest
applied. Over real sockets, in front of real simulators."""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import os
import signal
import subprocess
import sys
from collections.abc import AsyncIterator
from pathlib import Path

import pytest

from plcstack.clients.e71 import E71Client
from plcstack.codecs import s5lan as lan_codec
from plcstack.errors import AddressError
from plcstack.gateway.faces import FaceSettings, GatewayFaces
from plcstack.poll.config import parse_poll_config
from plcstack.poll.engine import Poller
from plcstack.sim import e71 as e71_sim
from plcstack.sim import s5lan as lan_sim
from plcstack.sim.s5memory import S5Memory
from plcstack.url import parse_url
from tests.faces_helpers import RawStream
from tests.ports import free_port

ROOT = Path(__file__).resolve().parents[1]

PLCS = """
[poll]
interval = 0.05
backoff_max = 0.2

[[plc]]
name = "kiln1"
url = "{kiln1}"

[plc.tags]
v = "DB1.DW0"

[[plc]]
name = "kiln2"
url = "{kiln2}"

[plc.tags]
v = "DB1.DW0"
"""


def _memory(mark: int) -> S5Memory:
    memory = lan_sim.default_memory()
    memory.write_db_words(1, 0, [mark] * 16)
    return memory


def _face(protocol: str, port: int, plc: str = "kiln1", **options: object) -> FaceSettings:
    return FaceSettings(protocol, "127.0.0.1", port, plc, **options)  # type: ignore[arg-type]


async def _ask(stream: RawStream) -> int:
    """DB1.DW0 through an S5-LAN face."""
    answer, _ = await stream.ask(lan_codec.Request.read("D", "W", 0, 1, db=1), timeout=5.0)
    assert answer.err == 0
    return int.from_bytes(answer.data[:2], "little")


async def _closed(stream: RawStream) -> bool:
    """Whether the face closed the connection (EOF within a few seconds)."""
    with contextlib.suppress(ConnectionError):
        async with asyncio.timeout(5.0):
            return await stream.reader.read(100) == b""
    return True


@contextlib.asynccontextmanager
async def _plant(
    faces: list[FaceSettings],
) -> AsyncIterator[tuple[Poller, GatewayFaces, lan_sim.S5LanSimulator, lan_sim.S5LanSimulator]]:
    """Two S5-LAN modules of one connection each (DB1.DW0 = 0x1111 and 0x2222), polled, and
    ``faces`` running on the poller's connections."""
    one = await lan_sim.start(_memory(0x1111))
    two = await lan_sim.start(_memory(0x2222))
    async with one, two:
        config = parse_poll_config(PLCS.format(kiln1=one.url, kiln2=two.url))
        async with Poller(config) as poller:
            natives = GatewayFaces(faces, poller.client)
            async with natives:
                yield poller, natives, one, two


async def test_a_changed_entry_restarts_alone_and_the_unchanged_keep_their_clients(
    caplog: pytest.LogCaptureFixture,
) -> None:
    a, b, c = free_port(), free_port(), free_port()
    before = [_face("s5lan", a, writable="DB10"), _face("s5lan", b)]
    async with _plant(before) as (_, natives, one, _two):
        on_a = await RawStream.open("127.0.0.1", a, lan_codec.ClientConnection())
        on_b = await RawStream.open("127.0.0.1", b, lan_codec.ClientConnection())
        assert await _ask(on_a) == await _ask(on_b) == 0x1111
        caplog.set_level(logging.INFO, "plcstack.gateway")
        after = [_face("s5lan", a, writable="DB10-11"), _face("s5lan", b), _face("s5lan", c)]
        applied = await natives.apply(after)
        assert applied.restarted == (f"s5lan face of kiln1 on 127.0.0.1:{a} (TCP)",)
        assert applied.started == (f"s5lan face of kiln1 on 127.0.0.1:{c} (TCP)",)
        assert applied.closed == applied.failed == ()
        assert applied.kept == 1
        assert await _closed(on_a)  # told by a closed connection
        assert await _ask(on_b) == 0x1111  # the same connection goes on
        on_c = await RawStream.open("127.0.0.1", c, lan_codec.ClientConnection())
        again = await RawStream.open("127.0.0.1", a, lan_codec.ClientConnection())
        assert await _ask(on_c) == await _ask(again) == 0x1111
        said = [r for r in caplog.records if "restarted" in r.getMessage()]
        assert [(r.levelno, r.getMessage()) for r in said] == [
            (
                logging.WARNING,
                f"s5lan face of kiln1 on 127.0.0.1:{a} (TCP) restarted (its [[gateway]] entry"
                " changed: writable); its 1 clients' connections closed",
            )
        ]
        assert [f.writable for f in natives.settings] == ["DB10-11", "", ""]
        for stream in (on_a, on_b, on_c, again):
            await stream.aclose()
        assert one.connection_count.peak == 1  # the poller's, all along


async def test_removed_entries_close_and_a_new_plc_s_faces_start() -> None:
    a, b = free_port(), free_port()
    async with _plant([_face("s5lan", a), _face("fetchwrite", b)]) as (_, natives, one, two):
        on_a = await RawStream.open("127.0.0.1", a, lan_codec.ClientConnection())
        assert await _ask(on_a) == 0x1111
        applied = await natives.apply([_face("s5lan", a), _face("s5lan", b, "kiln2")])
        # b was kiln1's FETCH/WRITE face; now kiln2's S5-LAN face on the same port
        assert applied.restarted == (f"s5lan face of kiln2 on 127.0.0.1:{b} (TCP)",)
        assert applied.kept == 1 and applied.started == applied.closed == ()
        on_b = await RawStream.open("127.0.0.1", b, lan_codec.ClientConnection())
        assert await _ask(on_a) == 0x1111 and await _ask(on_b) == 0x2222
        applied = await natives.apply([_face("s5lan", b, "kiln2")])
        assert applied.closed == (f"s5lan face of kiln1 on 127.0.0.1:{a} (TCP)",)
        assert applied.kept == 1
        assert await _closed(on_a)
        assert await _ask(on_b) == 0x2222
        assert [p.name for p in natives.plcs] == ["kiln2"]
        # the closed PLC's faces still count in the run's last lines
        first, now = natives.summary()
        assert first.startswith("faces of kiln1 (until a reload): ") and now.startswith(
            "faces of kiln2: "
        )
        assert int(first.split(": ")[1].split()[0]) >= 2  # kiln1's requests through a
        with pytest.raises(OSError):
            await asyncio.open_connection("127.0.0.1", a)
        await on_a.aclose()
        await on_b.aclose()
        # every face gone: nothing listens, and an empty apply is fine
        assert (await natives.apply([])).closed == (f"s5lan face of kiln2 on 127.0.0.1:{b} (TCP)",)
        assert natives.plcs == [] and natives.listening() == []
        assert one.connection_count.peak == two.connection_count.peak == 1


async def test_faces_of_a_plc_connected_anew_start_again_on_the_new_connection() -> None:
    a = free_port()
    async with _plant([_face("s5lan", a)]) as (poller, natives, one, two):
        on_a = await RawStream.open("127.0.0.1", a, lan_codec.ClientConnection())
        assert await _ask(on_a) == 0x1111
        third = await lan_sim.start(_memory(0x3333))
        async with third:
            moved = PLCS.format(kiln1=third.url, kiln2=two.url)
            await poller.reconfigure(parse_poll_config(moved))
            applied = await natives.apply([_face("s5lan", a)])
            assert applied.restarted == (f"s5lan face of kiln1 on 127.0.0.1:{a} (TCP)",)
            assert await _closed(on_a)
            again = await RawStream.open("127.0.0.1", a, lan_codec.ClientConnection())
            assert await _ask(again) == 0x3333  # the new PLC, on the poller's new connection
            await again.aclose()
            await on_a.aclose()
            assert third.connection_count.peak == 1
        assert one.connection_count.current == 0  # the old connection closed with its faces


async def test_a_port_taken_is_said_and_the_rest_applied(caplog: pytest.LogCaptureFixture) -> None:
    a, b, c = free_port(), free_port(), free_port()
    squatter = await asyncio.start_server(lambda r, w: w.close(), "127.0.0.1", c)
    async with squatter, _plant([_face("s5lan", a)]) as (_, natives, _one, _two):
        applied = await natives.apply([_face("s5lan", a), _face("s5lan", b), _face("s5lan", c)])
        assert applied.started == (f"s5lan face of kiln1 on 127.0.0.1:{b} (TCP)",)
        (failed,) = applied.failed
        assert failed.startswith(f"s5lan face of kiln1 on 127.0.0.1:{c} (TCP): ")
        assert "in use" in failed
        assert "cannot listen" in applied.summary()
        assert any(
            r.levelno == logging.ERROR and "cannot listen" in r.getMessage() for r in caplog.records
        )
        squatter.close()
        await squatter.wait_closed()
        # the same file applied again tries the face that could not listen
        applied = await natives.apply([_face("s5lan", a), _face("s5lan", b), _face("s5lan", c)])
        assert applied.started == (f"s5lan face of kiln1 on 127.0.0.1:{c} (TCP)",)
        assert applied.kept == 2 and applied.failed == ()


async def test_a_face_that_does_not_fit_its_plc_changes_nothing() -> None:
    a = free_port()
    async with _plant([_face("s5lan", a)]) as (_, natives, _one, _two):
        on_a = await RawStream.open("127.0.0.1", a, lan_codec.ClientConnection())
        with pytest.raises(AddressError, match="E71"):
            await natives.apply([_face("e71", free_port())])
        assert await _ask(on_a) == 0x1111
        await on_a.aclose()


async def test_a_queue_change_restarts_the_plc_s_faces_and_a_same_file_keeps_all() -> None:
    a, b = free_port(), free_port()
    faces = [_face("s5lan", a), _face("fetchwrite", b)]
    async with _plant(faces) as (_, natives, _one, _two):
        on_a = await RawStream.open("127.0.0.1", a, lan_codec.ClientConnection())
        assert (await natives.apply(faces)).kept == 2
        assert await _ask(on_a) == 0x1111
        longer = [dataclasses.replace(f, max_wait=5.0) for f in faces]
        applied = await natives.apply(longer)
        assert len(applied.restarted) == 2 and applied.kept == 0
        assert await _closed(on_a)
        assert natives.plcs[0].share.max_wait == 5.0
        await on_a.aclose()


class _Broken(BaseException):
    """What no face queue catches: a defect."""


class _BrokenE71(E71Client):
    """An E71 client whose connection breaks the face queue that asks for a turn."""

    @contextlib.asynccontextmanager
    async def turn(self, deadline: float | None = None) -> AsyncIterator[None]:
        raise _Broken("the queue broke")
        yield


async def test_watch_says_a_face_queue_that_stopped_by_itself_but_not_one_closed() -> None:
    async with await e71_sim.start() as plc:
        clients: dict[str, E71Client] = {
            "good": E71Client.create(parse_url(plc.url), {}),
            "bad": _BrokenE71.create(parse_url(plc.url), {}),
        }
        faces = [_face("e71", 0, "good"), _face("e71", 0, "bad")]
        async with GatewayFaces(faces, clients.__getitem__) as natives:
            watch = asyncio.create_task(natives.watch())
            await asyncio.sleep(0)  # it follows the queues now
            await natives.apply([faces[0]])  # the bad PLC's faces closed: not a failure
            await asyncio.sleep(0.05)
            assert not watch.done()
            applied = await natives.apply(faces)  # started again, then asked
            assert len(applied.started) == 1
            (bad,) = [p for p in natives.plcs if p.name == "bad"]
            server = bad.servers[0]
            _, writer = await asyncio.open_connection(server.host, server.port)
            writer.write(bytes.fromhex("00ff0a006400000020440100"))  # read D100
            with pytest.raises(RuntimeError, match="the face queue of bad stopped"):
                async with asyncio.timeout(5.0):
                    await watch
            writer.close()
        for client in clients.values():
            await client.aclose()


def _gateway(port: int, writable: str = "") -> str:
    return (
        f'\n[[gateway]]\nprotocol = "s5lan"\nlisten = "127.0.0.1:{port}"\nplc = "kiln1"\n'
        f'writable = "{writable}"\n'
    )


async def _line_with(stream: asyncio.StreamReader, text: str) -> str:
    async with asyncio.timeout(20):
        while True:
            line = (await stream.readline()).decode()
            assert line, f"plcstack poll ended before it said {text!r}"
            if text in line:
                return line


async def test_sighup_applies_gateway_entries_in_plcstack_poll_and_the_run_goes_on(
    tmp_path: Path,
) -> None:
    """Before: a reload said [[gateway]] waited for a restart; and the run watched the face
    queues of its start, so a reload that closed one would have ended the run."""
    a, b = free_port(), free_port()
    config = tmp_path / "plant.toml"
    plc = '[poll]\ninterval = 0.05\n[[plc]]\nname = "kiln1"\nurl = "{url}"\n'
    plc += '[plc.tags]\nv = "DB1.DW0"\n'
    async with await lan_sim.start(_memory(0x1111)) as module:
        plc = plc.format(url=module.url)
        config.write_text(plc + _gateway(a, "DB10"))
        proc = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "plcstack", "-v", "poll", str(config), "--format", "none",
            "--duration", "60",
            stderr=subprocess.PIPE, env={**os.environ, "PYTHONPATH": str(ROOT)}, cwd=ROOT,
        )  # fmt: skip
        assert proc.stderr is not None
        try:
            await _line_with(proc.stderr, f"listening on 127.0.0.1:{a}")
            on_a = await RawStream.open("127.0.0.1", a, lan_codec.ClientConnection())
            assert await _ask(on_a) == 0x1111
            # a's entry changed, b new: a restarts alone, b starts
            config.write_text(plc + _gateway(a, "DB10-11") + _gateway(b))
            proc.send_signal(signal.SIGHUP)
            said = await _line_with(proc.stderr, "reload (SIGHUP)")
            assert f"[[gateway]] faces: 1 started (s5lan face of kiln1 on 127.0.0.1:{b}" in said
            assert f"1 restarted (s5lan face of kiln1 on 127.0.0.1:{a} (TCP))" in said
            assert await _closed(on_a)
            on_b = await RawStream.open("127.0.0.1", b, lan_codec.ClientConnection())
            assert await _ask(on_b) == 0x1111
            # every face removed: their queue closes, and the run goes on
            config.write_text(plc)
            proc.send_signal(signal.SIGHUP)
            said = await _line_with(proc.stderr, "reload (SIGHUP)")
            assert "[[gateway]] faces: 0 started, 0 restarted, 2 closed" in said, said
            assert await _closed(on_b)
            await asyncio.sleep(0.5)
            assert proc.returncode is None, "the run ended when its faces were closed"
            await on_a.aclose()
            await on_b.aclose()
        finally:
            if proc.returncode is None:
                proc.terminate()
            _, err = await asyncio.wait_for(proc.communicate(), 10)
        assert proc.returncode == 0, err.decode()
        assert module.connection_count.peak == 1
