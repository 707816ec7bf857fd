"""Deployment files: Dockerfile, deploy/feedmon.service, deploy/monitor.toml.

No Docker engine runs here, so the image is not built; instead the Dockerfile is parsed and what
it does is done for real:

* the build context is assembled from its COPY lines (honouring .dockerignore), its ``pip
  install .`` runs in a **fresh virtual environment**, then its other RUN step (the Numba
  warm-up), ``feedmon run --help``, ``feedmon status --help`` and the HEALTHCHECK command run
  from that environment's entry point;
* the ENTRYPOINT + ``--config`` (deploy/monitor.toml with its paths pointed at a model, state and
  log directory made here) starts a real monitor from the fresh install; the HEALTHCHECK command
  exits 0 while it runs and non-zero when no monitor answers; SIGTERM stops it with exit 0, an
  MCAP log and a saved tracker state.

Fresh install with or without dependencies: ``pip install .`` with all dependencies from the
index into a new environment took 4 min 42 s here (rerun-sdk alone is 170 MB, pyarrow 55 MB),
about as long as the rest of the suite, and CI has just done the same install for the
suite itself. So by default the fresh environment gets ``pip install --no-deps .`` — which still
builds the wheel from exactly the files the Dockerfile copies (pyproject, packages, package data,
the ``feedmon`` console script) — and sees the already installed dependencies through a ``.pth``
line (site-packages of the running interpreter; the editable install of the repository is *not*
picked up, which the test asserts: ``monitor`` is imported from the fresh environment).
``FEEDMON_DEPLOY_FULL_INSTALL=1`` runs the Dockerfile's command unchanged (with dependencies).
"""

from __future__ import annotations

import fnmatch
import json
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import sysconfig
import threading
import time
import tomllib
from pathlib import Path

import pytest

from feedio import transport as T
from feedmon.cli import build_parser
from feedmon.run_config import run_config_from_args
from monitor.model_file import AxisModel, TrackerConfig, save_model

ROOT = Path(__file__).resolve().parents[1]
DOCKERFILE = ROOT / "Dockerfile"
UNIT = ROOT / "deploy" / "feedmon.service"
CONFIG = ROOT / "deploy" / "monitor.toml"
FULL_INSTALL = os.environ.get("FEEDMON_DEPLOY_FULL_INSTALL") == "1"


# ---- Dockerfile parsing ---------------------------------------------------------------------
def dockerfile() -> list[tuple[str, str]]:
    """``[(INSTRUCTION, arguments)]`` with line continuations joined and comments dropped."""
    out: list[tuple[str, str]] = []
    buf = ""
    for raw in DOCKERFILE.read_text(encoding="utf-8").splitlines():
        line = raw.strip()
        if not buf and (not line or line.startswith("#")):
            continue
        if buf and line.startswith("#"):
            continue
        if line.endswith("\\"):
            buf += line[:-1] + " "
            continue
        buf += line
        instr, _, args = buf.strip().partition(" ")
        out.append((instr.upper(), args.strip()))
        buf = ""
    assert not buf, "Dockerfile ends inside a continued line"
    return out


def instr(name: str) -> list[str]:
    return [a for i, a in dockerfile() if i == name]


def exec_form(args: str) -> list[str]:
    value = json.loads(args)
    assert isinstance(value, list) and all(isinstance(x, str) for x in value), args
    return value


def healthcheck() -> tuple[dict[str, str], list[str]]:
    (hc,) = instr("HEALTHCHECK")
    opts_part, _, cmd = hc.partition("CMD")
    opts = dict(o[2:].split("=", 1) for o in opts_part.split())
    return opts, exec_form(cmd.strip())


def seconds(duration: str) -> float:
    m = re.fullmatch(r"(\d+(?:\.\d+)?)(ms|s|m|h)", duration)
    assert m, f"bad duration {duration!r}"
    return float(m[1]) * {"ms": 1e-3, "s": 1.0, "m": 60.0, "h": 3600.0}[m[2]]


def run_steps() -> list[str]:
    """The shell commands of the RUN lines, split at ``&&``."""
    steps = []
    for r in instr("RUN"):
        steps += [s.strip() for s in r.split("&&")]
    return steps


