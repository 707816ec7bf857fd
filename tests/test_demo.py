"""`feedmon demo`: one command, real Zenoh on loopback, real MCAP and .rrd files."""

import subprocess
import sys

from feedio.mcapio import iter_blocks


def test_demo_end_to_end(tmp_path):
    out = tmp_path / "demo"
    proc = subprocess.run(
        [sys.executable, "-m", "feedmon.cli", "demo", "--out", str(out), "--duration", "12", "--rate", "20"],
        capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode == 0, proc.stderr + proc.stdout
    text = proc.stdout + proc.stderr
    assert "correlation, one-step-ahead prediction" in text
    assert (out / "monitor.rrd").stat().st_size > 10_000
    samples = sum(len(b.t) for _, b in iter_blocks(out / "monitor.mcap", kinds=("samples",)))
    estimates = sum(len(b.t) for _, b in iter_blocks(out / "monitor.mcap", kinds=("disturbance",)))
    assert samples == estimates == int(round(12 * 333))
    verify = subprocess.run([sys.executable, "-m", "rerun", "rrd", "verify", str(out / "monitor.rrd")],
                            capture_output=True, text=True, timeout=120)
    assert verify.returncode == 0, verify.stderr
