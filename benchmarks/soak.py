"""Soak test: one axis at 333 Hz for hours (default 24 h = 28.8 million samples) through the
monitor's own per-sample path, at full speed, without a trial file on disk.

Usage::

    /work/venv/bin/python benchmarks/soak.py                  # 24 h of stream (28.8 M samples)
    /work/venv/bin/python benchmarks/soak.py --hours 1        # one hour (1.2 M samples)
    /work/venv/bin/python benchmarks/soak.py --hours 0.05     # CI size (tests/test_soak.py)
    /work/venv/bin/python benchmarks/soak.py --rate-check     # throughput is a criterion too

What runs
---------
* **The stream** is generated on the fly, chunk by chunk (:class:`DriveStream`), from the exact
  ZOH model of ``kernels.feed_drive`` (the same plant as ``replay.simulator``'s exact path:
  P velocity loop, viscous damping, Coulomb friction on the true velocity, measurement noise seen
  by the loop), carrying the plant state across chunks. Nothing is written to disk.

  The axis runs a machining cycle (dwell, feed pass at +50 mm/s, dwell, rapid return at
  −200 mm/s). During every feed pass a periodic disturbance acts (the shaker of the thesis' case
  study 1: 55 Hz fundamental + 15 % second harmonic, plus a mean feed force), switched on and off
  abruptly at each pass. Its amplitude and phase drift slowly: the drift periods are T/4 and T/3
  of the run length T, so the first and the last quality windows see the same conditions (the
  cosine amplitude drift is even in time, the sine phase drift has an even rate), and any
  difference between them is the estimator's ageing, not the scenario's.

  Defects as a controller bridge produces them: recorder glitches (the previous v_meas repeated:
  STALE rows), isolated non-finite readings (NaN v_meas: REJECTED rows), sequence gaps (the head
  of a block lost: GAP, chain restart) and re-sent blocks (duplicates: no rows).
* **The monitor path**: the model file (true β, thesis tracker hyperparameters) is written with
  ``save_model`` and loaded with ``monitor.axes.load_axes``; ``monitor.warm.warm_up`` compiles first. Every
  SampleBlock is encoded to JSON and decoded by :meth:`Pipeline.receive` (the wire path of
  ``feedmon run``; ``--no-wire`` skips it), estimated by :meth:`Pipeline.estimate` (the
  :class:`~monitor.estimator.AxisEstimator` of ``feedmon run`` and ``feedmon run --from``) and the
  EstimateBlock is encoded as the live monitor publishes it. ``--mcap FILE`` (off by default;
  ``/dev/null`` works) also writes samples and estimates with the MCAP writer of ``run --from``.

Checks (the exit code is 1 when one fails)
-------------------------------------------
* **NaN**: no NaN estimate outside REJECTED rows — ``f_next``/``f_next_var``/``force_next`` on
  every row once the tracker holds data, ``f``/``f_var``/``force`` on every row that trained
  (finite residual). NaN by design (and not counted): ``f``/``residual`` on chain-restart and
  STALE rows.
* **accounting**: every sample sent is counted in, every non-duplicate one gives a row, no
  estimator error.
* **memory**: resident set size (``VmRSS``) after the warm-up (``--warmup-minutes`` of stream)
  grows by at most ``--max-rss-growth`` MB (default 10).
* **inverse**: ``max |Q K_D − I|`` (``tracker.inverse_error()``, sampled every
  ``--inverse-every`` blocks) stays ≤ ``--max-inverse-error``.
* **quality**: correlation of ``force_next`` (one-step-ahead prediction, N) with the true
  disturbance force, and the RMS error relative to the RMS of the truth, over the first and the
  last window (one hour, or a third of shorter runs): equal within ``--corr-tol`` and
  ``--nrmse-tol``. Rows flagged REJECTED or WARMUP are left out.
* **health**: the axis' health reports (about one per second of stream, online β in the default
  *track* mode) are all ``ok`` at these nominal conditions: no ``warn``, no ``alarm``.
* **rate** (only with ``--rate-check``): overall throughput ≥ ``--min-rate`` samples/s
  (default 3330 = 10× real time of one 333 Hz axis), and no slowdown: the last checkpoint
  interval runs at ≥ 80 % of the first post-warm-up one.

Figures of the table: per checkpoint interval (throughput, max ‖QK−I‖, correlation and RMS error
of that interval) plus the cumulative NaN count and RSS.
"""

