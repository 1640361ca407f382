"""The walkthroughs of the docs run as written.

A walkthrough is a section whose heading starts with ``## Walkthrough``; a page may have several,
each a test of its own. The ``toml`` blocks of a page's walkthroughs whose first line is
``# FILE`` are written to FILE in a fresh working directory (the source checkout's
``examples/`` is there too), and a section's one ``sh`` block runs line by line, in order:

- a ``plcstack`` line runs in this process (the same ``args.func`` as the command line). An
  ``&`` line of a server (``sim``, ``gateway``, ``serve``) is started and waited for until it
  says ``listening on`` (on stdout or stderr); any other ``&`` line (``poll``) is started.
- ``plcstack ... | CMD``: what plcstack printed is CMD's stdin; ``plcstack ... > FILE``: it is
  written to FILE.
- any other line runs in ``/bin/sh`` in the working directory, with this Python's scripts first
  on PATH (``python``, ``uaread``). An ``&`` line (a broker, a database) is started and waited
  for until every port it names, on the line or in a file it names, accepts connections.
- A trailing comment is the output: the comment and the comment-only lines right after the
  command must each match a line of the output, in order, ``...`` standing for any text (for a
  server's ``&`` line: what it printed when it started). ``# exit N`` (and a reason after it)
  is the exit code instead; comment-only lines after it are still the output.

Every port the block and its files name is replaced by a free one (``tests.ports``: reserved
for this process, never one the kernel hands out meanwhile), the same one wherever it repeats,
so a walkthrough neither needs nor takes its documented ports. After each line, a background
command that has ended fails the test with what it printed. A walkthrough has :data:`BUDGET`
seconds in all, less than pytest's own timeout, so whatever it started is stopped at the end
even when it hangs; and a process it starts gets SIGTERM from the kernel if this one dies.
"""

from __future__ import annotations

import asyncio
import contextlib
import ctypes
import os
import re
import shlex
import signal
import sys
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from plcstack.cli import build_parser
from tests.ports import free_port
from tests.test_docs import _run

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
#: (page, walkthrough number on the page). Slow: OPC UA (~9 s: an asyncua server and three
#: asyncua clients, each a new interpreter) and scale-out (~3.5 s: two polls of 1 s each)
WALKTHROUGHS = [
    pytest.param("gateway.md", 0, id="gateway"),
    pytest.param("gateway.md", 1, id="gateway-e71"),
    pytest.param("north.md", 0, id="north-mqtt"),
    pytest.param("north.md", 1, id="north-sparkplug"),
    pytest.param("north.md", 2, id="north-influx"),
    pytest.param("systemd.md", 0, id="systemd"),
    pytest.param("opcua.md", 0, id="opcua", marks=pytest.mark.slow),
    pytest.param("scale-out.md", 0, id="scale-out", marks=pytest.mark.slow),
    pytest.param("wire.md", 0, id="wire"),
]
#: plcstack commands that serve something and say "listening on" when they do
SERVERS = {"sim", "gateway", "serve"}
PORT = re.compile(
    r"(?:127\.0\.0\.1:|--port[ =]|-p |port = |--metrics-port |tcp\.port==)(\d{4,5})\b"
)
#: bound for one line: a command to end, a server to come up (run() holds every line to it)
TIMEOUT = 30.0
#: bound for a whole walkthrough (pytest's timeout is 60 s: the stop must run before it)
BUDGET = 45.0
_PR_SET_PDEATHSIG = 1


def _die_with_parent() -> None:
    """In the child before exec: the kernel sends it SIGTERM when this process ends, so a test
    process killed by a timeout leaves no broker or subscriber behind."""
    ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)


@dataclass
class Step:
    command: str
    expected: list[str] = field(default_factory=list)

    @property
    def background(self) -> bool:
        return self.command.endswith("&")


def _sections(page: str) -> list[str]:
    text = (DOCS / page).read_text(encoding="utf-8")
    return [part for part in re.split(r"^## ", text, flags=re.M) if part.startswith("Walkthrough")]


def _files(page: str) -> dict[str, str]:
    """FILE -> text of every ``toml`` block of the page's walkthroughs that starts ``# FILE``."""
    files = {}
    for section in _sections(page):
        for block in re.findall(r"```toml\n(.*?)```", section, flags=re.S):
            if m := re.match(r"# ([\w.-]+)\s*\n", block):
                files[m.group(1)] = block
    return files


def _split_comment(line: str) -> tuple[str, str]:
    """``cmd 'a/#' # out`` -> ("cmd 'a/#'", "out"): a ``#`` after a blank, outside quotes."""
    quote = ""
    for i, ch in enumerate(line):
        if quote:
            quote = "" if ch == quote else quote
        elif ch in "'\"":
            quote = ch
        elif ch == "#" and (i == 0 or line[i - 1].isspace()):
            return line[:i].strip(), line[i + 1 :].strip()
    return line.strip(), ""


