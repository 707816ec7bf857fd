"""``feedmon identify``: candidate models chosen by evidence, a model file and a report ."""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import math
import os
import sys
from pathlib import Path

from rich.console import Console
from rich.table import Table


def register(sub) -> None:
    p = sub.add_parser(
        "identify",
        help="identify an axis model (β) from a recorded trial: LS and PL-LSSVM candidates, chosen by evidence",
        description="Identify the feed-drive model of one axis from a trial file. Candidates — least squares, "
        "PL-LSSVM with a squared-exponential kernel in time, PL-LSSVM with the locally periodic kernel at the "
        "period(s) in play — are tuned by restricted marginal likelihood and the valid one with the highest "
        "evidence is written to the model file for 'feedmon run'. A model that cannot be right (unstable pole, "
        "inertia or damping ≤ 0, negative Coulomb friction) is refused: exit 1, nothing written. The model "
        "written is then run through the monitor over the same trial (self-check): a drift warning there means "
        "the identified values and the tracker's view of the same data disagree.",
    )
    p.add_argument("trial", help="trial file (.mcap) from 'feedmon simulate', 'feedmon import' or a monitor log")
    p.add_argument("-o", "--output", help="model file to write (TOML; an existing one is replaced), e.g. "
                   "axis-x.model.toml; default: TRIAL.model.toml next to the trial, which must not exist yet")
    p.add_argument("--dry-run", action="store_true", help="identify and report, but write no model file")
    p.add_argument("--axis", help="axis name (or machine/axis) when the trial holds several")
    p.add_argument("--form", choices=["velocity-loop", "force-input"], help="input form (default: the trial's)")
    p.add_argument("--period", type=float, help="disturbance period ψ in s (e.g. 0.018182 for 55 Hz); "
                   "default: the spindle speed, else found in the data")
    p.add_argument("--spindle-rpm", type=float, help="spindle speed (rpm): ψ = 60/rpm (tool runout)")
    p.add_argument("--teeth", type=int, help="cutting edges of the tool, 1 … 1000 (default: the trial's): with runout "
                   "ψ is the spindle period and the tooth-passing line one of its harmonics; with a changing spindle "
                   "speed a spindle-phase candidate per tooth is tried beside the one per revolution")
    p.add_argument("--sigma1", type=float, help="σ1 (s) of the locally periodic kernel (start of tuning; "
                   "kept with --no-tune; default 0.59)")
    p.add_argument("--sigma2", type=float, help="σ2 of the locally periodic kernel (default 0.42)")
    p.add_argument("--gamma", type=float, help="regularisation γ (default 50.3)")
    p.add_argument("--no-tune", action="store_true",
                   help="keep the given (or thesis) hyperparameters instead of tuning them by REML")
    p.add_argument("--tune", action="store_true", help=argparse.SUPPRESS)  # the default now; old scripts still run
    p.add_argument("--method", choices=["auto", "ls", "pl-lssvm"], default="auto",
                   help="model to write: the valid candidate with the highest evidence (auto), or the best of one family")
    p.add_argument("--force", action="store_true",
                   help="write the model even when it is not valid (with a warning in the file; 'feedmon run' refuses it)")
    p.add_argument("--no-coulomb", action="store_true", help="drop the Coulomb friction columns")
    p.add_argument("--coulomb", action="store_true", help="keep the Coulomb columns even without speed reversal")
    p.add_argument("--omega", type=float, help="Coulomb dead band Ω in m/s (default: 3× the velocity noise)")
    p.add_argument("--loop-gain", type=float, help="velocity-loop gain K (N·s/m) to get J and B instead of J/K, B/K")
    p.add_argument("--delay", type=int, metavar="N", help="the force acts N samples (0 … 16) after it is commanded "
                   "(default: 0, or the delay the model-adequacy test finds, modelled)")
    p.add_argument("--start", type=float, metavar="S",
                   help="identify from S seconds after the trial's first sample (default: its start)")
    p.add_argument("--end", type=float, metavar="S",
                   help="identify up to S seconds after the trial's first sample (default: its end)")
    p.add_argument("--report", metavar="DIR", help="write PNG figures and a markdown summary into DIR")
    p.add_argument("--json", action="store_true", help="print one JSON document instead of the table")
    p.set_defaults(func=run)


#: the longest stretch of the record the self-check runs the monitor over (s, from the window's start)
SELF_CHECK_SECONDS = 120.0


