"""AS511 PLC simulator (an S5 CPU's programming port) over TCP or a pseudo-terminal.

The AG state machine of :mod:`plcstack.codecs.as511` on the shared :class:`S5Memory`: function
18h answers the system parameters, 1Ah the block address, 04h/03h read and write absolute memory,
1Bh the block address list, 1Eh the operating mode. A missing block, an unknown function, a read
beyond 64 KiB or above ``max_read``, and a write outside memory or onto a block header are
refused with DLE NAK (B.9.2, D.B3, D.B5). Optional line-rate emulation (``baud``) delays every
chunk by the time its bytes need on a serial line (11 bits per byte at 8E1), so timings measured
against the simulator match a real 9600 baud line.

``plcstack sim as511 --pty`` prints ``serial port PATH`` (the end a PG opens);
``plcstack sim as511 --port 5020`` prints ``listening on HOST:PORT``.
"""

from __future__ import annotations

import argparse
import array
import asyncio
import contextlib
import logging
import os
import struct
from collections.abc import Callable
from typing import cast

from plcstack.codecs._common import NEED_DATA
from plcstack.codecs.as511 import (
    DEFAULT_CHAR_TIMEOUT,
    FN_B_INFO,
    FN_BLOCK_LIST,
    FN_OPERATING_MODE,
    FN_READ,
    FN_SYSTEM_PARAMETERS,
    FN_WRITE,
    AGConnection,
    AGState,
    Idled,
    Request,
)
from plcstack.errors import ConnectionLost
from plcstack.sim.base import (
    CLOSE_LINGER,
    DEFAULT_IDLE_TIMEOUT,
    DEFAULT_MAX_CONNECTIONS,
    Limits,
    Simulator,
    TcpSimulator,
    add_guard_arguments,
    limits_of,
    module_guard,
)
from plcstack.sim.s5memory import BLOCK_HEADER_BYTES, BlockType, S5AccessError, S5Memory
from plcstack.transports import tap
from plcstack.transports.base import HELD_UP, QueueProtocolMixin
from plcstack.transports.guard import Visit

__all__ = [
    "AS511Machine",
    "PtySimulator",
    "add_cli_arguments",
    "default_memory",
    "serve_cli",
    "start",
    "start_pty",
]

log = logging.getLogger(__name__)

#: bits per character at 8E1 (start, 8 data, parity, stop)
BITS_PER_BYTE = 11
DEFAULT_MAX_READ = 4096
#: bytes per step of the line-rate emulation (16 bytes = 18 ms at 9600 baud)
_PACE_PIECE = 16
#: offset of the mode byte in the system data (B.7.5)
MODE_OFFSET = 0x0C


def default_memory() -> S5Memory:
    """DB1..DB10 with 256 data words each (DBn.DWk = n * 100h + k mod 100h) and DX1 (64 words).

    Distinct values per DB and word make a wrong address visible at once in the CLI and tests.
    """
    mem = S5Memory()
    for n in range(1, 11):
        words = [(n << 8) | (k & 0xFF) for k in range(256)]
        mem.create_block(BlockType.DB, n, 256, struct.pack(">256H", *words))
    mem.create_block(BlockType.DX, 1, 64)
    return mem


