"""scripts/setup-test-machine: the set-up of the README's test command and of .ci/run.

The script is run for real, by bash, on a PATH that holds only what each case allows: stand-ins
for ``dpkg-query`` (what is installed), ``apt-get`` (records its arguments and "installs" by
writing the state file the stand-in ``dpkg-query`` reads), ``id`` (who we are) and ``sudo``.
So each branch (nothing missing, everything missing as root, as a user with and without sudo,
a package apt-get did not install, a machine without apt) is taken without touching this
machine's packages. Whether this machine itself has what the suite needs is the last test.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "setup-test-machine"
BASH = shutil.which("bash") or "/bin/bash"

#: the real tools the script itself uses (python3: the interpreter this venv was made from)
TOOLS = ("env", "sed", "cat", "grep")


def listed() -> list[str]:
    out = subprocess.run([BASH, str(SCRIPT), "--list"], capture_output=True, text=True, check=True)
    return out.stdout.split()


class Machine:
    """A PATH of stand-ins: which packages dpkg reports, who ``id`` says we are."""

    def __init__(self, tmp: Path, *, installed: set[str], uid: int = 0) -> None:
        self.bin = tmp / "bin"
        self.bin.mkdir()
        self.state = tmp / "installed"
        self.state.write_text("".join(f"{p}\n" for p in sorted(installed)))
        self.calls = tmp / "calls"
        self.calls.touch()
        for tool in TOOLS:
            found = shutil.which(tool)
            assert found is not None, tool
            (self.bin / tool).symlink_to(found)
        (self.bin / "python3").symlink_to(Path(sys.executable).resolve())
        self.tool(
            "dpkg-query",
            # dpkg-query -W -f=FORMAT PACKAGE
            f'grep -qx "$3" {self.state} && printf installed && exit 0\n'
            'echo "dpkg-query: no packages found matching $3" >&2; exit 1',
        )
        self.tool("apt-get", f'echo "apt-get $*" >> {self.calls}')
        self.tool("id", f"echo {uid}")

    def tool(self, name: str, body: str) -> None:
        path = self.bin / name
        path.write_text(f"#!{BASH}\n{body}\n")
        path.chmod(0o755)

    def apt_installs(self, *, except_: str = "") -> None:
        """apt-get install adds its packages to the state (all but ``except_``)."""
        self.tool(
            "apt-get",
            f'echo "apt-get $*" >> {self.calls}\n'
            'if [ "$1" = install ]; then for p in "$@"; do case "$p" in -*|install) ;;'
            f' {except_ or "-"}) ;; *) echo "$p" >> {self.state};; esac; done; fi',
        )

    def run(self, *args: str) -> subprocess.CompletedProcess[str]:
        env = {"PATH": str(self.bin), "HOME": str(self.bin.parent)}
        return subprocess.run(
            [BASH, str(SCRIPT), *args], capture_output=True, text=True, env=env, timeout=30
        )

    def apt_calls(self) -> list[str]:
        return self.calls.read_text().splitlines()


def test_nothing_missing_installs_nothing(tmp_path: Path) -> None:
    machine = Machine(tmp_path, installed=set(listed()))
    done = machine.run()
    assert done.returncode == 0, done.stderr
    assert (
        done.stdout
        == f"setup-test-machine: the {len(listed())} packages the tests need are installed\n"
    )
    assert machine.apt_calls() == []


def test_as_root_everything_missing_is_installed_without_sudo(tmp_path: Path) -> None:
    machine = Machine(tmp_path, installed=set())
    machine.apt_installs()
    done = machine.run()
    assert done.returncode == 0, done.stderr
    packages = " ".join(listed())
    assert machine.apt_calls() == [
        "apt-get update -qq",
        f"apt-get install -y -qq --no-install-recommends {packages}",
    ]
    assert done.stdout.splitlines()[-1] == f"setup-test-machine: installed {packages}"


def test_a_user_installs_through_sudo(tmp_path: Path) -> None:
    machine = Machine(tmp_path, installed=set(listed()) - {"influxdb", "tshark"}, uid=1000)
    machine.tool("sudo", f'echo "sudo $*" >> {machine.calls}; exec "$@"')
    machine.apt_installs()
    done = machine.run()
    assert done.returncode == 0, done.stderr
    assert machine.apt_calls() == [
        "sudo env DEBIAN_FRONTEND=noninteractive apt-get update -qq",
        "apt-get update -qq",
        "sudo env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends"
        " influxdb tshark",
        "apt-get install -y -qq --no-install-recommends influxdb tshark",
    ]


def test_dry_run_says_the_commands_and_runs_none(tmp_path: Path) -> None:
    machine = Machine(tmp_path, installed=set(listed()) - {"chromium"}, uid=1000)
    machine.tool("sudo", f'echo "sudo $*" >> {machine.calls}')
    done = machine.run("--dry-run")
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines() == [
        "setup-test-machine: installing chromium",
        "sudo env DEBIAN_FRONTEND=noninteractive apt-get update -qq",
        "sudo env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends"
        " chromium",
    ]
    assert machine.apt_calls() == []


def test_a_user_without_sudo_is_told_to_run_it_as_root(tmp_path: Path) -> None:
    machine = Machine(tmp_path, installed=set(listed()) - {"mosquitto"}, uid=1000)
    done = machine.run()
    assert done.returncode == 1
    assert "missing mosquitto" in done.stderr and "run this script as root" in done.stderr
    assert machine.apt_calls() == []


def test_a_package_apt_did_not_install_fails_the_set_up(tmp_path: Path) -> None:
    machine = Machine(tmp_path, installed=set(listed()) - {"mbpoll", "curl"})
    machine.apt_installs(except_="mbpoll")
    done = machine.run()
    assert done.returncode == 1
    assert done.stderr.strip() == "setup-test-machine: apt-get ended without installing mbpoll"


def test_a_machine_without_apt_is_told_what_to_install(tmp_path: Path) -> None:
    machine = Machine(tmp_path, installed=set())
    (machine.bin / "apt-get").unlink()
    done = machine.run()
    assert done.returncode == 1
    assert "not a Debian-based machine" in done.stderr
    assert " ".join(listed()) in done.stderr


def test_python_without_ensurepip_gets_python3_venv(tmp_path: Path) -> None:
    machine = Machine(tmp_path, installed=set(listed()))
    (machine.bin / "python3").unlink()
    machine.tool("python3", "exit 1")  # Debian's python3 before python3-venv: no ensurepip
    done = machine.run("--dry-run")
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines()[0] == "setup-test-machine: installing python3-venv"


def test_an_unknown_argument_is_refused(tmp_path: Path) -> None:
    done = Machine(tmp_path, installed=set()).run("--dryrun")
    assert done.returncode == 1
    assert "unknown argument --dryrun" in done.stderr


def test_readme_ci_and_script_agree() -> None:
    """The README's second command starts with the set-up and names what it installs; .ci/run
    runs the same script and the same test command."""
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    block = re.search(r"```sh\n(.*?)```", readme, re.DOTALL)
    assert block is not None
    commands = [line for line in block.group(1).splitlines() if line and line[0] != "#"]
    assert len(commands) == 2, commands
    setup, *rest = commands[1].split(" && ")
    assert setup == "scripts/setup-test-machine"
    assert rest[-1] == ".venv/bin/python -m pytest"
    said = readme[block.end() : readme.index("\n\n", block.end() + 2)]
    named = re.findall(r"`([a-z0-9.-]+)`", said.split("(and")[0])
    assert named == listed()
    ci = (ROOT / ".ci" / "run").read_text(encoding="utf-8").splitlines()
    assert "scripts/setup-test-machine" in ci
    assert rest[-1] in ci
    assert ci.index("scripts/setup-test-machine") < ci.index(rest[-1])


def test_this_machine_has_what_the_suite_needs() -> None:
    """The suite's own machine went through the set-up: nothing is missing."""
    done = subprocess.run(
        [BASH, str(SCRIPT), "--dry-run"], capture_output=True, text=True, timeout=30
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith("setup-test-machine: the "), done.stdout