def run(args) -> int:
    if not args.json:
        return _run(args)
    try:  # --json: one document on stdout whatever happens — the error too (then on stderr as well)
        return _run(args)
    except (ValueError, OSError) as exc:
        from .errors import describe

        print(json.dumps({key: None for key in JSON_KEYS} | {"error": describe(exc, "identify")}, indent=2))
        raise


#: the keys of the --json document (docs/identify.md, "Output")
JSON_KEYS = ("form", "Ts", "chosen", "period", "candidates", "ls", "pl_lssvm", "model", "truth", "checks",
             "self_check", "error")


def _run(args) -> int:
    from feedio import __version__
    from feedio.mcapio import read_trial
    from monitor.identify import identify
    from monitor.model_file import save_model

    if args.coulomb and args.no_coulomb:
        raise ValueError("--coulomb and --no-coulomb contradict each other; give one")
    if args.period is not None and args.spindle_rpm is not None:
        raise ValueError("--period and --spindle-rpm both give the disturbance period; give one of them")
    if args.tune and args.no_tune:
        raise ValueError("--tune and --no-tune contradict each other; tuning is the default")
    if args.delay is not None and not 0 <= args.delay <= 16:
        raise ValueError(f"--delay must be a whole number of samples 0 … 16, got {args.delay}")
    if args.dry_run and args.output:
        raise ValueError("--dry-run and -o contradict each other: -o writes the model file, --dry-run writes none")
    coulomb = False if args.no_coulomb else (True if args.coulomb else None)
    output = _check_outputs(args)  # before the identification (minutes), not after it
    whole = read_trial(args.trial, axis=args.axis)
    t0 = float(whole.t[0]) if len(whole) else 0.0
    trial = whole.window(args.start, args.end)  # a bad window: the error names start/end (feedmon.errors)
    del whole
    if args.teeth is not None:
        import msgspec

        trial = dataclasses.replace(trial, meta=msgspec.structs.replace(trial.meta, teeth=args.teeth))
    err = Console(stderr=True)
    with _progress(err, enabled=not args.no_tune and sys.stderr.isatty() and not args.json) as progress_cb:
        ident = identify(
            trial, form=args.form, period=args.period, spindle_rpm=args.spindle_rpm, sigma1=args.sigma1,
            sigma2=args.sigma2, gamma=args.gamma, tune=not args.no_tune, method=args.method, coulomb=coulomb,
            omega=args.omega, loop_gain=args.loop_gain, delay=args.delay, progress=progress_cb,
        )
    if args.start is not None or args.end is not None:
        ident.notes.append(f"identified on the window {trial.t[0] - t0:.6g} … {trial.t[-1] - t0:.6g} s of the trial "
                           f"(seq {int(trial.seq[0])} … {int(trial.seq[-1])}; --start/--end)")
    doc = ident.to_json()
    written = []
    refused = ident.refusal is not None and not args.force
    check = doc["self_check"] = None  # no model, nothing to check
    doc["error"] = ident.refusal if refused else None
    if not refused and ident.model_result is not None:
        model = ident.to_model(feedmon_version=__version__, force=args.force)
        check = _self_check(args.trial, model, _self_check_range(trial, float(ident.Ts)))
        doc["self_check"] = check
        model.identification["self_check"] = check["summary"][:4000]
        if output is not None:
            written.append(save_model(model, output))
    if args.report:
        from monitor.report import write_report

        written += write_report(ident, args.report, self_check=check)
    if args.json:
        print(json.dumps(doc, indent=2, default=_jsonable))
    else:
        _print_table(ident)
        if check is not None:
            style = "" if check["state"] == "ok" else "[bold yellow]"
            Console().print(f"{style}self-check{'[/]' if style else ''}: {check['summary']}")
    for path in written:
        err.print(f"wrote {path}")
    if ident.refusal is not None:
        if refused:
            err.print(f"[bold red]error:[/] {ident.refusal}. Nothing written"
                      + (" (--force writes it anyway, with a warning in the file)" if output is not None else ""))
            return 1
        err.print(f"[bold yellow]warning:[/] {ident.refusal}; written anyway (--force), 'feedmon run' will refuse it")
    return 0


@contextlib.contextmanager
def _progress(console, *, enabled: bool):
    """A progress bar with the tuning's likelihood evaluations done / planned and the time remaining; yields
    the identification's ``progress(label, done, total)`` callback (None when not shown)."""
    if not enabled:
        yield None
        return
    from rich.progress import BarColumn, Progress, TaskProgressColumn, TextColumn, TimeRemainingColumn

    bar = Progress(TextColumn("{task.description}"), BarColumn(), TaskProgressColumn(), TimeRemainingColumn(),
                   console=console, transient=True)
    task = bar.add_task("identifying", total=None)

    def report(label, done, total):
        bar.update(task, description=f"tuning {label}", completed=done, total=total)

    with bar:
        yield report