class AS511Machine:
    """What the CPU does with a request (B.9.2 "execute"), plus fault injection for tests.

    ``busy``: answer the next STX with DLE NAK. ``mute``: ignore the line (a dead cable).
    ``running`` follows the stop/start writes of B.7.5 and function 1Eh.
    """

    def __init__(
        self,
        memory: S5Memory | None = None,
        *,
        baud: int | None = None,
        char_timeout: float = DEFAULT_CHAR_TIMEOUT,
        max_read: int = DEFAULT_MAX_READ,
        protect_headers: bool = True,
    ) -> None:
        if baud is not None and baud <= 0:
            raise ValueError("baud must be positive")
        self.memory = memory if memory is not None else default_memory()
        self.baud = baud
        self.char_timeout = char_timeout
        self.max_read = max_read
        self.protect_headers = protect_headers
        self.busy = False
        self.mute = False
        self.running = True
        #: requests executed (answered or refused), refusals, completed transactions
        self.requests = 0
        self.refusals = 0
        self.transactions = 0
        self._line_free_at = 0.0

    @property
    def byte_time(self) -> float:
        return BITS_PER_BYTE / self.baud if self.baud else 0.0

    # -- execute ---------------------------------------------------------------------------------
    def execute(self, fn: int, params: bytes) -> bytes | bool | None:
        """The data frame to send, ``None`` for "no data frame", or ``False`` to refuse (NAK)."""
        mem = self.memory
        if fn == FN_SYSTEM_PARAMETERS:
            return b"\x00" + mem.params.to_bytes() if not params else False
        if fn == FN_B_INFO:
            # [R] B.7.2/D.B3: a missing block or unknown type is refused with DLE NAK at step 9
            if len(params) != 2:
                return False
            try:
                btype = BlockType(params[0])
                dw0, header = mem.block_info(btype, params[1])
            except (ValueError, S5AccessError):
                return False  # D.B3: missing block or unknown type -> NAK at step 9
            return b"\x00" + struct.pack(">H", dw0) + header
        if fn == FN_READ:
            if len(params) != 4:
                return False
            start, end = struct.unpack(">HH", params)
            # [R] B.7.3: up to max_read (4096) bytes, NAK above; answer = 5 zero bytes + data
            if end < start or end - start + 1 > self.max_read:
                return False
            return bytes(5) + mem.read_absolute(start, end - start + 1)
        if fn == FN_WRITE:
            return self._write(params)
        if fn == FN_BLOCK_LIST:
            if len(params) != 1:
                return False
            return self._block_list(params[0])
        if fn == FN_OPERATING_MODE:
            if len(params) != 1 or params[0] > 2:
                return False
            self.running = params[0] != 0
            return None if params[0] == 0 else bytes([0x24 + params[0]])  # 25h / 26h [R]
        return False

    def _write(self, params: bytes) -> bytes | bool | None:
        if len(params) < 2:
            return False
        start = (params[0] << 8) | params[1]
        data = params[2:]
        end = start + len(data)
        if end > 0x10000:
            return False
        # [R] B.7.4: outside 64 KiB or onto a block header -> NAK; else applied before DLE ACK
        if self.protect_headers and self._touches_header(start, end):
            return False
        if data:
            self.memory.write_absolute(start, data)
        mode = self.memory.params.system_data + MODE_OFFSET
        if start <= mode < end:
            # B.7.5 [R]: STOP when bit 7 (STOZUS) of that byte is set, otherwise RUN.
            self.running = not (self.memory.image[mode] & 0x80)
        return None

    def _touches_header(self, start: int, end: int) -> bool:
        for btype, number in self.memory.blocks():
            dw0, _ = self.memory.block_info(btype, number)
            header = dw0 - BLOCK_HEADER_BYTES
            if start < dw0 and end > header:
                return True
        return False

    def _block_list(self, type_code: int) -> bytes | bool:
        # [R] B.7.6: one word per block number; the address is the one B_INFO returns
        try:
            btype = BlockType(type_code)
        except ValueError:
            return False
        entries = 256
        words = [0] * entries
        for kind, number in self.memory.blocks():
            if kind is btype:
                words[number] = self.memory.block_info(kind, number)[0]
        return b"\x00" + struct.pack(f">{entries}H", *words)

    # -- one line ------------------------------------------------------------------------------
    def new_line(self) -> AGConnection:
        """The AG's side of one new line (a connection, a serial port), with this machine's
        timing."""
        return AGConnection(char_timeout=self.char_timeout, tx_byte_time=self.byte_time)

    async def serve_line(
        self,
        line: AgLine,
        write: Callable[[bytes], None],
        ag: AGConnection | None = None,
        *,
        visit: Visit | None = None,
    ) -> bool:
        """Run the AG (``ag``, or a :meth:`new_line`) on ``line`` until it ends (False) or the
        ``visit`` of a TCP line ends between transactions (True: no first transaction in time
        after connecting, or nothing for the idle timeout; counted and said by its guard).

        A gap is what the AG saw, not what its clock says: bytes the line hands over before
        its deadline ran out are in time however late the loop saw them, and a deadline
        whose timer ran late (the loop was held up: :data:`HELD_UP`) is granted its wait
        again (``AGConnection.held_up``).
        """
        loop = asyncio.get_running_loop()
        ag = ag if ag is not None else self.new_line()
        requests = self.requests
        while True:
            if visit is not None and self.requests != requests:
                visit.served()  # a transaction's parameters came complete
                requests = self.requests
            deadline = ag.deadline
            until = deadline if deadline is not None or visit is None else visit.due
            try:
                data = await line.read(until)
            except TimeoutError:
                now = loop.time()
                if deadline is None:
                    if visit is not None and visit.expired() is not None:
                        return True
                    continue
                if now - deadline > HELD_UP:
                    ag.held_up(now)
                else:
                    ag.timer(now)
                    self._drain_events(ag, now)
                continue
            if not data:
                return False
            if visit is not None:
                visit.touch()
            if self.mute:
                continue
            ag.busy = self.busy
            if not self.byte_time:
                arrived = line.arrived or loop.time()
                ag.held_up(arrived)  # handed over before the deadline ran out: in time
                ag.receive_data(data, arrived)
                self._drain_events(ag, arrived)
                out = ag.data_to_send()
                if out:
                    write(out)
                continue
            # Line-rate emulation: bytes take their line time in pieces, as on a real line,
            # so the peer sees a steady trickle and no artificial gap longer than a piece. The
            # line's clock runs from when the bytes arrived, not from when this loop got round
            # to each piece: a loaded loop wakes late from every sleep, and counting from then
            # made the emulated line slower with every piece (a 512-byte write took a second).
            at = line.arrived or loop.time()
            for i in range(0, len(data), _PACE_PIECE):
                piece = data[i : i + _PACE_PIECE]
                at = await self._line_time(len(piece), at)
                ag.held_up(at)  # handed over before the deadline ran out: in time
                ag.receive_data(piece, at)
                self._drain_events(ag, at)
                out = ag.data_to_send()
                for j in range(0, len(out), _PACE_PIECE):
                    chunk = out[j : j + _PACE_PIECE]
                    at = await self._line_time(len(chunk), at)
                    write(chunk)

    async def _line_time(self, nbytes: int, start: float) -> float:
        """Sleep until ``nbytes`` more bytes, on the line from ``start`` (or once the
        half-duplex line is free), have passed the emulated line; returns when that is."""
        end = self._line_free_at = max(start, self._line_free_at) + nbytes * self.byte_time
        await asyncio.sleep(max(0.0, end - asyncio.get_running_loop().time()))
        return end

    def _drain_events(self, ag: AGConnection, now: float) -> None:
        while (event := ag.next_event()) is not NEED_DATA:
            if isinstance(event, Request):
                self.requests += 1
                try:
                    answer = self.execute(event.fn, event.params)
                except Exception:  # the simulator must never die on input
                    log.exception("AS511 simulator: function %02Xh failed", event.fn)
                    answer = False
                if answer is False:
                    self.refusals += 1
                    ag.refuse(now)
                else:
                    ag.respond(answer if isinstance(answer, bytes) else None, now)
            elif isinstance(event, Idled):
                log.debug("AS511 simulator idle: %s", event.reason)
            else:
                self.transactions += 1


