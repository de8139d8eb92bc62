#!/usr/bin/env python3
"""Run the socketcan tests (or any command) inside a User-Mode Linux guest that has a kernel CAN bus.

This machine's kernel has no AF_CAN; Debian's `user-mode-linux` package is a Linux 6.1 kernel that
runs as an ordinary process and has the `can`, `can-raw`, `can-dev`, `vcan` and `slcan` modules. The
guest boots with the host's `/` as its root (hostfs), so it sees this checkout and this Python
unchanged; its init (written here) mounts proc/sys/devpts, loads the CAN modules, runs one command
with its output in a file and powers off. The `linux` process then exits non-zero by design ("Attempted
to kill init"), so the run is judged by the files the guest wrote, never by that exit code.

    python3 tools/vcan_guest.py                  # the socketcan tests: fails if any fails or is skipped
    python3 tools/vcan_guest.py -- python3 tools/socketcan_speed.py --time-scale 10   # any command

Inside the guest a test makes its own vcan (`ip link add dev vcan-<name> type vcan`; see
tests/socketcan_bus.py) and runs `slcand` (can-utils) itself. Needs: `apt-get install
user-mode-linux kmod can-utils` (docs/can-on-linux.md). Prints the guest's wall time.
"""

from __future__ import annotations

import argparse
import os
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import xml.etree.ElementTree as ET
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
SOCKETCAN_MARK = "mark.socketcan"
"""How a test file marks socketcan tests (`@pytest.mark.socketcan`, `pytestmark = [...socketcan]`)."""
MODULES = ("drivers/net/can/dev/can-dev.ko", "net/can/can.ko", "net/can/can-raw.ko",
           "drivers/net/can/vcan.ko", "drivers/net/can/slcan/slcan.ko")
GUEST_PATH = "/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin"
BOOT_MARGIN_S = 60.0  # boot, module loading and power-off on a loaded host, on top of the command's timeout


def uml_modules_dir() -> Path | None:
    """/usr/lib/uml/modules/<version>/kernel of the installed UML kernel (None: not installed)."""
    base = Path("/usr/lib/uml/modules")
    versions = sorted(base.iterdir()) if base.is_dir() else []
    return versions[-1] / "kernel" if versions else None


def init_script(out: Path, command: list[str], timeout_s: float, modules: Path, cwd: Path = REPO) -> str:
    """The guest's /sbin/init: a shell script (kernel words with spaces do not reach init intact)."""
    env = {"PATH": f"{Path(sys.executable).parent}:{GUEST_PATH}", "HOME": str(out), "LANG": "C.UTF-8",
           "PYTHONDONTWRITEBYTECODE": "1", "NORTHFINDER_VCAN_GUEST": "1", "TMPDIR": str(out / "tmp")}
    exports = "\n".join(f"export {k}={shlex.quote(v)}" for k, v in env.items())
    inserts = "\n".join(f"insmod {modules / m} >>{out}/boot.log 2>&1" for m in MODULES)
    return f"""#!/bin/sh
{exports}
mount -t proc proc /proc; mount -t sysfs sys /sys
mkdir -p /dev/pts /dev/shm; mount -t devpts -o ptmxmode=0666 devpts /dev/pts; mount -t tmpfs tmpfs /dev/shm
[ -e /dev/ptmx ] || ln -s /dev/pts/ptmx /dev/ptmx
ip link set lo up
{inserts}
mkdir -p "$TMPDIR"
echo booted >{out}/booted
cd {shlex.quote(str(cwd))}
start=$(date +%s.%N)
timeout -k 5 {int(timeout_s)} {shlex.join(command)} </dev/null >{out}/command.log 2>&1
echo $? >{out}/rc
echo "$start $(date +%s.%N)" >{out}/times
sync
echo o >/proc/sysrq-trigger
sleep 30
"""