# ---- the Dockerfile itself ------------------------------------------------------------------
def test_dockerfile_structure():
    parsed = dockerfile()
    names = [i for i, _ in parsed]
    (base,) = instr("FROM")
    assert re.fullmatch(r"python:3\.11-slim(-\w+)?", base), base
    # non-root before anything runs in the container
    users = instr("USER")
    assert users and users[-1] not in ("root", "0")
    assert names.index("USER") < names.index("ENTRYPOINT")
    assert any(re.search(r"\buseradd\b.*\bfeedmon\b", s) for s in run_steps())
    assert "pip install ." in run_steps()
    assert exec_form(instr("ENTRYPOINT")[0]) == ["feedmon", "run"]
    # CMD is valid for `feedmon run` (real parser), and listens on the exposed port
    cmd = exec_form(instr("CMD")[0])
    args = build_parser().parse_args(["run", *cmd])
    assert args.config == "/etc/feedmon/monitor.toml"
    (listen,) = args.listen
    port = int(listen.rsplit(":", 1)[1])
    exposed = {int(p.split("/")[0]) for e in instr("EXPOSE") for p in e.split()}
    assert port == T.DEFAULT_PORT and port in exposed
    # the shipped config lands where CMD reads it
    assert any(c.split() == ["deploy/monitor.toml", "/etc/feedmon/monitor.toml"] for c in instr("COPY"))
    volumes = exec_form(instr("VOLUME")[0])
    assert {"/var/lib/feedmon", "/var/log/feedmon"} <= set(volumes)
    assert instr("STOPSIGNAL") == ["SIGTERM"]


def test_healthcheck_asks_the_status_queryable():
    opts, cmd = healthcheck()
    assert cmd[:2] == ["feedmon", "status"]
    args = build_parser().parse_args(cmd[1:])
    assert args.func.__module__ == "feedmon.status_cmd"
    # the query gives up before Docker kills the check; the start period covers a cold Numba compile
    assert args.timeout + 5 <= seconds(opts["timeout"])
    assert seconds(opts["start-period"]) >= 60 and seconds(opts["interval"]) >= 10 and int(opts["retries"]) >= 1


def test_config_paths_are_on_volumes_and_writable_in_the_unit():
    doc = tomllib.loads(CONFIG.read_text(encoding="utf-8"))["run"]
    volumes = exec_form(instr("VOLUME")[0])
    rw = _unit()["Service"]["ReadWritePaths"][-1].split()
    for path in [*doc["model"], doc["state_dir"], doc["mcap"]]:
        assert any(path == v or path.startswith(v + "/") for v in volumes), path
        assert any(path == v or path.startswith(v + "/") for v in rw), path


# ---- deploy/monitor.toml through the real loader --------------------------------------------
def _model(path: Path) -> Path:
    save_model(AxisModel(
        machine="mill-1", axis="X", form="velocity-loop", Ts=1 / 333, beta=[0.834, 0.163], omega=5e-4,
        coulomb=False, loop_gain=83300.0, method="truth", tracker=TrackerConfig(),
        provenance={"source": "tests/test_deploy.py"},
    ), path)
    return path


def _config_for(tmp: Path) -> tuple[Path, Path, Path, Path]:
    """deploy/monitor.toml with its model, state and log paths moved into ``tmp``."""
    (tmp / "models").mkdir(parents=True)
    model = _model(tmp / "models" / "axis-x.model.toml")
    state, logs = tmp / "state", tmp / "logs"
    text = CONFIG.read_text(encoding="utf-8")
    for old, new in (('"/var/lib/feedmon/models/axis-x.model.toml"', model), ('"/var/lib/feedmon/state"', state),
                     ('"/var/log/feedmon"', logs)):
        assert old in text, f"{old} is no longer in {CONFIG}: update this test"
        text = text.replace(old, json.dumps(str(new)))
    cfg = tmp / "monitor.toml"
    cfg.write_text(text, encoding="utf-8")
    return cfg, model, state, logs


def test_example_config_is_accepted_by_run_config_loader(tmp_path):
    args = build_parser().parse_args(["run", "--config", str(CONFIG)])
    run = run_config_from_args(args)  # the shipped file as is: keys known, types and ranges right
    assert run.model == ["/var/lib/feedmon/models/axis-x.model.toml"]
    assert run.state_dir == "/var/lib/feedmon/state" and run.mcap == "/var/log/feedmon"
    assert run.prefix == "feedmon" and run.limits.queue_messages == 8192

    cfg, model, state, logs = _config_for(tmp_path)
    args = build_parser().parse_args(["run", "--config", str(cfg), "--queue", "100"])
    run = run_config_from_args(args)
    assert run.model == [str(model)] and run.state_dir == str(state) and run.mcap == str(logs)
    assert run.limits.queue_messages == 100  # the command line wins
    from monitor.axes import load_axes

    axes = load_axes(run.model)  # the model file named by the config loads
    assert list(axes) == [("mill-1", "X")]