def _self_check_range(trial, Ts: float) -> tuple[int, int]:
    """The samples the self-check runs over: the window identified, at most :data:`SELF_CHECK_SECONDS` of it."""
    first, last = int(trial.seq[0]), int(trial.seq[-1])
    return first, min(last, first + int(round(SELF_CHECK_SECONDS / Ts)))


def default_output(trial) -> Path:
    """The model file written without ``-o``: ``TRIAL.model.toml`` next to the trial."""
    path = Path(trial)
    return path.with_name(f"{path.stem}.model.toml")


def _check_outputs(args) -> Path | None:
    """The options checked before the identification runs: ``--teeth`` in range, the model file (``-o``, else
    :func:`default_output`, which must not exist yet; none with ``--dry-run``) in an existing, writable
    directory, ``--report`` a directory (or a path to create). Returns the model file to write."""
    if args.teeth is not None and not 1 <= args.teeth <= 1000:
        raise ValueError(f"--teeth must be the tool's number of cutting edges, 1 … 1000, got {args.teeth}")
    out = None
    if not args.dry_run and not args.output:
        out = default_output(args.trial)
        if out.exists():
            raise ValueError(f"{out} exists (the model file written next to the trial without -o); give -o to replace "
                             "it or to choose another file, or --dry-run to write none")
    if args.output or out is not None:
        out = Path(args.output) if args.output else out
        what = f"-o {out}" if args.output else f"{out} (the model file by default; -o chooses another)"
        folder = out.parent if str(out.parent) else Path(".")
        if out.is_dir():
            raise ValueError(f"{what}: is a directory; give the model file's name, e.g. {out / 'axis.model.toml'}")
        if not folder.is_dir():
            raise ValueError(f"{what}: the directory {folder} does not exist; create it first")
        if not os.access(folder, os.W_OK):
            raise ValueError(f"{what}: the directory {folder} is not writable")
    if args.report and Path(args.report).exists() and not Path(args.report).is_dir():
        raise ValueError(f"--report {args.report}: is a file; give a directory for the report's PNGs and summary")
    return out


def _self_check(trial: str, model, seq_range: tuple[int, int]) -> dict:
    """:func:`monitor.self_check.self_check` as JSON; a check that cannot run says why (it never stops
    the identification)."""
    from monitor.self_check import self_check

    try:
        return self_check(trial, model, seq_range).to_json()
    except (ValueError, OSError) as exc:
        return {"state": "not run", "summary": f"not run: {exc}"}


def _jsonable(x):
    if hasattr(x, "tolist"):
        return x.tolist()
    raise TypeError(f"not JSON serialisable: {type(x).__name__}")


def _print_table(ident) -> None:
    from monitor.report import candidate_rows, summary_columns, summary_table

    console = Console()
    cands = Table(title=f"{ident.machine}/{ident.axis} — {Path(ident.trial_path).name} ({ident.form}): candidates")
    for col in ("candidate", "hyperparameters", "log evidence", "valid", ""):
        cands.add_column(col, justify="left" if col in ("candidate", "hyperparameters", "") else "right",
                         overflow="fold")
    for row in candidate_rows(ident):
        cands.add_row(*row)
    console.print(cands)
    table = Table(title="parameters (± standard error)")
    for col in summary_columns(ident):
        table.add_column(col, justify="right" if col != "parameter" else "left")
    for row in summary_table(ident):
        table.add_row(*row)
    console.print(table)
    psi = "none" if ident.period is None else f"{ident.period:.6g} s ({ident.period_source})"
    console.print(f"Ts = {ident.Ts:.6g} s, ψ = {psi}, Ω = {ident.omega:.3g} m/s; {ident.coulomb_note}")
    if ident.chosen is not None:
        console.print(f"[bold]chosen: {ident.chosen.label}[/] (log evidence {ident.chosen.log_evidence:.6g})")
    truth = ident.truth or {}
    for key, label in (("disturbance_correlation", "disturbance vs truth: correlation"),
                       ("pl_lssvm_disturbance_correlation", "PL-LSSVM disturbance vs truth: correlation")):
        value = truth.get(key)
        if value is not None and math.isfinite(value):
            console.print(f"{label} {value:.4f}")
            break
    for note in ident.notes + (ident.pl.candidate.notes if ident.pl else []):
        console.print(f"note: {note}")