def run_in_guest(command: list[str], out: Path, timeout_s: float, mem: str, cwd: Path = REPO) -> dict:
    """Boot the guest, run `command` in it; its rc, output and times as the guest wrote them."""
    modules = uml_modules_dir()
    if shutil.which("linux") is None or modules is None:
        raise SystemExit("vcan_guest: no User-Mode Linux kernel here — apt-get install user-mode-linux kmod "
                         "can-utils")
    out.mkdir(parents=True, exist_ok=True)
    for stale in ("rc", "times", "booted", "command.log", "junit.xml"):  # a reused --out: judge this run only
        (out / stale).unlink(missing_ok=True)
    init = out / "init.sh"
    init.write_text(init_script(out, command, timeout_s, modules, cwd))
    init.chmod(0o755)
    t0 = time.monotonic()
    with open(out / "kernel.log", "wb") as klog:
        # its own process group: UML runs as several host processes, all ended together on a timeout
        guest = subprocess.Popen(["linux", f"mem={mem}", "rootfstype=hostfs", "rw", f"init={init}",
                                  "con=null", "con0=null", "quiet"], stdin=subprocess.DEVNULL, stdout=klog,
                                 stderr=subprocess.STDOUT, process_group=0,
                                 env={"PATH": os.environ.get("PATH", GUEST_PATH), "TMPDIR": "/tmp",
                                      "HOME": str(out)})  # UML keeps its pid file under $HOME/.uml
        try:
            guest.wait(timeout=timeout_s + BOOT_MARGIN_S)
        except subprocess.TimeoutExpired:
            pass  # judged below: no rc file
        finally:  # a timeout, or this script ended (SIGTERM from .ci/run, Ctrl-C): the guest goes too
            if guest.poll() is None:
                os.killpg(guest.pid, signal.SIGKILL)
                guest.wait()
    wall_s = time.monotonic() - t0
    rc_file, times = out / "rc", out / "times"
    rc = int(rc_file.read_text()) if rc_file.exists() else None
    command_s = None
    if times.exists():
        t_start, t_end = (float(v) for v in times.read_text().split())
        command_s = t_end - t_start
    log = (out / "command.log").read_text(errors="replace") if (out / "command.log").exists() else ""
    return {"rc": rc, "wall_s": wall_s, "command_s": command_s, "log": log,
            "booted": (out / "booted").exists()}


def socketcan_test_files(tests: Path = REPO / "tests") -> list[Path]:
    """The test files that mark socketcan tests: the guest collects only these (collecting the whole
    suite took 12 s of the guest's slow Python, these four 1–4 s). A host test
    (tests/test_vcan_guest.py) checks that every socketcan-marked test the suite collects is in one."""
    return sorted(f for f in tests.glob("test_*.py") if SOCKETCAN_MARK in f.read_text(encoding="utf-8"))


def pytest_command(junit: Path) -> list[str]:
    """pytest in the guest: the socketcan tests of those files, serially (the guest has one CPU), none
    of the suite's addopts (xdist's four workers), no plugin it does not need (xdist, the cache,
    hypothesis's, benchmark: ~2 s of start-up in the guest); the ini file's timeout still holds."""
    files = [str(f.relative_to(REPO)) for f in socketcan_test_files()]
    return [sys.executable, "-m", "pytest", "-o", "addopts=", "-p", "no:xdist", "-p", "no:cacheprovider",
            "-p", "no:hypothesispytest", "-p", "no:benchmark", "-m", "socketcan", "-rA", "--durations=0",
            f"--junitxml={junit}", *files]


def junit_counts(path: Path) -> dict[str, int]:
    """tests / failures / errors / skipped from pytest's JUnit XML."""
    root = ET.parse(path).getroot()
    suites = [root] if root.tag == "testsuite" else list(root)
    return {k: sum(int(s.get(k, 0)) for s in suites) for k in ("tests", "failures", "errors", "skipped")}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--timeout", type=float, default=600.0, metavar="S", help="the command's timeout (600)")
    p.add_argument("--mem", default="1G", help="guest memory (1G)")
    p.add_argument("--out", metavar="DIR", help="where the guest writes (default: a fresh temporary dir)")
    p.add_argument("command", nargs="*",
                   help="run this (after --, in the current directory) instead of the socketcan tests")
    args = p.parse_args(argv)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # through run_in_guest's cleanup
    out = Path(args.out or tempfile.mkdtemp(prefix="vcan-guest-")).resolve()
    junit = out / "junit.xml"
    tests = not args.command
    command = args.command or pytest_command(junit)
    got = run_in_guest(command, out, args.timeout, args.mem, Path.cwd() if args.command else REPO)
    print(got["log"], end="")
    timing = (f"guest wall {got['wall_s']:.1f} s (command {got['command_s']:.1f} s)" if got["command_s"]
              else f"guest wall {got['wall_s']:.1f} s")
    if got["rc"] is None:
        why = "did not boot" if not got["booted"] else "did not finish"
        print(f"vcan_guest: the guest {why} — see {out}/kernel.log, {out}/boot.log; {timing}",
              file=sys.stderr)
        return 1
    if not tests:
        print(f"vcan_guest: command exit {got['rc']}; {timing}", file=sys.stderr)
        return got["rc"]
    if not junit.exists():
        print(f"vcan_guest: pytest wrote no report (exit {got['rc']}); {timing}", file=sys.stderr)
        return 1
    n = junit_counts(junit)
    passed = n["tests"] - n["failures"] - n["errors"] - n["skipped"]
    print(f"vcan_guest: socketcan tests in the guest: {n['tests']} executed, {passed} passed, "
          f"{n['failures'] + n['errors']} failed, {n['skipped']} skipped; {timing}")
    ok = got["rc"] == 0 and n["tests"] > 0 and passed == n["tests"]
    if not ok:
        print("vcan_guest: FAILED — every socketcan test must run and pass in the guest (none skipped)",
              file=sys.stderr)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