from __future__ import annotations

import argparse
import gc
import json
import math
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from feedio import schema as S  # noqa: E402
from kernels.feed_drive import physical_to_beta  # noqa: E402
from replay.simulator import closed_loop_zoh  # noqa: E402  (the simulator's plant: one definition)

RATE = 333.0
MACHINE, AXIS = "soak", "X"
#: the drive of the shaker case study (replay/scenarios/_shaker.toml)
DRIVE = dict(inertia=300.0, damping=300.0, loop_gain=83300.0, coulomb_pos=9.0, coulomb_neg=10.0, omega=0.0005)
#: machining cycle: (time in cycle s, v_ref m/s) knots, linear in between; 18 s
CYCLE = np.array([
    (0.0, 0.0), (1.0, 0.0), (1.1, 0.05), (13.1, 0.05), (13.2, 0.0), (14.0, 0.0),
    (14.4, -0.2), (17.4, -0.2), (17.8, 0.0), (18.0, 0.0),
])
CUT = (1.1, 13.1)  # the disturbance acts during the constant-feed part of the pass


# ---------------------------------------------------------------------------------------------
# the stream
# ---------------------------------------------------------------------------------------------
@dataclass
class Chunk:
    seq0: int
    t: np.ndarray
    v_ref: np.ndarray
    v_meas: np.ndarray  # as recorded: glitches and NaNs included
    force: np.ndarray  # true disturbance force T_c held over [k, k+1), N


class DriveStream:
    """Samples of one axis, generated chunk by chunk with the plant state carried over."""

    def __init__(self, seconds: float, *, seed: int = 1, noise_std: float = 5e-6, amplitude: float = 60.0,
                 frequency: float = 55.0, harmonic2: float = 0.15, mean_force: float = 10.0,
                 glitch_rate: float = 2e-4, nan_rate: float = 2e-6):
        self.Ts = 1.0 / RATE
        self.total = int(round(seconds * RATE))
        self.T = self.total * self.Ts
        self.rng = np.random.default_rng(seed)
        self.noise_std, self.amplitude, self.frequency = noise_std, amplitude, frequency
        self.harmonic2, self.mean_force = harmonic2, mean_force
        self.glitch_rate, self.nan_rate = glitch_rate, nan_rate
        self.k = 0
        self.v = 0.0
        self.last_vm = 0.0

    def force(self, t_mid: np.ndarray) -> np.ndarray:
        """True disturbance force (N) at the interval midpoints ``t_mid``."""
        T = self.T
        phase_in_cycle = np.mod(t_mid, CYCLE[-1, 0])
        on = (phase_in_cycle >= CUT[0]) & (phase_in_cycle < CUT[1])
        amp = self.amplitude * (1.0 + 0.25 * np.cos(2 * np.pi * t_mid / (T / 4)))
        drift = 1.5 * np.sin(2 * np.pi * t_mid / (T / 3))  # rad
        psi = 2 * np.pi * self.frequency * t_mid + drift
        f = amp * (np.sin(psi) + self.harmonic2 * np.sin(2 * psi + np.radians(30.0))) + self.mean_force
        return np.where(on, f, 0.0)

    def next_chunk(self, n: int) -> Chunk | None:
        n = min(n, self.total - self.k)
        if n <= 0:
            return None
        k = np.arange(self.k, self.k + n, dtype=np.float64)
        t = k * self.Ts
        v_ref = np.interp(np.mod(t, CYCLE[-1, 0]), CYCLE[:, 0], CYCLE[:, 1])
        tc = self.force(t + 0.5 * self.Ts)
        noise = self.rng.normal(0.0, self.noise_std, n)
        d = DRIVE
        _, vm, _, _, self.v, _ = closed_loop_zoh(v_ref, tc, noise, self.Ts, d["inertia"], d["damping"],
                                                 d["loop_gain"], d["coulomb_pos"], d["coulomb_neg"], d["omega"],
                                                 self.v, 0.0)
        rec = vm.copy()
        glitch = np.flatnonzero(self.rng.random(n) < self.glitch_rate)
        for i in glitch:  # the recorder repeats the previous value (the loop is not affected)
            rec[i] = rec[i - 1] if i > 0 else self.last_vm
        rec[self.rng.random(n) < self.nan_rate] = np.nan
        self.last_vm = float(rec[-1])
        chunk = Chunk(self.k, t, v_ref, rec, tc)
        self.k += n
        return chunk