def _steps(section: str) -> list[Step]:
    block = section.split("```sh\n", 1)[1].split("```", 1)[0]
    steps: list[Step] = []
    for raw in block.splitlines():
        command, comment = _split_comment(raw)
        if command:
            steps.append(Step(command, [comment] if comment else []))
        elif comment:
            assert steps, f"a comment before any command: {raw}"
            steps[-1].expected.append(comment)
    return steps


def _moved_ports(texts: list[str]) -> dict[str, str]:
    """Documented port -> a free one, a different one for each (the kernel may hand out a port
    it just gave again once it is closed)."""
    moved: dict[str, str] = {}
    for port in sorted({m.group(1) for text in texts for m in PORT.finditer(text)}):
        while (free := str(free_port())) in moved.values():
            pass
        moved[port] = free
    return moved


def _moved(text: str, ports: dict[str, str]) -> str:
    return re.sub(r"\b(\d{4,5})\b", lambda m: ports.get(m.group(1), m.group(1)), text)


def _check(expected: list[str], output: str, what: str) -> None:
    """Each expected line matches a line of ``output``, in order; ``...`` is any text."""
    lines = iter(line.strip() for line in output.splitlines())
    for want in expected:
        pattern = re.compile(".*".join(re.escape(part) for part in want.split("...")))
        assert any(pattern.fullmatch(line) for line in lines), (
            f"{what}: no line {want!r} (in order) in the output:\n{output}"
        )


def _exit_code(expected: list[str]) -> tuple[int, list[str]]:
    """``# exit 1: why`` -> (1, the output lines after it); else (0, every line)."""
    if expected and (m := re.match(r"exit (\d+)", expected[0])):
        return int(m.group(1)), expected[1:]
    return 0, expected


def _text(path: Path) -> str:
    return path.read_text(errors="replace")


async def _ports_accept(ports: list[int], proc: asyncio.subprocess.Process, log: Path) -> None:
    for port in ports:
        while True:
            assert proc.returncode is None, f"ended early: {_text(log)}"
            try:
                _, writer = await asyncio.open_connection("127.0.0.1", port)
            except OSError:
                await asyncio.sleep(0.02)
                continue
            writer.close()
            await writer.wait_closed()
            break


