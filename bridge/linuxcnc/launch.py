"""Start the HAL plant and headless LinuxCNC of this package, for tests, benchmarks and demos.

HAL's ``rtapi_app`` refuses to run as root: when this process is root, HAL and its tools run as
:func:`hal_user` (``FEEDMON_HAL_USER``, default ``lcnc``) through ``runuser``, in a work directory
that user owns (:func:`workdir`, in its home: a root-only temporary directory would be out of its
reach). One HAL (one realtime session) runs per machine at a time.
"""

from __future__ import annotations

import os
import pwd
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import tomllib
from pathlib import Path

from feedio import schema as S
from kernels.feed_drive import beta_names, physical_to_beta

__all__ = ["HAL_DIR", "SIM_DIR", "INSTALL_HINT", "plant_truth", "plant_meta", "hal_user", "as_hal_user", "linuxcnc_missing", "workdir",
           "halcmd", "counting", "give", "HalPlant", "LinuxCNC", "Rsh", "wait_for", "Proc",
           "bridge_config", "start_bridge"]

HAL_DIR = Path(__file__).with_name("hal")
SIM_DIR = Path(__file__).with_name("sim")
INSTALL_HINT = ("install LinuxCNC: apt-get install -y --no-install-recommends linuxcnc-uspace (Debian 12), and, when "
                "running as root, create the user HAL runs as: useradd -m lcnc (or set FEEDMON_HAL_USER)")


def plant_truth() -> dict:
    """The HAL plant's known truth (``hal/truth.toml``): mass (kg), damping (N·s/m), coulomb (N), omega (m/s),
    loop_gain (N·s/m), and each plant file's servo period (``rates``)."""
    return tomllib.loads((HAL_DIR / "truth.toml").read_text(encoding="utf-8"))


def plant_meta(Ts: float, machine: str = "plant", axis: str = "X") -> S.TrialMeta:
    """Trial metadata of the plant sampled every ``Ts`` s with its true β (force-input form, the exact ZOH
    discretisation the plant integrates): ``monitor.model_file.truth_model`` makes its model from it."""
    tr = plant_truth()
    beta = physical_to_beta("force-input", Ts, tr["mass"], tr["damping"], coulomb_pos=tr["coulomb"],
                            coulomb_neg=tr["coulomb"])
    physical = {"inertia": tr["mass"], "damping": tr["damping"], "coulomb_pos": tr["coulomb"],
                "coulomb_neg": tr["coulomb"], "loop_gain": tr["loop_gain"]}
    return S.TrialMeta(Ts=Ts, form="force-input", machine=machine, axis=axis,
                       provenance=S.Provenance(source="linuxcnc", tool="HAL plant", version="1"),
                       truth=S.TrialTruth(beta=beta.tolist(), omega=tr["omega"], coulomb=True, physical=physical,
                                          beta_names=list(beta_names("force-input"))))


def hal_user() -> str | None:
    """The user HAL runs as when this process is root (None: run as this process' user)."""
    return os.environ.get("FEEDMON_HAL_USER", "lcnc") if os.geteuid() == 0 else None


def as_hal_user(cmd: list[str]) -> list[str]:
    user = hal_user()
    return cmd if user is None else ["runuser", "-u", user, "--", *cmd]


def linuxcnc_missing(python: str = "/usr/bin/python3") -> str | None:
    """Why LinuxCNC cannot run here (None: it can), with how to install it."""
    for tool in ("halrun", "halcmd", "halsampler", "halstreamer", "linuxcnc", "linuxcncrsh"):
        if shutil.which(tool) is None:
            return f"{tool} not found: {INSTALL_HINT}"
    if subprocess.run([python, "-c", "import hal"], capture_output=True).returncode != 0:
        return f"{python} cannot import LinuxCNC's hal module: {INSTALL_HINT}"
    user = hal_user()
    if user is not None:
        try:
            pwd.getpwnam(user)
        except KeyError:
            return (f"HAL refuses root and the user {user!r} it would run as does not exist: create it (useradd -m "
                    f"{user}) or set FEEDMON_HAL_USER to an existing user")
    return None


def workdir(prefix: str = "feedmon-hal-") -> Path:
    """A fresh directory the HAL user owns (remove it with ``shutil.rmtree``)."""
    user = hal_user()
    if user is None:
        return Path(tempfile.mkdtemp(prefix=prefix))
    pw = pwd.getpwnam(user)
    path = Path(tempfile.mkdtemp(prefix=prefix, dir=pw.pw_dir))
    os.chown(path, pw.pw_uid, pw.pw_gid)
    return path


def give(path: Path) -> Path:
    """Hand ``path`` (a file written by this process) to the HAL user."""
    user = hal_user()
    if user is not None:
        pw = pwd.getpwnam(user)
        os.chown(path, pw.pw_uid, pw.pw_gid)
    return path


