"""The force in newtons on jobs the model was not identified on, as a user works.

    python benchmarks/out_of_sample.py                   # every pair below, seed 2 / 3
    python benchmarks/out_of_sample.py --pairs aircut    # the pairs whose name contains "aircut"
    python benchmarks/out_of_sample.py --json out.json   # also write the figures

For each pair (identification trial → monitored trial) this runs the user's path through the
command line, with no flags: ``feedmon identify ID.mcap -o m.toml`` once, then
``feedmon run --from OTHER.mcap --model m.toml``, and compares the monitor's per-sample
scalars with the truth the simulator (or the EMPS pulse record) carries:

* ``force_next`` and filtered ``force`` against the true disturbance force: correlation, RMS
  error and RMS error relative to the force's RMS (the mean included: a bias counts), from
  ``--skip`` seconds on;
* calibration: the share of samples whose ±2σ interval (``force_sd``) holds the truth;
* health: warn/alarm reports (and, for ``milling-payload``, those before the step and the delay
  to the first alarm after it).

Every figure is out of sample: the model never saw the monitored trial. The identification
and monitored trials use different seeds.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path

import msgspec
import numpy as np
from mcap.reader import make_reader

FEEDMON = [sys.executable, "-m", "feedmon"]


@dataclass
class Pair:
    name: str
    ident: str            # scenario or path of the identification trial
    monitored: str        # scenario or path of the monitored trial
    skip: float = 2.0     # s at the start left out of the figures (warm-up)
    step_at: float | None = None  # s, time of a true drive change (health must alarm after, not before)


PAIRS = [
    Pair("aircut->inc", "milling-aircut", "milling-inc"),
    Pair("aircut->incdec", "milling-aircut", "milling-incdec"),
    Pair("aircut->dec", "milling-aircut", "milling-dec"),
    Pair("aircut->spindle-change", "milling-aircut", "milling-spindle-change"),
    Pair("aircut->payload", "milling-aircut", "milling-payload", step_at=24.0),
    Pair("incdec->inc", "milling-incdec", "milling-inc"),
    Pair("control->constant", "shaker-control", "shaker-constant"),
    Pair("control->sweep", "shaker-control", "shaker-sweep"),
    Pair("emps->pulses", "emps:DATA_EMPS.mat", "emps:DATA_EMPS_PULSES.mat", skip=2.0),
]


def _run(args: list[str]) -> subprocess.CompletedProcess:
    return subprocess.run(FEEDMON + args, capture_output=True, text=True)


def _trial(spec: str, seed: int, work: Path, emps_dir: Path) -> Path:
    """A trial file: a simulated scenario (at ``seed``) or an imported EMPS record."""
    if spec.startswith("emps:"):
        name = spec.split(":", 1)[1]
        out = work / (Path(name).stem + ".mcap")
        if not out.exists():
            p = _run(["import", "emps", str(emps_dir / name), "-o", str(out)])
            if p.returncode != 0:
                raise SystemExit(p.stderr)
        return out
    out = work / f"{spec}-{seed}.mcap"
    if not out.exists():
        p = _run(["simulate", spec, "-o", str(out), "--seed", str(seed)])
        if p.returncode != 0:
            raise SystemExit(p.stderr)
    return out


def _model(trial: Path, work: Path) -> Path:
    out = work / (trial.stem + ".model.toml")
    if not out.exists():
        p = _run(["identify", str(trial), "-o", str(out)])
        if p.returncode != 0:
            raise SystemExit(f"identify {trial.name} failed:\n{p.stdout}\n{p.stderr}")
    return out


def _read(path: Path) -> tuple[dict[str, np.ndarray], list[dict]]:
    """The scalars channel as columns, and the health reports."""
    cols: dict[str, list] = {k: [] for k in ("t", "seq", "flags", "force", "force_sd", "force_next", "truth_force")}
    health = []
    with open(path, "rb") as fh:
        for _schema, channel, message in make_reader(fh).iter_messages():
            if channel.topic.endswith("/disturbance/scalars"):
                d = msgspec.json.decode(message.data)
                for k in cols:
                    cols[k].append(d.get(k, np.nan))
            elif channel.topic.endswith("/health"):
                health.append(msgspec.json.decode(message.data))
    return {k: np.asarray(v, dtype=float) for k, v in cols.items()}, health


@dataclass
class Figures:
    pair: str
    samples: int
    force_rms: float
    next_corr: float
    next_rms: float
    next_rel: float
    filt_corr: float
    filt_rms: float
    filt_rel: float
    filt_bias: float
    cover2: float
    next_cover2: float
    warn_alarm: int
    reports: int
    before_step: int | None = None
    alarm_delay: float | None = None


def _corr(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.corrcoef(a, b)[0, 1])


def evaluate(pair: Pair, seed_id: int, seed_mon: int, work: Path, emps_dir: Path) -> Figures:
    ident = _trial(pair.ident, seed_id, work, emps_dir)
    monitored = _trial(pair.monitored, seed_mon, work, emps_dir)
    model = _model(ident, work)
    out = work / f"{pair.name.replace('>', '')}.est.mcap"
    p = _run(["run", "--from", str(monitored), "-o", str(out), "--model", str(model)])
    if p.returncode not in (0, 1):
        raise SystemExit(f"run --from failed:\n{p.stderr}")
    c, health = _read(out)
    keep = (c["t"] - c["t"][0] >= pair.skip) & np.isfinite(c["truth_force"]) & np.isfinite(c["force"])
    keep &= np.isfinite(c["force_next"]) & np.isfinite(c["force_sd"])
    truth, filt, nxt, sd = c["truth_force"][keep], c["force"][keep], c["force_next"][keep], c["force_sd"][keep]
    frms = float(np.sqrt(np.mean(truth**2)))
    ef, en = filt - truth, nxt - truth
    bad = [h for h in health if h["state"] != "ok"]
    fig = Figures(
        pair=pair.name, samples=int(keep.sum()), force_rms=frms,
        next_corr=_corr(nxt, truth), next_rms=float(np.sqrt(np.mean(en**2))),
        next_rel=float(np.sqrt(np.mean(en**2)) / frms),
        filt_corr=_corr(filt, truth), filt_rms=float(np.sqrt(np.mean(ef**2))),
        filt_rel=float(np.sqrt(np.mean(ef**2)) / frms), filt_bias=float(np.mean(ef)),
        cover2=float(np.mean(np.abs(ef) <= 2 * sd)),
        next_cover2=float("nan"),
        warn_alarm=len(bad), reports=len(health),
    )
    if pair.step_at is not None:
        fig.before_step = sum(1 for h in bad if h["t"] < pair.step_at)
        after = [h["t"] for h in health if h["state"] == "alarm" and h["t"] >= pair.step_at]
        fig.alarm_delay = (after[0] - pair.step_at) if after else None
    return fig


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--pairs", default="", help="only pairs whose name contains this text")
    ap.add_argument("--seed-id", type=int, default=2, help="seed of the identification trials")
    ap.add_argument("--seed", type=int, default=3, help="seed of the monitored trials")
    ap.add_argument("--work", default=None, help="directory for trials and models (kept; default: temporary)")
    ap.add_argument("--emps-dir", default=str(Path(__file__).resolve().parents[1].parent / "shared/data/emps"))
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    work = Path(a.work) if a.work else Path(tempfile.mkdtemp(prefix="feedmon-oos-"))
    work.mkdir(parents=True, exist_ok=True)
    rows = []
    print(f"{'pair':24s} {'N':>6s} {'F rms':>7s} | {'next r':>7s} {'rms':>6s} {'rel':>5s} | "
          f"{'filt r':>7s} {'rms':>6s} {'rel':>5s} {'bias':>6s} | {'±2σ':>5s} | health")
    for pair in PAIRS:
        if a.pairs not in pair.name:
            continue
        f = evaluate(pair, a.seed_id, a.seed, work, Path(a.emps_dir))
        rows.append(asdict(f))
        extra = ""
        if f.before_step is not None:
            extra = f" before step {f.before_step}, alarm after {f.alarm_delay}"
        print(f"{f.pair:24s} {f.samples:6d} {f.force_rms:7.1f} | {f.next_corr:7.3f} {f.next_rms:6.1f} {f.next_rel:5.2f} | "
              f"{f.filt_corr:7.3f} {f.filt_rms:6.1f} {f.filt_rel:5.2f} {f.filt_bias:6.1f} | {f.cover2:5.2f} | "
              f"{f.warn_alarm}/{f.reports}{extra}", flush=True)
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