def model_file(path: Path) -> Path:
    """The axis model file with the stream's true β and the thesis tracker (Table 4.5)."""
    from monitor.model_file import AxisModel, TrackerConfig, save_model
    from monitor.online_settings import LocallyPeriodicKernel

    d = DRIVE
    beta = physical_to_beta("velocity-loop", 1.0 / RATE, d["inertia"], d["damping"], gain=d["loop_gain"],
                            coulomb_pos=d["coulomb_pos"], coulomb_neg=d["coulomb_neg"], coulomb=True)
    save_model(AxisModel(
        machine=MACHINE, axis=AXIS, form="velocity-loop", Ts=1.0 / RATE, beta=[float(b) for b in beta],
        omega=d["omega"], coulomb=True, loop_gain=d["loop_gain"], method="truth",
        tracker=TrackerConfig(kernel=LocallyPeriodicKernel(sigma1=1.2, sigma2=0.495, period=1 / 55),
                              gamma=5.85, forgetting=0.996, budget=100),
        provenance={"source": "benchmarks/soak.py (true beta)"},
    ), path)
    return path


# ---------------------------------------------------------------------------------------------
# statistics
# ---------------------------------------------------------------------------------------------
def rss_mb() -> float:
    """Resident set size of this process (VmRSS, MB)."""
    with open("/proc/self/status", encoding="ascii") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return math.nan


@dataclass
class Moments:
    """Streaming sums for correlation and RMS error (no sample buffers: memory stays flat)."""

    n: int = 0
    sx: float = 0.0
    sy: float = 0.0
    sxx: float = 0.0
    syy: float = 0.0
    sxy: float = 0.0
    see: float = 0.0

    def add(self, est: np.ndarray, truth: np.ndarray) -> None:
        if est.size:
            self.n += est.size
            self.sx += float(est.sum())
            self.sy += float(truth.sum())
            self.sxx += float(est @ est)
            self.syy += float(truth @ truth)
            self.sxy += float(est @ truth)
            e = est - truth
            self.see += float(e @ e)

    @property
    def corr(self) -> float:
        if self.n < 2:
            return math.nan
        n = self.n
        cxx, cyy = self.sxx - self.sx ** 2 / n, self.syy - self.sy ** 2 / n
        cxy = self.sxy - self.sx * self.sy / n
        return cxy / math.sqrt(cxx * cyy) if cxx > 0 and cyy > 0 else math.nan

    @property
    def rmse(self) -> float:
        return math.sqrt(self.see / self.n) if self.n else math.nan

    @property
    def nrmse(self) -> float:
        """RMS error / RMS of the truth."""
        return math.sqrt(self.see / self.syy) if self.syy > 0 else math.nan


def nan_violations(est: S.EstimateBlock) -> int:
    """Rows (not REJECTED) with a NaN where the estimator must give a number (see the module doc)."""
    flags = np.asarray(est.flags)
    ok = (flags & S.REJECTED) == 0
    has_data = ok & (np.asarray(est.dict_size) > 0)
    trained = ok & np.isfinite(np.asarray(est.residual, dtype=np.float64))
    bad = np.zeros(flags.size, dtype=bool)
    for name in ("f_next", "f_next_var", "force_next"):
        bad |= has_data & ~np.isfinite(np.asarray(getattr(est, name), dtype=np.float64))
    for name in ("f", "f_var", "force", "force_var"):
        bad |= trained & ~np.isfinite(np.asarray(getattr(est, name), dtype=np.float64))
    return int(bad.sum())


@dataclass
class Row:
    stream_s: float
    samples: int
    wall_s: float
    rate: float  # samples/s over the interval
    nan: int  # cumulative
    rss_mb: float
    inv_err: float  # max over the interval
    dict_size: int
    corr: float  # interval
    rmse_n: float  # interval
    nrmse: float  # interval
    gaps: int
    stale: int
    rejected: int


