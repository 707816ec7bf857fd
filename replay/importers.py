"""Importers: real recordings → MCAP trial files (:mod:`feedio.mcapio`).

* :func:`import_emps` — the EMPS benchmark drive (Janot et al., nonlinearbenchmark.org),
  force-input form.
* :func:`import_csv` — any controller export as CSV, with a column map and unit conversion.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from feedio import schema as S
from feedio.digest import file_sha256
from feedio.limits import SAMPLE_LIMITS
from feedio.mcapio import MAX_TRIAL_SAMPLES
from kernels.errors import ParameterError

__all__ = [
    "ImportedTrial",
    "load_emps",
    "import_emps",
    "read_csv_trial",
    "import_csv",
    "write_imported",
    "UNIT_FACTORS",
    "EMPS_REFERENCE",
    "EMPS_HOWTO",
]

# published IDIM-LS reference of the EMPS (symmetric friction model)
EMPS_REFERENCE = {"M": 95.1089, "Fv": 203.5034, "Fc": 20.3935, "offset": -3.1648}
EMPS_HOWTO = (
    "the EMPS data set (DATA_EMPS.mat, DATA_EMPS_PULSES.mat) is available from "
    "nonlinearbenchmark.org (benchmark 'EMPS: Electro-Mechanical Positioning System'); "
    "download and unzip it and point FEEDMON_EMPS_DIR at the folder"
)


@dataclass
class ImportedTrial:
    meta: S.TrialMeta
    t: np.ndarray
    v_ref: np.ndarray
    v_meas: np.ndarray
    u: np.ndarray | None = None
    current: np.ndarray | None = None
    position: np.ndarray | None = None
    spindle_rpm: np.ndarray | None = None
    truth_force: np.ndarray | None = None  # T_c (N), method §1 sign: positive opposes positive motion
    truth_f: np.ndarray | None = None  # m/s

    def __len__(self) -> int:
        return int(self.t.size)


# ============================================================================================
# EMPS
# ============================================================================================
def load_emps(path, *, rate: int = 333, cutoff: float = 100.0, order: int = 4) -> ImportedTrial:
    """Read an EMPS ``.mat`` file into a force-input trial.

    * Force command ``u = gtau·vir`` (N); for the PULSES file the PD-law force
      ``gtau·(vir − 1.014·pulses_N)`` and the pulse force ``gtau·1.014·pulses_N`` goes to the
      truth (``T_c = −pulse``: the pulse pushes in the + direction).
    * Velocity from the motor position ``qm``: zero-phase Butterworth (``order``, ``cutoff`` Hz,
      ``filtfilt``) then central differences at 1 kHz; ``v_ref`` likewise from ``qg``.
    * ``rate=333``: sample k is at the 1 kHz index 3k, ``Ts = 3 ms``; the velocity is the value
      at the start of the interval and ``u(k)`` the **mean force over the interval**
      [3k, 3k+3) — the force the ZOH model of method §1–2 integrates from v(k) to v(k+1).
      (Taking the force at 3k only, or shifting the velocity by one 1 kHz sample, moves Fv
      by several percent.) ``rate=1000`` keeps the 1 kHz samples.
    """
    from scipy.io import loadmat
    from scipy.signal import butter, filtfilt

    path = Path(path)
    if rate not in (333, 1000):
        raise ParameterError(f"rate must be 333 or 1000 (Hz), got {rate!r}", "rate")
    if not path.is_file():
        raise OSError(f"EMPS file {path} not found; {EMPS_HOWTO}")
    try:
        d = loadmat(path)
    except Exception as exc:  # noqa: BLE001 - scipy raises ValueError/TypeError/MatReadError on non-.mat input
        raise ValueError(f"{path} is not a MATLAB .mat file readable by scipy.io.loadmat ({exc})") from None
    missing = [k for k in ("t", "qm", "qg", "vir", "gtau") if k not in d]
    if missing:
        have = ", ".join(sorted(k for k in d if not k.startswith("__")))
        raise ValueError(f"{path} is not an EMPS data file: variable(s) {', '.join(missing)} missing (has: {have})")
    t1 = np.asarray(d["t"], dtype=np.float64).ravel()
    qm = np.asarray(d["qm"], dtype=np.float64).ravel()
    qg = np.asarray(d["qg"], dtype=np.float64).ravel()
    vir = np.asarray(d["vir"], dtype=np.float64).ravel()
    gtau = float(np.asarray(d["gtau"]).ravel()[0])
    pulses = np.asarray(d["pulses_N"], dtype=np.float64).ravel() if "pulses_N" in d else None
    n1 = t1.size
    if not (qm.size == qg.size == vir.size == n1) or n1 < 100:
        raise ValueError(f"{path}: t, qm, qg, vir must have the same length ≥ 100 (got {n1}, {qm.size}, {qg.size}, {vir.size})")
    dt = float(np.median(np.diff(t1)))
    fs = 1.0 / dt
    b, a = butter(order, cutoff / (fs / 2.0), "low")
    v1 = np.gradient(filtfilt(b, a, qm), dt)
    vr1 = np.gradient(filtfilt(b, a, qg), dt)
    force_pd = gtau * vir if pulses is None else gtau * (vir - 1.014 * pulses)
    pulse1 = None if pulses is None else gtau * 1.014 * pulses

    step = 3 if rate == 333 else 1
    n = (n1 - 1) // step  # every interval [step k, step k + step) complete
    idx = step * np.arange(n)

    def interval_mean(x):
        return x[: n * step].reshape(n, step).mean(axis=1)

    Ts = step * dt
    u = interval_mean(force_pd)
    sha = file_sha256(path)
    ref = EMPS_REFERENCE
    meta = S.TrialMeta(
        Ts=Ts,
        form="force-input",
        machine="emps",
        axis="X",
        units=dict(S.UNITS),
        provenance=S.Provenance(
            source="emps",
            tool="feedmon import emps",
            version=_version(),
            details={
                "file": path.name,
                "sha256": sha,
                "rate_hz": rate,
                "velocity": f"filtfilt Butterworth order {order} at {cutoff:g} Hz on qm, central difference at 1 kHz",
                "force": "gtau·vir" if pulses is None else "gtau·(vir − 1.014·pulses_N) (PD law)",
                "alignment": "v(k) at the interval start, u(k) mean force over the interval",
                "gtau": gtau,
                "reference": "Janot, Gautier, Brunot 2019, IDIM-LS symmetric friction",
                "reference_M": ref["M"],
                "reference_Fv": ref["Fv"],
                "reference_Fc": ref["Fc"],
                "reference_offset": ref["offset"],
            },
        ),
        description="EMPS electro-mechanical positioning system (real data), force-input form",
    )
    out = ImportedTrial(
        meta=meta,
        t=t1[idx] - t1[0],
        v_ref=vr1[idx],
        v_meas=v1[idx],
        u=u,
        position=qm[idx],
    )
    if pulse1 is not None:
        from kernels.feed_drive import force_to_disturbance, physical_to_beta

        tc = 0.0 - interval_mean(pulse1)  # (0.0 − x: no negative zeros in the file)
        beta_ref = physical_to_beta("force-input", Ts, ref["M"], ref["Fv"])
        out.truth_force = tc
        out.truth_f = force_to_disturbance("force-input", beta_ref, tc)
    return out


def _version() -> str:
    from feedio import __version__

    return __version__


def import_emps(path, output, *, rate: int = 333, start=None) -> ImportedTrial:
    """``feedmon import emps``: read an EMPS ``.mat`` and write an MCAP trial file (``start``: the
    trial's start time, see :func:`write_imported`)."""
    tr = load_emps(path, rate=rate)
    write_imported(tr, output, start=start)
    return tr


# ============================================================================================
# CSV
# ============================================================================================
# unit → (dimension, factor to SI)
UNIT_FACTORS: dict[str, tuple[str, float]] = {
    "s": ("time", 1.0), "ms": ("time", 1e-3), "us": ("time", 1e-6),
    "m/s": ("velocity", 1.0), "mm/s": ("velocity", 1e-3), "mm/min": ("velocity", 1e-3 / 60.0),
    "m/min": ("velocity", 1.0 / 60.0),
    "N": ("force", 1.0), "kN": ("force", 1e3),
    "A": ("current", 1.0), "mA": ("current", 1e-3),
    "m": ("length", 1.0), "mm": ("length", 1e-3), "um": ("length", 1e-6),
    "rpm": ("speed", 1.0), "rev/s": ("speed", 60.0),
}
#: dimension → (|value| beyond which a sample is absurd for a machine-tool axis, SI unit); feedio.limits
_ABSURD = {"velocity": (SAMPLE_LIMITS.v_max, "m/s"), "force": (SAMPLE_LIMITS.u_max, "N"), "speed": (SAMPLE_LIMITS.spindle_rpm_max, "rpm")}

FIELD_DIMENSION = {
    "t": "time", "v_ref": "velocity", "v_meas": "velocity", "u": "force",
    "current": "current", "position": "length", "spindle_rpm": "speed",
}


def _parse_pairs(text: str | None, what: str) -> dict[str, str]:
    """``"k=v,k=v"`` (fields of :data:`FIELD_DIMENSION`) as a dict; errors name the parameter ``what``."""
    out: dict[str, str] = {}
    if not text:
        return out
    for part in text.split(","):
        part = part.strip()
        if not part:
            continue
        if "=" not in part:
            raise ParameterError(f"{what}: {part!r} is not FIELD=VALUE (e.g. t=time)", what)
        k, v = (s.strip() for s in part.split("=", 1))
        if k not in FIELD_DIMENSION:
            raise ParameterError(f"{what}: unknown field {k!r}; fields: {', '.join(FIELD_DIMENSION)}", what)
        out[k] = v
    return out


#: sampling times (s) a machine-tool controller records at: 10 µs (100 kHz) … 1 s. A time step outside
#: is a time column read in the wrong unit (``t=ms`` on seconds gives 1000 × too small), not a recording
TS_RANGE = (1e-5, 1.0)


def _check_sampling_time(path, Ts: float, step: float, unit: str, given: bool) -> None:
    """Refuse a sampling time no controller has, naming the likely fix (another unit of ``t``)."""
    lo, hi = TS_RANGE
    if lo <= Ts <= hi:
        return
    what = f"Ts = {Ts:.6g} s (given)" if given else f"the median time step is {step:.6g} s (t read in {unit})"
    hint = ""
    for other, f in UNIT_FACTORS.items():
        if f[0] == "time" and other != unit and lo <= step / UNIT_FACTORS[unit][1] * f[1] <= hi and not given:
            hint = f"; if the column is in {other}, say units t={other}"
            break
    raise ParameterError(f"CSV file {path}: {what}, outside the {lo:g} … {hi:g} s a machine-tool controller samples "
                         f"at: check the unit of the time column{hint}", "Ts" if given else "units")


def _float(cell: str) -> float | None:
    cell = cell.strip()
    if cell == "" or cell.lower() in ("nan", "na", "null", "none"):
        return None
    return float(cell)


def _checked_arguments(mapping, units, form: str, loop_gain) -> tuple[dict[str, str], dict[str, str]]:
    """``(mapping, units)`` of :func:`read_csv_trial` as dicts, checked against the form and the known units."""
    mapping = _parse_pairs(mapping, "mapping") if isinstance(mapping, str) else dict(mapping)
    units = _parse_pairs(units, "units") if isinstance(units, str) or units is None else dict(units)
    if form not in ("velocity-loop", "force-input"):
        raise ParameterError(f"form must be 'velocity-loop' or 'force-input', got {form!r}", "form")
    if loop_gain is not None and not (np.isfinite(loop_gain) and loop_gain > 0):
        raise ParameterError(f"loop_gain must be a positive number (N·s/m), got {loop_gain!r}", "loop_gain")
    need = ["t", "v_meas"] + (["v_ref"] if form == "velocity-loop" else ["u"])
    lacking = [f for f in need if f not in mapping]
    if lacking == ["v_ref"] and "u" in mapping:  # a force command and no velocity reference: the other form
        raise ParameterError("mapping gives u (a force command) and no v_ref: that is the force-input form; set "
                             "form='force-input' (or map the velocity reference v_ref for the velocity-loop form)",
                             "form", "mapping")
    if lacking == ["u"] and "v_ref" in mapping:
        raise ParameterError("mapping gives v_ref (a velocity reference) and no u: that is the velocity-loop form; set "
                             "form='velocity-loop' (or map the force command u for the force-input form)",
                             "form", "mapping")
    if lacking:
        raise ParameterError(f"mapping must give the column of {', '.join(lacking)} for the {form} form "
                             "(form='velocity-loop' needs v_ref, form='force-input' needs u)", "mapping", "form")
    for field, unit in units.items():
        if field not in FIELD_DIMENSION:
            raise ParameterError(f"units: unknown field {field!r}; fields: {', '.join(FIELD_DIMENSION)}", "units")
        if unit not in UNIT_FACTORS:
            raise ParameterError(f"units {field}={unit}: unknown unit; known: {', '.join(UNIT_FACTORS)}", "units")
        if UNIT_FACTORS[unit][0] != FIELD_DIMENSION[field]:
            raise ParameterError(f"units {field}={unit}: {unit} is a {UNIT_FACTORS[unit][0]} unit, {field} needs a "
                                 f"{FIELD_DIMENSION[field]} unit", "units")
    return mapping, units


def _read_columns(path: Path, mapping: dict[str, str]) -> tuple[dict[str, list], list[int]]:
    """The mapped columns of a CSV file as lists of numbers (NaN for an empty cell) and the file line of
    each data row; ``ValueError`` naming the file, line and column of what cannot be read."""
    try:
        fh = open(path, newline="", encoding="utf-8-sig")
    except OSError as exc:
        raise OSError(f"cannot read CSV file {path}: {exc.strerror or exc}") from exc
    reader = None
    try:
        with fh:
            sample = fh.read(65536)
            fh.seek(0)
            try:
                dialect = csv.Sniffer().sniff(sample, delimiters=",;\t ")
            except csv.Error:
                dialect = csv.excel
            reader = csv.reader(fh, dialect)
            try:
                header = [h.strip() for h in next(reader)]
            except StopIteration:
                raise ValueError(f"CSV file {path} is empty") from None
            missing = [f"{c!r} (for {f})" for f, c in mapping.items() if c not in header]
            if missing:
                raise ValueError(
                    f"CSV file {path}: column {', '.join(missing)} not found; available columns: {', '.join(map(repr, header))}"
                )
            cols = {f: header.index(c) for f, c in mapping.items()}
            data: dict[str, list] = {f: [] for f in cols}
            lines: list[int] = []
            for lineno, row in enumerate(reader, start=2):
                if not row or all(not c.strip() for c in row):
                    continue
                if len(lines) == MAX_TRIAL_SAMPLES:
                    raise ValueError(f"CSV file {path}, line {lineno}: more than {MAX_TRIAL_SAMPLES:,} data rows, the "
                                     "most one trial file holds (every row is kept in memory while importing); "
                                     "split the file")
                lines.append(lineno)
                for f, j in cols.items():
                    try:
                        data[f].append(_float(row[j]))
                    except (ValueError, IndexError):
                        cell = row[j] if j < len(row) else "<missing>"
                        raise ValueError(
                            f"CSV file {path}, line {lineno}, column {mapping[f]!r} (for {f}): {cell!r} is not a number"
                        ) from None
    except (csv.Error, UnicodeDecodeError) as exc:  # a binary file, a field beyond csv.field_size_limit
        where = f", line {reader.line_num}" if reader is not None and reader.line_num else ""
        raise ValueError(f"CSV file {path}{where}: not a readable CSV text file ({exc})") from None
    return data, lines


def _si_arrays(path: Path, data: dict[str, list], lines: list[int], mapping: dict[str, str],
               units: dict[str, str]) -> dict[str, np.ndarray]:
    """The columns in SI units; a value beyond the limits of any machine-tool axis is refused (units)."""
    arrays = {}
    for f, vals in data.items():
        factor = UNIT_FACTORS[units.get(f, {"time": "s", "velocity": "m/s", "force": "N", "current": "A",
                                             "length": "m", "speed": "rpm"}[FIELD_DIMENSION[f]])][1]
        arrays[f] = np.array(vals, dtype=np.float64) * factor
        limit = _ABSURD.get(FIELD_DIMENSION[f])
        over = np.flatnonzero(np.isfinite(arrays[f]) & (np.abs(arrays[f]) > limit[0])) if limit else []
        if len(over):  # (an empty or non-finite cell is a missing sample)
            k = int(over[0])
            raise ParameterError(f"CSV file {path}, line {lines[k]}, column {mapping[f]!r} (for {f}): {vals[k]:g} "
                                 f"({arrays[f][k]:.6g} {limit[1]}) is beyond the {limit[0]:g} {limit[1]} of any "
                                 f"machine-tool axis ({len(over)} such value(s)): check the units, or remove the faulty "
                                 "rows", "units")
    return arrays


def _sampling_time(path: Path, t: np.ndarray, lines: list[int], mapping: dict[str, str], units: dict[str, str],
                   Ts: float | None) -> float:
    """``Ts`` (s; default the median step) after checking that the times are finite, increasing, ≥ 0 and
    sampled at that one rate."""
    if not np.all(np.isfinite(t)):
        raise ValueError(f"CSV file {path}: column {mapping['t']!r} (t) has empty or non-numeric times at rows {np.flatnonzero(~np.isfinite(t))[:5] + 2}")
    dts = np.diff(t)
    if np.any(dts <= 0):
        k = int(np.flatnonzero(dts <= 0)[0])
        raise ValueError(f"CSV file {path}: time {mapping['t']!r} does not increase at data row {k + 2} → {k + 3}")
    if t[0] < 0:
        raise ValueError(f"CSV file {path}: times must be ≥ 0 s (first is {t[0]:g} s)")
    Ts_ = float(Ts) if Ts is not None else float(np.median(dts))
    if not (np.isfinite(Ts_) and Ts_ > 0):
        raise ParameterError(f"Ts must be a positive number of seconds, got {Ts!r}", "Ts")
    _check_sampling_time(path, Ts_, float(np.median(dts)), units.get("t", "s"), Ts is not None)
    off = np.flatnonzero((dts < 0.5 * Ts_) | (dts > 1.5 * Ts_))
    if off.size:  # a gap (lost rows) or another rate: consecutive rows would pose as consecutive samples
        k = int(off[0])
        raise ParameterError(f"CSV file {path}: the time step from line {lines[k]} to {lines[k + 1]} is {dts[k]:.6g} s, "
                             f"not the sampling time Ts = {Ts_:.6g} s ({off.size} such step(s)): the file has a gap or is "
                             "not sampled at one rate; split it at the gap, resample it to one rate, or give the right Ts",
                             "Ts")
    return Ts_


def read_csv_trial(
    path,
    mapping: dict[str, str] | str,
    units: dict[str, str] | str | None = None,
    *,
    form: str = "velocity-loop",
    machine: str = "machine",
    axis: str = "X",
    loop_gain: float | None = None,
    Ts: float | None = None,
) -> ImportedTrial:
    """Read a CSV export (header row; delimiter sniffed) into a trial.

    ``mapping`` feedmon field → CSV column (``t`` and ``v_meas`` required, ``v_ref`` for the
    velocity-loop form, ``u`` for the force-input form); ``units`` feedmon field → unit of the
    column (default SI). ``Ts`` defaults to the median time step.
    """
    path = Path(path)
    mapping, units = _checked_arguments(mapping, units, form, loop_gain)
    data, lines = _read_columns(path, mapping)
    if len(data["t"]) < 3:
        raise ValueError(f"CSV file {path} has {len(data['t'])} data rows; a trial needs at least 3")
    arrays = _si_arrays(path, data, lines, mapping, units)
    t = arrays["t"]
    Ts_ = _sampling_time(path, t, lines, mapping, units, Ts)
    n = t.size
    meta = S.TrialMeta(
        Ts=Ts_,
        form=form,
        machine=machine,
        axis=axis,
        units=dict(S.UNITS),
        loop_gain=loop_gain,
        provenance=S.Provenance(
            source="csv",
            tool="feedmon import csv",
            version=_version(),
            details={"file": path.name, "sha256": file_sha256(path),
                     "map": ",".join(f"{k}={v}" for k, v in mapping.items()),
                     "units": ",".join(f"{k}={v}" for k, v in units.items())},
        ),
    )
    return ImportedTrial(
        meta=meta,
        t=t,
        v_ref=arrays.get("v_ref", np.full(n, np.nan)),
        v_meas=arrays["v_meas"],
        u=arrays.get("u"),
        current=arrays.get("current"),
        position=arrays.get("position"),
        spindle_rpm=arrays.get("spindle_rpm"),
    )


def import_csv(path, output, mapping, units=None, *, start=None, **kw) -> ImportedTrial:
    tr = read_csv_trial(path, mapping, units, **kw)
    write_imported(tr, output, start=start)
    return tr


# ============================================================================================
def write_imported(tr: ImportedTrial, output, *, block: int = 100, start=None) -> None:
    """Write an imported trial (and pulse truth, if any) to an MCAP trial file. ``start``: the
    wall-clock time of its first sample (ISO 8601, datetime or ns since the epoch; default: now,
    the creation time), which the MCAP log times count from."""
    from feedio.mcapio import write_arrays

    truth = None if tr.truth_force is None else dict(t=tr.t, force=tr.truth_force, f=tr.truth_f)
    write_arrays(output, tr.meta, dict(t=tr.t, v_ref=tr.v_ref, v_meas=tr.v_meas, u=tr.u, current=tr.current,
                                       position=tr.position, spindle_rpm=tr.spindle_rpm), truth, block=block,
                 start=start)