def halcmd(*args: str, check: bool = True) -> str:
    """``halcmd -s ARGS`` as the HAL user (``halcmd`` run before HAL is up would create an empty HAL of its
    own — owned by root, it would lock the HAL user's next session out)."""
    res = subprocess.run(as_hal_user(["halcmd", "-s", *args]), capture_output=True, text=True, timeout=30)
    if check and res.returncode != 0:
        raise RuntimeError(f"halcmd {' '.join(args)}: {res.stderr.strip() or res.stdout.strip()}")
    return res.stdout


def wait_for(condition, timeout: float, what: str, interval: float = 0.05):
    """``condition()``'s first truthy value within ``timeout`` s, else ``TimeoutError`` naming ``what``."""
    deadline = time.monotonic() + timeout
    while True:
        value = condition()
        if value:
            return value
        if time.monotonic() > deadline:
            raise TimeoutError(f"{what}: not within {timeout:g} s")
        time.sleep(interval)


def counting() -> int:
    """The servo-cycle counter ``threadtest.0.count`` of a running plant (0: HAL not up or not started)."""
    if _no_hal():
        return 0
    text = halcmd("getp", "threadtest.0.count", check=False).strip()
    return int(text) if text.isdigit() else 0


def _no_hal() -> bool:
    with open("/proc/sysvipc/shm") as f:
        return not any(line.split()[0] == str(0x48414C32) for line in f.readlines()[1:] if line.split())


class HalPlant:
    """``halrun -I -f FILE`` kept up by an open stdin; :meth:`stop` closes it (halrun tears HAL down).
    ``files``: further files to copy next to it (force files for ``halstreamer``)."""

    def __init__(self, hal_file: Path, work: Path, *, timeout: float = 60.0) -> None:
        self.work = work
        self.file = work / hal_file.name
        if hal_file.resolve() != self.file.resolve():
            shutil.copy(hal_file, self.file)
        give(self.file)
        wait_for(_no_hal, timeout, "an earlier HAL session to end")
        self.log = open(work / f"{self.file.stem}.halrun.log", "w")
        self.proc = subprocess.Popen(as_hal_user(["halrun", "-I", "-f", str(self.file)]), cwd=work,
                                     stdin=subprocess.PIPE, stdout=self.log, stderr=subprocess.STDOUT)
        self.children: list[subprocess.Popen] = []
        try:
            wait_for(lambda: self.proc.poll() is not None or counting() > 0, timeout, "HAL to start")
            if self.proc.poll() is not None:
                raise RuntimeError(f"halrun ended at once: {(work / self.log.name).read_text()[-2000:]}")
        except BaseException:
            self.stop()
            raise

    def streamer(self, values_file: Path, channel: int = 0) -> subprocess.Popen:
        """``halstreamer -c CHANNEL FILE``: feeds ``streamer.CHANNEL`` until the file ends."""
        path = self.work / values_file.name
        if values_file.resolve() != path.resolve():
            shutil.copy(values_file, path)
        give(path)
        proc = subprocess.Popen(as_hal_user(["halstreamer", "-c", str(channel), str(path)]), cwd=self.work,
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        self.children.append(proc)
        return proc

    def sampler(self, out: Path, channel: int) -> subprocess.Popen:
        """``halsampler -c CHANNEL -t`` writing ``out`` (a file in the work directory)."""
        proc = subprocess.Popen(as_hal_user(["halsampler", "-c", str(channel), "-t", str(out)]), cwd=self.work,
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        self.children.append(proc)
        return proc

    def stop(self, timeout: float = 60.0) -> None:
        for child in self.children:
            if child.poll() is None:
                child.terminate()
        for child in self.children:
            try:
                child.wait(timeout)
            except subprocess.TimeoutExpired:
                child.kill()
        try:
            self.proc.stdin.close()
        except OSError:
            pass
        try:
            self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            subprocess.run(as_hal_user(["halrun", "-U"]), capture_output=True, timeout=60)
        self.log.close()

    def __enter__(self) -> HalPlant:
        return self

    def __exit__(self, *exc) -> None:
        self.stop()


class Rsh:
    """A ``linuxcncrsh`` client (LinuxCNC's telnet-like interface, port 5007)."""

    def __init__(self, port: int = 5007, timeout: float = 30.0) -> None:
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=timeout)
        self.file = self.sock.makefile("rw")
        self.ask("hello EMC feedmon 1.0")
        self.ask("set enable EMCTOO")  # echoed (echo is on until the next line)
        self.ask("set echo off")
        self.ask("set verbose on")  # from now on every set command is answered ACK or NAK

    def ask(self, line: str) -> str:
        self.file.write(line + "\r\n")
        self.file.flush()
        reply = self.file.readline().strip()
        if "NAK" in reply:
            raise RuntimeError(f"linuxcncrsh refused {line!r}: {reply}")
        return reply

    def run_program(self, path: Path) -> None:
        """Estop off, machine on, home every joint in place, run ``path`` in auto mode."""
        for line in ("set estop off", "set machine on", "set mode manual", "set home 0",
                     "set home 1", "set home 2", "set mode auto", f"set open {path}", "set run"):
            self.ask(line)

    def close(self) -> None:
        self.sock.close()


class LinuxCNC:
    """``linuxcnc feedmon-sim.ini`` (headless, linuxcncrsh) in ``work``; :meth:`stop` shuts it down."""

    def __init__(self, work: Path, ini: str = "feedmon-sim.ini", *, timeout: float = 90.0) -> None:
        for f in SIM_DIR.iterdir():
            if f.is_file() and f.suffix in (".ini", ".hal", ".ngc", ".tbl"):
                give(Path(shutil.copy(f, work)))
        wait_for(_no_hal, timeout, "an earlier HAL session to end")
        self.work = work
        self.log = open(work / "linuxcnc.log", "a")
        env = {k: v for k, v in os.environ.items() if k != "DISPLAY"}  # headless: never ask through a window
        self.proc = subprocess.Popen(as_hal_user(["linuxcnc", ini]), cwd=work, stdin=subprocess.DEVNULL,
                                     stdout=self.log, stderr=subprocess.STDOUT, start_new_session=True, env=env)
        try:
            self.rsh = wait_for(self._connect, timeout, "linuxcncrsh to answer on port 5007", interval=0.5)
        except BaseException:
            self.stop()
            raise

    def _connect(self) -> Rsh | None:
        if self.proc.poll() is not None:
            raise RuntimeError(f"linuxcnc ended at once: {(self.work / 'linuxcnc.log').read_text()[-3000:]}")
        try:
            return Rsh()
        except OSError:
            return None

    def stop(self, timeout: float = 60.0) -> int | None:
        """Shut LinuxCNC down (``shutdown`` through linuxcncrsh, then signals); its exit code."""
        rsh = getattr(self, "rsh", None)
        if rsh is not None:
            try:
                rsh.file.write("shutdown\r\n")
                rsh.file.flush()
            except OSError:
                pass
            rsh.close()
            self.rsh = None
        try:
            return self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            os.killpg(self.proc.pid, 15)
            try:
                return self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, 9)
                return self.proc.wait(timeout)
        finally:
            self.log.close()
            wait_for(_no_hal, timeout, "HAL to end after LinuxCNC")


