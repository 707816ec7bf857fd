"""``feedmon identify``: LS and PL-LSSVM on a recorded trial, a model file and a report."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from rich.console import Console
from rich.table import Table


def register(sub) -> None:
    p = sub.add_parser(
        "identify",
        help="identify an axis model (β) from a recorded trial by LS and PL-LSSVM",
        description="Identify the feed-drive model of one axis from a trial file (LS and PL-LSSVM, method §3–4) "
        "and write the model file for 'feedmon run'.",
    )
    p.add_argument("trial", help="trial file (.mcap) from 'feedmon simulate', 'feedmon import' or a monitor log")
    p.add_argument("-o", "--output", help="model file to write (TOML), e.g. axis-x.model.toml")
    p.add_argument("--axis", help="axis name (or machine/axis) when the trial holds several")
    p.add_argument("--form", choices=["velocity-loop", "force-input"], help="input form (default: the trial's)")
    p.add_argument("--period", type=float, help="disturbance period ψ in s (e.g. 0.018182 for 55 Hz)")
    p.add_argument("--spindle-rpm", type=float, help="spindle speed (rpm): ψ = 60/rpm (tool runout)")
    p.add_argument("--teeth", type=int, help="tooth count of the tool (recorded; ψ is the spindle period)")
    p.add_argument("--sigma1", type=float, help="σ1 (s) of the locally periodic kernel (default 0.59)")
    p.add_argument("--sigma2", type=float, help="σ2 of the locally periodic kernel (default 0.42)")
    p.add_argument("--gamma", type=float, help="regularisation γ (default 50.3)")
    p.add_argument("--tune", action="store_true", help="choose σ1, σ2, γ by maximum marginal likelihood")
    p.add_argument("--no-coulomb", action="store_true", help="drop the Coulomb friction columns")
    p.add_argument("--coulomb", action="store_true", help="keep the Coulomb columns even without speed reversal")
    p.add_argument("--omega", type=float, help="Coulomb dead band Ω in m/s (default: 3× the velocity noise)")
    p.add_argument("--loop-gain", type=float, help="velocity-loop gain K (N·s/m) to get J and B instead of J/K, B/K")
    p.add_argument("--method", choices=["pl-lssvm", "ls"], default="pl-lssvm", help="β written to the model file")
    p.add_argument("--report", metavar="DIR", help="write PNG figures and a markdown summary into DIR")
    p.add_argument("--json", action="store_true", help="print one JSON document instead of the table")
    p.set_defaults(func=run)


def run(args) -> int:
    from feedio import __version__
    from feedio.mcapio import read_trial
    from monitor.identify import identify
    from monitor.model_file import save_model

    if args.coulomb and args.no_coulomb:
        raise ValueError("--coulomb and --no-coulomb contradict each other; give one")
    coulomb = False if args.no_coulomb else (True if args.coulomb else None)
    trial = read_trial(args.trial, axis=args.axis)
    err = Console(stderr=True)
    show_progress = args.tune and sys.stderr.isatty() and not args.json
    progress_cb = None
    if show_progress:
        from rich.progress import Progress

        progress = Progress(console=err, transient=True)
        task = progress.add_task("tuning σ1, σ2, γ", total=None)
        progress.start()

        def progress_cb(n, params, ll, best):
            progress.update(task, description=f"tuning: {n} evaluations, best log-likelihood {best:.6g}")
    try:
        ident = identify(
            trial, form=args.form, period=args.period, spindle_rpm=args.spindle_rpm, sigma1=args.sigma1,
            sigma2=args.sigma2, gamma=args.gamma, tune=args.tune, coulomb=coulomb, omega=args.omega,
            loop_gain=args.loop_gain, progress=progress_cb,
        )
    finally:
        if show_progress:
            progress.stop()
    doc = ident.to_json()
    if args.teeth is not None:
        doc["teeth"] = args.teeth
    written = []
    if args.output:
        model = ident.to_model(method=args.method, feedmon_version=__version__)
        written.append(save_model(model, args.output))
        doc["model_file"] = str(args.output)
    if args.report:
        from monitor.report import write_report

        written += write_report(ident, args.report)
        doc["report"] = [str(p) for p in written[1 if args.output else 0:]]
    if args.json:
        print(json.dumps(doc, indent=2, default=_jsonable))
        return 0
    _print_table(ident, doc)
    for path in written:
        err.print(f"wrote {path}")
    return 0


def _jsonable(x):
    if hasattr(x, "tolist"):
        return x.tolist()
    raise TypeError(f"not JSON serialisable: {type(x).__name__}")


def _print_table(ident, doc) -> None:
    from monitor.report import summary_table

    console = Console()
    hp = ident.hyperparameters
    table = Table(title=f"{ident.machine}/{ident.axis} — {Path(ident.trial_path).name} ({ident.form})")
    for col in ("parameter", "LS (± s.e.)", "PL-LSSVM", "truth"):
        table.add_column(col, justify="right" if col != "parameter" else "left")
    for row in summary_table(ident):
        table.add_row(*row)
    console.print(table)
    console.print(
        f"Ts = {ident.Ts:.6g} s, ψ = {ident.period:.6g} s ({ident.period_source}), Ω = {ident.omega:.3g} m/s; "
        f"σ1 = {hp['sigma1']:.4g} s, σ2 = {hp['sigma2']:.4g}, γ = {hp['gamma']:.4g}"
        + (f" (tuned, log-likelihood {hp['log_likelihood']:.6g}, {hp.get('evaluations')} evaluations)" if hp.get("tuned") else "")
    )
    if ident.truth and ident.truth.get("disturbance_correlation") is not None:
        console.print(f"disturbance vs truth: correlation {ident.truth['disturbance_correlation']:.4f}")
    for note in ident.notes:
        console.print(f"note: {note}")