@dataclass
class SoakResult:
    hours: float
    samples: int
    seconds: float
    rows: list[Row] = field(default_factory=list)
    checks: dict[str, tuple[bool, str]] = field(default_factory=dict)
    first: Moments = field(default_factory=Moments)
    last: Moments = field(default_factory=Moments)
    window_s: float = 0.0
    rss_base: float = math.nan
    rss_max_after: float = math.nan
    inv_err_max: float = 0.0  # after the warm-up
    inv_err_all: float = 0.0  # including the warm-up (the dictionary filling)
    nan: int = 0
    counters: dict[str, int] = field(default_factory=dict)
    objects: list[int] = field(default_factory=list)
    health: dict[str, int] = field(default_factory=lambda: {"ok": 0, "warn": 0, "alarm": 0})
    health_reasons: set[str] = field(default_factory=set)
    health_events: list[str] = field(default_factory=list)  # the first non-ok reports (stream time, reasons)
    nu2_max: float = 0.0  # largest window mean of ν² in a report
    alarms: list[str] = field(default_factory=list)  # process alarms with --monitors (stream time, kind, value)
    z_max: dict[str, float] = field(default_factory=dict)  # largest |drift| of each parameter vs the model file (%)
    zs_max: dict[str, float] = field(default_factory=dict)  # largest |drift| in standard errors (the model's β is exact)

    @property
    def rate(self) -> float:
        return self.samples / self.seconds if self.seconds > 0 else math.inf

    @property
    def ok(self) -> bool:
        return all(ok for ok, _ in self.checks.values())


# ---------------------------------------------------------------------------------------------
# the run
# ---------------------------------------------------------------------------------------------
def _fmt_t(s: float) -> str:
    h, rem = divmod(int(round(s)), 3600)
    m, sec = divmod(rem, 60)
    return f"{h:d}:{m:02d}:{sec:02d}"


HEADER = (f"{'stream':>8} {'samples':>11} {'wall s':>8} {'samples/s':>10} {'NaN':>4} {'RSS MB':>7} "
          f"{'max|QK-I|':>9} {'dict':>4} {'corr':>6} {'RMSE N':>7} {'NRMSE':>6} {'gaps':>5} {'stale':>6} {'rej':>4}")


def _fmt_row(r: Row) -> str:
    return (f"{_fmt_t(r.stream_s):>8} {r.samples:>11,} {r.wall_s:>8.1f} {r.rate:>10,.0f} {r.nan:>4} {r.rss_mb:>7.1f} "
            f"{r.inv_err:>9.1e} {r.dict_size:>4} {r.corr:>6.3f} {r.rmse_n:>7.2f} {r.nrmse:>6.3f} {r.gaps:>5} "
            f"{r.stale:>6} {r.rejected:>4}")


