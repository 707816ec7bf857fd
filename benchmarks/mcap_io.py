"""MCAP I/O figures: checked reading, replay over many axes, per-sample scalars, recover, run --from.

    python benchmarks/mcap_io.py            # prints a table (medians of --repeat runs)
    python benchmarks/mcap_io.py --quick

* read_trial of a 120 s, 333 Hz trial (samples + truth): samples/s, and the share of the CRC checks
  (data-section pre-pass and chunk CRCs);
* replay of files with N axes (scan + one pass, no Zenoh): seconds and seconds per axis — linear in N;
* the disturbance/scalars channel: pairing + writing, µs per sample;
* recover of the same trial, healthy and with one flipped byte per chunk;
* run --from (estimation + writing samples, estimates, truth and scalars): samples/s.

Figures taken while other processes load the machine are noisy: compare same-run ratios.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np


def _median(fn, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="smaller files, fewer repeats")
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()
    repeat = 3 if args.quick else args.repeat
    duration = 30.0 if args.quick else 120.0

    from feedio import schema as S
    from feedio.mcapfile import McapFile
    from feedio.mcapio import TrialWriter, read_trial
    from feedio.scalars import ScalarsPairer
    from monitor.axes import load_axes
    from monitor.model_file import AxisModel, TrackerConfig, save_model
    from monitor.offline import run_offline
    from monitor.online_settings import LocallyPeriodicKernel
    from replay.player import _pass_stream, scan_trial
    from replay.recover import recover
    from replay.simulator import simulate_scenario, write_trial

    rows: list[tuple[str, str]] = []
    with tempfile.TemporaryDirectory(prefix="feedmon-mcapio-") as tmp:
        d = Path(tmp)
        trial = d / "trial.mcap"
        res = simulate_scenario("milling-incdec", seed=1, duration=duration, created="2024-05-01T08:00:00Z")
        write_trial(res, trial)
        n = len(res)
        size = trial.stat().st_size

        t_read = _median(lambda: read_trial(trial), repeat)

        def open_only():
            with McapFile(trial):
                pass

        t_open = _median(open_only, repeat)
        rows.append(("read_trial, 120 s trial" if not args.quick else "read_trial, 30 s trial",
                     f"{n / t_read:,.0f} samples/s ({size / t_read / 1e6:.1f} MB/s); opening with the data-CRC "
                     f"pre-pass {t_open / t_read:.0%} of it"))

        # replay over many axes
        per_axis = []
        for n_axes in ((50, 200, 800) if args.quick else (100, 1000, 3000)):
            path = d / f"axes{n_axes}.mcap"
            metas = [S.TrialMeta(Ts=0.003, form="velocity-loop", machine="m", axis=f"A{i}",
                                 provenance=S.Provenance(source="bench", tool="bench", version="0"))
                     for i in range(n_axes)]
            with TrialWriter(path, metas, start=0) as w:
                for seq in (0, 10):
                    t = [(seq + i) * 0.003 for i in range(10)]
                    for i in range(n_axes):
                        w.write_samples(S.SampleBlock(machine="m", axis=f"A{i}", seq=seq, t=t, v_ref=[0.0] * 10,
                                                      v_meas=[0.0] * 10))

            def one_pass(path=path):
                scan = scan_trial(path)
                for _ in _pass_stream(str(path), scan, None, 0):
                    pass

            t = _median(one_pass, max(1, repeat // 2))
            per_axis.append((n_axes, t, path.stat().st_size))
        rows.append(("replay scan + pass, N axes (2 blocks each)",
                     "; ".join(f"N={a}: {t:.2f} s ({t / a * 1e3:.2f} ms/axis, {sz / 1e6:.1f} MB)"
                               for a, t, sz in per_axis)))

        # scalars: pairing + writing
        blocks = []
        rng = np.random.default_rng(0)
        for k in range(0, n, 100):
            m = min(100, n - k)
            r = rng.standard_normal(m).tolist()
            blocks.append(S.EstimateBlock(machine="m", axis="X", seq=k, t=[(k + i) * 0.003 for i in range(m)],
                                          v_meas=r, v_pred=r, residual=r, f=r, f_var=[1e-8] * m, f_next=r,
                                          f_next_var=[1e-8] * m, dict_size=[50] * m, removed=[-1] * m,
                                          flags=[0] * m, force=r, force_var=[1.0] * m, force_next=r))
        meta = S.TrialMeta(Ts=0.003, form="force-input", machine="m", axis="X",
                           provenance=S.Provenance(source="bench", tool="bench", version="0"))

        def scalars():
            p = ScalarsPairer(expect_truth=False)
            with TrialWriter(d / "scalars.mcap", meta, start=0) as w:
                for b in blocks:
                    for batch in p.add_estimates(b, b.seq * 3_000_000):
                        w.write_scalars_batch(batch)
                for batch in p.drain():
                    w.write_scalars_batch(batch)

        def scalars_one_by_one():  # the same messages through the per-message writer (as before the fast path)
            p = ScalarsPairer(expect_truth=False)
            with TrialWriter(d / "scalars1.mcap", meta, start=0) as w:
                for b in blocks:
                    for batch in p.add_estimates(b, b.seq * 3_000_000):
                        w.write_scalars("m", "X", list(zip(batch.log_ns.tolist(), batch.messages())))
                for batch in p.drain():
                    w.write_scalars("m", "X", list(zip(batch.log_ns.tolist(), batch.messages())))

        def estimates_only():
            with TrialWriter(d / "est.mcap", meta, start=0) as w:
                for b in blocks:
                    w.write_estimates(b)

        t_sc, t_est = _median(scalars, repeat), _median(estimates_only, repeat)
        t_one = _median(scalars_one_by_one, repeat)
        same = (d / "scalars.mcap").read_bytes() == (d / "scalars1.mcap").read_bytes()
        rows.append(("disturbance/scalars: pair + write",
                     f"{t_sc / n * 1e6:.1f} µs per sample, zstd included (one message at a time: {t_one / n * 1e6:.1f} µs, "
                     f"{t_one / t_sc:.1f}×; files {'identical' if same else 'DIFFERENT'}; the estimate blocks "
                     f"themselves: {t_est / n * 1e6:.1f} µs)"))

        # recover
        t_rec = _median(lambda: recover(trial, d / "copy.mcap"), repeat)
        data = bytearray(trial.read_bytes())
        from mcap.records import Chunk
        from mcap.stream_reader import StreamReader

        with open(trial, "rb") as fh:
            ends = [fh.tell() for rec in StreamReader(fh, emit_chunks=True).records if isinstance(rec, Chunk)]
        for e in ends:
            data[e - 40] ^= 0x5A
        (d / "damaged.mcap").write_bytes(bytes(data))
        t_dmg = _median(lambda: recover(d / "damaged.mcap", d / "damaged-fixed.mcap"), repeat)
        rows.append(("recover", f"healthy {size / t_rec / 1e6:.1f} MB/s; one flipped byte in each of {len(ends)} "
                                f"chunks {size / t_dmg / 1e6:.1f} MB/s"))

        # run --from
        model = d / "x.model.toml"
        m = read_trial(trial).meta
        save_model(AxisModel(machine=m.machine, axis=m.axis, form=m.form, Ts=m.Ts, beta=list(m.truth.beta),
                             omega=m.truth.omega, coulomb=m.truth.coulomb, loop_gain=m.loop_gain, method="truth",
                             tracker=TrackerConfig(kernel=LocallyPeriodicKernel(sigma1=1.2, sigma2=0.495, period=0.02),
                                                   gamma=5.85, forgetting=0.996, budget=100),
                             provenance={"source": "benchmark"}), model)
        run_offline(trial, d / "warm.mcap", load_axes([model]))
        rates = []
        for _ in range(repeat):
            r = run_offline(trial, d / "out.mcap", load_axes([model]))
            rates.append(r.rate)
        rows.append(("run --from (with scalars)", f"{statistics.median(rates):,.0f} samples/s (median of {repeat})"))

    width = max(len(a) for a, _ in rows)
    print(f"{'what':<{width}}  figure")
    for a, b in rows:
        print(f"{a:<{width}}  {b}")


if __name__ == "__main__":
    main()
