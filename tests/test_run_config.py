"""``feedmon run --config``: one msgspec ``RunConfig``; errors name the file, the key and the allowed
range; command-line options override the file key by key and are checked against the same ranges."""

from __future__ import annotations

import subprocess
import sys

import pytest

from feedio.limits import InputLimits
from feedmon.cli import build_parser
from feedmon.run_config import RunConfig, load_config_file, run_config_from_args


def _args(*argv):
    return build_parser().parse_args(["run", *map(str, argv)])


def _write(tmp_path, text: str):
    p = tmp_path / "monitor.toml"
    p.write_text(text, encoding="utf-8")
    return p


def test_file_values_paths_relative_to_the_file_and_cli_overrides(tmp_path):
    cfg = _write(tmp_path, """
[run]
model = "models/x.model.toml"
state_dir = "state"
mcap = "/var/log/feedmon"
rotate_mb = 64
fresh = true
prefix = "feedmon/hall-2"
drain_seconds = 5
sink_priority = "low"

[run.limits]
max_message_bytes = 1_048_576
queue_bytes = 8_388_608
status_rate = 5
""")
    run = run_config_from_args(_args("--config", cfg))
    assert run.model == [str(tmp_path / "models" / "x.model.toml")] and run.state_dir == str(tmp_path / "state")
    assert run.mcap == "/var/log/feedmon" and run.rotate_mb == 64.0 and run.fresh and run.drain_seconds == 5.0
    assert run.prefix == "feedmon/hall-2" and run.sink_priority == "low"
    assert run.limits == InputLimits(max_message_bytes=1 << 20, queue_bytes=8 << 20, status_rate=5.0)
    run = run_config_from_args(_args("--config", cfg, "--model", "a.toml", "--model", "b.toml", "--queue", "100",
                                     "--limit", "status_rate=0.5", "--limit", "max-block-samples=2_000",
                                     "--prefix", "p", "--drain-seconds", "0", "--sink-priority", "idle"))
    assert run.model == ["a.toml", "b.toml"] and run.prefix == "p" and run.drain_seconds == 0.0
    assert run.sink_priority == "idle"
    assert run.limits.queue_messages == 100 and run.limits.status_rate == 0.5 and run.limits.max_block_samples == 2000
    assert run.limits.max_message_bytes == 1 << 20  # the file's value where the command line says nothing
    assert run_config_from_args(_args()) == RunConfig()  # no file, no options: the defaults


@pytest.mark.parametrize("text,needle", [
    ("[run]\nqueue = 5\n", "key run: Object contains unknown field `queue`; known keys here: model"),
    ("[run.limits]\nqueue_bytes = 5\n", "key run.limits.queue_bytes: Expected `int` >= 1024 "
                                        "(allowed: 1024 ≤ queue_bytes ≤ 17179869184)"),
    ("[run]\nrotate_mb = -1\n", "key run.rotate_mb: Expected `float` > 0.0 (allowed: 0 < rotate_mb ≤ 1e+06)"),
    ("[run]\nserve_rerun = 70000\n", "key run.serve_rerun: Expected `int` <= 65535"),
    ("[run]\nmodel = 5\n", "key run.model: Expected `array`, got `int`"),
    ("[run]\nfresh = \"yes\"\n", "key run.fresh: Expected `bool`, got `str`"),
    ("[run]\nmode = \"router\"\n", "key run.mode: Invalid enum value 'router' (allowed: mode one of client, peer)"),
    ("[run]\nsink_priority = \"realtime\"\n", "key run.sink_priority: Invalid enum value 'realtime' (allowed: sink_priority one of idle, low)"),
    ("[run.limits]\nmax_message_bytes = 1073741824\n", "queue_bytes (67108864) must be >= max_message_bytes"),
    ("[run.limits]\nstatus_rate = 1e9\n", "allowed: 0.1 ≤ status_rate ≤ 100000"),
    ("model = [\"x\"]\n", "unknown field `model`; known keys here: run, monitors (the options of feedmon run go in a [run] table)"),
    ("[run\n", "not valid TOML"),
])
def test_bad_file_names_file_key_and_range(tmp_path, text, needle):
    cfg = _write(tmp_path, text)
    with pytest.raises(ValueError) as exc:
        load_config_file(cfg)
    assert str(cfg) in str(exc.value) and needle in str(exc.value), str(exc.value)


@pytest.mark.parametrize("argv,needle", [
    (["--queue", "0"], "option --queue: Expected `int` >= 1 (allowed: 1 ≤ queue_messages ≤ 1000000)"),
    (["--limit", "max_message_bytes=10"], "option --limit max_message_bytes: Expected `int` >= 1024"),
    (["--limit", "nonsense=1"], "--limit nonsense: unknown limit; known: max_message_bytes"),
    (["--limit", "status_rate"], "expected NAME=VALUE"),
    (["--limit", "status_rate=fast"], "is not a number"),
    (["--limit", "queue_bytes=2048"], "queue_bytes (2048) must be >= max_message_bytes"),
    (["--rotate-mb", "0"], "option --rotate-mb: Expected `float` > 0.0"),
    (["--serve-rerun", "0"], "option --serve-rerun: Expected `int` >= 1"),
])
def test_bad_options_name_the_option_and_range(argv, needle):
    with pytest.raises(ValueError) as exc:
        run_config_from_args(_args("--model", "x.toml", *argv))
    assert needle in str(exc.value), str(exc.value)


def test_config_file_size_and_nesting_are_bounded(tmp_path):
    big = _write(tmp_path, "# " + "x" * (1 << 20) + "\n[run]\n")
    with pytest.raises(ValueError, match="at most 1048576"):
        load_config_file(big)
    deep = _write(tmp_path, "[run]\nmodel = " + "[" * 100_000 + "]" * 100_000 + "\n")
    with pytest.raises(ValueError, match="nested too deeply|not valid TOML|run.model"):
        load_config_file(deep)


def test_cli_reports_config_errors_without_traceback(tmp_path):
    cfg = _write(tmp_path, "[run]\nmodel = [\"x.toml\"]\n[run.limits]\nqueue_messages = 0\n")
    r = subprocess.run([sys.executable, "-m", "feedmon.cli", "run", "--config", str(cfg)], capture_output=True,
                       text=True, timeout=60)
    assert r.returncode == 2
    assert "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert str(cfg) in r.stderr and "run.limits.queue_messages" in r.stderr and "1 ≤ queue_messages" in r.stderr