def run_soak(opts: argparse.Namespace, out=sys.stdout) -> SoakResult:
    from monitor.axes import live_meta, load_axes
    from monitor.pipeline import Pipeline
    from monitor.warm import warm_up

    def say(msg: str = "") -> None:
        print(msg, file=out, flush=True)

    D = DRIVE
    seconds = opts.hours * 3600.0
    stream = DriveStream(seconds, seed=opts.seed, glitch_rate=opts.glitch_rate, nan_rate=opts.nan_rate)
    total = stream.total
    if total < 10 * opts.block:
        raise ValueError(f"--hours {opts.hours} is too short: {total} samples")
    checkpoint_s = opts.checkpoint if opts.checkpoint else (3600.0 if opts.hours >= 2 else seconds / 10)
    window_s = min(3600.0, seconds / 3)
    warmup_s = opts.warmup_minutes * 60.0 if opts.warmup_minutes is not None else min(600.0, 0.05 * seconds)
    res = SoakResult(opts.hours, 0, 0.0, window_s=window_s)

    tmp = tempfile.TemporaryDirectory(prefix="feedmon-soak-")
    model = model_file(Path(tmp.name) / "soak.model.toml")
    axes = load_axes([model])
    warm_up(axes)
    ax = axes[(MACHINE, AXIS)]
    monitors = None
    if opts.monitors:
        from monitor.process_monitor import build_monitors
        from monitor.process_monitor.settings import ImpulseSettings, MonitorSettings

        # the collision floor is the user's setting for the process: this stream's force starts in one
        # sample at up to 85 N (a shaker switched on), which the default floor of 50 N calls a collision
        monitors = build_monitors(axes, MonitorSettings(enabled=True,
                                                        impulse=ImpulseSettings(limit_N=opts.collision_floor)))
    pipe = Pipeline(axes, monitors=monitors)
    key = f"feedmon/{MACHINE}/{AXIS}/samples"
    writer = None
    if opts.mcap:
        from feedio.mcapio import TrialWriter

        writer = TrialWriter(opts.mcap, [live_meta(ax, source="soak")])

    say(f"soak: {opts.hours:g} h of one axis at {RATE:g} Hz = {total:,} samples in blocks of {opts.block}, "
        f"{'JSON wire round trip' if opts.wire else 'no wire encoding'}"
        f"{', MCAP -> ' + opts.mcap if writer else ''}; checkpoints every {_fmt_t(checkpoint_s)} of stream, "
        f"quality windows {_fmt_t(window_s)}, memory baseline after {_fmt_t(warmup_s)}")
    say(HEADER)

    rng = np.random.default_rng(opts.seed + 1000)
    gap_p, dup_p = opts.gap_rate, opts.dup_rate
    sent = duplicates_sent = 0
    blocks = 0
    interval = Moments()
    inv_max_interval = 0.0
    next_cp = checkpoint_s
    prev_wall, prev_samples = 0.0, 0
    rss0 = rss_mb()
    prev_block: S.SampleBlock | None = None
    gc.collect()
    t_start = time.perf_counter()
    chunk_n = int(60 * RATE)
    first_end, last_start = window_s, seconds - window_s
    base_taken = False

    def handle(block: S.SampleBlock) -> S.EstimateBlock | None:
        if opts.wire:
            decoded = pipe.receive(key, S.encode(block))
            if decoded is None:
                raise AssertionError("the soak stream produced a malformed block")
            block = decoded
        res_est = pipe.estimate(block)
        rows = res_est.est
        res.alarms += [f"{_fmt_t(a.t)} {a.kind} {a.value:.1f} N against {a.limit:.1f} N" for a in res_est.alarms]
        est = None if rows is None else rows.block()
        for h in res_est.health:
            res.health[h.state] += 1
            if h.state != "ok" and len(res.health_events) < 20:
                res.health_events.append(f"{_fmt_t(h.t)} {h.state}: {'; '.join(h.reasons)}")
            res.health_reasons.update(r.split(" (")[0] for r in h.reasons if not r.startswith("not "))
            if h.nu2 is not None:
                res.nu2_max = max(res.nu2_max, h.nu2)
            for name, ref in (("inertia", D["inertia"]), ("damping", D["damping"]),
                              ("coulomb", 0.5 * (D["coulomb_pos"] + D["coulomb_neg"]))):
                v = getattr(h, name)
                if v is not None:
                    res.z_max[name] = max(res.z_max.get(name, 0.0), 100.0 * abs(v / ref - 1.0))
            for name, ref in (("inertia", D["inertia"]), ("damping", D["damping"]),
                              ("coulomb_pos", D["coulomb_pos"]), ("coulomb_neg", D["coulomb_neg"])):
                v, se = getattr(h, name), getattr(h, f"{name}_se")
                if v is not None and se:
                    res.zs_max[name] = max(res.zs_max.get(name, 0.0), abs(v - ref) / se)
        if est is not None:
            if opts.wire:
                rows.json()  # what the monitor publishes
            if writer is not None:
                writer.write_samples(block)
                writer.write_estimates(est)
        return est

    while (chunk := stream.next_chunk(chunk_n)) is not None:
        truth_all = chunk.force
        for i0 in range(0, chunk.t.size, opts.block):
            i1 = min(i0 + opts.block, chunk.t.size)
            lo = i0
            if rng.random() < gap_p:  # the head of this block is lost on the way
                lo = i0 + int(rng.integers(1, i1 - i0))
            block = S.SampleBlock(machine=MACHINE, axis=AXIS, seq=chunk.seq0 + lo, t=chunk.t[lo:i1].tolist(),
                                  v_ref=chunk.v_ref[lo:i1].tolist(), v_meas=chunk.v_meas[lo:i1].tolist())
            sent += i1 - lo
            est = handle(block)
            blocks += 1
            if prev_block is not None and rng.random() < dup_p:  # the bridge re-sends the previous block
                sent += len(prev_block.t)
                duplicates_sent += len(prev_block.t)
                if handle(prev_block) is not None:
                    raise AssertionError("a re-sent block produced estimate rows")
            prev_block = block
            if est is None:
                continue
            res.nan += nan_violations(est)
            flags = np.asarray(est.flags)
            fn = np.asarray(est.force_next, dtype=np.float64)
            use = ((flags & (S.REJECTED | S.WARMUP)) == 0) & np.isfinite(fn)
            idx = np.asarray(est.seq + np.arange(len(est.t))) - chunk.seq0
            e, tr = fn[use], truth_all[idx[use]]
            interval.add(e, tr)
            t_blk = est.t[0]
            if t_blk < first_end:
                res.first.add(e, tr)
            elif t_blk >= last_start:
                res.last.add(e, tr)
            if blocks % opts.inverse_every == 0:
                inv = ax.estimator.tracker.inverse_error()
                inv_max_interval = max(inv_max_interval, inv)
                if base_taken:
                    res.inv_err_max = max(res.inv_err_max, inv)
            if not base_taken and est.t[-1] >= warmup_s:
                gc.collect()
                res.rss_base = rss_mb()
                res.rss_max_after = res.rss_base
                base_taken = True
            if est.t[-1] + stream.Ts >= next_cp - 1e-9 or (chunk.seq0 + i1 >= total and i1 == chunk.t.size):
                wall = time.perf_counter() - t_start
                inv = ax.estimator.tracker.inverse_error()
                inv_max_interval = max(inv_max_interval, inv)
                res.inv_err_max = max(res.inv_err_max, inv if base_taken else 0.0)
                res.inv_err_all = max(res.inv_err_all, inv_max_interval)
                c = ax.estimator.counters
                rss = rss_mb()
                if base_taken:
                    res.rss_max_after = max(res.rss_max_after, rss)
                res.objects.append(len(gc.get_objects()))
                res.rows.append(Row(
                    stream_s=est.t[-1] + stream.Ts, samples=sent, wall_s=wall,
                    rate=(sent - prev_samples) / max(wall - prev_wall, 1e-9), nan=res.nan, rss_mb=rss,
                    inv_err=inv_max_interval, dict_size=ax.estimator.tracker.size, corr=interval.corr,
                    rmse_n=interval.rmse, nrmse=interval.nrmse, gaps=c["gaps"], stale=c["stale"],
                    rejected=c["rejected_non_finite"] + c["rejected_out_of_range"],
                ))
                say(_fmt_row(res.rows[-1]))
                prev_wall, prev_samples = wall, sent
                interval = Moments()
                inv_max_interval = 0.0
                while next_cp <= est.t[-1] + stream.Ts + 1e-9:
                    next_cp += checkpoint_s
    res.seconds = time.perf_counter() - t_start
    res.samples = sent
    if writer is not None:
        writer.close()
    tmp.cleanup()
    c = dict(ax.estimator.counters)
    c.update({f"status.{k}": v for k, v in ax.status.counters.items()})
    c.update({f"pipeline.{k}": v for k, v in pipe.counters.items()})
    res.counters = {k: int(v) for k, v in sorted(c.items())}
    _judge(res, opts, sent, duplicates_sent, rss0)
    _report(res, opts, say)
    return res