# -- the AG's end of a line ---------------------------------------------------------------------
class AgLine(QueueProtocolMixin, asyncio.Protocol):
    """What the PG sends on one line (a TCP connection, a pty's master side), as a client's
    transport receives it: chunks queued with their arrival time (:attr:`arrived`), a read
    deadline that looks for input waiting in the kernel before it declares silence, and
    reading paused while a flood is queued."""

    def __init__(
        self,
        peer: str,
        on_made: Callable[[AgLine, asyncio.Transport], None] | None = None,
        wire: tap.ConnectionTap | None = None,
    ) -> None:
        self._init_queue(peer)
        self._on_made = on_made
        #: records what is received (a line the capture tap cannot wrap: the pty)
        self.wire = wire
        #: bytes received so far
        self.received = 0
        #: the AG works through bytes it has read (from a read that returned until the next)
        self.handling = False
        self._writable = asyncio.Event()
        self._writable.set()
        self._gone = asyncio.Event()

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        super().connection_made(transport)
        if self._on_made is not None:
            # a stream transport (uvloop's are not subclasses of asyncio's)
            self._on_made(self, cast(asyncio.Transport, transport))

    def data_received(self, data: bytes) -> None:
        self.received += len(data)
        if self.wire is not None:
            self.wire.received(data)
        self._push(data)

    def eof_received(self) -> bool | None:
        self._fail(EOFError("the PG closed the line"))
        return None

    def connection_lost(self, exc: Exception | None) -> None:
        self._fail(exc or EOFError("line closed"))
        self._writable.set()
        self._gone.set()

    def pause_writing(self) -> None:
        self._writable.clear()

    def resume_writing(self) -> None:
        self._writable.set()

    async def read(self, deadline: float | None) -> bytes:
        """The bytes received since the last read (b"" once the line ended); raises
        ``TimeoutError`` when ``deadline`` passes in silence. A PG that does not read our
        answers is waited for first, so nothing piles up here."""
        self.handling = False
        await self._writable.wait()
        try:
            data = await self._next_chunk(True, deadline)
        except ConnectionLost:
            return b""
        self.handling = True
        return data

    @property
    def queued(self) -> int:
        """Bytes received and not read yet."""
        return self.counters.queued

    async def close(self, transport: asyncio.BaseTransport) -> None:
        """Close the line; abort it if it has not closed after :data:`CLOSE_LINGER` (a PG that
        reads nothing keeps our last answer queued)."""
        transport.close()
        try:
            async with asyncio.timeout(CLOSE_LINGER):
                await self._gone.wait()
        except (TimeoutError, asyncio.CancelledError):
            transport.abort()  # type: ignore[attr-defined]