# ---- systemd unit ---------------------------------------------------------------------------
def _unit() -> dict[str, dict[str, list[str]]]:
    """Sections → key → values (systemd allows repeated keys)."""
    out: dict[str, dict[str, list[str]]] = {}
    section = None
    for raw in UNIT.read_text(encoding="utf-8").splitlines():
        line = raw.strip()
        if not line or line[0] in "#;":
            continue
        if line.startswith("["):
            section = line.strip("[]")
            out.setdefault(section, {})
            continue
        key, sep, value = line.partition("=")
        assert sep and section, f"bad unit line {raw!r}"
        out[section].setdefault(key.strip(), []).append(value.strip())
    return out


def test_systemd_unit_structure():
    u = _unit()
    s = {k: v[-1] for k, v in u["Service"].items()}
    assert s["Type"] == "simple"
    assert s["Restart"] in ("on-failure", "always") and float(s["RestartSec"]) > 0
    assert s["User"] == "feedmon" and s["WorkingDirectory"].startswith("/var/lib/feedmon")
    exe, *argv = shlex.split(s["ExecStart"])
    assert exe.endswith("/feedmon") and argv == ["run", "--config", "/etc/feedmon/monitor.toml"]
    build_parser().parse_args(argv)
    assert s["KillSignal"] == "SIGTERM"
    # Monitor.stop: up to 30 s to drain the input queue + 30 s for the MCAP sink to finish
    assert int(s["TimeoutStopSec"]) >= 60
    for key in ("NoNewPrivileges", "PrivateTmp", "ProtectHome"):
        assert s[key] == "yes", key
    assert s["ProtectSystem"] == "strict"
    assert {"/var/lib/feedmon", "/var/log/feedmon"} <= set(s["ReadWritePaths"].split())
    assert "MemoryDenyWriteExecute" not in s  # would break the Numba JIT
    assert u["Install"]["WantedBy"] == ["multi-user.target"]


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze not installed")
def test_systemd_analyze_verify(tmp_path):
    """``systemd-analyze verify`` exits 0 even on unknown keys, so its output must be empty too.
    ExecStart is pointed at an existing feedmon (verify checks the binary exists)."""
    exe = Path(sys.executable).with_name("feedmon")
    assert exe.exists()
    text = UNIT.read_text(encoding="utf-8").replace("/opt/feedmon/bin/feedmon", str(exe))
    unit = tmp_path / "feedmon.service"
    unit.write_text(text, encoding="utf-8")
    r = subprocess.run(["systemd-analyze", "verify", "--man=no", str(unit)], capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 0 and not (r.stdout + r.stderr).strip(), r.stdout + r.stderr


# ---- the image's commands in a fresh environment --------------------------------------------
def _context(dest: Path) -> None:
    """The build context as Docker would send it (COPY lines, .dockerignore)."""
    ignore = [ln.strip() for ln in (ROOT / ".dockerignore").read_text().splitlines()
              if ln.strip() and not ln.startswith("#")]

    def ignored(rel: str) -> bool:
        name = rel.rsplit("/", 1)[-1]
        return any(fnmatch.fnmatch(rel, p) or (p.startswith("**/") and fnmatch.fnmatch(name, p[3:])) for p in ignore)

    for c in instr("COPY"):
        *srcs, dst = c.split()
        if dst.startswith("/"):  # files copied outside the build dir (config): not part of the install
            continue
        for src in srcs:
            s = ROOT / src
            assert s.exists(), f"COPY {src}: not in the repository"
            assert not ignored(src), f"COPY {src} is excluded by .dockerignore"
            target = dest / dst / s.name if dst.endswith("/") else dest / dst  # COPY dir dst: its contents into dst
            if s.is_dir():
                shutil.copytree(s, target, ignore=lambda d, names: [
                    n for n in names if ignored(str((Path(d) / n).relative_to(ROOT)))])
            else:
                target.parent.mkdir(parents=True, exist_ok=True)
                shutil.copy2(s, target)


class _Proc:
    """A subprocess whose stderr is collected by a thread; ``wait_for(text)``."""

    def __init__(self, argv, env, cwd):
        self.p = subprocess.Popen(argv, env=env, cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        self.lines: list[str] = []
        self._t = threading.Thread(target=self._read, daemon=True)
        self._t.start()

    def _read(self):
        for line in self.p.stdout:
            self.lines.append(line)

    def wait_for(self, text: str, timeout: float) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if any(text in ln for ln in self.lines):
                return True
            if self.p.poll() is not None:
                time.sleep(0.2)
                return any(text in ln for ln in self.lines)
            time.sleep(0.1)
        return False

    @property
    def output(self) -> str:
        return "".join(self.lines)


@pytest.mark.slow
def test_dockerfile_commands_work_in_a_fresh_venv(tmp_path):
    t0 = time.monotonic()
    ctx = tmp_path / "src"
    ctx.mkdir()
    _context(ctx)
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=300)
    bin_ = venv / "bin"
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV", "PYTHONHOME")}
    env.update(PATH=f"{bin_}{os.pathsep}{env.get('PATH', '')}", VIRTUAL_ENV=str(venv),
               NUMBA_CACHE_DIR=str(tmp_path / "numba-cache"), PYTHONDONTWRITEBYTECODE="1")

    # the RUN steps, in order, from the build directory (WORKDIR /src)
    steps = [s for s in run_steps() if s.startswith(("pip install", "python -c"))]
    assert steps[0] == "pip install ." and steps[1].startswith("python -c")
    install = shlex.split(steps[0])
    if not FULL_INSTALL:
        install.append("--no-deps")
    r = subprocess.run(install, cwd=ctx, env=env, capture_output=True, text=True, timeout=1800)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    purelib = Path(subprocess.check_output([str(bin_ / "python"), "-c",
                                            "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                                           env=env, text=True).strip())
    if not FULL_INSTALL:
        deps = {sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"]}
        (purelib / "zz_feedmon_test_deps.pth").write_text("\n".join(sorted(deps)) + "\n")
    installed = time.monotonic() - t0

    run = dict(cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
    # the installed copy is what runs, not the repository's editable install
    where = subprocess.run([str(bin_ / "python"), "-c", "import monitor, kernels, replay, importlib.metadata as m; "
                            "print(monitor.__file__); print(kernels.__file__); "
                            "print(m.entry_points(group='console_scripts')['feedmon'].load().__module__)"], **run)
    assert where.returncode == 0, where.stderr
    mon_file, kern_file, ep_module = where.stdout.split()
    assert Path(mon_file).is_relative_to(purelib) and Path(kern_file).is_relative_to(purelib), where.stdout
    assert ep_module == "feedmon.cli"
    assert (purelib / "replay" / "scenarios" / "shaker-constant.toml").is_file()  # package data made it

    # RUN python -c ... (Numba warm-up into NUMBA_CACHE_DIR)
    r = subprocess.run(shlex.split(steps[1]), **run)
    assert r.returncode == 0, r.stderr[-3000:]
    assert any((tmp_path / "numba-cache").rglob("*.nbi")), "the warm-up left no Numba cache"

    # entry point and the commands of ENTRYPOINT / HEALTHCHECK
    entry = exec_form(instr("ENTRYPOINT")[0])
    assert shutil.which(entry[0], path=str(bin_)) == str(bin_ / "feedmon")
    for argv in ([*entry, "--help"], ["feedmon", "status", "--help"]):
        r = subprocess.run(argv, **run)
        assert r.returncode == 0 and "usage: feedmon" in r.stdout, r.stderr
    _, health = healthcheck()
    prefix = f"deploytest{os.getpid()}"
    r = subprocess.run([*health, "--prefix", prefix], **run)  # nobody answers on this prefix
    assert r.returncode == 1 and "no monitor answered" in r.stderr, r.stdout + r.stderr

    # ENTRYPOINT --config <deploy/monitor.toml moved to tmp> as the container would run it
    cfg, _model_path, state, logs = _config_for(tmp_path / "etc")
    port = T.free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    mon = _Proc([*entry, "--config", str(cfg), "--listen", endpoint, "--prefix", prefix], env, tmp_path)
    try:
        assert mon.wait_for("ready", 300), mon.output
        r = subprocess.run([*health, "--connect", endpoint, "--prefix", prefix], **run)
        assert r.returncode == 0, r.stdout + r.stderr
        status = json.loads(r.stdout)
        assert status[0]["monitor"]["prefix"] == prefix and "mill-1/X" in status[0]["axes"]
        mon.p.send_signal(signal.SIGTERM)
        assert mon.p.wait(90) == 0, mon.output
    finally:
        if mon.p.poll() is None:
            mon.p.kill()
            mon.p.wait(10)
    assert "SIGTERM: stopping" in mon.output
    assert list(logs.glob("feedmon-*.mcap")), mon.output
    # no sample came: nothing learned, so no state written (one that exists would be left as it is)
    assert "tracker state of mill-1/X not saved: it learned nothing" in mon.output and state.is_dir(), mon.output
    r = subprocess.run([*health, "--connect", endpoint, "--prefix", prefix], **run)
    assert r.returncode != 0  # stopped monitor: unhealthy
    print(f"fresh venv: install {'with' if FULL_INSTALL else 'without'} dependencies {installed:.1f} s, "
          f"whole test {time.monotonic() - t0:.1f} s")