def _judge(res: SoakResult, opts, sent: int, duplicates_sent: int, rss0: float) -> None:
    c = res.counters
    ch = res.checks
    ch["nan"] = (res.nan == 0, f"{res.nan} NaN estimates outside REJECTED rows (must be 0)")
    errors = c.get("status.estimator_error", 0) + c.get("pipeline.malformed", 0) + c.get("status.malformed", 0)
    dropped = c.get("duplicate", 0) + c.get("out_of_order", 0)  # a re-sent block is behind the chain: out_of_order
    acc_ok = (c.get("samples_in", 0) == sent and dropped == duplicates_sent
              and c.get("estimates_out", 0) == sent - duplicates_sent and errors == 0)
    ch["accounting"] = (acc_ok, f"{sent:,} sent = {c.get('samples_in', 0):,} in; {c.get('estimates_out', 0):,} rows "
                                f"= sent − {duplicates_sent:,} re-sent ({dropped:,} counted duplicate/out_of_order); "
                                f"{errors} estimator/decoder errors")
    growth = res.rss_max_after - res.rss_base
    ch["memory"] = (growth <= opts.max_rss_growth,
                    f"RSS {res.rss_base:.1f} MB after warm-up → max {res.rss_max_after:.1f} MB: growth {growth:+.1f} MB "
                    f"(limit {opts.max_rss_growth:g} MB; {rss0:.1f} MB at start)")
    ch["inverse"] = (res.inv_err_max <= opts.max_inverse_error,
                     f"max |Q K_D − I| after the warm-up = {res.inv_err_max:.2e} (limit {opts.max_inverse_error:.0e}); "
                     f"{res.inv_err_all:.2e} including it")
    f, l_ = res.first, res.last
    dc, dn = l_.corr - f.corr, l_.nrmse - f.nrmse
    q_ok = (f.n > 0 and l_.n > 0 and abs(dc) <= opts.corr_tol and abs(dn) <= opts.nrmse_tol
            and f.corr >= opts.min_corr and l_.corr >= opts.min_corr)
    ch["quality"] = (q_ok, f"first {_fmt_t(res.window_s)}: corr {f.corr:.4f}, NRMSE {f.nrmse:.4f} (RMSE {f.rmse:.2f} N); "
                           f"last: corr {l_.corr:.4f}, NRMSE {l_.nrmse:.4f} (RMSE {l_.rmse:.2f} N); "
                           f"Δcorr {dc:+.4f} (tol {opts.corr_tol:g}), ΔNRMSE {dn:+.4f} (tol {opts.nrmse_tol:g}), "
                           f"corr ≥ {opts.min_corr:g}")
    hc = res.health
    drift = ", ".join(f"{k} {v:.2f} %" for k, v in res.z_max.items())
    drift += "; in standard errors: " + ", ".join(f"{k} {v:.1f}" for k, v in res.zs_max.items())
    ch["health"] = (hc["warn"] == 0 and hc["alarm"] == 0 and hc["ok"] > 0,
                    f"{hc['ok']:,} ok / {hc['warn']} warn / {hc['alarm']} alarm health reports (must be no warn, no "
                    f"alarm); largest mean ν² of a report {res.nu2_max:.2f}; largest online parameter error vs the "
                    f"truth: {drift}" + (f"; reasons: {'; '.join(sorted(res.health_reasons))}"
                                         if res.health_reasons else ""))
    if opts.monitors:
        ch["alarms"] = (not res.alarms, f"{len(res.alarms)} process alarms (must be 0)"
                                        + (": " + "; ".join(res.alarms[:10]) if res.alarms else ""))
    if opts.rate_check:
        rows = [r for r in res.rows if r.stream_s > (opts.warmup_minutes or 0) * 60.0] or res.rows
        first_rate = rows[0].rate if len(rows) > 1 else res.rate
        last_rate = rows[-1].rate
        r_ok = res.rate >= opts.min_rate and last_rate >= 0.8 * first_rate
        ch["rate"] = (r_ok, f"{res.rate:,.0f} samples/s overall (min {opts.min_rate:,.0f}); last interval "
                            f"{last_rate:,.0f} vs first {first_rate:,.0f} samples/s (must be ≥ 80 %)")