# -- TCP -------------------------------------------------------------------------------------
class AS511TcpSimulator(TcpSimulator):
    """TCP variant; ``machine`` and ``memory`` give tests access to the CPU state."""

    machine: AS511Machine
    memory: S5Memory


async def start(
    memory: S5Memory | None = None,
    *,
    host: str = "127.0.0.1",
    port: int = 0,
    baud: int | None = None,
    char_timeout: float = DEFAULT_CHAR_TIMEOUT,
    idle_timeout: float | None = DEFAULT_IDLE_TIMEOUT,
    max_connections: int = DEFAULT_MAX_CONNECTIONS,
    limits: Limits | None = None,
) -> AS511TcpSimulator:
    """Serve AS511 over TCP (a serial device server's view); returns once it accepts clients.

    ``idle_timeout``: seconds after which a connection that sent nothing is closed (default
    600, ``None``: never); ``max_connections``: connections at once, further ones are closed
    at once and counted in ``refused_connections``; ``limits`` replaces both (see
    :func:`~plcstack.sim.base.module_guard`).
    """
    guard = module_guard("as511", "AS511 simulator", max_connections, idle_timeout, limits)
    machine = AS511Machine(memory, baud=baud, char_timeout=char_timeout)
    sim: AS511TcpSimulator | None = None

    async def serve(line: AgLine, transport: asyncio.Transport, visit: Visit) -> None:
        try:
            await machine.serve_line(line, transport.write, visit=visit)
        except (ConnectionError, OSError):
            pass
        except asyncio.CancelledError:
            # aclose() ended this connection: end normally, as a handler of start_server would
            pass
        finally:
            visit.leave()
            await line.close(transport)

    def connected(line: AgLine, transport: asyncio.Transport) -> None:
        visit = guard.admit(transport.get_extra_info("peername"))
        if visit is None:
            transport.abort()
            return
        task = asyncio.get_running_loop().create_task(serve(line, transport, visit))
        if sim is not None:
            sim.track(task)

    server = await tap.create_server(lambda: AgLine(f"{host}:{port}", connected), host, port)
    query = f"baud={baud}" if baud else ""
    sim = AS511TcpSimulator(server, "as511+tcp", query, guard)
    sim.machine = machine
    sim.memory = machine.memory
    return sim