class Proc:
    """A ``feedmon`` sub-command as a subprocess (this interpreter), its stderr collected by a thread."""

    def __init__(self, args: list[str], cwd: Path) -> None:
        self.proc = subprocess.Popen([sys.executable, "-m", "feedmon.cli", *args], cwd=cwd, stdout=subprocess.PIPE,
                                     stderr=subprocess.PIPE, text=True)
        self.lines: list[str] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        for line in self.proc.stderr:
            self.lines.append(line)

    @property
    def stderr(self) -> str:
        return "".join(self.lines)

    def count(self, text: str) -> int:
        return sum(text in line for line in list(self.lines))

    def wait_line(self, pattern: str, timeout: float, n: int = 1) -> re.Match:
        """The ``n``-th stderr line matching ``pattern`` (a regex), waiting up to ``timeout`` s."""
        def found():
            hits = [m for m in (re.search(pattern, line) for line in list(self.lines)) if m]
            if len(hits) < n and self.proc.poll() is not None:
                self._reader.join(5)
                raise RuntimeError(f"process ended ({self.proc.returncode}) before {pattern!r}:\n{self.stderr}")
            return hits[n - 1] if len(hits) >= n else None
        try:
            return wait_for(found, timeout, f"a line {pattern!r}")
        except TimeoutError as exc:
            raise TimeoutError(f"{exc}; stderr so far:\n{self.stderr[-3000:]}") from None

    def wait(self, timeout: float) -> int:
        rc = self.proc.wait(timeout)
        self._reader.join(5)
        return rc

    def stop(self, timeout: float = 60.0) -> int:
        """SIGTERM and wait; the exit code."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        try:
            return self.wait(timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.wait(10)
            raise RuntimeError(f"process did not stop within {timeout:g} s:\n{self.stderr[-3000:]}") from None


def bridge_config(src: Path, work: Path, extra: str = "") -> Path:
    """``src`` (a bridge config) written into ``work`` with ``extra`` appended and, when this process is
    root, ``[hal] user`` set to :func:`hal_user`."""
    text = src.read_text(encoding="utf-8") + "\n" + extra
    user = hal_user()
    if user is not None:
        text += f'\n[hal]\nuser = "{user}"\n'
    path = work / src.name
    path.write_text(text, encoding="utf-8")
    return path


def start_bridge(config: Path, work: Path, *args: str, timeout: float = 60.0) -> Proc:
    """``feedmon bridge linuxcnc --config CONFIG ARGS``, once attached to HAL."""
    proc = Proc(["bridge", "linuxcnc", "--config", str(config), *args], work)
    proc.wait_line(r"attached to sampler", timeout)
    return proc