def _report(res: SoakResult, opts, say) -> None:
    say()
    day = 24 * 3600 * RATE
    say(f"{res.samples:,} samples in {res.seconds:.1f} s = {res.rate:,.0f} samples/s "
        f"({res.rate / RATE:,.0f}× real time; 24 h of one axis would take {day / res.rate / 60:.1f} min)")
    c = res.counters
    say("estimator counters: " + ", ".join(f"{k}={v:,}" for k, v in c.items()))
    if res.objects:
        say(f"GC-tracked objects at the checkpoints: first {res.objects[0]:,}, last {res.objects[-1]:,}")
    for name, (ok, text) in res.checks.items():
        say(f"  [{'PASS' if ok else 'FAIL'}] {name:<10} {text}")
    for line in res.health_events:
        say(f"  health report {line}")
    say("soak: PASS" if res.ok else "soak: FAIL")
    if opts.json:
        Path(opts.json).write_text(json.dumps({
            "hours": res.hours, "samples": res.samples, "seconds": res.seconds, "rate": res.rate,
            "rows": [r.__dict__ for r in res.rows], "checks": {k: {"ok": ok, "detail": d} for k, (ok, d) in res.checks.items()},
            "counters": res.counters, "ok": res.ok,
        }, indent=1, default=float))


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--hours", type=float, default=24.0, help="stream length in hours of one 333 Hz axis (default 24)")
    p.add_argument("--rate-check", action="store_true",
                   help="make throughput a criterion: ≥ --min-rate overall and no slowdown over the run")
    p.add_argument("--min-rate", type=float, default=10 * RATE,
                   help="samples/s required with --rate-check (default 3330 = 10x real time)")
    p.add_argument("--block", type=int, default=100, help="samples per SampleBlock (default 100)")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--checkpoint", type=float, default=None, metavar="SECONDS",
                   help="stream seconds between table rows (default 1 h, or a tenth of runs shorter than 2 h)")
    p.add_argument("--warmup-minutes", type=float, default=None,
                   help="stream minutes before the memory baseline (default min(10, 5 %% of the run))")
    p.add_argument("--max-rss-growth", type=float, default=10.0, metavar="MB",
                   help="allowed RSS growth after the warm-up (default 10 MB)")
    p.add_argument("--max-inverse-error", type=float, default=1e-6,
                   help="bound on max |Q K_D − I| after the warm-up (default 1e-6; the estimator refines q, ~1e-8)")
    p.add_argument("--inverse-every", type=int, default=20, metavar="BLOCKS",
                   help="sample tracker.inverse_error() every so many blocks (default 20; ~1 ms a call)")
    p.add_argument("--corr-tol", type=float, default=0.01, help="|corr(last) − corr(first)| allowed (default 0.01)")
    p.add_argument("--nrmse-tol", type=float, default=0.03,
                   help="|NRMSE(last) − NRMSE(first)| allowed (default 0.03)")
    p.add_argument("--min-corr", type=float, default=0.9, help="both windows need at least this correlation (default 0.9)")
    p.add_argument("--glitch-rate", type=float, default=2e-4, help="probability per sample of a repeated v_meas")
    p.add_argument("--nan-rate", type=float, default=2e-6, help="probability per sample of a NaN v_meas")
    p.add_argument("--gap-rate", type=float, default=1 / 2000, help="probability per block of a lost block head")
    p.add_argument("--dup-rate", type=float, default=1 / 5000, help="probability per block of a re-sent block")
    p.add_argument("--no-wire", dest="wire", action="store_false", help="skip the JSON encode/decode of the live path")
    p.add_argument("--mcap", default=None, metavar="FILE", help="also write samples + estimates to this MCAP (/dev/null ok)")
    p.add_argument("--monitors", action="store_true",
                   help="run the process monitors (defaults) on the estimates too; any alarm fails the soak")
    p.add_argument("--collision-floor", type=float, default=150.0, metavar="N",
                   help="with --monitors: the collision monitor's absolute floor limit_N (default 150 N; the stream's "
                        "force reaches 85 N within one sample at each feed pass)")
    p.add_argument("--json", default=None, metavar="FILE", help="write the figures and checks as JSON")
    return p


def main(argv: list[str] | None = None, out=sys.stdout) -> int:
    opts = build_parser().parse_args(argv)
    if not opts.hours > 0:
        print("soak: --hours must be > 0", file=sys.stderr)
        return 2
    res = run_soak(opts, out=out)
    return 0 if res.ok else 1


if __name__ == "__main__":
    sys.exit(main())