# -- pseudo-terminal -------------------------------------------------------------------------
class PtySimulator(Simulator):
    """The AG on the master side of a pty pair; a PG opens :attr:`path` (``/dev/pts/N``)."""

    def __init__(self, machine: AS511Machine) -> None:
        self.machine = machine
        self.memory = machine.memory
        import tty  # POSIX only: keep the module importable (TCP sim) elsewhere

        self._master, self._slave = os.openpty()
        # Raw slave from the start: no echo, no CR/LF mangling before a PG configures it. We keep
        # the slave open so the master never reads EIO while no PG has the port open.
        tty.setraw(self._slave)
        os.set_blocking(self._master, False)
        self.path = os.ttyname(self._slave)
        query = f"?baud={machine.baud}" if machine.baud else ""
        self.url = f"as511://{self.path}{query}"
        self._reader: asyncio.ReadTransport | None = None
        self._pending = bytearray()
        self._ag = machine.new_line()
        self._task: asyncio.Task[bool] | None = None
        self._closed = False
        # recorded when started inside a ``capturing`` block (``plcstack sim as511 --pty
        # --pcap``): the PG is the far end of this line
        capture = tap.current_tap()
        self._wire = (
            None
            if capture is None
            else capture.connection(tap.Endpoints("serial", ("", 0), ("", 0), "remote", self.path))
        )
        self._line = AgLine(self.path, wire=self._wire)

    async def _start(self) -> None:
        loop = asyncio.get_running_loop()
        # a duplicate of the master for the read side, which closes it with itself
        pipe = os.fdopen(os.dup(self._master), "rb", buffering=0)
        self._reader, _ = await loop.connect_read_pipe(lambda: self._line, pipe)
        self._task = loop.create_task(self.machine.serve_line(self._line, self._write, self._ag))

    @property
    def received(self) -> int:
        """Bytes read from the PG side so far (a pty passes them on in the kernel's own time:
        a test that wrote N bytes waits for this to count them before it looks at
        :attr:`idle`)."""
        return self._line.received

    @property
    def idle(self) -> bool:
        """The line is quiet: no byte from the PG waits to be read or handled, the AG has no
        job under way (its character timeout ended any half-received one) and its answers are
        all written. A PG that starts talking before this (after noise on the line, or a PG
        that let go mid-job) has its first bytes taken as part of what came before."""
        import fcntl  # POSIX only, as the pty itself
        import termios

        unread = array.array("i", [0])
        fcntl.ioctl(self._master, termios.FIONREAD, unread)
        return (
            not unread[0]
            and not self._line.handling
            and not self._line.queued
            and not self._pending
            and self._ag.state is AGState.IDLE
        )

    def _write(self, data: bytes) -> None:
        if self._wire is not None and data:
            self._wire.sent(data)
        self._pending += data
        self._flush()

    def _flush(self) -> None:
        loop = asyncio.get_running_loop()
        while self._pending:
            try:
                n = os.write(self._master, self._pending)
            except BlockingIOError:
                loop.add_writer(self._master, self._flush)
                return
            except OSError:
                self._pending.clear()
                break
            del self._pending[:n]
        loop.remove_writer(self._master)

    async def aclose(self) -> None:
        if self._closed:
            return
        self._closed = True
        loop = asyncio.get_running_loop()
        if self._reader is not None:
            self._reader.close()
        loop.remove_writer(self._master)
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
        os.close(self._master)
        os.close(self._slave)
        if self._wire is not None:
            self._wire.ended(by_peer=False)
            self._wire = None


async def start_pty(
    memory: S5Memory | None = None,
    *,
    baud: int | None = None,
    char_timeout: float = DEFAULT_CHAR_TIMEOUT,
) -> PtySimulator:
    """Serve AS511 on a new pseudo-terminal pair; ``.path`` is the end a PG opens."""
    sim = PtySimulator(AS511Machine(memory, baud=baud, char_timeout=char_timeout))
    await sim._start()
    return sim


# -- CLI ---------------------------------------------------------------------------------------
def add_cli_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--pty", action="store_true", help="serve on a new pseudo-terminal instead of TCP"
    )
    add_guard_arguments(parser, DEFAULT_MAX_CONNECTIONS)
    parser.add_argument("--host", default="127.0.0.1", help="TCP address (default 127.0.0.1)")
    parser.add_argument("--port", type=int, default=5020, help="TCP port (default 5020; 0 = any)")
    parser.add_argument(
        "--baud", type=int, default=None, help="emulate the line rate of this baud rate at 8E1"
    )


async def serve_cli(args: argparse.Namespace, announce: Callable[[str], None]) -> None:
    sim: Simulator
    if args.pty:
        pty_sim = await start_pty(baud=args.baud)
        announce(f"serial port {pty_sim.path}")
        sim = pty_sim
    else:
        tcp_sim = await start(
            host=args.host, port=args.port, baud=args.baud, limits=limits_of(args)
        )
        announce(f"listening on {tcp_sim.host}:{tcp_sim.port} (TCP)")
        sim = tcp_sim
    await sim.serve_forever()