class Walkthrough:
    """One walkthrough's run: its working directory, ports, and what it started."""

    def __init__(self, page: str, capsys: pytest.CaptureFixture[str], cwd: Path) -> None:
        self.page, self.capsys, self.cwd = page, capsys, cwd
        self.tasks: list[asyncio.Task[int]] = []
        self.procs: list[asyncio.subprocess.Process] = []
        self.logs: list[Path] = []
        self.env = dict(os.environ)
        path = [str(Path(sys.executable).parent), self.env.get("PATH", ""), "/usr/sbin", "/sbin"]
        self.env["PATH"] = os.pathsep.join(path)

    def plcstack_argv(self, command: str) -> list[str]:
        argv = shlex.split(command)
        assert argv[0] == "plcstack", command
        build_parser().parse_args(argv[1:])  # every line is valid as written
        return argv[1:]

    async def plcstack(self, step: Step, command: str) -> None:
        pipe_to = into = None
        if " | " in command:
            command, pipe_to = (part.strip() for part in command.split(" | ", 1))
        elif " > " in command:
            command, into = (part.strip() for part in command.split(" > ", 1))
        argv = self.plcstack_argv(command)
        if step.background:
            task = asyncio.create_task(_run(argv))
            self.tasks.append(task)
            if argv[0] in SERVERS:
                await self.wait_listening(task, step)
            return
        self.capsys.readouterr()  # what started before is not this command's output
        code = await _run(argv)
        shown = self.capsys.readouterr()
        if pipe_to is not None:
            assert code == 0, f"{self.page}: {command}: exit {code}: {shown.err}"
            await self.shell(step, pipe_to, shown.out.encode())
            return
        if into is not None:
            assert code == 0, f"{self.page}: {command}: exit {code}: {shown.err}"
            (self.cwd / into).write_text(shown.out)
            return
        expected_code, expected = _exit_code(step.expected)
        assert code == expected_code, f"{self.page}: {step.command}: exit {code}: {shown.err}"
        _check(expected, shown.out, f"{self.page}: {step.command}")

    async def wait_listening(self, task: asyncio.Task[int], step: Step) -> None:
        seen = ""
        while "listening on" not in seen:
            assert not task.done(), f"ended before listening: {task.result()}; {seen}"
            out, err = self.capsys.readouterr()
            seen += out + err
            await asyncio.sleep(0.02)
        _check(step.expected, seen, f"{self.page}: {step.command}")

    async def shell(self, step: Step, command: str, stdin: bytes | None = None) -> None:
        proc = await asyncio.create_subprocess_shell(
            command,
            stdin=asyncio.subprocess.PIPE if stdin is not None else asyncio.subprocess.DEVNULL,
            stdout=asyncio.subprocess.PIPE,
            stderr=asyncio.subprocess.PIPE,
            cwd=self.cwd,
            env=self.env,
            preexec_fn=_die_with_parent,
        )
        try:
            out, err = await proc.communicate(stdin)
        finally:  # also when the line's time ran out (see run)
            if proc.returncode is None:
                proc.kill()
                await proc.wait()
        expected_code, expected = _exit_code(step.expected)
        what = f"{self.page}: {step.command}"
        assert proc.returncode == expected_code, f"{what}: exit {proc.returncode}: {err.decode()}"
        _check(expected, out.decode(), what)

    async def start(self, command: str) -> None:
        """An ``&`` line that is not plcstack: started, then waited for until its ports accept."""
        argv = shlex.split(command)
        log = self.cwd / f"job{len(self.procs)}.log"
        out = log.open("wb")  # handed to the child as its stdout and stderr
        try:
            proc = await asyncio.create_subprocess_exec(
                *argv,
                stdin=asyncio.subprocess.DEVNULL,
                stdout=out,
                stderr=asyncio.subprocess.STDOUT,
                cwd=self.cwd,
                env=self.env,
                start_new_session=True,
                preexec_fn=_die_with_parent,
            )
        finally:
            out.close()
        self.procs.append(proc)
        self.logs.append(log)
        named = [command] + [
            _text(self.cwd / arg) for arg in argv[1:] if (self.cwd / arg).is_file()
        ]
        ports = sorted({int(m.group(1)) for text in named for m in PORT.finditer(text)})
        await _ports_accept(ports, proc, log)
        assert proc.returncode is None, f"{command}: ended: {_text(log)}"

    async def run(self, steps: list[Step], ports: dict[str, str]) -> None:
        for step in steps:
            command = _moved(step.command.removesuffix("&").strip(), ports)
            step.expected = [_moved(line, ports) for line in step.expected]
            try:
                async with asyncio.timeout(TIMEOUT):
                    if command.startswith("plcstack "):
                        await self.plcstack(step, command)
                    elif step.background:
                        await self.start(command)
                    else:
                        await self.shell(step, command)
            except TimeoutError:
                raise AssertionError(
                    f"{self.page}: {command}: no end within {TIMEOUT:g} s{self.background()}"
                ) from None
            self.check_background(command)

    def check_background(self, after: str) -> None:
        """Every background command still runs: one that ended, even with exit 0, took away
        what the next lines need (a server, a worker)."""
        for task in self.tasks:
            if task.done():
                ended = repr(task.exception()) if task.exception() else f"exit {task.result()}"
                raise AssertionError(f"{self.page}: after {after}: a plcstack job ended: {ended}")
        for proc, log in zip(self.procs, self.logs, strict=True):
            assert proc.returncode is None, (
                f"{self.page}: after {after}: {log.name} ended (exit {proc.returncode}): "
                f"{_text(log)}"
            )

    def background(self) -> str:
        """What the background jobs printed so far, for a failure message."""
        out, err = self.capsys.readouterr()
        logs = "".join(f"\n--- {log.name}:\n{_text(log)}" for log in self.logs)
        return f"\n--- plcstack jobs:\n{out}{err}{logs}"

    async def stop(self) -> None:
        for task in self.tasks:
            task.cancel()
        await asyncio.gather(*self.tasks, return_exceptions=True)
        for proc in self.procs:
            if proc.returncode is None:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(proc.pid, signal.SIGTERM)
                try:
                    async with asyncio.timeout(10):
                        await proc.wait()
                except TimeoutError:
                    proc.kill()
                    await proc.wait()


@pytest.mark.parametrize(("page", "number"), WALKTHROUGHS)
async def test_walkthrough_runs_as_written(
    page: str,
    number: int,
    capsys: pytest.CaptureFixture[str],
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    section = _sections(page)[number]
    steps = _steps(section)
    files = _files(page)
    ports = _moved_ports([step.command for step in steps] + list(files.values()))
    for name, text in files.items():
        (tmp_path / name).write_text(_moved(text, ports), encoding="utf-8")
    (tmp_path / "examples").symlink_to(ROOT / "examples")
    monkeypatch.chdir(tmp_path)  # plcstack's relative paths, as the shell lines' are
    walk = Walkthrough(page, capsys, tmp_path)
    try:
        async with asyncio.timeout(BUDGET):
            await walk.run(steps, ports)
    except TimeoutError:
        raise AssertionError(f"{page}: not done within {BUDGET:g} s{walk.background()}") from None
    finally:
        await walk.stop()


def test_every_walkthrough_of_the_docs_is_run() -> None:
    """A page that gains a walkthrough gains its test here."""
    run = {(p.values[0], p.values[1]) for p in WALKTHROUGHS}
    found = {
        (page.name, number)
        for page in sorted(DOCS.glob("*.md"))
        for number in range(len(_sections(page.name)))
    }
    assert found == run
